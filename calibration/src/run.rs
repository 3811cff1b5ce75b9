//! A capture folder to a camera's calibration: detection, intrinsics (given or calibrated),
//! the views' fits, the hand-eye solve and refinement, acceptance, and (for a sim capture) the
//! errors against the truth, per hand-eye method.

use crate::CalibError;
use crate::detect::{Detection, Detector, MIN_CORNERS};
use crate::solve::{self, HandEyeMethod, MAX_VIEW_RMS_PX, MIN_VIEWS, Pinhole, ViewError, ViewFit};
use labrig_msgs::calibration::{CALIBRATION_VERSION, CalibrationFile, CaptureFile, Intrinsics, Mount, ViewResidual};
use opencv::core::{Mat, Point2f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::imgcodecs;
use opencv::prelude::*;
use serde::Serialize;
use std::path::Path;

/// How to solve.
#[derive(Debug, Clone)]
pub struct SolveOptions {
    pub method: HandEyeMethod,
    /// Refine by reprojection after the closed form.
    pub refine: bool,
    /// Calibrate the intrinsics from the views even where the capture has some.
    pub intrinsics: bool,
    /// Seed of the 70/30 split.
    pub seed: u64,
    /// Fail when the views' joint reprojection error exceeds this (px).
    pub max_rms_px: f64,
}

impl Default for SolveOptions {
    fn default() -> SolveOptions {
        SolveOptions { method: HandEyeMethod::Daniilidis, refine: true, intrinsics: false, seed: 0, max_rms_px: 3.0 }
    }
}

/// One method's result against the truth.
#[derive(Debug, Clone, Serialize)]
pub struct MethodError {
    pub method: &'static str,
    pub closed_form_mm: f64,
    pub closed_form_deg: f64,
    pub refined_mm: f64,
    pub refined_deg: f64,
}

/// What a solve found, beside the file.
#[derive(Debug, Clone, Serialize)]
pub struct SolveReport {
    pub camera: String,
    pub mount: Mount,
    pub views_captured: usize,
    pub views_used: usize,
    /// Why views were dropped, with counts.
    pub dropped: Vec<(String, usize)>,
    pub unreachable_poses: usize,
    pub rms_px: f64,
    /// Against the sim's truth (absent for a real rig): the chosen method, refined.
    pub position_error_mm: Option<f64>,
    pub rotation_error_deg: Option<f64>,
    /// Every method, closed form and refined, against the truth.
    pub methods: Vec<MethodError>,
    /// The intrinsics calibrated from the views, when asked: RMS (px) and focal error vs the
    /// capture's own intrinsics where it had some.
    pub intrinsics_rms_px: Option<f64>,
}

/// Reads `capture.json` in `dir`.
pub fn read_capture(dir: &Path) -> Result<CaptureFile, CalibError> {
    let path = dir.join("capture.json");
    let text = std::fs::read_to_string(&path).map_err(|e| CalibError::io(&path, e))?;
    let cap: CaptureFile =
        serde_json::from_str(&text).map_err(|e| CalibError::Capture(format!("{}: {e}", path.display())))?;
    if cap.version != labrig_msgs::calibration::CAPTURE_VERSION {
        return Err(CalibError::Capture(format!(
            "{}: capture version {} (this labrig reads {})",
            path.display(),
            cap.version,
            labrig_msgs::calibration::CAPTURE_VERSION
        )));
    }
    Ok(cap)
}

/// An image of the capture, 8-bit grey.
pub fn load_grey(path: &Path) -> Result<Mat, CalibError> {
    let name = path.to_str().ok_or_else(|| CalibError::Image(format!("{} is not UTF-8", path.display())))?;
    let img = imgcodecs::imread(name, imgcodecs::IMREAD_GRAYSCALE)?;
    if img.empty() {
        return Err(CalibError::Image(format!("cannot read {} (missing or not an image)", path.display())));
    }
    Ok(img)
}

/// Detections of every view of a capture, in order.
pub fn detect_all(
    dir: &Path,
    cap: &CaptureFile,
    detector: &Detector,
    progress: &indicatif::ProgressBar,
) -> Result<Vec<Detection>, CalibError> {
    cap.views
        .iter()
        .map(|v| {
            let img = load_grey(&dir.join(&v.image))?;
            if let Some(k) = &cap.intrinsics
                && (img.cols() as u32, img.rows() as u32) != (k.width, k.height)
            {
                return Err(CalibError::Image(format!(
                    "{} is {}x{} but the camera's intrinsics are for {}x{}",
                    v.image,
                    img.cols(),
                    img.rows(),
                    k.width,
                    k.height
                )));
            }
            let d = detector.detect(&img);
            progress.inc(1);
            d
        })
        .collect()
}

/// Intrinsics calibrated from the views' corners (OpenCV's calibrateCameraCharuco, k1 k2 p1 p2
/// k3). Returns them and the RMS reprojection error (px).
pub fn calibrate_intrinsics(
    detector: &Detector,
    detections: &[Detection],
    size: (u32, u32),
) -> Result<(Intrinsics, f64), CalibError> {
    let (mut corners, mut ids) = (Vector::<Vector<Point2f>>::new(), Vector::<Vector<i32>>::new());
    for d in detections.iter().filter(|d| d.corners.len() >= MIN_CORNERS) {
        corners.push(d.corners.iter().map(|p| Point2f::new(p[0] as f32, p[1] as f32)).collect());
        ids.push(d.ids.iter().copied().collect());
    }
    if corners.len() < MIN_VIEWS {
        return Err(CalibError::Rejected {
            camera: String::new(),
            reason: format!("intrinsics need {MIN_VIEWS} views with >= {MIN_CORNERS} corners; {} have", corners.len()),
        });
    }
    let board = crate::board::charuco(detector.spec())?;
    let (mut k, mut dist) = (Mat::default(), Mat::default());
    let (mut rv, mut tv) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let criteria = TermCriteria::new(TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32, 100, 1e-9)?;
    let rms = opencv::aruco::calibrate_camera_charuco(
        &corners,
        &ids,
        &board,
        Size::new(size.0 as i32, size.1 as i32),
        &mut k,
        &mut dist,
        &mut rv,
        &mut tv,
        0,
        criteria,
    )?;
    let at = |r: i32, c: i32| k.at_2d::<f64>(r, c).copied();
    let distortion = (0..dist.total() as i32).map(|i| dist.at::<f64>(i).copied()).collect::<Result<Vec<_>, _>>()?;
    Ok((
        Intrinsics {
            width: size.0,
            height: size.1,
            fx: at(0, 0)?,
            fy: at(1, 1)?,
            cx: at(0, 2)?,
            cy: at(1, 2)?,
            distortion,
            source: "calibrated".into(),
        },
        rms,
    ))
}

/// Solves a capture folder. On success: the calibration file (not yet written) and the
/// report; a calibration that fails acceptance is an error that says why.
pub fn solve_capture(
    dir: &Path,
    opts: &SolveOptions,
    progress: &indicatif::ProgressBar,
) -> Result<(CalibrationFile, SolveReport, Vec<ViewFit>), CalibError> {
    let cap = read_capture(dir)?;
    let camera = cap.camera.clone();
    let reject = |reason: String| CalibError::Rejected { camera: camera.clone(), reason };
    if cap.views.is_empty() {
        return Err(reject(format!(
            "the capture has no views ({} poses of the set were unreachable)",
            cap.unreachable
        )));
    }
    let detector = Detector::new(&cap.board)?;
    let detections = detect_all(dir, &cap, &detector, progress)?;
    let (intrinsics, intrinsics_rms) = match (&cap.intrinsics, opts.intrinsics) {
        (Some(k), false) => (k.clone(), None),
        (given, _) => {
            let size = match given {
                Some(k) => (k.width, k.height),
                None => {
                    let img = load_grey(&dir.join(&cap.views[0].image))?;
                    (img.cols() as u32, img.rows() as u32)
                }
            };
            let (k, rms) = calibrate_intrinsics(&detector, &detections, size).map_err(|e| match e {
                CalibError::Rejected { reason, .. } => reject(reason),
                other => other,
            })?;
            (k, Some(rms))
        }
    };
    let mut fits = Vec::new();
    let mut residuals = Vec::new();
    let mut dropped: Vec<(String, usize)> = Vec::new();
    for (i, (v, d)) in cap.views.iter().zip(detections).enumerate() {
        let tcp = solve::iso_of(&v.tcp);
        let corners = d.corners.len();
        match solve::fit_view(&detector, &intrinsics, i, v.image.clone(), tcp, d)? {
            Ok(fit) => {
                residuals.push(ViewResidual {
                    index: i,
                    image: v.image.clone(),
                    corners,
                    single_view_rms_px: fit.rms_px,
                    calibrated_rms_px: None,
                    dropped: String::new(),
                });
                fits.push(fit);
            }
            Err(why) => {
                let kind = match why {
                    ViewError::PoorFit { .. } => format!("board fit above {MAX_VIEW_RMS_PX} px"),
                    ViewError::NotSeen => "board not seen".to_string(),
                    ViewError::TooFewCorners { .. } => format!("fewer than {MIN_CORNERS} corners"),
                };
                match dropped.iter_mut().find(|(k, _)| *k == kind) {
                    Some((_, n)) => *n += 1,
                    None => dropped.push((kind, 1)),
                }
                residuals.push(ViewResidual {
                    index: i,
                    image: v.image.clone(),
                    corners,
                    single_view_rms_px: f64::NAN,
                    calibrated_rms_px: None,
                    dropped: why.to_string(),
                });
            }
        }
    }
    if fits.len() < MIN_VIEWS {
        let mut why: Vec<String> = dropped.iter().map(|(k, n)| format!("{n} {k}")).collect();
        if cap.unreachable > 0 {
            why.push(format!("and {} poses of the set unreachable", cap.unreachable));
        }
        return Err(reject(format!(
            "{} usable views of {} ({}); at least {MIN_VIEWS} needed — is the board in `{camera}`'s view, \
             and is the board spec the one printed?",
            fits.len(),
            cap.views.len(),
            if why.is_empty() { "none dropped".into() } else { why.join(", ") }
        )));
    }
    let cam = Pinhole::of(&intrinsics);
    let (x0, x, y) = solve::calibrate(&cam, cap.mount, &fits, opts.method, opts.refine)?;
    let rms = solve::total_rms(&cam, cap.mount, &fits, &x, &y);
    for f in &fits {
        residuals[f.index].calibrated_rms_px = Some(solve::view_rms(&cam, cap.mount, f, &x, &y));
    }
    if rms > opts.max_rms_px {
        let worst = fits
            .iter()
            .map(|f| (solve::view_rms(&cam, cap.mount, f, &x, &y), f.image.as_str()))
            .fold((0.0, ""), |a, b| if b.0 > a.0 { b } else { a });
        return Err(reject(format!(
            "the views disagree with one rigid board: {rms:.2} px RMS over all corners > {} px (worst {} at {:.1} px); \
             did the board move in the gripper or on the table, or do the robot poses not match the images?",
            opts.max_rms_px, worst.1, worst.0
        )));
    }
    let check = solve::split_check(&cam, cap.mount, &fits, opts.method, opts.seed)?;
    if !check.pass {
        return Err(reject(format!(
            "DROID's 70/30 check failed: the held-out gripper poses are off by {:.1} mm / {:.2} deg on average \
             (per-axis MSE {:?} m^2, {:?} rad^2; limits 1e-3, 1e-2)",
            check.mean_position_error_mm, check.mean_rotation_error_deg, check.position_mse_m2, check.rotation_mse_rad2
        )));
    }
    let mut methods = Vec::new();
    let (mut pos_err, mut rot_err) = (None, None);
    if let Some(truth) = &cap.truth {
        let t = solve::iso_of(&truth.camera);
        let (mm, deg) = solve::pose_difference(&x, &t);
        pos_err = Some(mm);
        rot_err = Some(deg);
        for m in HandEyeMethod::ALL {
            let Ok((c, r, _)) = solve::calibrate(&cam, cap.mount, &fits, m, true) else { continue };
            let (cm, cd) = solve::pose_difference(&c, &t);
            let (rm, rd) = solve::pose_difference(&r, &t);
            methods.push(MethodError {
                method: m.name(),
                closed_form_mm: cm,
                closed_form_deg: cd,
                refined_mm: rm,
                refined_deg: rd,
            });
        }
    }
    let now = chrono::Utc::now();
    let file = CalibrationFile {
        version: CALIBRATION_VERSION,
        rig: cap.rig.clone(),
        camera: camera.clone(),
        mount: cap.mount,
        parent_frame: cap.mount.parent_frame().into(),
        child_frame: format!("{camera}_optical"),
        pose: solve::pose_of(&x),
        droid_extrinsics: solve::droid_extrinsics(&x),
        closed_form: solve::pose_of(&x0),
        method: if opts.refine { format!("{}+refined", opts.method.name()) } else { opts.method.name().into() },
        board_pose: solve::pose_of(&y),
        intrinsics,
        board: cap.board.clone(),
        rms_px: rms,
        views: residuals,
        check,
        date: now.to_rfc3339_opts(chrono::SecondsFormat::Secs, true),
        unix_time_s: now.timestamp(),
        sim_scene: cap.sim_scene.clone(),
    };
    let report = SolveReport {
        camera,
        mount: cap.mount,
        views_captured: cap.views.len(),
        views_used: fits.len(),
        dropped,
        unreachable_poses: cap.unreachable,
        rms_px: rms,
        position_error_mm: pos_err,
        rotation_error_deg: rot_err,
        methods,
        intrinsics_rms_px: intrinsics_rms,
    };
    Ok((file, report, fits))
}

/// Writes a calibration file (pretty JSON), creating its folder.
pub fn write_calibration(path: &Path, file: &CalibrationFile) -> Result<(), CalibError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| CalibError::io(dir, e))?;
    }
    let text = serde_json::to_string_pretty(file).expect("a calibration serialises");
    std::fs::write(path, text + "\n").map_err(|e| CalibError::io(path, e))
}

/// Reads a calibration file.
pub fn read_calibration(path: &Path) -> Result<CalibrationFile, CalibError> {
    let text = std::fs::read_to_string(path).map_err(|e| CalibError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| CalibError::Capture(format!("{}: {e}", path.display())))
}
