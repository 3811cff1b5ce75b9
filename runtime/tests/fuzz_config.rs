//! Bad input never panics: labrig-runtime's config loading, the path every node's TOML takes
//! (`parse_config`, `load_config`, and the node skeleton's `load`: the file, `--set key=value`
//! on the TOML tree, the node's flags, `--domain-id`, `RosConfig::validate`, the node's
//! `validate`). A node of this test's own stands in for the real ones (they depend on this
//! crate; tests/tests/fuzz_config.rs runs every real node's config and the launch files).
//!
//! Each: no panic; a config loads or the error names the file (or `<command line>`) it came
//! from, and a rule's error names its key.

use labrig_msgs::Invalid;
use labrig_runtime::Shutdown;
use labrig_runtime::config::{ConfigError, RosConfig, load_config, parse_config};
use labrig_runtime::node::{CommonFlags, Node, load};
use proptest::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// `n` cases; failures are reported with their minimal input, not persisted (a regression
/// worth keeping becomes a named test below).
fn cases(n: u32) -> ProptestConfig {
    ProptestConfig { cases: n, failure_persistence: None, ..ProptestConfig::default() }
}

/// A config shaped like the nodes': nested tables, an enum, a list, defaults for every key.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct Cfg {
    ros: RosConfig,
    mode: Mode,
    period_s: f64,
    cameras: Vec<String>,
    max_steps: u64,
    priority: u8,
    inner: Inner,
    file: Option<PathBuf>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
enum Mode {
    #[default]
    Lockstep,
    Realtime,
}

#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
struct Inner {
    gain: f64,
    limits: [f64; 3],
}

impl Default for Inner {
    fn default() -> Self {
        Inner { gain: 1.0, limits: [0.1, 0.2, 0.3] }
    }
}

impl Default for Cfg {
    fn default() -> Self {
        Cfg {
            ros: RosConfig::default(),
            mode: Mode::Lockstep,
            period_s: 0.05,
            cameras: vec!["ext1".into()],
            max_steps: 400,
            priority: 80,
            inner: Inner::default(),
            file: None,
        }
    }
}

/// The flags, declared as the nodes declare theirs (each names the key it sets).
#[derive(Debug, Default, clap::Args, Serialize)]
struct Flags {
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    period_s: Option<f64>,
    #[arg(long)]
    #[serde(rename = "inner.gain", skip_serializing_if = "Option::is_none")]
    gain: Option<f64>,
    #[arg(long)]
    #[serde(skip_serializing_if = "Option::is_none")]
    file: Option<PathBuf>,
}

#[derive(Debug)]
struct TestNode;

impl Node for TestNode {
    const NAME: &'static str = "labrig-test";
    const ABOUT: &'static str = "a node for the config properties";
    type Config = Cfg;
    type Flags = Flags;
    type Stats = ();

    fn ros(config: &mut Cfg) -> &mut RosConfig {
        &mut config.ros
    }

    fn validate(c: &Cfg) -> Result<(), Invalid> {
        if !(c.period_s.is_finite() && (0.001..=1.0).contains(&c.period_s)) {
            return Err(Invalid::new("period_s", format!("period_s = {} must be in 0.001..=1", c.period_s)));
        }
        if !c.inner.gain.is_finite() || c.inner.limits.iter().any(|l| !(l.is_finite() && *l > 0.0)) {
            return Err(Invalid::new("inner", "inner: gain and limits must be finite, limits > 0"));
        }
        Ok(())
    }

    async fn run(_config: Cfg, _shutdown: Shutdown) -> anyhow::Result<()> {
        Ok(())
    }
}

/// A config file using every key.
const GOOD: &str = r#"mode = "realtime"
period_s = 0.02
cameras = ["ext1", "wrist"]
max_steps = 100
priority = 90
file = "trace.logcat"

[ros]
domain_id = 7
loopback_only = true
namespace = "/rig1"

[inner]
gain = 0.5
limits = [0.01, 0.02, 0.03]
"#;

/// The error of a config from `origin` names it; a rule's names its key.
fn check_error(e: &ConfigError, origin: &Path) {
    let text = e.to_string();
    assert!(text.contains(&origin.display().to_string()), "the error does not name {}: {text}", origin.display());
    match e {
        ConfigError::Rule { rule, .. } => assert!(!rule.key.is_empty() && text.contains(&rule.message), "{text}"),
        ConfigError::Invalid { key, .. } => assert!(!key.is_empty(), "{text}"),
        ConfigError::Parse { message, .. } => assert!(!message.is_empty(), "{text}"),
        ConfigError::Read { .. } => {}
    }
}

/// The skeleton's `load` on this text (as a file, or none when `text` is `None`), the
/// `--set`s, the flags and `--domain-id`: a config that passes both checks, or a named error.
fn load_with(text: Option<&str>, set: Vec<(String, String)>, flags: Flags, domain_id: Option<u16>) -> Option<Cfg> {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("node.toml");
    if let Some(t) = text {
        std::fs::write(&path, t).unwrap();
    }
    let origin = if text.is_some() { path.clone() } else { PathBuf::from("<command line>") };
    let common = CommonFlags { config: text.map(|_| path.clone()), set, domain_id, json: false, stats_out: None };
    match load::<TestNode>(&common, flags) {
        Ok(cfg) => {
            assert!(cfg.ros.validate(&origin).is_ok() && TestNode::validate(&cfg).is_ok());
            Some(cfg)
        }
        Err(e) => {
            check_error(&e, &origin);
            None
        }
    }
}

