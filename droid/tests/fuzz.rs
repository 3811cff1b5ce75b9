//! Bad input never panics: `import droid` on damaged DROID episodes. The fixture is the
//! committed labrig episode (tests/fixtures/episodes/pick_place_seed7) exported once with
//! `export_episode` (trajectory.h5, metadata JSON, five MP4s; ffmpeg only, no Python).
//!
//! - the metadata JSON: values anywhere replaced (wrong types, nulls, extremes), keys removed
//!   or added, the text cut, any text at all;
//! - trajectory.h5 as data (`from_droid` on a mutated document: shapes, dtypes, extreme
//!   timestamps, cameras added or removed) and as a file (cut, bits flipped, written from a
//!   mutated document);
//! - the MP4s: a few deterministic damages (empty, cut, header and frame bytes flipped,
//!   garbage).
//!
//! Each: no panic; the import either succeeds or its error names the file it could not read.
//! Imports of the JSON and h5 properties leave the MP4s out (the import warns and goes on
//! without images), so a case takes milliseconds.

use labrig_droid::droid::from_droid;
use labrig_droid::export::{ExportOptions, export_episode};
use labrig_droid::h5doc::{self, Attr, Column, Data, H5Doc};
use labrig_droid::import::{ImportOptions, import_episode};
use labrig_droid::meta;
use proptest::prelude::*;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

/// The exported fixture: its directory (kept for the whole run), the JSON's name and text,
/// trajectory.h5's bytes and document.
struct Fixture {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
    json_name: String,
    json: String,
    h5: Vec<u8>,
    doc: H5Doc,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let episode = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/episodes/pick_place_seed7");
        let tmp = tempfile::tempdir().unwrap();
        let out = export_episode(&episode, tmp.path(), &ExportOptions::default()).unwrap();
        let json_path = std::fs::read_dir(&out.dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.file_name().unwrap().to_string_lossy().starts_with("metadata_"))
            .unwrap();
        let h5 = std::fs::read(out.dir.join("trajectory.h5")).unwrap();
        Fixture {
            dir: out.dir.clone(),
            json_name: json_path.file_name().unwrap().to_string_lossy().into_owned(),
            json: std::fs::read_to_string(&json_path).unwrap(),
            doc: h5doc::read(&out.dir.join("trajectory.h5")).unwrap(),
            h5,
            _tmp: tmp,
        }
    })
}

/// A DROID episode directory under `tmp` from these parts (MP4s: which cameras' files, as
/// they are or replaced); imports it into `tmp/out`.
fn import(tmp: &Path, json: &str, h5: &[u8], mp4: &[(&str, Option<&[u8]>)]) -> Result<(), String> {
    let f = fixture();
    let src = tmp.join("droid");
    std::fs::create_dir_all(src.join("recordings/MP4")).unwrap();
    std::fs::write(src.join(&f.json_name), json).unwrap();
    std::fs::write(src.join("trajectory.h5"), h5).unwrap();
    for (serial, bytes) in mp4 {
        let name = format!("recordings/MP4/{serial}.mp4");
        match bytes {
            Some(b) => std::fs::write(src.join(&name), b).unwrap(),
            None => std::fs::copy(f.dir.join(&name), src.join(&name)).map(|_| ()).unwrap(),
        }
    }
    match import_episode(&src, &tmp.join("out"), &ImportOptions::default()) {
        Ok(imported) => {
            // What was imported reads as a finished episode.
            let back =
                labrig_episode::inspect(&imported.dir).unwrap_or_else(|e| panic!("the import does not read: {e}"));
            assert!(back.complete);
            assert_eq!(back.steps as usize, imported.steps);
            Ok(())
        }
        Err(e) => {
            let text = e.to_string();
            assert!(text.contains(&tmp.display().to_string()), "the error names no file: {text}");
            Err(text)
        }
    }
}

/// Imports with this JSON (trajectory.h5 as exported, no MP4s).
fn import_json(json: &str) -> Result<(), String> {
    let tmp = tempfile::tempdir().unwrap();
    let r = import(tmp.path(), json, &fixture().h5, &[]);
    if let Err(e) = &r {
        // Every JSON problem is reported against the JSON file (the h5 is good).
        assert!(e.contains(&fixture().json_name), "{e}");
    }
    r
}

