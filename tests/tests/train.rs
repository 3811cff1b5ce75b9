//! `labrig train` end to end: the simulated rig records a tiny episode set (`labrig demo`),
//! the small low-dimensional preset trains on it until the validation loss has fallen >= 10x,
//! a resumed run continues from the last checkpoint, co-training draws follow w, and bad
//! input (a camera the episodes lack, a checkpoint of another preset) is named.

use labrig_tests::{domain_for, labrig_bin, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};

fn demo(out: &Path, episodes: u32) {
    for p in ["labrig-sim", "labrig-franka", "labrig-gripper", "labrig-recorder", "labrig-control"] {
        workspace_bin(p, p);
    }
    let domain = domain_for("train_demo_episodes");
    let o = Command::new(labrig_bin())
        .args(["demo", "--episodes", &episodes.to_string(), "--first-seed", "0", "--json", "--domain-id"])
        .arg(domain.to_string())
        .arg("--out")
        .arg(out)
        .env(labrig_runtime::frames::NAMESPACE_ENV, format!("train_{}", std::process::id()))
        .output()
        .unwrap();
    assert!(o.status.success(), "demo failed: {}", String::from_utf8_lossy(&o.stderr));
}

fn train(args: &[&str]) -> Output {
    workspace_bin("labrig-policies", "labrig-policies");
    Command::new(labrig_bin())
        .arg("train")
        .args(args)
        .args(["--threads", "1"])
        .env("OMP_NUM_THREADS", "1")
        .output()
        .unwrap()
}

/// `labrig train` with a preset file holding `toml`.
fn train_with_file(dir: &Path, toml: &str, target: &str, out: &Path, more: &[&str]) -> Output {
    let file = dir.join("preset.toml");
    std::fs::write(&file, toml).unwrap();
    let args = ["--target", target, "--preset", file.to_str().unwrap(), "--out", out.to_str().unwrap()];
    train(&[&args[..], more].concat())
}

fn report(o: &Output) -> Value {
    assert!(o.status.success(), "labrig train failed: {}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let json = &text[text.find("\n{").map(|i| i + 1).unwrap_or(0)..];
    serde_json::from_str(json).unwrap_or_else(|e| panic!("{e}: {text}"))
}

fn err(o: &Output) -> String {
    assert!(!o.status.success(), "expected a failure: {}", String::from_utf8_lossy(&o.stdout));
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn train_converges_resumes_cotrains_and_names_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let eps = dir.path().join("demo");
    demo(&eps, 10);
    let run = dir.path().join("run");
    let (eps_s, run_s) = (eps.to_str().unwrap(), run.to_str().unwrap());

    // One successful episode in ten is held out; 600 steps of batch 32 (one thread: the run is
    // deterministic, seeded data, noise and draws).
    let common = ["--target", eps_s, "--preset", "small_lowdim", "--batch-size", "32", "--val-every", "100", "--json"];
    let r = report(&train(&[&common[..], &["--out", run_s, "--steps", "600", "--checkpoint-every", "300"]].concat()));
    let kept = r["target_episodes"].as_u64().unwrap() + r["val_episodes"].as_u64().unwrap();
    assert_eq!(kept + r["skipped_unsuccessful"].as_u64().unwrap(), 10, "{r}");
    assert!(kept >= 8 && r["val_episodes"] == 1, "{r}");
    let (first, last) = (r["first_val_loss"].as_f64().unwrap(), r["last_val_loss"].as_f64().unwrap());
    eprintln!("validation loss {first:.4} -> {last:.4} ({:.1}x lower)", first / last);
    assert!(first / last >= 10.0, "validation loss {first:.4} -> {last:.4}: fell only {:.1}x", first / last);
    assert_eq!(r["drawn_target"], 600 * 32);
    assert!(
        run.join("checkpoints/step_300/checkpoint.json").is_file()
            && run.join("checkpoints/step_600/ema.safetensors").is_file()
    );
    assert!(std::fs::metadata(run.join("loss.png")).unwrap().len() > 10_000);
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("checkpoints/step_600/checkpoint.json")).unwrap())
            .unwrap();
    assert_eq!(meta["manifest"].as_array().unwrap().len() as u64, kept, "every episode by uuid: {meta}");
    assert_eq!(meta["config"]["state_dim"], 14, "pose 7 + gripper 1 + scene 6");

    // Resumed: from step 600 to 650, the loss log continued without repeats.
    let r = report(&train(&[&common[..], &["--out", run_s, "--steps", "650", "--resume"]].concat()));
    assert_eq!((r["resumed_from"].as_u64(), r["steps"].as_u64()), (Some(600), Some(650)), "{r}");
    let csv = std::fs::read_to_string(run.join("loss.csv")).unwrap();
    let steps: Vec<u64> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    assert_eq!(steps, (0..=650).collect::<Vec<u64>>());

    // A second run into the same directory without --resume is refused (the run is kept).
    let e = err(&train(&[&common[..], &["--out", run_s, "--steps", "10"]].concat()));
    assert!(e.contains("holds a run already: --resume continues it"), "{e}");

    // Another model config cannot resume this run.
    let e = err(&train_with_file(
        dir.path(),
        "preset = \"small_lowdim\"\n[model]\ndown_dims = [32, 64]\n",
        eps_s,
        &run,
        &["--steps", "700", "--resume"],
    ));
    assert!(e.contains("made by another model config than --preset's"), "{e}");

    // Co-training: w = 0.3 of the samples from the target (one episode), the rest from the others.
    let one = dir.path().join("one.txt");
    let list: Vec<_> = labrig_episode::episode::find_episodes(&eps)
        .into_iter()
        .filter(|p| p.to_string_lossy().contains("/success/"))
        .collect();
    std::fs::write(&one, format!("{}\n", list[0].display())).unwrap();
    let rest = dir.path().join("rest.txt");
    std::fs::write(&rest, list[1..].iter().map(|p| format!("{}\n", p.display())).collect::<String>()).unwrap();
    let co = dir.path().join("co");
    let r = report(&train(&[
        "--target",
        one.to_str().unwrap(),
        "--cotrain",
        rest.to_str().unwrap(),
        "--w",
        "0.3",
        "--preset",
        "small_lowdim",
        "--batch-size",
        "64",
        "--out",
        co.to_str().unwrap(),
        "--steps",
        "10",
        "--json",
    ]));
    let (t, c) = (r["drawn_target"].as_f64().unwrap(), r["drawn_cotrain"].as_f64().unwrap());
    assert_eq!(t + c, 640.0);
    // 640 draws at p = 0.3: sd 11.6; within 4 sd of 192.
    assert!((t - 192.0).abs() < 47.0, "{t} target draws of 640 at w = 0.3");
    assert_eq!((r["cotrain_episodes"].as_u64(), r["val_episodes"].as_u64()), (Some(kept - 1), Some(0)), "{r}");

    // An image preset asking for a camera the episodes lack names it and the episode.
    let toml = "preset = \"small\"\n[model]\ncameras = [\"ext9\"]\n";
    let e = err(&train_with_file(dir.path(), toml, eps_s, &dir.path().join("y"), &["--steps", "1"]));
    assert!(e.contains("no camera `ext9`") && e.contains("episode") && e.contains("ext1"), "{e}");
}
