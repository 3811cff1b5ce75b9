//! Camera calibration files (serde): what `labrig calibrate` writes to
//! `calibration/<rig>/<camera>.json` and what the camera node, the sim bridge and the recorder
//! read back, plus the capture a calibration is solved from (`capture.json` beside the views).
//! The solver (OpenCV) lives in labrig-calibration; the schema lives here so that readers
//! link no OpenCV.

use crate::Invalid;
use serde::{Deserialize, Serialize};

/// The calibration file's schema version.
pub const CALIBRATION_VERSION: u32 = 1;

/// A ChArUco board: `squares_x` x `squares_y` chessboard squares with ArUco markers in the
/// white ones, as OpenCV 4.6's `CharucoBoard::create` takes them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoardSpec {
    pub squares_x: u32,
    pub squares_y: u32,
    /// Side of a chessboard square, m.
    pub square_m: f64,
    /// Side of a marker, m.
    pub marker_m: f64,
    /// An OpenCV predefined dictionary, e.g. `DICT_5X5_100`.
    pub dictionary: String,
}

impl Default for BoardSpec {
    fn default() -> BoardSpec {
        BoardSpec::droid()
    }
}

impl BoardSpec {
    /// DROID's board: 9 x 14 squares of 20 mm, 16 mm markers, DICT_5X5_100.
    pub fn droid() -> BoardSpec {
        BoardSpec { squares_x: 9, squares_y: 14, square_m: 0.020, marker_m: 0.016, dictionary: "DICT_5X5_100".into() }
    }

    /// The printed area (width along x, height along y), m.
    pub fn size_m(&self) -> [f64; 2] {
        [self.squares_x as f64 * self.square_m, self.squares_y as f64 * self.square_m]
    }

    /// Inner chessboard corners (the ChArUco corners).
    pub fn corners(&self) -> usize {
        (self.squares_x.saturating_sub(1) * self.squares_y.saturating_sub(1)) as usize
    }

    /// Markers on the board (one per white square).
    pub fn markers(&self) -> usize {
        (self.squares_x * self.squares_y / 2) as usize
    }

    pub fn validate(&self) -> Result<(), Invalid> {
        if self.squares_x < 3 || self.squares_y < 3 || self.squares_x > 64 || self.squares_y > 64 {
            return Err(Invalid::new(
                "board.squares_x/squares_y",
                format!("{} x {} squares: each must be 3..64", self.squares_x, self.squares_y),
            ));
        }
        if !(self.square_m.is_finite() && self.square_m > 0.001 && self.square_m < 1.0) {
            return Err(Invalid::new(
                "board.square_m",
                format!("{} m is not a square size (1 mm .. 1 m)", self.square_m),
            ));
        }
        if !(self.marker_m.is_finite() && self.marker_m > 0.0 && self.marker_m < self.square_m) {
            return Err(Invalid::new(
                "board.marker_m",
                format!("{} m must be positive and smaller than the square ({} m)", self.marker_m, self.square_m),
            ));
        }
        Ok(())
    }
}

/// A pinhole camera of a `width` x `height` image with OpenCV's distortion (plumb_bob: k1 k2 p1
/// p2 k3), ROS's pixel-centre convention (the centre of the top-left pixel is (0, 0)). The one
/// intrinsics type: calibration files, the camera node's sources and configs, the sim.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub distortion: Vec<f64>,
    /// Where they came from: `sim`, `zed-factory`, `realsense`, `calibrated`, `config`, `file`
    /// (empty in a file or config that does not say).
    #[serde(default)]
    pub source: String,
}

/// Intrinsics asked for at a size of another aspect ratio than the sensor's.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "intrinsics for {have_w}x{have_h} do not scale to {want_w}x{want_h}: the aspect ratios differ ({:.3} vs {:.3})",
    *have_w as f64 / *have_h as f64, *want_w as f64 / *want_h as f64
)]
pub struct AspectMismatch {
    pub have_w: u32,
    pub have_h: u32,
    pub want_w: u32,
    pub want_h: u32,
}

