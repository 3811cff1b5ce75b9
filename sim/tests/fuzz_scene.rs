//! Bad input never panics: scene specs (`SceneSpec::parse` on the TOML files in sim/scenes and
//! on any text) and what a spec gives (`sample`, the textures). A spec read from a recording
//! (`labrig replay` deserializes the episode's scene spec without the TOML path) goes straight
//! to `sample`, so `sample` must refuse an invalid spec too, naming the field, not panic.
//!
//! Mutations work on the parsed TOML tree of each built-in spec: a value anywhere replaced by
//! any TOML value (NaN, infinities, huge, negative, wrong types, arrays of any length), a key
//! removed, an unknown key added; and on the text itself (cut, spliced, characters replaced).

use labrig_sim::SceneSpec;
use labrig_sim::scene::{BUILTIN_SCENES, SceneError, object_texture, table_texture};
use proptest::prelude::*;
use toml::Value;

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

/// The spec files in sim/scenes, by name, as text.
fn spec_files() -> Vec<(String, String)> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    let mut files: Vec<(String, String)> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .map(|p| (p.file_stem().unwrap().to_string_lossy().into_owned(), std::fs::read_to_string(&p).unwrap()))
        .collect();
    files.sort();
    assert!(files.len() >= BUILTIN_SCENES.len(), "{files:?}");
    files
}

/// What a spec gives for a few seeds: values (or a sampling error that names the scene) and
/// textures; nothing panics.
fn use_spec(spec: &SceneSpec, seeds: &[u64]) {
    for &seed in seeds {
        match spec.sample(seed) {
            Ok(values) => {
                assert_eq!(object_texture(&values, spec.object.noise_octaves).len(), 64 * 64 * 3);
                assert_eq!(table_texture(&values, spec.table.jitter).len(), 64 * 64 * 3);
                assert!(values.object_position.iter().all(|v| v.is_finite()), "{values:?}");
                let json = serde_json::to_string(&values).unwrap();
                let _: labrig_sim::scene::SceneValues = serde_json::from_str(&json).unwrap();
            }
            Err(SceneError::Sample { name, .. }) => assert_eq!(name, spec.name),
            Err(e) => assert!(matches!(e, SceneError::Invalid { .. }), "sample: {e}"),
        }
    }
}

/// Parses `text` as a spec from `origin`; an error names the origin (and, for a rule, the field).
fn parse(text: &str, origin: &str) -> Result<SceneSpec, SceneError> {
    let r = SceneSpec::parse(text, origin);
    match &r {
        Ok(spec) => use_spec(spec, &[0, 7, u64::MAX]),
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains(origin), "the error does not name {origin}: {msg}");
            if let SceneError::Invalid { field, .. } = e {
                assert!(!field.is_empty() && msg.contains(&format!("`{field}`")), "{msg}");
            }
        }
    }
    r
}

/// Any TOML value, weighted toward the ones a spec's checks must catch.
fn value() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        4 => -2.0f64..2.0,
        1 => prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY), Just(1e308), Just(-1e308), Just(0.0), Just(-0.0)],
        1 => any::<f64>(),
    ]
    .prop_map(Value::Float);
    let other = prop_oneof![
        any::<i64>().prop_map(Value::Integer),
        (0i64..10).prop_map(Value::Integer),
        any::<bool>().prop_map(Value::Boolean),
        prop_oneof![
            Just("pick_place".to_owned()),
            Just("drawer_open".to_owned()),
            Just("drawer_close".to_owned()),
            Just("shoulder-left".to_owned()),
            Just("agent-front".to_owned()),
            ".{0,8}",
        ]
        .prop_map(Value::String),
    ];
    let scalar = prop_oneof![3 => leaf, 1 => other];
    scalar.prop_recursive(2, 24, 6, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,6}", inner, 0..3).prop_map(|m| Value::Table(m.into_iter().collect())),
        ]
    })
}

/// One edit of a spec's TOML tree, at the `at`-th node (depth first).
#[derive(Debug, Clone)]
enum Edit {
    /// Keeps the node's type (so the spec still deserializes and its checks are what is
    /// tested): a float set to this value, an integer to it truncated, an array one element
    /// shorter or longer, a string another name, a boolean flipped.
    Tweak(prop::sample::Index, f64, u8),
    Replace(prop::sample::Index, Value),
    Remove(prop::sample::Index),
    AddKey(prop::sample::Index, String, Value),
}

