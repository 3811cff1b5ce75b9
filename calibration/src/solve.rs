//! From a capture (views + the TCP poses the robot reported) to a camera's calibration:
//! per-view board poses (PnP), the closed-form hand-eye solution (OpenCV's
//! `calibrateHandEye`, Daniilidis by default), then both unknown transforms refined together by
//! minimising the reprojection error of every corner of every view; DROID's acceptance
//! (views above 3 px dropped, >= 10 views kept) and its 70/30 check.
//!
//! The two unknowns, for view i with the robot's TCP pose `T_i` (base -> tcp) and the board
//! pose `B_i` (camera -> board) measured in the image, `B_i = X^-1 A_i Y`:
//! - eye-to-hand (external cameras, board in the gripper): X = base -> camera,
//!   Y = tcp -> board, A_i = T_i;
//! - eye-in-hand (wrist camera, board on the table): X = tcp -> camera, Y = base -> board,
//!   A_i = T_i^-1.

use crate::CalibError;
use crate::detect::{Detection, Detector, MIN_CORNERS};
use labrig_msgs::calibration::{Intrinsics, Mount, Pose, SplitCheck};
use nalgebra::{DMatrix, DVector, Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;
use rand::seq::SliceRandom;
use rand_chacha::rand_core::SeedableRng;

/// Views whose own board fit is worse than this are dropped (DROID's rule).
pub const MAX_VIEW_RMS_PX: f64 = 3.0;
/// The least views a calibration needs (DROID's rule).
pub const MIN_VIEWS: usize = 10;

/// OpenCV's hand-eye methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum HandEyeMethod {
    Tsai,
    Park,
    Horaud,
    Andreff,
    Daniilidis,
}

impl HandEyeMethod {
    pub const ALL: [HandEyeMethod; 5] = [
        HandEyeMethod::Tsai,
        HandEyeMethod::Park,
        HandEyeMethod::Horaud,
        HandEyeMethod::Andreff,
        HandEyeMethod::Daniilidis,
    ];

    fn opencv(self) -> calib3d::HandEyeCalibrationMethod {
        use calib3d::HandEyeCalibrationMethod as M;
        match self {
            HandEyeMethod::Tsai => M::CALIB_HAND_EYE_TSAI,
            HandEyeMethod::Park => M::CALIB_HAND_EYE_PARK,
            HandEyeMethod::Horaud => M::CALIB_HAND_EYE_HORAUD,
            HandEyeMethod::Andreff => M::CALIB_HAND_EYE_ANDREFF,
            HandEyeMethod::Daniilidis => M::CALIB_HAND_EYE_DANIILIDIS,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            HandEyeMethod::Tsai => "tsai",
            HandEyeMethod::Park => "park",
            HandEyeMethod::Horaud => "horaud",
            HandEyeMethod::Andreff => "andreff",
            HandEyeMethod::Daniilidis => "daniilidis",
        }
    }
}

/// A pinhole camera (the corners are undistorted before any fit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    pub fn of(k: &Intrinsics) -> Pinhole {
        Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy }
    }

    /// Pixel of a point in the camera's optical frame (None behind the camera).
    pub fn project(&self, p: &Point3<f64>) -> Option<[f64; 2]> {
        (p.z > 1e-6).then(|| [self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy])
    }

    fn matrix(&self) -> Result<Mat, CalibError> {
        let k = [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]];
        Ok(Mat::from_slice_2d(&k)?)
    }
}

/// One view's data for the fits.
#[derive(Debug, Clone)]
pub struct ViewFit {
    pub index: usize,
    pub image: String,
    /// base -> tcp, as the robot reported it.
    pub tcp: Isometry3<f64>,
    pub detection: Detection,
    /// The corners, undistorted (pinhole pixels).
    pub pixels: Vec<[f64; 2]>,
    /// The board's corner positions (board frame) for those ids.
    pub object: Vec<Point3<f64>>,
    /// camera -> board from this view alone, and its RMS reprojection error (px).
    pub board: Isometry3<f64>,
    pub rms_px: f64,
}

