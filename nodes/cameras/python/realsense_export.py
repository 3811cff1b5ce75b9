"""Write a RealSense's calibration for labrig's Rust alignment (`labrig cameras realsense-export`):
the colour and depth streams' intrinsics, the depth -> colour extrinsics and the depth scale, as
librealsense (pyrealsense2) reports them. Run once at set-up, off the robot path; the running rig
reads the file and needs no Python.

    python realsense_export.py (--serial S | --file F.db3) --out CAL.json
                               [--width 1280 --height 720 --fps 30] [--frames DIR]

The intrinsics depend on the stream's resolution: export at the size the rig runs the camera
at (a recording: its own). --frames DIR also writes one frameset for checking the Rust side:
DIR/depth.u16 (the raw z16 frame), DIR/aligned.u16 (librealsense's `align` to colour), both
little endian. Errors go to stderr, one line naming the problem, exit 2.
"""
import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pyrealsense2 as rs


def fail(msg):
    print(msg, file=sys.stderr, flush=True)
    sys.exit(2)


def intrinsics(i):
    return {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "ppx": i.ppx, "ppy": i.ppy,
            "model": str(i.model).split(".")[-1], "coeffs": list(i.coeffs)}


def main():
    p = argparse.ArgumentParser()
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--serial")
    src.add_argument("--file")
    p.add_argument("--out", required=True)
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--frames")
    a = p.parse_args()

    cfg = rs.config()
    if a.file:
        cfg.enable_device_from_file(a.file, repeat_playback=False)
        cfg.enable_stream(rs.stream.color)
        cfg.enable_stream(rs.stream.depth)
    else:
        found = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
        if a.serial not in found:
            fail(f"no RealSense with serial {a.serial} (found: {', '.join(found) or 'none'})")
        cfg.enable_device(a.serial)
        cfg.enable_stream(rs.stream.color, a.width, a.height, rs.format.yuyv, a.fps)
        cfg.enable_stream(rs.stream.depth, rs.format.z16, a.fps)
    pipe = rs.pipeline()
    try:
        prof = pipe.start(cfg)
    except RuntimeError as e:
        fail(f"librealsense: {e} (the device or recording needs a colour and a depth stream)")
    dev = prof.get_device()
    colour = prof.get_stream(rs.stream.color).as_video_stream_profile()
    depth = prof.get_stream(rs.stream.depth).as_video_stream_profile()
    ext = depth.get_extrinsics_to(colour)
    serial = dev.get_info(rs.camera_info.serial_number) if dev.supports(rs.camera_info.serial_number) else ""
    name = dev.get_info(rs.camera_info.name) if dev.supports(rs.camera_info.name) else ""
    cal = {
        "serial": serial,
        "name": name,
        "colour": intrinsics(colour.get_intrinsics()),
        "depth": intrinsics(depth.get_intrinsics()),
        "depth_to_colour": {"rotation": list(ext.rotation), "translation": list(ext.translation)},
        "depth_scale_m": dev.first_depth_sensor().get_depth_scale(),
    }
    if a.frames:
        out = Path(a.frames)
        out.mkdir(parents=True, exist_ok=True)
        align = rs.align(rs.stream.color)
        while True:
            frames = pipe.wait_for_frames(5000)
            d = frames.get_depth_frame()
            if not d or not frames.get_color_frame():
                continue
            (out / "depth.u16").write_bytes(np.asanyarray(d.get_data()).astype("<u2").tobytes())
            aligned = align.process(frames).get_depth_frame()
            (out / "aligned.u16").write_bytes(np.asanyarray(aligned.get_data()).astype("<u2").tobytes())
            break
    pipe.stop()
    Path(a.out).write_text(json.dumps(cal, indent=1))
    print(f"wrote {a.out}: serial {serial}, colour {cal['colour']['width']}x{cal['colour']['height']}, "
          f"depth {cal['depth']['width']}x{cal['depth']['height']}, depth scale {cal['depth_scale_m']} m")


if __name__ == "__main__":
    main()
