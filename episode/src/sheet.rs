//! An episode's contact sheet: one PNG, a row per moment (first, middle, last recorded frame),
//! a column per camera (`labrig demo` writes one per episode; the operator station serves them).

use labrig_msgs::rig::RIG_CAMERAS;
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_msgs::topics;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum SheetError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: {what}")]
    Bad { path: String, what: String },
}

/// The contact sheet of the MCAP file `mcap_file` as PNG bytes.
pub fn contact_sheet_png(mcap_file: &Path) -> Result<Vec<u8>, SheetError> {
    let path = mcap_file.display().to_string();
    let bad = |what: String| SheetError::Bad { path: path.clone(), what };
    let buf = std::fs::read(mcap_file).map_err(|source| SheetError::Io { path: path.clone(), source })?;
    let mut frames: Vec<Vec<Vec<u8>>> = vec![Vec::new(); RIG_CAMERAS.len()];
    for m in mcap::MessageStream::new(&buf).map_err(|e| bad(e.to_string()))? {
        let m = m.map_err(|e| bad(e.to_string()))?;
        let Some(cam) =
            m.channel.topic.strip_prefix(topics::CAMERAS_PREFIX).and_then(|t| t.strip_suffix("/image/compressed"))
        else {
            continue;
        };
        let Some(i) = RIG_CAMERAS.iter().position(|c| *c == cam) else { continue };
        let img = labrig_msgs::decode::<CompressedImage>(&m.data).map_err(|e| bad(e.to_string()))?;
        frames[i].push(img.data);
    }
    let n = frames.iter().map(Vec::len).min().unwrap_or(0);
    if n == 0 {
        return Err(bad("the episode has no frames from every camera".into()));
    }
    let decode = |jpeg: &[u8]| crate::jpeg::decode_rgb(jpeg).map_err(|e| bad(e.to_string()));
    let first = decode(&frames[0][0])?;
    let (w, h) = (first.width, first.height);
    let rows = [0, n / 2, n - 1];
    let gap = 4;
    let (sw, sh) = (RIG_CAMERAS.len() * (w + gap) - gap, rows.len() * (h + gap) - gap);
    let mut sheet = vec![32u8; sw * sh * 3];
    for (r, &k) in rows.iter().enumerate() {
        for (c, cam) in frames.iter().enumerate() {
            let img = decode(&cam[k])?;
            if (img.width, img.height) != (w, h) {
                return Err(bad(format!("cameras of different sizes ({}x{} vs {w}x{h})", img.width, img.height)));
            }
            for y in 0..h {
                let dst = ((r * (h + gap) + y) * sw + c * (w + gap)) * 3;
                sheet[dst..dst + w * 3].copy_from_slice(&img.pixels[y * w * 3..(y + 1) * w * 3]);
            }
        }
    }
    crate::png::encode_rgb(&sheet, sw as u32, sh as u32).map_err(|e| bad(format!("encoding the PNG: {e}")))
}

/// [`contact_sheet_png`] written to `png_out`.
pub fn contact_sheet(mcap_file: &Path, png_out: &Path) -> Result<(), SheetError> {
    let png = contact_sheet_png(mcap_file)?;
    std::fs::write(png_out, png).map_err(|source| SheetError::Io { path: png_out.display().to_string(), source })
}
