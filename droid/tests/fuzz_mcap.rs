//! Bad input never panics: `import droid-mcap` on damaged DROID-layout MCAP files. The fixture
//! is the committed labrig episode (tests/fixtures/episodes/pick_place_seed7) exported once with
//! `export_mcap`; each case damages it and imports it:
//!
//! - the file: cut anywhere, bytes flipped anywhere;
//! - one message's payload (a robot state, an action, an image, ...): replaced by any JSON value,
//!   by that message's JSON with a value anywhere replaced or removed, or by arbitrary bytes,
//!   the file rewritten with mcap's writer;
//! - one message dropped.
//!
//! Each: no panic; the import either succeeds or its error names the file.

use labrig_droid::droid_mcap::{export_mcap, import_mcap};
use labrig_droid::export::ExportOptions;
use labrig_droid::import::ImportOptions;
use proptest::prelude::*;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

/// A message of the fixture: topic, schema (name, encoding, text), log time, payload.
type Message = (String, (String, String, Vec<u8>), u64, Vec<u8>);

struct Fixture {
    _tmp: tempfile::TempDir,
    bytes: Vec<u8>,
    messages: Vec<Message>,
    metadata: Vec<mcap::records::Metadata>,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let episode = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures/episodes/pick_place_seed7");
        let tmp = tempfile::tempdir().unwrap();
        let out = export_mcap(&episode, tmp.path(), &ExportOptions::default()).unwrap();
        let bytes = std::fs::read(&out.file).unwrap();
        let mut messages = Vec::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            let s = m.channel.schema.as_ref().unwrap();
            messages.push((
                m.channel.topic.clone(),
                (s.name.clone(), s.encoding.clone(), s.data.to_vec()),
                m.log_time,
                m.data.to_vec(),
            ));
        }
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let metadata = summary.metadata_indexes.iter().map(|i| mcap::read::metadata(&bytes, i).unwrap()).collect();
        Fixture { _tmp: tmp, bytes, messages, metadata }
    })
}

/// The fixture's messages, written again with mcap's writer.
fn write(messages: &[Message]) -> Vec<u8> {
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let mut w = mcap::Writer::new(&mut buf).unwrap();
        let mut channels: BTreeMap<String, u16> = BTreeMap::new();
        for (seq, (topic, (name, enc, text), t, data)) in messages.iter().enumerate() {
            let c = match channels.get(topic) {
                Some(&c) => c,
                None => {
                    let s = w.add_schema(name, enc, text).unwrap();
                    let c = w.add_channel(s, topic, "json", &BTreeMap::new()).unwrap();
                    channels.insert(topic.clone(), c);
                    c
                }
            };
            let header =
                mcap::records::MessageHeader { channel_id: c, sequence: seq as u32, log_time: *t, publish_time: *t };
            w.write_to_known_channel(&header, data).unwrap();
        }
        for m in &fixture().metadata {
            w.write_metadata(m).unwrap();
        }
        w.finish().unwrap();
    }
    buf.into_inner()
}

/// Imports `bytes` as a DROID MCAP file in a directory of its own.
fn import(bytes: &[u8]) -> Result<(), String> {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("trajectory.mcap");
    std::fs::write(&file, bytes).unwrap();
    match import_mcap(&file, &tmp.path().join("out"), &ImportOptions::default()) {
        Ok(_) => Ok(()),
        Err(e) => {
            let e = e.to_string();
            if e.contains(&file.display().to_string()) { Err(e) } else { panic!("an error that names no file: {e}") }
        }
    }
}

fn any_json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<f64>().prop_filter("finite", |x| x.is_finite()).prop_map(Value::from),
        ".{0,12}".prop_map(Value::String),
    ];
    leaf.prop_recursive(3, 24, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..4).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,8}", inner, 0..4)
                .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// Every path to a value in `v`.
fn paths(v: &Value, at: &mut Vec<Value>, out: &mut Vec<Vec<Value>>) {
    out.push(at.clone());
    match v {
        Value::Object(m) => {
            for (k, x) in m {
                at.push(Value::String(k.clone()));
                paths(x, at, out);
                at.pop();
            }
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate().take(3) {
                at.push(Value::from(i));
                paths(x, at, out);
                at.pop();
            }
        }
        _ => {}
    }
}

/// `v` with the value at `path` replaced (`Some`) or removed (`None`).
fn edit(v: &mut Value, path: &[Value], with: Option<Value>) {
    let Some((last, head)) = path.split_last() else {
        *v = with.unwrap_or(Value::Null);
        return;
    };
    let mut at = v;
    for p in head {
        at = match (at, p) {
            (Value::Object(m), Value::String(k)) => m.get_mut(k).unwrap(),
            (Value::Array(a), Value::Number(i)) => &mut a[i.as_u64().unwrap() as usize],
            _ => unreachable!("a path from paths()"),
        };
    }
    match (at, last, with) {
        (Value::Object(m), Value::String(k), Some(w)) => {
            m.insert(k.clone(), w);
        }
        (Value::Object(m), Value::String(k), None) => {
            m.remove(k);
        }
        (Value::Array(a), Value::Number(i), Some(w)) => a[i.as_u64().unwrap() as usize] = w,
        (Value::Array(a), Value::Number(i), None) => {
            a.remove(i.as_u64().unwrap() as usize);
        }
        _ => unreachable!("a path from paths()"),
    }
}

#[test]
fn the_fixture_imports_whole() {
    assert!(fixture().messages.len() > 50 * 7);
    import(&fixture().bytes).unwrap();
    import(&write(&fixture().messages)).unwrap();
}

proptest! {
    #![proptest_config(cases(48))]

    #[test]
    fn a_cut_or_flipped_file_is_imported_or_named(at in any::<prop::sample::Index>(), flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..), 0..4)) {
        let f = fixture();
        let mut bytes = f.bytes.clone();
        for (i, x) in &flips {
            let k = i.index(bytes.len());
            bytes[k] ^= x;
        }
        if flips.is_empty() {
            bytes.truncate(at.index(bytes.len()));
        }
        let _ = import(&bytes);
    }

    #[test]
    fn an_edited_payload_is_imported_or_named(which in any::<prop::sample::Index>(), path in any::<prop::sample::Index>(), with in prop::option::of(any_json()), raw in prop::option::of(prop::collection::vec(any::<u8>(), 0..16))) {
        let f = fixture();
        let mut messages = f.messages.clone();
        let k = which.index(messages.len());
        match raw {
            Some(bytes) => messages[k].3 = bytes,
            None => {
                let mut v: Value = serde_json::from_slice(&messages[k].3).unwrap();
                let mut all = Vec::new();
                paths(&v, &mut Vec::new(), &mut all);
                let p = &all[path.index(all.len())];
                edit(&mut v, p, with);
                messages[k].3 = serde_json::to_vec(&v).unwrap();
            }
        }
        let _ = import(&write(&messages));
    }

    #[test]
    fn a_dropped_message_is_imported_or_named(which in any::<prop::sample::Index>()) {
        let mut messages = fixture().messages.clone();
        messages.remove(which.index(messages.len()));
        let _ = import(&write(&messages));
    }
}

#[test]
fn paths_cover_nested_values() {
    let v: Value = serde_json::json!({"a": [1, {"b": 2}], "c": 3});
    let mut all = Vec::new();
    paths(&v, &mut Vec::new(), &mut all);
    assert_eq!(all.len(), 6);
    let mut w = v.clone();
    edit(&mut w, &[Value::from("a"), Value::from(1), Value::from("b")], None);
    assert_eq!(w, serde_json::json!({"a": [1, {}], "c": 3}));
}
