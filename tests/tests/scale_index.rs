//! DROID-scale indexing beyond one process (issue 36): `labrig dataset index --shard i/N` run
//! as N Ray tasks (scripts/scale/ray_index.py on a local Ray head, scripts/scale/ray_local.sh)
//! and as a Slurm job array with a dependent merge (scripts/scale/slurm_index.sh on a one-node
//! Slurm, scripts/scale/slurm_local.sh), over DROID raw episodes (h5py, tests/peers/
//! make_droid_raw.py), the committed RLDS shard and a committed labrig episode. Each merged
//! index equals the one-process index (`--shard 0/1`, then `labrig dataset merge`) in every
//! column of every row (pyarrow, tests/peers/query_index.py); a Ray worker killed under its
//! shard (a genuine lost worker: `kill -9` of the worker process) and a failing command are
//! retried and the index is still equal; a shard that keeps failing is named and nothing is
//! merged; DuckDB and pyarrow, hive partitioning on, select the same episodes from the merged
//! index as `labrig dataset retrieve --align camPose,objSpat`. Every daemon listens on
//! 127.0.0.1 only (checked with `ss`); the Ray head takes only drivers holding its token; every
//! wait is bounded.

use labrig_tests::droid_raw::{CAMS, OBJECTS};
use labrig_tests::{cache_dir, labrig_bin, repo_root, workspace_bin};
use serde_json::{Value, json};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

/// Port bases (ray_local.sh and slurm_local.sh pin every port from them): below the ephemeral
/// range, in blocks DDS's port mapping (7400 + 250 domain + 0..~110) leaves free, and apart from
/// the scripts' defaults (22600, 22850), so a developer's head beside the suite does not clash.
const RAY_PORT_BASE: u16 = 23100;
const SLURM_PORT_BASE: u16 = 23350;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn text(out: &Output) -> String {
    labrig_tests::output_text(out)
}

fn venv_python(var: &str, venv: &str) -> PathBuf {
    let p = std::env::var_os(var).map(PathBuf::from).unwrap_or_else(|| cache_dir().join(venv).join("bin/python"));
    assert!(p.exists(), "the venv {} is missing: run `bash scripts/setup.sh`", p.display());
    p
}

/// Ray 2.60, DuckDB, pyarrow (scripts/setup.sh's venv-scale).
fn scale_python() -> PathBuf {
    venv_python("LABRIG_SCALE_PYTHON", "venv-scale")
}

fn labrig() -> PathBuf {
    workspace_bin("labrig-dataset", "labrig-dataset");
    labrig_bin()
}

/// Runs `cmd` to its end, at most `timeout` (then kills it and panics with what it printed).
fn bounded(what: &str, mut cmd: Command, timeout: Duration) -> Output {
    let dir = tempfile::tempdir().unwrap();
    let (o, e) = (dir.path().join("out"), dir.path().join("err"));
    cmd.stdin(Stdio::null()).stdout(std::fs::File::create(&o).unwrap()).stderr(std::fs::File::create(&e).unwrap());
    let mut child = cmd.spawn().unwrap_or_else(|err| panic!("starting {what}: {err}"));
    let deadline = Instant::now() + timeout;
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "{what}: still running after {timeout:?}\nstdout: {}\nstderr: {}",
                std::fs::read_to_string(&o).unwrap_or_default(),
                std::fs::read_to_string(&e).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    Output { status, stdout: std::fs::read(&o).unwrap(), stderr: std::fs::read(&e).unwrap() }
}

fn ok_json(what: &str, out: &Output) -> Value {
    assert!(out.status.success(), "{what}: {}", text(out));
    let last = String::from_utf8_lossy(&out.stdout).lines().rev().find(|l| l.starts_with('{')).map(str::to_owned);
    serde_json::from_str(&last.unwrap_or_default()).unwrap_or_else(|e| panic!("{what}: no JSON ({e}): {}", text(out)))
}

