#!/usr/bin/env python3
"""librealsense's side of scripts/bench-depth.sh: the depth chain of a point-cloud grab
through pyrealsense2 on the frame the rgbd criterion bench exported.

    python3 tools/rs_bench.py --frame /tmp/rgbd-bench-1280x720 [--iterations 60]

Chain: decimation (2) -> depth to disparity -> spatial (defaults) -> disparity to
depth -> hole filling (farest_from_around) -> point cloud; then, when numpy is
importable, the transform into the world and the 3D ROI (librealsense has no block for
them). Prints one JSON object with median and mean milliseconds per frame.
"""

import argparse
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import pyrealsense2 as rs  # noqa: E402
from rs_reference import SoftwareDepth  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frame", required=True, help="path prefix of <frame>.z16 and <frame>.json")
    ap.add_argument("--iterations", type=int, default=60)
    args = ap.parse_args()
    with open(args.frame + ".json") as f:
        meta = json.load(f)
    with open(args.frame + ".z16", "rb") as f:
        pixels = f.read()
    dev = SoftwareDepth(meta)
    depth = dev.frame(pixels)

    decimation = rs.decimation_filter()
    decimation.set_option(rs.option.filter_magnitude, 2)
    to_disparity = rs.disparity_transform(True)
    spatial = rs.spatial_filter()
    to_depth = rs.disparity_transform(False)
    holes = rs.hole_filling_filter(1)
    pointcloud = rs.pointcloud()

    try:
        import numpy as np
        linear = np.array(meta["to_world"]["linear"], dtype=np.float32)
        translation = np.array(meta["to_world"]["translation"], dtype=np.float32)
        lo = np.array(meta["roi"]["min"], dtype=np.float32)
        hi = np.array(meta["roi"]["max"], dtype=np.float32)
    except ImportError:
        np = None

    def chain():
        f = decimation.process(depth)
        f = to_disparity.process(f)
        f = spatial.process(f)
        f = to_depth.process(f)
        f = holes.process(f)
        return pointcloud.calculate(f)

    def crop(points):
        v = np.asarray(points.get_vertices()).view(np.float32).reshape(-1, 3)
        v = v[v[:, 2] > 0]
        w = v @ linear.T + translation
        return w[np.all((w >= lo) & (w <= hi), axis=1)]

    def timed(fn):
        for _ in range(5):
            fn()
        times = []
        for _ in range(args.iterations):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
        return {"median_ms": statistics.median(times), "mean_ms": statistics.mean(times)}

    result = {
        "librealsense": rs.__version__,
        "frame": f"{meta['width']}x{meta['height']}",
        "filters_and_points": timed(chain),
    }
    if np is not None:
        result["full_chain"] = timed(lambda: crop(chain()))
        result["points_in_roi"] = int(len(crop(chain())))
    dev.close()
    print(json.dumps(result))


if __name__ == "__main__":
    main()
