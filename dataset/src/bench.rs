//! `labrig dataset bench`: retrieval over a synthetic index of many episodes (written and read
//! back as Parquet like a real one), and index-building throughput on the episodes of a folder.

use crate::INDEX_VERSION;
use crate::retrieve::{self, Dim, Target, Thresholds};
use crate::row::{CAMERAS, CameraRow, IndexRow};
use rand::{Rng, SeedableRng};

/// `n` synthetic rows: cameras around a table in the paper's bins and elsewhere, objects over
/// the table, a few objects, primitives and colours.
pub fn synthetic(n: usize, seed: u64) -> Vec<IndexRow> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let objects = ["cube", "cup", "marker", "bowl", "towel", "drawer"];
    let primitives = ["pick", "place", "push", "pull", "open", "close"];
    let colours = ["red", "green", "blue", "yellow", "white", "black"];
    (0..n)
        .map(|i| {
            let cameras = CAMERAS
                .iter()
                .enumerate()
                .map(|(k, _)| {
                    if (2..4).contains(&k) {
                        // DROID has two external cameras: rs1/rs2 empty.
                        return CameraRow::default();
                    }
                    let r = rng.random_range(0.6..1.4);
                    let polar = rng.random_range(30.0f64..75.0).to_radians();
                    let az = rng.random_range(-180.0f64..180.0).to_radians();
                    let p = [0.5 + r * polar.sin() * az.cos(), r * polar.sin() * az.sin(), r * polar.cos()];
                    crate::dv::camera_row(
                        Some(format!("{k}{i}")),
                        Some([p[0], p[1], p[2], 0.0, 0.0, 0.0]),
                        [0.5, 0.0, 0.0],
                    )
                })
                .collect();
            let pick = |rng: &mut rand_chacha::ChaCha8Rng, v: &[&str]| Some(v[rng.random_range(0..v.len())].to_owned());
            IndexRow {
                index_version: INDEX_VERSION,
                episode_id: format!("SYN+op+{i}"),
                source_path: format!("/droid/{i}"),
                source_format: "droid_raw".into(),
                file_size: 1_000_000,
                success: Some(rng.random_bool(0.8)),
                lab: format!("LAB{}", i % 13),
                instruction: Some("synthetic".into()),
                length: rng.random_range(100..600),
                cameras,
                object_position: rng
                    .random_bool(0.9)
                    .then(|| [rng.random_range(0.2..0.9), rng.random_range(-0.5..0.5), rng.random_range(0.0..0.3)]),
                object: pick(&mut rng, &objects),
                primitive: pick(&mut rng, &primitives),
                colour: pick(&mut rng, &colours),
                ..IndexRow::default()
            }
        })
        .collect()
}

/// The align combinations the bench times.
pub fn combinations() -> Vec<Vec<Dim>> {
    vec![
        vec![Dim::Object],
        vec![Dim::CamPose],
        vec![Dim::ObjSpat],
        vec![Dim::Object, Dim::Skill],
        vec![Dim::Object, Dim::Skill, Dim::CamPose],
        vec![Dim::Object, Dim::Skill, Dim::CamPose, Dim::ObjTex, Dim::ObjSpat],
        vec![Dim::CamPose, Dim::ObjSpat],
    ]
}

/// A target in the middle of the synthetic distribution.
pub fn target() -> Target {
    Target {
        cameras: vec![[0.5, 0.8, 0.6]],
        setups: vec![],
        object_position: Some([0.55, 0.0, 0.1]),
        object: Some("cube".into()),
        skill: Some("place".into()),
        colour: Some("red".into()),
    }
}

/// Milliseconds of each of `runs` selections of `align` over `columns`, sorted, what was
/// kept, and the milliseconds of writing that selection's manifest (once).
pub fn time_retrieval(
    rows: &[IndexRow],
    columns: &retrieve::Columns,
    align: &[Dim],
    runs: usize,
) -> (Vec<f64>, usize, f64) {
    let t = target();
    let th = Thresholds::default();
    let mut ms = Vec::with_capacity(runs);
    let mut last = (Vec::new(), Vec::new());
    for _ in 0..runs {
        let t0 = std::time::Instant::now();
        last = retrieve::select(columns, &t, align, &th);
        ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    ms.sort_by(f64::total_cmp);
    let t0 = std::time::Instant::now();
    let m = retrieve::manifest(rows, &t, align, &th, &last.0, last.1);
    let manifest_ms = t0.elapsed().as_secs_f64() * 1e3;
    (ms, m.episodes.len(), manifest_ms)
}