fn labrig_json(args: &[&str]) -> Value {
    let mut cmd = Command::new(labrig());
    cmd.args(args);
    ok_json(&format!("labrig {}", args.join(" ")), &bounded("labrig", cmd, Duration::from_secs(120)))
}

/// The three roots: 14 DROID raw episodes (one damaged), the RLDS shard (9 episodes) and one
/// labrig episode: 16 sources, 23 rows.
fn fixtures(dir: &Path) -> Vec<PathBuf> {
    let raw = dir.join("droid_raw");
    labrig_tests::droid_raw::write(&raw);
    let rlds = dir.join("rlds");
    std::fs::create_dir_all(&rlds).unwrap();
    let shard = "droid_101-train.tfrecord-00000-of-00001";
    std::fs::copy(repo_root().join("tests/fixtures/rlds").join(shard), rlds.join(shard)).unwrap();
    let demo = dir.join("demo/pick_place_seed7");
    std::fs::create_dir_all(&demo).unwrap();
    for f in ["episode_0.mcap", "metadata.yaml"] {
        std::fs::copy(repo_root().join("tests/fixtures/episodes/pick_place_seed7").join(f), demo.join(f)).unwrap();
    }
    vec![raw, rlds, dir.join("demo")]
}

const ROWS: u64 = 23;
const SOURCES: u64 = 16;

/// The one-process index: `--shard 0/1`, then merged.
fn one_process_index(roots: &[PathBuf], out: &Path) -> PathBuf {
    let parts = out.join("parts");
    let mut args = vec!["dataset", "index"];
    args.extend(roots.iter().map(|r| s(r)));
    args.extend(["--out", s(&parts), "--shard", "0/1", "--json"]);
    let r = labrig_json(&args);
    assert_eq!((r["found"].as_u64(), r["indexed"].as_u64()), (Some(SOURCES), Some(ROWS)), "{r}");
    assert_eq!(r["by_format"], json!({"droid_raw": 13, "labrig": 1, "rlds": 9}), "{r}");
    let index = out.join("index");
    let m = labrig_json(&["dataset", "merge", s(&parts), "--out", s(&index), "--json"]);
    assert_eq!((m["rows"].as_u64(), m["shards"].as_u64()), (Some(ROWS), Some(1)), "{m}");
    index
}

/// tests/peers/query_index.py with pyarrow and DuckDB.
fn peer(args: &[&str]) -> Value {
    let mut cmd = Command::new(scale_python());
    cmd.arg(repo_root().join("tests/peers/query_index.py")).args(args);
    ok_json("query_index.py", &bounded("query_index.py", cmd, Duration::from_secs(120)))
}

/// Every column of every row (sorted by source_path) equal, and each hive partition's files
/// leaving the key to the folder name (pyarrow's `read_table(dir)` reads it).
fn assert_same_index(a: &Path, b: &Path) {
    let c = peer(&["compare", s(a), s(b)]);
    assert_eq!(c["equal"], true, "{} and {} differ: {c}", a.display(), b.display());
    assert_eq!((c["rows_a"].as_u64(), c["rows_b"].as_u64()), (Some(ROWS), Some(ROWS)), "{c}");
    assert!(c["columns_a"].as_array().unwrap().len() > 50, "{c}");
    for p in c["partitions_consistent"].as_array().unwrap() {
        assert_ne!(p, &json!(false), "a partition's file holds the key column too: {c}");
    }
    // labrig reads both layouts alike.
    let st = |i: &Path| labrig_json(&["dataset", "stats", "--index", s(i), "--json"]);
    let (sa, sb) = (st(a), st(b));
    assert_eq!(sa, sb);
    assert_eq!(sa["episodes"], ROWS, "{sa}");
}

