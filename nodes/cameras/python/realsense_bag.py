"""Write a RealSense recording (.db3, rosbag2: librealsense 2.59 records no .bag) with synthetic colour frames and no camera: librealsense's software
device fed by this script, recorded by librealsense's own recorder (pyrealsense2). labrig's
tests play such a file back through the camera node's RealSense source.

With --depth the device has a second sensor, as a D435's stereo module: z16 depth (depth
units 1 mm) of a wall at 1000 mm with a block at 900 mm in columns [5/8 W, 6/8 W), seen with
other intrinsics (fx, fy x 0.8) from 15 mm along x of the colour camera (the extrinsics
registered depth -> colour), so depth aligned to colour differs from the raw depth by a
computable shift.

    python realsense_bag.py OUT.db3 [--frames 30] [--width 640] [--height 480] [--fps 30] [--depth]
"""
import argparse

import numpy as np
import pyrealsense2 as rs


def add_stream(sensor, kind, uid, fmt, bpp, a, fx, fy):
    """A video stream of the args' size and rate on a software sensor, pinhole (fx, fy), centred."""
    intr = rs.intrinsics()
    intr.width, intr.height = a.width, a.height
    intr.fx, intr.fy = fx, fy
    intr.ppx, intr.ppy = (a.width - 1) / 2.0, (a.height - 1) / 2.0
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0, 0.0, 0.0, 0.0, 0.0]
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = kind, 0, uid
    vs.width, vs.height, vs.fps, vs.bpp = a.width, a.height, a.fps, bpp
    vs.fmt = fmt
    vs.intrinsics = intr
    return sensor.add_video_stream(vs)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--fx", type=float, default=615.0)
    p.add_argument("--fy", type=float, default=614.5)
    p.add_argument("--depth", action="store_true")
    a = p.parse_args()

    dev = rs.software_device()
    sensor = dev.add_sensor("RGB Camera")
    profile = add_stream(sensor, rs.stream.color, 0, rs.format.rgb8, 3, a, a.fx, a.fy)
    if a.depth:
        stereo = dev.add_sensor("Stereo Module")
        depth_profile = add_stream(stereo, rs.stream.depth, 1, rs.format.z16, 2, a, a.fx * 0.8, a.fy * 0.8)
        stereo.add_read_only_option(rs.option.depth_units, 0.001)
        ext = rs.extrinsics()
        ext.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        ext.translation = [0.015, 0.0, 0.0]
        depth_profile.register_extrinsics_to(profile, ext)
        wall = np.full((a.height, a.width), 1000, np.uint16)
        wall[:, a.width * 5 // 8 : a.width * 6 // 8] = 900
    dev.register_info(rs.camera_info.serial_number, "BAG-000000001")
    recorder = rs.recorder(a.out, dev)
    sensor.open(profile)
    sensor.start(lambda f: None)
    if a.depth:
        stereo.open(depth_profile)
        stereo.start(lambda f: None)
    # Frame k: a horizontal ramp whose red channel is k, so a reader can tell frames apart.
    ramp = np.tile(np.linspace(0, 255, a.width, dtype=np.uint8), (a.height, 1))
    for k in range(a.frames):
        img = np.stack([np.full_like(ramp, k % 256), ramp, 255 - ramp], axis=-1)
        f = rs.software_video_frame()
        f.pixels = img.tobytes()
        f.bpp, f.stride = 3, a.width * 3
        f.timestamp = k * 1000.0 / a.fps
        f.domain = rs.timestamp_domain.hardware_clock
        f.frame_number = k
        f.profile = profile.as_video_stream_profile()
        sensor.on_video_frame(f)
        if a.depth:
            d = rs.software_video_frame()
            d.pixels = wall.tobytes()
            d.bpp, d.stride = 2, a.width * 2
            d.timestamp = f.timestamp
            d.domain = rs.timestamp_domain.hardware_clock
            d.frame_number = k
            d.depth_units = 0.001
            d.profile = depth_profile.as_video_stream_profile()
            stereo.on_video_frame(d)
    sensor.stop()
    sensor.close()
    if a.depth:
        stereo.stop()
        stereo.close()
    del recorder


if __name__ == "__main__":
    main()