/// Imports with this trajectory.h5 (the JSON as exported, no MP4s).
fn import_h5(h5: &[u8]) -> Result<(), String> {
    let tmp = tempfile::tempdir().unwrap();
    let r = import(tmp.path(), &fixture().json, h5, &[]);
    if let Err(e) = &r {
        assert!(e.contains("trajectory.h5"), "{e}");
    }
    r
}

// ---- JSON -------------------------------------------------------------------------------

/// Any JSON value, weighted toward what a metadata field must survive.
fn json_value() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<u64>().prop_map(Value::from),
        any::<f64>().prop_filter("JSON has no NaN", |v| v.is_finite()).prop_map(Value::from),
        prop_oneof![
            Just("2023-07-07-09h-42m-23s".to_owned()),
            Just("9999-99-99-99h-99m-99s".to_owned()),
            Just("teleop".to_owned()),
            ".{0,12}",
        ]
        .prop_map(Value::String),
    ];
    leaf.prop_recursive(2, 16, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..7).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_0-9]{1,10}", inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// One edit of a JSON tree at its `at`-th node (depth first).
#[derive(Debug, Clone)]
enum JsonEdit {
    /// Keeps the node's type: a number changed (to an extreme or another sign), a string
    /// changed, an array one shorter or longer, a key of an object removed, a bool flipped.
    Tweak(prop::sample::Index, i64, String),
    Replace(prop::sample::Index, Value),
    AddKey(prop::sample::Index, String, Value),
}

fn json_edit() -> impl Strategy<Value = JsonEdit> {
    let number = prop_oneof![Just(i64::MIN), Just(i64::MAX), Just(-1), Just(0), any::<i64>()];
    prop_oneof![
        4 => (any::<prop::sample::Index>(), number, ".{0,6}").prop_map(|(i, n, s)| JsonEdit::Tweak(i, n, s)),
        2 => (any::<prop::sample::Index>(), json_value()).prop_map(|(i, v)| JsonEdit::Replace(i, v)),
        1 => (any::<prop::sample::Index>(), prop_oneof![
                Just("labrig".to_owned()), Just("start_ns".to_owned()), Just("cameras".to_owned()),
                Just("extrinsics".to_owned()), Just("sim_scene".to_owned()), "[a-z_]{1,8}"], json_value())
            .prop_map(|(i, k, v)| JsonEdit::AddKey(i, k, v)),
    ]
}

fn json_nodes(v: &Value) -> Vec<Vec<String>> {
    fn walk(v: &Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        out.push(path.clone());
        match v {
            Value::Array(a) => {
                for (i, x) in a.iter().enumerate() {
                    path.push(i.to_string());
                    walk(x, path, out);
                    path.pop();
                }
            }
            Value::Object(o) => {
                for (k, x) in o {
                    path.push(k.clone());
                    walk(x, path, out);
                    path.pop();
                }
            }
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(v, &mut Vec::new(), &mut out);
    out
}

fn json_at<'a>(v: &'a mut Value, path: &[String]) -> &'a mut Value {
    path.iter().fold(v, |v, k| match v {
        Value::Array(a) => &mut a[k.parse::<usize>().unwrap()],
        Value::Object(o) => o.get_mut(k).unwrap(),
        _ => unreachable!(),
    })
}

fn edited_json(edits: &[JsonEdit]) -> Value {
    let mut v: Value = serde_json::from_str(&fixture().json).unwrap();
    for e in edits {
        let nodes = json_nodes(&v);
        let i = match e {
            JsonEdit::Tweak(i, _, _) | JsonEdit::Replace(i, _) | JsonEdit::AddKey(i, _, _) => i,
        };
        let node = json_at(&mut v, &nodes[i.index(nodes.len())]);
        match e {
            JsonEdit::Tweak(_, n, s) => match node {
                Value::Number(_) => *node = Value::from(*n),
                Value::String(old) => *old = s.clone(),
                Value::Bool(b) => *b = !*b,
                Value::Array(a) => {
                    if *n < 0 {
                        a.pop();
                    } else {
                        a.push(Value::from(*n));
                    }
                }
                Value::Object(o) => {
                    let keys: Vec<String> = o.keys().cloned().collect();
                    if !keys.is_empty() {
                        o.remove(&keys[n.unsigned_abs() as usize % keys.len()]);
                    }
                }
                Value::Null => *node = Value::String(s.clone()),
            },
            JsonEdit::Replace(_, new) => *node = new.clone(),
            JsonEdit::AddKey(_, k, new) => match node {
                Value::Object(o) => {
                    o.insert(k.clone(), new.clone());
                }
                other => *other = new.clone(),
            },
        }
    }
    v
}

