#!/usr/bin/env bash
# Installs what a fresh Debian 12 / Ubuntu 24.04 machine lacks for rtwalk: Mesa EGL/GL (llvmpipe),
# PoCL (OpenCL on the CPU; it brings clang, which tests/test_portability.py uses for NVIDIA's OpenCL
# target), glslang-tools (the reference GLSL compiler: the same test), Xvfb for the windowed smoke
# test, python3-venv; then the project with its test extras into the project's own virtual
# environment .venv (the system Python is externally managed, PEP 668, and is never written to).
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null; then SUDO="sudo"; fi
PY="${RTWALK_PYTHON:-python3}"
APT_PKGS="libegl1 libegl-mesa0 libgl1-mesa-dri libgles2 libglu1-mesa pocl-opencl-icd ocl-icd-libopencl1 glslang-tools xvfb xauth"
# a python3 without the venv module (Debian's python3 without python3-venv) needs the package
if ! "$PY" -c "import venv, ensurepip" >/dev/null 2>&1; then
  ver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
  APT_PKGS="$APT_PKGS python3-venv python${ver}-venv"
fi
missing=""
for p in $APT_PKGS; do
  dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "installing apt packages:$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi
if [ ! -x .venv/bin/python ]; then
  echo "creating the virtual environment .venv"
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
echo "rtwalk installed in .venv: run .venv/bin/rtwalk, or activate it with '. .venv/bin/activate'"
