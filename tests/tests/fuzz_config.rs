//! Bad input never panics: every node's TOML config through the node skeleton's `load` (the
//! file, `--set`, the node's own `validate`), for every node (franka, gripper, recorder,
//! control, teleop, the sim bridge, the station, the cameras; not the policy server, whose
//! crate links libtorch), and the launch configs through `LaunchConfig::parse`.
//! Here, not in labrig-runtime, because the nodes depend on labrig-runtime.
//!
//! Inputs: the real files in launch_configs/ (and an empty file for nodes without one), their
//! TOML trees edited (a value anywhere replaced by a value of its type or of any type, NaN,
//! infinities and extremes included; keys removed; any of the node's own keys added, found by
//! asking the config type itself), their text mangled, any `--set key=value`.
//!
//! Each: no panic; the config loads or the error names the file, and a rule's error names its
//! key. A config that loads must also be one the node can start with: every time the node
//! turns into a `Duration` (and adds to `Instant::now()`) fits one. The findings (durations
//! that validated and then panicked, rule errors without the file's name) are named
//! regression tests at the end.

use labrig_runtime::config::{ConfigError, parse_config};
use labrig_runtime::node::{CommonFlags, Node, load};
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use toml::Value;

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

fn launch_configs() -> PathBuf {
    labrig_tests::repo_root().join("launch_configs")
}

/// A node's flags with none given (as `labrig-<node> run` alone).
fn no_flags<F: clap::Args + clap::FromArgMatches>() -> F {
    let m = F::augment_args(clap::Command::new("t")).try_get_matches_from(["t"]).unwrap();
    F::from_arg_matches(&m).unwrap()
}

/// What a key takes, as far as serde's errors tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Float,
    Integer,
    Bool,
    Str,
    Array,
    Table,
}

/// A key of a config (dotted) and the kinds of value it takes.
#[derive(Debug, Clone)]
struct Key {
    name: String,
    kinds: Vec<Kind>,
}

/// The keys of `N`'s config, found by asking serde: an unknown key's error lists the expected
/// ones, at the top and in every nested table; each key then takes the kinds of value whose
/// error (if any) is not "invalid type".
fn keys_of<N: Node>() -> Vec<Key> {
    let mut names = Vec::new();
    let mut tables = vec![String::new()];
    while let Some(prefix) = tables.pop() {
        let text =
            if prefix.is_empty() { "zz_unknown = 1\n".to_owned() } else { format!("[{prefix}]\nzz_unknown = 1\n") };
        let Err(e) = parse_config::<N::Config>(&text, Path::new("k.toml")) else { continue };
        let msg = e.to_string();
        let Some(list) = msg.split("expected one of ").nth(1).or_else(|| msg.split("expected `").nth(1).map(|_| ""))
        else {
            continue;
        };
        for k in list.split(", ").filter_map(|s| s.trim().strip_prefix('`')?.split('`').next()) {
            let full = if prefix.is_empty() { k.to_owned() } else { format!("{prefix}.{k}") };
            if full.matches('.').count() < 3 {
                tables.push(full.clone());
            }
            names.push(full);
        }
    }
    names.sort();
    names.dedup();
    let probes = [
        (Kind::Float, Value::Float(0.5)),
        (Kind::Integer, Value::Integer(1)),
        (Kind::Bool, Value::Boolean(true)),
        (Kind::Str, Value::String("sim".into())),
        (Kind::Array, Value::Array(Vec::new())),
        (Kind::Table, Value::Table(toml::Table::new())),
    ];
    names
        .into_iter()
        .map(|name| {
            let kinds = probes
                .iter()
                .filter(|(_, v)| {
                    let mut t = toml::Table::new();
                    set_path(&mut t, &name, v.clone());
                    let text = toml::to_string(&t).unwrap_or_default();
                    match parse_config::<N::Config>(&text, Path::new("k.toml")) {
                        Ok(_) => true,
                        Err(e) => !e.to_string().contains("invalid type"),
                    }
                })
                .map(|(k, _)| *k)
                .collect();
            Key { name, kinds }
        })
        .collect()
}