/// Listening TCP sockets (`ss -ltnpH`) of the given processes: (local address, process).
fn listening(pids: &BTreeSet<u32>) -> Vec<(String, String)> {
    let out = Command::new("ss").args(["-ltnpH"]).output().expect("ss (iproute2)");
    assert!(out.status.success(), "ss: {}", text(&out));
    let mut found = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let cols: Vec<&str> = line.split_whitespace().collect();
        let (Some(local), Some(procs)) = (cols.get(3), cols.last()) else { continue };
        // users:(("raylet",pid=2112,fd=30),...)
        let owners: Vec<u32> = procs.split("pid=").skip(1).filter_map(|p| p.split(',').next()?.parse().ok()).collect();
        if owners.iter().any(|p| pids.contains(p)) {
            found.push((local.to_string(), procs.to_string()));
        }
    }
    found
}

fn assert_loopback_only(what: &str, pids: &BTreeSet<u32>, at_least: usize) {
    let socks = listening(pids);
    assert!(socks.len() >= at_least, "{what}: {} listening sockets, expected {at_least}+: {socks:?}", socks.len());
    for (addr, procs) in &socks {
        assert!(
            addr.starts_with("127.0.0.1:") || addr.starts_with("[::ffff:127.0.0.1]:") || addr.starts_with("[::1]:"),
            "{what}: {procs} listens on {addr}, not loopback"
        );
    }
}

/// The processes of a process group.
fn group(pgid: u32) -> BTreeSet<u32> {
    let out = Command::new("ps").args(["-o", "pid=", "-g", &pgid.to_string()]).output().unwrap();
    String::from_utf8_lossy(&out.stdout).split_whitespace().filter_map(|p| p.parse().ok()).collect()
}

/// A local Ray head (scripts/scale/ray_local.sh) stopped on drop, whatever the test did.
struct RayHead {
    dir: tempfile::TempDir,
    address: String,
}

impl RayHead {
    fn start(base: u16) -> RayHead {
        // Short: Ray's Unix sockets live under it.
        let dir = tempfile::Builder::new().prefix("lr-ray").tempdir_in("/tmp").unwrap();
        let head = RayHead { dir, address: format!("127.0.0.1:{base}") };
        let mut cmd = Command::new(repo_root().join("scripts/scale/ray_local.sh"));
        cmd.args(["start", s(head.dir.path()), &base.to_string()]).env("LABRIG_SCALE_PYTHON", scale_python());
        let out = bounded("ray_local.sh start", cmd, Duration::from_secs(120));
        assert!(out.status.success(), "ray_local.sh start: {}", text(&out));
        assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), head.address);
        // Token authentication, with a token of the head's own that only its user reads.
        use std::os::unix::fs::PermissionsExt;
        let token = std::fs::metadata(head.dir.path().join("auth_token")).unwrap();
        assert_eq!((token.len(), token.permissions().mode() & 0o777), (64, 0o600));
        head
    }

    fn processes(&self) -> BTreeSet<u32> {
        let pgid: u32 = std::fs::read_to_string(self.dir.path().join("pgid")).unwrap().trim().parse().unwrap();
        group(pgid)
    }
}

impl Drop for RayHead {
    fn drop(&mut self) {
        let mut cmd = Command::new(repo_root().join("scripts/scale/ray_local.sh"));
        cmd.args(["stop", s(self.dir.path())]);
        let _ = bounded("ray_local.sh stop", cmd, Duration::from_secs(60));
    }
}

/// ray_index.py against the head; its summary (--json) and what it printed.
fn ray_index(head: &RayHead, roots: &[PathBuf], out: &Path, labrig: &Path, extra: &[&str]) -> (Output, Option<Value>) {
    let mut cmd = Command::new(scale_python());
    cmd.arg(repo_root().join("scripts/scale/ray_index.py"))
        .args(roots)
        .args(["--out", s(out), "--shards", "4", "--address", &head.address, "--labrig", s(labrig)])
        .args(["--num-cpus-per-task", "1", "--memory-per-task", "256M", "--json"])
        // The head's own token (ray_local.sh: token authentication on).
        .args(["--auth-token-path", s(&head.dir.path().join("auth_token"))])
        .args(extra);
    let o = bounded("ray_index.py", cmd, Duration::from_secs(300));
    let summary = String::from_utf8_lossy(&o.stdout).lines().rev().find_map(|l| serde_json::from_str(l).ok());
    (o, summary)
}

