//! `labrig export lerobot` read by LeRobot's own `LeRobotDataset` (offline, PyAV): format v3.0
//! by lerobot 0.4.4 (setup's venv-lerobot-data), v2.1 by lerobot 0.3.3 (venv-lerobot-v21, the
//! line openpi pins). Two demo episodes of the simulated rig, every frame iterated with an action
//! chunk of 16; state, action and timestamps equal labrig's steps, images within H.264's
//! tolerance of the recorded JPEGs, and the statistics labrig wrote equal what LeRobot computes
//! from the same frames.

use labrig_msgs::labrig_msgs::Step;
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
    let listed: Vec<String> = episodes.iter().chain([&broken]).map(|p| p.display().to_string()).collect();
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
    }
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
    // computation from the frames it read.
    let (theirs, ours) = (&r["stats_lerobot"], &r["stats_file"]);
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
    // v3.0 carries the quantiles (10 statistics a feature), v2.1 min/max/mean/std/count.
    let per = if format == "v3.0" { 10 } else { 5 };
    assert!(compared >= 16 * per, "{format}: {compared} statistics compared");
}
