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
    let dict = dictionary(&spec.dictionary)?;
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

/// Writes the print as a one-page PDF whose page is the board plus a 5 mm margin, at true size
/// (print at 100% / "actual size"): the image, Flate-compressed greyscale, drawn over the page.
pub fn write_pdf(spec: &BoardSpec, px_per_square: u32, path: &Path) -> Result<(), CalibError> {
    use std::io::Write;
    let img = draw(spec, px_per_square)?;
    let (w, h) = (img.cols() as usize, img.rows() as usize);
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    z.write_all(img.data_bytes()?).map_err(|e| CalibError::io(path, e))?;
    let data = z.finish().map_err(|e| CalibError::io(path, e))?;
    // PDF units are points (1/72 in).
    let pt = |m: f64| m / 0.0254 * 72.0;
    let [bw, bh] = spec.size_m();
    let margin = pt(0.005);
    let (page_w, page_h) = (pt(bw) + 2.0 * margin, pt(bh) + 2.0 * margin);
    let content = format!("q {:.4} 0 0 {:.4} {margin:.4} {margin:.4} cm /Board Do Q\n", pt(bw), pt(bh));
    let mut out: Vec<u8> = b"%PDF-1.4\n".to_vec();
    let mut offsets = Vec::new();
    let mut object = |out: &mut Vec<u8>, body: &[u8]| {
        offsets.push(out.len());
        out.extend_from_slice(format!("{} 0 obj\n", offsets.len()).as_bytes());
        out.extend_from_slice(body);
        out.extend_from_slice(b"\nendobj\n");
    };
    object(&mut out, b"<< /Type /Catalog /Pages 2 0 R >>");
    object(&mut out, b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>");
    object(
        &mut out,
        format!(
            "<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {page_w:.4} {page_h:.4}] \
             /Resources << /XObject << /Board 5 0 R >> >> /Contents 4 0 R >>"
        )
        .as_bytes(),
    );
    object(&mut out, format!("<< /Length {} >>\nstream\n{content}endstream", content.len()).as_bytes());
    let mut image = format!(
        "<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace /DeviceGray \
         /BitsPerComponent 8 /Filter /FlateDecode /Length {} >>\nstream\n",
        data.len()
    )
    .into_bytes();
    image.extend_from_slice(&data);
    image.extend_from_slice(b"\nendstream");
    object(&mut out, &image);
    let xref = out.len();
    out.extend_from_slice(format!("xref\n0 {}\n0000000000 65535 f \n", offsets.len() + 1).as_bytes());
    for o in &offsets {
        out.extend_from_slice(format!("{o:010} 00000 n \n").as_bytes());
    }
    out.extend_from_slice(
        format!("trailer\n<< /Size {} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n", offsets.len() + 1).as_bytes(),
    );
    std::fs::write(path, out).map_err(|e| CalibError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pdf_is_one_page_at_true_size_with_a_consistent_xref() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("board.pdf");
        write_pdf(&BoardSpec::droid(), 40, &path).unwrap();
        let pdf = std::fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&pdf);
        // 180 x 280 mm + 2 x 5 mm = 190 x 290 mm = 538.58 x 822.05 pt.
        assert!(text.contains("/MediaBox [0 0 538.5827 822.0472]"), "{}", &text[..400]);
        let start: usize = text.rsplit("startxref\n").next().unwrap().lines().next().unwrap().parse().unwrap();
        assert!(pdf[start..].starts_with(b"xref\n0 6\n"));
        let entries: Vec<usize> = String::from_utf8_lossy(&pdf[start..])
            .lines()
            .skip(3)
            .take(5)
            .map(|l| l.split(' ').next().unwrap().parse().unwrap())
            .collect();
        for (k, off) in entries.iter().enumerate() {
            assert!(pdf[*off..].starts_with(format!("{} 0 obj", k + 1).as_bytes()), "object {} at {off}", k + 1);
        }
        assert!(text.contains("/Width 360 /Height 560"));
    }

    #[test]
    fn a_board_needs_a_marker_per_white_square() {
        let big = BoardSpec { squares_x: 20, squares_y: 20, dictionary: "DICT_4X4_50".into(), ..BoardSpec::droid() };
        let e = charuco(&big).unwrap_err().to_string();
        assert!(e.contains("200 markers") && e.contains("holds only 50"), "{e}");
        let e = charuco(&BoardSpec { dictionary: "DICT_9X9_1".into(), ..BoardSpec::droid() }).unwrap_err().to_string();
        assert!(e.contains("unknown ArUco dictionary `DICT_9X9_1`"), "{e}");
    }
}
