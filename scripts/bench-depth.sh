#!/usr/bin/env bash
# The depth chain of a point-cloud grab, ours against librealsense's, on the same
# 1280x720 synthetic D415 frame in the same run: criterion bench `rgbd/depth` (which
# exports the frame), then tools/rs_bench.py (pyrealsense2; numpy adds the transform +
# ROI stage on librealsense's side), then the table and the ratios.
set -euo pipefail
cd "$(dirname "$0")/.."
target="${CARGO_TARGET_DIR:-target}"
python="${PYTHON:-python3}"
frame="$("$python" -c 'import tempfile; print(tempfile.gettempdir())')/rgbd-bench-1280x720"

cargo bench -p rgbd --bench depth -- --noplot "full_chain|filters_and_points"
"$python" tools/rs_bench.py --frame "$frame" > "$target/rs_bench.json"

"$python" - "$target" <<'PY'
import json, sys
target = sys.argv[1]
lrs = json.load(open(f"{target}/rs_bench.json"))
def ours(name):
    est = json.load(open(f"{target}/criterion/depth_chain_1280x720/{name}/new/estimates.json"))
    return est["median"]["point_estimate"] / 1e6
print(f"\ndepth chain, 1280x720 synthetic D415 frame, librealsense {lrs['librealsense']} (pyrealsense2)")
print(f"{'stage':<58} {'ours ms':>8} {'librealsense ms':>16} {'ratio':>6}")
rows = [("decimation 2 -> spatial -> hole filling -> points", "filters_and_points")]
if "full_chain" in lrs:
    rows.append(("... -> transform + 3D ROI (librealsense side: numpy)", "full_chain"))
for label, name in rows:
    o, l = ours(name), lrs[name]["median_ms"]
    print(f"{label:<58} {o:8.2f} {l:16.2f} {l / o:5.1f}x")
if "full_chain" not in lrs:
    print("(numpy not importable: transform + ROI compared on our side only)")
PY
