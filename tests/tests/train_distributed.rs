//! `labrig train` data-parallel over torch.distributed's c10d (Gloo), as a launcher starts it:
//! this test is the launcher (WORLD_SIZE, RANK, MASTER_ADDR = 127.0.0.1, MASTER_PORT per rank,
//! what torchrun --no-python and srun set), so every socket stays on loopback. Two ranks of
//! batch 8 must train as one process of batch 16 does (the same losses step by step, within
//! float tolerance), end with identical weights, resume, and name a broken launch.

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
    demo(&eps, 3);
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
