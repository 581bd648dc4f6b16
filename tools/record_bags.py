#!/usr/bin/env python3
"""Recordings made by librealsense's own recorder, for coapcam's playback tests.

Builds a software device that looks like a D415 (a "Stereo Module" with a Z16 depth
stream and an "RGB Camera" with an RGB8 color stream, both 640x480 at 30 fps, D415-like
intrinsics, depth units 0.0001 m, serial 725112060411), records FRAMES deterministic
frames of each stream with `rs.recorder`, then plays the file back with librealsense's
own playback device and writes what it returns beside the recording:

    <out>/<name>.bag|.db3            the recording
    <out>/<name>.expected.json       librealsense's playback: serial, name, depth scale,
                                     stream intrinsics, and per frame its number and the
                                     FNV-1a 64 hash, size and first values of its pixels

pyrealsense2 2.56.x writes ROS 1 bags; 2.57 and later write only ROS 2 `.db3` (SQLite).
The extension follows the library version. Run it once per version (one virtual
environment each; tools/record_bags.sh does both):

    python3 tools/record_bags.py --out crates/rgbd/tests/fixtures/bag --name d415

Needs only the standard library and pyrealsense2 (and the libusb-1.0 runtime it links).
"""

import argparse
import json
import os
import struct
import sys
import time

import pyrealsense2 as rs

WIDTH, HEIGHT, FPS = 640, 480, 30
FRAMES = 3
SERIAL = "725112060411"
NAME = "Intel RealSense D415"
# Not librealsense's default (0.001): a reader that ignores the recorded value fails.
DEPTH_UNITS = 0.0001
# A D415 at 640x480 (depth: fx = 896.1 * 2/3, pinhole; color: 912.5 * 2/3, inverse
# Brown-Conrady with small coefficients so that they are checked too).
DEPTH_K = (597.4, 597.4, 318.0, 242.6, rs.distortion.brown_conrady, [0.0] * 5)
COLOR_K = (608.33, 607.47, 325.6, 237.6, rs.distortion.inverse_brown_conrady,
           [0.12, -0.21, 0.0011, -0.0007, 0.09])
# 2 degrees about y, column-major; and the translation in metres.
DEPTH_TO_COLOR_ROTATION = [0.9993908, 0.0, -0.0348995, 0.0, 1.0, 0.0, 0.0348995, 0.0, 0.9993908]
DEPTH_TO_COLOR_TRANSLATION = [0.015, -0.0002, 0.0004]
TILE = 16
PREFIX = 8  # leading pixel values listed in the JSON, for readable diffs


def depth_pixels(frame):
    """Z16 pixels of depth frame `frame` (1-based): 16x16 tiles of distinct depths, a
    hole where the tile index is a multiple of 7, and a one-pixel diagonal line."""
    out = bytearray(WIDTH * HEIGHT * 2)
    for y in range(HEIGHT):
        row = bytearray(WIDTH * 2)
        for x in range(WIDTH):
            tx, ty = x // TILE, y // TILE
            if (tx + ty * 40) % 7 == 0:
                v = 0
            else:
                v = 4000 + 97 * tx + 331 * ty + 50 * frame
            if x == y + frame:
                v = 65535
            struct.pack_into("<H", row, 2 * x, v)
        out[y * WIDTH * 2:(y + 1) * WIDTH * 2] = row
    return bytes(out)


def color_pixels(frame):
    """RGB8 pixels of color frame `frame` (1-based): 16x16 tiles of distinct colors."""
    out = bytearray(WIDTH * HEIGHT * 3)
    for y in range(HEIGHT):
        row = bytearray(WIDTH * 3)
        for x in range(WIDTH):
            tx, ty = x // TILE, y // TILE
            row[3 * x:3 * x + 3] = bytes(
                ((7 * tx + frame * 20) % 256, (11 * ty) % 256, (5 * tx + 3 * ty) % 256))
        out[y * WIDTH * 3:(y + 1) * WIDTH * 3] = row
    return bytes(out)


def fnv1a64(data):
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return "%016x" % h


def intrinsics(k):
    fx, fy, ppx, ppy, model, coeffs = k
    i = rs.intrinsics()
    i.width, i.height = WIDTH, HEIGHT
    i.fx, i.fy, i.ppx, i.ppy = fx, fy, ppx, ppy
    i.model, i.coeffs = model, coeffs
    return i


MODEL_NAMES = {
    rs.distortion.none: "None",
    rs.distortion.modified_brown_conrady: "ModifiedBrownConrady",
    rs.distortion.inverse_brown_conrady: "InverseBrownConrady",
    rs.distortion.brown_conrady: "BrownConrady",
    rs.distortion.kannala_brandt4: "KannalaBrandt4",
}


def intrinsics_json(i):
    return {
        "width": i.width, "height": i.height, "ppx": i.ppx, "ppy": i.ppy,
        "fx": i.fx, "fy": i.fy, "model": MODEL_NAMES[i.model], "coeffs": list(i.coeffs),
    }


def version():
    try:
        return rs.__version__
    except AttributeError:
        return rs.pyrealsense2.__version__