/// A value of one of `key`'s kinds, from the case's numbers (extremes and edges weighted in).
fn typed(key: &Key, x: f64, c: u8) -> Option<Value> {
    let kind = *key.kinds.get(c as usize % key.kinds.len().max(1))?;
    let ints = [x as i64, -1, 0, 1, 255, 256, 65_536, i64::MAX, i64::MIN, 233];
    Some(match kind {
        Kind::Float => Value::Float(x),
        Kind::Integer => Value::Integer(ints[(c / 8) as usize % ints.len()]),
        Kind::Bool => Value::Boolean(c.is_multiple_of(2)),
        Kind::Str => Value::String(WORDS[(c / 8) as usize % WORDS.len()].to_owned()),
        Kind::Array => Value::Array(
            (0..(c / 8) % 9)
                .map(|k| {
                    if c.is_multiple_of(2) {
                        Value::Float(x + f64::from(k))
                    } else {
                        Value::String(WORDS[k as usize].to_owned())
                    }
                })
                .collect(),
        ),
        Kind::Table => Value::Table(toml::Table::new()),
    })
}

/// A time the node sleeps or waits for: a `Duration` and an `Instant` after now can hold it.
fn sleepable(key: &str, seconds: f64) {
    let ok = Duration::try_from_secs_f64(seconds).ok().and_then(|d| Instant::now().checked_add(d)).is_some();
    assert!(ok, "`{key}` = {seconds:e} s validated, but the node cannot wait that long (Duration / Instant overflow)");
}

/// The node skeleton's `load` on `text` as the node's config file (`None`: no file) with
/// `set`: a config that passes (then `after` checks what the node does with it) or an error
/// naming the file and, for a rule, the key.
fn load_node<N: Node>(text: Option<&str>, set: Vec<(String, String)>, after: impl Fn(&N::Config)) -> Result<(), String>
where
    N::Flags: clap::FromArgMatches,
{
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("node.toml");
    if let Some(t) = text {
        std::fs::write(&path, t).unwrap();
    }
    let origin = if text.is_some() { path.display().to_string() } else { "<command line>".to_owned() };
    let common = CommonFlags { config: text.map(|_| path.clone()), set, domain_id: None, json: false, stats_out: None };
    match load::<N>(&common, no_flags::<N::Flags>()) {
        Ok(cfg) => {
            after(&cfg);
            Ok(())
        }
        Err(e) => {
            let msg = e.to_string();
            assert!(msg.contains(&origin), "{}: the error does not name {origin}: {msg}", N::NAME);
            if let ConfigError::Rule { rule, .. } = &e {
                let last = rule.key.rsplit('.').next().unwrap_or_default().split('[').next().unwrap_or_default();
                // The sim bridge names its flag (`--hardware-prefix`) for the key: the finding
                // `the_bridge_s_hardware_prefix_rule_names_the_config_key`.
                let flag = format!("--{}", last.replace('_', "-"));
                let named = rule.message.contains(last) || rule.message.contains(&flag);
                assert!(!rule.key.is_empty() && named, "{}: the rule does not name its key: {msg}", N::NAME);
            }
            Err(msg)
        }
    }
}

/// What each node turns into sleeps and deadlines (the keys that once overflowed them are
/// also regression tests below).
fn teleop_after(c: &labrig_quest_teleop::node::TeleopConfig) {
    sleepable("input.keyboard_hz (1 / it)", 1.0 / c.input.keyboard_hz);
    sleepable("input.reconnect_s", c.input.reconnect_s);
}

fn gripper_after(c: &labrig_gripper::node::GripperNodeConfig) {
    sleepable("request_timeout_s", c.request_timeout_s);
    sleepable("rate_hz (1 / it)", 1.0 / c.rate_hz);
    // activation_timeout_s: `a_gripper_activation_timeout_no_duration_can_hold_is_refused`.
}

fn franka_after(c: &labrig_franka::node::FrankaNodeConfig) {
    sleepable("connect_timeout_s", c.connect_timeout_s.max(0.0));
    sleepable("rate_hz (1 / it)", 1.0 / c.rate_hz);
}

fn bridge_after(c: &labrig_sim_bridge::bridge::BridgeConfig) {
    sleepable("period_s", c.period_s);
}

fn station_after(c: &labrig_station::StationConfig) {
    sleepable("thumbnail_hz (1 / it)", 1.0 / c.thumbnail_hz);
    let addr: std::net::SocketAddr = c.listen.parse().expect("a validated listen address parses");
    assert!(
        addr.ip().is_loopback() || c.token.as_deref().is_some_and(|t| t.len() >= 8),
        "listening on {addr} without a token: {c:?}"
    );
    assert!(c.calibration_max_age_s > 0.0, "{c:?}");
}

// control: teleop_max_age_s, source_timeout_s; recorder: rejoin_wait_s — the findings below.

