//! Pictures of a calibration: a view with its detected corners and the corners reprojected
//! through the calibration; the residuals per view.

use crate::CalibError;
use crate::run::load_grey;
use crate::solve::{Pinhole, ViewFit};
use labrig_msgs::calibration::{CalibrationFile, Mount};
use nalgebra::Isometry3;
use opencv::core::{Point, Scalar, Vector};
use opencv::{imgcodecs, imgproc};
use plotters::prelude::*;
use std::path::Path;

/// The view with the most corners: detected corners as green circles, the same corners through
/// the calibration (board pose from the robot's TCP, not from the image) as red crosses.
pub fn overlay(
    dir: &Path,
    fit: &ViewFit,
    cam: &Pinhole,
    mount: Mount,
    x: &Isometry3<f64>,
    y: &Isometry3<f64>,
    out: &Path,
) -> Result<(), CalibError> {
    let grey = load_grey(&dir.join(&fit.image))?;
    let mut img = opencv::core::Mat::default();
    imgproc::cvt_color(&grey, &mut img, imgproc::COLOR_GRAY2BGR, 0)?;
    let a = match mount {
        Mount::EyeToHand => fit.tcp,
        Mount::EyeInHand => fit.tcp.inverse(),
    };
    let b = x.inverse() * a * y;
    let px = |p: [f64; 2]| Point::new(p[0].round() as i32, p[1].round() as i32);
    for (o, p) in fit.object.iter().zip(&fit.detection.corners) {
        imgproc::circle(&mut img, px(*p), 6, Scalar::new(0.0, 200.0, 0.0, 0.0), 2, imgproc::LINE_AA, 0)?;
        if let Some(q) = cam.project(&(b * o)) {
            imgproc::draw_marker(
                &mut img,
                px(q),
                Scalar::new(0.0, 0.0, 255.0, 0.0),
                imgproc::MARKER_CROSS,
                10,
                1,
                imgproc::LINE_AA,
            )?;
        }
    }
    let name = out.to_str().ok_or_else(|| CalibError::Image(format!("{} is not UTF-8", out.display())))?;
    if !imgcodecs::imwrite(name, &img, &Vector::new())? {
        return Err(CalibError::Image(format!("OpenCV could not write {}", out.display())));
    }
    Ok(())
}

/// Bars per view: the board fitted to the view alone, and through the calibration (px RMS).
pub fn residual_plot(file: &CalibrationFile, out: &Path) -> Result<(), CalibError> {
    let fail = |e: String| CalibError::Image(format!("{}: {e}", out.display()));
    let font = labrig_episode::font::dejavu_sans().map_err(|e| fail(e.to_string()))?;
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, font);
    let root = BitMapBackend::new(out, (900, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| fail(e.to_string()))?;
    let n = file.views.len().max(1);
    let top = file
        .views
        .iter()
        .flat_map(|v| [v.single_view_rms_px, v.calibrated_rms_px.unwrap_or(0.0)])
        .filter(|v| v.is_finite())
        .fold(0.5f64, f64::max)
        * 1.15;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            format!(
                "{}: reprojection per view ({} used of {}, {:.3} px RMS, {})",
                file.camera,
                file.views.iter().filter(|v| v.dropped.is_empty()).count(),
                file.views.len(),
                file.rms_px,
                file.method
            ),
            ("sans-serif", 18),
        )
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0f64..n as f64, 0f64..top)
        .map_err(|e| fail(e.to_string()))?;
    chart.configure_mesh().x_desc("view").y_desc("RMS (px)").draw().map_err(|e| fail(e.to_string()))?;
    let single = file.views.iter().filter(|v| v.single_view_rms_px.is_finite()).map(|v| {
        let x = v.index as f64;
        Rectangle::new([(x + 0.05, 0.0), (x + 0.45, v.single_view_rms_px)], BLUE.mix(0.6).filled())
    });
    chart
        .draw_series(single)
        .map_err(|e| fail(e.to_string()))?
        .label("board fitted to the view alone")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], BLUE.mix(0.6).filled()));
    let calibrated = file.views.iter().filter_map(|v| {
        let x = v.index as f64;
        v.calibrated_rms_px.map(|r| Rectangle::new([(x + 0.5, 0.0), (x + 0.9, r)], RED.mix(0.7).filled()))
    });
    chart
        .draw_series(calibrated)
        .map_err(|e| fail(e.to_string()))?
        .label("through the calibration")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], RED.mix(0.7).filled()));
    let dropped = file.views.iter().filter(|v| !v.dropped.is_empty()).map(|v| {
        let x = v.index as f64;
        Rectangle::new([(x + 0.05, 0.0), (x + 0.9, top * 0.03)], BLACK.filled())
    });
    chart
        .draw_series(dropped)
        .map_err(|e| fail(e.to_string()))?
        .label("dropped")
        .legend(|(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], BLACK.filled()));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| fail(e.to_string()))?;
    root.present().map_err(|e| fail(e.to_string()))?;
    Ok(())
}
