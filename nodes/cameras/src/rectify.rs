//! Stereo rectification of a ZED's frames from its factory calibration, as the ZED SDK
//! delivers them to DROID: both eyes undistorted and rotated so that their rows align.
//!
//! The conventions are Stereolabs' own (zed-open-capture, `examples/include/calibration.hpp`,
//! `initCalibration`, commit 9373915): per resolution, each eye's `fx fy cx cy k1 k2 p1 p2 k3`,
//! the rotation vector `[RX, CV, RZ]` (Rodrigues), the translation `[Baseline, TY, TZ]` in mm,
//! then OpenCV's `stereoRectify` with `CALIB_ZERO_DISPARITY`, `alpha = 0` and the input size,
//! `initUndistortRectifyMap` with each eye's own matrix and distortion and its `R`/`P`, and a
//! bilinear `remap`. This module computes the same: [`stereo_rectify`] follows the steps of
//! OpenCV's `stereoRectify` (an average rotation that halves the stereo rotation, the rotation
//! that makes the baseline horizontal, a common focal length, principal points from the
//! undistorted image corners, then the scale that leaves no invalid pixel), including the
//! single-precision points OpenCV keeps on the way, so that K and P agree with OpenCV's to
//! floating-point rounding; [`RemapTable`] resamples as OpenCV's fixed-point bilinear remap
//! does (source positions to 1/32 pixel). The suite checks both against OpenCV itself
//! (tests/tests/rectify.rs, with opencv-python-headless).

use crate::intrinsics::{Eye, IntrinsicsError, ZedCalibration};
use nalgebra::{Matrix3, Rotation3, Vector3};

/// One eye as the factory file describes it at one resolution.
#[derive(Debug, Clone, PartialEq)]
pub struct EyeModel {
    pub k: Matrix3<f64>,
    /// OpenCV's order: k1 k2 p1 p2 k3.
    pub distortion: [f64; 5],
}

/// A ZED's two eyes and the stereo transform at one resolution (Stereolabs' conventions).
#[derive(Debug, Clone, PartialEq)]
pub struct StereoModel {
    pub width: u32,
    pub height: u32,
    pub left: EyeModel,
    pub right: EyeModel,
    /// Rodrigues vector `[RX, CV, RZ]`.
    pub rotation: Vector3<f64>,
    /// `[Baseline, TY, TZ]`, mm, as Stereolabs hands it to OpenCV.
    pub translation_mm: Vector3<f64>,
}

/// The rectification of one eye: what OpenCV's `stereoRectify` returns for it.
#[derive(Debug, Clone, PartialEq)]
pub struct EyeRectification {
    /// The rotation from the raw eye's frame to the rectified one (ROS's `R`).
    pub r: Matrix3<f64>,
    /// The rectified pinhole: fx = fy, cx, cy (P's left 3x3; no distortion).
    pub fx: f64,
    pub cx: f64,
    pub cy: f64,
}

/// Both eyes rectified, and the baseline.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    pub width: u32,
    pub height: u32,
    pub left: EyeRectification,
    pub right: EyeRectification,
    /// The rectified baseline (the translation's length along the rectified x axis), m.
    pub baseline_m: f64,
}

impl Rectification {
    pub fn eye(&self, eye: Eye) -> &EyeRectification {
        match eye {
            Eye::Left => &self.left,
            Eye::Right => &self.right,
        }
    }

