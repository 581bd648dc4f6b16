#!/usr/bin/env python3
"""Golden outputs of librealsense's depth processing blocks for coapcam's rgbd tests.

Feeds each depth fixture (<name>.z16 + <name>.json, written by the rgbd example
`depth_fixtures`) through a librealsense software device and the SDK's processing
blocks (pyrealsense2), and writes every output plus manifest.json describing the cases.

    python3 tools/rs_reference.py --fixtures crates/rgbd/tests/fixtures/rgbd \
        --out crates/rgbd/tests/fixtures/rgbd/librealsense

Output formats: z16 = little-endian u16, f32 = little-endian float32 (disparity),
xyz32 = three little-endian float32 per point. Only the standard library and
pyrealsense2 are needed.
"""

import argparse
import array
import json
import os
import struct
import sys

import pyrealsense2 as rs

MODELS = {
    "None": rs.distortion.none,
    "ModifiedBrownConrady": rs.distortion.modified_brown_conrady,
    "InverseBrownConrady": rs.distortion.inverse_brown_conrady,
    "BrownConrady": rs.distortion.brown_conrady,
    "KannalaBrandt4": rs.distortion.kannala_brandt4,
}
MODEL_NAMES = {v: k for k, v in MODELS.items()}

# Wide-angle intrinsics (128x96, fx 90) so that distortion moves rays noticeably.
DISTORTION_CASES = [
    ("None", [0.0, 0.0, 0.0, 0.0, 0.0]),
    ("BrownConrady", [0.11, -0.06, 0.0012, -0.0021, 0.013]),
    ("InverseBrownConrady", [-0.055, 0.065, -0.0008, 0.0011, -0.021]),
    ("ModifiedBrownConrady", [0.09, -0.03, 0.001, 0.002, 0.0]),
    ("KannalaBrandt4", [-0.012, 0.034, -0.021, 0.0046, 0.0]),
]
DEPROJECT_STEP = 4

SPATIAL_CASES = [
    {"alpha": 0.5, "delta": 20, "iterations": 2, "holes_fill": 0},
    {"alpha": 0.35, "delta": 8, "iterations": 3, "holes_fill": 2},
    {"alpha": 0.8, "delta": 50, "iterations": 1, "holes_fill": 5},
]
HOLE_MODES = {"fill_from_left": 0, "farest_from_around": 1, "nearest_from_around": 2}
DECIMATIONS = [2, 3, 4, 5, 8]
THRESHOLD = {"min_m": 0.85, "max_m": 1.1}


def f32(x):
    """Rounds a Python float to the nearest float32."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def intrinsics_to_json(k):
    return {
        "width": k.width,
        "height": k.height,
        "ppx": k.ppx,
        "ppy": k.ppy,
        "fx": k.fx,
        "fy": k.fy,
        "model": MODEL_NAMES[k.model],
        "coeffs": list(k.coeffs),
    }


def intrinsics_from_json(j):
    k = rs.intrinsics()
    k.width, k.height = j["width"], j["height"]
    k.ppx, k.ppy, k.fx, k.fy = j["ppx"], j["ppy"], j["fx"], j["fy"]
    k.model = MODELS[j["model"]]
    k.coeffs = [float(c) for c in j["coeffs"]]
    return k


class SoftwareDepth:
    """A librealsense software device with one Z16 depth stream of the fixture's
    size, intrinsics, depth units and stereo baseline."""

    def __init__(self, meta):
        self.meta = meta
        self.device = rs.software_device()
        self.sensor = self.device.add_sensor("Depth")
        vs = rs.video_stream()
        vs.type = rs.stream.depth
        vs.index = 0
        vs.uid = 0
        vs.width = meta["width"]
        vs.height = meta["height"]
        vs.fps = 30
        vs.bpp = 2
        vs.fmt = rs.format.z16
        vs.intrinsics = intrinsics_from_json(meta["intrinsics"])
        self.profile = self.sensor.add_video_stream(vs)
        self.sensor.add_read_only_option(rs.option.depth_units, meta["depth_scale"])
        self.sensor.add_read_only_option(rs.option.stereo_baseline, meta["baseline_mm"])
        self.queue = rs.frame_queue(4, keep_frames=True)
        self.sensor.open(self.profile)
        self.sensor.start(self.queue)
        self.number = 0
        self.keep = []

    def frame(self, pixels):
        """Pushes one frame of raw little-endian Z16 bytes and returns librealsense's frame."""
        self.number += 1
        sw = rs.software_video_frame()
        sw.pixels = pixels
        sw.stride = self.meta["width"] * 2
        sw.bpp = 2
        sw.timestamp = float(self.number)
        sw.domain = rs.timestamp_domain.hardware_clock
        sw.frame_number = self.number
        sw.profile = self.profile.as_video_stream_profile()
        sw.depth_units = self.meta["depth_scale"]
        self.keep.append(pixels)
        self.sensor.on_video_frame(sw)
        return self.queue.wait_for_frame(5000)

    def close(self):
        self.sensor.stop()
        self.sensor.close()


