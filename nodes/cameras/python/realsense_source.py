"""The camera node's RealSense source: librealsense through pyrealsense2, in its own process.

pyrealsense2's extension module carries librealsense (Debian has no package), but it cannot be
loaded into a non-Python process: it leaves CPython's data symbols (PyExc_ValueError, ...)
unresolved. So labrig-cameras runs this script with the Python of scripts/setup.sh
(LABRIG_REALSENSE_PYTHON) and reads its stdout:

    line 1:    JSON {"serial", "name", "intrinsics": {width, height, fx, fy, cx, cy,
               distortion}, "fps", "depth_scale_m"}   (the colour stream's, from the device;
                                                       depth_scale_m: null without --depth)
    per frame: JSON {"seq", "ts_ms", "domain", "bytes", "depth_bytes"} + newline, then
               `bytes` of RGB8, then `depth_bytes` of depth (--depth: the depth frame aligned
               to the colour image by librealsense, so pixel (u, v) of both is the same ray;
               uint16 little endian, millimetres, 0 = no depth; else 0 bytes)

Errors go to stderr, one line naming the problem, exit 2.

    python realsense_source.py (--serial S | --file F.db3 [--loop]) --width W --height H --fps F [--depth]
"""
import argparse
import json
import sys

import pyrealsense2 as rs


def fail(msg):
    print(msg, file=sys.stderr, flush=True)
    sys.exit(2)


def main():
    p = argparse.ArgumentParser()
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--serial")
    src.add_argument("--file")
    p.add_argument("--loop", action="store_true")
    p.add_argument("--width", type=int, required=True)
    p.add_argument("--height", type=int, required=True)
    p.add_argument("--fps", type=int, required=True)
    p.add_argument("--depth", action="store_true")
    a = p.parse_args()

    cfg = rs.config()
    if a.file:
        cfg.enable_device_from_file(a.file, repeat_playback=a.loop)
        cfg.enable_stream(rs.stream.color)
        if a.depth:
            cfg.enable_stream(rs.stream.depth)
    else:
        found = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        if a.serial not in found:
            fail(f"no RealSense with serial {a.serial} (found: {', '.join(found) or 'none'})")
        cfg.enable_device(a.serial)
        cfg.enable_stream(rs.stream.color, a.width, a.height, rs.format.rgb8, a.fps)
        if a.depth:
            # Any depth size the device offers at this rate: it is aligned to the colour size.
            cfg.enable_stream(rs.stream.depth, rs.format.z16, a.fps)
    pipe = rs.pipeline()
    try:
        prof = pipe.start(cfg)
    except RuntimeError as e:
        fail(f"librealsense: {e}" + (" (depth = true: the device or recording needs a depth stream)" if a.depth else ""))
    dev = prof.get_device()
    if a.file:
        dev.as_playback().set_real_time(True)
    vs = prof.get_stream(rs.stream.color).as_video_stream_profile()
    i = vs.get_intrinsics()
    if (i.width, i.height) != (a.width, a.height):
        fail(f"the colour stream is {i.width}x{i.height}, the camera is configured for {a.width}x{a.height}")
    if vs.format() not in (rs.format.rgb8, rs.format.bgr8):
        fail(f"the colour stream's format is {vs.format()}, not rgb8/bgr8")
    bgr = vs.format() == rs.format.bgr8
    align = rs.align(rs.stream.color) if a.depth else None
    scale = dev.first_depth_sensor().get_depth_scale() if a.depth else None
    out = sys.stdout.buffer
    def info(key):
        return dev.get_info(key) if dev.supports(key) else ""

    head = {
        "serial": info(rs.camera_info.serial_number),
        "name": info(rs.camera_info.name),
        "fps": vs.fps(),
        "intrinsics": {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy,
                       "cx": i.ppx, "cy": i.ppy, "distortion": list(i.coeffs)},
        "depth_scale_m": scale,
    }
    out.write((json.dumps(head) + "\n").encode())
    out.flush()
    while True:
        try:
            frames = pipe.wait_for_frames(2000)
        except RuntimeError:
            if a.file and not a.loop:
                return 0  # the recording is over
            fail("no frame for 2 s")
        depth = b""
        if align is not None:
            frames = align.process(frames)
            d = frames.get_depth_frame()
            if not d:
                continue
            import numpy as np
            z = np.asanyarray(d.get_data())
            if (z.shape[1], z.shape[0]) != (a.width, a.height):
                fail(f"the aligned depth is {z.shape[1]}x{z.shape[0]}, the colour image {a.width}x{a.height}")
            if abs(scale - 0.001) > 1e-9:
                z = np.clip(np.round(z * (scale * 1000.0)), 0, 65535)
            depth = z.astype("<u2").tobytes()
        c = frames.get_color_frame()
        if not c:
            continue
        data = bytes(c.get_data())
        if bgr:
            import numpy as np
            data = np.frombuffer(data, np.uint8).reshape(-1, 3)[:, ::-1].tobytes()
        meta = {"seq": c.get_frame_number(), "ts_ms": c.get_timestamp(),
                "domain": str(c.get_frame_timestamp_domain()).split(".")[-1], "bytes": len(data),
                "depth_bytes": len(depth)}
        try:
            out.write((json.dumps(meta) + "\n").encode())
            out.write(data)
            out.write(depth)
            out.flush()
        except BrokenPipeError:
            return 0


if __name__ == "__main__":
    sys.exit(main())
