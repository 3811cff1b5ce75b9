"""OpenCV's side of the ZED rectification test (issue 57), with opencv-python-headless.

  zed_rectify.py render CONF WIDTH HEIGHT OUT
      renders a checkerboard (and a smooth coloured background) on a plane in front of the
      camera through the factory model of CONF (each eye's distortion, the stereo rotation and
      translation) into OUT/raw.png, the side-by-side frame a ZED would send; rectifies it as
      Stereolabs does (zed-open-capture's initCalibration: stereoRectify with
      CALIB_ZERO_DISPARITY and alpha 0, initUndistortRectifyMap CV_32FC1, remap INTER_LINEAR)
      into OUT/cv_left.png and OUT/cv_right.png, and writes OUT/cv.json: each eye's K (P's left
      3x3), R and P (ROS's convention: the right eye's Tx = -fx * baseline, m), and each rectified
      pixel's source position (to leave the image's border out of comparisons).
  zed_rectify.py compare DIR
      compares labrig's DIR/left.png and DIR/right.png with OpenCV's (DIR/cv_*.png, rendered
      there); pixels whose source lies within a pixel of the raw image's border are left out;
      prints JSON per eye: pixels compared, the share within 1 grey level (every channel), the
      largest difference.
  zed_rectify.py corners LEFT RIGHT
      finds the checkerboard's corners in two rectified images; prints JSON with the mean and
      max vertical disparity between matching corners.
"""
import configparser
import json
import sys
from pathlib import Path

import cv2
import numpy as np

BOARD = (9, 6)  # inner corners
SQUARE_MM = 70.0
DEPTH_MM = 1400.0
NAMES = {2208: "2k", 1920: "fhd", 1280: "hd", 672: "vga"}


def load(conf, width):
    ini = configparser.ConfigParser()
    ini.read(conf)
    res = NAMES[width]

    def eye(side):
        s = ini[f"{side}_CAM_{res.upper()}"]
        k = np.array([[float(s["fx"]), 0, float(s["cx"])], [0, float(s["fy"]), float(s["cy"])], [0, 0, 1]])
        d = np.array([float(s[n]) for n in ("k1", "k2", "p1", "p2", "k3")])
        return k, d

    st = ini["STEREO"]
    rvec = np.array([float(st[f"rx_{res}"]), float(st[f"cv_{res}"]), float(st[f"rz_{res}"])])
    t = np.array([float(st["baseline"]), float(st[f"ty_{res}"]), float(st[f"tz_{res}"])])
    return eye("LEFT"), eye("RIGHT"), rvec, t


def texture(x, y):
    """RGB of the plane at (x, y) mm in the left camera's frame: a checkerboard with a white
    margin, on a smooth coloured background (smooth edges: a bilinear resampling's error stays
    small, and the corners are found)."""
    bx0 = -SQUARE_MM * (BOARD[0] + 1) / 2 + 60.0
    by0 = -SQUARE_MM * (BOARD[1] + 1) / 2
    u = (x - bx0) / SQUARE_MM
    v = (y - by0) / SQUARE_MM
    on_board = (u > -1) & (u < BOARD[0] + 2) & (v > -1) & (v < BOARD[1] + 2)
    inner = (u > 0) & (u < BOARD[0] + 1) & (v > 0) & (v < BOARD[1] + 1)
    sharp = 6.0
    checker = 0.5 + 0.5 * np.tanh(sharp * np.sin(np.pi * u)) * np.tanh(sharp * np.sin(np.pi * v))
    grey = np.where(inner, 20 + 215 * checker, 235.0)
    rgb = np.stack([grey, grey, grey], axis=-1)
    bg = np.stack([
        128 + 60 * np.sin(x / 170.0) * np.cos(y / 230.0),
        128 + 60 * np.cos(x / 260.0 + 0.5) * np.sin(y / 190.0 + 0.3),
        128 + 50 * np.sin((x + y) / 300.0),
    ], axis=-1)
    return np.where(on_board[..., None], rgb, bg)


