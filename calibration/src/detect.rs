//! ChArUco corners in an image, with OpenCV 4.6's two accuracy traps handled
//! (../shared/FACTS.md, measured again in the sim by `labrig calibrate --sim`):
//! - the markers' sub-pixel refinement uses a 2 px window: the default (5) lets a marker corner
//!   snap onto the chessboard corner 2 mm away (DROID's 16 mm markers in 20 mm squares);
//! - 4.6's interpolated ChArUco corners come back shifted by (+0.5, +0.5) px: subtracted, then
//!   each corner is refined again with cornerSubPix in the same small window.

use crate::CalibError;
use crate::board;
use labrig_msgs::calibration::BoardSpec;
use opencv::core::{Mat, Point2f, Ptr, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;
use opencv::{aruco, imgproc};

/// The least ChArUco corners a view must show (DROID's rule).
pub const MIN_CORNERS: usize = 10;

/// Sub-pixel refinement half-window (px).
const REFINE_WINDOW: i32 = 2;

/// The corners found in one image.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Detection {
    /// Markers found (after refinement against the board).
    pub markers: usize,
    /// ChArUco corner ids and their pixel positions (OpenCV convention: pixel centres at
    /// integer coordinates).
    pub ids: Vec<i32>,
    pub corners: Vec<[f64; 2]>,
}

/// Finds a board's corners.
pub struct Detector {
    spec: BoardSpec,
    board: Ptr<aruco::CharucoBoard>,
    /// The same board as OpenCV's base class (refineDetectedMarkers takes that).
    as_board: Ptr<aruco::Board>,
    dictionary: Ptr<aruco::Dictionary>,
    params: Ptr<aruco::DetectorParameters>,
    /// Apply the 4.6 half-pixel correction (off only to measure the trap).
    pub half_pixel_fix: bool,
}

impl std::fmt::Debug for Detector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Detector").field("board", &self.spec).finish()
    }
}

impl Detector {
    pub fn new(spec: &BoardSpec) -> Result<Detector, CalibError> {
        let board = board::charuco(spec)?;
        let dictionary = board::dictionary(&spec.dictionary)?;
        let mut params = aruco::DetectorParameters::create()?;
        params.set_corner_refinement_method(aruco::CORNER_REFINE_SUBPIX);
        params.set_corner_refinement_win_size(REFINE_WINDOW);
        params.set_corner_refinement_max_iterations(50);
        params.set_corner_refinement_min_accuracy(0.01);
        let as_board: Ptr<aruco::Board> = board::charuco(spec)?.into();
        Ok(Detector { spec: spec.clone(), board, as_board, dictionary, params, half_pixel_fix: true })
    }

    pub fn spec(&self) -> &BoardSpec {
        &self.spec
    }

    /// The board's corner positions in its own frame (m), by ChArUco id.
    pub fn object_points(&self) -> Vec<[f64; 3]> {
        self.board.chessboard_corners().iter().map(|p| [p.x as f64, p.y as f64, p.z as f64]).collect()
    }

    /// The corners in an 8-bit greyscale image.
    pub fn detect(&self, grey: &Mat) -> Result<Detection, CalibError> {
        let mut corners: Vector<Vector<Point2f>> = Vector::new();
        let mut ids: Vector<i32> = Vector::new();
        let mut rejected: Vector<Vector<Point2f>> = Vector::new();
        aruco::detect_markers(grey, &self.dictionary, &mut corners, &mut ids, &self.params, &mut rejected)?;
        if ids.is_empty() {
            return Ok(Detection::default());
        }
        let mut recovered: Vector<i32> = Vector::new();
        aruco::refine_detected_markers(
            grey,
            &self.as_board,
            &mut corners,
            &mut ids,
            &mut rejected,
            &Mat::default(),
            &Mat::default(),
            10.0,
            3.0,
            true,
            &mut recovered,
            &self.params,
        )?;
        let mut ch_corners: Vector<Point2f> = Vector::new();
        let mut ch_ids: Vector<i32> = Vector::new();
        let found = aruco::interpolate_corners_charuco(
            &corners,
            &ids,
            grey,
            &self.board,
            &mut ch_corners,
            &mut ch_ids,
            &Mat::default(),
            &Mat::default(),
            2,
        )?;
        let mut out = Detection { markers: ids.len(), ..Default::default() };
        if found <= 0 {
            return Ok(out);
        }
        if self.half_pixel_fix {
            let mut shifted: Vector<Point2f> = ch_corners.iter().map(|p| Point2f::new(p.x - 0.5, p.y - 0.5)).collect();
            let criteria =
                TermCriteria::new(TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32, 50, 0.001)?;
            imgproc::corner_sub_pix(
                grey,
                &mut shifted,
                Size::new(REFINE_WINDOW, REFINE_WINDOW),
                Size::new(-1, -1),
                criteria,
            )?;
            ch_corners = shifted;
        }
        out.ids = ch_ids.to_vec();
        out.corners = ch_corners.iter().map(|p| [p.x as f64, p.y as f64]).collect();
        Ok(out)
    }
}
