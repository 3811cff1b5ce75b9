//! Layering: msgs and runtime never depend on the heavy native crates (tch, mujoco, opencv),
//! the CLI links neither MuJoCo nor libhdf5,
//! and msgs stays a leaf (no async runtime, no DDS, no shared memory). Checked on the real
//! dependency graph with `cargo tree`.

use std::process::Command;

fn deps(package: &str) -> Vec<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["tree", "--offline", "-p", package, "-e", "normal,build", "--prefix", "none", "--format", "{p}"])
        .current_dir(labrig_tests::repo_root())
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

fn assert_free_of(package: &str, forbidden: &[&str]) {
    let deps = deps(package);
    assert!(deps.len() > 1, "cargo tree listed nothing for {package}");
    let bad: Vec<&String> =
        deps.iter().filter(|d| forbidden.iter().any(|f| d.as_str() == *f || d.starts_with(&format!("{f}-")))).collect();
    assert!(bad.is_empty(), "{package} depends on {bad:?}");
}

const HEAVY: &[&str] = &["tch", "torch-sys", "mujoco-rs", "mujoco", "opencv", "opencv-sys"];

#[test]
fn msgs_is_a_leaf() {
    let mut forbidden = HEAVY.to_vec();
    forbidden.extend(["tokio", "rustdds", "ros2-client", "iceoryx2", "mio"]);
    assert_free_of("labrig-msgs", &forbidden);
}

#[test]
fn runtime_has_no_heavy_native_dependencies() {
    assert_free_of("labrig-runtime", HEAVY);
}

#[test]
fn the_check_sees_real_dependencies() {
    // Guards the guard: runtime does depend on rustdds, so the tree lookup works.
    assert!(deps("labrig-runtime").iter().any(|d| d == "rustdds"));
}

#[test]
fn the_cli_links_neither_mujoco_nor_libhdf5() {
    // `labrig` execs labrig-sim (MuJoCo) and labrig-droid (libhdf5) from beside itself, so the
    // CLI runs where neither library is installed.
    assert_free_of("labrig", &["mujoco-rs", "hdf5-metno", "hdf5-metno-sys"]);
    assert_free_of("labrig-droid", HEAVY);
    assert!(deps("labrig-droid").iter().any(|d| d == "hdf5-metno-sys"), "the guard sees hdf5");
}
