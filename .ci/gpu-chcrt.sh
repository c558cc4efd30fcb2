#!/usr/bin/env bash
# Issue 20's GPU figures in one device call (limits add up to 9 min): chcrt against glsl with both
# traversal stages, at city 10 M, from a device cold start, and without hit hints.
#
# Here:   bash ../shared/gpu/prepare.sh          (fills the git-ignored .gpu/)
# There:  the device tool's `run`, carry [".gpu"], command `bash .ci/gpu-chcrt.sh`
#         (it sources .gpu/setup.sh itself; reports, logs and one summary land in $OUT)
# A dry run on a CPU machine with small sizes checks the commands, not the figures:
#   GPU_CHCRT_SIZE=160x90 GPU_CHCRT_SIZE10M=160x90 GPU_CHCRT_TRIS=20000 GPU_CHCRT_FRAMES=3 \
#   OUT=/tmp/gpu-chcrt-dry PATH=.venv/bin:$PATH bash .ci/gpu-chcrt.sh
# Steps, most wanted first, each under its own limit so a slow one cannot take the rest's time.
set -u
OUT=${OUT:-/tmp/gpu-chcrt}
SIZE=${GPU_CHCRT_SIZE:-1280x720}
SIZE10M=${GPU_CHCRT_SIZE10M:-1920x1080}
TRIS=${GPU_CHCRT_TRIS:-10000000}
FRAMES=${GPU_CHCRT_FRAMES:-12}
W=$(mktemp -d /tmp/gpu-chcrt-work.XXXXXX)
mkdir -p "$OUT"
T0=$(date +%s)
step() {  # step NAME LIMIT_S COMMAND...: one command's output in $OUT/NAME.log, its exit status in steps.log
  local name=$1 limit=$2
  shift 2
  echo "== $name: $*" > "$OUT/$name.log"
  timeout "$limit" "$@" >> "$OUT/$name.log" 2>&1
  echo "[$(($(date +%s) - T0)) s] $name rc=$?" | tee -a "$OUT/steps.log"
}
if [ -f .gpu/setup.sh ] && [ -d /usr/local/nvidia ]; then
  # shellcheck disable=SC1091
  . .gpu/setup.sh > "$OUT/setup.log" 2>&1
  tail -2 "$OUT/setup.log"
fi

# 1. fragment against compute stages for glsl and chcrt (which one `auto` should pick there)
step stages 150 rtwalk bench-chcrt --study stages --recordings city-near.json,sibenik-walk.json --sizes "$SIZE" \
  --effects primary,ao:20 --frames "$FRAMES" --out "$W/stages"
# 2. the issue's large scene: glsl and chcrt at their defaults (stages chosen by `auto`)
for b in glsl chcrt; do
  step "city10m-$b" 100 rtwalk bench city --scene-size "$TRIS" --recording recordings/city-near.json --backend "$b" \
    --effects primary,ao:20 --size "$SIZE10M" --frames 4 --first-frame 120 --reference none --quiet \
    --out "$W/city10m" --name "$b"
done
# 3. a new front: the host's synchronous waves against the device's settling front
step coldstart 150 rtwalk bench-chcrt --study coldstart --recordings city-near.json --sizes "$SIZE" \
  --effects primary,ao:20,diffuse:20 --frames $((2 * FRAMES)) --out "$W/coldstart"
# 4. camera rays without hit hints (an H200 with fragment stages: 7.5 ms against 9.6 with them)
step hints 60 rtwalk bench-chcrt --study table2 --recordings city-near.json --sizes "$SIZE" --effects primary \
  --frames "$FRAMES" --chcrt hit_hint=0 --out "$W/hints"

(cd "$W" && tar czf "$OUT/reports.tgz" . 2>/dev/null)
{
  for f in stages coldstart hints; do
    echo "=== $f"
    grep -h "^| " "$W/$f"/*.md 2>/dev/null | head -12
  done
  for b in glsl chcrt; do
    echo "=== city10m $b"
    grep -h -E "steady|chc:|I/O|trace" "$OUT/city10m-$b.log" 2>/dev/null | head -12
    # rays per frame and type (an H200 once reported chcrt's first frame with twice glsl's AO rays)
    python3 -c 'import json, sys; print([f["rays"] for f in json.load(open(sys.argv[1]))["frames"]])' \
      "$W/city10m/$b.json" 2>/dev/null
  done
  cat "$OUT/steps.log"
} | tee "$OUT/summary.txt"
