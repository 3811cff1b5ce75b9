//! Camera frames are recorded as JPEG in `sensor_msgs/CompressedImage` (`format: "jpeg"`):
//! 4:2:0, quality 90 by default. At the sim's 128x128 that is ~3-6 kB a frame.

use jpeg_encoder::{ColorType, Encoder};

#[derive(Debug, thiserror::Error)]
pub enum JpegError {
    #[error("{width}x{height} RGB needs {expected} bytes, got {got}")]
    Size { width: u16, height: u16, expected: usize, got: usize },
    #[error("JPEG encoding: {0}")]
    Encode(#[from] jpeg_encoder::EncodingError),
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
    }
}
