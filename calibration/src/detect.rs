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

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
    use opencv::core::{BORDER_CONSTANT, Scalar};

    /// Pixels per square of the print; it is blurred before it is warped ~4x down (a print
    /// warped down unfiltered aliases its edges by ~0.4 px).
    const PX: u32 = 96;

    /// DROID's board drawn at [`PX`] px per square, warped into a 1280x720 view of a known pose
    /// (the print's pixel u covers [u, u+1) of the board: its centre is at (u + 0.5) px), and
    /// the true pixel of every corner.
    fn synthetic_view() -> (Mat, Detector, Vec<[f64; 2]>) {
        let spec = BoardSpec::droid();
        let det = Detector::new(&spec).unwrap();
        let sharp = crate::board::draw(&spec, PX).unwrap();
        let mut print = Mat::default();
        opencv::imgproc::gaussian_blur(&sharp, &mut print, Size::new(0, 0), 1.6, 1.6, BORDER_CONSTANT).unwrap();
        let s = spec.square_m / PX as f64;
        let (f, cx, cy) = (623.5, 639.5, 359.5);
        let k = Matrix3::new(f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0);
        let r = Rotation3::from_euler_angles(0.35, -0.25, 0.1);
        let t = Vector3::new(-0.08, -0.12, 0.52);
        let rt = Matrix3::from_columns(&[r.matrix().column(0).into(), r.matrix().column(1).into(), t]);
        let m = Matrix3::new(s, 0.0, 0.5 * s, 0.0, s, 0.5 * s, 0.0, 0.0, 1.0);
        let h = k * rt * m;
        let rows: Vec<[f64; 3]> = (0..3).map(|i| [h[(i, 0)], h[(i, 1)], h[(i, 2)]]).collect();
        let hm = Mat::from_slice_2d(&rows).unwrap();
        let mut img = Mat::default();
        opencv::imgproc::warp_perspective(
            &print,
            &mut img,
            &hm,
            Size::new(1280, 720),
            opencv::imgproc::INTER_LINEAR,
            BORDER_CONSTANT,
            Scalar::all(128.0),
        )
        .unwrap();
        let truth = det
            .object_points()
            .iter()
            .map(|o| {
                let p = k * (r * Point3::new(o[0], o[1], o[2]).coords + t);
                [p.x / p.z, p.y / p.z]
            })
            .collect();
        (img, det, truth)
    }

    /// The median distance (px) of the detected corners from the truth.
    fn median_error(d: &Detection, truth: &[[f64; 2]]) -> f64 {
        let mut e: Vec<f64> = d
            .ids
            .iter()
            .zip(&d.corners)
            .map(|(&id, c)| ((c[0] - truth[id as usize][0]).powi(2) + (c[1] - truth[id as usize][1]).powi(2)).sqrt())
            .collect();
        e.sort_by(f64::total_cmp);
        e[e.len() / 2]
    }

    #[test]
    fn corners_land_on_the_truth_only_with_the_4_6_half_pixel_fix() {
        let (img, mut det, truth) = synthetic_view();
        let fixed = det.detect(&img).unwrap();
        assert!(fixed.corners.len() >= 90, "{} of 104 corners", fixed.corners.len());
        let with_fix = median_error(&fixed, &truth);
        det.half_pixel_fix = false;
        let raw = det.detect(&img).unwrap();
        let without = median_error(&raw, &truth);
        eprintln!("median corner error: {with_fix:.3} px with the fix, {without:.3} px without");
        assert!(with_fix < 0.2 && with_fix < without / 2.0, "{with_fix:.3} px");
        assert!(without > 0.3, "the trap is gone from this OpenCV ({without:.3} px): drop the fix");
    }
}
