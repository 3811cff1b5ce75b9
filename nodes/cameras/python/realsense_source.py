"""The camera node's RealSense source: librealsense through pyrealsense2, in its own process.

pyrealsense2's extension module carries librealsense (Debian has no package), but it cannot be
loaded into a non-Python process: it leaves CPython's data symbols (PyExc_ValueError, ...)
unresolved. So labrig-cameras runs this script with the Python of scripts/setup.sh
(LABRIG_REALSENSE_PYTHON) and reads its stdout:

    line 1:    JSON {"serial", "name", "intrinsics": {width, height, fx, fy, cx, cy,
               distortion}, "fps"}                    (the colour stream's, from the device)
    per frame: JSON {"seq", "ts_ms", "domain", "bytes"} + newline, then `bytes` of RGB8

Errors go to stderr, one line naming the problem, exit 2.

    python realsense_source.py (--serial S | --file F.db3 [--loop]) --width W --height H --fps F
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
    a = p.parse_args()

    cfg = rs.config()
    if a.file:
        cfg.enable_device_from_file(a.file, repeat_playback=a.loop)
        cfg.enable_stream(rs.stream.color)
    else:
        found = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        if a.serial not in found:
            fail(f"no RealSense with serial {a.serial} (found: {', '.join(found) or 'none'})")
        cfg.enable_device(a.serial)
        cfg.enable_stream(rs.stream.color, a.width, a.height, rs.format.rgb8, a.fps)
    pipe = rs.pipeline()
    try:
        prof = pipe.start(cfg)
    except RuntimeError as e:
        fail(f"librealsense: {e}")
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
    out = sys.stdout.buffer
    def info(key):
        return dev.get_info(key) if dev.supports(key) else ""

    head = {
        "serial": info(rs.camera_info.serial_number),
        "name": info(rs.camera_info.name),
        "fps": vs.fps(),
        "intrinsics": {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy,
                       "cx": i.ppx, "cy": i.ppy, "distortion": list(i.coeffs)},
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
        c = frames.get_color_frame()
        if not c:
            continue
        data = bytes(c.get_data())
        if bgr:
            import numpy as np
            data = np.frombuffer(data, np.uint8).reshape(-1, 3)[:, ::-1].tobytes()
        meta = {"seq": c.get_frame_number(), "ts_ms": c.get_timestamp(),
                "domain": str(c.get_frame_timestamp_domain()).split(".")[-1], "bytes": len(data)}
        try:
            out.write((json.dumps(meta) + "\n").encode())
            out.write(data)
            out.flush()
        except BrokenPipeError:
            return 0


if __name__ == "__main__":
    sys.exit(main())
