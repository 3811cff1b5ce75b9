//! `labrig export droid-mcap` / `labrig import droid-mcap`: DROID's own MCAP layout.
//!
//! - The committed fixture exported to DROID's MCAP layout is read by an independent reader
//!   (tests/peers/read_droid_mcap.py: the PyPI `mcap` reader + json), every value of its wrapped
//!   topics equal to the fixture's trajectory.h5 as h5py reads it; imported back, its DROID raw
//!   export is byte for byte the fixture's, and its images are the same JPEGs.
//! - Files written the way DROID's tools write them (tests/peers/make_droid_mcap.py: h5py and
//!   the PyPI `mcap` writer, both upstream variants, DROID's millisecond log times) import.
//! - Bad input is named, and nothing is written for it.

use labrig_tests::{cache_dir, labrig_bin, repo_root, workspace_bin};
use serde_json::Value;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixture() -> PathBuf {
    repo_root().join("tests/fixtures/episodes/pick_place_seed7")
}

fn labrig(args: &[&str]) -> Output {
    workspace_bin("labrig-droid", "labrig-droid");
    Command::new(labrig_bin()).args(args).output().unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn ok(out: &Output) -> String {
    assert!(out.status.success(), "{}", labrig_tests::output_text(out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn failed(out: &Output) -> String {
    assert!(!out.status.success(), "expected a failure: {}", labrig_tests::output_text(out));
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A tests/peers script under venv-droid (h5py + the PyPI `mcap`), its stdout as JSON.
fn py(script: &str, args: &[&str]) -> Value {
    let python = cache_dir().join("venv-droid/bin/python");
    assert!(python.exists(), "{} is missing: run `bash scripts/setup.sh`", python.display());
    let out = Command::new(python).arg(repo_root().join("tests/peers").join(script)).args(args).output().unwrap();
    assert!(out.status.success(), "{script}: {}", labrig_tests::output_text(&out));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{script}: {e}: {}", labrig_tests::output_text(&out)))
}

/// The one file named `name` under `root`.
fn only_file(root: &Path, name: &str) -> PathBuf {
    let mut found = Vec::new();
    let mut stack = vec![root.to_owned()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.file_name().is_some_and(|n| n == name) {
                found.push(p);
            }
        }
    }
    assert_eq!(found.len(), 1, "{name} under {}: {found:?}", root.display());
    found.remove(0)
}

const CAMERAS: [&str; 5] = ["ext1", "ext2", "rs1", "rs2", "wrist"];

fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Each step's image sha256 per image topic, from read_droid_mcap.py's report.
fn images(r: &Value) -> Vec<Value> {
    r["steps"].as_array().unwrap().iter().map(|s| s["images"].clone()).collect()
}

#[test]
fn the_export_is_droid_s_mcap_layout_and_imports_back_to_the_same_episode() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    // The reference: the fixture's DROID raw export, read by h5py in the reader.
    ok(&labrig(&["export", "droid", s(&fixture()), s(&t.join("raw_a"))]));
    let h5 = only_file(&t.join("raw_a"), "trajectory.h5");

    let text = ok(&labrig(&["export", "droid-mcap", s(&fixture()), s(&t.join("mcap_a"))]));
    assert!(text.contains("50 steps, 5 cameras, 250 images"), "{text}");
    let file = only_file(&t.join("mcap_a"), "trajectory.mcap");
    assert!(
        file.parent().unwrap().strip_prefix(t.join("mcap_a")).unwrap().starts_with("failure"),
        "{}",
        file.display()
    );
    let r = py("read_droid_mcap.py", &[s(&file), "--h5", s(&h5)]);
    let steps = r["steps"].as_array().unwrap();
    assert_eq!(steps.len(), 50, "one timestep per step by log time");
    for (i, st) in steps.iter().enumerate() {
        let topics: BTreeSet<&str> = st["topics"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
        for want in ["/robot_state", "/action", "/camera_extrinsics", "/camera_intrinsics", "/camera_type"] {
            assert!(topics.contains(want), "step {i} has no {want}: {topics:?}");
        }
        assert_eq!(st["images"].as_object().unwrap().len(), 5, "step {i}: {st}");
    }
    let ch = &r["channels"];
    assert_eq!(
        (ch["/robot_state"]["schema"].as_str(), ch["/robot_state"]["schema_encoding"].as_str()),
        (Some("droid.RobotState"), Some("jsonschema"))
    );
    for cam in CAMERAS {
        let c = &ch[format!("/camera/{cam}_left/compressed")];
        assert_eq!(c["schema"], "foxglove.CompressedImage", "{ch}");
        assert_eq!((c["message_encoding"].as_str(), c["base64_declared"].as_bool()), (Some("json"), Some(true)), "{c}");
        assert_eq!(c["count"], 50);
    }
    // Every value of the wrapped topics is trajectory.h5's, exactly (h5py against json).
    let h = &r["h5"];
    assert!(h["compared"].as_u64().unwrap() >= 50 * 30, "{h}");
    assert_eq!(h["mismatches"], serde_json::json!([]), "{h}");
    let md = &r["metadata"];
    assert_eq!(md["current_task"]["value"], md["droid_metadata"]["current_task"], "{md}");
    assert!(md["droid_episode"]["uuid"].as_str().is_some_and(|u| !u.is_empty()), "{md}");

    // Imported back: a whole labrig episode whose DROID raw export is the fixture's, byte for byte.
    let text = ok(&labrig(&["import", "droid-mcap", s(&file), "--out", s(&t.join("eps"))]));
    assert!(text.contains("wrapped") && text.contains("50 steps, 5 cameras"), "{text}");
    assert!(!text.contains("warning"), "{text}");
    let imported = only_file(&t.join("eps"), "episode_0.mcap");
    let out = Command::new(labrig_bin()).arg("inspect").arg(&imported).output().unwrap();
    assert!(out.status.success(), "{}", labrig_tests::output_text(&out));
    // One image per step and camera, as the file had them (250 of 250), each the JPEG the file
    // had at that step, untouched.
    let imported_images = labrig_tests::camera_images(&imported);
    let source = images(&r);
    assert_eq!(source.len(), 50);
    for cam in CAMERAS {
        let got = &imported_images[cam];
        assert_eq!(got.len(), 50, "camera {cam}: {} images for 50 steps", got.len());
        for (i, (_, jpeg)) in got.iter().enumerate() {
            let want = source[i][format!("/camera/{cam}_left/compressed")].as_str().unwrap();
            assert_eq!(sha256_hex(jpeg), want, "camera {cam}, step {i}");
        }
    }
    ok(&labrig(&["export", "droid", s(&imported), s(&t.join("raw_b"))]));
    let h5_b = only_file(&t.join("raw_b"), "trajectory.h5");
    assert!(
        std::fs::read(&h5).unwrap() == std::fs::read(&h5_b).unwrap(),
        "trajectory.h5 differs after the MCAP round trip"
    );
    // ...and so is its metadata JSON (the episode's metadata went through the MCAP whole).
    let json_of = |dir: &Path| -> Vec<u8> {
        let p = std::fs::read_dir(dir)
            .unwrap()
            .flatten()
            .map(|e| e.path())
            .find(|p| p.file_name().unwrap().to_string_lossy().starts_with("metadata_"))
            .unwrap();
        std::fs::read(p).unwrap()
    };
    assert_eq!(json_of(h5.parent().unwrap()), json_of(h5_b.parent().unwrap()), "the metadata JSON differs");
    // The JPEGs went through untouched: exported again, the same image at every step.
    ok(&labrig(&["export", "droid-mcap", s(&imported), s(&t.join("mcap_b"))]));
    let r_b = py("read_droid_mcap.py", &[s(&only_file(&t.join("mcap_b"), "trajectory.mcap")), "--h5", s(&h5)]);
    assert_eq!(r_b["h5"]["mismatches"], serde_json::json!([]), "{}", r_b["h5"]);
    assert_eq!(images(&r_b), images(&r));
}

/// Synthetic JPEGs, one per camera and step (different each), as the peer script's input.
fn write_images(dir: &Path) {
    for (c, cam) in CAMERAS.iter().enumerate() {
        let d = dir.join(format!("{cam}_left"));
        std::fs::create_dir_all(&d).unwrap();
        for i in 0..50u32 {
            let (w, h) = (32u16, 24u16);
            let px: Vec<u8> = (0..w as u32 * h as u32)
                .flat_map(|k| [(k * 7 + i * 13) as u8, (c as u32 * 50 + i) as u8, (k / 32 * 9) as u8])
                .collect();
            let jpeg = labrig_episode::jpeg::encode_rgb(&px, w, h, 90).unwrap();
            std::fs::write(d.join(format!("{i}.jpg")), jpeg).unwrap();
        }
    }
}

/// The fixture's trajectory.h5 (its DROID raw export) and synthetic JPEGs for it, under `t`.
fn h5_and_images(t: &Path) -> (PathBuf, PathBuf) {
    ok(&labrig(&["export", "droid", s(&fixture()), s(&t.join("raw"))]));
    let imgs = t.join("images");
    write_images(&imgs);
    (only_file(&t.join("raw"), "trajectory.h5"), imgs)
}

#[test]
fn files_written_as_droid_s_tools_write_them_import_in_both_variants() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let (h5, imgs) = h5_and_images(t);
    for variant in ["wrapped", "flat"] {
        let file = t.join(format!("{variant}.mcap"));
        let mut args = vec![s(&h5), s(&file), "--images", s(&imgs), "--variant", variant];
        if variant == "flat" {
            args.push("--vr");
        }
        let made = py("make_droid_mcap.py", &args);
        assert_eq!(made["steps"], 50);
        let eps = t.join(format!("eps_{variant}"));
        let out = ok(&labrig(&["import", "droid-mcap", s(&file), "--out", s(&eps), "--json"]));
        let r: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
        assert_eq!((r["variant"].as_str(), r["steps"].as_u64()), (Some(variant), Some(50)), "{r}");
        assert_eq!(r["times_in_ms"], true, "DROID's log times are milliseconds: {r}");
        assert_eq!(r["cameras"].as_array().unwrap().len(), 5, "{r}");
        assert!(r["frames"].as_u64().unwrap() > 0, "{r}");
        let imported = only_file(&eps, "episode_0.mcap");
        let o = Command::new(labrig_bin()).arg("inspect").arg(&imported).output().unwrap();
        assert!(o.status.success(), "{variant}: {}", labrig_tests::output_text(&o));
        // Exported again, read by the independent reader against the h5 it came from.
        let again = t.join(format!("again_{variant}"));
        ok(&labrig(&["export", "droid-mcap", s(&imported), s(&again)]));
        let back = py("read_droid_mcap.py", &[s(&only_file(&again, "trajectory.mcap")), "--h5", s(&h5)]);
        let mismatched: Vec<&str> =
            back["h5"]["mismatched_keys"].as_array().unwrap().iter().map(|k| k.as_str().unwrap()).collect();
        if variant == "wrapped" {
            assert!(mismatched.is_empty(), "{}", back["h5"]);
        } else {
            // The flat writer carries the state and DROID's 7-vector action: those are exact.
            for key in [
                "observation/robot_state/joint_positions",
                "observation/robot_state/joint_velocities",
                "observation/robot_state/cartesian_position",
                "observation/robot_state/gripper_position",
                "action/cartesian_velocity",
                "action/gripper_velocity",
            ] {
                assert!(!mismatched.contains(&key), "{key}: {}", back["h5"]);
            }
            assert!(out.contains("next step's observed state"), "the derived action keys are said: {out}");
            // The Quest's state went in as /teleop/state and came out as /vr_controller again.
            let sent = made["vr"].as_array().unwrap();
            assert_eq!(sent.len(), 50);
            for (i, st) in back["steps"].as_array().unwrap().iter().enumerate() {
                let (got, want) = (&st["vr"], &sent[i]);
                for k in ["movement_enabled", "controller_on", "success", "failure"] {
                    assert_eq!(got[k], want[k], "step {i} {k}: {got} against {want}");
                }
                for k in ["A", "RG", "RJ", "rightTrig", "rightGrip", "rightJS"] {
                    assert_eq!(got["buttons"][k], want["buttons"][k], "step {i} {k}: {got} against {want}");
                }
                let (g, w) = (got["poses"]["r"].as_array().unwrap(), want["poses"]["r"].as_array().unwrap());
                let worst =
                    g.iter().zip(w).map(|(a, b)| (a.as_f64().unwrap() - b.as_f64().unwrap()).abs()).fold(0.0, f64::max);
                assert!(g.len() == 16 && worst < 1e-12, "step {i}: the pose came back {worst} off");
            }
        }
        // The import keeps each step's image exactly: 50 per camera, each the JPEG the file had
        // at that step.
        let sent = &made["images"];
        let imported_images = labrig_tests::camera_images(&imported);
        for cam in CAMERAS {
            let got = &imported_images[cam];
            assert_eq!(got.len(), 50, "{variant} {cam}: {} images for 50 steps", got.len());
            for (i, (_, jpeg)) in got.iter().enumerate() {
                assert_eq!(sha256_hex(jpeg), sent[cam][i].as_str().unwrap(), "{variant} step {i} {cam}");
            }
        }
        // Exported again, each step's image is the one the file had at that step, except where
        // the step names its predecessor's capture time (a reused frame): the export writes a
        // capture's frame once, so such a step gets the predecessor's. Those steps are counted
        // from the steps themselves, and are the only ones allowed to differ.
        let steps = labrig_episode::read_episode(&imported).unwrap().steps;
        assert_eq!(steps.len(), 50);
        let back_images = images(&back);
        assert_eq!(back_images.len(), 50);
        for cam in CAMERAS {
            let capture = |i: usize| steps[i].cameras.iter().find(|c| c.camera_id == cam).map(|c| c.capture_ns);
            let mut reused = 0;
            for (i, st) in back_images.iter().enumerate() {
                let got = st[format!("/camera/{cam}_left/compressed")].as_str().unwrap();
                if got != sent[cam][i].as_str().unwrap() {
                    assert!(i > 0 && capture(i) == capture(i - 1), "{variant} step {i} {cam}: another step's image");
                    assert_eq!(got, sent[cam][i - 1].as_str().unwrap(), "{variant} step {i} {cam}");
                    reused += 1;
                }
            }
            assert!(reused <= 5, "{variant} {cam}: {reused} steps exported with their predecessor's image");
        }
    }
}

#[test]
fn bad_droid_mcap_input_is_named_and_nothing_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let (h5, imgs) = h5_and_images(t);
    let out = t.join("out");
    for (bad, variant, says) in [
        ("no_robot_state", "wrapped", "has no /robot_state"),
        ("no_robot_state", "flat", "has no /robot_state"),
        ("bad_image", "wrapped", "the image is not a whole JPEG"),
        ("not_droid", "wrapped", "no /robot_state channel: not DROID's MCAP layout"),
    ] {
        let file = t.join(format!("{bad}_{variant}.mcap"));
        py("make_droid_mcap.py", &[s(&h5), s(&file), "--images", s(&imgs), "--variant", variant, "--bad", bad]);
        let e = failed(&labrig(&["import", "droid-mcap", s(&file), "--out", s(&out)]));
        assert!(e.contains(says) && e.contains(s(&file)), "{bad} ({variant}): {e}");
    }
    // A labrig episode is not DROID's layout; a zip is not MCAP; a directory without any.
    // LZ4 chunks (the Python writer's other codec): labrig's mcap reads zstd only, and says so.
    let lz4 = t.join("lz4.mcap");
    py("make_droid_mcap.py", &[s(&h5), s(&lz4), "--images", s(&imgs), "--lz4"]);
    let e = failed(&labrig(&["import", "droid-mcap", s(&lz4), "--out", s(&out)]));
    assert!(e.contains("its chunks are compressed with lz4, which labrig does not read"), "{e}");
    let e = failed(&labrig(&["import", "droid-mcap", s(&fixture().join("episode_0.mcap")), "--out", s(&out)]));
    assert!(e.contains("a labrig episode (ROS 2 CDR messages), not DROID's MCAP layout"), "{e}");
    let zip = t.join("x.mcap");
    std::fs::write(&zip, b"PK\x03\x04 a zip").unwrap();
    let e = failed(&labrig(&["import", "droid-mcap", s(&zip), "--out", s(&out)]));
    assert!(e.contains("not an MCAP file"), "{e}");
    let empty = t.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let e = failed(&labrig(&["import", "droid-mcap", s(&empty), "--out", s(&out)]));
    assert!(e.contains("no episodes found"), "{e}");
    assert!(!out.exists() || labrig_tests::episode_dirs(&out).is_empty(), "nothing written for bad input");
}

#[test]
fn dataset_index_reads_droid_mcap_files_beside_labrig_episodes() {
    workspace_bin("labrig-dataset", "labrig-dataset");
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let root = t.join("root");
    // A labrig episode, its DROID MCAP export (wrapped, with DROID's metadata JSON), a flat file
    // written as DROID's newer writer does, and a file that is not DROID's layout.
    let ep = root.join("labrig/pick_place_seed7");
    std::fs::create_dir_all(&ep).unwrap();
    for e in std::fs::read_dir(fixture()).unwrap().flatten() {
        std::fs::copy(e.path(), ep.join(e.file_name())).unwrap();
    }
    ok(&labrig(&["export", "droid-mcap", s(&fixture()), s(&root.join("droid_mcap"))]));
    let (h5, imgs) = h5_and_images(t);
    std::fs::create_dir_all(root.join("flat")).unwrap();
    py(
        "make_droid_mcap.py",
        &[s(&h5), s(&root.join("flat/trajectory.mcap")), "--images", s(&imgs), "--variant", "flat"],
    );
    std::fs::write(root.join("notes.mcap"), b"not an mcap").unwrap();
    let out = ok(&labrig(&["dataset", "index", s(&root), "--out", s(&t.join("index")), "--json"]));
    let r: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    assert_eq!(r["by_format"], serde_json::json!({"droid_mcap": 2, "labrig": 1}), "{r}");
    let bad = r["bad"].as_array().unwrap();
    assert_eq!(bad.len(), 1, "{r}");
    assert!(bad[0]["reason"].as_str().unwrap().contains("not an MCAP file"), "{r}");
}

#[test]
fn a_manifest_names_the_episodes_to_export_and_droid_data_in_it_is_sent_to_its_import() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let list = t.join("episodes.txt");
    std::fs::write(&list, format!("# one episode\n{}\n", fixture().display())).unwrap();
    let text = ok(&labrig(&["export", "droid-mcap", s(&list), s(&t.join("out"))]));
    assert!(text.contains("50 steps, 5 cameras"), "{text}");
    only_file(&t.join("out"), "trajectory.mcap");
    // A retrieval manifest that lists a DROID MCAP file: refused with the command that converts it.
    let manifest = t.join("m.json");
    let entry = serde_json::json!({"episodes": [{"path": "x/trajectory.mcap", "format": "droid_mcap"}]});
    std::fs::write(&manifest, entry.to_string()).unwrap();
    let e = failed(&labrig(&["export", "droid-mcap", s(&manifest), s(&t.join("out2"))]));
    assert!(e.contains("x/trajectory.mcap is droid_mcap data: convert it first with `labrig import droid-mcap"), "{e}");
}