def load_fixture(directory, name):
    with open(os.path.join(directory, name + ".json")) as f:
        meta = json.load(f)
    with open(os.path.join(directory, name + ".z16"), "rb") as f:
        pixels = f.read()
    if len(pixels) != 2 * meta["width"] * meta["height"]:
        raise SystemExit(f"{name}.z16 does not hold {meta['width']}x{meta['height']} pixels")
    return meta, pixels


class Writer:
    def __init__(self, out):
        self.out = out
        self.cases = []

    def frame(self, name, input_name, op, params, frame, fmt):
        vf = frame.as_video_frame()
        data = bytes(vf.get_data())
        width, height = vf.get_width(), vf.get_height()
        bpp = 4 if fmt == "f32" else 2
        if len(data) != width * height * bpp:
            raise SystemExit(f"{name}: unexpected buffer size {len(data)}")
        file = name + "." + fmt
        with open(os.path.join(self.out, file), "wb") as f:
            f.write(data)
        k = frame.get_profile().as_video_stream_profile().get_intrinsics()
        self.cases.append({
            "name": name, "input": input_name, "op": op, "params": params,
            "output": file, "format": fmt, "width": width, "height": height,
            "intrinsics": intrinsics_to_json(k),
        })

    def points(self, name, input_name, op, params, floats, count, extra=None):
        file = name + ".xyz32"
        with open(os.path.join(self.out, file), "wb") as f:
            f.write(floats.tobytes())
        case = {"name": name, "input": input_name, "op": op, "params": params,
                "output": file, "format": "xyz32", "points": count}
        case.update(extra or {})
        self.cases.append(case)


def decimate(frame, magnitude):
    dec = rs.decimation_filter()
    dec.set_option(rs.option.filter_magnitude, magnitude)
    return dec.process(frame)


