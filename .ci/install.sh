#!/usr/bin/env bash
# Installs what a fresh Debian machine lacks for rtwalk: Mesa EGL/GL (llvmpipe), PoCL (OpenCL on
# the CPU), Xvfb for the windowed smoke test; then the project with its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null; then SUDO="sudo"; fi
APT_PKGS="libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libglu1-mesa pocl-opencl-icd ocl-icd-libopencl1 xvfb xauth"
missing=""
for p in $APT_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "installing apt packages:$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi
python3 -m pip install -q --disable-pip-version-check -e ".[test]"