fn edit() -> impl Strategy<Value = Edit> {
    let number = prop_oneof![
        4 => -2.0f64..2.0,
        2 => -200.0f64..200.0,
        1 => prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY), Just(1e308), Just(-0.0), Just(f64::MIN_POSITIVE)],
    ];
    prop_oneof![
        8 => (any::<prop::sample::Index>(), number, any::<u8>()).prop_map(|(i, v, c)| Edit::Tweak(i, v, c)),
        2 => (any::<prop::sample::Index>(), value()).prop_map(|(i, v)| Edit::Replace(i, v)),
        1 => any::<prop::sample::Index>().prop_map(Edit::Remove),
        1 => (any::<prop::sample::Index>(), "[a-z_]{1,8}", value()).prop_map(|(i, k, v)| Edit::AddKey(i, k, v)),
    ]
}

/// Every node of `v`'s tree, depth first (the root included).
fn count(v: &Value) -> usize {
    1 + match v {
        Value::Array(a) => a.iter().map(count).sum(),
        Value::Table(t) => t.values().map(count).sum(),
        _ => 0,
    }
}

/// Applies `e` at node `k` of `v`; `k` counts down through the tree.
fn apply_at(v: &mut Value, k: &mut usize, e: &Edit) -> bool {
    if *k == 0 {
        match e {
            Edit::Tweak(_, x, c) => match v {
                Value::Float(f) => *f = *x,
                Value::Integer(i) => *i = if c.is_multiple_of(2) { *x as i64 } else { x.to_bits() as i64 },
                Value::Boolean(b) => *b = !*b,
                Value::String(s) => {
                    let names =
                        ["pick_place", "drawer_open", "drawer_close", "shoulder-left", "agent-front", "nowhere", ""];
                    *s = names[*c as usize % names.len()].to_owned();
                }
                Value::Array(a) => match (c % 2, a.last().cloned()) {
                    (0, Some(_)) => {
                        a.pop();
                    }
                    (_, Some(last)) => a.push(last),
                    _ => a.push(Value::Float(*x)),
                },
                Value::Table(t) => {
                    let keys: Vec<String> = t.keys().cloned().collect();
                    if !keys.is_empty() {
                        t.remove(&keys[*c as usize % keys.len()]);
                    }
                }
                Value::Datetime(_) => {}
            },
            Edit::Replace(_, new) => *v = new.clone(),
            Edit::AddKey(_, key, new) => match v {
                Value::Table(t) => {
                    t.insert(key.clone(), new.clone());
                }
                Value::Array(a) => a.push(new.clone()),
                other => *other = new.clone(),
            },
            Edit::Remove(_) => return false,
        }
        return true;
    }
    *k -= 1;
    match v {
        Value::Array(a) => {
            for i in 0..a.len() {
                if *k == 0 && matches!(e, Edit::Remove(_)) {
                    a.remove(i);
                    return true;
                }
                if apply_at(&mut a[i], k, e) {
                    return true;
                }
            }
        }
        Value::Table(t) => {
            let keys: Vec<String> = t.keys().cloned().collect();
            for key in keys {
                if *k == 0 && matches!(e, Edit::Remove(_)) {
                    t.remove(&key);
                    return true;
                }
                if apply_at(t.get_mut(&key).unwrap(), k, e) {
                    return true;
                }
            }
        }
        _ => {}
    }
    false
}

fn edited(text: &str, edits: &[Edit]) -> Value {
    let mut v = Value::Table(toml::from_str(text).unwrap());
    for e in edits {
        let at = match e {
            Edit::Tweak(i, _, _) | Edit::Replace(i, _) | Edit::Remove(i) | Edit::AddKey(i, _, _) => i,
        };
        let mut k = at.index(count(&v));
        apply_at(&mut v, &mut k, e);
    }
    v
}

/// One edit of a spec's text, in characters.
fn text_edit() -> impl Strategy<Value = (prop::sample::Index, usize, String)> {
    (any::<prop::sample::Index>(), 0usize..12, prop_oneof!["[\\[\\]{}=,.\"#\\n 0-9a-z_\\-]{0,6}", "\\PC{0,3}"])
}

