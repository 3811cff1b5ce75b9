//! `labrig train` data-parallel over torch.distributed's c10d (Gloo), as a launcher starts it:
//! this test is the launcher (WORLD_SIZE, RANK, MASTER_ADDR = 127.0.0.1, MASTER_PORT per rank,
//! what torchrun --no-python and srun set), so every socket stays on loopback. Two ranks of
//! batch 8 must train as one process of batch 16 does (the same losses step by step, within
//! float tolerance), end with identical weights, resume, and name a broken launch. The same
//! run launched by `srun -n 2` on a one-node Slurm (scripts/scale/slurm_local.sh, daemons on
//! 127.0.0.1) takes its ranks from srun's step and trains the same.

use labrig_tests::{domain_for, labrig_bin, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::{Child, Command, Output, Stdio};

fn demo(out: &Path, episodes: u32) {
    for p in ["labrig-sim", "labrig-franka", "labrig-gripper", "labrig-recorder", "labrig-control"] {
        workspace_bin(p, p);
    }
    let o = Command::new(labrig_bin())
        .args(["demo", "--episodes", &episodes.to_string(), "--first-seed", "0", "--json", "--domain-id"])
        .arg(domain_for("train_distributed_demo").to_string())
        .arg("--out")
        .arg(out)
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("train_dist_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(o.status.success(), "demo failed: {}", String::from_utf8_lossy(&o.stderr));
}

fn train(args: &[&str]) -> Command {
    workspace_bin("labrig-policies", "labrig-policies");
    let mut c = Command::new(labrig_bin());
    c.arg("train").args(args).args(["--threads", "1", "--json"]).env("OMP_NUM_THREADS", "1");
    for v in ["WORLD_SIZE", "RANK", "MASTER_ADDR", "MASTER_PORT", "SLURM_STEP_NUM_TASKS", "SLURM_PROCID"] {
        c.env_remove(v);
    }
    c
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// `world` ranks of `labrig train args`, each with the launcher's environment.
fn ranks(world: usize, args: &[&str]) -> Vec<Output> {
    let port = free_port().to_string();
    let children: Vec<Child> = (0..world)
        .map(|rank| {
            train(args)
                .env("WORLD_SIZE", world.to_string())
                .env("RANK", rank.to_string())
                .env("MASTER_ADDR", "127.0.0.1")
                .env("MASTER_PORT", &port)
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    children.into_iter().map(|c| c.wait_with_output().unwrap()).collect()
}

/// A one-node Slurm on loopback (scripts/scale/slurm_local.sh), stopped on drop. Port base
/// 23600: clear of tests/tests/scale_index.rs's (23350) and of DDS's ports.
struct Slurm {
    state: tempfile::TempDir,
}

impl Slurm {
    fn start() -> Slurm {
        let state = tempfile::tempdir().unwrap();
        let o = Command::new("bash")
            .arg(labrig_tests::repo_root().join("scripts/scale/slurm_local.sh"))
            .args(["start", state.path().to_str().unwrap(), "23600"])
            .output()
            .unwrap();
        let slurm = Slurm { state };
        assert!(o.status.success(), "slurm_local.sh start: {}", labrig_tests::output_text(&o));
        slurm
    }
}

impl Drop for Slurm {
    fn drop(&mut self) {
        let _ = Command::new("bash")
            .arg(labrig_tests::repo_root().join("scripts/scale/slurm_local.sh"))
            .args(["stop", self.state.path().to_str().unwrap()])
            .output();
    }
}

fn report(o: &Output) -> Value {
    assert!(o.status.success(), "labrig train failed: {}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let json = &text[text.find("\n{").map(|i| i + 1).unwrap_or(0)..];
    serde_json::from_str(json).unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// loss.csv's (step, train loss, validation loss) rows.
fn losses(run: &Path) -> Vec<(u64, f64, Option<f64>)> {
    let text = std::fs::read_to_string(run.join("loss.csv")).unwrap();
    text.lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0].parse().unwrap(), f[1].parse().unwrap(), f[2].parse().ok())
        })
        .collect()
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-4 * a.abs().max(b.abs()).max(1.0)
}

#[test]
fn two_gloo_ranks_train_as_one_process_with_the_doubled_batch() {
    let dir = tempfile::tempdir().unwrap();
    let eps = dir.path().join("demo");
    demo(&eps, 2);
    let cache = dir.path().join("cache");
    let (one, two) = (dir.path().join("one"), dir.path().join("two"));
    let s = |p: &Path| p.to_str().unwrap().to_owned();
    let common = |out: &Path, batch: &str, steps: &str| {
        vec![
            "--target".to_owned(),
            s(&eps),
            "--preset".into(),
            "small_lowdim".into(),
            "--cache".into(),
            s(&cache),
            "--out".into(),
            s(out),
            "--batch-size".into(),
            batch.into(),
            "--steps".into(),
            steps.into(),
            "--val-every".into(),
            "3".into(),
            "--checkpoint-every".into(),
            "3".into(),
        ]
    };

    // One process, batch 16, fills the frame cache first.
    let a = common(&one, "16", "6");
    let r1 = report(&train(&strs(&a)).output().unwrap());
    assert_eq!((r1["steps"].as_u64(), r1["world_size"].as_u64()), (Some(6), Some(1)), "{r1}");

    // Two ranks of batch 8.
    let outs = ranks(2, &strs(&common(&two, "8", "6")));
    let r2 = report(&outs[0]);
    assert!(outs[1].status.success(), "rank 1: {}", String::from_utf8_lossy(&outs[1].stderr));
    assert!(String::from_utf8_lossy(&outs[1].stderr).contains("rank 1 done: 6 steps"));
    assert_eq!((r2["steps"].as_u64(), r2["world_size"].as_u64()), (Some(6), Some(2)), "{r2}");
    // The ranks end holding the same weights, bit for bit.
    assert_eq!(r2["ranks_weight_diff"].as_f64(), Some(0.0), "{r2}");
    // Step by step, the same training and validation losses as the single process's.
    let (l1, l2) = (losses(&one), losses(&two));
    assert_eq!(l1.len(), 7, "{l1:?}");
    assert_eq!(l1.iter().map(|r| r.0).collect::<Vec<_>>(), l2.iter().map(|r| r.0).collect::<Vec<_>>());
    for (x, y) in l1.iter().zip(&l2) {
        assert!(close(x.1, y.1), "train loss at step {}: one process {} vs two ranks {}", x.0, x.1, y.1);
        match (x.2, y.2) {
            (Some(u), Some(v)) => assert!(close(u, v), "validation loss at step {}: {u} vs {v}", x.0),
            (None, None) => {}
            other => panic!("validation rows differ at step {}: {other:?}", x.0),
        }
    }
    assert!(l1[6].1 < l1[1].1, "the loss fell: {l1:?}");
    // Rank 0 alone wrote the run: its checkpoints carry both ranks' steps.
    assert!(two.join("checkpoints/step_6").is_dir() && two.join("run.json").is_file());
    assert_eq!(
        (r1["drawn_target"].as_u64(), r2["drawn_target"].as_u64()),
        (Some(96), Some(96)),
        "both drew 6 x 16 samples in all"
    );

    // --resume continues both ranks from rank 0's checkpoint.
    let mut c = common(&two, "8", "9");
    c.push("--resume".into());
    let outs = ranks(2, &strs(&c));
    let r3 = report(&outs[0]);
    assert!(outs[1].status.success(), "rank 1: {}", String::from_utf8_lossy(&outs[1].stderr));
    assert_eq!((r3["steps"].as_u64(), r3["resumed_from"].as_u64()), (Some(9), Some(6)), "{r3}");
    assert_eq!(r3["ranks_weight_diff"].as_f64(), Some(0.0), "{r3}");
    assert_eq!(losses(&two).len(), 10);

    // The pixel preset (random crops differ by rank) stays in step too.
    let vision = dir.path().join("vision");
    let mut v = common(&vision, "4", "2");
    v[3] = "small_vision".into();
    let outs = ranks(2, &strs(&v));
    let r4 = report(&outs[0]);
    assert_eq!(r4["ranks_weight_diff"].as_f64(), Some(0.0), "{r4}");

    // srun -n 2 on a one-node Slurm: the ranks from srun's step, the same losses again.
    let slurm = Slurm::start();
    let srun_out = dir.path().join("srun");
    let mut cmd = Command::new("timeout");
    cmd.args(["120", "srun", "-n", "2", "--cpus-per-task", "1", "--kill-on-bad-exit=1"])
        .arg(labrig_bin())
        .arg("train")
        .args(strs(&common(&srun_out, "8", "6")))
        .args(["--threads", "1", "--json"])
        .env("SLURM_CONF", slurm.state.path().join("slurm.conf"))
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", free_port().to_string())
        .env("OMP_NUM_THREADS", "1");
    for v in ["WORLD_SIZE", "RANK"] {
        cmd.env_remove(v);
    }
    let o = cmd.output().unwrap();
    drop(slurm);
    let r5 = report(&o);
    assert_eq!((r5["world_size"].as_u64(), r5["ranks_weight_diff"].as_f64()), (Some(2), Some(0.0)), "{r5}");
    let ls = losses(&srun_out);
    let steps = |l: &[(u64, f64, Option<f64>)]| l.iter().map(|x| x.0).collect::<Vec<_>>();
    assert!(
        !ls.is_empty() && steps(&ls) == steps(&l1),
        "srun logged steps {:?}, one process {:?}",
        steps(&ls),
        steps(&l1)
    );
    for (x, y) in l1.iter().zip(&ls) {
        assert!(close(x.1, y.1), "srun: train loss at step {}: {} vs {}", x.0, x.1, y.1);
    }

    // A launch without RANK, and a rank whose peer never comes, are named.
    let o = train(&strs(&a)).env("WORLD_SIZE", "2").output().unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("RANK") && e.contains("unset"), "{e}");
    let lone = dir.path().join("lone");
    let mut d = common(&lone, "8", "2");
    d.extend(["--dist-timeout-s".into(), "3".into()]);
    let o = train(&strs(&d))
        .env("WORLD_SIZE", "2")
        .env("RANK", "0")
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", free_port().to_string())
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("rank 0 of 2"), "{e}");
}