    /// ROS's 3x4 projection of an eye: the right eye's `Tx = -fx * baseline` (m), the left's 0.
    pub fn projection(&self, eye: Eye) -> [f64; 12] {
        let e = self.eye(eye);
        let tx = match eye {
            Eye::Left => 0.0,
            Eye::Right => -e.fx * self.baseline_m,
        };
        [e.fx, 0.0, e.cx, tx, 0.0, e.fx, e.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    }
}

impl ZedCalibration {
    /// Both eyes and the stereo transform at a resolution the file has a section for (the ZED
    /// rectifies each readout with its own values; a size of none is refused, naming the sizes).
    pub fn stereo(&self, width: u32, height: u32) -> Result<StereoModel, IntrinsicsError> {
        let (name, _, _) = crate::intrinsics::ZED_RESOLUTIONS
            .iter()
            .find(|(_, w, h)| (*w, *h) == (width, height))
            .ok_or(IntrinsicsError::NotRectifiable { width, height })?;
        let eye = |e: Eye| -> Result<EyeModel, IntrinsicsError> {
            let i = self.eye(e, width, height)?;
            let d = &i.distortion;
            Ok(EyeModel {
                k: Matrix3::new(i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0),
                distortion: [d[0], d[1], d[2], d[3], d[4]],
            })
        };
        let stereo = |key: &str| self.value("STEREO", key);
        Ok(StereoModel {
            width,
            height,
            left: eye(Eye::Left)?,
            right: eye(Eye::Right)?,
            rotation: Vector3::new(
                stereo(&format!("rx_{name}"))?,
                stereo(&format!("cv_{name}"))?,
                stereo(&format!("rz_{name}"))?,
            ),
            translation_mm: Vector3::new(
                stereo("baseline")?,
                stereo(&format!("ty_{name}"))?,
                stereo(&format!("tz_{name}"))?,
            ),
        })
    }
}

/// Rodrigues' formula: a rotation vector to its matrix.
fn rodrigues(v: &Vector3<f64>) -> Matrix3<f64> {
    Rotation3::from_scaled_axis(*v).into_inner()
}

/// OpenCV's iterative undistortion of one pixel (its default: five fixed-point iterations) to
/// normalised coordinates, then, when given, through `rr` (the new camera matrix times the
/// rectifying rotation) back to pixels.
fn undistort_point(p: (f32, f32), eye: &EyeModel, rr: Option<&Matrix3<f64>>) -> (f32, f32) {
    let (x, y) = undistort(f64::from(p.0), f64::from(p.1), eye, rr, 5);
    (x as f32, y as f32)
}

/// [`undistort_point`] in double precision throughout (OpenCV's path for CV_64F points), with
/// `iterations` steps (OpenCV's default: 5).
fn undistort(u: f64, v: f64, eye: &EyeModel, rr: Option<&Matrix3<f64>>, iterations: usize) -> (f64, f64) {
    let [k1, k2, p1, p2, k3] = eye.distortion;
    let (fx, fy, cx, cy) = (eye.k[(0, 0)], eye.k[(1, 1)], eye.k[(0, 2)], eye.k[(1, 2)]);
    let x0 = (u - cx) * (1.0 / fx);
    let y0 = (v - cy) * (1.0 / fy);
    let (mut x, mut y) = (x0, y0);
    for _ in 0..iterations {
        let r2 = x * x + y * y;
        let icdist = 1.0 / (1.0 + ((k3 * r2 + k2) * r2 + k1) * r2);
        if icdist < 0.0 {
            (x, y) = (x0, y0);
            break;
        }
        let dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        x = (x0 - dx) * icdist;
        y = (y0 - dy) * icdist;
    }
    if let Some(rr) = rr {
        let xx = rr[(0, 0)] * x + rr[(0, 1)] * y + rr[(0, 2)];
        let yy = rr[(1, 0)] * x + rr[(1, 1)] * y + rr[(1, 2)];
        let ww = 1.0 / (rr[(2, 0)] * x + rr[(2, 1)] * y + rr[(2, 2)]);
        (x, y) = (xx * ww, yy * ww);
    }
    (x, y)
}

/// The rectangles inside which every pixel is valid (`inner`) and which hold every pixel
/// (`outer`) of an eye's rectified image: the border points of a 9 x 9 grid over the raw image
/// (corners left out), undistorted and rectified (OpenCV's `getUndistortRectangles`). Each as
/// (x, y, width, height).
fn rectangles(eye: &EyeModel, r: &Matrix3<f64>, p: &Matrix3<f64>, w: u32, h: u32) -> ([f64; 4], [f64; 4]) {
    const N: u32 = 9;
    let rr = p * r;
    let (step_x, step_y) = (f64::from(w - 1) / f64::from(N - 1), f64::from(h - 1) / f64::from(N - 1));
    let max = f64::from(f32::MAX);
    let (mut ix0, mut ix1, mut iy0, mut iy1) = (-max, max, -max, max);
    let (mut ox0, mut ox1, mut oy0, mut oy1) = (max, -max, max, -max);
    for y in 0..N {
        for x in 0..N {
            let border = x == 0 || x == N - 1 || y == 0 || y == N - 1;
            let corner = (x == 0 || x == N - 1) && (y == 0 || y == N - 1);
            if !border || corner {
                continue;
            }
            let (u, v) = undistort(f64::from(x) * step_x, f64::from(y) * step_y, eye, Some(&rr), 5);
            ox0 = ox0.min(u);
            ox1 = ox1.max(u);
            oy0 = oy0.min(v);
            oy1 = oy1.max(v);
            if x == 0 {
                ix0 = ix0.max(u);
            }
            if x == N - 1 {
                ix1 = ix1.min(u);
            }
            if y == 0 {
                iy0 = iy0.max(v);
            }
            if y == N - 1 {
                iy1 = iy1.min(v);
            }
        }
    }
    ([ix0, iy0, ix1 - ix0, iy1 - iy0], [ox0, oy0, ox1 - ox0, oy1 - oy0])
}

/// OpenCV's `stereoRectify` with `CALIB_ZERO_DISPARITY`, `alpha = 0` and the input size, as
/// Stereolabs calls it; the baseline comes back in metres.
pub fn stereo_rectify(m: &StereoModel) -> Rectification {
    let (nx, ny) = (m.width as i64, m.height as i64);
    // Rotate both eyes half way, each towards the other.
    let r_r = rodrigues(&(m.rotation * -0.5));
    let t = r_r * m.translation_mm;
    // Then together, about the axis that makes the baseline horizontal.
    let idx = if t[0].abs() > t[1].abs() { 0 } else { 1 };
    let c = t[idx];
    let nt = t.norm();
    let mut uu = Vector3::zeros();
    uu[idx] = if c > 0.0 { 1.0 } else { -1.0 };
    let mut ww = t.cross(&uu);
    let nw = ww.norm();
    if nw > 0.0 {
        ww *= (c.abs() / nt).acos() / nw;
    }
    let w_r = rodrigues(&ww);
    let r1 = w_r * r_r.transpose();
    let r2 = w_r * r_r;
    let t_rect = r2 * m.translation_mm;

    // One focal length for both, then principal points that centre each eye's undistorted
    // corners; with CALIB_ZERO_DISPARITY both eyes share their mean.
    let fc = (m.left.k[(1 - idx, 1 - idx)] + m.right.k[(1 - idx, 1 - idx)]) * 0.5;
    let mut cc = [(0.0f64, 0.0f64); 2];
    for (k, (eye, r)) in [(&m.left, &r1), (&m.right, &r2)].into_iter().enumerate() {
        let mut sum = (0.0f64, 0.0f64);
        for i in 0..4 {
            let corner = (((i % 2) * (nx - 1)) as f32, ((i / 2) * (ny - 1)) as f32);
            let (x, y) = undistort_point(corner, eye, None);
            // Projected through the rectifying rotation with focal fc and no offset.
            let q = r * Vector3::new(f64::from(x), f64::from(y), 1.0);
            let z = 1.0 / q[2];
            sum.0 += f64::from((fc * q[0] * z) as f32);
            sum.1 += f64::from((fc * q[1] * z) as f32);
        }
        cc[k] = ((nx - 1) as f64 / 2.0 - sum.0 / 4.0, (ny - 1) as f64 / 2.0 - sum.1 / 4.0);
    }
    let mean = ((cc[0].0 + cc[1].0) * 0.5, (cc[0].1 + cc[1].1) * 0.5);
    cc = [mean, mean];

    // alpha = 0: the largest scale at which every rectified pixel of both eyes is valid.
    let pmat = |c: (f64, f64)| Matrix3::new(fc, 0.0, c.0, 0.0, fc, c.1, 0.0, 0.0, 1.0);
    let (inner1, _) = rectangles(&m.left, &r1, &pmat(cc[0]), m.width, m.height);
    let (inner2, _) = rectangles(&m.right, &r2, &pmat(cc[1]), m.width, m.height);
    let (w, h) = (f64::from(m.width), f64::from(m.height));
    let mut s0 = f64::MIN;
    for (c, inner) in [(cc[0], inner1), (cc[1], inner2)] {
        let [x, y, iw, ih] = inner;
        s0 = s0
            .max(c.0 / (c.0 - x))
            .max(c.1 / (c.1 - y))
            .max((w - 1.0 - c.0) / (x + iw - c.0))
            .max((h - 1.0 - c.1) / (y + ih - c.1));
    }
    let f = fc * s0;
    let eye = |r: Matrix3<f64>, c: (f64, f64)| EyeRectification { r, fx: f, cx: c.0, cy: c.1 };
    Rectification {
        width: m.width,
        height: m.height,
        left: eye(r1, cc[0]),
        right: eye(r2, cc[1]),
        baseline_m: t_rect[idx].abs() / 1000.0,
    }
}

/// Where each rectified pixel samples the raw image, OpenCV's `initUndistortRectifyMap`
/// (single-precision maps), for one eye.
pub fn rectify_map(eye: &EyeModel, rect: &EyeRectification, width: u32, height: u32) -> (Vec<f32>, Vec<f32>) {
    let a = Matrix3::new(rect.fx, 0.0, rect.cx, 0.0, rect.fx, rect.cy, 0.0, 0.0, 1.0);
    let ir = (a * rect.r).try_inverse().expect("a rotation times a pinhole is invertible");
    let [k1, k2, p1, p2, k3] = eye.distortion;
    let (fx, fy, u0, v0) = (eye.k[(0, 0)], eye.k[(1, 1)], eye.k[(0, 2)], eye.k[(1, 2)]);
    let n = width as usize * height as usize;
    let (mut mx, mut my) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for i in 0..height {
        let fi = f64::from(i);
        let (mut x_, mut y_, mut w_) =
            (fi * ir[(0, 1)] + ir[(0, 2)], fi * ir[(1, 1)] + ir[(1, 2)], fi * ir[(2, 1)] + ir[(2, 2)]);
        for _ in 0..width {
            let w = 1.0 / w_;
            let (x, y) = (x_ * w, y_ * w);
            let (x2, y2) = (x * x, y * y);
            let r2 = x2 + y2;
            let xy2 = 2.0 * x * y;
            let kr = 1.0 + ((k3 * r2 + k2) * r2 + k1) * r2;
            mx.push((fx * (x * kr + p1 * xy2 + p2 * (r2 + 2.0 * x2)) + u0) as f32);
            my.push((fy * (y * kr + p1 * (r2 + 2.0 * y2) + p2 * xy2) + v0) as f32);
            x_ += ir[(0, 0)];
            y_ += ir[(1, 0)];
            w_ += ir[(2, 0)];
        }
    }
    (mx, my)
}

/// Subpixel steps of a sample position (OpenCV's INTER_TAB_SIZE).
const TAB: i32 = 32;
/// Fixed-point weights: 2^15 is one (OpenCV's INTER_REMAP_COEF_BITS).
const ONE: i32 = 1 << 15;

/// A precomputed bilinear resampling of RGB8 images of one size (computed once at start;
/// [`RemapTable::apply`] per frame). Each output pixel reads a 2 x 2 block at a position
/// rounded to 1/32 pixel, with 15-bit weights, as OpenCV's `remap` with `INTER_LINEAR` does;
/// taps outside the source read black (`BORDER_CONSTANT`).
#[derive(Clone)]
pub struct RemapTable {
    width: u32,
    height: u32,
    /// Per output pixel, packed in 4 bytes (a frame reads 3.7 MB of table at 1280x720, not 11):
    /// the source pixel of the block's top-left tap (22 bits) and the position's fraction
    /// (`fy * 32 + fx`, 10 bits). A block not wholly inside reads pixel 0 here (no branch in
    /// the per-pixel loop) and is computed again from `edge`, which has its taps.
    entry: Vec<u32>,
    /// The four weights (top-left, top-right, bottom-left, bottom-right) of each fraction.
    weights: Vec<[u16; 4]>,
    /// Output pixels at the border: (pixel, taps as source pixel index or None, weights).
    edge: Vec<(u32, [Option<u32>; 4], [u16; 4])>,
}

/// The four fixed-point weights of a position's fraction (in 1/32 pixel), summing to one.
fn weights(fx: i32, fy: i32) -> [u16; 4] {
    let (ax, ay) = (fx as f32 / TAB as f32, fy as f32 / TAB as f32);
    let w = [(1.0 - ay) * (1.0 - ax), (1.0 - ay) * ax, ay * (1.0 - ax), ay * ax];
    let mut q = w.map(|v| (v * ONE as f32).round_ties_even() as i32);
    // Rounding may leave the sum one off: OpenCV moves the difference onto the largest weight.
    let diff = q.iter().sum::<i32>() - ONE;
    if diff != 0 {
        let k = (0..4).max_by_key(|&i| q[i]).expect("four weights");
        q[k] -= diff;
    }
    q.map(|v| v as u16)
}

impl std::fmt::Debug for RemapTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RemapTable({}x{}, {} border pixels)", self.width, self.height, self.edge.len())
    }
}

