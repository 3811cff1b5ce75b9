//! Layering, checked on the real dependency graph (`cargo tree`, `cargo metadata`):
//! - msgs is a leaf (no async runtime, DDS or shared memory);
//! - the libraries (episode, arm, sim) carry no transport: no tokio, DDS or iceoryx2, so the
//!   trainer and the dataset tools read episodes and step the sim without a node's baggage;
//! - heavy native crates stay where they belong: tch in the policy crates, opencv in
//!   calibration and the camera node, MuJoCo in the sim crates, libhdf5 in droid;
//! - the CLI links neither MuJoCo nor libhdf5;
//! - every crate's folder is named after it, and ARCHITECTURE.md's crate table lists every
//!   workspace crate with its folder and exactly the labrig crates it depends on.

use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

fn cargo() -> Command {
    let mut c = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    c.current_dir(labrig_tests::repo_root());
    c
}

fn deps(package: &str) -> Vec<String> {
    let out = cargo()
        .args(["tree", "--offline", "-p", package, "-e", "normal,build", "--prefix", "none", "--format", "{p}"])
        .output()
        .expect("cargo tree");
    assert!(out.status.success(), "cargo tree -p {package}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .map(str::to_owned)
        .collect()
}

fn matches(dep: &str, names: &[&str]) -> bool {
    names.iter().any(|f| dep == *f || dep.starts_with(&format!("{f}-")))
}

fn assert_free_of(package: &str, forbidden: &[&str]) {
    let deps = deps(package);
    assert!(deps.len() > 1, "cargo tree listed nothing for {package}");
    let bad: BTreeSet<&String> = deps.iter().filter(|d| matches(d, forbidden)).collect();
    assert!(bad.is_empty(), "{package} depends on {bad:?}");
}

const TRANSPORT: &[&str] = &["tokio", "rustdds", "ros2-client", "iceoryx2", "mio"];
const TORCH: &[&str] = &["tch", "torch-sys"];
const OPENCV: &[&str] = &["opencv", "opencv-sys"];
const MUJOCO: &[&str] = &["mujoco-rs", "mujoco"];
const HDF5: &[&str] = &["hdf5-metno", "hdf5-metno-sys"];

/// The workspace's crates: name -> (folder relative to the root, labrig crates it depends on
/// normally).
fn workspace() -> BTreeMap<String, (String, BTreeSet<String>)> {
    let out = cargo().args(["metadata", "--offline", "--format-version", "1", "--no-deps"]).output().unwrap();
    assert!(out.status.success(), "cargo metadata: {}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let root = std::fs::canonicalize(labrig_tests::repo_root()).unwrap();
    let mut crates = BTreeMap::new();
    for p in v["packages"].as_array().unwrap() {
        let name = p["name"].as_str().unwrap().to_owned();
        let manifest = std::path::PathBuf::from(p["manifest_path"].as_str().unwrap());
        let folder = manifest.parent().unwrap().strip_prefix(&root).unwrap().display().to_string();
        let labrig: BTreeSet<String> = p["dependencies"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| d["kind"].is_null())
            .filter_map(|d| d["name"].as_str())
            .filter(|d| d.starts_with("labrig"))
            .map(str::to_owned)
            .collect();
        crates.insert(name, (folder, labrig));
    }
    crates
}

#[test]
fn msgs_is_a_leaf() {
    let mut forbidden = [TORCH, OPENCV, MUJOCO, HDF5].concat();
    forbidden.extend(TRANSPORT);
    assert_free_of("labrig-msgs", &forbidden);
}

#[test]
fn the_libraries_carry_no_transport() {
    for lib in ["labrig-episode", "labrig-arm", "labrig-sim"] {
        assert_free_of(lib, TRANSPORT);
    }
    assert_free_of("labrig-episode", &[MUJOCO, HDF5, TORCH, OPENCV].concat());
    assert_free_of("labrig-arm", &[MUJOCO, HDF5, TORCH, OPENCV, &["franka-rs"]].concat());
}

#[test]
fn the_check_sees_real_dependencies() {
    // Guards the guard: runtime does depend on rustdds and the sim on MuJoCo.
    assert!(deps("labrig-runtime").iter().any(|d| d == "rustdds"));
    assert!(deps("labrig-sim").iter().any(|d| matches(d, MUJOCO)));
    assert!(deps("labrig-droid").iter().any(|d| d == "hdf5-metno-sys"), "the guard sees hdf5");
    assert!(deps("labrig-policies").iter().any(|d| d == "torch-sys"), "the guard sees libtorch");
}

#[test]
fn heavy_native_crates_stay_where_they_belong() {
    let allowed: [(&[&str], &[&str]); 4] = [
        (TORCH, &["labrig-policies", "labrig-policy-server"]),
        (OPENCV, &["labrig-calibration", "labrig-cameras"]),
        (MUJOCO, &["labrig-sim", "labrig-sim-bridge"]),
        // The dataset index reads DROID raw trajectory.h5 files through labrig-droid.
        (HDF5, &["labrig-droid", "labrig-dataset"]),
    ];
    let mut bad = Vec::new();
    for name in workspace().keys().filter(|n| n.as_str() != "labrig-tests") {
        let d = deps(name);
        for (heavy, owners) in &allowed {
            if !owners.contains(&name.as_str())
                && let Some(h) = d.iter().find(|d| matches(d, heavy))
            {
                bad.push(format!("{name} depends on {h} (allowed in {owners:?} only)"));
            }
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

#[test]
fn the_cli_links_neither_mujoco_nor_libhdf5() {
    // `labrig` execs labrig-sim (MuJoCo) and labrig-droid (libhdf5) from beside itself, so the
    // CLI runs where neither library is installed.
    assert_free_of("labrig", &[MUJOCO, HDF5].concat());
    assert_free_of("labrig-droid", &[TORCH, OPENCV, MUJOCO].concat());
}

#[test]
fn every_crate_lives_in_the_folder_of_its_name() {
    let mut bad = Vec::new();
    for (name, (folder, _)) in workspace() {
        let last = folder.rsplit('/').next().unwrap().replace('_', "-");
        let expected = if last == "labrig" { "labrig".to_owned() } else { format!("labrig-{last}") };
        if name != expected {
            bad.push(format!("{name} is in {folder}/ (that folder holds {expected})"));
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

#[test]
fn architecture_md_lists_every_crate_as_it_is() {
    let text = std::fs::read_to_string(labrig_tests::repo_root().join("ARCHITECTURE.md")).unwrap();
    let begin = text.find("<!-- crates:begin -->").expect("ARCHITECTURE.md has a <!-- crates:begin --> marker");
    let end = text.find("<!-- crates:end -->").expect("ARCHITECTURE.md has a <!-- crates:end --> marker");
    // | layer | `crate` | `folder/` | `labrig-a`, `labrig-b` | what else | never |
    let mut listed: BTreeMap<String, (String, BTreeSet<String>)> = BTreeMap::new();
    for line in text[begin..end].lines().filter(|l| l.starts_with('|')) {
        let cells: Vec<&str> = line.trim_matches('|').split('|').map(str::trim).collect();
        let Some(name) = cells.get(1).and_then(|c| c.strip_prefix('`')).and_then(|c| c.strip_suffix('`')) else {
            continue;
        };
        let folder = cells[2].trim_matches('`').trim_end_matches('/').to_owned();
        let uses: BTreeSet<String> = cells[3]
            .split(',')
            .map(|c| c.trim().trim_matches('`').to_owned())
            .filter(|c| c.starts_with("labrig"))
            .collect();
        assert!(listed.insert(name.to_owned(), (folder, uses)).is_none(), "{name} is listed twice");
    }
    let actual = workspace();
    let mut bad = Vec::new();
    for (name, (folder, uses)) in &actual {
        match listed.get(name) {
            None => bad.push(format!("{name} ({folder}/) is not in ARCHITECTURE.md's crate table")),
            Some((f, _)) if f != folder => bad.push(format!("{name}: the table says {f}/, it is in {folder}/")),
            Some((_, u)) if u != uses => bad.push(format!("{name}: the table says it uses {u:?}, it uses {uses:?}")),
            Some(_) => {}
        }
    }
    for name in listed.keys().filter(|n| !actual.contains_key(*n)) {
        bad.push(format!("the table lists {name}, which is not a workspace crate"));
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

#[test]
fn the_readme_wrapper_builds_packages_and_programs_that_exist() {
    // scripts/labrig (the README's `./scripts/labrig demo`) builds `-p <package> --bin <program>`
    // pairs: each package must exist and own that program (a crate rename once broke it).
    let script = std::fs::read_to_string(labrig_tests::repo_root().join("scripts/labrig")).unwrap();
    // Every `cargo build` line (the policy program has its own, for the commands that run it).
    let line: String = script.lines().filter(|l| l.contains("cargo build")).collect::<Vec<_>>().join(" ");
    let words: Vec<&str> = line.split_whitespace().collect();
    let out = cargo().args(["metadata", "--offline", "--format-version", "1", "--no-deps"]).output().unwrap();
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let bins: BTreeMap<String, BTreeSet<String>> = v["packages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let targets = p["targets"].as_array().unwrap();
            let b = targets
                .iter()
                .filter(|t| t["kind"].as_array().unwrap().iter().any(|k| k == "bin"))
                .map(|t| t["name"].as_str().unwrap().to_owned())
                .collect();
            (p["name"].as_str().unwrap().to_owned(), b)
        })
        .collect();
    let mut pairs = 0;
    for w in words.windows(4) {
        if w[0] == "-p" && w[2] == "--bin" {
            pairs += 1;
            let owned = bins.get(w[1]).unwrap_or_else(|| panic!("scripts/labrig builds -p {}: no such package", w[1]));
            assert!(owned.contains(w[3]), "scripts/labrig builds --bin {} from {}, which has {owned:?}", w[3], w[1]);
        }
    }
    // Every program the launcher and the CLI run is built.
    assert!(pairs >= 9, "{pairs} -p/--bin pairs in: {line}");
    assert!(line.contains("-p labrig-policies --bin labrig-policies"), "{line}");
}

#[test]
fn the_launch_library_and_the_doctor_depend_on_no_command() {
    // What starts and supervises rigs is a library (labrig-launch); the CLI crate (labrig) is
    // its commands. Neither the library nor the doctor may reach back into the commands.
    for lib in ["labrig-launch", "labrig-doctor"] {
        let d = deps(lib);
        assert!(d.len() > 1, "cargo tree listed nothing for {lib}");
        assert!(
            !d.iter().any(|p| p == "labrig"),
            "{lib} depends on the CLI crate `labrig` (move what it needs into labrig-launch)"
        );
    }
    assert!(deps("labrig").iter().any(|p| p == "labrig-launch"), "the guard sees the CLI's library");
}

/// The CLI crate's command modules (a file `src/<name>.rs`, or a folder `src/<name>/`), less
/// `cli` (the dispatcher, which knows them all), `lib` and `main`.
fn command_modules(src: &std::path::Path) -> BTreeSet<String> {
    std::fs::read_dir(src)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter_map(|p| {
            let stem = p.file_stem()?.to_str()?.to_owned();
            (p.is_dir() || p.extension().is_some_and(|x| x == "rs")).then_some(stem)
        })
        .filter(|m| !["cli", "lib", "main"].contains(&m.as_str()))
        .collect()
}

/// `(file, line, imported command)` for every reference from one command module's sources to
/// another's: `crate::<other>`, `super::<other>` in a top-level module (its `super` is the
/// crate), a `use crate::{.., <other>, ..}` group (nested or over several lines), or the crate
/// by its own name (`labrig::...`). Comments are left out.
fn command_imports(src: &std::path::Path) -> Vec<(String, usize, String)> {
    let commands = command_modules(src);
    let mut found = Vec::new();
    for module in &commands {
        let mut files = Vec::new();
        let file = src.join(format!("{module}.rs"));
        if file.is_file() {
            files.push(file);
        }
        let dir = src.join(module);
        if dir.is_dir() {
            for e in walk(&dir) {
                files.push(e);
            }
        }
        let shown = |f: &std::path::Path| f.strip_prefix(src).unwrap().display().to_string();
        for f in files {
            let top_level = f.parent() == Some(src);
            let text = std::fs::read_to_string(&f).unwrap();
            // The code of each line, comments cut off; kept line by line for the line numbers.
            let code: Vec<&str> = text.lines().map(|l| l.split("//").next().unwrap_or("")).collect();
            let roots: &[&str] = if top_level { &["crate::", "super::"] } else { &["crate::"] };
            for (n, line) in code.iter().enumerate() {
                for other in commands.iter().filter(|c| *c != module) {
                    let direct = roots.iter().any(|r| {
                        [
                            format!("{r}{other}::"),
                            format!("{r}{other};"),
                            format!("{r}{other} "),
                            format!("{r}{other},"),
                        ]
                        .iter()
                        .any(|d| line.contains(d.as_str()))
                    });
                    if direct {
                        found.push((shown(&f), n + 1, other.clone()));
                    }
                }
                // The crate by its own name (`labrig::demo::...`) is the same import.
                if line
                    .split(|c: char| !(c.is_alphanumeric() || c == '_' || c == ':'))
                    .any(|w| w.starts_with("labrig::"))
                {
                    found.push((shown(&f), n + 1, "labrig".to_owned()));
                }
            }
            // Groups: `crate::{a, b::{c}, d}` may span lines; the names at its top level.
            let joined = code.join("\n");
            for root in roots {
                let open = format!("{root}{{");
                for (at, _) in joined.match_indices(open.as_str()) {
                    let line = joined[..at].matches('\n').count() + 1;
                    for name in group_heads(&joined[at + open.len()..]) {
                        if &name != module && commands.contains(&name) {
                            found.push((shown(&f), line, name));
                        }
                    }
                }
            }
        }
    }
    found.sort();
    found.dedup();
    found
}

/// The first path segment of each item at the top level of a `{...}` group whose text starts
/// after its opening brace: `demo::run, other, x::{y, z}}` gives demo, other, x.
fn group_heads(rest: &str) -> Vec<String> {
    let (mut depth, mut heads, mut item) = (0usize, Vec::new(), String::new());
    let take = |item: &mut String, heads: &mut Vec<String>| {
        let head = item.trim().split("::").next().unwrap_or("").trim().to_owned();
        if !head.is_empty() {
            heads.push(head);
        }
        item.clear();
    };
    for c in rest.chars() {
        match c {
            '{' => depth += 1,
            '}' if depth == 0 => break,
            '}' => depth -= 1,
            ',' if depth == 0 => take(&mut item, &mut heads),
            _ if depth == 0 => item.push(c),
            _ => {}
        }
    }
    take(&mut item, &mut heads);
    heads
}

fn walk(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
    out
}

#[test]
fn no_command_module_imports_another() {
    let src = labrig_tests::repo_root().join("nodes/labrig/src");
    let commands = command_modules(&src);
    for expected in ["demo", "rollout", "launch", "bench_latency", "experiment", "topic"] {
        assert!(commands.contains(expected), "the check sees the command `{expected}`: {commands:?}");
    }
    let found = command_imports(&src);
    assert!(
        found.is_empty(),
        "command modules import other commands (move what they share into labrig-launch): {found:#?}"
    );
}

#[test]
fn the_command_check_sees_an_import() {
    // Guards the guard: a command that imports another, in a scratch copy of the crate's layout.
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path();
    std::fs::write(src.join("cli.rs"), "use crate::demo;\n").unwrap();
    std::fs::write(src.join("demo.rs"), "pub fn run() {}\n").unwrap();
    std::fs::write(src.join("rollout.rs"), "use crate::{demo::run, other};\n// crate::bench::x in a comment\n")
        .unwrap();
    std::fs::create_dir(src.join("bench")).unwrap();
    std::fs::write(src.join("bench/inner.rs"), "fn f() { crate::rollout::go() }\nuse labrig::demo;\n").unwrap();
    // A group over several lines, nested; `super::` from a top-level module is the crate.
    std::fs::write(
        src.join("topic.rs"),
        "use crate::{\n    other::{x, y},\n    bench::{self},\n};\nfn g() { super::demo::run() }\n",
    )
    .unwrap();
    let found = command_imports(src);
    assert_eq!(
        found,
        vec![
            ("bench/inner.rs".to_owned(), 1, "rollout".to_owned()),
            ("bench/inner.rs".to_owned(), 2, "labrig".to_owned()),
            ("rollout.rs".to_owned(), 1, "demo".to_owned()),
            ("topic.rs".to_owned(), 1, "bench".to_owned()),
            ("topic.rs".to_owned(), 5, "demo".to_owned()),
        ]
    );
}