proptest! {
    #![proptest_config(cases(256))]

    /// A built-in spec with values anywhere replaced, keys removed or added: parsed and
    /// sampled, or refused naming the spec and the field.
    #[test]
    fn an_edited_spec_never_panics(file in any::<prop::sample::Index>(), edits in prop::collection::vec(edit(), 1..4)) {
        let files = spec_files();
        let (name, text) = &files[file.index(files.len())];
        let v = edited(text, &edits);
        let text = toml::to_string(&v).unwrap_or_default();
        let _ = parse(&text, &format!("{name}.toml"));
    }

    /// A spec file's text cut, spliced or with characters replaced.
    #[test]
    fn a_mangled_spec_text_never_panics(file in any::<prop::sample::Index>(), edits in prop::collection::vec(text_edit(), 1..6)) {
        let files = spec_files();
        let (name, text) = &files[file.index(files.len())];
        let mut c: Vec<char> = text.chars().collect();
        for (at, del, ins) in edits {
            let k = at.index(c.len() + 1);
            c.splice(k..(k + del).min(c.len()), ins.chars());
        }
        let _ = parse(&c.into_iter().collect::<String>(), &format!("{name}.toml"));
    }

    /// Any text at all.
    #[test]
    fn arbitrary_text_never_panics(s in any::<String>()) {
        let _ = parse(&s, "any.toml");
    }
}

/// Every built-in spec parses, samples and makes its textures (the control for the above).
#[test]
fn every_spec_file_parses_and_samples() {
    for (name, text) in spec_files() {
        let spec = parse(&text, &name).unwrap_or_else(|e| panic!("{name}: {e}"));
        use_spec(&spec, &[0, 1, 2, u64::MAX]);
        spec.sample(0).unwrap();
    }
}

/// `labrig replay` takes the scene spec from the episode's metadata (JSON) without the TOML
/// path's checks, and `sample` indexed a camera the spec did not have: `cameras["ext1"]`
/// panicked ("key not found"). Now `sample` checks the spec first and names the field.
#[test]
fn a_recorded_spec_without_a_camera_is_an_error_not_a_panic() {
    let mut spec = SceneSpec::default_pick_place();
    spec.cameras.remove("ext1");
    let e = spec.sample(0).unwrap_err().to_string();
    assert!(e.contains("`cameras.ext1` is missing"), "{e}");
}

/// ... and an empty or inverted range reached `random_range`, which panics on it.
#[test]
fn a_recorded_spec_with_an_inverted_range_is_an_error_not_a_panic() {
    let mut spec = SceneSpec::default_pick_place();
    spec.object.yaw_deg = [10.0, -10.0];
    let e = spec.sample(0).unwrap_err().to_string();
    assert!(e.contains("`object.yaw_deg` min 10 > max -10"), "{e}");
    let mut spec = SceneSpec::default_pick_place();
    spec.receptacle.boxes.clear();
    let e = spec.sample(0).unwrap_err().to_string();
    assert!(e.contains("`receptacle.boxes` is an empty union of boxes"), "{e}");
}

/// The same edits as `an_edited_spec_never_panics`, the spec then read as a recording carries
/// it (JSON, no TOML checks): `sample` refuses what `validate` refuses, and never panics.
/// Counted over the cases: enough of them must deserialise and reach `sample` (and enough of
/// those be invalid), else the check tests nothing.
#[test]
fn an_edited_spec_from_a_recording_never_panics() {
    use proptest::test_runner::TestRunner;
    let (reached, invalid) = (std::cell::Cell::new(0u32), std::cell::Cell::new(0u32));
    let strategy = (any::<prop::sample::Index>(), prop::collection::vec(edit(), 1..4), any::<u64>());
    TestRunner::new(cases(256))
        .run(&strategy, |(file, edits, seed)| {
            let files = spec_files();
            let (_, text) = &files[file.index(files.len())];
            let v = edited(text, &edits);
            let Ok(json) = serde_json::to_value(&v) else { return Ok(()) };
            let Ok(spec) = serde_json::from_value::<SceneSpec>(json) else { return Ok(()) };
            reached.set(reached.get() + 1);
            let valid = spec.validate("recording").is_ok();
            let sampled = spec.sample(seed);
            if !valid {
                invalid.set(invalid.get() + 1);
                prop_assert!(matches!(sampled, Err(SceneError::Invalid { .. })), "{:?}", sampled);
            }
            use_spec(&spec, &[seed]);
            Ok(())
        })
        .unwrap();
    eprintln!("{} of 256 cases reached sample, {} of them invalid", reached.get(), invalid.get());
    assert!(reached.get() >= 40 && invalid.get() >= 10, "{} reached, {} invalid", reached.get(), invalid.get());
}
