//! `labrig export droid` / `labrig import droid` on the committed episode fixture: the export
//! is DROID's raw layout as h5py, json and ffprobe read it (tests/peers/check_droid.py);
//! export -> import -> export gives the same trajectory.h5 and metadata; the imported episode
//! inspects clean and replays against the sim exactly; bad input is named.

use labrig_tests::{cache_dir, check_droid_with_python as check_droid, labrig_bin, repo_root, workspace_bin};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixture() -> PathBuf {
    repo_root().join("tests/fixtures/episodes/pick_place_seed7")
}

fn labrig(args: &[&str]) -> Output {
    workspace_bin("labrig-droid", "labrig-droid"); // `labrig export|import droid` runs it
    Command::new(labrig_bin()).args(args).output().unwrap()
}

fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "exit {:?}\nstdout: {}\nstderr: {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn failed(out: &Output) -> String {
    assert!(!out.status.success(), "expected a failure, got: {}", String::from_utf8_lossy(&out.stdout));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The one episode directory under a DROID or MCAP root.
fn only_episode(root: &Path, file: &str) -> PathBuf {
    let mut found = Vec::new();
    let mut stack = vec![root.to_owned()];
    while let Some(d) = stack.pop() {
        if d.join(file).is_file() {
            found.push(d.clone());
        }
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            if e.path().is_dir() {
                stack.push(e.path());
            }
        }
    }
    assert_eq!(found.len(), 1, "{found:?}");
    found.remove(0)
}

fn metadata_json(dir: &Path) -> PathBuf {
    std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.file_name().unwrap().to_str().unwrap().starts_with("metadata_"))
        .unwrap()
}

#[test]
fn the_export_is_droid_s_raw_layout() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("droid");
    let text = ok(&labrig(&["export", "droid", fixture().to_str().unwrap(), out.to_str().unwrap()]));
    assert!(text.contains("exported") && text.contains("50 steps, 5 cameras"), "{text}");
    let (good, reports, problems) = check_droid(&out);
    assert!(good, "{problems}");
    assert_eq!(reports.len(), 1);
    let r = &reports[0];
    assert_eq!(r["steps"], 50);
    assert_eq!(r["serials"], serde_json::json!(["ext1", "ext2", "rs1", "rs2", "wrist"]));
    for (serial, v) in r["mp4"].as_object().unwrap() {
        assert_eq!(v["frames"], 50, "{serial}");
        assert_eq!(v["codec"], "h264", "{serial}");
    }
    // The fixture ended on its step budget: DROID's failure/ side, both flags.
    assert!(r["dir"].as_str().unwrap().starts_with("failure/"), "{r}");
    assert!(r["hand_extrinsics_error"].as_f64().unwrap() < 1e-9);
    // The checker fails when the layout is broken (so it can fail).
    let ep = only_episode(&out, "trajectory.h5");
    std::fs::remove_file(ep.join("recordings/MP4/rs1.mp4")).unwrap();
    let (good, _, problems) = check_droid(&out);
    assert!(!good && problems.contains("no recordings/MP4/rs1.mp4"), "{problems}");
}

#[test]
fn export_import_export_is_identical_and_the_import_replays_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, mcap, b) = (tmp.path().join("a"), tmp.path().join("mcap"), tmp.path().join("b"));
    ok(&labrig(&["export", "droid", fixture().to_str().unwrap(), a.to_str().unwrap()]));
    // A root with one DROID episode under it: found by the directory walk.
    let text = ok(&labrig(&["import", "droid", a.to_str().unwrap(), "--out", mcap.to_str().unwrap()]));
    assert!(text.contains("imported") && text.contains("50 steps, 5 cameras"), "{text}");
    assert!(!text.contains("warning"), "{text}");
    let imported = only_episode(&mcap, "episode_0.mcap");
    ok(&labrig(&["export", "droid", imported.to_str().unwrap(), b.to_str().unwrap(), "--json"]));
    let (ea, eb) = (only_episode(&a, "trajectory.h5"), only_episode(&b, "trajectory.h5"));
    assert_eq!(ea.strip_prefix(&a).unwrap(), eb.strip_prefix(&b).unwrap(), "same DROID directory");
    let (ha, hb) = (std::fs::read(ea.join("trajectory.h5")).unwrap(), std::fs::read(eb.join("trajectory.h5")).unwrap());
    assert!(ha.len() > 50_000, "a real trajectory.h5: {} bytes", ha.len());
    assert!(ha == hb, "trajectory.h5 differs after export -> import -> export");
    assert_eq!(std::fs::read(metadata_json(&ea)).unwrap(), std::fs::read(metadata_json(&eb)).unwrap());
    let (good, reports, problems) = check_droid(&b);
    assert!(good, "{problems}");
    assert_eq!(reports[0]["mp4"]["wrist"]["frames"], 50);

    // Every step keeps its frame: one image per step and camera, stamped with the capture
    // time the step names (the fixture's first step had none of its own: it was exported with
    // the camera's first frame, and imported as such, not dropped).
    let steps = labrig_episode::read_episode(&imported).unwrap().steps;
    assert_eq!(steps.len(), 50);
    let images = labrig_tests::camera_images(&imported.join("episode_0.mcap"));
    assert_eq!(images.len(), 5, "{:?}", images.keys().collect::<Vec<_>>());
    for (cam, imgs) in &images {
        assert_eq!(imgs.len(), 50, "camera {cam}: {} images for 50 steps", imgs.len());
        for (i, (stamp, _)) in imgs.iter().enumerate() {
            let want = steps[i].cameras.iter().find(|c| &c.camera_id == cam).map(|c| c.capture_ns);
            assert_eq!(Some(*stamp), want, "camera {cam}, step {i}");
        }
    }
    let c = tmp.path().join("c");
    let text = ok(&labrig(&["export", "droid", fixture().to_str().unwrap(), c.to_str().unwrap(), "--json"]));
    let report: Value = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    assert_eq!(report["frames_filled"], 5, "the fixture's first step, filled for each camera, is counted: {report}");

    // The imported episode is a whole labrig episode: inspect finds nothing to flag...
    let out = Command::new(labrig_bin()).arg("inspect").arg(&imported).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    // ...and it carries its sim scene, so it replays, state for state.
    workspace_bin("labrig-sim", "labrig-sim");
    let out = Command::new(labrig_bin()).arg("replay").arg(&imported).args(["--sim", "--json"]).output().unwrap();
    let r: Value = serde_json::from_slice(&ok(&out).into_bytes()).unwrap();
    assert_eq!(r["steps"], 50);
    let joints = r["joint_rad"].as_array().unwrap().iter().map(|e| e["max"].as_f64().unwrap());
    let worst = joints.chain(["tcp_m", "gripper"].map(|k| r[k]["max"].as_f64().unwrap())).fold(0.0, f64::max);
    assert!(worst < 1e-9, "imported episode replays with error {worst}");
}

