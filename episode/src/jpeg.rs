//! Camera frames are recorded as JPEG in `sensor_msgs/CompressedImage` (`format: "jpeg"`):
//! 4:2:0, quality 90 by default. At the sim's 128x128 that is ~3-6 kB a frame.

use jpeg_encoder::{ColorType, Encoder};

#[derive(Debug, thiserror::Error)]
pub enum JpegError {
    #[error("{width}x{height} RGB needs {expected} bytes, got {got}")]
    Size { width: u16, height: u16, expected: usize, got: usize },
    #[error("JPEG encoding: {0}")]
    Encode(#[from] jpeg_encoder::EncodingError),
    #[error("JPEG decoding: {0}")]
    Decode(#[from] jpeg_decoder::Error),
    #[error("JPEG decoding: a {0:?} image, not RGB")]
    NotRgb(jpeg_decoder::PixelFormat),
}

/// A decoded frame: tightly packed RGB8, row by row.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rgb {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

/// Decodes a recorded (RGB) JPEG frame.
pub fn decode_rgb(jpeg: &[u8]) -> Result<Rgb, JpegError> {
    let mut d = jpeg_decoder::Decoder::new(jpeg);
    let pixels = d.decode()?;
    let info = d.info().ok_or(JpegError::Decode(jpeg_decoder::Error::Format("no header".into())))?;
    if info.pixel_format != jpeg_decoder::PixelFormat::RGB24 {
        return Err(JpegError::NotRgb(info.pixel_format));
    }
    Ok(Rgb { width: info.width as usize, height: info.height as usize, pixels })
}

/// Encodes tightly packed RGB8 pixels.
pub fn encode_rgb(pixels: &[u8], width: u16, height: u16, quality: u8) -> Result<Vec<u8>, JpegError> {
    let expected = width as usize * height as usize * 3;
    if pixels.len() != expected {
        return Err(JpegError::Size { width, height, expected, got: pixels.len() });
    }
    let mut out = Vec::with_capacity(expected / 8);
    Encoder::new(&mut out, quality).encode(pixels, width, height, ColorType::Rgb)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_frame_becomes_a_jpeg() {
        let px: Vec<u8> = (0..128 * 128 * 3).map(|i| (i % 256) as u8).collect();
        let j = super::encode_rgb(&px, 128, 128, 90).unwrap();
        assert_eq!(&j[..2], &[0xFF, 0xD8]);
        assert_eq!(&j[j.len() - 2..], &[0xFF, 0xD9]);
        assert!(super::encode_rgb(&px[1..], 128, 128, 90).unwrap_err().to_string().contains("needs 49152 bytes"));
        // Decoded again: the size, and the pixels within JPEG's loss of a smooth gradient.
        let smooth: Vec<u8> = (0..64 * 32).flat_map(|i| [(i % 64 * 4) as u8, (i / 64 * 8) as u8, 128]).collect();
        let back = super::decode_rgb(&super::encode_rgb(&smooth, 64, 32, 95).unwrap()).unwrap();
        assert_eq!((back.width, back.height, back.pixels.len()), (64, 32, smooth.len()));
        let worst = back.pixels.iter().zip(&smooth).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
        assert!(worst <= 12, "largest pixel error {worst}");
        assert!(super::decode_rgb(&j[..100]).unwrap_err().to_string().starts_with("JPEG decoding"));
    }
}