def render_eye(k, d, r_to_left, origin, width, height):
    """Each raw pixel's ray (undistorted to convergence), from `origin` in the left frame."""
    us, vs = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([us.ravel(), vs.ravel()], axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    norm = cv2.undistortPointsIter(pts, k, d, None, None, crit).reshape(-1, 2)
    rays = np.concatenate([norm, np.ones((norm.shape[0], 1))], axis=1) @ r_to_left.T
    s = (DEPTH_MM - origin[2]) / rays[:, 2]
    x = origin[0] + s * rays[:, 0]
    y = origin[1] + s * rays[:, 1]
    img = texture(x, y).reshape(height, width, 3)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def render(conf, width, height, out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (kl, dl), (kr, dr), rvec, t = load(conf, width)
    r, _ = cv2.Rodrigues(rvec)
    # The scene: X_r = R X_l - t (OpenCV's X_r = R X_l + T, with T = -t: the right eye sits at
    # +Baseline along x). stereoRectify's rotations do not depend on T's sign, so Stereolabs'
    # call with +t rectifies this pair exactly.
    left = render_eye(kl, dl, np.eye(3), np.zeros(3), width, height)
    right = render_eye(kr, dr, r.T, r.T @ t, width, height)
    raw = np.concatenate([left, right], axis=1)
    cv2.imwrite(str(out / "raw.png"), cv2.cvtColor(raw, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(out / "raw_left.png"), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(out / "raw_right.png"), cv2.cvtColor(right, cv2.COLOR_RGB2BGR))

    size = (width, height)
    # Stereolabs' call (zed-open-capture calibration.hpp): T = [Baseline, TY, TZ] in mm.
    r1, r2, p1, p2, _q, _roi1, _roi2 = cv2.stereoRectify(kl, dl, kr, dr, size, r, t.reshape(3, 1),
                                                          flags=cv2.CALIB_ZERO_DISPARITY, alpha=0,
                                                          newImageSize=size)
    result = {"opencv": cv2.__version__}
    for name, k, d, rr, p, img in (("left", kl, dl, r1, p1, left), ("right", kr, dr, r2, p2, right)):
        mx, my = cv2.initUndistortRectifyMap(k, d, rr, p, size, cv2.CV_32FC1)
        rect = cv2.remap(img, mx, my, cv2.INTER_LINEAR)
        cv2.imwrite(str(out / f"cv_{name}.png"), cv2.cvtColor(rect, cv2.COLOR_RGB2BGR))
        inside = (mx >= 1) & (my >= 1) & (mx <= width - 2) & (my <= height - 2)
        cv2.imwrite(str(out / f"cv_{name}_inside.png"), inside.astype(np.uint8) * 255)
        # ROS: P of the right eye carries Tx = -fx' * B (m); OpenCV's here is +fx' * B (mm).
        p_ros = p.copy()
        p_ros[0, 3] = -abs(p[0, 3]) / 1000.0
        result[name] = {"k": p[:, :3].ravel().tolist(), "r": rr.ravel().tolist(), "p": p_ros.ravel().tolist()}
    (out / "cv.json").write_text(json.dumps(result, indent=1))


def compare(d):
    d = Path(d)
    result = {}
    for name in ("left", "right"):
        ours = cv2.imread(str(d / f"{name}.png")).astype(np.int32)
        theirs = cv2.imread(str(d / f"cv_{name}.png")).astype(np.int32)
        inside = cv2.imread(str(d / f"cv_{name}_inside.png"), cv2.IMREAD_GRAYSCALE) > 0
        diff = np.abs(ours - theirs).max(axis=2)[inside]
        result[name] = {"pixels": int(diff.size), "within_1": float((diff <= 1).mean()),
                        "max_diff": int(diff.max()), "exact": float((diff == 0).mean())}
    print(json.dumps(result))


def corners(left, right):
    found = {}
    for name, path in (("left", left), ("right", right)):
        grey = cv2.cvtColor(cv2.imread(path), cv2.COLOR_BGR2GRAY)
        ok, c = cv2.findChessboardCorners(grey, BOARD)
        if not ok:
            print(json.dumps({"error": f"no {BOARD[0]}x{BOARD[1]} checkerboard found in {path}"}))
            sys.exit(1)
        c = cv2.cornerSubPix(grey, c, (5, 5), (-1, -1),
                             (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4))
        found[name] = c.reshape(-1, 2)
    dy = np.abs(found["left"][:, 1] - found["right"][:, 1])
    dx = found["left"][:, 0] - found["right"][:, 0]
    print(json.dumps({"corners": int(dy.size), "mean_dy": float(dy.mean()), "max_dy": float(dy.max()),
                      "mean_disparity": float(dx.mean())}))


if __name__ == "__main__":
    if sys.argv[1] == "render":
        render(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
    elif sys.argv[1] == "compare":
        compare(sys.argv[2])
    elif sys.argv[1] == "corners":
        corners(sys.argv[2], sys.argv[3])
    else:
        sys.exit(__doc__)
