"""Issue 57's peer: librealsense's own YUYV -> RGB8 conversion of a RealSense colour frame.

    realsense_yuyv.py OUT [--width 640 --height 480 --seed 57]

A software device (pyrealsense2) with a colour stream in YUYV sends one frame whose bytes are
drawn at random (every Y, U and V value occurs); librealsense's `yuy_decoder` converts it to
RGB8, as the SDK does for a D435's colour stream. Writes OUT/yuyv.bin (the frame) and
OUT/rgb.bin (librealsense's RGB8), raw bytes, row by row.
"""

import argparse
import pathlib

import numpy as np
import pyrealsense2 as rs


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=pathlib.Path)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--seed", type=int, default=57)
    a = ap.parse_args()
    w, h = a.width, a.height
    yuyv = np.random.default_rng(a.seed).integers(0, 256, size=(h, w * 2), dtype=np.uint8)

    device = rs.software_device()
    sensor = device.add_sensor("Color")
    intr = rs.intrinsics()
    intr.width, intr.height = w, h
    intr.fx = intr.fy = 600.0
    intr.ppx, intr.ppy = w / 2, h / 2
    intr.model = rs.distortion.none
    intr.coeffs = [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = rs.stream.color, 0, 0
    stream.width, stream.height, stream.fps, stream.bpp = w, h, 30, 2
    stream.fmt = rs.format.yuyv
    stream.intrinsics = intr
    profile = sensor.add_video_stream(stream)
    queue = rs.frame_queue(4, keep_frames=True)
    sensor.open(profile)
    sensor.start(queue)
    frame = rs.software_video_frame()
    frame.pixels = yuyv
    frame.bpp, frame.stride = 2, w * 2
    frame.timestamp, frame.frame_number = 0.0, 1
    frame.domain = rs.timestamp_domain.hardware_clock
    frame.profile = profile.as_video_stream_profile()
    sensor.on_video_frame(frame)
    got = queue.wait_for_frame(5000)
    assert got.get_profile().format() == rs.format.yuyv, got.get_profile().format()
    rgb = rs.yuy_decoder().process(got)
    assert rgb.get_profile().format() == rs.format.rgb8, rgb.get_profile().format()
    pixels = np.asanyarray(rgb.get_data())
    assert pixels.shape == (h, w, 3), pixels.shape
    a.out.mkdir(parents=True, exist_ok=True)
    yuyv.tofile(a.out / "yuyv.bin")
    pixels.astype(np.uint8).tofile(a.out / "rgb.bin")
    sensor.stop()
    sensor.close()


if __name__ == "__main__":
    main()
