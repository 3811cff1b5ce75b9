//! `labrig rollout`: a policy's closed-loop success rate in the simulated rig (the rollout
//! engine is [`labrig_launch::rollout`]; this command prints its report).

use labrig_launch::rollout::{RolloutArgs, RolloutReport, rate_text, run_quiet};
use std::process::ExitCode;

pub fn run(args: RolloutArgs) -> anyhow::Result<ExitCode> {
    let json = args.json;
    let report = run_quiet(args)?;
    if json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        print!("{}", report_text(&report));
    }
    Ok(if report.errors.is_empty() { ExitCode::SUCCESS } else { ExitCode::from(1) })
}

fn report_text(r: &RolloutReport) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let n = r.rollouts.len();
    let _ = writeln!(
        s,
        "labrig rollout: {}, {} in {}, seeds {}..{} (both included)",
        rate_text(r),
        r.scene,
        r.mode,
        r.first_seed,
        (r.first_seed + n as u64).saturating_sub(1).max(r.first_seed)
    );
    let _ = writeln!(s, "policy {}", r.policy);
    let _ = writeln!(
        s,
        "inference per chunk p50 {:.1} ms / p99 {:.1} ms over {} chunks; {} steps held for lack of an action, {} after the first chunk ({:.1}% of {} steps)",
        r.inference_ms_p50,
        r.inference_ms_p99,
        r.chunks,
        r.held_steps,
        r.held_after_first_chunk,
        100.0 * r.held_after_first_chunk as f64 / r.steps_after_first_chunk.max(1) as f64,
        r.steps_after_first_chunk
    );
    if let Some(who) = &r.intervene {
        let _ = writeln!(
            s,
            "operator corrections ({who}): {} takeovers, {} operator steps; {} of {} successes without help",
            r.takeovers, r.operator_steps, r.successes_without_help, r.successes
        );
    }
    if let Some(c) = &r.control {
        let us = |k: &str, i: usize| c[k][i].as_f64().unwrap_or(f64::NAN);
        let _ = writeln!(
            s,
            "the loop: {} ticks, {} missed; period jitter p50 {:.0} / p99 {:.0} / max {:.0} us; tick lateness p99 {:.0} us; request round trip p50 {:.1} / p99 {:.1} ms",
            c["ticks"],
            c["missed_ticks"],
            us("jitter_us", 0),
            us("jitter_us", 1),
            us("jitter_us", 2),
            us("tick_lateness_us", 1),
            c["source"]["round_trip_ms"][0].as_f64().unwrap_or(f64::NAN),
            c["source"]["round_trip_ms"][1].as_f64().unwrap_or(f64::NAN),
        );
    }
    let _ = writeln!(s);
    let _ = writeln!(s, "  #  seed  outcome  steps  held  chunks  skipped  takeovers  operator  reason");
    for (k, o) in r.rollouts.iter().enumerate() {
        let _ = writeln!(
            s,
            "{k:>3} {:>5}  {:<7}  {:>5}  {:>4}  {:>6}  {:>7}  {:>9}  {:>8}  {}",
            o.seed.map_or("-".into(), |v| v.to_string()),
            if o.success { "success" } else { "failure" },
            o.steps,
            o.held_steps,
            o.chunks,
            o.skipped_rows,
            o.takeovers,
            o.operator_steps,
            o.reason
        );
    }
    if let Some(p) = &r.summary_png {
        let _ = writeln!(s, "\nsummary: {}; contact sheets: rollout_NN_cameras.png beside it", p.display());
    }
    for e in &r.errors {
        let _ = writeln!(s, "error: {e}");
    }
    s
}
