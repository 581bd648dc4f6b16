#!/usr/bin/env bash
# Regenerates the rgbd differential-test fixtures in crates/rgbd/tests/fixtures/rgbd:
# the depth inputs (synthetic D415 windows, Rust example `depth_fixtures`) and the
# librealsense goldens (tools/rs_reference.py, needs `python3 -m pip install pyrealsense2`
# and the libusb-1.0 runtime).
set -euo pipefail
cd "$(dirname "$0")/.."
dir=crates/rgbd/tests/fixtures/rgbd
python="${PYTHON:-python3}"
"$python" -c 'import pyrealsense2' || {
    echo "pyrealsense2 is not importable by $python: python3 -m pip install pyrealsense2" >&2
    exit 1
}
rm -rf "$dir"
cargo run --quiet -p rgbd --example depth_fixtures -- "$dir"
"$python" tools/rs_reference.py --fixtures "$dir" --out "$dir/librealsense"
du -sh "$dir"
