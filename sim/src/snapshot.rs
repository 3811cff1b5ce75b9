//! `labrig sim snapshot`: one PNG per camera and the scene's sampled values as JSON, so a person
//! can look at the rig a spec + seed produce.

use crate::render::RenderedFrame;
use crate::{Meshes, SceneSpec, Sim, SimError};
use labrig_msgs::Nanos;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error("cannot write {path}: {message}")]
    Write { path: PathBuf, message: String },
}

/// Writes an RGB8 image as PNG.
pub fn write_png(path: &Path, width: usize, height: usize, rgb: &[u8]) -> Result<(), SnapshotError> {
    let fail = |message: String| SnapshotError::Write { path: path.to_owned(), message };
    let file = std::fs::File::create(path).map_err(|e| fail(e.to_string()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width as u32, height as u32);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(|e| fail(e.to_string()))?;
    writer.write_image_data(rgb).map_err(|e| fail(e.to_string()))?;
    writer.finish().map_err(|e| fail(e.to_string()))
}

/// Tiles frames of equal size into one image, `columns` across (row-major, RGB8).
pub fn contact_sheet(frames: &[RenderedFrame], columns: usize) -> (usize, usize, Vec<u8>) {
    let (w, h) = frames.first().map_or((0, 0), |f| (f.width, f.height));
    let rows = frames.len().div_ceil(columns.max(1));
    let (sw, sh) = (w * columns, h * rows);
    let mut sheet = vec![40u8; sw * sh * 3];
    for (i, f) in frames.iter().enumerate() {
        let (ox, oy) = ((i % columns) * w, (i / columns) * h);
        for y in 0..h {
            let src = &f.rgb[y * w * 3..(y + 1) * w * 3];
            let dst = ((oy + y) * sw + ox) * 3;
            sheet[dst..dst + w * 3].copy_from_slice(src);
        }
    }
    (sw, sh, sheet)
}

/// What `snapshot` wrote.
#[derive(Debug)]
pub struct Snapshot {
    pub images: Vec<PathBuf>,
    pub sheet: PathBuf,
    pub values: PathBuf,
}

/// Builds the scene, renders the five cameras at the reset pose and writes
/// `<out>/<camera>.png`, `<out>/cameras.png` (all five) and `<out>/scene.json`.
pub fn snapshot(
    assets: &Path,
    spec: &SceneSpec,
    seed: u64,
    out: &Path,
    size: (usize, usize),
    meshes: Meshes,
) -> Result<Snapshot, SnapshotError> {
    let mut sim = Sim::new(assets, spec, seed, Nanos::from_millis(50))?;
    sim.enable_cameras(size.0, size.1, meshes)?;
    let frames = sim.render_all()?;
    std::fs::create_dir_all(out).map_err(|e| SnapshotError::Write { path: out.to_owned(), message: e.to_string() })?;
    let mut images = Vec::new();
    for f in &frames {
        let path = out.join(format!("{}.png", f.camera));
        write_png(&path, f.width, f.height, &f.rgb)?;
        images.push(path);
    }
    let (w, h, sheet_rgb) = contact_sheet(&frames, 3);
    let sheet = out.join("cameras.png");
    write_png(&sheet, w, h, &sheet_rgb)?;
    let values = out.join("scene.json");
    let json = serde_json::json!({ "spec": spec, "values": sim.scene() });
    let text = serde_json::to_string_pretty(&json).expect("scene values serialise");
    std::fs::write(&values, text + "\n")
        .map_err(|e| SnapshotError::Write { path: values.clone(), message: e.to_string() })?;
    Ok(Snapshot { images, sheet, values })
}
