//! `labrig experiment retrieval` at CI size (experiments/retrieval/ci.toml): the same scenes
//! and conditions as the documented run, a few demos, two training steps and one short rollout
//! per condition. It checks the mechanics the full run relies on: the data recorded by two rigs
//! at once, every condition's manifest (each retrieval's episodes from the sets that can match
//! it), training on the right sets, rollouts and the summary; a run cut off is continued (the
//! finished stages are not run again, a training resumes, cut rollouts run again); a run made
//! by another experiment is refused. The retrievals' expected episodes are exact (by the demos'
//! seeds), for the target demos as the target and for a TOML target.

use labrig_tests::{domains_for, labrig_bin, output_text, repo_root, workspace_bin};
use serde_json::Value;
use std::path::Path;
use std::process::Command;

fn read(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

fn experiment(config: &Path, out: &Path, domain: u16, extra: &[&str]) -> std::process::Output {
    Command::new(labrig_bin())
        .args(["experiment", "retrieval", "--config"])
        .arg(config)
        .arg("--out")
        .arg(out)
        .args(["--domain-id", &domain.to_string(), "--threads", "2"])
        .args(extra)
        .current_dir(repo_root())
        .output()
        .unwrap()
}

/// The manifest's episode paths.
fn retrieved(out: &Path, condition: &str) -> Vec<String> {
    let m = read(&out.join("conditions").join(condition).join("manifest.json"));
    m["episodes"].as_array().unwrap().iter().map(|e| e["path"].as_str().unwrap().to_owned()).collect()
}

/// A CI-sized experiment run once (the programs built, its two demo domains), from `config`
/// under experiments/retrieval/: its folder (kept alive by the temp dir), its domain and its
/// JSON results.
fn first_run(key: &str, config: &str) -> (tempfile::TempDir, std::path::PathBuf, u16, Value) {
    for p in ["labrig-sim", "labrig-recorder", "labrig-control", "labrig-policy", "labrig-dataset", "labrig-policies"] {
        workspace_bin(p, p);
    }
    let (domain, count) = domains_for(key);
    assert_eq!(count, 2, "two demo rigs at once");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("exp");
    let first = experiment(&repo_root().join("experiments/retrieval").join(config), &out, domain, &["--json"]);
    assert!(first.status.success(), "{}", output_text(&first));
    let stdout = String::from_utf8_lossy(&first.stdout);
    let results: Value = serde_json::from_str(stdout.lines().last().unwrap()).unwrap();
    (dir, out, domain, results)
}

#[test]
fn the_retrieval_experiment_runs_every_condition_and_continues_where_it_was_cut() {
    let (dir, out, domain, results) = first_run("experiment_retrieval_ci", "ci.toml");
    let config = repo_root().join("experiments/retrieval/ci.toml");
    let conditions = results["conditions"].as_array().unwrap();
    let names: Vec<&str> = conditions.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["target_only", "all", "camPose+objSpat", "camPose", "objSpat", "objTex"]);
    assert_eq!(results["target_successful"], 2, "{results}");
    assert_eq!(results["prior_episodes"], 3, "{results}");

    // Every condition trained its two steps on the right sets and was judged.
    for c in conditions {
        let name = c["name"].as_str().unwrap();
        assert_eq!(c["status"], "done", "{name}: {c}");
        assert_eq!(c["steps"], 2, "{name}");
        assert_eq!(c["rollouts"], 1, "{name}");
        let run = read(&out.join("conditions").join(name).join("run/run.json"));
        let rollouts = read(&out.join("conditions").join(name).join("rollouts/rollouts.json"));
        assert_eq!(rollouts["rollouts"].as_array().unwrap().len(), 1, "{name}");
        assert_eq!(rollouts["first_seed"], 1000, "{name}");
        assert!(
            rollouts["scene"].as_str().unwrap().ends_with("experiments/retrieval/target.toml"),
            "{name}: {rollouts}"
        );
        assert!(rollouts["policy"].as_str().unwrap().contains(&format!("conditions/{name}/run")), "{name}: {rollouts}");
        // Target episodes: 2 recorded, one held out for validation.
        assert_eq!(run["target_episodes"].as_u64().unwrap() + run["val_episodes"].as_u64().unwrap(), 2, "{name}");
        match name {
            "target_only" => {
                assert_eq!(run["cotrain_episodes"], 0);
                assert_eq!(run["drawn_cotrain"], 0);
                assert!(!out.join("conditions/target_only/manifest.json").exists());
            }
            "all" => {
                assert_eq!(run["cotrain_episodes"], 3, "{run}");
                assert!(run["drawn_cotrain"].as_u64().unwrap() > 0, "{run}");
            }
            _ => {
                let kept = retrieved(&out, name);
                assert_eq!(run["cotrain_episodes"].as_u64().unwrap() as usize, kept.len(), "{name}: {run}");
                assert!(run["drawn_cotrain"].as_u64().unwrap() > 0, "{name}: {run}");
                let m = read(&out.join("conditions").join(name).join("manifest.json"));
                let stages: Vec<&str> =
                    m["funnel"].as_array().unwrap().iter().map(|s| s["stage"].as_str().unwrap()).collect();
                assert_eq!(stages[0], "all", "{name}: {m}");
                assert_eq!(m["funnel"][0]["kept"], 3, "{name}: {m}");
            }
        }
    }
    // What each retrieval kept, exactly (ci.toml chooses the prior's seeds for it): region A
    // seed 100 has ext1 in the target's camera window and a red cube, 101 neither, region B
    // seed 225 ext1 in the window and another colour. The demo's report lists its episodes in
    // seed order.
    let dirs = |set: &str| -> Vec<String> {
        let r = read(&out.join("data/prior").join(set).join("demo.json"));
        r["episodes"].as_array().unwrap().iter().map(|e| e["dir"].as_str().unwrap().to_owned()).collect()
    };
    let (a, b) = (dirs("pick_place_region_A"), dirs("pick_place_region_B"));
    let (a100, a101, b225) = (a[0].clone(), a[1].clone(), b[0].clone());
    let sorted = |mut v: Vec<String>| {
        v.sort();
        v
    };
    assert_eq!(sorted(retrieved(&out, "camPose")), sorted(vec![a100.clone(), b225]), "camPose");
    assert_eq!(sorted(retrieved(&out, "objSpat")), sorted(vec![a100.clone(), a101]), "objSpat");
    assert_eq!(retrieved(&out, "camPose+objSpat"), [a100.as_str()], "camPose+objSpat");
    assert_eq!(retrieved(&out, "objTex"), [a100.as_str()], "objTex");
    let m = read(&out.join("conditions/camPose+objSpat/manifest.json"));
    let funnel: Vec<u64> = m["funnel"].as_array().unwrap().iter().map(|f| f["kept"].as_u64().unwrap()).collect();
    assert_eq!(funnel, [3, 3, 3, 2, 1], "all, object, skill, camPose, objSpat: {m}");

    // A task with no demos yet, as a TOML target (ext1 at target.toml's window centre, the cube
    // box of region A) retrieves from the same index what the target demos did.
    let (polar, az, radius) = (52f64.to_radians(), 45f64.to_radians(), 1.02);
    let cam = [0.5 + radius * polar.sin() * az.cos(), radius * polar.sin() * az.sin(), radius * polar.cos()];
    let spec = dir.path().join("target_spec.toml");
    let text = format!(
        "cameras = [[{}, {}, {}]]\nobject_position = [0.47, -0.15, 0.05]\nobject = \"cube\"\n",
        cam[0], cam[1], cam[2]
    );
    std::fs::write(&spec, text).unwrap();
    let manifest = dir.path().join("spec.json");
    let o = Command::new(labrig_bin())
        .args(["dataset", "retrieve", "--index"])
        .arg(out.join("index"))
        .arg("--target")
        .arg(&spec)
        .args(["--align", "object,camPose,objSpat", "--obj-box-m", "0.2,0.2,0.3", "--out"])
        .arg(&manifest)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", output_text(&o));
    let m = read(&manifest);
    let kept: Vec<&str> = m["episodes"].as_array().unwrap().iter().map(|e| e["path"].as_str().unwrap()).collect();
    assert_eq!(kept, [a100.as_str()], "{m}");

    // The summary: a table naming every condition and a figure.
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    for n in &names {
        assert!(md.contains(&format!("| {n} |")), "{md}");
    }
    let png = std::fs::read(out.join("results.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");

    // Cut off: objSpat's rollouts half written, camPose's training before its run.json.
    let run_json = out.join("conditions/camPose/run/run.json");
    std::fs::remove_file(&run_json).unwrap();
    std::fs::remove_file(out.join("conditions/objSpat/rollouts/rollouts.json")).unwrap();
    let objtex_run = out.join("conditions/objTex/run/run.json");
    let objtex_mtime = std::fs::metadata(&objtex_run).unwrap().modified().unwrap();
    let again = experiment(&config, &out, domain, &[]);
    assert!(again.status.success(), "{}", output_text(&again));
    let text = String::from_utf8_lossy(&again.stdout);
    for line in [
        "[data] target: recorded earlier (2 episodes, 2 successful)",
        "[train] target_only: trained earlier (2 steps)",
        "[train] camPose: 2 steps (resumed)",
        "[train] objSpat: trained earlier (2 steps)",
        "[rollout] objSpat seeds 1000..1000: ",
        "[rollout] objTex seeds 1000..1000: done earlier",
    ] {
        assert!(text.contains(line), "`{line}` missing from:\n{text}");
    }
    assert!(!text.contains("[rollout] objSpat seeds 1000..1000: done earlier"), "{text}");
    assert_eq!(
        std::fs::metadata(&objtex_run).unwrap().modified().unwrap(),
        objtex_mtime,
        "objTex was not trained again"
    );
    assert!(run_json.exists() && out.join("conditions/objSpat/rollouts/rollouts.json").exists());
    assert!(text.contains("success on the target's rollouts"), "{text}");

    // Another experiment in the same folder is refused, naming what differs.
    let other = dir.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    for f in ["target.toml", "prior_region_A.toml", "prior_region_B.toml"] {
        std::fs::copy(repo_root().join("experiments/retrieval").join(f), other.join(f)).unwrap();
    }
    let text = std::fs::read_to_string(&config).unwrap().replace("steps = 2\n", "steps = 3\n");
    std::fs::write(other.join("ci.toml"), text).unwrap();
    let refused = experiment(&other.join("ci.toml"), &out, domain, &[]);
    assert!(!refused.status.success());
    let err = output_text(&refused);
    assert!(err.contains("made by another experiment") && err.contains("steps"), "{err}");

    // A seed set added later: only it runs (for the condition asked), and the condition's
    // success counts both sets; the others are reported as partly judged.
    let text = std::fs::read_to_string(&config)
        .unwrap()
        .replace("rollout_first_seed = 1000\n", "rollout_first_seed = 1000\nmore_rollout_seeds = [2000]\n");
    assert!(text.contains("more_rollout_seeds"));
    std::fs::write(other.join("ci.toml"), text).unwrap();
    let more = experiment(&other.join("ci.toml"), &out, domain, &["--conditions", "objTex", "--json"]);
    assert!(more.status.success(), "{}", output_text(&more));
    let r: Value = serde_json::from_str(String::from_utf8_lossy(&more.stdout).lines().last().unwrap()).unwrap();
    let objtex = r["conditions"].as_array().unwrap().iter().find(|c| c["name"] == "objTex").unwrap();
    assert_eq!((objtex["status"].as_str(), objtex["rollouts"].as_u64()), (Some("done"), Some(2)), "{objtex}");
    assert_eq!(objtex["by_seed_set"][1][0], 2000, "{objtex}");
    let rollouts = read(&out.join("conditions/objTex/rollouts_2000/rollouts.json"));
    assert_eq!(rollouts["first_seed"], 2000);
    let all = r["conditions"].as_array().unwrap().iter().find(|c| c["name"] == "all").unwrap();
    assert_eq!((all["status"].as_str(), all["rollouts"].as_u64()), (Some("partly judged"), Some(1)), "{all}");

    // --summary-only builds the table without running anything.
    let summary = experiment(&config, &out, domain, &["--summary-only"]);
    assert!(summary.status.success(), "{}", output_text(&summary));
    assert!(String::from_utf8_lossy(&summary.stdout).contains("camPose+objSpat"));
}

/// experiments/retrieval/droid.toml's machinery at CI size (ci_droid.toml): every condition
/// trained once per training seed it takes, each policy in its own folder with its seed and its
/// preset (the ext1-only ablation's model has one camera), judged on the same seeds; the
/// summary pools the policies and compares two conditions over seeds; a seed added to a
/// condition later trains only the new policy.
#[test]
fn the_droid_shaped_experiment_trains_every_seed_and_compares_over_them() {
    let (dir, out, domain, results) = first_run("experiment_retrieval_droid_ci", "ci_droid.toml");
    let config = repo_root().join("experiments/retrieval/ci_droid.toml");
    assert_eq!(results["train_seeds"], serde_json::json!([0, 1]), "{results}");
    let conditions = results["conditions"].as_array().unwrap();
    let find = |n: &str| conditions.iter().find(|c| c["name"] == n).unwrap_or_else(|| panic!("{n}: {results}"));
    // Each policy: its own folder, the seed it was trained with, its preset, one rollout.
    for (name, seeds, cameras) in
        [("target_only", vec![0, 1], 2), ("camPose+objSpat", vec![0], 2), ("target_only_ext1", vec![0], 1)]
    {
        let c = find(name);
        assert_eq!(c["status"], "done", "{name}: {c}");
        assert_eq!(c["policies_done"], seeds.len(), "{name}: {c}");
        assert_eq!(c["rollouts"], seeds.len(), "{name}: pooled over its policies: {c}");
        let policies = c["policies"].as_array().unwrap();
        assert_eq!(policies.iter().map(|p| p["seed"].as_u64().unwrap()).collect::<Vec<_>>(), seeds, "{name}");
        let mut weights = Vec::new();
        for s in &seeds {
            let unit = out.join("conditions").join(name).join(format!("seed_{s}"));
            // The training was given its seed (the log holds each stage's command line).
            let log = std::fs::read_to_string(out.join(format!("logs/{name}_seed{s}_train.log"))).unwrap();
            let command = log.lines().find(|l| l.starts_with("$ labrig train")).unwrap();
            assert!(
                command.ends_with(&format!("--seed {s}")) || command.contains(&format!("--seed {s} ")),
                "{command}"
            );
            // (`checkpoints/last` names the newest checkpoint's folder.)
            let last = std::fs::read_to_string(unit.join("run/checkpoints/last")).unwrap();
            let last = unit.join("run/checkpoints").join(last.trim());
            let checkpoint = read(&last.join("checkpoint.json"));
            assert_eq!(checkpoint["config"]["cameras"].as_array().unwrap().len(), cameras, "{name}: {checkpoint}");
            let rollouts = read(&unit.join("rollouts/rollouts.json"));
            assert_eq!(
                (rollouts["first_seed"].as_u64(), rollouts["rollouts"].as_array().unwrap().len()),
                (Some(3000), 1)
            );
            assert!(rollouts["policy"].as_str().unwrap().contains(&format!("conditions/{name}/seed_{s}/run")));
            weights.push(std::fs::read(last.join("model.safetensors")).unwrap());
        }
        if weights.len() == 2 {
            assert_ne!(weights[0], weights[1], "{name}: two seeds, two different policies");
        }
        assert!(!out.join("conditions").join(name).join("run").exists(), "{name}: no unseeded policy");
    }
    // The retrieval ran once for its condition, before its first policy.
    let m = read(&out.join("conditions/camPose+objSpat/manifest.json"));
    assert!(!m["episodes"].as_array().unwrap().is_empty(), "{m}");
    // The comparison over seeds: 1 + 2 policies, C(3, 1) = 3 relabellings.
    let comparisons = results["comparisons"].as_array().unwrap();
    assert_eq!(comparisons.len(), 1, "{results}");
    let c = &comparisons[0];
    assert_eq!((c["a"].as_str(), c["b"].as_str()), (Some("camPose+objSpat"), Some("target_only")));
    assert_eq!(
        (c["policies_a"].as_u64(), c["policies_b"].as_u64(), c["relabellings"].as_u64()),
        (Some(1), Some(2), Some(3))
    );
    // (One rollout per policy: a policy's rate is its successes.)
    let rate = |n: &str| {
        let p = find(n)["policies"].as_array().unwrap();
        p.iter().map(|p| p["successes"].as_f64().unwrap()).sum::<f64>() / p.len() as f64
    };
    assert!((c["diff"].as_f64().unwrap() - (rate("camPose+objSpat") - rate("target_only"))).abs() < 1e-9, "{c}");
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(md.contains("camPose+objSpat vs target_only") && md.contains("over 3 relabellings"), "{md}");
    assert_eq!(&std::fs::read(out.join("results.png")).unwrap()[..8], b"\x89PNG\r\n\x1a\n");

    // A second seed for the ablation later: only its new policy is trained and judged.
    let other = dir.path().join("more");
    std::fs::create_dir_all(other.join("droid")).unwrap();
    let src = repo_root().join("experiments/retrieval");
    for f in ["target.toml", "ext1_only.toml", "droid/aligned.toml", "droid/region_B_other_cams.toml"] {
        std::fs::copy(src.join(f), other.join(f)).unwrap();
    }
    let text = std::fs::read_to_string(&config).unwrap();
    let text = text.replace("preset = \"ext1_only.toml\"\nseeds = 1\n", "preset = \"ext1_only.toml\"\nseeds = 2\n");
    assert!(text.contains("seeds = 2\n"));
    std::fs::write(other.join("ci_droid.toml"), text).unwrap();
    let before = std::fs::metadata(out.join("conditions/target_only/seed_1/run/run.json")).unwrap().modified().unwrap();
    let more = experiment(&other.join("ci_droid.toml"), &out, domain, &[]);
    assert!(more.status.success(), "{}", output_text(&more));
    let text = String::from_utf8_lossy(&more.stdout);
    for line in [
        "[train] target_only seed 1: trained earlier (2 steps)",
        "[rollout] target_only_ext1 seed 0 seeds 3000..3000: done earlier",
        "[train] target_only_ext1 seed 1: 2 steps in",
    ] {
        assert!(text.contains(line), "`{line}` missing from:\n{text}");
    }
    assert_eq!(
        std::fs::metadata(out.join("conditions/target_only/seed_1/run/run.json")).unwrap().modified().unwrap(),
        before
    );
    assert!(out.join("conditions/target_only_ext1/seed_1/rollouts/rollouts.json").exists());
}
