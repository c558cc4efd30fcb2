"""`rtwalk bench-bvh-trace`: trace speed of clbvh on the SAH tree and on the device-built tree,
same scene and rays.

    rtwalk bench-bvh-trace [--triangles N] [--rays N] [--scene FILE]

Rays: origins spread over the top of the scene box looking down at random angles (primary-like,
coherent enough to be typical), plus random rays inside the box (secondary-like). Each tree is
traced REPS times interleaved; medians are reported with the ratio device / SAH.
"""

from __future__ import annotations

import sys
import time

import numpy as np

REPS = 6  # timed traces per tree (after one warm-up round), interleaved


def make_rays(tris: np.ndarray, n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    lo, hi = tris.reshape(-1, 3).min(0), tris.reshape(-1, 3).max(0)
    o = rng.uniform(lo, hi, (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    half = n // 2
    o[:half, 1] = hi[1] + 0.1 * (hi[1] - lo[1])  # from above, looking down
    d[:half, 1] = -np.abs(d[:half, 1]) - 0.5
    return o, d


WRITES_REPORTS = False  # a table on stdout: no --force (it had one that did nothing)
HELP = "clbvh trace speed and SAH cost on the SAH-built and the device-built BVH, same rays"


def add_arguments(p) -> None:
    p.add_argument("--triangles", type=int, default=200_000, help="procedural city size (without --scene)")
    p.add_argument("--rays", type=int, default=200_000, help="rays traced per tree and round")
    p.add_argument("--scene", default=None, help="a scene file instead of the city (e.g. ../shared/scenes/...)")


def run(args) -> int:
    from viewer.cli_args import check_at_least

    check_at_least(args.triangles, 1, "--triangles")
    check_at_least(args.rays, 1, "--rays")
    return main([str(args.triangles), str(args.rays), *([args.scene] if args.scene else [])])


def main(argv: list[str]) -> int:
    from viewer.accel.bvh import build_bvh
    from viewer.accel.bvh_device import build_bvh_device
    from viewer.backends.clbvh import ClbvhScene
    from viewer.cl.transfer import HitStage, RayStage

    n_tris = int(argv[0]) if argv else 200_000
    n_rays = int(argv[1]) if len(argv) > 1 else 200_000
    if len(argv) > 2:
        from viewer.scene_io import load_scene

        scene = load_scene(argv[2], progress=False)
    else:
        from viewer.procedural import make_city

        scene = make_city(n_tris, 1)
    tris = scene.triangles
    o, d = make_rays(tris, n_rays)
    lo = np.zeros(n_rays, np.float32)
    hi = np.full(n_rays, np.inf, np.float32)
    trees = {"sah": build_bvh(tris), "device": build_bvh_device(tris)}
    scenes = {k: ClbvhScene(b.triangles_in_leaf_order(tris), b) for k, b in trees.items()}
    size = (n_rays, 1)
    ctx = scenes["sah"].ctx
    rs, hs = RayStage(size, ctx), HitStage(size, ctx)
    rs.upload_arrays(np.c_[o, lo], np.c_[d, hi])
    times: dict[str, list[float]] = {k: [] for k in scenes}
    hits = {}
    for rep in range(REPS + 1):
        for k, sc in scenes.items():
            ctx.finish()
            t0 = time.perf_counter()
            sc.enqueue(rs.origin, rs.dir, hs.t, hs.tri, n_rays, False)
            ctx.finish()
            if rep:  # the first round compiles and warms
                times[k].append(time.perf_counter() - t0)
            t, slot = hs.read()
            slot = np.asarray(slot).reshape(-1)[:n_rays]
            hits[k] = np.where(slot >= 0, trees[k].tri_order[np.maximum(slot, 0)], -1)
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"scene {scene.name}: {len(tris):,} triangles, {n_rays:,} rays")
    for k in scenes:
        print(f"  {k:>6}: SAH cost {trees[k].stats.sah_cost:.1f}, trace {med[k] * 1e3:.1f} ms "
              f"({n_rays / med[k] / 1e6:.2f} Mrays/s)")
    print(f"  device / sah: SAH cost {trees['device'].stats.sah_cost / trees['sah'].stats.sah_cost:.3f}, "
          f"trace time {med['device'] / med['sah']:.3f}; same hit triangle on "
          f"{100 * np.mean(hits['sah'] == hits['device']):.2f}% of rays")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
