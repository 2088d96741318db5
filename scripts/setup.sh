#!/usr/bin/env bash
# Set up sparseart on a fresh machine: the system library open3d needs, then the package itself.
# Idempotent; safe to run again. Torch (the optional refinement) is installed first and pinned:
# `torch==2.13.0` is a CPU wheel on this machine's disk; a bare `torch` could pull a multi-GB CUDA build.
# The other dependencies are held at the versions the benches were measured with (constraints.txt).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    echo "setup: installing libusb-1.0 (needed by open3d)" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq >/dev/null
    $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi
if [ ! -x /usr/bin/chromium ]; then
    echo "setup: installing chromium (the headless browser of the sparseart view test)" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq >/dev/null
    $SUDO apt-get install -y -qq chromium chromium-driver >/dev/null
fi
python3 -c "import torch" 2>/dev/null || python3 -m pip install -q --disable-pip-version-check torch==2.13.0 2>&1 \
    | grep -v -E "^WARNING: (Location|Running pip as)" || true
python3 -m pip install -q --disable-pip-version-check -c constraints.txt -e ".[test,refine,view,sim]" 2>&1 \
    | grep -v -E "^WARNING: (Location|Running pip as)" || true
python3 -c "import sparseart, open3d, cv2, scipy, torch, onnx, onnxruntime, coacd, trimesh, mujoco, pybullet, pxr"
