//! labrig-calibration: camera extrinsics from a ChArUco board and hand-eye calibration, on
//! Debian's OpenCV 4.6 (the only crate of labrig, with the camera node, that links OpenCV).
//!
//! - [`board`]: the board (DROID's 9 x 14, 20 mm squares, 16 mm markers, DICT_5X5_100 by
//!   default) and its print at scale;
//! - [`detect`]: ChArUco corners, with 4.6's two accuracy traps handled;
//! - [`solve`]: per-view board poses, the closed-form hand-eye solution, the joint refinement
//!   over every corner's reprojection, DROID's acceptance and 70/30 check;
//! - [`run`]: a capture folder (views + TCP poses, `capture.json`) to
//!   `calibration/<rig>/<camera>.json`, with its pictures.
//!
//! The file formats are in `labrig_msgs::calibration`, so readers link no OpenCV.

pub mod board;
pub mod detect;
pub mod figures;
pub mod run;
pub mod solve;

use std::path::Path;

/// Why a calibration could not be made. Every variant names what to fix.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error("board: {0}")]
    Board(String),
    #[error("image: {0}")]
    Image(String),
    #[error("{path}: {error}")]
    Io { path: String, error: std::io::Error },
    #[error("{0}")]
    Capture(String),
    #[error("hand-eye: {0}")]
    Solve(String),
    /// The calibration is not good enough to be written.
    #[error("calibration of `{camera}` rejected: {reason}")]
    Rejected { camera: String, reason: String },
}

impl CalibError {
    pub fn io(path: &Path, error: std::io::Error) -> CalibError {
        CalibError::Io { path: path.display().to_string(), error }
    }
}