impl Intrinsics {
    /// The same camera at `width` x `height` (the sensor read out at another resolution):
    /// focal lengths scale with the size, the principal point keeps its place on the sensor
    /// (`c' = (c + 0.5) s - 0.5` in pixel-centre coordinates); distortion does not change.
    pub fn scaled(&self, width: u32, height: u32) -> Result<Intrinsics, AspectMismatch> {
        if (width, height) == (self.width, self.height) {
            return Ok(self.clone());
        }
        let (sx, sy) = (width as f64 / self.width as f64, height as f64 / self.height as f64);
        if (sx / sy - 1.0).abs() > 0.01 {
            return Err(AspectMismatch { have_w: self.width, have_h: self.height, want_w: width, want_h: height });
        }
        Ok(Intrinsics {
            width,
            height,
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: (self.cx + 0.5) * sx - 0.5,
            cy: (self.cy + 0.5) * sy - 0.5,
            distortion: self.distortion.clone(),
            source: self.source.clone(),
        })
    }

    /// `sensor_msgs/CameraInfo` for a frame stamped `stamp` in the optical frame `frame_id`.
    pub fn camera_info(
        &self,
        stamp: crate::builtin_interfaces::Time,
        frame_id: &str,
    ) -> crate::sensor_msgs::CameraInfo {
        let mut d = self.distortion.clone();
        d.resize(5, 0.0);
        crate::sensor_msgs::CameraInfo {
            header: crate::std_msgs::Header { stamp, frame_id: frame_id.to_owned() },
            height: self.height,
            width: self.width,
            distortion_model: "plumb_bob".into(),
            d,
            k: [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [self.fx, 0.0, self.cx, 0.0, 0.0, self.fy, self.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            ..crate::sensor_msgs::CameraInfo::default()
        }
    }
}

/// How the camera is mounted, and so what its calibration is relative to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mount {
    /// Fixed beside the robot (external cameras): camera -> robot base; the board is carried
    /// by the gripper.
    EyeToHand,
    /// On the wrist: camera -> gripper (the TCP); the board lies on the table.
    EyeInHand,
}

impl Mount {
    /// The frame the calibrated pose is given in.
    pub fn parent_frame(self) -> &'static str {
        match self {
            Mount::EyeToHand => "base",
            Mount::EyeInHand => "tcp",
        }
    }
}

/// A rigid transform: `parent -> child` maps child coordinates into the parent frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pose {
    pub position: [f64; 3],
    /// Unit quaternion, w x y z.
    pub quaternion_wxyz: [f64; 4],
}

/// One view's fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewResidual {
    pub index: usize,
    pub image: String,
    /// ChArUco corners found.
    pub corners: usize,
    /// RMS reprojection error of the board pose fitted to this view alone (px).
    pub single_view_rms_px: f64,
    /// RMS reprojection error through the final calibration (px); absent if the view was dropped.
    pub calibrated_rms_px: Option<f64>,
    /// Why it was not used (empty: used).
    pub dropped: String,
}

/// DROID's check: the calibration solved on a random 70% of the views predicts the gripper
/// pose of the other 30%; it passes below 1e-3 m^2 and 1e-2 rad^2 mean squared error per axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SplitCheck {
    pub train_views: usize,
    pub test_views: usize,
    pub position_mse_m2: [f64; 3],
    pub rotation_mse_rad2: [f64; 3],
    pub mean_position_error_mm: f64,
    pub mean_rotation_error_deg: f64,
    pub pass: bool,
}

/// A camera's calibration: `calibration/<rig>/<camera>.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    pub version: u32,
    pub rig: String,
    pub camera: String,
    pub mount: Mount,
    /// `base` (eye-to-hand) or `tcp` (eye-in-hand).
    pub parent_frame: String,
    /// `<camera>_optical` (z forward, x right, y down).
    pub child_frame: String,
    /// parent -> camera optical frame, after refinement.
    pub pose: Pose,
    /// The same as DROID's `<camera>_cam_extrinsics`: x y z + extrinsic x-y-z Euler angles.
    pub droid_extrinsics: [f64; 6],
    /// The closed-form hand-eye solution before refinement.
    pub closed_form: Pose,
    /// `<hand-eye method>` + `+refined` when the reprojection refinement ran.
    pub method: String,
    /// The board's pose in the frame it is fixed to (tcp for eye-to-hand, base for eye-in-hand).
    pub board_pose: Pose,
    pub intrinsics: Intrinsics,
    pub board: BoardSpec,
    /// RMS reprojection error over every corner of the used views (px).
    pub rms_px: f64,
    pub views: Vec<ViewResidual>,
    pub check: SplitCheck,
    /// When it was calibrated: RFC 3339 (UTC) and Unix seconds.
    pub date: String,
    pub unix_time_s: i64,
    /// For a simulated rig: the scene it was calibrated in (`<spec name> seed <N>`; each seed
    /// places the cameras anew). The sim bridge uses it in that scene only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim_scene: Option<String>,
}

