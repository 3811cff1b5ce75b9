//! The ChArUco board: OpenCV's object from a [`BoardSpec`], and its print at true scale.

use crate::CalibError;
use labrig_msgs::calibration::BoardSpec;
use opencv::core::{Mat, Ptr, Size};
use opencv::prelude::*;
use opencv::{aruco, imgcodecs};
use std::path::Path;

/// OpenCV's predefined dictionary of that name (`DICT_5X5_100`, ...).
pub fn dictionary(name: &str) -> Result<Ptr<aruco::Dictionary>, CalibError> {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    let id = match name {
        "DICT_4X4_50" => D::DICT_4X4_50,
        "DICT_4X4_100" => D::DICT_4X4_100,
        "DICT_4X4_250" => D::DICT_4X4_250,
        "DICT_4X4_1000" => D::DICT_4X4_1000,
        "DICT_5X5_50" => D::DICT_5X5_50,
        "DICT_5X5_100" => D::DICT_5X5_100,
        "DICT_5X5_250" => D::DICT_5X5_250,
        "DICT_5X5_1000" => D::DICT_5X5_1000,
        "DICT_6X6_50" => D::DICT_6X6_50,
        "DICT_6X6_100" => D::DICT_6X6_100,
        "DICT_6X6_250" => D::DICT_6X6_250,
        "DICT_6X6_1000" => D::DICT_6X6_1000,
        "DICT_7X7_50" => D::DICT_7X7_50,
        "DICT_7X7_100" => D::DICT_7X7_100,
        "DICT_7X7_250" => D::DICT_7X7_250,
        "DICT_7X7_1000" => D::DICT_7X7_1000,
        "DICT_ARUCO_ORIGINAL" => D::DICT_ARUCO_ORIGINAL,
        other => {
            return Err(CalibError::Board(format!(
                "unknown ArUco dictionary `{other}` (DICT_4X4_50 .. DICT_7X7_1000 or DICT_ARUCO_ORIGINAL)"
            )));
        }
    };
    Ok(aruco::get_predefined_dictionary(id)?)
}

/// The number of markers a dictionary holds (its name's last number).
fn dictionary_size(name: &str) -> Option<usize> {
    if name == "DICT_ARUCO_ORIGINAL" {
        return Some(1024);
    }
    name.rsplit('_').next()?.parse().ok()
}

/// OpenCV's board for `spec` (checked: the dictionary must hold a marker per white square).
pub fn charuco(spec: &BoardSpec) -> Result<Ptr<aruco::CharucoBoard>, CalibError> {
    spec.validate().map_err(|e| CalibError::Board(e.to_string()))?;
    if let Some(n) = dictionary_size(&spec.dictionary)
        && n < spec.markers()
    {
        return Err(CalibError::Board(format!(
            "a {} x {} board has {} markers but {} holds only {n}",
            spec.squares_x,
            spec.squares_y,
            spec.markers(),
            spec.dictionary
        )));
    }
    let dict = dictionary(&spec.dictionary)?;
    Ok(aruco::CharucoBoard::create(
        spec.squares_x as i32,
        spec.squares_y as i32,
        spec.square_m as f32,
        spec.marker_m as f32,
        &dict,
    )?)
}

/// The board drawn edge to edge, `px_per_square` pixels per square, 8-bit grey.
pub fn draw(spec: &BoardSpec, px_per_square: u32) -> Result<Mat, CalibError> {
    let mut board = charuco(spec)?;
    let size = Size::new((spec.squares_x * px_per_square) as i32, (spec.squares_y * px_per_square) as i32);
    let mut img = Mat::default();
    board.draw(size, &mut img, 0, 1)?;
    Ok(img)
}

/// Writes the print as PNG with its physical resolution (pHYs), so a viewer printing at 100%
/// prints it at scale, plus a 5 mm white margin. Returns the dots per inch.
pub fn write_png(spec: &BoardSpec, px_per_square: u32, margin: bool, path: &Path) -> Result<f64, CalibError> {
    let img = draw(spec, px_per_square)?;
    let (w, h) = (img.cols() as usize, img.rows() as usize);
    let px_per_m = px_per_square as f64 / spec.square_m;
    let pad = if margin { (0.005 * px_per_m).round() as usize } else { 0 };
    let (ow, oh) = (w + 2 * pad, h + 2 * pad);
    let mut grey = vec![255u8; ow * oh];
    let data = img.data_bytes()?;
    for r in 0..h {
        grey[(r + pad) * ow + pad..(r + pad) * ow + pad + w].copy_from_slice(&data[r * w..(r + 1) * w]);
    }
    let file = std::fs::File::create(path).map_err(|e| CalibError::io(path, e))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), ow as u32, oh as u32);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    let ppm = px_per_m.round() as u32;
    enc.set_pixel_dims(Some(png::PixelDimensions { xppu: ppm, yppu: ppm, unit: png::Unit::Meter }));
    let mut writer = enc.write_header().map_err(|e| CalibError::Image(format!("{}: {e}", path.display())))?;
    writer.write_image_data(&grey).map_err(|e| CalibError::Image(format!("{}: {e}", path.display())))?;
    Ok(px_per_m * 0.0254)
}

/// Writes the print with OpenCV (any format it knows), no margin.
pub fn write_image(spec: &BoardSpec, px_per_square: u32, path: &Path) -> Result<(), CalibError> {
    let img = draw(spec, px_per_square)?;
    let name = path.to_str().ok_or_else(|| CalibError::Image(format!("{} is not UTF-8", path.display())))?;
    if !imgcodecs::imwrite(name, &img, &opencv::core::Vector::new())? {
        return Err(CalibError::Image(format!("OpenCV could not write {}", path.display())));
    }
    Ok(())
}