/// Words the configs' enums and strings take.
const WORDS: [&str; 22] = [
    "sim",
    "wall",
    "fci",
    "robotiq",
    "emulated",
    "adb",
    "playback",
    "keyboard",
    "right",
    "left",
    "scripted",
    "hold",
    "teleop",
    "lockstep",
    "realtime",
    "visual",
    "collision",
    "/",
    "/sim",
    "",
    "pick_place",
    "robot",
];

/// Any TOML value, weighted toward what a config's checks must catch.
fn value() -> impl Strategy<Value = Value> {
    let float = prop_oneof![
        3 => -2.0f64..2.0,
        2 => prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, 1e18, -1e300, 0.0, -0.0, 1e-300, 86_400.5]),
        1 => any::<f64>(),
    ];
    let leaf = prop_oneof![
        3 => float.prop_map(Value::Float),
        2 => prop_oneof![any::<i64>(), -2i64..300, Just(i64::MAX)].prop_map(Value::Integer),
        1 => any::<bool>().prop_map(Value::Boolean),
        2 => prop_oneof![prop::sample::select(WORDS.to_vec()).prop_map(str::to_owned), "\\PC{0,8}"].prop_map(Value::String),
    ];
    leaf.prop_recursive(2, 12, 4, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..5).prop_map(Value::Array),
            prop::collection::btree_map("[a-z_]{1,6}", inner, 0..3).prop_map(|m| Value::Table(m.into_iter().collect())),
        ]
    })
}

/// One edit of a config's TOML tree.
#[derive(Debug, Clone)]
enum Edit {
    /// At the `at`-th node: a float/integer set to this number, a string to a word, a bool
    /// flipped, an array shorter or longer, a key of a table removed.
    Tweak(prop::sample::Index, f64, u8),
    Replace(prop::sample::Index, Value),
    /// One of the node's own keys (dotted) set to a value of its kind (from the number and
    /// the choice), or to the given value of any kind.
    Set(prop::sample::Index, f64, u8, Option<Value>),
}

fn number_for_set() -> impl Strategy<Value = f64> {
    prop_oneof![
        2 => -2.0f64..2.0,
        1 => 0.0f64..2000.0,
        2 => prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, 1e19, 1e18, -1.0, 0.0, -0.0, 1e-300, 1e-3, 300.0, 1001.0, 86_401.0]),
    ]
}

fn edit() -> impl Strategy<Value = Edit> {
    let number = prop_oneof![
        2 => -2.0f64..2.0,
        1 => prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e300, 1e18, -1.0, 0.0, 1e-300, 300.0, 1001.0]),
    ];
    prop_oneof![
        4 => (any::<prop::sample::Index>(), number, any::<u8>()).prop_map(|(i, x, c)| Edit::Tweak(i, x, c)),
        1 => (any::<prop::sample::Index>(), value()).prop_map(|(i, v)| Edit::Replace(i, v)),
        4 => (any::<prop::sample::Index>(), number_for_set(), any::<u8>(), prop_oneof![6 => Just(None), 1 => value().prop_map(Some)])
            .prop_map(|(i, x, c, v)| Edit::Set(i, x, c, v)),
    ]
}

/// Every node of `v` (the root first), as a path of table keys and array indices.
fn paths(v: &Value) -> Vec<Vec<String>> {
    fn walk(v: &Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
        out.push(path.clone());
        match v {
            Value::Array(a) => a.iter().enumerate().for_each(|(i, x)| {
                path.push(i.to_string());
                walk(x, path, out);
                path.pop();
            }),
            Value::Table(t) => t.iter().for_each(|(k, x)| {
                path.push(k.clone());
                walk(x, path, out);
                path.pop();
            }),
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk(v, &mut Vec::new(), &mut out);
    out
}

fn at<'a>(v: &'a mut Value, path: &[String]) -> &'a mut Value {
    path.iter().fold(v, |v, k| match v {
        Value::Array(a) => &mut a[k.parse::<usize>().unwrap()],
        Value::Table(t) => t.get_mut(k).unwrap(),
        _ => unreachable!("a path goes through arrays and tables"),
    })
}

/// `key` (dotted) = `value` in `table`, making tables on the way (as `--set` does).
fn set_path(table: &mut toml::Table, key: &str, value: Value) {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().unwrap();
    let mut at = table;
    for p in parts {
        let e = at.entry(p.to_owned()).or_insert_with(|| Value::Table(toml::Table::new()));
        if !e.is_table() {
            *e = Value::Table(toml::Table::new());
        }
        at = e.as_table_mut().unwrap();
    }
    at.insert(last.to_owned(), value);
}