// ---- trajectory.h5 as a document --------------------------------------------------------

/// One edit of trajectory.h5's content, keeping what HDF5 itself guarantees (values = the
/// product of the shape).
#[derive(Debug, Clone)]
enum DocEdit {
    Remove(prop::sample::Index),
    Reshape(prop::sample::Index, Vec<usize>),
    Retype(prop::sample::Index, u8),
    /// One value of a dataset set to an extreme (timestamps to times no clock gives).
    Value(prop::sample::Index, prop::sample::Index, f64, i64),
    /// A camera serial the JSON does not name, with a camera type and optional keys.
    Camera(String, i64, bool, Vec<usize>),
    Attr(String, u8),
}

fn doc_edit() -> impl Strategy<Value = DocEdit> {
    let shape =
        prop::collection::vec(prop_oneof![Just(0usize), Just(1), Just(3), Just(7), Just(49), Just(50), Just(51)], 0..4);
    let float = prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(-1e300), Just(1e300), Just(-1.0), any::<f64>()];
    let int = prop_oneof![Just(i64::MAX), Just(i64::MIN), Just(-1), Just(i64::MAX / 1_000_000 + 1), any::<i64>()];
    prop_oneof![
        2 => any::<prop::sample::Index>().prop_map(DocEdit::Remove),
        2 => (any::<prop::sample::Index>(), shape.clone()).prop_map(|(i, s)| DocEdit::Reshape(i, s)),
        1 => (any::<prop::sample::Index>(), any::<u8>()).prop_map(|(i, t)| DocEdit::Retype(i, t)),
        4 => (any::<prop::sample::Index>(), any::<prop::sample::Index>(), float, int).prop_map(|(d, k, f, i)| DocEdit::Value(d, k, f, i)),
        1 => ("[a-z0-9]{0,6}", prop_oneof![Just(0i64), Just(1), any::<i64>()], any::<bool>(), shape)
            .prop_map(|(s, t, k, sh)| DocEdit::Camera(s, t, k, sh)),
        1 => (prop_oneof![Just("success".to_owned()), Just("failure".to_owned()), Just("user".to_owned()), Just("current_task".to_owned())], any::<u8>())
            .prop_map(|(k, t)| DocEdit::Attr(k, t)),
    ]
}

fn filled(data: &Data, len: usize) -> Data {
    match data {
        Data::F64(v) => Data::F64((0..len).map(|i| v.get(i).copied().unwrap_or(0.5)).collect()),
        Data::I64(v) => Data::I64((0..len).map(|i| v.get(i).copied().unwrap_or(1)).collect()),
        Data::Bool(v) => Data::Bool((0..len).map(|i| v.get(i).copied().unwrap_or(true)).collect()),
    }
}