#[test]
fn bad_input_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let out = t.join("out");
    let s = |p: &Path| p.to_str().unwrap().to_owned();

    let e = failed(&labrig(&["export", "parquet", "x", "y"]));
    assert!(e.contains("unknown format `parquet`"), "{e}");

    let foreign = t.join("foreign.mcap");
    std::fs::write(&foreign, b"PK\x03\x04 a zip, not an episode").unwrap();
    let e = failed(&labrig(&["export", "droid", &s(&foreign), &s(&out)]));
    assert!(e.contains("not an MCAP file"), "{e}");

    // A recorder killed mid-episode: the file has no summary.
    let whole = std::fs::read(fixture().join("episode_0.mcap")).unwrap();
    let cut = t.join("cut/episode_0.mcap");
    std::fs::create_dir_all(cut.parent().unwrap()).unwrap();
    std::fs::write(&cut, &whole[..whole.len() / 2]).unwrap();
    let e = failed(&labrig(&["export", "droid", &s(cut.parent().unwrap()), &s(&out)]));
    assert!(e.contains("not finished") && e.contains("labrig recover"), "{e}");

    let empty = t.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = failed(&labrig(&["export", "droid", &s(&empty), &s(&out)]));
    assert!(e.contains("no episodes (directories holding episode_0.mcap) under it"), "{e}");
    let e = failed(&labrig(&["import", "droid", &s(&empty), "--out", &s(&out)]));
    assert!(e.contains("no episodes found"), "{e}");

    // Exported twice: the first stays unless --overwrite.
    ok(&labrig(&["export", "droid", &s(&fixture()), &s(&out)]));
    let e = failed(&labrig(&["export", "droid", &s(&fixture()), &s(&out)]));
    assert!(e.contains("holds this episode already") && e.contains("--overwrite"), "{e}");
    ok(&labrig(&["export", "droid", &s(&fixture()), &s(&out), "--overwrite"]));
    let ep = only_episode(&out, "trajectory.h5");

    // DROID episodes with parts missing.
    let copy = |name: &str| {
        let d = t.join(name);
        std::fs::create_dir_all(d.join("recordings/MP4")).unwrap();
        for f in std::fs::read_dir(&ep).unwrap().flatten().filter(|f| f.path().is_file()) {
            std::fs::copy(f.path(), d.join(f.file_name())).unwrap();
        }
        for f in std::fs::read_dir(ep.join("recordings/MP4")).unwrap().flatten() {
            std::fs::copy(f.path(), d.join("recordings/MP4").join(f.file_name())).unwrap();
        }
        d
    };
    let no_json = copy("no_json");
    std::fs::remove_file(metadata_json(&no_json)).unwrap();
    let e = failed(&labrig(&["import", "droid", &s(&no_json), "--out", &s(&t.join("m1"))]));
    assert!(e.contains("no metadata_<uuid>.json"), "{e}");

    let not_h5 = copy("not_h5");
    std::fs::write(not_h5.join("trajectory.h5"), b"not hdf5 at all").unwrap();
    let e = failed(&labrig(&["import", "droid", &s(&not_h5), "--out", &s(&t.join("m2"))]));
    assert!(e.contains("trajectory.h5: opening it as HDF5"), "{e}");

    // A trajectory without the actions (deleted with h5py, DROID's own reader).
    let no_action = copy("no_action");
    let python = std::env::var_os("LABRIG_DROID_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache_dir().join("venv-droid/bin/python"));
    let script = "import h5py, sys\nwith h5py.File(sys.argv[1], 'a') as f:\n    del f['action/joint_position']\n";
    let st = Command::new(python).args(["-c", script]).arg(no_action.join("trajectory.h5")).status().unwrap();
    assert!(st.success());
    let e = failed(&labrig(&["import", "droid", &s(&no_action), "--out", &s(&t.join("m3"))]));
    assert!(e.contains("no `action/joint_position`"), "{e}");

    // A camera's video missing: imported without its images, and said so.
    let no_video = copy("no_video");
    std::fs::remove_file(no_video.join("recordings/MP4/ext2.mp4")).unwrap();
    let text = ok(&labrig(&["import", "droid", &s(&no_video), "--out", &s(&t.join("m4"))]));
    assert!(text.contains("warning: camera ext2 (ext2): no") && text.contains("imported without images"), "{text}");
    // Nothing is written for an episode that cannot be imported.
    for m in ["m1", "m2", "m3"] {
        assert!(!t.join(m).exists(), "{m}");
    }
}