impl CalibrationFile {
    /// A plausible calibration of `camera` (eye-to-hand, 1280x720, a passed check) made at
    /// `unix_time_s`: for tests and examples of the readers.
    pub fn example(camera: &str, unix_time_s: i64) -> CalibrationFile {
        let pose = Pose { position: [0.1, 0.2, 0.3], quaternion_wxyz: [1.0, 0.0, 0.0, 0.0] };
        CalibrationFile {
            version: CALIBRATION_VERSION,
            rig: "lab".into(),
            camera: camera.into(),
            mount: Mount::EyeToHand,
            parent_frame: "base".into(),
            child_frame: format!("{camera}_optical"),
            pose,
            droid_extrinsics: [0.1, 0.2, 0.3, 0.0, 0.0, 0.0],
            closed_form: pose,
            method: "daniilidis+refined".into(),
            board_pose: pose,
            intrinsics: Intrinsics {
                width: 1280,
                height: 720,
                fx: 600.0,
                fy: 600.0,
                cx: 639.5,
                cy: 359.5,
                distortion: vec![],
                source: "sim".into(),
            },
            board: BoardSpec::droid(),
            rms_px: 0.4,
            views: vec![],
            check: SplitCheck {
                train_views: 42,
                test_views: 18,
                position_mse_m2: [0.0; 3],
                rotation_mse_rad2: [0.0; 3],
                mean_position_error_mm: 0.3,
                mean_rotation_error_deg: 0.1,
                pass: true,
            },
            date: "2026-11-25T12:00:00Z".into(),
            unix_time_s,
            sim_scene: None,
        }
    }
    /// Age at `now_unix_s`, s.
    pub fn age_s(&self, now_unix_s: i64) -> i64 {
        now_unix_s - self.unix_time_s
    }
}

/// The capture file's schema version.
pub const CAPTURE_VERSION: u32 = 1;

/// One view of a capture: the image file (beside `capture.json`) and the TCP pose the robot
/// reported when it was taken (base -> tcp).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CapturedView {
    pub image: String,
    pub tcp: Pose,
}

/// What the sim knows and a real rig does not (for the accuracy report).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CaptureTruth {
    /// parent (base or tcp) -> camera optical frame.
    pub camera: Pose,
    /// The board in the frame it is fixed to (tcp or base).
    pub board: Pose,
}

/// A calibration capture: `capture.json` beside its images.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CaptureFile {
    pub version: u32,
    pub rig: String,
    pub camera: String,
    pub mount: Mount,
    pub board: BoardSpec,
    /// The camera's own intrinsics, if it has some (else `--intrinsics` calibrates them).
    pub intrinsics: Option<Intrinsics>,
    pub views: Vec<CapturedView>,
    /// Poses of the pose set the arm could not reach (skipped, counted).
    #[serde(default)]
    pub unreachable: usize,
    #[serde(default)]
    pub truth: Option<CaptureTruth>,
    /// A sim capture's scene (`<spec name> seed <N>`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim_scene: Option<String>,
}

/// The calibration board's frame on `/tf_static` (OpenCV's ChArUco frame: origin at the print's
/// top-left corner, x right, y down, z into the board), when a rig knows where the board is.
pub const BOARD_FRAME: &str = "calib_board";

/// How a sim scene is named in calibration files.
pub fn sim_scene_name(spec_name: &str, seed: u64) -> String {
    format!("{spec_name} seed {seed}")
}