fn edited_doc(edits: &[DocEdit]) -> H5Doc {
    let mut doc = fixture().doc.clone();
    let pick = |doc: &H5Doc, i: &prop::sample::Index| doc.datasets.keys().nth(i.index(doc.datasets.len())).cloned();
    for e in edits {
        match e {
            DocEdit::Remove(i) => {
                if let Some(k) = pick(&doc, i) {
                    doc.datasets.remove(&k);
                }
            }
            DocEdit::Reshape(i, shape) => {
                if let Some(k) = pick(&doc, i) {
                    let c = doc.datasets.get_mut(&k).unwrap();
                    c.data = filled(&c.data, shape.iter().product());
                    c.shape = shape.clone();
                }
            }
            DocEdit::Retype(i, t) => {
                if let Some(k) = pick(&doc, i) {
                    let c = doc.datasets.get_mut(&k).unwrap();
                    let n = c.data.len();
                    c.data = match t % 3 {
                        0 => Data::F64(vec![1.0; n]),
                        1 => Data::I64(vec![1; n]),
                        _ => Data::Bool(vec![true; n]),
                    };
                }
            }
            DocEdit::Value(d, k, f, i) => {
                if let Some(key) = pick(&doc, d) {
                    let c = doc.datasets.get_mut(&key).unwrap();
                    match &mut c.data {
                        Data::F64(v) if !v.is_empty() => {
                            let at = k.index(v.len());
                            v[at] = *f;
                        }
                        Data::I64(v) if !v.is_empty() => {
                            let at = k.index(v.len());
                            v[at] = *i;
                        }
                        Data::Bool(v) if !v.is_empty() => {
                            let at = k.index(v.len());
                            v[at] ^= true;
                        }
                        _ => {}
                    }
                }
            }
            DocEdit::Camera(serial, kind, keys, shape) => {
                let n = 50;
                doc.datasets.insert(
                    format!("observation/camera_type/{serial}"),
                    Column { shape: vec![n], data: Data::I64(vec![*kind; n]) },
                );
                if *keys {
                    let len = shape.iter().product();
                    let t = "observation/timestamp/cameras";
                    doc.datasets.insert(
                        format!("{t}/{serial}_estimated_capture"),
                        Column { shape: shape.clone(), data: Data::I64(vec![i64::MAX; len]) },
                    );
                    doc.datasets.insert(
                        format!("observation/camera_intrinsics/{serial}_left"),
                        Column { shape: shape.clone(), data: Data::F64(vec![1.0; len]) },
                    );
                    doc.datasets.insert(
                        format!("observation/camera_extrinsics/{serial}_left_gripper_offset"),
                        Column { shape: shape.clone(), data: Data::F64(vec![0.0; len]) },
                    );
                }
            }
            DocEdit::Attr(key, t) => {
                let v = match t % 4 {
                    0 => Attr::Str("true".into()),
                    1 => Attr::I64(1),
                    2 => Attr::F64(f64::NAN),
                    _ => Attr::Bool(t % 8 < 4),
                };
                doc.attrs.insert(key.clone(), v);
            }
        }
    }
    doc
}

/// `from_droid` on `doc`: steps, one per row, or an error naming the key.
fn read_doc(doc: &H5Doc, serial_to_id: &BTreeMap<String, String>) {
    match from_droid(doc, "IRIS+x+2023-07-07-09h-42m-23s", serial_to_id) {
        Ok(t) => {
            assert!(!t.steps.is_empty());
            assert!(t.steps.iter().enumerate().all(|(i, s)| s.step_index == i as u64));
        }
        Err(e) => assert!(!e.key.is_empty() && e.to_string().contains("trajectory.h5"), "{e}"),
    }
}

// ---- the properties ---------------------------------------------------------------------

proptest! {
    #![proptest_config(cases(512))]

    /// The JSON's parser alone, on edited documents and on any JSON at all.
    #[test]
    fn the_metadata_parser_never_panics(edits in prop::collection::vec(json_edit(), 1..5), any_json in json_value()) {
        let _ = meta::parse(&edited_json(&edits));
        let _ = meta::parse(&any_json);
    }

    /// trajectory.h5's content edited: steps or an error naming the key.
    #[test]
    fn an_edited_trajectory_document_never_panics(edits in prop::collection::vec(doc_edit(), 1..5), named in any::<bool>()) {
        let ids: BTreeMap<String, String> =
            if named { [("ext1".to_owned(), "wrist".to_owned()), ("".to_owned(), "ext9".to_owned())].into() } else { BTreeMap::new() };
        read_doc(&edited_doc(&edits), &ids);
    }
}

proptest! {
    #![proptest_config(cases(64))]

    /// The metadata JSON edited anywhere: imported, or an error naming the JSON file.
    #[test]
    fn an_edited_metadata_json_is_imported_or_named(edits in prop::collection::vec(json_edit(), 1..4)) {
        let _ = import_json(&serde_json::to_string_pretty(&edited_json(&edits)).unwrap());
    }

    /// The metadata JSON cut anywhere, or replaced by any text.
    #[test]
    fn a_cut_or_arbitrary_metadata_json_is_named(at in any::<prop::sample::Index>(), text in ".{0,40}") {
        let json = &fixture().json;
        let mut cut = at.index(json.len());
        while !json.is_char_boundary(cut) {
            cut -= 1;
        }
        prop_assert!(import_json(&json[..cut]).is_err());
        let _ = import_json(&text);
    }
}

