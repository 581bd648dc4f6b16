#!/usr/bin/env bash
# Records the playback fixtures in crates/rgbd/tests/fixtures/bag with librealsense's own
# recorder: d415.bag with pyrealsense2 2.56.5 (the last ROS 1 writer) and d415.db3 with
# pyrealsense2 2.59.1 (ROS 2 SQLite), each in its own virtual environment under
# ${VENV_DIR:-$HOME/.cache/coapcam/venvs}. Needs python3 with venv, network access to
# PyPI, and the libusb-1.0 runtime. See tools/record_bags.py.
set -euo pipefail
cd "$(dirname "$0")/.."
out=crates/rgbd/tests/fixtures/bag
venvs="${VENV_DIR:-$HOME/.cache/coapcam/venvs}"
for version in 2.56.5.9235 2.59.1.11053; do
    venv="$venvs/pyrealsense2-$version"
    if ! "$venv/bin/python" -c 'import pyrealsense2' 2>/dev/null; then
        python3 -m venv "$venv"
        "$venv/bin/python" -m pip install --quiet "pyrealsense2==$version"
    fi
    "$venv/bin/python" tools/record_bags.py --out "$out" --name d415
done
du -sh "$out"
