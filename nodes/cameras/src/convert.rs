//! From what a camera sends (YUYV 4:2:2, MJPEG, RGB; one image or a stereo pair side by side)
//! to the RGB8 image the rig records, and the small JPEG previews.

use crate::intrinsics::Eye;

/// Pixels as a source delivers them.
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    /// Packed RGB, 3 bytes per pixel.
    Rgb8(Vec<u8>),
    /// YUYV 4:2:2 (Y0 U Y1 V per two pixels), as UVC cameras and the ZEDs send.
    Yuyv(Vec<u8>),
    /// One JPEG image (a part of an MJPEG stream, an MJPG V4L2 buffer).
    Jpeg(Vec<u8>),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ConvertError {
    #[error("{what} of {got} bytes for {width}x{height} (expected {expected})")]
    Size { what: &'static str, got: usize, expected: usize, width: u32, height: u32 },
    #[error("a side-by-side frame must have an even width, not {0}")]
    OddWidth(u32),
    #[error("JPEG: {0}")]
    Jpeg(String),
    #[error("the image is {got_w}x{got_h}, the camera is configured for {want_w}x{want_h}")]
    WrongSize { got_w: u32, got_h: u32, want_w: u32, want_h: u32 },
}

/// The rectangle of one eye in a frame: the whole frame, or its left/right half.
fn eye_columns(width: u32, side_by_side: Option<Eye>) -> Result<(u32, u32), ConvertError> {
    match side_by_side {
        None => Ok((0, width)),
        Some(_) if !width.is_multiple_of(2) => Err(ConvertError::OddWidth(width)),
        Some(Eye::Left) => Ok((0, width / 2)),
        Some(Eye::Right) => Ok((width / 2, width / 2)),
    }
}

/// BT.601 limited-range YCbCr -> RGB (what UVC cameras send), in fixed point.
#[inline]
fn yuv_to_rgb(y: u8, u: u8, v: u8) -> [u8; 3] {
    let c = (i32::from(y) - 16) * 298;
    let d = i32::from(u) - 128;
    let e = i32::from(v) - 128;
    let clamp = |x: i32| ((x + 128) >> 8).clamp(0, 255) as u8;
    [clamp(c + 409 * e), clamp(c - 100 * d - 208 * e), clamp(c + 516 * d)]
}

/// YUYV `width` x `height` -> RGB8 of the chosen eye (`side_by_side`: the frame holds two
/// images side by side; `None`: the whole frame).
pub fn yuyv_to_rgb(yuyv: &[u8], width: u32, height: u32, side_by_side: Option<Eye>) -> Result<Vec<u8>, ConvertError> {
    let expected = width as usize * height as usize * 2;
    if yuyv.len() < expected || !width.is_multiple_of(2) {
        return Err(ConvertError::Size { what: "YUYV frame", got: yuyv.len(), expected, width, height });
    }
    let (x0, w) = eye_columns(width, side_by_side)?;
    if !w.is_multiple_of(2) || !x0.is_multiple_of(2) {
        return Err(ConvertError::OddWidth(width));
    }
    let mut out = Vec::with_capacity(w as usize * height as usize * 3);
    let row_bytes = width as usize * 2;
    for row in yuyv[..expected].chunks_exact(row_bytes) {
        let eye = &row[x0 as usize * 2..(x0 + w) as usize * 2];
        for q in eye.chunks_exact(4) {
            out.extend_from_slice(&yuv_to_rgb(q[0], q[1], q[3]));
            out.extend_from_slice(&yuv_to_rgb(q[2], q[1], q[3]));
        }
    }
    Ok(out)
}

/// YUYV `width` x `height` -> RGB8 as librealsense converts a RealSense's colour stream (the
/// SSSE3 path its x86-64 builds run, `unpack_yuy2`): BT.601 limited range with each term of the
/// fixed-point sum floored on its own and no rounding term, with c = Y - 16, d = U - 128,
/// e = V - 128: R = 298c/256 + 409e/256, G = 298c/256 - 100d/256 - 208e/256,
/// B = 298c/256 + 516d/256 (each quotient floored), clamped to 0..=255. It differs from
/// [`yuyv_to_rgb`]'s rounded sum by up to 2 grey levels; the RealSense read in Rust uses this
/// one so its images are librealsense's byte for byte (tests/tests/realsense_align.rs).
pub fn yuyv_to_rgb_librealsense(yuyv: &[u8], width: u32, height: u32) -> Result<Vec<u8>, ConvertError> {
    let expected = width as usize * height as usize * 2;
    if yuyv.len() < expected || !width.is_multiple_of(2) {
        return Err(ConvertError::Size { what: "YUYV frame", got: yuyv.len(), expected, width, height });
    }
    let term = |k: i32, x: i32| (k * x) >> 8;
    let pixel = |y: u8, d: i32, e: i32| {
        let c = term(298, i32::from(y) - 16);
        let clamp = |x: i32| x.clamp(0, 255) as u8;
        [clamp(c + term(409, e)), clamp(c - term(100, d) - term(208, e)), clamp(c + term(516, d))]
    };
    let mut out = Vec::with_capacity(width as usize * height as usize * 3);
    for q in yuyv[..expected].chunks_exact(4) {
        let (d, e) = (i32::from(q[1]) - 128, i32::from(q[3]) - 128);
        out.extend_from_slice(&pixel(q[0], d, e));
        out.extend_from_slice(&pixel(q[2], d, e));
    }
    Ok(out)
}

/// The chosen eye of an RGB8 side-by-side frame (or the frame itself).
pub fn crop_rgb(rgb: Vec<u8>, width: u32, height: u32, side_by_side: Option<Eye>) -> Result<Vec<u8>, ConvertError> {
    let expected = width as usize * height as usize * 3;
    if rgb.len() != expected {
        return Err(ConvertError::Size { what: "RGB frame", got: rgb.len(), expected, width, height });
    }
    let (x0, w) = eye_columns(width, side_by_side)?;
    if w == width {
        return Ok(rgb);
    }
    let mut out = Vec::with_capacity(w as usize * height as usize * 3);
    for row in rgb.chunks_exact(width as usize * 3) {
        out.extend_from_slice(&row[x0 as usize * 3..(x0 + w) as usize * 3]);
    }
    Ok(out)
}

/// Decodes a JPEG to RGB8; returns the pixels and the image's size.
pub fn decode_jpeg(jpeg: &[u8]) -> Result<(Vec<u8>, u32, u32), ConvertError> {
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB);
    let mut d = zune_jpeg::JpegDecoder::new_with_options(jpeg, options);
    let rgb = d.decode().map_err(|e| ConvertError::Jpeg(format!("{e:?}")))?;
    let (w, h) = d.dimensions().ok_or_else(|| ConvertError::Jpeg("no dimensions after decoding".into()))?;
    Ok((rgb, w as u32, h as u32))
}