/// Undistorts pixel positions (OpenCV's model), leaving pinhole pixels of the same camera.
pub fn undistort(points: &[[f64; 2]], k: &Intrinsics) -> Result<Vec<[f64; 2]>, CalibError> {
    if k.distortion.iter().all(|&d| d == 0.0) {
        return Ok(points.to_vec());
    }
    let pin = Pinhole::of(k).matrix()?;
    let src: Vector<Point2f> = points.iter().map(|p| Point2f::new(p[0] as f32, p[1] as f32)).collect();
    let dist = Mat::from_slice(&k.distortion)?;
    let mut dst: Vector<Point2f> = Vector::new();
    calib3d::undistort_points(&src, &mut dst, &pin, &dist, &Mat::default(), &pin)?;
    Ok(dst.iter().map(|p| [p.x as f64, p.y as f64]).collect())
}

fn iso_from_rt(rvec: &Mat, tvec: &Mat) -> Result<Isometry3<f64>, CalibError> {
    let r = [*rvec.at::<f64>(0)?, *rvec.at::<f64>(1)?, *rvec.at::<f64>(2)?];
    let t = [*tvec.at::<f64>(0)?, *tvec.at::<f64>(1)?, *tvec.at::<f64>(2)?];
    Ok(Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_scaled_axis(Vector3::from(r))))
}

/// RMS reprojection error (px) of `object` seen at `pose` (camera -> board) against `pixels`.
pub fn rms(cam: &Pinhole, pose: &Isometry3<f64>, object: &[Point3<f64>], pixels: &[[f64; 2]]) -> f64 {
    let mut sum = 0.0;
    for (o, p) in object.iter().zip(pixels) {
        match cam.project(&(pose * o)) {
            Some(q) => sum += (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2),
            None => sum += 1e6,
        }
    }
    (sum / object.len().max(1) as f64).sqrt()
}

/// The board's pose in one view (camera -> board): SQPnP, then iterative refinement.
pub fn board_pose(
    cam: &Pinhole,
    object: &[Point3<f64>],
    pixels: &[[f64; 2]],
) -> Result<(Isometry3<f64>, f64), CalibError> {
    let obj: Vector<opencv::core::Point3d> = object.iter().map(|p| opencv::core::Point3d::new(p.x, p.y, p.z)).collect();
    let img: Vector<opencv::core::Point2d> = pixels.iter().map(|p| opencv::core::Point2d::new(p[0], p[1])).collect();
    let k = cam.matrix()?;
    let (mut rvec, mut tvec) = (Mat::default(), Mat::default());
    calib3d::solve_pnp(&obj, &img, &k, &Mat::default(), &mut rvec, &mut tvec, false, calib3d::SOLVEPNP_SQPNP)?;
    calib3d::solve_pnp(&obj, &img, &k, &Mat::default(), &mut rvec, &mut tvec, true, calib3d::SOLVEPNP_ITERATIVE)?;
    let pose = iso_from_rt(&rvec, &tvec)?;
    Ok((pose, rms(cam, &pose, object, pixels)))
}

/// Why a view is left out of the calibration (the report's `dropped`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ViewError {
    #[error("board not seen (no marker found)")]
    NotSeen,
    #[error("only {corners} ChArUco corners ({markers} markers); {} needed", MIN_CORNERS)]
    TooFewCorners { corners: usize, markers: usize },
    #[error("board fit {rms_px:.2} px RMS > {} px", MAX_VIEW_RMS_PX)]
    PoorFit { rms_px: f64 },
}