impl RemapTable {
    /// The table for maps of `width` x `height` output pixels into a source of the same size.
    pub fn new(map_x: &[f32], map_y: &[f32], width: u32, height: u32) -> RemapTable {
        let n = width as usize * height as usize;
        assert_eq!((map_x.len(), map_y.len()), (n, n), "one map entry per output pixel");
        assert!(n < 1 << 22, "{width}x{height}: more pixels than a packed entry holds");
        let mut entry = Vec::with_capacity(n);
        let ws: Vec<[u16; 4]> = (0..TAB * TAB).map(|f| weights(f % TAB, f / TAB)).collect();
        let mut edge = Vec::new();
        let (w, h) = (width as i32, height as i32);
        for (i, (&x, &y)) in map_x.iter().zip(map_y).enumerate() {
            let xi = (x * TAB as f32).round_ties_even() as i32;
            let yi = (y * TAB as f32).round_ties_even() as i32;
            let (sx, sy) = (xi >> 5, yi >> 5);
            let frac = ((yi & (TAB - 1)) * TAB + (xi & (TAB - 1))) as u32;
            let wt = ws[frac as usize];
            if sx >= 0 && sy >= 0 && sx + 1 < w && sy + 1 < h {
                entry.push(((sy as u32 * width + sx as u32) << 10) | frac);
            } else {
                entry.push(frac);
                let tap = |dx: i32, dy: i32| {
                    let (tx, ty) = (sx + dx, sy + dy);
                    (tx >= 0 && ty >= 0 && tx < w && ty < h).then(|| ty as u32 * width + tx as u32)
                };
                edge.push((i as u32, [tap(0, 0), tap(1, 0), tap(0, 1), tap(1, 1)], wt));
            }
        }
        RemapTable { width, height, entry, weights: ws, edge }
    }

    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Resamples `src` (RGB8, the table's size) into `dst` (resized to fit).
    #[allow(unsafe_code)]
    pub fn apply(&self, src: &[u8], dst: &mut Vec<u8>) {
        let stride = self.width as usize * 3;
        assert_eq!(src.len(), stride * self.height as usize, "a source image of the table's size");
        dst.resize(src.len(), 0);
        let round = 1u32 << 14;
        let table: &[[u16; 4]; (TAB * TAB) as usize] = self.weights[..].try_into().expect("a weight per fraction");
        let last_block = src.len() - stride - 6;
        for (out, &e) in dst.chunks_exact_mut(3).zip(&self.entry) {
            let o = (e >> 10) as usize * 3;
            debug_assert!(o <= last_block);
            // SAFETY: `new` packs a position only when its whole 2x2 block lies inside the
            // width x height image (sx + 1 < width, sy + 1 < height), so o + stride + 6 <= the
            // length checked above; `entry` is private and written by `new` alone.
            let (a, b) =
                unsafe { (&*src.as_ptr().add(o).cast::<[u8; 6]>(), &*src.as_ptr().add(o + stride).cast::<[u8; 6]>()) };
            let [w0, w1, w2, w3] = table[(e & 1023) as usize].map(u32::from);
            for c in 0..3 {
                let v =
                    u32::from(a[c]) * w0 + u32::from(a[c + 3]) * w1 + u32::from(b[c]) * w2 + u32::from(b[c + 3]) * w3;
                out[c] = ((v + round) >> 15) as u8;
            }
        }
        for (i, taps, w) in &self.edge {
            let i = *i as usize * 3;
            for c in 0..3 {
                let mut v = 0u32;
                for (tap, wk) in taps.iter().zip(w) {
                    if let Some(t) = tap {
                        v += u32::from(src[*t as usize * 3 + c]) * u32::from(*wk);
                    }
                }
                dst[i + c] = ((v + round) >> 15).min(255) as u8;
            }
        }
    }
}

/// An eye ready to rectify frames: its table, and the rectification its camera_info carries.
#[derive(Debug, Clone)]
pub struct EyeRectifier {
    pub eye: Eye,
    pub rectification: Rectification,
    pub table: RemapTable,
}

impl EyeRectifier {
    /// From a factory file at one eye's size (a ZED resolution; others are refused by name).
    pub fn new(
        calibration: &ZedCalibration,
        eye: Eye,
        width: u32,
        height: u32,
    ) -> Result<EyeRectifier, IntrinsicsError> {
        let model = calibration.stereo(width, height)?;
        let rectification = stereo_rectify(&model);
        let (raw, rect) = match eye {
            Eye::Left => (&model.left, &rectification.left),
            Eye::Right => (&model.right, &rectification.right),
        };
        let (mx, my) = rectify_map(raw, rect, width, height);
        let table = RemapTable::new(&mx, &my, width, height);
        Ok(EyeRectifier { eye, rectification, table })
    }

