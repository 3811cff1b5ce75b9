"""Write a RealSense recording (.db3, rosbag2: librealsense 2.59 records no .bag) with synthetic colour frames and no camera: librealsense's software
device fed by this script, recorded by librealsense's own recorder (pyrealsense2). labrig's
tests play such a file back through the camera node's RealSense source.

    python realsense_bag.py OUT.db3 [--frames 30] [--width 640] [--height 480] [--fps 30]
"""
import argparse

import numpy as np
import pyrealsense2 as rs


def main():
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--fps", type=int, default=30)
    p.add_argument("--fx", type=float, default=615.0)
    p.add_argument("--fy", type=float, default=614.5)
    a = p.parse_args()

    dev = rs.software_device()
    sensor = dev.add_sensor("RGB Camera")
    intr = rs.intrinsics()
    intr.width, intr.height = a.width, a.height
    intr.fx, intr.fy = a.fx, a.fy
    intr.ppx, intr.ppy = (a.width - 1) / 2.0, (a.height - 1) / 2.0
    intr.model = rs.distortion.brown_conrady
    intr.coeffs = [0.0, 0.0, 0.0, 0.0, 0.0]
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = rs.stream.color, 0, 0
    vs.width, vs.height, vs.fps, vs.bpp = a.width, a.height, a.fps, 3
    vs.fmt = rs.format.rgb8
    vs.intrinsics = intr
    profile = sensor.add_video_stream(vs)
    dev.register_info(rs.camera_info.serial_number, "BAG-000000001")
    recorder = rs.recorder(a.out, dev)
    sensor.open(profile)
    sensor.start(lambda f: None)
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
    sensor.stop()
    sensor.close()
    del recorder


if __name__ == "__main__":
    main()