/// `base` (a config's text) with `edits` applied, as text.
fn edited(base: &str, keys: &[Key], edits: &[Edit]) -> String {
    let mut root = Value::Table(toml::from_str(base).unwrap());
    for e in edits {
        match e {
            Edit::Set(i, x, c, v) => {
                let key = &keys[i.index(keys.len())];
                if let Some(v) = v.clone().or_else(|| typed(key, *x, *c)) {
                    set_path(root.as_table_mut().unwrap(), &key.name, v);
                }
            }
            Edit::Tweak(i, x, c) => {
                let all = paths(&root);
                match at(&mut root, &all[i.index(all.len())]) {
                    Value::Float(f) => *f = *x,
                    Value::Integer(n) => *n = if c.is_multiple_of(2) { *x as i64 } else { !(*x as i64) },
                    Value::Boolean(b) => *b = !*b,
                    Value::String(s) => *s = WORDS[*c as usize % WORDS.len()].to_owned(),
                    Value::Array(a) => {
                        if c.is_multiple_of(2) {
                            a.pop();
                        } else if let Some(last) = a.last().cloned() {
                            a.push(last);
                        }
                    }
                    Value::Table(t) => {
                        let keys: Vec<String> = t.keys().cloned().collect();
                        if !keys.is_empty() {
                            t.remove(&keys[*c as usize % keys.len()]);
                        }
                    }
                    Value::Datetime(_) => {}
                }
            }
            Edit::Replace(i, v) => {
                let all = paths(&root);
                let path = &all[i.index(all.len())];
                if !path.is_empty() {
                    *at(&mut root, path) = v.clone();
                }
            }
        }
    }
    toml::to_string(&root).unwrap_or_default()
}

/// One edit of a config's text: characters cut, inserted or replaced.
fn text_edit() -> impl Strategy<Value = (prop::sample::Index, usize, String)> {
    (
        any::<prop::sample::Index>(),
        0usize..10,
        prop_oneof![
            "[\\[\\]{}=,.\"'#\\n 0-9a-z_\\-]{0,6}",
            "(nan|inf|1e999|-1|\\[ros\\]|\\[\\[node\\]\\])",
            "\\PC{0,3}"
        ],
    )
}

fn mangled(base: &str, edits: &[(prop::sample::Index, usize, String)]) -> String {
    let mut c: Vec<char> = base.chars().collect();
    for (i, del, ins) in edits {
        let k = i.index(c.len() + 1);
        c.splice(k..(k + del).min(c.len()), ins.chars());
    }
    c.into_iter().collect()
}

/// `--set` pairs: the node's own keys (or malformed ones) and a value of the key's kind (as
/// TOML text), or TOML values and bare words of any kind.
#[derive(Debug, Clone)]
struct SetPair {
    key: prop::sample::Index,
    malformed_key: Option<String>,
    x: f64,
    c: u8,
    word: Option<String>,
}

fn set_pairs() -> impl Strategy<Value = Vec<SetPair>> {
    let word = prop_oneof![
        prop::sample::select(vec![
            "nan", "-inf", "1e400", "-1", "0", "1e300", "[]", "{}", "[1, 2]", "\"sim\"", "x", "=", "true"
        ])
        .prop_map(str::to_owned),
        "\\PC{0,8}",
    ];
    let pair = (
        any::<prop::sample::Index>(),
        prop_oneof![4 => Just(None), 1 => "[a-z_.]{0,10}".prop_map(Some)],
        number_for_set(),
        any::<u8>(),
        prop_oneof![3 => Just(None), 1 => word.prop_map(Some)],
    )
        .prop_map(|(key, malformed_key, x, c, word)| SetPair { key, malformed_key, x, c, word });
    prop_oneof![2 => Just(Vec::new()), 1 => prop::collection::vec(pair, 1..3)]
}

/// One node: its config files in launch_configs/nodes (by name prefix; none: an empty file).
struct Subject {
    files: Vec<String>,
    keys: Vec<Key>,
}

fn subject<N: Node>(prefix: &str) -> Subject {
    let dir = launch_configs().join("nodes");
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_string_lossy().starts_with(prefix))
        .map(|p| std::fs::read_to_string(p).unwrap())
        .collect();
    if files.is_empty() {
        files.push(String::new());
    }
    let keys = keys_of::<N>();
    assert!(keys.len() > 3, "{}: {keys:?}", N::NAME);
    Subject { files, keys }
}

/// The inputs of one case, applied to one node.
#[derive(Debug, Clone)]
struct Case {
    file: prop::sample::Index,
    edits: Vec<Edit>,
    text_edits: Vec<(prop::sample::Index, usize, String)>,
    set: Vec<SetPair>,
}

