#!/usr/bin/env bash
# Set up sparseart on a fresh machine: the system library open3d needs, then the package itself.
# Idempotent; safe to run again. Torch (for the optional refinement) is not installed here:
# use `pip install torch==2.13.0` first when you need it (a CPU wheel lies on this machine's disk).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    echo "setup: installing libusb-1.0 (needed by open3d)" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq >/dev/null
    $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi
python3 -m pip install -q --disable-pip-version-check -e ".[test]" 2>&1 \
    | grep -v -E "^WARNING: (Location|Running pip as)" || true
python3 -c "import sparseart, open3d, cv2, scipy" 