/// One eye as RGB8 at `want` (width, height) from what the source sent at `size` (for JPEG
/// the size comes from the image itself). A size other than the configured one is an error,
/// never a silent resize.
pub fn to_rgb(
    pixels: Pixels,
    size: (u32, u32),
    side_by_side: Option<Eye>,
    want: (u32, u32),
) -> Result<Vec<u8>, ConvertError> {
    let (rgb, (w, h)) = match pixels {
        Pixels::Rgb8(v) => {
            let (_, ew) = eye_columns(size.0, side_by_side)?;
            (crop_rgb(v, size.0, size.1, side_by_side)?, (ew, size.1))
        }
        Pixels::Yuyv(v) => {
            let (_, ew) = eye_columns(size.0, side_by_side)?;
            (yuyv_to_rgb(&v, size.0, size.1, side_by_side)?, (ew, size.1))
        }
        Pixels::Jpeg(v) => {
            let (rgb, w, h) = decode_jpeg(&v)?;
            let (_, ew) = eye_columns(w, side_by_side)?;
            (crop_rgb(rgb, w, h, side_by_side)?, (ew, h))
        }
    };
    if (w, h) != want {
        return Err(ConvertError::WrongSize { got_w: w, got_h: h, want_w: want.0, want_h: want.1 });
    }
    Ok(rgb)
}

