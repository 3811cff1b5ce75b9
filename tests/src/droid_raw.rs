//! The DROID raw fixture the dataset tests index: two camera regions x two object regions,
//! three episodes each (the third unsuccessful), one episode that names no object, written by
//! tests/peers/make_droid_raw.py (h5py, in scripts/setup.sh's venv-droid), and one damaged
//! episode (its trajectory is not HDF5): 14 sources, 13 readable.

use crate::{cache_dir, repo_root};
use serde_json::json;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// The external camera poses (DROID's 6-vector extrinsics) of the two camera regions.
pub const CAMS: [[f64; 6]; 2] = [[0.3, 0.6, 0.5, -2.3, 0.0, -1.6], [1.1, -0.5, 0.5, -2.3, 0.0, 2.4]];
/// Where the object is grasped in the two object regions.
pub const OBJECTS: [[f64; 3]; 2] = [[0.5, 0.1, 0.05], [0.5, 0.5, 0.05]];

/// The episode id of camera region `cam`, object region `obj`, episode `k`.
pub fn uuid(cam: usize, obj: usize, k: usize) -> String {
    format!("FIX+op+c{cam}o{obj}k{k}")
}

/// The venv-droid Python (h5py, pyarrow).
pub fn droid_python() -> PathBuf {
    let p = std::env::var_os("LABRIG_DROID_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache_dir().join("venv-droid/bin/python"));
    assert!(p.exists(), "the venv {} is missing: run `bash scripts/setup.sh`", p.display());
    p
}

/// Writes the fixture under `root`.
pub fn write(root: &Path) {
    let mut eps = Vec::new();
    for (c, cam) in CAMS.iter().enumerate() {
        for (o, obj) in OBJECTS.iter().enumerate() {
            for k in 0..3 {
                eps.push(json!({
                    "name": format!("c{c}o{o}k{k}"), "success": k != 2, "uuid": uuid(c, o, k),
                    "task": "Put the red cube in the bin", "steps": 80,
                    "ext1": cam, "ext2": [0.5, -0.9, 0.7, -2.0, 0.0, 0.0],
                    "grasp_step": 40, "grasp_xyz": obj, "accidental_step": 12, "decoy_xyz": [0.9, 0.9, 0.3],
                }));
            }
        }
    }
    eps.push(json!({
        "name": "wipe", "success": true, "uuid": "FIX+op+wipe", "task": "wipe the table", "steps": 30,
        "ext1": CAMS[0], "ext2": CAMS[0], "grasp_step": null, "grasp_xyz": [0, 0, 0],
    }));
    let mut child = Command::new(droid_python())
        .arg(repo_root().join("tests/peers/make_droid_raw.py"))
        .arg(root)
        .stdin(Stdio::piped())
        .spawn()
        .unwrap();
    child.stdin.take().unwrap().write_all(serde_json::to_string(&eps).unwrap().as_bytes()).unwrap();
    assert!(child.wait().unwrap().success(), "make_droid_raw.py failed");
    let bad = root.join("success/2026-11-26/damaged");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(bad.join("trajectory.h5"), b"not hdf5").unwrap();
    std::fs::write(bad.join("metadata_FIX+op+bad.json"), r#"{"uuid": "FIX+op+bad"}"#).unwrap();
}