/// Prepares one view: corners, undistorted; the single-view fit. `Err(why)` when unusable.
pub fn fit_view(
    detector: &Detector,
    k: &Intrinsics,
    index: usize,
    image: String,
    tcp: Isometry3<f64>,
    detection: Detection,
) -> Result<Result<ViewFit, ViewError>, CalibError> {
    if detection.corners.len() < MIN_CORNERS {
        let why = if detection.markers == 0 {
            ViewError::NotSeen
        } else {
            ViewError::TooFewCorners { corners: detection.corners.len(), markers: detection.markers }
        };
        return Ok(Err(why));
    }
    let all = detector.object_points();
    let object: Vec<Point3<f64>> = detection
        .ids
        .iter()
        .map(|&id| all.get(id as usize).map(|p| Point3::new(p[0], p[1], p[2])))
        .collect::<Option<_>>()
        .ok_or_else(|| CalibError::Board("a corner id beyond the board".into()))?;
    let mut pixels = undistort(&detection.corners, k)?;
    let mut object = object;
    let mut detection = detection;
    let cam = Pinhole::of(k);
    let (mut board, mut rms_px) = board_pose(&cam, &object, &pixels)?;
    // A corner the refinement snapped onto a marker edge sits pixels off while the rest agree
    // to a tenth: drop corners beyond max(1 px, 4 x the median residual) and fit again.
    let residual = |pose: &Isometry3<f64>, o: &Point3<f64>, p: &[f64; 2]| {
        cam.project(&(pose * o)).map_or(f64::INFINITY, |q| ((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt())
    };
    let res: Vec<f64> = object.iter().zip(&pixels).map(|(o, p)| residual(&board, o, p)).collect();
    let mut sorted = res.clone();
    sorted.sort_by(f64::total_cmp);
    let limit = (4.0 * sorted[sorted.len() / 2]).max(1.0);
    let keep: Vec<bool> = res.iter().map(|&r| r <= limit).collect();
    let kept = keep.iter().filter(|&&k| k).count();
    if kept < res.len() && kept >= MIN_CORNERS {
        object = kept_only(object, &keep);
        pixels = kept_only(pixels, &keep);
        detection.ids = kept_only(detection.ids, &keep);
        detection.corners = kept_only(detection.corners, &keep);
        (board, rms_px) = board_pose(&cam, &object, &pixels)?;
    }
    if rms_px > MAX_VIEW_RMS_PX {
        return Ok(Err(ViewError::PoorFit { rms_px }));
    }
    Ok(Ok(ViewFit { index, image, tcp, detection, pixels, object, board, rms_px }))
}

fn kept_only<T>(v: Vec<T>, keep: &[bool]) -> Vec<T> {
    v.into_iter().zip(keep).filter(|(_, k)| **k).map(|(x, _)| x).collect()
}

/// A_i of the model `B_i = X^-1 A_i Y`.
fn robot(mount: Mount, tcp: &Isometry3<f64>) -> Isometry3<f64> {
    match mount {
        Mount::EyeToHand => *tcp,
        Mount::EyeInHand => tcp.inverse(),
    }
}

fn mat3(r: &Matrix3<f64>) -> Result<Mat, CalibError> {
    let rows =
        [[r[(0, 0)], r[(0, 1)], r[(0, 2)]], [r[(1, 0)], r[(1, 1)], r[(1, 2)]], [r[(2, 0)], r[(2, 1)], r[(2, 2)]]];
    Ok(Mat::from_slice_2d(&rows)?)
}

fn vec3(t: &Vector3<f64>) -> Result<Mat, CalibError> {
    Ok(Mat::from_slice_2d(&[[t.x], [t.y], [t.z]])?)
}

/// The mean of rigid transforms (rotation: the chordal mean, projected back onto SO(3)).
fn mean_pose(poses: &[Isometry3<f64>]) -> Isometry3<f64> {
    let n = poses.len().max(1) as f64;
    let t: Vector3<f64> = poses.iter().map(|p| p.translation.vector).sum::<Vector3<f64>>() / n;
    let m: Matrix3<f64> = poses.iter().map(|p| *p.rotation.to_rotation_matrix().matrix()).sum();
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u.expect("u"), svd.v_t.expect("v_t"));
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(u * d * v_t);
    Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_rotation_matrix(&r))
}

/// The closed-form hand-eye solution (X, Y).
pub fn hand_eye(
    mount: Mount,
    views: &[ViewFit],
    method: HandEyeMethod,
) -> Result<(Isometry3<f64>, Isometry3<f64>), CalibError> {
    let (mut r_g, mut t_g, mut r_t, mut t_t) =
        (Vector::<Mat>::new(), Vector::<Mat>::new(), Vector::<Mat>::new(), Vector::<Mat>::new());
    for v in views {
        // OpenCV's "gripper -> base" is A_i^-1 in both mounts (eye-to-hand: base -> gripper).
        let g = robot(mount, &v.tcp).inverse();
        r_g.push(mat3(g.rotation.to_rotation_matrix().matrix())?);
        t_g.push(vec3(&g.translation.vector)?);
        r_t.push(mat3(v.board.rotation.to_rotation_matrix().matrix())?);
        t_t.push(vec3(&v.board.translation.vector)?);
    }
    let (mut r, mut t) = (Mat::default(), Mat::default());
    calib3d::calibrate_hand_eye(&r_g, &t_g, &r_t, &t_t, &mut r, &mut t, method.opencv())?;
    let rm = Matrix3::from_fn(|i, j| *r.at_2d::<f64>(i as i32, j as i32).expect("3x3"));
    if !rm.iter().all(|v| v.is_finite()) {
        return Err(CalibError::Solve(format!("{} returned no solution (degenerate motion?)", method.name())));
    }
    let tv = Vector3::new(*t.at::<f64>(0)?, *t.at::<f64>(1)?, *t.at::<f64>(2)?);
    let x = Isometry3::from_parts(
        Translation3::from(tv),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&rm)),
    );
    let ys: Vec<Isometry3<f64>> = views.iter().map(|v| robot(mount, &v.tcp).inverse() * x * v.board).collect();
    Ok((x, mean_pose(&ys)))
}

