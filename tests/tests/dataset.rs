//! `labrig dataset`: the index over DROID raw episodes written by h5py (tests/peers/
//! make_droid_raw.py: known extrinsics, gripper traces with an accidental 3-step close before
//! the grasp, instructions) and a committed labrig episode of the simulated rig; the index read back by
//! pyarrow (tests/peers/read_index.py) with its documented columns; shards that together are
//! the unsharded index; retrieval aligned with one camera region and one object region
//! returning exactly the episodes generated there, with its funnel, and the same ids from the
//! same query run by pyarrow; a manifest of DROID raw episodes refused by `labrig train` with
//! the way to convert them.

use labrig_tests::droid_raw::{CAMS, OBJECTS, droid_python as python, uuid, write as write_fixtures};
use labrig_tests::{labrig_bin, repo_root, workspace_bin};
use serde_json::{Value, json};
use std::collections::BTreeSet;
use std::path::Path;
use std::process::{Command, Output};

fn labrig(args: &[&str]) -> Output {
    workspace_bin("labrig-dataset", "labrig-dataset");
    Command::new(labrig_bin()).args(args).output().unwrap()
}

fn text(out: &Output) -> String {
    labrig_tests::output_text(out)
}

fn ok_json(out: &Output) -> Value {
    assert!(out.status.success(), "{}", text(out));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("not JSON ({e}): {}", text(out)))
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn pyarrow(index: &Path, query: &Value) -> Value {
    let out = Command::new(python())
        .arg(repo_root().join("tests/peers/read_index.py"))
        .arg(index)
        .arg(query.to_string())
        .output()
        .unwrap();
    assert!(out.status.success(), "read_index.py: {}", text(&out));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// `labrig dataset retrieve ... --json`: its report and the manifest it wrote.
fn retrieve(index: &Path, target: &Path, align: &str, manifest: &Path) -> (Value, Value) {
    let r = ok_json(&labrig(&[
        "dataset",
        "retrieve",
        "--index",
        s(index),
        "--target",
        s(target),
        "--align",
        align,
        "--out",
        s(manifest),
        "--json",
    ]));
    (r, serde_json::from_str(&std::fs::read_to_string(manifest).unwrap()).unwrap())
}

/// The strings of a JSON array (of `key` in each element, or the elements themselves for "").
fn strings(v: &Value, key: &str) -> BTreeSet<String> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|e| if key.is_empty() { e } else { &e[key] }.as_str().unwrap().to_owned())
        .collect()
}

