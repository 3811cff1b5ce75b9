//! `labrig export lerobot` read by LeRobot's own `LeRobotDataset` (offline, PyAV): format v3.0
//! by lerobot 0.4.4 (setup's venv-lerobot-data), v2.1 by lerobot 0.3.3 (venv-lerobot-v21, the
//! line openpi pins). Two demo episodes of the simulated rig, every frame iterated with an action
//! chunk of 16; state, action and timestamps equal labrig's steps, images within H.264's
//! tolerance of the recorded JPEGs, and the statistics labrig wrote equal what LeRobot computes
//! from the same frames.

use labrig_msgs::rig::Step;
use labrig_msgs::sensor_msgs::CompressedImage;
use labrig_tests::{cache_dir, domain_for, labrig_bin, lerobot_python, repo_root};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

/// Each camera's recorded JPEG by its capture stamp.
fn frames_of(file: &Path) -> BTreeMap<(String, i64), Vec<u8>> {
    let buf = std::fs::read(file).unwrap();
    let mut out = BTreeMap::new();
    for m in mcap::MessageStream::new(&buf).unwrap() {
        let m = m.unwrap();
        let Some(rest) = m.channel.topic.strip_prefix(labrig_msgs::topics::CAMERAS_PREFIX) else { continue };
        let Some(cam) = rest.strip_suffix("/image/compressed") else { continue };
        let img: CompressedImage = labrig_msgs::decode(&m.data).unwrap();
        out.insert((cam.to_owned(), labrig_msgs::Nanos::from(img.header.stamp).0), img.data);
    }
    out
}

/// 8x8 block means per channel of an RGB image, in [0, 1] (as the peer computes them).
fn blocks(rgb: &[u8], w: usize, h: usize) -> Vec<Vec<Vec<f64>>> {
    let (bh, bw) = (h / 8, w / 8);
    (0..3)
        .map(|c| {
            (0..8)
                .map(|by| {
                    (0..8)
                        .map(|bx| {
                            let mut s = 0.0;
                            for y in by * bh..(by + 1) * bh {
                                for x in bx * bw..(bx + 1) * bw {
                                    s += f64::from(rgb[(y * w + x) * 3 + c]);
                                }
                            }
                            s / (bh * bw) as f64 / 255.0
                        })
                        .collect()
                })
                .collect()
        })
        .collect()
}

fn f32s(v: &Value) -> Vec<f32> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
}