def record(path):
    dev = rs.software_device()
    depth_sensor = dev.add_sensor("Stereo Module")
    color_sensor = dev.add_sensor("RGB Camera")
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.depth, 0, 0
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = WIDTH, HEIGHT, FPS, 2, rs.format.z16
    vs.intrinsics = intrinsics(DEPTH_K)
    depth_profile = depth_sensor.add_video_stream(vs)
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.color, 0, 1
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = WIDTH, HEIGHT, FPS, 3, rs.format.rgb8
    vs.intrinsics = intrinsics(COLOR_K)
    color_profile = color_sensor.add_video_stream(vs)
    # A D415-like depth -> color transform: 15 mm along x and a slight rotation about y
    # (column-major, as rs2_extrinsics), so a reader's conventions are checked.
    e = rs.extrinsics()
    e.rotation = DEPTH_TO_COLOR_ROTATION
    e.translation = DEPTH_TO_COLOR_TRANSLATION
    depth_profile.register_extrinsics_to(color_profile, e)
    depth_sensor.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)
    dev.register_info(rs.camera_info.serial_number, SERIAL)
    dev.register_info(rs.camera_info.name, NAME)
    dev.register_info(rs.camera_info.product_line, "D400")

    recorder = rs.recorder(path, dev)
    sensors = {s.get_info(rs.camera_info.name): s for s in recorder.query_sensors()}
    received = []
    for name, profile in (("Stereo Module", depth_profile), ("RGB Camera", color_profile)):
        sensors[name].open(profile)
        sensors[name].start(lambda f: received.append(f.get_frame_number()))

    for n in range(1, FRAMES + 1):
        for sensor, profile, pixels, bpp in (
            (depth_sensor, depth_profile, depth_pixels(n), 2),
            (color_sensor, color_profile, color_pixels(n), 3),
        ):
            f = rs.software_video_frame()
            f.pixels = pixels
            f.bpp = bpp
            f.stride = WIDTH * bpp
            f.timestamp = n * 1000.0 / FPS
            f.domain = rs.timestamp_domain.hardware_clock
            f.frame_number = n
            f.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(f)
    deadline = time.monotonic() + 10
    while len(received) < 2 * FRAMES and time.monotonic() < deadline:
        time.sleep(0.01)
    if len(received) < 2 * FRAMES:
        sys.exit("recorder delivered %d of %d frames" % (len(received), 2 * FRAMES))
    for s in sensors.values():
        s.stop()
        s.close()
    del recorder  # closes the file


def playback(path):
    """What librealsense's own playback returns for the recording."""
    ctx = rs.context()
    dev = ctx.load_device(path)
    pb = dev.as_playback()
    pb.set_real_time(False)
    statuses = []
    pb.set_status_changed_callback(statuses.append)

    def ended():
        seen = list(statuses)
        return rs.playback_status.playing in seen and seen[-1] == rs.playback_status.stopped
    frames = {"depth": [], "color": []}
    streams = {}
    depth_scale = None
    for sensor in dev.query_sensors():
        if sensor.is_depth_sensor():
            depth_scale = sensor.as_depth_sensor().get_depth_scale()
        profiles = sensor.get_stream_profiles()

        def on_frame(f):
            kind = "depth" if f.get_profile().stream_type() == rs.stream.depth else "color"
            data = bytes(f.get_data())
            if kind == "depth":
                prefix = list(struct.unpack_from("<%dH" % PREFIX, data))
                units = f.as_depth_frame().get_units()
            else:
                prefix = list(data[:PREFIX])
                units = None
            frames[kind].append({
                "frame_number": f.get_frame_number(),
                "timestamp_ms": f.get_timestamp(),
                "bytes": len(data),
                "fnv1a64": fnv1a64(data),
                "prefix": prefix,
                "units": units,
            })

        for p in profiles:
            vp = p.as_video_stream_profile()
            kind = "depth" if p.stream_type() == rs.stream.depth else "color"
            streams[kind] = {
                "format": str(p.format()).split(".")[-1].upper(),
                "fps": p.fps(),
                "intrinsics": intrinsics_json(vp.get_intrinsics()),
            }
        sensor.open(profiles)
        sensor.start(on_frame)
    # The status reads `stopped` before playback begins as well as after it ends: wait
    # for `stopped` after `playing`.
    deadline = time.monotonic() + 30
    while not ended() and time.monotonic() < deadline:
        time.sleep(0.01)
    if not ended():
        sys.exit("librealsense's playback of %s did not finish: %s" % (path, statuses))
    for sensor in dev.query_sensors():
        sensor.stop()
        sensor.close()
    depth_profile = next(p for s in dev.query_sensors() for p in s.get_stream_profiles()
                         if p.stream_type() == rs.stream.depth)
    color_profile = next(p for s in dev.query_sensors() for p in s.get_stream_profiles()
                         if p.stream_type() == rs.stream.color)
    e = depth_profile.get_extrinsics_to(color_profile)
    for kind in frames:
        frames[kind].sort(key=lambda f: f["frame_number"])
    return {
        "librealsense": version(),
        "serial": dev.get_info(rs.camera_info.serial_number),
        "name": dev.get_info(rs.camera_info.name),
        "depth_scale": depth_scale,
        "depth_to_color": {"rotation": list(e.rotation), "translation": list(e.translation)},
        "streams": streams,
        "frames": frames,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="directory for the recording and its JSON")
    ap.add_argument("--name", default="d415", help="file name without extension")
    args = ap.parse_args()
    ext = ".db3" if tuple(int(p) for p in version().split(".")[:2]) >= (2, 57) else ".bag"
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, args.name + ext)
    if os.path.exists(path):
        os.remove(path)
    record(path)
    expected = playback(path)
    expected["recording"] = os.path.basename(path)
    expected["written"] = {
        "frames": FRAMES,
        "depth_fnv1a64": [fnv1a64(depth_pixels(n)) for n in range(1, FRAMES + 1)],
        "color_fnv1a64": [fnv1a64(color_pixels(n)) for n in range(1, FRAMES + 1)],
    }
    with open(os.path.join(args.out, args.name + ext + ".expected.json"), "w") as f:
        json.dump(expected, f, indent=1, sort_keys=True)
        f.write("\n")
    print("%s: %d bytes, librealsense %s" % (path, os.path.getsize(path), version()))


if __name__ == "__main__":
    main()
