//! 8-bit grey images, as calibration views are kept: BT.601 luma of RGB pixels, binary PGM.

use std::path::Path;

/// The BT.601 luma of an RGB pixel, rounded.
pub fn luma(r: u8, g: u8, b: u8) -> u8 {
    ((299 * r as u32 + 587 * g as u32 + 114 * b as u32 + 500) / 1000).min(255) as u8
}

/// Tightly packed RGB8 pixels as grey.
pub fn from_rgb(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3).map(|p| luma(p[0], p[1], p[2])).collect()
}

/// Writes grey pixels (`width` x `height`, row by row) as a binary PGM.
pub fn write_pgm(path: &Path, width: usize, height: usize, grey: &[u8]) -> std::io::Result<()> {
    let mut out = format!("P5\n{width} {height}\n255\n").into_bytes();
    out.extend_from_slice(grey);
    std::fs::write(path, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn luma_weighs_green_most_and_keeps_the_ends() {
        assert_eq!(luma(0, 0, 0), 0);
        assert_eq!(luma(255, 255, 255), 255);
        assert_eq!(from_rgb(&[255, 0, 0, 0, 255, 0, 0, 0, 255]), vec![76, 150, 29]);
    }
}