    /// The rectified eye's intrinsics: the common pinhole, no distortion.
    pub fn intrinsics(&self) -> crate::intrinsics::Intrinsics {
        let e = self.rectification.eye(self.eye);
        crate::intrinsics::Intrinsics {
            width: self.rectification.width,
            height: self.rectification.height,
            fx: e.fx,
            fy: e.fx,
            cx: e.cx,
            cy: e.cy,
            distortion: vec![0.0; 5],
            source: "zed-rectified".into(),
        }
    }

    /// The eye's camera_info: rectified K, zero distortion, R and P by ROS's stereo convention.
    pub fn camera_info(
        &self,
        stamp: labrig_msgs::builtin_interfaces::Time,
        frame_id: &str,
    ) -> labrig_msgs::sensor_msgs::CameraInfo {
        let mut info = self.intrinsics().camera_info(stamp, frame_id);
        let r = self.rectification.eye(self.eye).r;
        info.r = [r[(0, 0)], r[(0, 1)], r[(0, 2)], r[(1, 0)], r[(1, 1)], r[(1, 2)], r[(2, 0)], r[(2, 1)], r[(2, 2)]];
        info.p = self.rectification.projection(self.eye);
        info
    }
}

/// `labrig-cameras rectify`: a side-by-side PNG through both eyes' rectifiers.
pub fn rectify_png(conf: &std::path::Path, input: &std::path::Path, out: &std::path::Path) -> anyhow::Result<()> {
    use anyhow::Context;
    let calibration = ZedCalibration::load(conf)?;
    let bytes = std::fs::read(input).with_context(|| format!("{}", input.display()))?;
    let img = labrig_episode::png::decode_rgb(&bytes).with_context(|| format!("{}", input.display()))?;
    let (w, h, rgb) = (img.width as u32, img.height as u32, img.pixels);
    std::fs::create_dir_all(out).with_context(|| format!("{}", out.display()))?;
    let mut eyes = serde_json::Map::new();
    for (eye, name) in [(Eye::Left, "left"), (Eye::Right, "right")] {
        let raw = crate::convert::crop_rgb(rgb.clone(), w, h, Some(eye))?;
        let r = EyeRectifier::new(&calibration, eye, w / 2, h)?;
        let mut rect = Vec::new();
        r.table.apply(&raw, &mut rect);
        let path = out.join(format!("{name}.png"));
        std::fs::write(&path, labrig_episode::png::encode_rgb(&rect, w / 2, h)?)
            .with_context(|| format!("{}", path.display()))?;
        let info = r.camera_info(labrig_msgs::builtin_interfaces::Time::default(), name);
        eyes.insert(name.into(), serde_json::json!({ "k": info.k, "d": info.d, "r": info.r, "p": info.p }));
    }
    std::fs::write(out.join("rectification.json"), serde_json::to_string_pretty(&eyes)?)?;
    println!("rectified {} ({}x{} per eye) into {}", input.display(), w / 2, h, out.display());
    Ok(())
}

/// What `labrig-cameras bench-rectify` measures.
#[derive(Debug)]
pub struct BenchArgs {
    pub intrinsics: Option<std::path::PathBuf>,
    pub width: u32,
    pub height: u32,
    pub frames: usize,
    pub zeds: u32,
    pub fps: f64,
    pub json: bool,
}

/// The test fixture's values, for a bench without a camera's own file.
const BENCH_FIXTURE: &str = include_str!("../tests/fixtures/SN000012345.conf");

/// `labrig bench rectify`: per-frame times on synthetic frames (a moving gradient).
pub fn bench(a: BenchArgs) -> anyhow::Result<()> {
    use labrig_episode::inspect::Percentiles;
    let calibration = match &a.intrinsics {
        Some(p) => ZedCalibration::load(p)?,
        None => ZedCalibration::parse(BENCH_FIXTURE, "SN000012345.conf (the test fixture)")?,
    };
    let t0 = std::time::Instant::now();
    let r = EyeRectifier::new(&calibration, Eye::Left, a.width, a.height)?;
    let setup_ms = t0.elapsed().as_secs_f64() * 1e3;
    let (w, h) = (a.width as usize, a.height as usize);
    let bar = labrig_episode::progress::bar("{bar:25} {pos}/{len} frames", a.frames as u64, a.json);
    let (mut remap_ms, mut path_ms) = (Vec::new(), Vec::new());
    let mut rect = Vec::new();
    for f in 0..a.frames {
        // A side-by-side YUYV frame whose content changes every frame.
        let yuyv: Vec<u8> = (0..2 * w * h * 2).map(|i| ((i / 2 + f * 7) % 251) as u8).collect();
        let start = std::time::Instant::now();
        let rgb = crate::convert::yuyv_to_rgb(&yuyv, 2 * a.width, a.height, Some(Eye::Left))?;
        let mid = std::time::Instant::now();
        r.table.apply(&rgb, &mut rect);
        let end = std::time::Instant::now();
        std::hint::black_box(&rect);
        remap_ms.push((end - mid).as_secs_f64() * 1e3);
        path_ms.push((end - start).as_secs_f64() * 1e3);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let remap = Percentiles::of(remap_ms).expect("frames");
    let path = Percentiles::of(path_ms).expect("frames");
    let rate = f64::from(a.zeds) * a.fps;
    let report = serde_json::json!({
        "width": a.width, "height": a.height, "frames": a.frames,
        "profile": if cfg!(debug_assertions) { "debug" } else { "release" },
        "maps_setup_ms": setup_ms,
        "remap_ms": remap, "yuyv_to_rectified_ms": path,
        "zeds": a.zeds, "fps": a.fps,
        "core_share_remap_p50": remap.p50 * rate / 1e3,
        "core_share_path_p50": path.p50 * rate / 1e3,
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "rectify {}x{} ({}, {} frames; maps computed once in {setup_ms:.0} ms)",
            a.width,
            a.height,
            report["profile"].as_str().unwrap_or("?"),
            a.frames
        );
        println!("  remap alone            p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms", remap.p50, remap.p99, remap.max);
        println!("  YUYV -> eye -> rectified p50 {:.2} ms  p99 {:.2} ms  max {:.2} ms", path.p50, path.p99, path.max);
        println!(
            "  {} ZEDs at {} fps: remap {:.0}% of one core, the whole path {:.0}% (p50)",
            a.zeds,
            a.fps,
            remap.p50 * rate / 10.0,
            path.p50 * rate / 10.0
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const FIXTURE: &str = include_str!("../tests/fixtures/SN000012345.conf");

    #[test]
    fn weights_sum_to_one_at_every_fraction() {
        for fy in 0..TAB {
            for fx in 0..TAB {
                let w = weights(fx, fy);
                assert_eq!(w.iter().map(|&v| i32::from(v)).sum::<i32>(), ONE, "({fx}, {fy})");
            }
        }
        assert_eq!(weights(0, 0), [ONE as u16, 0, 0, 0]);
    }

    #[test]
    fn rectified_rows_are_epipolar_lines() {
        // A point seen by both eyes lands on the same row of both rectified images, and its
        // disparity is f * B / Z.
        let z = ZedCalibration::parse(FIXTURE, "SN000012345.conf").unwrap();
        let m = z.stereo(1280, 720).unwrap();
        let r = stereo_rectify(&m);
        let rl = rodrigues(&m.rotation);
        for p in [Vector3::new(0.1, -0.2, 1.5), Vector3::new(-0.4, 0.3, 2.0), Vector3::new(0.6, 0.25, 0.9)] {
            // X_r = R X_l - (B, TY, TZ): OpenCV's convention with T negated (the right eye sits
            // at +Baseline on x); the rectifying rotations do not depend on T's sign.
            let pl = p * 1000.0;
            let pr = rl * pl - m.translation_mm;
            let project = |e: &EyeRectification, x: Vector3<f64>| {
                let q = e.r * x;
                (e.fx * q[0] / q[2] + e.cx, e.fx * q[1] / q[2] + e.cy)
            };
            let (ul, vl) = project(&r.left, pl);
            let (ur, vr) = project(&r.right, pr);
            assert!((vl - vr).abs() < 1e-6, "rows {vl} vs {vr}");
            let depth = (r.left.r * pl)[2] / 1000.0;
            assert!(((ul - ur) - r.left.fx * r.baseline_m / depth).abs() < 1e-6, "disparity {}", ul - ur);
        }
        assert!((r.baseline_m - 0.11998).abs() < 1e-4, "{}", r.baseline_m);
        assert_eq!(r.projection(Eye::Right)[3], -r.right.fx * r.baseline_m);
    }

    #[test]
    fn the_map_inverts_the_undistortion() {
        // Each rectified pixel's source, undistorted and rectified again, comes back to it.
        let z = ZedCalibration::parse(FIXTURE, "SN000012345.conf").unwrap();
        let m = z.stereo(672, 376).unwrap();
        let r = stereo_rectify(&m);
        let (mx, my) = rectify_map(&m.left, &r.left, 672, 376);
        let p = Matrix3::new(r.left.fx, 0.0, r.left.cx, 0.0, r.left.fx, r.left.cy, 0.0, 0.0, 1.0);
        let rr = p * r.left.r;
        for &(u, v) in &[(0usize, 0usize), (335, 187), (671, 375), (100, 300)] {
            let i = v * 672 + u;
            // Iterated to convergence (OpenCV's five steps leave ~0.1 px at the far corners).
            let back = undistort(f64::from(mx[i]), f64::from(my[i]), &m.left, Some(&rr), 50);
            assert!((back.0 - u as f64).abs() < 1e-3 && (back.1 - v as f64).abs() < 1e-3, "{back:?}");
        }
    }

    #[test]
    fn a_constant_image_stays_constant_inside() {
        let z = ZedCalibration::parse(FIXTURE, "SN000012345.conf").unwrap();
        let r = EyeRectifier::new(&z, Eye::Right, 672, 376).unwrap();
        let src = vec![200u8; 672 * 376 * 3];
        let mut dst = Vec::new();
        r.table.apply(&src, &mut dst);
        // alpha = 0: every rectified pixel samples inside the raw image (no black border).
        let inside = dst.iter().filter(|&&v| v == 200).count();
        assert!(inside as f64 >= 0.999 * dst.len() as f64, "{inside} of {}", dst.len());
        let e = EyeRectifier::new(&z, Eye::Left, 640, 360).unwrap_err();
        assert!(e.to_string().starts_with("640x360 cannot be rectified"), "{e}");
    }
}