proptest! {
    #![proptest_config(cases(24))]

    /// trajectory.h5 written from an edited document: the import goes through HDF5 too.
    #[test]
    fn an_edited_trajectory_file_is_imported_or_named(edits in prop::collection::vec(doc_edit(), 1..4)) {
        let doc = edited_doc(&edits);
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("t.h5");
        // An edit HDF5 itself cannot store (an empty group name) is no input to test.
        prop_assume!(h5doc::write(&p, &doc).is_ok());
        let _ = import_h5(&std::fs::read(&p).unwrap());
    }

    /// trajectory.h5 cut anywhere (an interrupted copy): refused, naming it.
    #[test]
    fn a_cut_trajectory_file_is_named(at in any::<prop::sample::Index>()) {
        let h5 = &fixture().h5;
        prop_assert!(import_h5(&h5[..at.index(h5.len())]).is_err());
    }

    /// trajectory.h5 with bits flipped: imported (the flip hit a value) or refused, naming it.
    #[test]
    fn a_bit_flipped_trajectory_file_is_imported_or_named(flips in prop::collection::vec((any::<prop::sample::Index>(), 0u8..8), 1..4)) {
        let mut h5 = fixture().h5.clone();
        for (at, bit) in flips {
            let i = at.index(h5.len());
            h5[i] ^= 1 << bit;
        }
        let _ = import_h5(&h5);
    }
}

/// The MP4s, damaged a few ways each (decoding runs ffmpeg, so these are deterministic): the
/// import goes on without the camera's images (a warning) or its error names the video.
#[test]
fn damaged_videos_are_imported_without_their_frames_or_named() {
    let f = fixture();
    let good = std::fs::read(f.dir.join("recordings/MP4/wrist.mp4")).unwrap();
    let flipped = |at: usize| {
        let mut b = good.clone();
        for k in 0..16 {
            b[(at + k * 7) % good.len()] ^= 0xA5;
        }
        b
    };
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("empty", Vec::new()),
        ("cut to 100 bytes", good[..100].to_vec()),
        ("cut in half", good[..good.len() / 2].to_vec()),
        ("cut 10 bytes short", good[..good.len() - 10].to_vec()),
        ("header flipped", flipped(40)),
        ("middle flipped", flipped(good.len() / 2)),
        ("end flipped", flipped(good.len() - 200)),
        ("garbage", (0..4096u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8).collect()),
    ];
    for (what, bytes) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let r = import(tmp.path(), &f.json, &f.h5, &[("wrist", Some(&bytes)), ("ext1", None)]);
        if let Err(e) = r {
            assert!(e.contains("wrist.mp4") || e.contains("droid"), "{what}: {e}");
        }
    }
}

/// The control for the properties above: the fixture, untouched, imports with every camera.
#[test]
fn the_exported_fixture_imports() {
    let f = fixture();
    let tmp = tempfile::tempdir().unwrap();
    import(tmp.path(), &f.json, &f.h5, &[("wrist", None)]).unwrap();
}

/// A garbled timestamp (int64 ms) was multiplied into ns unchecked: `i64::MAX` ms in
/// `observation/timestamp/control/step_start` (or a camera's capture time, or a float64 column
/// of 1e300 read as integers) overflowed, a panic in a debug build and a wrapped time in
/// release. Now the key and the step are named.
#[test]
fn a_timestamp_past_i64_nanoseconds_is_an_error_naming_the_key_not_an_overflow() {
    let key = "observation/timestamp/control/step_start";
    for (at, ms) in [(0, i64::MAX), (3, i64::MAX / 1_000_000 + 1), (49, -1)] {
        let mut doc = fixture().doc.clone();
        let Some(Column { data: Data::I64(v), .. }) = doc.datasets.get_mut(key) else { panic!("{key} is int64") };
        v[at] = ms;
        let e = from_droid(&doc, "x", &BTreeMap::new()).unwrap_err().to_string();
        assert!(e.contains(&format!("`{key}` step {at}: {ms} ms is not a time")), "{e}");
    }
    let mut doc = fixture().doc.clone();
    let cam = doc.datasets.keys().find(|k| k.ends_with("_estimated_capture")).unwrap().clone();
    doc.datasets.insert(cam.clone(), Column { shape: vec![50], data: Data::F64(vec![1e300; 50]) });
    let e = from_droid(&doc, "x", &BTreeMap::new()).unwrap_err().to_string();
    assert!(e.contains(&format!("`{cam}` step 0")), "{e}");
}