fn case() -> impl Strategy<Value = Case> {
    (
        any::<prop::sample::Index>(),
        prop::collection::vec(edit(), 0..4),
        prop_oneof![3 => Just(Vec::new()), 1 => prop::collection::vec(text_edit(), 1..4)],
        set_pairs(),
    )
        .prop_map(|(file, edits, text_edits, set)| Case { file, edits, text_edits, set })
}

fn run_case<N: Node>(s: &Subject, c: &Case, after: impl Fn(&N::Config)) -> Result<(), String>
where
    N::Flags: clap::FromArgMatches,
{
    let base = &s.files[c.file.index(s.files.len())];
    let text = mangled(&edited(base, &s.keys, &c.edits), &c.text_edits);
    let set = c
        .set
        .iter()
        .map(|p| {
            let key = &s.keys[p.key.index(s.keys.len())];
            let value = p.word.clone().or_else(|| typed(key, p.x, p.c).map(|v| v.to_string())).unwrap_or_default();
            (p.malformed_key.clone().unwrap_or_else(|| key.name.clone()), value)
        })
        .collect();
    load_node::<N>(Some(&text), set, after)
}

fn subjects() -> &'static [Subject; 8] {
    static S: std::sync::OnceLock<[Subject; 8]> = std::sync::OnceLock::new();
    S.get_or_init(|| {
        [
            subject::<labrig_franka::FrankaNode>("franka"),
            subject::<labrig_gripper::GripperNode>("gripper"),
            subject::<labrig_recorder::RecorderNode>("recorder"),
            subject::<labrig_control::ControlNode>("control"),
            subject::<labrig_quest_teleop::TeleopNode>("teleop"),
            subject::<labrig_sim_bridge::bridge::BridgeNode>("sim"),
            subject::<labrig_station::StationNode>("station"),
            subject::<labrig_cameras::CamerasNode>("cameras"),
        ]
    })
}

proptest! {
    #![proptest_config(cases(96))]

    /// Any text as any node's config.
    #[test]
    fn arbitrary_text_as_a_node_config_never_panics(text in any::<String>()) {
        let _ = load_node::<labrig_franka::FrankaNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_gripper::GripperNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_recorder::RecorderNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_control::ControlNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_quest_teleop::TeleopNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_sim_bridge::bridge::BridgeNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_station::StationNode>(Some(&text), Vec::new(), |_| {});
        let _ = load_node::<labrig_cameras::CamerasNode>(Some(&text), Vec::new(), |_| {});
    }

    /// The launch configs, edited and mangled: a start order, or refused. A parse error names
    /// the file; a rule's (`validate`) does not yet (`a_launch_config_rule_error_names_the_file`).
    #[test]
    fn a_launch_config_parses_or_names_the_problem(
        file in any::<prop::sample::Index>(),
        edits in prop::collection::vec(edit(), 0..4),
        text_edits in prop_oneof![3 => Just(Vec::new()), 1 => prop::collection::vec(text_edit(), 1..4)],
    ) {
        let (origin, text) = &launch_files()[file.index(launch_files().len())];
        let keys = [
            ("rig.name", Kind::Str),
            ("rig.domain_id", Kind::Integer),
            ("rig.on_failure", Kind::Str),
            ("rig.devices.robot_ip", Kind::Str),
            ("rig.devices.camera_serials", Kind::Table),
            ("node", Kind::Array),
        ]
        .map(|(k, kind)| Key { name: k.to_owned(), kinds: vec![kind] });
        let text = mangled(&edited(text, &keys, &edits), &text_edits);
        match labrig_launch::config::LaunchConfig::parse(&text, origin) {
            Ok((cfg, order)) => {
                let mut sorted = order.clone();
                sorted.sort_unstable();
                prop_assert_eq!(sorted, (0..cfg.nodes.len()).collect::<Vec<_>>(), "a start order is every node once");
            }
            Err(e) => {
                if let Some(c) = e.downcast_ref::<ConfigError>() {
                    prop_assert!(c.to_string().contains(&origin.display().to_string()), "{}", c);
                }
            }
        }
    }
}

fn launch_files() -> &'static Vec<(PathBuf, String)> {
    static F: std::sync::OnceLock<Vec<(PathBuf, String)>> = std::sync::OnceLock::new();
    F.get_or_init(|| {
        let mut files: Vec<(PathBuf, String)> = std::fs::read_dir(launch_configs())
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "toml"))
            .map(|p| {
                let text = std::fs::read_to_string(&p).unwrap();
                (p, text)
            })
            .collect();
        files.sort();
        assert!(files.len() >= 2);
        files
    })
}