#[test]
fn droid_raw_and_labrig_episodes_are_indexed_sharded_and_retrieved_by_alignment() {
    let dir = tempfile::tempdir().unwrap();
    let raw = dir.path().join("droid_raw");
    write_fixtures(&raw);
    // One labrig episode of the simulated rig (the committed pick-and-place fixture).
    let demo = dir.path().join("demo");
    let fixture = repo_root().join("tests/fixtures/episodes/pick_place_seed7");
    std::fs::create_dir_all(demo.join("pick_place_seed7")).unwrap();
    for f in ["episode_0.mcap", "metadata.yaml"] {
        std::fs::copy(fixture.join(f), demo.join("pick_place_seed7").join(f)).unwrap();
    }

    let index = dir.path().join("index");
    let r = ok_json(&labrig(&["dataset", "index", s(&raw), s(&demo), "--out", s(&index), "--json"]));
    assert_eq!(r["found"], 15, "{r}");
    assert_eq!(r["by_format"], json!({"droid_raw": 13, "labrig": 1}), "{r}");
    let bad = r["bad"].as_array().unwrap();
    assert_eq!(bad.len(), 1, "{r}");
    assert!(bad[0]["path"].as_str().unwrap().ends_with("damaged"), "{r}");

    // pyarrow reads it with the documented columns; the object is where the gripper closed for
    // good (the accidental close at the decoy is ignored).
    let q = json!({"object": "cube", "cam": &CAMS[0][..3], "cam_xy": 0.2, "cam_z": 0.1,
                   "box_centre": OBJECTS[0], "box": [0.6, 0.6, 0.3]});
    let py = pyarrow(&index, &q);
    let cols: BTreeSet<&str> = py["columns"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
    for c in [
        "index_version",
        "episode_id",
        "source_path",
        "source_format",
        "success",
        "lab",
        "building",
        "scene_id",
        "instruction",
        "length",
        "ext1_serial",
        "ext1_x",
        "ext1_y",
        "ext1_z",
        "ext1_roll",
        "ext1_radius_m",
        "ext1_polar_deg",
        "ext1_azimuth_deg",
        "ext1_bin",
        "wrist_x",
        "object_x",
        "object_y",
        "object_z",
        "object",
        "primitive",
        "colour",
        "sim_dv",
    ] {
        assert!(cols.contains(c), "column {c} missing: {cols:?}");
    }
    let rows = py["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 14);
    for row in rows.iter().filter(|r| r["episode_id"].as_str().unwrap().starts_with("FIX+op+c")) {
        let id = row["episode_id"].as_str().unwrap();
        let o = if id.contains("o0") { OBJECTS[0] } else { OBJECTS[1] };
        assert_eq!([row["object_x"].as_f64(), row["object_y"].as_f64()], [Some(o[0]), Some(o[1])], "{id}");
    }
    let wipe = rows.iter().find(|r| r["episode_id"] == "FIX+op+wipe").unwrap();
    assert!(wipe["object_x"].is_null(), "the gripper never closes: {wipe}");
    let sim = rows.iter().find(|r| r["source_format"] == "labrig").unwrap();
    assert!(sim["object_x"].is_number() && sim["ext1_bin"].is_string(), "the demo's row: {sim}");

    // Shards: two disjoint halves, together the unsharded index.
    let sharded = dir.path().join("sharded");
    let a =
        ok_json(&labrig(&["dataset", "index", s(&raw), s(&demo), "--out", s(&sharded), "--shard", "0/2", "--json"]));
    let b =
        ok_json(&labrig(&["dataset", "index", s(&raw), s(&demo), "--out", s(&sharded), "--shard", "1/2", "--json"]));
    assert_eq!(a["in_shard"].as_u64().unwrap() + b["in_shard"].as_u64().unwrap(), 15);
    let ids = |v: &Value| -> BTreeSet<String> {
        v["rows"].as_array().unwrap().iter().map(|r| r["episode_id"].as_str().unwrap().to_owned()).collect()
    };
    let py_sharded = pyarrow(&sharded, &q);
    assert_eq!(py_sharded["rows"].as_array().unwrap().len(), 14, "no episode twice");
    assert_eq!(ids(&py_sharded), ids(&py));
    // Re-indexing an unchanged shard reads nothing again.
    let again =
        ok_json(&labrig(&["dataset", "index", s(&raw), s(&demo), "--out", s(&sharded), "--shard", "0/2", "--json"]));
    assert_eq!(
        again["unchanged"],
        a["in_shard"].as_u64().unwrap() - a["bad"].as_array().unwrap().len() as u64,
        "{again}"
    );

    // Retrieval aligned with camera region 0 and object region 0: exactly those three episodes.
    let target = dir.path().join("target.toml");
    std::fs::write(
        &target,
        format!(
            "cameras = [[{}, {}, {}]]\nobject_position = [{}, {}, {}]\nobject = \"cube\"\nskill = \"place\"\ncolour = \"red\"\n",
            CAMS[0][0], CAMS[0][1], CAMS[0][2], OBJECTS[0][0], OBJECTS[0][1], OBJECTS[0][2]
        ),
    )
    .unwrap();
    let manifest = dir.path().join("manifest.json");
    let (r, m) = retrieve(&index, &target, "objSpat,camPose,object,skill", &manifest);
    let funnel: Vec<(String, u64)> = r["funnel"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| (f["stage"].as_str().unwrap().to_owned(), f["kept"].as_u64().unwrap()))
        .collect();
    // 14 rows; the wipe has no object; the sim episode's cube is placed, its cameras elsewhere.
    assert_eq!(funnel[0], ("all".to_owned(), 14), "{r}");
    assert_eq!(funnel[1], ("object".to_owned(), 13), "{r}");
    assert_eq!(funnel[2], ("skill".to_owned(), 13), "{r}");
    assert_eq!(funnel[3].0, "camPose", "{r}");
    assert_eq!(funnel[4], ("objSpat".to_owned(), 3), "{r}");
    let got = strings(&m["episodes"], "id");
    let want: BTreeSet<String> = (0..3).map(|k| uuid(0, 0, k)).collect();
    assert_eq!(got, want);
    assert_eq!(m["episodes"][0]["passed"], json!(["object", "skill", "camPose", "objSpat"]));
    // pyarrow's query (object, camera, object box) keeps the same ids.
    assert_eq!(strings(&py["kept"], ""), want);

    // The stats: the same funnel, counts by bin, and the picture.
    let png = dir.path().join("stats.png");
    let st = ok_json(&labrig(&[
        "dataset",
        "stats",
        "--index",
        s(&index),
        "--target",
        s(&target),
        "--align",
        "object,skill,camPose,objSpat",
        "--plot",
        s(&png),
        "--json",
    ]));
    assert_eq!(st["funnel"], r["funnel"], "{st}");
    assert_eq!(st["episodes"], 14);
    assert_eq!(st["formats"], json!({"droid_raw": 13, "labrig": 1}), "{st}");
    assert!(std::fs::metadata(&png).unwrap().len() > 10_000);

    // DROID's re-calibrated extrinsics (cam2base_extrinsics.json, keyed by episode, then camera
    // serial): one episode's ext1 (serial 21) moves to the other camera region and leaves the
    // retrieval; an entry for a serial the episode lacks changes nothing and is counted.
    let recal = dir.path().join("cam2base_extrinsics.json");
    std::fs::write(
        &recal,
        json!({
            uuid(0, 0, 0): {"21": CAMS[1], "21_metric_type": "quality"},
            uuid(0, 0, 1): {"99": CAMS[1]},
        })
        .to_string(),
    )
    .unwrap();
    let recal_index = dir.path().join("recal_index");
    let index_with = |extra: &[&str]| {
        ok_json(&labrig(
            &[&["dataset", "index", s(&raw), s(&demo), "--out", s(&recal_index), "--json"], extra].concat(),
        ))
    };
    let r = index_with(&["--extrinsics", s(&recal)]);
    assert_eq!(
        r["extrinsics_override"],
        json!({"file_episodes": 2, "recalibrated": 1, "named_without_serials": 1}),
        "{r}"
    );
    let (_, m) = retrieve(&recal_index, &target, "object,skill,camPose,objSpat", &manifest);
    assert_eq!(strings(&m["episodes"], "id"), (1..3).map(|k| uuid(0, 0, k)).collect::<BTreeSet<_>>());
    let py = pyarrow(&recal_index, &q);
    let moved = py["rows"].as_array().unwrap().iter().find(|r| r["episode_id"] == uuid(0, 0, 0)).unwrap();
    assert_eq!(
        (moved["ext1_extrinsics_from"].as_str(), moved["ext1_x"].as_f64()),
        (Some("recalibrated"), Some(CAMS[1][0]))
    );
    assert_eq!(strings(&py["kept"], ""), (1..3).map(|k| uuid(0, 0, k)).collect::<BTreeSet<_>>());
    // The same file again: nothing re-read; without it: every row re-derived, the episode back.
    assert_eq!(index_with(&["--extrinsics", s(&recal)])["unchanged"], 14);
    assert_eq!(index_with(&[])["unchanged"], 0);
    let (_, m) = retrieve(&recal_index, &target, "object,skill,camPose,objSpat", &manifest);
    assert_eq!(strings(&m["episodes"], "id"), want);

    // A target whose dimension is missing is named; the trainer refuses DROID raw data with the way on.
    let no_obj = dir.path().join("no_object.toml");
    std::fs::write(&no_obj, "cameras = [[0.3, 0.6, 0.5]]\n").unwrap();
    let out = labrig(&[
        "dataset",
        "retrieve",
        "--index",
        s(&index),
        "--target",
        s(&no_obj),
        "--align",
        "objSpat",
        "--out",
        s(&manifest),
    ]);
    assert!(
        !out.status.success() && text(&out).contains("objSpat: the target has no object position"),
        "{}",
        text(&out)
    );
    workspace_bin("labrig-policies", "labrig-policies");
    let out = Command::new(labrig_bin())
        .args([
            "train",
            "--target",
            s(&demo),
            "--cotrain",
            s(&manifest),
            "--out",
            s(&dir.path().join("run")),
            "--steps",
            "1",
        ])
        .output()
        .unwrap();
    assert!(
        !out.status.success() && text(&out).contains("convert it first with `labrig import droid"),
        "{}",
        text(&out)
    );
}

/// `labrig dataset bench` (functional, not timing: the figures are the README's): every
/// `--align` combination timed over a small synthetic index, and the index throughput of the
/// RLDS fixture counted in episodes, not shards.
#[test]
fn the_dataset_bench_reports_every_combination_and_the_index_throughput() {
    let rlds = repo_root().join("tests/fixtures/rlds");
    let r = ok_json(&labrig(&[
        "dataset",
        "bench",
        "--episodes",
        "2000",
        "--runs",
        "2",
        "--episodes-root",
        s(&rlds),
        "--json",
    ]));
    assert_eq!(r["episodes"], 2000, "{r}");
    let combos = r["retrieval"].as_array().unwrap();
    assert_eq!(combos.len(), 7, "{r}");
    for c in combos {
        assert!(c["p50_ms"].as_f64().unwrap() > 0.0 && c["p99_ms"].as_f64() >= c["p50_ms"].as_f64(), "{c}");
        assert!(c["kept"].as_u64().unwrap() <= 2000, "{c}");
    }
    let t = &r["index_throughput"];
    assert_eq!((t["sources"].as_u64(), t["indexed"].as_u64()), (Some(1), Some(9)), "{t}");
    assert!(t["index_episodes_per_s"].as_f64().unwrap() > 0.0, "{t}");
}

/// DROID's RLDS release: the committed shard (tests/fixtures/rlds, written by the PyPI
/// `tfrecord` package from make_rlds.py: nine episodes, fake image bytes, an accidental close
/// before each grasp) is indexed without TensorFlow, read back by pyarrow, retrieved by
/// alignment; a damaged copy is listed as bad with the reason.
#[test]
fn an_rlds_shard_is_indexed_and_retrieved_and_a_damaged_one_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let shard = repo_root().join("tests/fixtures/rlds/droid_101-train.tfrecord-00000-of-00001");
    let root = dir.path().join("rlds");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::copy(&shard, root.join("droid_101-train.tfrecord-00000-of-00002")).unwrap();
    let mut damaged = std::fs::read(&shard).unwrap();
    let mid = damaged.len() / 2;
    damaged[mid] ^= 0x55;
    std::fs::write(root.join("droid_101-train.tfrecord-00001-of-00002"), damaged).unwrap();
    let index = dir.path().join("index");
    let r = ok_json(&labrig(&["dataset", "index", s(&root), "--out", s(&index), "--json"]));
    assert_eq!(r["by_format"], json!({"rlds": 9}), "{r}");
    let bad = r["bad"].as_array().unwrap();
    assert_eq!(bad.len(), 1, "{r}");
    assert!(bad[0]["reason"].as_str().unwrap().contains("CRC does not match"), "{r}");

    let q = json!({"object": "cube", "cam": [0.3, 0.6, 0.5], "cam_xy": 0.2, "cam_z": 0.1,
                   "box_centre": [0.5, 0.1, 0.05], "box": [0.6, 0.6, 0.3]});
    let py = pyarrow(&index, &q);
    let rows = py["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 9);
    for row in rows {
        let id = row["episode_id"].as_str().unwrap();
        // DROID's episode key: recording_folderpath--file_path.
        assert!(id.starts_with("gs://droid/") && id.contains("--gs://droid/"), "{id}");
        if id.contains("/wave/") {
            assert!(row["object_x"].is_null(), "{row}");
        } else {
            let y = if id.contains("o0k") { 0.1 } else { 0.5 };
            assert!((row["object_y"].as_f64().unwrap() - y).abs() < 1e-6, "the grasp, not the decoy: {row}");
        }
    }
    let target = dir.path().join("target.toml");
    std::fs::write(&target, "cameras = [[0.3, 0.6, 0.5]]\nobject_position = [0.5, 0.1, 0.05]\nobject = \"cube\"\n")
        .unwrap();
    let (r, m) = retrieve(&index, &target, "object,camPose,objSpat", &dir.path().join("m.json"));
    let got = strings(&m["episodes"], "id");
    assert_eq!(got.len(), 2, "{r}");
    assert!(got.iter().all(|id| id.contains("/c0o0k")), "{got:?}");
    assert_eq!(strings(&py["kept"], ""), got);
}