/// Keys as `--set` is given them: the config's own, nested and not, and malformed ones.
fn set_key() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::sample::select(vec![
            "period_s",
            "mode",
            "cameras",
            "max_steps",
            "priority",
            "file",
            "ros",
            "ros.domain_id",
            "ros.namespace",
            "ros.loopback_only",
            "inner",
            "inner.gain",
            "inner.limits",
            "inner.gain.x",
            "period_s.x",
            "",
            ".",
            "..",
            "ros.",
            ".ros",
            "a..b",
            " period_s ",
        ])
        .prop_map(str::to_owned),
        "[a-z_.]{0,14}",
        "\\PC{0,6}",
    ]
}

/// Values as `--set` is given them: TOML (numbers of every kind, strings, arrays, inline
/// tables) and bare words.
fn set_value() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::sample::select(vec![
            "1",
            "0",
            "-1",
            "0.05",
            "nan",
            "-inf",
            "inf",
            "1e400",
            "-0.0",
            "9223372036854775808",
            "300",
            "233",
            "\"realtime\"",
            "realtime",
            "\"/x\"",
            "x",
            "[]",
            "[1, 2]",
            "[0.1, 0.2, 0.3]",
            "[[1]]",
            "{}",
            "{gain = 1}",
            "true",
            "\"\"",
            "=",
            "[",
            "{",
            "\"",
            "1979-05-27T07:32:00Z",
        ])
        .prop_map(str::to_owned),
        "\\PC{0,12}",
    ]
}

fn flags() -> impl Strategy<Value = Flags> {
    let num = prop_oneof![Just(f64::NAN), Just(f64::INFINITY), Just(-1.0), Just(0.02), Just(1e300), any::<f64>()];
    (prop::option::of(num.clone()), prop::option::of(num), prop::option::of("\\PC{0,8}"))
        .prop_map(|(period_s, gain, file)| Flags { period_s, gain, file: file.map(PathBuf::from) })
}

/// One edit of a config's text: characters cut, inserted or replaced.
fn text_edit() -> impl Strategy<Value = (prop::sample::Index, usize, String)> {
    (
        any::<prop::sample::Index>(),
        0usize..10,
        prop_oneof![
            "[\\[\\]{}=,.\"'#\\n 0-9a-z_\\-]{0,6}",
            "(nan|inf|1e999|-1|\\[\\[ros\\]\\]|\\[ros\\])",
            "\\PC{0,3}"
        ],
    )
}

proptest! {
    #![proptest_config(cases(256))]

    /// Any text: parsed into the node's config (or a bare table), or refused naming the file.
    #[test]
    fn arbitrary_text_never_panics(s in any::<String>()) {
        let origin = Path::new("any.toml");
        if let Err(e) = parse_config::<Cfg>(&s, origin) {
            check_error(&e, origin);
        }
        if let Err(e) = parse_config::<toml::Table>(&s, origin) {
            check_error(&e, origin);
        }
        let _ = load_with(Some(&s), Vec::new(), Flags::default(), None);
    }

    /// A good config file cut, spliced, characters replaced.
    #[test]
    fn a_mangled_config_never_panics(edits in prop::collection::vec(text_edit(), 1..5)) {
        let mut c: Vec<char> = GOOD.chars().collect();
        for (at, del, ins) in edits {
            let k = at.index(c.len() + 1);
            c.splice(k..(k + del).min(c.len()), ins.chars());
        }
        let _ = load_with(Some(&c.into_iter().collect::<String>()), Vec::new(), Flags::default(), None);
    }

    /// Any `--set`s, flags and `--domain-id`, on the good file or on none.
    #[test]
    fn any_command_line_never_panics(
        set in prop::collection::vec((set_key(), set_value()), 0..5),
        flags in flags(),
        domain_id in prop::option::of(any::<u16>()),
        with_file in any::<bool>(),
    ) {
        let cfg = load_with(with_file.then_some(GOOD), set.clone(), flags, domain_id);
        if let (Some(cfg), Some(d)) = (cfg, domain_id) {
            prop_assert_eq!(cfg.ros.domain_id, d);
        }
    }

    /// `load_config` on a file, and on a path that is not one.
    #[test]
    fn load_config_names_what_it_cannot_read(s in ".{0,60}", missing in any::<bool>()) {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("c.toml");
        if !missing {
            std::fs::write(&p, &s).unwrap();
        }
        if let Err(e) = load_config::<Cfg>(&p) {
            check_error(&e, &p);
        }
    }

    /// Any domain id and namespace: valid or a named key.
    #[test]
    fn ros_config_validation_never_panics(domain_id in any::<u16>(), namespace in "\\PC{0,8}") {
        let ros = RosConfig { domain_id, loopback_only: true, namespace };
        if let Err(e) = ros.validate(Path::new("n.toml")) {
            check_error(&e, Path::new("n.toml"));
        }
    }
}

/// The control for the above: every key of the good file and the command line reach the
/// config.
#[test]
fn the_good_file_and_a_command_line_load() {
    let set = vec![("inner.limits".to_owned(), "[1, 2, 3]".to_owned()), ("mode".to_owned(), "lockstep".to_owned())];
    let cfg = load_with(Some(GOOD), set, Flags { gain: Some(2.0), ..Flags::default() }, Some(3)).unwrap();
    assert_eq!(
        (cfg.mode, cfg.ros.domain_id, cfg.inner.gain, cfg.inner.limits),
        (Mode::Lockstep, 3, 2.0, [1.0, 2.0, 3.0])
    );
    assert_eq!(load_with(None, Vec::new(), Flags::default(), None), Some(Cfg::default()));
}