def golden_cases(meta, pixels, name, w):
    """Writes the goldens the fixture's sidecar asks for (its "goldens" list)."""
    wanted = set(meta["goldens"])
    unknown = wanted - {"decimation", "threshold", "hole_filling", "disparity", "spatial",
                        "chain", "pointcloud", "deproject"}
    if unknown:
        raise SystemExit(f"{name}: unknown goldens {sorted(unknown)}")
    dev = SoftwareDepth(meta)
    depth = dev.frame(pixels)

    if "decimation" in wanted:
        for s in DECIMATIONS:
            w.frame(f"{name}.decimation.{s}", name, "decimation", {"magnitude": s},
                    decimate(depth, s), "z16")

    if "threshold" in wanted:
        thr = rs.threshold_filter(THRESHOLD["min_m"], THRESHOLD["max_m"])
        w.frame(f"{name}.threshold", name, "threshold", THRESHOLD, thr.process(depth), "z16")

    if "hole_filling" in wanted:
        for mode, value in HOLE_MODES.items():
            hf = rs.hole_filling_filter(value)
            w.frame(f"{name}.hole_filling.{mode}", name, "hole_filling", {"mode": mode},
                    hf.process(depth), "z16")

    if "disparity" in wanted:
        disparity = rs.disparity_transform(True).process(depth)
        w.frame(f"{name}.to_disparity", name, "to_disparity", {}, disparity, "f32")
        w.frame(f"{name}.to_depth", name, "to_depth", {},
                rs.disparity_transform(False).process(disparity), "z16")

    if "spatial" in wanted:
        # On the frame decimated by 2, as in the chain.
        for i, p in enumerate(SPATIAL_CASES):
            sp = rs.spatial_filter(p["alpha"], p["delta"], p["iterations"], p["holes_fill"])
            disp = rs.disparity_transform(True).process(decimate(depth, 2))
            w.frame(f"{name}.spatial.{i}", name, "spatial", dict(p, decimation=2),
                    sp.process(disp), "f32")

    if "chain" in wanted:
        # The PostProcessing chain: decimation 2 -> disparity -> spatial (defaults) ->
        # depth -> hole filling (farest_from_around).
        out = decimate(depth, 2)
        out = rs.disparity_transform(True).process(out)
        out = rs.spatial_filter().process(out)
        out = rs.disparity_transform(False).process(out)
        out = rs.hole_filling_filter(1).process(out)
        w.frame(f"{name}.chain", name, "chain",
                {"decimation": 2, "spatial": SPATIAL_CASES[0],
                 "holefilling": "farest_from_around"}, out, "z16")

    if "pointcloud" in wanted:
        # The point-cloud block on the frame decimated by 4: one vertex per pixel,
        # (0, 0, 0) where depth is 0.
        small = decimate(depth, 4)
        pts = rs.pointcloud().calculate(small)
        vertices = array.array("f", bytes(pts.get_vertices()))
        if sys.byteorder != "little":
            vertices.byteswap()
        k = small.get_profile().as_video_stream_profile().get_intrinsics()
        w.points(f"{name}.pointcloud", name, "pointcloud", {"decimation": 4}, vertices,
                 len(vertices) // 3, {"intrinsics": intrinsics_to_json(k)})

    if "deproject" in wanted:
        # rs2_deproject_pixel_to_point on a pixel grid, for every distortion model.
        raw = array.array("H", pixels)
        if sys.byteorder != "little":
            raw.byteswap()
        scale = f32(meta["depth_scale"])
        width, height = meta["width"], meta["height"]
        for model, coeffs in DISTORTION_CASES:
            k = rs.intrinsics()
            k.width, k.height = width, height
            k.fx, k.fy = 90.0, 91.5
            k.ppx, k.ppy = width / 2 - 0.7, height / 2 + 0.4
            k.model = MODELS[model]
            k.coeffs = coeffs
            floats = array.array("f")
            count = 0
            for v in range(0, height, DEPROJECT_STEP):
                for u in range(0, width, DEPROJECT_STEP):
                    z = f32(scale * raw[v * width + u])
                    floats.extend(rs.rs2_deproject_pixel_to_point(k, [float(u), float(v)], z))
                    count += 1
            w.points(f"{name}.deproject.{model}", name, "deproject", {"step": DEPROJECT_STEP},
                     floats, count, {"intrinsics": intrinsics_to_json(k)})
    dev.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fixtures", required=True, help="directory of <name>.z16 + <name>.json")
    ap.add_argument("--out", required=True, help="directory for the goldens and manifest.json")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    names = sorted(f[:-4] for f in os.listdir(args.fixtures) if f.endswith(".z16"))
    if not names:
        raise SystemExit(f"no .z16 fixtures in {args.fixtures}")
    w = Writer(args.out)
    for name in names:
        meta, pixels = load_fixture(args.fixtures, name)
        golden_cases(meta, pixels, name, w)
    manifest = {"librealsense": rs.__version__, "cases": w.cases}
    with open(os.path.join(args.out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)
        f.write("\n")
    print(f"librealsense {rs.__version__}: {len(w.cases)} goldens in {args.out}")


if __name__ == "__main__":
    main()