/// What reads a file in launch_configs/.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reader {
    /// `labrig launch` (`LaunchConfig`).
    Launch,
    /// The node run by this program (as a launch file's `program` names it), with the file as
    /// its `--config`.
    Node(&'static str),
    /// No program reads it; the reason.
    NotAConfig(&'static str),
}

/// Every file in launch_configs/ (nested folders too, paths relative to it) and what reads
/// it. `every_real_config_loads` fails on a file missing here, so a new config is loaded by
/// its reader or named as no config, never skipped without a word.
const REAL_CONFIGS: [(&str, Reader); 18] = [
    ("README.md", Reader::NotAConfig("the folder's description, for people")),
    ("bench_rig.toml", Reader::Launch),
    ("real_droid.toml", Reader::Launch),
    ("real_policy.toml", Reader::Launch),
    ("real_openpi.toml", Reader::Launch),
    ("sim_demo.toml", Reader::Launch),
    ("sim_droid.toml", Reader::Launch),
    ("sim_rollout.toml", Reader::Launch),
    ("nodes/cameras_bench.toml", Reader::Node("labrig-cameras")),
    ("nodes/cameras_real.toml", Reader::Node("labrig-cameras")),
    ("nodes/control_real.toml", Reader::Node("labrig-control")),
    ("nodes/control_real_policy.toml", Reader::Node("labrig-control")),
    ("nodes/control_real_openpi.toml", Reader::Node("labrig-control")),
    ("nodes/franka_fr3.toml", Reader::Node("labrig-franka")),
    ("nodes/gripper_2f85.toml", Reader::Node("labrig-gripper")),
    ("nodes/recorder_real.toml", Reader::Node("labrig-recorder")),
    ("nodes/teleop_quest.toml", Reader::Node("labrig-teleop")),
    ("nodes/teleop_sim_trace.toml", Reader::Node("labrig-teleop")),
];

/// Programs the launch files start that this test cannot load a config for, and why.
const NOT_LOADED: [(&str, &str); 1] =
    [("labrig-policy", "the policy server's crate links libtorch, which this test crate does not build against")];

/// Every file under `dir`, nested folders too, relative to `dir`, sorted.
fn files_under(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// The node skeleton's `load` on a real file where it lies (so that paths in it resolve
/// against its own folder, as when the launcher passes it), or with no file; the config must
/// load, then `after` checks what the node does with it.
fn load_real_with<N: Node>(file: Option<&Path>, after: impl Fn(&N::Config))
where
    N::Flags: clap::FromArgMatches,
{
    let common = CommonFlags {
        config: file.map(Path::to_owned),
        set: Vec::new(),
        domain_id: None,
        json: false,
        stats_out: None,
    };
    match load::<N>(&common, no_flags::<N::Flags>()) {
        Ok(cfg) => after(&cfg),
        Err(e) => panic!("{} refuses {}: {e}", N::NAME, file.map_or("no config".into(), |f| f.display().to_string())),
    }
}

/// `file` (`None`: no config file) loaded by the node `program` runs.
fn load_real(program: &str, file: Option<&Path>) {
    match program {
        "labrig-franka" => load_real_with::<labrig_franka::FrankaNode>(file, franka_after),
        "labrig-gripper" => load_real_with::<labrig_gripper::GripperNode>(file, gripper_after),
        "labrig-recorder" => load_real_with::<labrig_recorder::RecorderNode>(file, |_| {}),
        "labrig-control" => load_real_with::<labrig_control::ControlNode>(file, |_| {}),
        "labrig-teleop" => load_real_with::<labrig_quest_teleop::TeleopNode>(file, |c| {
            teleop_after(c);
            // A recorded trace is resolved against the config's folder: it must be there.
            if let Some(trace) = &c.input.file {
                let config = file.map_or("no config".into(), |f| f.display().to_string());
                assert!(trace.is_file(), "{config}: the trace {} is not a file", trace.display());
            }
        }),
        "labrig-sim" => load_real_with::<labrig_sim_bridge::bridge::BridgeNode>(file, bridge_after),
        "labrig-station" => load_real_with::<labrig_station::StationNode>(file, station_after),
        "labrig-cameras" => load_real_with::<labrig_cameras::CamerasNode>(file, |_| {}),
        other => panic!("{other}: no node here to load its config with; add it to `load_real`"),
    }
}

/// The control for the above: every real file in launch_configs/ (nested folders too) is
/// loaded as it is by what reads it: the launch files by the launcher, each node config by
/// the node the launch files start with it; the nodes they start with no config file load
/// with none. A file or program this test cannot load is named, with why.
#[test]
fn every_real_config_loads() {
    let root = launch_configs();
    let found = files_under(&root);
    let unnamed: Vec<&String> = found.iter().filter(|f| !REAL_CONFIGS.iter().any(|(n, _)| n == f)).collect();
    assert!(unnamed.is_empty(), "launch_configs/ holds {unnamed:?}: name each in `REAL_CONFIGS` with what reads it");
    let gone: Vec<&str> = REAL_CONFIGS.iter().map(|(n, _)| *n).filter(|n| !found.iter().any(|f| f == n)).collect();
    assert!(gone.is_empty(), "`REAL_CONFIGS` names {gone:?}, which launch_configs/ does not hold");
    let reader_of = |rel: &str| REAL_CONFIGS.iter().find(|(f, _)| *f == rel).map(|(_, r)| *r);
    let mut without_config = std::collections::BTreeSet::new();
    for (rel, reader) in REAL_CONFIGS {
        let path = root.join(rel);
        match reader {
            Reader::Launch => {
                let (cfg, _) = labrig_launch::config::LaunchConfig::load(&path)
                    .unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
                // The launch file says which node reads each config: the table must agree, so
                // each config below is loaded by the node that will really read it.
                for n in &cfg.nodes {
                    match &n.config {
                        Some(c) => {
                            let c = path.parent().unwrap().join(c);
                            let c = c.strip_prefix(&root).unwrap_or(&c).to_string_lossy().into_owned();
                            assert!(
                                matches!(reader_of(&c), Some(Reader::Node(p)) if p == n.program),
                                "{rel}: node {} runs {} with {c}, which `REAL_CONFIGS` gives to {:?}",
                                n.name,
                                n.program,
                                reader_of(&c)
                            );
                        }
                        None => {
                            without_config.insert(n.program.clone());
                        }
                    }
                }
            }
            Reader::Node(program) => load_real(program, Some(&path)),
            Reader::NotAConfig(_) => {}
        }
    }
    for program in &without_config {
        if !NOT_LOADED.iter().any(|(p, _)| p == program) {
            load_real(program, None);
        }
    }
    // An entry for a program no launch file starts without a config excuses nothing: stale.
    for (program, _) in NOT_LOADED {
        assert!(without_config.contains(program), "NOT_LOADED names {program}, which no launch file starts");
    }
}

/// `--set k=v` for one node, no file.
fn with_set<N: Node>(key: &str, value: &str, after: impl Fn(&N::Config)) -> Result<(), String>
where
    N::Flags: clap::FromArgMatches,
{
    load_node::<N>(None, vec![(key.to_owned(), value.to_owned())], after)
}

/// The teleop node's keyboard thread sleeps `1 / input.keyboard_hz` and its adb thread
/// `input.reconnect_s`: `keyboard_hz = 1e-300` and `reconnect_s = 1e300` passed the checks and
/// panicked the input thread (`Duration::from_secs_f64`: value too big); `reconnect_s = 1e19`
/// overflowed `Instant + Duration`. Now refused, naming the key.
#[test]
fn a_teleop_keyboard_rate_or_reconnect_time_no_duration_can_hold_is_refused() {
    use labrig_quest_teleop::TeleopNode;
    for (key, value) in [("input.keyboard_hz", "1e-300"), ("input.reconnect_s", "1e300"), ("input.reconnect_s", "1e19")]
    {
        let e = with_set::<TeleopNode>(key, value, teleop_after).unwrap_err();
        assert!(e.contains(key), "{e}");
    }
}

// ---- findings: the inputs that failed once, kept as regression tests --------------------

/// Finding (nodes/control/src/node.rs): `source_timeout_s` and `teleop_max_age_s` are checked
/// finite and > 0 only; `1e300` passes and `Duration::from_secs_f64` panics when the node
/// starts (`1e19`: `Instant + Duration` overflows).
#[test]
fn a_control_timeout_no_duration_can_hold_is_refused() {
    use labrig_control::ControlNode;
    for (key, value) in [("source_timeout_s", "1e300"), ("source_timeout_s", "1e19"), ("teleop_max_age_s", "1e300")] {
        let r = with_set::<ControlNode>(key, value, |c| {
            sleepable("source_timeout_s", c.source_timeout_s);
            sleepable("teleop_max_age_s", c.teleop_max_age_s);
        });
        assert!(r.is_err(), "{key} = {value} is accepted");
    }
}

/// Finding (nodes/gripper/src/node.rs): `activation_timeout_s` is checked finite and > 0 only;
/// `1e300` passes and `Duration::from_secs_f64` panics at start, `1e19` overflows the
/// activation deadline (`Instant::now() + within`, nodes/gripper/src/driver.rs).
#[test]
fn a_gripper_activation_timeout_no_duration_can_hold_is_refused() {
    use labrig_gripper::GripperNode;
    for value in ["1e300", "1e19"] {
        let r = with_set::<GripperNode>("activation_timeout_s", value, |c| {
            sleepable("activation_timeout_s", c.activation_timeout_s)
        });
        assert!(r.is_err(), "activation_timeout_s = {value} is accepted");
    }
}

/// Finding (nodes/recorder/src/node.rs): `rejoin_wait_s` is checked finite and >= 0 only;
/// `1e300` passes and `Duration::from_secs_f64(rejoin_wait_s)` panics when the recorder starts.
#[test]
fn a_recorder_rejoin_wait_no_duration_can_hold_is_refused() {
    use labrig_recorder::RecorderNode;
    let r = with_set::<RecorderNode>("rejoin_wait_s", "1e300", |c| sleepable("rejoin_wait_s", c.rejoin_wait_s));
    assert!(r.is_err(), "rejoin_wait_s = 1e300 is accepted");
}

/// Finding (nodes/labrig/src/launch.rs): `LaunchConfig::validate`'s errors (no node, a
/// duplicate, an unknown program, a cycle, a missing config file) name the node but not the
/// launch file, and `labrig launch` prints them as they are.
#[test]
fn a_launch_config_rule_error_names_the_file() {
    let origin = launch_configs().join("sim_droid.toml");
    let text = "[rig]\nname = \"r\"\n[[node]]\nname = \"a\"\nprogram = \"rm\"\nhealth = \"/x\"\n";
    let e = labrig_launch::config::LaunchConfig::parse(text, &origin).unwrap_err();
    assert!(format!("{e:#}").contains(&origin.display().to_string()), "{e:#}");
}

/// Finding (sim_bridge/src/bridge.rs): a bad `hardware_prefix` in the bridge's config file is
/// reported as `--hardware-prefix ":" must look like /sim`: the flag, not the key the file set.
#[test]
fn the_bridge_s_hardware_prefix_rule_names_the_config_key() {
    let e = load_node::<labrig_sim_bridge::bridge::BridgeNode>(Some("hardware_prefix = \":\"\n"), Vec::new(), |_| {})
        .unwrap_err();
    assert!(e.contains("`hardware_prefix`") || e.contains("hardware_prefix:"), "{e}");
}

/// Every node's config, edited, mangled and overridden: loaded (and then checked by the node's
/// own assertions) or refused naming the file and the key. Counted per node over the cases, so
/// that a generator whose cases never load, or never break a config, fails.
#[test]
fn every_node_config_loads_or_names_the_problem() {
    use proptest::test_runner::TestRunner;
    const NODES: [&str; 8] = ["franka", "gripper", "recorder", "control", "teleop", "sim", "station", "cameras"];
    let tallies = std::cell::RefCell::new([(0u32, 0u32); 8]);
    let mut runner = TestRunner::new(cases(96));
    runner
        .run(&case(), |c| {
            let s = subjects();
            let results = [
                run_case::<labrig_franka::FrankaNode>(&s[0], &c, franka_after),
                run_case::<labrig_gripper::GripperNode>(&s[1], &c, gripper_after),
                run_case::<labrig_recorder::RecorderNode>(&s[2], &c, |_| {}),
                run_case::<labrig_control::ControlNode>(&s[3], &c, |_| {}),
                run_case::<labrig_quest_teleop::TeleopNode>(&s[4], &c, teleop_after),
                run_case::<labrig_sim_bridge::bridge::BridgeNode>(&s[5], &c, bridge_after),
                run_case::<labrig_station::StationNode>(&s[6], &c, station_after),
                run_case::<labrig_cameras::CamerasNode>(&s[7], &c, |_| {}),
            ];
            let mut t = tallies.borrow_mut();
            for (k, r) in results.iter().enumerate() {
                if r.is_ok() {
                    t[k].0 += 1;
                } else {
                    t[k].1 += 1;
                }
            }
            Ok(())
        })
        .unwrap();
    let t = tallies.into_inner();
    eprintln!("(loaded, refused) of 96 per node: {:?}", NODES.iter().zip(t).collect::<Vec<_>>());
    for (name, (loaded, refused)) in NODES.iter().zip(t) {
        assert!(loaded >= 10 && refused >= 10, "{name}: {loaded} loaded and {refused} refused of 96 cases");
    }
}