fn shard_names(v: &Value, key: &str) -> Vec<String> {
    v[key].as_array().unwrap().iter().map(|e| e["shard"].as_str().unwrap().to_owned()).collect()
}

/// A `--labrig` stand-in: the real labrig, except `shard`'s first attempt (no marker yet),
/// which does `action` (a shell snippet; $PPID is the Ray worker that runs it).
fn wrapper(dir: &Path, name: &str, shard: &str, action: &str) -> PathBuf {
    let path = dir.join(name);
    let marker = dir.join(format!("{name}.marker"));
    std::fs::write(
        &path,
        format!(
            "#!/bin/sh\ncase \" $* \" in\n*\" --shard {shard} \"*)\n    if [ ! -e '{m}' ]; then\n        {action}\n    fi ;;\nesac\nexec '{labrig}' \"$@\"\n",
            m = marker.display(),
            labrig = labrig().display()
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    path
}

#[test]
fn ray_tasks_index_the_shards_survive_a_killed_worker_and_merge_to_the_one_process_index() {
    let dir = tempfile::tempdir().unwrap();
    let roots = fixtures(&dir.path().join("data"));
    let one = one_process_index(&roots, &dir.path().join("one"));
    let head = RayHead::start(RAY_PORT_BASE);
    assert_loopback_only("the Ray head", &head.processes(), 9);

    // Four shards, one task each.
    let out = dir.path().join("ray");
    let (o, sum) = ray_index(&head, &roots, &out, &labrig(), &[]);
    let sum = sum.unwrap_or_else(|| panic!("ray_index.py printed no summary: {}", text(&o)));
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(shard_names(&sum, "ok"), (0..4).map(|i| format!("part-{i:05}-of-00004")).collect::<Vec<_>>(), "{sum}");
    assert_eq!((sum["sources"].as_u64(), sum["episodes"].as_u64()), (Some(SOURCES), Some(ROWS)), "{sum}");
    assert_eq!(sum["retried"], json!([]), "{sum}");
    assert_eq!(sum["resources_per_task"], json!({"num_cpus": 1.0, "memory": 256 * 1024 * 1024}), "{sum}");
    // Progress, shard by shard, as they finish (stderr with --json).
    let progress = String::from_utf8_lossy(&o.stderr);
    for i in 0..4 {
        assert!(progress.contains(&format!("part-{i:05}-of-00004: ")), "{progress}");
    }
    let index = PathBuf::from(sum["index"].as_str().unwrap());
    assert_eq!(sum["merge"]["report"]["shards"], 4, "{sum}");
    let meta: Value = serde_json::from_str(&std::fs::read_to_string(index.join("_index.json")).unwrap()).unwrap();
    assert_eq!((meta["rows"].as_u64(), meta["shards"].as_u64()), (Some(ROWS), Some(4)), "{meta}");
    assert_same_index(&one, &index);
    // The flat one-process part and the merged Ray index: the same rows too.
    assert_same_index(&dir.path().join("one/parts"), &index);
    // While it ran, a driver and its workers joined the head: still nothing off loopback.
    assert_loopback_only("the Ray head after a run", &head.processes(), 9);

    // A lost worker: the wrapper kills the Ray worker process running shard 2's task
    // (`kill -9 $PPID`); Ray retries the task on a new worker.
    let killer = wrapper(
        dir.path(),
        "kill_worker.sh",
        "2/4",
        "tr '\\0' ' ' </proc/$PPID/cmdline >\"$0.marker\"; echo \" pid $PPID\" >>\"$0.marker\"; kill -9 $PPID; exit 137",
    );
    let out_k = dir.path().join("ray_killed");
    let (o, sum) = ray_index(&head, &roots, &out_k, &killer, &[]);
    let sum = sum.unwrap_or_else(|| panic!("ray_index.py printed no summary: {}", text(&o)));
    assert!(o.status.success(), "{}", text(&o));
    let killed = std::fs::read_to_string(dir.path().join("kill_worker.sh.marker")).unwrap();
    assert!(killed.starts_with("ray::"), "the wrapper's parent was not a Ray worker: {killed}");
    let pid: i32 = killed.rsplit("pid ").next().unwrap().trim().parse().unwrap();
    assert!(!Path::new(&format!("/proc/{pid}")).exists(), "worker {pid} still alive");
    assert_eq!(sum["retried"], json!([{"shard": "part-00002-of-00004", "attempts": 2}]), "{sum}");
    assert_eq!(sum["failed"], json!([]), "{sum}");
    let progress = String::from_utf8_lossy(&o.stderr);
    assert!(progress.contains("part-00002-of-00004 was retried: 2 attempts"), "{progress}");
    assert_same_index(&one, Path::new(sum["index"].as_str().unwrap()));

    // A failing command (exit 3 on shard 1's first attempt) is retried too (retry_exceptions).
    let flaky = wrapper(dir.path(), "fail_once.sh", "1/4", "touch \"$0.marker\"; echo injected >&2; exit 3");
    let out_f = dir.path().join("ray_flaky");
    let (o, sum) = ray_index(&head, &roots, &out_f, &flaky, &[]);
    let sum = sum.unwrap_or_else(|| panic!("ray_index.py printed no summary: {}", text(&o)));
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(sum["retried"], json!([{"shard": "part-00001-of-00004", "attempts": 2}]), "{sum}");
    assert_same_index(&one, Path::new(sum["index"].as_str().unwrap()));

    // A shard that keeps failing: named, exit non-zero, nothing merged.
    let broken = dir.path().join("broken.sh");
    std::fs::write(
        &broken,
        format!(
            "#!/bin/sh\ncase \" $* \" in *\" --shard 3/4 \"*) echo 'disk gone' >&2; exit 3;; esac\nexec '{}' \"$@\"\n",
            labrig().display()
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&broken, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out_b = dir.path().join("ray_broken");
    let (o, sum) = ray_index(&head, &roots, &out_b, &broken, &["--max-retries", "1"]);
    let sum = sum.unwrap_or_else(|| panic!("ray_index.py printed no summary: {}", text(&o)));
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert_eq!(shard_names(&sum, "failed"), vec!["part-00003-of-00004"], "{sum}");
    assert_eq!(sum["failed"][0]["attempts"], 2, "{sum}");
    assert!(sum["failed"][0]["error"].as_str().unwrap().contains("disk gone"), "{sum}");
    assert!(String::from_utf8_lossy(&o.stderr).contains("shards failed: part-00003-of-00004"), "{}", text(&o));
    assert!(sum["merge"].is_null() && !out_b.join("index").exists(), "{sum}");
    // Run again with a working labrig: the three good parts are reused, the missing one made.
    let (o, sum) = ray_index(&head, &roots, &out_b, &labrig(), &[]);
    let sum = sum.unwrap_or_else(|| panic!("ray_index.py printed no summary: {}", text(&o)));
    assert!(o.status.success(), "{}", text(&o));
    let indexed: Vec<(String, u64)> = sum["ok"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["shard"].as_str().unwrap().to_owned(), r["indexed"].as_u64().unwrap()))
        .collect();
    assert_eq!(indexed.len(), 4, "every shard reported: {indexed:?}");
    for (shard, n) in &indexed {
        assert_eq!(*n == 0, shard != "part-00003-of-00004", "only the missing shard is indexed again: {indexed:?}");
    }
    assert_same_index(&one, Path::new(sum["index"].as_str().unwrap()));

    // DuckDB and pyarrow (hive partitioning on) select what `labrig dataset retrieve` does for
    // camPose + objSpat (camera region 0, object region 0).
    let target = dir.path().join("target.toml");
    std::fs::write(
        &target,
        format!(
            "cameras = [[{}, {}, {}]]\nobject_position = [{}, {}, {}]\n",
            CAMS[0][0], CAMS[0][1], CAMS[0][2], OBJECTS[0][0], OBJECTS[0][1], OBJECTS[0][2]
        ),
    )
    .unwrap();
    let manifest = dir.path().join("manifest.json");
    let r = labrig_json(&[
        "dataset",
        "retrieve",
        "--index",
        s(&index),
        "--target",
        s(&target),
        "--align",
        "camPose,objSpat",
        "--out",
        s(&manifest),
        "--json",
    ]);
    let m: Value = serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    let retrieved: Vec<String> = {
        let mut v: Vec<String> =
            m["episodes"].as_array().unwrap().iter().map(|e| e["path"].as_str().unwrap().to_owned()).collect();
        v.sort();
        v
    };
    // Three DROID raw episodes of camera and object region 0 and two RLDS ones.
    assert_eq!(retrieved.len(), 5, "{r}");
    assert_eq!(retrieved.iter().filter(|p| p.contains("#")).count(), 2, "{retrieved:?}");
    let q = json!({"cameras": [&CAMS[0][..3]], "cam_xy": 0.2, "cam_z": 0.1, "box_centre": OBJECTS[0], "box": [0.6, 0.6, 0.3]});
    let got = peer(&["query", s(&index), &q.to_string()]);
    assert_eq!(got["rows"], ROWS, "{got}");
    assert_eq!(got["duckdb_by_format"], json!({"droid_raw": 13, "labrig": 1, "rlds": 9}), "{got}");
    assert_eq!(got["pyarrow"], json!(retrieved), "pyarrow against retrieve: {got}");
    assert_eq!(got["duckdb"], json!(retrieved), "DuckDB against retrieve: {got}");
}

/// A one-node Slurm on 127.0.0.1 (scripts/scale/slurm_local.sh: munged, slurmctld, slurmd with
/// a private slurm.conf, key and state), stopped on drop.
struct Slurm {
    dir: tempfile::TempDir,
}

impl Slurm {
    fn start(base: u16) -> Slurm {
        for d in ["munged", "slurmctld", "slurmd", "sbatch"] {
            let found = ["/usr/sbin", "/usr/bin"].iter().any(|p| Path::new(p).join(d).exists());
            assert!(
                found,
                "{d} is missing: Slurm is apt's slurm-wlm and munge (`bash scripts/setup.sh` installs them)"
            );
        }
        let slurm = Slurm { dir: tempfile::Builder::new().prefix("lr-slurm").tempdir_in("/tmp").unwrap() };
        let mut cmd = Command::new(repo_root().join("scripts/scale/slurm_local.sh"));
        cmd.args(["start", s(slurm.dir.path()), &base.to_string()]);
        let out = bounded("slurm_local.sh start", cmd, Duration::from_secs(60));
        assert!(out.status.success(), "slurm_local.sh start: {}", text(&out));
        slurm
    }

    fn conf(&self) -> PathBuf {
        self.dir.path().join("slurm.conf")
    }

    /// munged, slurmctld and slurmd (their pid files).
    fn daemons(&self) -> BTreeSet<u32> {
        ["munged", "slurmctld", "slurmd"]
            .iter()
            .map(|d| {
                let f = self.dir.path().join("run").join(format!("{d}.pid"));
                std::fs::read_to_string(&f).unwrap_or_else(|e| panic!("{}: {e}", f.display())).trim().parse().unwrap()
            })
            .collect()
    }
}

impl Drop for Slurm {
    fn drop(&mut self) {
        let mut cmd = Command::new(repo_root().join("scripts/scale/slurm_local.sh"));
        cmd.args(["stop", s(self.dir.path())]);
        let _ = bounded("slurm_local.sh stop", cmd, Duration::from_secs(60));
    }
}

#[test]
fn a_slurm_job_array_indexes_the_shards_and_a_dependent_job_merges_them_as_one_process_does() {
    let dir = tempfile::tempdir().unwrap();
    let roots = fixtures(&dir.path().join("data"));
    let one = one_process_index(&roots, &dir.path().join("one"));
    let slurm = Slurm::start(SLURM_PORT_BASE);
    // slurmctld and slurmd listen (munged has a Unix socket only), on 127.0.0.1 alone.
    assert_loopback_only("slurmctld and slurmd", &slurm.daemons(), 2);

    let out = dir.path().join("slurm");
    let mut cmd = Command::new(repo_root().join("scripts/scale/slurm_index.sh"));
    cmd.env("SLURM_CONF", slurm.conf())
        .args(["--shards", "4", "--out", s(&out), "--labrig", s(&labrig()), "--wait", "--json"])
        .args(&roots);
    let o = bounded("slurm_index.sh", cmd, Duration::from_secs(180));
    let ids = ok_json("slurm_index.sh", &o);
    let (array, merge) = (ids["array"].as_str().unwrap(), ids["merge"].as_str().unwrap());
    assert_ne!(array, merge);
    // Four array tasks, each its shard; the merge ran after them (afterok) and merged four parts.
    let mut shards = Vec::new();
    for i in 0..4 {
        let name = format!("part-{i:05}-of-00004");
        let r: Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("reports").join(format!("{name}.json"))).unwrap())
                .unwrap();
        assert_eq!(r["shard"], json!([i, 4]), "{r}");
        shards.push(r["in_shard"].as_u64().unwrap());
        let log = std::fs::read_to_string(out.join("logs").join(format!("index-{array}_{i}.out"))).unwrap();
        assert!(log.contains(&format!("{name}: done")) && log.contains(&format!("(job {array}_{i})")), "{log}");
    }
    assert_eq!(shards.iter().sum::<u64>(), SOURCES, "{shards:?}");
    let m: Value = serde_json::from_str(&std::fs::read_to_string(out.join("merge.json")).unwrap()).unwrap();
    assert_eq!((m["shards"].as_u64(), m["rows"].as_u64()), (Some(4), Some(ROWS)), "{m}");
    let sq =
        Command::new("scontrol").env("SLURM_CONF", slurm.conf()).args(["-o", "show", "job", merge]).output().unwrap();
    let sq = String::from_utf8_lossy(&sq.stdout);
    assert!(sq.contains("JobState=COMPLETED"), "{sq}");
    assert_same_index(&one, &out.join("index"));

    // A shard that fails: the merge never runs (cancelled: its dependency cannot be met), the
    // failed task is named, the submission exits non-zero.
    let broken = dir.path().join("broken.sh");
    std::fs::write(
        &broken,
        format!(
            "#!/bin/sh\ncase \" $* \" in *\" --shard 1/4 \"*) echo 'disk gone' >&2; exit 3;; esac\nexec '{}' \"$@\"\n",
            labrig().display()
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&broken, std::fs::Permissions::from_mode(0o755)).unwrap();
    let out_b = dir.path().join("slurm_broken");
    let mut cmd = Command::new(repo_root().join("scripts/scale/slurm_index.sh"));
    cmd.env("SLURM_CONF", slurm.conf())
        .args(["--shards", "4", "--out", s(&out_b), "--labrig", s(&broken), "--wait"])
        .args(&roots);
    let o = bounded("slurm_index.sh (a failing shard)", cmd, Duration::from_secs(180));
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("did not complete (CANCELLED") && err.contains("failed array tasks: 1 (FAILED)"), "{err}");
    assert!(!out_b.join("index").exists() && !out_b.join("merge.json").exists());
}