/// A small rigid perturbation (translation, rotation vector) applied on the left.
fn perturb(p: &Isometry3<f64>, d: &[f64]) -> Isometry3<f64> {
    let delta = Isometry3::from_parts(
        Translation3::new(d[0], d[1], d[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(d[3], d[4], d[5])),
    );
    delta * p
}

fn residuals(
    cam: &Pinhole,
    mount: Mount,
    views: &[ViewFit],
    x: &Isometry3<f64>,
    y: &Isometry3<f64>,
    out: &mut Vec<f64>,
) {
    out.clear();
    let x_inv = x.inverse();
    for v in views {
        let b = x_inv * robot(mount, &v.tcp) * y;
        for (o, p) in v.object.iter().zip(&v.pixels) {
            match cam.project(&(b * o)) {
                Some(q) => out.extend([q[0] - p[0], q[1] - p[1]]),
                None => out.extend([1e3, 1e3]),
            }
        }
    }
}

/// Both transforms refined together (Levenberg-Marquardt, numeric Jacobian over the 12
/// parameters of two small left perturbations), minimising every corner's reprojection error.
pub fn refine(
    cam: &Pinhole,
    mount: Mount,
    views: &[ViewFit],
    x0: &Isometry3<f64>,
    y0: &Isometry3<f64>,
) -> (Isometry3<f64>, Isometry3<f64>) {
    let (mut x, mut y) = (*x0, *y0);
    let mut r = Vec::new();
    residuals(cam, mount, views, &x, &y, &mut r);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut lambda = 1e-3;
    let n = r.len();
    let apply = |x: &Isometry3<f64>, y: &Isometry3<f64>, d: &[f64]| (perturb(x, &d[..6]), perturb(y, &d[6..]));
    let (mut rp, mut rm) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for _ in 0..100 {
        let mut jac = DMatrix::<f64>::zeros(n, 12);
        for k in 0..12 {
            let h = if k % 6 < 3 { 1e-6 } else { 1e-7 };
            let mut d = [0.0; 12];
            d[k] = h;
            let (xp, yp) = apply(&x, &y, &d);
            residuals(cam, mount, views, &xp, &yp, &mut rp);
            d[k] = -h;
            let (xm, ym) = apply(&x, &y, &d);
            residuals(cam, mount, views, &xm, &ym, &mut rm);
            for i in 0..n {
                jac[(i, k)] = (rp[i] - rm[i]) / (2.0 * h);
            }
        }
        let rv = DVector::from_column_slice(&r);
        let jtj = jac.transpose() * &jac;
        let jtr = jac.transpose() * rv;
        let mut improved = false;
        for _ in 0..10 {
            let mut a = jtj.clone();
            for k in 0..12 {
                a[(k, k)] += lambda * (jtj[(k, k)] + 1e-12);
            }
            let Some(step) = a.lu().solve(&(-&jtr)) else { break };
            let (xn, yn) = apply(&x, &y, step.as_slice());
            residuals(cam, mount, views, &xn, &yn, &mut rp);
            let c: f64 = rp.iter().map(|v| v * v).sum();
            if c < cost {
                let done = (cost - c) < 1e-12 * cost.max(1e-30) || step.norm() < 1e-12;
                x = xn;
                y = yn;
                cost = c;
                std::mem::swap(&mut r, &mut rp);
                lambda = (lambda / 10.0).max(1e-12);
                improved = true;
                if done {
                    return (x, y);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (x, y)
}

/// RMS reprojection error (px) of one view through (X, Y).
pub fn view_rms(cam: &Pinhole, mount: Mount, v: &ViewFit, x: &Isometry3<f64>, y: &Isometry3<f64>) -> f64 {
    let b = x.inverse() * robot(mount, &v.tcp) * y;
    rms(cam, &b, &v.object, &v.pixels)
}

/// RMS over every corner of `views`.
pub fn total_rms(cam: &Pinhole, mount: Mount, views: &[ViewFit], x: &Isometry3<f64>, y: &Isometry3<f64>) -> f64 {
    let mut r = Vec::new();
    residuals(cam, mount, views, x, y, &mut r);
    (r.iter().map(|v| v * v).sum::<f64>() / (r.len() / 2).max(1) as f64).sqrt()
}

/// The TCP pose (base -> tcp) a view predicts through (X, Y).
pub fn predict_tcp(mount: Mount, view: &ViewFit, x: &Isometry3<f64>, y: &Isometry3<f64>) -> Isometry3<f64> {
    let a = x * view.board * y.inverse();
    match mount {
        Mount::EyeToHand => a,
        Mount::EyeInHand => a.inverse(),
    }
}

/// The closed-form X, and the final (X, Y).
pub type Solution = (Isometry3<f64>, Isometry3<f64>, Isometry3<f64>);

/// A full solve: closed form, then refined (unless `refined` is false).
pub fn calibrate(
    cam: &Pinhole,
    mount: Mount,
    views: &[ViewFit],
    method: HandEyeMethod,
    refined: bool,
) -> Result<Solution, CalibError> {
    let (x0, y0) = hand_eye(mount, views, method)?;
    let (x, y) = if refined { refine(cam, mount, views, &x0, &y0) } else { (x0, y0) };
    Ok((x0, x, y))
}

/// DROID's check: solve on a random 70% (seeded), predict the TCP pose of the other 30%.
pub fn split_check(
    cam: &Pinhole,
    mount: Mount,
    views: &[ViewFit],
    method: HandEyeMethod,
    seed: u64,
) -> Result<SplitCheck, CalibError> {
    let mut order: Vec<usize> = (0..views.len()).collect();
    order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    let n_train = ((views.len() as f64) * 0.7).round() as usize;
    let train: Vec<ViewFit> = order[..n_train].iter().map(|&i| views[i].clone()).collect();
    let test: Vec<&ViewFit> = order[n_train..].iter().map(|&i| &views[i]).collect();
    let (_, x, y) = calibrate(cam, mount, &train, method, true)?;
    let (mut pos, mut rot) = ([0.0; 3], [0.0; 3]);
    let (mut mm, mut deg) = (0.0, 0.0);
    for v in &test {
        let pred = predict_tcp(mount, v, &x, &y);
        let dp = pred.translation.vector - v.tcp.translation.vector;
        let dr = (pred.rotation * v.tcp.rotation.inverse()).scaled_axis();
        for k in 0..3 {
            pos[k] += dp[k] * dp[k];
            rot[k] += dr[k] * dr[k];
        }
        mm += dp.norm() * 1e3;
        deg += dr.norm().to_degrees();
    }
    let n = test.len().max(1) as f64;
    let pos = pos.map(|v| v / n);
    let rot = rot.map(|v| v / n);
    Ok(SplitCheck {
        train_views: train.len(),
        test_views: test.len(),
        position_mse_m2: pos,
        rotation_mse_rad2: rot,
        mean_position_error_mm: mm / n,
        mean_rotation_error_deg: deg / n,
        pass: !test.is_empty() && pos.iter().all(|&v| v < 1e-3) && rot.iter().all(|&v| v < 1e-2),
    })
}

/// A pose as the calibration file stores it.
pub fn pose_of(p: &Isometry3<f64>) -> Pose {
    let q = p.rotation.quaternion();
    Pose { position: p.translation.vector.into(), quaternion_wxyz: [q.w, q.i, q.j, q.k] }
}

/// A stored pose back to a transform.
pub fn iso_of(p: &Pose) -> Isometry3<f64> {
    let [w, i, j, k] = p.quaternion_wxyz;
    Isometry3::from_parts(
        Translation3::from(Vector3::from(p.position)),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, i, j, k)),
    )
}

/// DROID's extrinsics 6-vector: x y z + extrinsic x-y-z Euler angles.
pub fn droid_extrinsics(p: &Isometry3<f64>) -> [f64; 6] {
    let (r, pi, y) = p.rotation.euler_angles();
    let t = p.translation.vector;
    [t.x, t.y, t.z, r, pi, y]
}

/// Position (mm) and rotation (deg) between two transforms.
pub fn pose_difference(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let dp = (a.translation.vector - b.translation.vector).norm() * 1e3;
    let dr = (a.rotation * b.rotation.inverse()).angle().to_degrees();
    (dp, dr)
}