/// The Python of setup's lerobot 0.3.3 venv.
fn lerobot_v21_python() -> PathBuf {
    let p = std::env::var_os("LABRIG_LEROBOT_V21_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| cache_dir().join("venv-lerobot-v21/bin/python"));
    assert!(p.exists(), "{} is missing: run `bash scripts/setup.sh`", p.display());
    p
}

#[test]
fn lerobots_own_readers_load_exports_of_demo_episodes() {
    for p in ["labrig-sim", "labrig-recorder", "labrig-control"] {
        labrig_tests::workspace_bin(p, p);
    }
    labrig_tests::workspace_bin("labrig-dataset", "labrig-dataset");
    let dir = tempfile::tempdir().unwrap();
    let demo = dir.path().join("demo");
    let out = Command::new(labrig_bin())
        .args(["demo", "--episodes", "2", "--first-seed", "5", "--json"])
        .args(["--domain-id", &domain_for("lerobot_export_demo").to_string(), "--out"])
        .arg(&demo)
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("lerobot_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(out.status.success(), "demo: {}", labrig_tests::output_text(&out));
    let episodes: Vec<PathBuf> = {
        let mut v = labrig_episode::episode::find_episodes(&demo.join("episodes"));
        v.sort();
        v
    };
    assert_eq!(episodes.len(), 2);
    let data: Vec<(Vec<Step>, String, PathBuf)> = episodes
        .iter()
        .map(|e| {
            let d = labrig_episode::read_episode(e).unwrap();
            (d.steps, d.metadata.unwrap().task_instruction, d.file)
        })
        .collect();
    // An unfinished recording (its file cut short) beside them, all listed in a manifest.
    let broken = dir.path().join("broken");
    std::fs::create_dir_all(&broken).unwrap();
    let mcap = std::fs::read(episodes[0].join("episode_0.mcap")).unwrap();
    std::fs::write(broken.join("episode_0.mcap"), &mcap[..mcap.len() / 2]).unwrap();
    let manifest = dir.path().join("manifest.txt");
    // The broken one between the two: the second episode's videos move to its place (episodes
    // are exported in parallel, each first under its place in the input).
    let listed: Vec<String> = [&episodes[0], &broken, &episodes[1]].iter().map(|p| p.display().to_string()).collect();
    std::fs::write(&manifest, listed.join("\n") + "\n").unwrap();
    for (format, python, version) in [("v3.0", lerobot_python(), "0.4.4"), ("v2.1", lerobot_v21_python(), "0.3.3")] {
        let ds = dir.path().join(format!("lerobot_{format}"));
        let o = Command::new(labrig_bin())
            .args(["export", "lerobot", "--format", format, "--json"])
            .arg(&manifest)
            .arg(&ds)
            .output()
            .unwrap();
        // The bad episode is skipped and named (exit 2); the rest is a whole dataset.
        assert_eq!(o.status.code(), Some(2), "export {format}: {}", labrig_tests::output_text(&o));
        let report: Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(report["episodes"], 2, "{report}");
        let skipped = report["skipped"].as_array().unwrap();
        assert_eq!(skipped.len(), 1, "{report}");
        assert_eq!(skipped[0][0], broken.display().to_string());
        assert!(skipped[0][1].as_str().unwrap().contains("not finished"), "{report}");
        assert!(!dir.path().join(format!("lerobot_{format}.partial")).exists());
        // An existing output is refused, not mixed into.
        let again = Command::new(labrig_bin()).args(["export", "lerobot"]).args(&episodes).arg(&ds).output().unwrap();
        assert_eq!(again.status.code(), Some(1));
        assert!(labrig_tests::output_text(&again).contains("exists: choose another output or pass --overwrite"));
        check(&ds, &python, version, format, &data, dir.path());
        round_trip(&ds, format, &data, &dir.path().join(format!("back_{format}")));
    }
    // The same two episodes in openpi's DROID schema and in labrig's, trained by lerobot-train.
    openpi_droid_schema(&demo.join("episodes"), &data, dir.path());
    trains_in_lerobot_and_comes_back(&demo.join("episodes"), &data, dir.path());
}

/// `labrig dataset index <roots>` into `out`, its rows as JSON objects (read with pyarrow).
fn index_rows(roots: &[&Path], out: &Path) -> Vec<serde_json::Map<String, Value>> {
    let o = Command::new(labrig_bin()).args(["dataset", "index"]).args(roots).arg("--out").arg(out).output().unwrap();
    assert!(o.status.success(), "index: {}", labrig_tests::output_text(&o));
    let py = "import json,sys,glob,pyarrow.parquet as pq\n\
              rows=[r for f in sorted(glob.glob(sys.argv[1]+'/*.parquet')) for r in pq.read_table(f).to_pylist()]\n\
              print(json.dumps(sorted(rows,key=lambda r:r['episode_id'])))";
    let o = Command::new(lerobot_python()).args(["-c", py]).arg(out).output().unwrap();
    assert!(o.status.success(), "reading the index: {}", labrig_tests::output_text(&o));
    serde_json::from_slice::<Vec<Value>>(&o.stdout)
        .unwrap()
        .into_iter()
        .map(|v| v.as_object().unwrap().clone())
        .collect()
}

/// The export at `ds` imported back (`labrig import lerobot`) equals what labrig recorded: the
/// steps' state and actions (at LeRobot's float32), the metadata whole, each step's frame within
/// the codecs' tolerance; and an imported episode replays in the sim as the original did.
fn round_trip(ds: &Path, format: &str, data: &[(Vec<Step>, String, PathBuf)], out: &Path) {
    let o = Command::new(labrig_bin()).args(["import", "lerobot", "--json"]).arg(ds).arg(out).output().unwrap();
    assert!(o.status.success(), "import {format}: {}", labrig_tests::output_text(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["version"], format);
    // labrig's export carries every DROID key: nothing was left at zero.
    assert_eq!(report["absent"], serde_json::json!({}), "{report}");
    let imported = report["episodes"].as_array().unwrap();
    assert_eq!(imported.len(), 2, "{report}");
    let f = |x: f64| x as f32;
    for (k, row) in imported.iter().enumerate() {
        let (steps, _, file) = &data[k];
        let dir = PathBuf::from(row[1].as_str().unwrap());
        let back = labrig_episode::read_episode(&dir).unwrap();
        let (orig_meta, back_meta) =
            (labrig_episode::read_episode(file.parent().unwrap()).unwrap().metadata.unwrap(), back.metadata.unwrap());
        assert_eq!(back_meta, orig_meta, "{format} episode {k}: the metadata");
        assert_eq!(back.steps.len(), steps.len());
        for (i, (a, b)) in steps.iter().zip(&back.steps).enumerate() {
            let at = format!("{format} episode {k} step {i}");
            assert_eq!(b.episode_id, a.episode_id, "{at}");
            assert_eq!(b.robot_state.joint_positions.map(f), a.robot_state.joint_positions.map(f), "{at}");
            assert_eq!(f(b.robot_state.gripper_position), f(a.robot_state.gripper_position), "{at}");
            assert_eq!(b.robot_state.cartesian_position.map(f), a.robot_state.cartesian_position.map(f), "{at}");
            let (x, y) = (&a.action, &b.action);
            assert_eq!(y.joint_position.map(f), x.joint_position.map(f), "{at}");
            assert_eq!(f(y.gripper_position), f(x.gripper_position), "{at}");
            assert_eq!(y.cartesian_position.map(f), x.cartesian_position.map(f), "{at}");
            assert_eq!(y.cartesian_velocity.map(f), x.cartesian_velocity.map(f), "{at}");
            assert_eq!(y.joint_velocity.map(f), x.joint_velocity.map(f), "{at}");
            assert_eq!(f(y.gripper_velocity), f(x.gripper_velocity), "{at}");
            // Steps on LeRobot's grid from the episode's start.
            let t = labrig_msgs::Nanos::from(b.header.stamp).0;
            assert_eq!(t, orig_meta.start_ns + i as i64 * 50_000_000, "{at}");
        }
        // Images: every step's frame, imported (MP4 -> JPEG) against the recorded JPEG.
        let (ours, theirs) = (frames_of(file), frames_of(&back.file));
        let mut compared = 0;
        for (i, (a, b)) in steps.iter().zip(&back.steps).enumerate() {
            for r in &b.cameras {
                let orig = a.cameras.iter().find(|c| c.camera_id == r.camera_id).expect("the camera");
                let decode = |j: &Vec<u8>| {
                    let img = labrig_episode::jpeg::decode_rgb(j).unwrap();
                    blocks(&img.pixels, img.width as usize, img.height as usize)
                };
                let x = decode(&ours[&(r.camera_id.clone(), orig.capture_ns)]);
                let y = decode(&theirs[&(r.camera_id.clone(), r.capture_ns)]);
                let worst = x
                    .iter()
                    .flatten()
                    .flatten()
                    .zip(y.iter().flatten().flatten())
                    .map(|(p, q)| (p - q).abs())
                    .fold(0.0, f64::max);
                assert!(worst < 0.04, "{format} episode {k} step {i} {}: block means differ by {worst}", r.camera_id);
                compared += 1;
            }
        }
        assert_eq!(compared, steps.len() * 5);
    }
    if format != "v3.0" {
        // (The index and the replay read what the import gave, alike for both formats.)
        return;
    }
    // `labrig dataset index` reads the export in place as it reads the recorded episodes: the
    // same rows (the positions at LeRobot's float32), only the source differs.
    let originals: Vec<&Path> = data.iter().map(|(_, _, f)| f.parent().unwrap()).collect();
    let (a, b) =
        (index_rows(&originals, &out.with_extension("idx_orig")), index_rows(&[ds], &out.with_extension("idx_lr")));
    assert_eq!(a.len(), 2);
    assert_eq!(b.len(), 2);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(y["source_format"], "lerobot");
        let mut compared = 0;
        for (k, v) in x {
            if ["source_path", "source_format", "file_size", "file_mtime_ns"].contains(&k.as_str()) {
                continue;
            }
            match (v.as_f64(), y[k].as_f64()) {
                (Some(p), Some(q)) if v.is_f64() => {
                    assert!((p - q).abs() <= 1e-5 * (1.0 + p.abs()), "{format} index {k}: {p} vs {q}")
                }
                _ => assert_eq!(&y[k], v, "{format} index {k}"),
            }
            compared += 1;
        }
        assert!(compared > 40, "{compared} columns compared");
        assert!(x.iter().any(|(k, v)| k.starts_with("object") && v.is_f64()), "the object position is derived: {x:?}");
    }
    // The imported episode replays against its scene (carried in the metadata) as recorded.
    let first = PathBuf::from(imported[0][1].as_str().unwrap());
    let r = Command::new(labrig_bin()).args(["replay", "--sim"]).arg(&first).output().unwrap();
    let text = labrig_tests::output_text(&r);
    assert!(r.status.success() && text.contains("PASS"), "replay of an imported episode: {text}");
    assert!(text.contains("task success: recorded true, replayed true"), "{text}");
}

/// A dataset written by LeRobot's own writer (tests/peers/lerobot_write.py, the DROID port's
/// keys): v3.0 by lerobot 0.4.4 (episodes sharing one data file and one AV1 MP4 per camera, at
/// 20 fps), v2.1 by lerobot 0.3.3 (at the port's 15 fps). Every value imported equals what the
/// writer wrote, each frame is the one written for that step (seeking into the shared MP4), the
/// port's cameras get labrig's ids and its extrinsics land in the metadata; an imported episode
/// replays in the sim; bad requests are named.
#[test]
fn datasets_lerobot_wrote_import_and_replay() {
    labrig_tests::workspace_bin("labrig-dataset", "labrig-dataset");
    labrig_tests::workspace_bin("labrig-sim", "labrig-sim");
    let dir = tempfile::tempdir().unwrap();
    for (format, python, fps) in [("v3.0", lerobot_python(), 20u32), ("v2.1", lerobot_v21_python(), 15)] {
        let ds = dir.path().join(format!("written_{format}"));
        let truth_path = dir.path().join(format!("truth_{format}.json"));
        let o = Command::new(&python)
            .arg(repo_root().join("tests/peers/lerobot_write.py"))
            .arg(&ds)
            .args(["3", "30", &fps.to_string()])
            .arg(&truth_path)
            .env("HF_HUB_OFFLINE", "1")
            .env("HF_HOME", dir.path().join("hf"))
            .output()
            .unwrap();
        assert!(o.status.success(), "LeRobot's writer ({format}): {}", labrig_tests::output_text(&o));
        let truth: Value = serde_json::from_str(&std::fs::read_to_string(&truth_path).unwrap()).unwrap();
        let info: Value = serde_json::from_str(&std::fs::read_to_string(ds.join("meta/info.json")).unwrap()).unwrap();
        assert_eq!(info["codebase_version"], format);

        let out = dir.path().join(format!("imported_{format}"));
        let o = Command::new(labrig_bin()).args(["import", "lerobot", "--json"]).arg(&ds).arg(&out).output().unwrap();
        assert!(o.status.success(), "import {format}: {}", labrig_tests::output_text(&o));
        let report: Value = serde_json::from_slice(&o.stdout).unwrap();
        let ids: Vec<&str> = report["cameras"].as_array().unwrap().iter().map(|c| c["id"].as_str().unwrap()).collect();
        // Two videos and (ext2) images stored in the Parquet as PNG.
        assert_eq!(ids, ["ext1", "wrist", "ext2"], "{report}");
        let imported = report["episodes"].as_array().unwrap();
        assert_eq!(imported.len(), 3, "{report}");
        let dt = (1e9 / f64::from(fps)).round() as i64;
        for (k, row) in imported.iter().enumerate() {
            let want = &truth["episodes"][k];
            let back = labrig_episode::read_episode(Path::new(row[1].as_str().unwrap())).unwrap();
            let meta = back.metadata.as_ref().unwrap();
            assert_eq!(meta.task_instruction, want["task"].as_str().unwrap());
            assert_eq!(meta.extrinsics["ext1"].map(|x| x as f32).to_vec(), f32s(&want["extrinsics_ext1"]));
            assert_eq!(meta.camera_serials["ext1"], "exterior_1_left");
            // The port's is_episode_successful (the last episode written as a failure), building
            // and collector.
            assert_eq!(meta.success, want["success"].as_bool(), "{format} episode {k}");
            assert_eq!(meta.building, want["building"].as_str().unwrap());
            assert_eq!(meta.user, "c0ffee");
            let frames = want["frames"].as_array().unwrap();
            assert_eq!(back.steps.len(), frames.len());
            let jpegs = frames_of(&back.file);
            for (i, (s, w)) in back.steps.iter().zip(frames).enumerate() {
                let at = format!("{format} episode {k} frame {i}");
                let t = labrig_msgs::Nanos::from(s.header.stamp).0;
                assert_eq!(t - meta.start_ns, i as i64 * dt, "{at}");
                assert_eq!(s.robot_state.joint_positions.map(|x| x as f32).to_vec(), f32s(&w["joints"]), "{at}");
                assert_eq!(s.robot_state.gripper_position as f32, w["gripper"].as_f64().unwrap() as f32, "{at}");
                assert_eq!(s.robot_state.cartesian_position.map(|x| x as f32).to_vec(), f32s(&w["cartesian"]), "{at}");
                assert_eq!(s.action.joint_position.map(|x| x as f32).to_vec(), f32s(&w["action_joints"]), "{at}");
                assert_eq!(
                    s.action.cartesian_position.map(|x| x as f32).to_vec(),
                    f32s(&w["action_cartesian"]),
                    "{at}"
                );
                for (cam, key) in [("ext1", "ext1"), ("wrist", "wrist"), ("ext2", "ext2")] {
                    let r = s.cameras.iter().find(|c| c.camera_id == cam).expect("a frame per camera");
                    let img = labrig_episode::jpeg::decode_rgb(&jpegs[&(cam.to_owned(), r.capture_ns)]).unwrap();
                    let ours = blocks(&img.pixels, img.width as usize, img.height as usize);
                    let differ = |w: &Value| {
                        let theirs: Vec<Vec<Vec<f64>>> = serde_json::from_value(w[key].clone()).unwrap();
                        ours.iter()
                            .flatten()
                            .flatten()
                            .zip(theirs.iter().flatten().flatten())
                            .map(|(a, b)| (a - b).abs())
                            .fold(0.0, f64::max)
                    };
                    // AV1 (LeRobot's default) at 64x48 then JPEG: within 0.15 of the frame
                    // written for the step, and nearer it than the next frame written (a frame off
                    // by one moves the blue bar two rows, 0.3 in its blocks).
                    let worst = differ(w);
                    assert!(worst < 0.15, "{at} {cam}: block means differ by up to {worst}");
                    if let Some(next) = frames.get(i + 1) {
                        let other = differ(next);
                        assert!(worst < other, "{at} {cam}: nearer the next frame ({other}) than its own ({worst})");
                    }
                }
            }
        }
        // Indexed in place: one row per episode, the port's extrinsics and tasks.
        let rows = index_rows(&[&ds], &dir.path().join(format!("index_{format}")));
        assert_eq!(rows.len(), 3);
        for (k, r) in rows.iter().enumerate() {
            assert_eq!(r["source_format"], "lerobot");
            assert_eq!(r["instruction"], truth["episodes"][k]["task"]);
            assert_eq!(r["length"], 30);
            assert_eq!(r["ext1_serial"], "exterior_1_left");
            assert_eq!(r["ext1_x"].as_f64().unwrap() as f32, f32s(&truth["episodes"][k]["extrinsics_ext1"])[0]);
        }
        if format == "v3.0" {
            // No sim scene in a dataset LeRobot wrote: replayed against a named one, every step.
            let second = PathBuf::from(imported[1][1].as_str().unwrap());
            let r = Command::new(labrig_bin())
                .args(["replay", "--sim", "--json", "--scene", "pick_place", "--seed", "1"])
                .arg(&second)
                .output()
                .unwrap();
            let text = labrig_tests::output_text(&r);
            // The dataset's motions are synthetic (a TCP sliding along x), not the scene's: the
            // replay runs every step and says it deviated (exit 5), as it must; a crash is 101.
            assert_eq!(r.status.code(), Some(5), "replay: {text}");
            let replayed: Value = serde_json::from_slice(&r.stdout).unwrap_or_else(|e| panic!("{e}: {text}"));
            assert_eq!(replayed["steps"], 30, "every step replayed: {text}");
            assert_eq!(replayed["tcp_replayed"].as_array().map(Vec::len), Some(30), "{text}");
            // Only episode 1 asked for: named when it is missing.
            let bad = Command::new(labrig_bin())
                .args(["import", "lerobot", "--episodes", "1,7"])
                .arg(&ds)
                .arg(dir.path().join("none"))
                .output()
                .unwrap();
            assert_eq!(bad.status.code(), Some(1));
            assert!(
                labrig_tests::output_text(&bad).contains("no episode [7] in the dataset"),
                "{}",
                labrig_tests::output_text(&bad)
            );
            let one = Command::new(labrig_bin())
                .args(["import", "lerobot", "--json", "--episodes", "1"])
                .arg(&ds)
                .arg(dir.path().join("one"))
                .output()
                .unwrap();
            let r: Value = serde_json::from_slice(&one.stdout).unwrap();
            assert_eq!(r["episodes"].as_array().unwrap().len(), 1);
            assert_eq!(r["episodes"][0][0], 1);
            // Importing the same episodes again is refused, naming the episode already there.
            let again = Command::new(labrig_bin()).args(["import", "lerobot"]).arg(&ds).arg(&out).output().unwrap();
            let said = labrig_tests::output_text(&again);
            assert_eq!(again.status.code(), Some(1), "{said}");
            let first = Path::new(imported[0][1].as_str().unwrap()).file_name().unwrap().to_string_lossy().into_owned();
            assert!(said.contains("holds this episode already") && said.contains(&first), "{said}");
        }
    }
    // Not a dataset: said.
    let o = Command::new(labrig_bin())
        .args(["import", "lerobot"])
        .arg(dir.path())
        .arg(dir.path().join("x"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(labrig_tests::output_text(&o).contains("not a LeRobot dataset"), "{}", labrig_tests::output_text(&o));
}

/// LeRobot `version` at `python` reads the export at `ds` (`format`) as labrig recorded `data`.
fn check(ds: &Path, python: &Path, version: &str, format: &str, data: &[(Vec<Step>, String, PathBuf)], tmp: &Path) {
    let o = Command::new(python)
        .arg(repo_root().join("tests/peers/lerobot_read.py"))
        .arg(ds)
        .env("HF_HUB_OFFLINE", "1")
        .env("HF_DATASETS_OFFLINE", "1")
        .env("HF_HOME", tmp.join("hf"))
        .output()
        .unwrap();
    assert!(o.status.success(), "LeRobot {version}: {}", labrig_tests::output_text(&o));
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["lerobot"].as_str(), r["codebase_version"].as_str()), (Some(version), Some(format)));
    let total: usize = data.iter().map(|(s, _, _)| s.len()).sum();
    assert_eq!(
        (r["episodes"].as_u64(), r["frames"].as_u64(), r["fps"].as_u64()),
        (Some(2), Some(total as u64), Some(20))
    );
    assert_eq!(r["cameras"].as_array().unwrap().len(), 5, "{}", r["cameras"]);
    let frames = r["frames_data"].as_array().unwrap();
    let mut checked_images = 0;
    for f in frames {
        let (ep, k) = (f["episode"].as_u64().unwrap() as usize, f["frame"].as_u64().unwrap() as usize);
        let (steps, task, file) = &data[ep];
        let s = &steps[k];
        assert_eq!(f["timestamp"].as_f64().unwrap() as f32, k as f32 / 20.0, "episode {ep} frame {k}");
        assert_eq!(f["task"], task.as_str());
        let mut state: Vec<f32> = s.robot_state.joint_positions.iter().map(|&x| x as f32).collect();
        state.push(s.robot_state.gripper_position as f32);
        assert_eq!(f32s(&f["state"]), state, "episode {ep} frame {k}");
        // The chunk of 16: the next steps' actions, padded (repeating the last) past the end.
        let chunk = f["action"].as_array().unwrap();
        let pad = f["pad"].as_array().unwrap();
        for (i, row) in chunk.iter().enumerate() {
            let j = (k + i).min(steps.len() - 1);
            let mut a: Vec<f32> = steps[j].action.joint_position.iter().map(|&x| x as f32).collect();
            a.push(steps[j].action.gripper_position as f32);
            assert_eq!(f32s(row), a, "episode {ep} frame {k} chunk row {i}");
            assert_eq!(pad[i].as_bool(), Some(k + i >= steps.len()));
        }
        // Images: the frame the step used, decoded from its JPEG, against LeRobot's decode of the MP4.
        if let Some(b) = f.get("blocks") {
            let jpegs = frames_of(file);
            for (cam, theirs) in b.as_object().unwrap() {
                let id = cam.trim_start_matches("observation.images.");
                let r = s.cameras.iter().find(|c| c.camera_id == id).expect("the step used a frame");
                let jpeg = &jpegs[&(id.to_owned(), r.capture_ns)];
                let img = labrig_episode::jpeg::decode_rgb(jpeg).unwrap();
                let ours = blocks(&img.pixels, img.width as usize, img.height as usize);
                let theirs: Vec<Vec<Vec<f64>>> = serde_json::from_value(theirs.clone()).unwrap();
                let worst = ours
                    .iter()
                    .flatten()
                    .flatten()
                    .zip(theirs.iter().flatten().flatten())
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(worst < 0.03, "episode {ep} frame {k} {cam}: 8x8 block means differ by up to {worst}");
                checked_images += 1;
            }
        }
    }
    assert_eq!(checked_images, 2 * 3 * 5);

    // The statistics labrig wrote (meta/stats.json, as LeRobot loaded them) against LeRobot's own
    // computation from the frames it read; in v3.0 also each episode's (its episodes table).
    let mut compared = 0;
    if format == "v3.0" {
        let (theirs, ours) =
            (r["episode_stats_lerobot"].as_array().unwrap(), r["episode_stats_file"].as_array().unwrap());
        assert_eq!((theirs.len(), ours.len()), (2, 2));
        let mut per_episode = 0;
        for (t, o) in theirs.iter().zip(ours) {
            per_episode += compare_stats(t, o);
        }
        assert!(per_episode >= 2 * 16 * 10, "{per_episode} per-episode statistics compared");
        // The images' statistics are there too, shaped (3, 1, 1).
        let img = &ours[0]["observation.images.ext1"];
        assert_eq!(img["mean"].as_array().map(Vec::len), Some(3), "{img}");
        assert!(img["q99"][0][0][0].is_f64(), "{img}");
    }
    compared += compare_stats(&r["stats_lerobot"], &r["stats_file"]);
    // v3.0 carries the quantiles (10 statistics a feature), v2.1 min/max/mean/std/count.
    let per = if format == "v3.0" { 10 } else { 5 };
    assert!(compared >= 16 * per, "{format}: {compared} statistics compared");
}

/// LeRobot's statistics (`theirs`, computed from the frames) against labrig's (`ours`) for every
/// feature and statistic LeRobot computed; how many were compared.
fn compare_stats(theirs: &Value, ours: &Value) -> usize {
    let mut compared = 0;
    for (feature, t) in theirs.as_object().unwrap() {
        let o = &ours[feature];
        assert!(o.is_object(), "stats.json has no {feature}");
        for (stat, tv) in t.as_object().unwrap() {
            let (a, b): (Vec<f64>, Vec<f64>) = (
                serde_json::from_value(tv.clone()).unwrap(),
                serde_json::from_value(o[stat].clone()).unwrap_or_else(|_| panic!("{feature}/{stat}: {}", o[stat])),
            );
            assert_eq!(a.len(), b.len(), "{feature}/{stat}");
            let span: f64 = serde_json::from_value::<Vec<f64>>(t["max"].clone())
                .unwrap()
                .iter()
                .zip(serde_json::from_value::<Vec<f64>>(t["min"].clone()).unwrap())
                .map(|(hi, lo)| hi - lo)
                .fold(0.0, f64::max);
            // Histogram quantiles: within a bin (1/5000 of the range); the rest to float32.
            let tol = if stat.starts_with('q') { span / 2000.0 + 1e-6 } else { 1e-5 * (1.0 + span) };
            for (x, y) in a.iter().zip(&b) {
                assert!((x - y).abs() <= tol, "{feature}/{stat}: LeRobot {x} vs labrig {y} (tolerance {tol})");
            }
            compared += 1;
        }
    }
    compared
}

/// `--schema openpi-droid` (v2.1 by default) read as openpi's `pi05_droid_finetune` reads its
/// dataset (tests/peers/openpi_droid_read.py: LeRobot 0.3.3, its repack keys, a 16-step
/// `actions` chunk): the state is the joints + gripper, each chunk row the recorded joint
/// velocity + gripper position, the prompt the instruction, the three images uint8 HWC.
fn openpi_droid_schema(episodes: &Path, data: &[(Vec<Step>, String, PathBuf)], tmp: &Path) {
    let ds = tmp.join("openpi_droid");
    let o = Command::new(labrig_bin())
        .args(["export", "lerobot", "--schema", "openpi-droid", "--json"])
        .arg(episodes)
        .arg(&ds)
        .output()
        .unwrap();
    assert!(o.status.success(), "export: {}", labrig_tests::output_text(&o));
    let o = Command::new(lerobot_v21_python())
        .arg(repo_root().join("tests/peers/openpi_droid_read.py"))
        .arg(&ds)
        .env("HF_HUB_OFFLINE", "1")
        .env("HF_DATASETS_OFFLINE", "1")
        .env("HF_HOME", tmp.join("hf"))
        .output()
        .unwrap();
    assert!(o.status.success(), "openpi's reading: {}", labrig_tests::output_text(&o));
    let r: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!((r["codebase_version"].as_str(), r["fps"].as_u64()), (Some("v2.1"), Some(20)));
    let frames = r["frames"].as_array().unwrap();
    assert_eq!(frames.len(), data.iter().map(|(s, _, _)| s.len()).sum::<usize>());
    for f in frames {
        let k = f["frame"].as_u64().unwrap() as usize;
        let (steps, task, _) = &data[f["episode"].as_u64().unwrap() as usize];
        let s = &steps[k];
        let mut state: Vec<f32> = s.robot_state.joint_positions.iter().map(|&x| x as f32).collect();
        state.push(s.robot_state.gripper_position as f32);
        assert_eq!(f32s(&f["state"]), state, "frame {k}");
        let chunk = f["actions"].as_array().unwrap();
        assert_eq!(chunk.len(), 16);
        for (i, row) in chunk.iter().enumerate() {
            let j = (k + i).min(steps.len() - 1);
            let mut a: Vec<f32> = steps[j].action.joint_velocity.iter().map(|&x| x as f32).collect();
            a.push(steps[j].action.gripper_position as f32);
            assert_eq!(f32s(row), a, "frame {k} row {i}");
            assert_eq!(f["pad"][i].as_bool(), Some(k + i >= steps.len()));
        }
        assert_eq!(f["prompt"], task.as_str());
        for key in ["exterior_image_1_left", "exterior_image_2_left", "wrist_image_left"] {
            assert_eq!(f["images"][format!("observation/{key}")], serde_json::json!([[128, 128, 3], "uint8"]));
        }
    }
    // Imported back (openpi's flat keys): the joints, gripper, joint velocities and gripper
    // action as recorded, the commanded joint position where the joints went next, the three
    // cameras; the keys openpi's schema lacks are named.
    let o = Command::new(labrig_bin())
        .args(["import", "lerobot", "--json"])
        .arg(&ds)
        .arg(tmp.join("openpi_back"))
        .output()
        .unwrap();
    assert!(o.status.success(), "import: {}", labrig_tests::output_text(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    let ids: Vec<&str> = report["cameras"].as_array().unwrap().iter().map(|c| c["id"].as_str().unwrap()).collect();
    assert_eq!(ids, ["ext1", "ext2", "wrist"], "{report}");
    assert_eq!(report["absent"]["action.cartesian_position"], 2, "{report}");
    let f = |x: f64| x as f32;
    let imported_rows = report["episodes"].as_array().unwrap();
    assert_eq!(imported_rows.len(), data.len(), "{report}");
    for (k, row) in imported_rows.iter().enumerate() {
        let back = labrig_episode::read_episode(Path::new(row[1].as_str().unwrap())).unwrap();
        let steps = &data[k].0;
        assert_eq!(back.steps.len(), steps.len());
        for (i, (a, b)) in steps.iter().zip(&back.steps).enumerate() {
            assert_eq!(b.robot_state.joint_positions.map(f), a.robot_state.joint_positions.map(f), "step {i}");
            assert_eq!(f(b.robot_state.gripper_position), f(a.robot_state.gripper_position), "step {i}");
            assert_eq!(b.action.joint_velocity.map(f), a.action.joint_velocity.map(f), "step {i}");
            assert_eq!(f(b.action.gripper_position), f(a.action.gripper_position), "step {i}");
            let next = &steps[(i + 1).min(steps.len() - 1)].robot_state.joint_positions;
            assert_eq!(b.action.joint_position.map(f), next.map(f), "step {i}");
            assert_eq!(b.cameras.len(), 3);
        }
    }
    // openpi's DROID schema needs its three cameras: asked for without one, refused by name.
    let o = Command::new(labrig_bin())
        .args(["export", "lerobot", "--schema", "openpi-droid", "--cameras", "ext1,wrist,top"])
        .arg(episodes)
        .arg(tmp.join("bad"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    assert!(labrig_tests::output_text(&o).contains("no camera top"), "{}", labrig_tests::output_text(&o));
}

/// The proof that an export trains: `labrig export lerobot --schema labrig` (two cameras) is
/// trained by LeRobot's own `lerobot-train` (lerobot 0.4.4, a Diffusion Policy, 2 steps on the
/// CPU), `labrig policy import-lerobot` converts what it saved, and the policy runs on the sim
/// rig (`labrig rollout`): its rows drive the arm. The exported state and action are labrig's
/// own training's (the TCP pose with its canonical quaternion + gripper; eef_axis_angle).
fn trains_in_lerobot_and_comes_back(episodes: &Path, data: &[(Vec<Step>, String, PathBuf)], tmp: &Path) {
    labrig_tests::workspace_bin("labrig-policies", "labrig-policies");
    labrig_tests::workspace_bin("labrig-policy", "labrig-policy-server");
    let ds = tmp.join("labrig_schema");
    let o = Command::new(labrig_bin())
        .args(["export", "lerobot", "--schema", "labrig", "--cameras", "ext1,ext2", "--json"])
        .arg(episodes)
        .arg(&ds)
        .output()
        .unwrap();
    assert!(o.status.success(), "export: {}", labrig_tests::output_text(&o));
    // The pose + gripper state, the eef_axis_angle action (the data file, read with pyarrow; the
    // trainer below reads it through LeRobotDataset).
    let py = "import json,sys,pyarrow.parquet as pq\n\
              t=pq.read_table(sys.argv[1]).to_pydict()\n\
              print(json.dumps({k:t[k] for k in ['episode_index','frame_index','observation.state','action']}))";
    let o = Command::new(lerobot_python())
        .args(["-c", py])
        .arg(ds.join("data/chunk-000/file-000.parquet"))
        .output()
        .unwrap();
    assert!(o.status.success(), "pyarrow: {}", labrig_tests::output_text(&o));
    let t: Value = serde_json::from_slice(&o.stdout).unwrap();
    let rows = t["frame_index"].as_array().unwrap().len();
    assert_eq!(rows, data.iter().map(|(s, _, _)| s.len()).sum::<usize>());
    for i in 0..rows {
        let (ep, k) =
            (t["episode_index"][i].as_u64().unwrap() as usize, t["frame_index"][i].as_u64().unwrap() as usize);
        let (rs, a) = (&data[ep].0[k].robot_state, &data[ep].0[k].action);
        let p = &rs.cartesian_position;
        let q = labrig_arm::ik::canonical_quaternion(&labrig_arm::ik::pose_from_xyz_euler(p).rotation);
        let want = [p[0], p[1], p[2], q[0], q[1], q[2], q[3], rs.gripper_position].map(|x| x as f32);
        assert_eq!(f32s(&t["observation.state"][i]), want, "episode {ep} frame {k}");
        let g = &a.cartesian_position;
        let aa = labrig_arm::ik::canonical_axis_angle(&labrig_arm::ik::pose_from_xyz_euler(g).rotation);
        let want = [g[0], g[1], g[2], aa[0], aa[1], aa[2], a.gripper_position].map(|x| x as f32);
        assert_eq!(f32s(&t["action"][i]), want, "episode {ep} frame {k}");
    }

    // LeRobot's trainer, offline on the CPU: a small Diffusion Policy labrig's model implements.
    let train = lerobot_python().with_file_name("lerobot-train");
    let out = tmp.join("train");
    let o = Command::new(&train)
        .arg("--dataset.repo_id=local/labrig")
        .arg(format!("--dataset.root={}", ds.display()))
        .args(["--dataset.video_backend=pyav", "--policy.type=diffusion", "--policy.device=cpu"])
        .args(["--policy.push_to_hub=false", "--policy.use_separate_rgb_encoder_per_camera=true"])
        .args(["--policy.noise_scheduler_type=DDIM", "--policy.num_inference_steps=10"])
        .args(["--policy.down_dims=[64,128]", "--policy.crop_shape=[116,116]"])
        .args(["--steps=2", "--batch_size=2", "--save_freq=2", "--log_freq=1", "--eval_freq=0"])
        .args(["--num_workers=0", "--wandb.enable=false"])
        .arg(format!("--output_dir={}", out.display()))
        .env("HF_HUB_OFFLINE", "1")
        .env("HF_DATASETS_OFFLINE", "1")
        .env("HF_HOME", tmp.join("hf"))
        .output()
        .unwrap();
    assert!(o.status.success(), "lerobot-train: {}", labrig_tests::output_text(&o));
    let pretrained = out.join("checkpoints/last/pretrained_model");
    assert!(pretrained.join("model.safetensors").is_file());

    let ckpt = tmp.join("imported");
    let o = Command::new(labrig_bin())
        .args(["policy", "import-lerobot"])
        .arg(&pretrained)
        .arg("--out")
        .arg(&ckpt)
        .output()
        .unwrap();
    assert!(o.status.success(), "import-lerobot: {}", labrig_tests::output_text(&o));
    let meta: Value = serde_json::from_str(&std::fs::read_to_string(ckpt.join("checkpoint.json")).unwrap()).unwrap();
    let c = &meta["config"];
    assert_eq!(
        (&c["cameras"], &c["state_dim"], &c["gripper_state"], &c["action_space"]),
        (
            &serde_json::json!(["ext1", "ext2"]),
            &serde_json::json!(8),
            &serde_json::json!(true),
            &serde_json::json!("eef_axis_angle")
        )
    );

    let key = "lerobot_trained_rollout";
    let o = Command::new(labrig_bin())
        .args(["rollout", "--threads", "1", "--json", "--episodes", "1", "--max-steps", "30"])
        .args(["--domain-id", &domain_for(key).to_string(), "--policy"])
        .arg(&ckpt)
        .arg("--out")
        .arg(tmp.join("rollout"))
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("{key}_{}", std::process::id()))
        .current_dir(repo_root())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    let report: Value = serde_json::from_str(stdout.lines().last().unwrap_or_default())
        .unwrap_or_else(|e| panic!("{e}: {}", labrig_tests::output_text(&o)));
    assert_eq!(o.status.code(), Some(0), "{report:#}");
    let run = &report["rollouts"][0];
    assert_eq!(run["reason"], "the step budget (30 steps) was spent", "{report:#}");
    let rows = report["control"]["source"]["rows_executed"].as_u64().unwrap();
    assert!(rows >= 20, "{rows} of 30 steps ran the imported policy's rows: {report:#}");
    let rec = labrig_episode::read_episode(Path::new(run["dir"].as_str().unwrap())).unwrap();
    assert!(rec.steps.iter().filter(|s| s.chunk_id > 0).count() as u64 >= rows, "the rows ran are recorded");
    assert!(
        rec.steps.iter().filter(|s| s.chunk_id > 0).all(|s| s.policy_id.starts_with("imported@")),
        "{:?}",
        rec.steps.last().map(|s| &s.policy_id)
    );
}
