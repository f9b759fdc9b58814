#!/usr/bin/env bash
# Create (or reuse) the virtual environment for nerfuser_ns and install the project into it.
# Prints the environment's path on its last line. The environment is keyed by a hash of the pinned
# requirements, so it is reused until they change; override its location with NERFUSER_VENV.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PYTHON="${PYTHON:-$(command -v python3.11 || command -v python3)}"
HASH="$(cat "$ROOT/requirements.lock" "$ROOT/scripts/setup_env.sh" | sha256sum | cut -c1-12)"
VENV="${NERFUSER_VENV:-$HOME/.cache/nerfuser_ns/venv-$HASH}"

# open3d's wheel links libusb-1.0, which minimal Debian/Ubuntu images lack.
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
    if command -v apt-get >/dev/null && [ "$(id -u)" = "0" ]; then
        echo "setup: installing libusb-1.0-0 (needed by open3d)" >&2
        (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >&2
    else
        echo "setup: open3d needs the system library libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0)" >&2
        exit 1
    fi
fi

if [ ! -f "$VENV/.nerfuser-complete" ]; then
    echo "setup: creating $VENV (first run: a few minutes, ~8 GB with torch's CUDA libraries)" >&2
    rm -rf "$VENV"
    mkdir -p "$(dirname "$VENV")"
    "$PYTHON" -m venv "$VENV"
    # Some machines offer a CPU-only torch wheel through pip's find-links; PyPI has no torchvision built
    # against it (its C ops fail to load), so install PyPI's matching torch/torchvision pair instead.
    PIP_FIND_LINKS=" " "$VENV/bin/pip" install --quiet --disable-pip-version-check -r "$ROOT/requirements.lock"
    # Three distributions ship cv2 (nerfstudio pins opencv-python-headless, nuscenes-devkit brings
    # opencv-python); make the contrib build the one that is importable.
    "$VENV/bin/pip" install --quiet --disable-pip-version-check --force-reinstall --no-deps \
        "$(grep '^opencv-contrib-python-headless==' "$ROOT/requirements.lock")"
    touch "$VENV/.nerfuser-complete"
fi
# Always (cheap): point the environment at this checkout.
"$VENV/bin/pip" install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e "$ROOT" >&2
"$VENV/bin/python" -c "import cv2, torchvision, pycolmap, open3d, nerfstudio.pipelines.base_pipeline, nerfuser_ns" \
    || { echo "setup: the environment at $VENV is broken; delete it and re-run" >&2; exit 1; }
echo "$VENV"