/// A preview: the image shrunk by an integer factor to at most `max_width` wide (each output
/// pixel the mean of its block), JPEG at `quality`.
pub fn preview_jpeg(rgb: &[u8], width: u32, height: u32, max_width: u32, quality: u8) -> Vec<u8> {
    let k = width.div_ceil(max_width.max(1)).max(1);
    let (w, h) = ((width / k).max(1), (height / k).max(1));
    let mut small = Vec::with_capacity(w as usize * h as usize * 3);
    let n = k * k;
    for y in 0..h {
        for x in 0..w {
            let mut acc = [0u32; 3];
            for dy in 0..k {
                let row = ((y * k + dy) * width) as usize;
                for dx in 0..k {
                    let p = (row + (x * k + dx) as usize) * 3;
                    for c in 0..3 {
                        acc[c] += u32::from(rgb[p + c]);
                    }
                }
            }
            small.extend(acc.iter().map(|a| (a / n) as u8));
        }
    }
    let mut out = Vec::new();
    let enc = jpeg_encoder::Encoder::new(&mut out, quality);
    enc.encode(&small, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
        .expect("JPEG of an RGB buffer of its own size");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yuyv_grey_and_primaries() {
        // Y=16 black, Y=235 white, U=V=128 neutral.
        assert_eq!(yuv_to_rgb(16, 128, 128), [0, 0, 0]);
        assert_eq!(yuv_to_rgb(235, 128, 128), [255, 255, 255]);
        // BT.601 red (Y 81, Cb 90, Cr 240) comes back red.
        let [r, g, b] = yuv_to_rgb(81, 90, 240);
        assert!(r > 250 && g < 5 && b < 5, "{r} {g} {b}");
    }

    /// A synthesised side-by-side YUYV frame: the left eye white, the right eye black. The
    /// left is what the node publishes; the right only when asked.
    #[test]
    fn a_side_by_side_yuyv_frame_gives_each_eye() {
        let (w, h) = (8u32, 2u32);
        let mut frame = Vec::new();
        for _ in 0..h {
            for x in (0..w).step_by(2) {
                let y = if x < w / 2 { 235 } else { 16 };
                frame.extend_from_slice(&[y, 128, y, 128]);
            }
        }
        let left = yuyv_to_rgb(&frame, w, h, Some(Eye::Left)).unwrap();
        assert_eq!(left.len(), 4 * 2 * 3);
        assert!(left.iter().all(|&v| v == 255));
        let right = yuyv_to_rgb(&frame, w, h, Some(Eye::Right)).unwrap();
        assert!(right.iter().all(|&v| v == 0));
        let both = yuyv_to_rgb(&frame, w, h, None).unwrap();
        assert_eq!(both.len(), 8 * 2 * 3);
        let short = yuyv_to_rgb(&frame[..10], w, h, None).unwrap_err();
        assert!(short.to_string().contains("YUYV frame of 10 bytes for 8x2"), "{short}");
    }

    #[test]
    fn jpeg_round_trip_is_cropped_and_size_checked() {
        // 16x8: left half red, right half blue.
        let (w, h) = (16u32, 8u32);
        let mut rgb = Vec::new();
        for _ in 0..h {
            for x in 0..w {
                rgb.extend_from_slice(if x < 8 { &[250, 0, 0] } else { &[0, 0, 250] });
            }
        }
        let mut jpeg = Vec::new();
        jpeg_encoder::Encoder::new(&mut jpeg, 95)
            .encode(&rgb, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
            .unwrap();
        let left = to_rgb(Pixels::Jpeg(jpeg.clone()), (0, 0), Some(Eye::Left), (8, 8)).unwrap();
        let mean_red = left.chunks(3).map(|p| f64::from(p[0])).sum::<f64>() / 64.0;
        assert!(mean_red > 200.0, "{mean_red}");
        let e = to_rgb(Pixels::Jpeg(jpeg), (0, 0), None, (8, 8)).unwrap_err();
        assert_eq!(e.to_string(), "the image is 16x8, the camera is configured for 8x8");
    }

    #[test]
    fn previews_are_small_jpegs() {
        let rgb = vec![128u8; 640 * 360 * 3];
        let p = preview_jpeg(&rgb, 640, 360, 320, 70);
        let (px, w, h) = decode_jpeg(&p).unwrap();
        assert_eq!((w, h), (320, 180));
        assert!(px.iter().all(|&v| (120..=136).contains(&v)));
    }
}
