//! RGB8 images as PNG files: the one decoder and encoder the tools share (`labrig cameras
//! rectify`, contact sheets, the tests' images).

pub use crate::jpeg::Rgb;

#[derive(Debug, thiserror::Error)]
pub enum PngError {
    #[error("PNG decoding: {0}")]
    Decode(#[from] ::png::DecodingError),
    #[error("PNG encoding: {0}")]
    Encode(#[from] ::png::EncodingError),
    #[error("a {1:?}-bit {0:?} PNG (labrig reads 8-bit RGB, RGBA and grey)")]
    Format(::png::ColorType, ::png::BitDepth),
    #[error("the PNG is too large to decode")]
    TooLarge,
    #[error("{width}x{height} RGB needs {expected} bytes, got {got}")]
    Size { width: u32, height: u32, expected: usize, got: usize },
}

/// Decodes an 8-bit RGB, RGBA (alpha dropped) or grey PNG to RGB8.
pub fn decode_rgb(bytes: &[u8]) -> Result<Rgb, PngError> {
    let mut reader = ::png::Decoder::new(std::io::Cursor::new(bytes)).read_info()?;
    let mut buf = vec![0u8; reader.output_buffer_size().ok_or(PngError::TooLarge)?];
    let info = reader.next_frame(&mut buf)?;
    let px = &buf[..info.buffer_size()];
    let pixels: Vec<u8> = match (info.color_type, info.bit_depth) {
        (::png::ColorType::Rgb, ::png::BitDepth::Eight) => px.to_vec(),
        (::png::ColorType::Rgba, ::png::BitDepth::Eight) => {
            px.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect()
        }
        (::png::ColorType::Grayscale, ::png::BitDepth::Eight) => px.iter().flat_map(|&g| [g, g, g]).collect(),
        (c, d) => return Err(PngError::Format(c, d)),
    };
    Ok(Rgb { width: info.width as usize, height: info.height as usize, pixels })
}

/// Encodes tightly packed RGB8 pixels as an 8-bit RGB PNG.
pub fn encode_rgb(pixels: &[u8], width: u32, height: u32) -> Result<Vec<u8>, PngError> {
    let expected = width as usize * height as usize * 3;
    if pixels.len() != expected {
        return Err(PngError::Size { width, height, expected, got: pixels.len() });
    }
    let mut out = Vec::new();
    {
        let mut enc = ::png::Encoder::new(&mut out, width, height);
        enc.set_color(::png::ColorType::Rgb);
        enc.set_depth(::png::BitDepth::Eight);
        enc.write_header()?.write_image_data(pixels)?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_image_comes_back_as_it_went_and_bad_sizes_are_named() {
        let rgb: Vec<u8> = (0..4 * 3 * 3).map(|i| i as u8 * 7).collect();
        let png = encode_rgb(&rgb, 4, 3).unwrap();
        assert_eq!(decode_rgb(&png).unwrap(), Rgb { width: 4, height: 3, pixels: rgb });
        assert_eq!(encode_rgb(&[0; 5], 4, 3).unwrap_err().to_string(), "4x3 RGB needs 36 bytes, got 5");
        assert!(decode_rgb(b"not a png").unwrap_err().to_string().starts_with("PNG decoding: "));
    }
}
