//! `labrig bench loop`: the rig loop free-running for minutes (the measurement is
//! [`labrig_launch::measure`]; this command prints its report).

use labrig_launch::measure::{LoopArgs, measure};
use std::process::ExitCode;

pub fn run(a: LoopArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.seconds >= 10.0 && a.seconds <= 3600.0, "--seconds must be in [10, 3600]");
    let tmp;
    let out = match &a.out {
        Some(p) => {
            std::fs::create_dir_all(p)?;
            std::fs::canonicalize(p)?
        }
        None => {
            tmp = std::env::temp_dir().join(format!("labrig-bench-loop-{}", std::process::id()));
            std::fs::create_dir_all(&tmp)?;
            tmp.clone()
        }
    };
    let report = measure(&a, &out, None)?;
    if a.out.is_none() {
        let _ = std::fs::remove_dir_all(&out);
    }
    if a.json {
        println!("{report}");
    } else {
        print_report(&report);
    }
    Ok(ExitCode::SUCCESS)
}

pub fn print_report(r: &serde_json::Value) {
    let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    println!(
        "labrig bench loop: {:.0} s free-running, sim in real time, {}",
        f(&r["seconds"]),
        r["cameras"].as_str().unwrap_or("")
    );
    println!("  (a shared 2-core machine: timings are noisy; compare ratios, rerun before concluding)");
    println!(
        "  control loop: {} ticks, period jitter p50 {:.0} us, p99 {:.0} us, max {:.0} us; missed ticks {}",
        r["ticks"],
        f(&r["tick_jitter_us"]["p50"]),
        f(&r["tick_jitter_us"]["p99"]),
        f(&r["tick_jitter_us"]["max"]),
        r["missed_ticks"]
    );
    println!(
        "  observations: {} steps with a camera missing, {} with a stale frame (> 100 ms); skew p50 {:.0} us, p99 {:.0} us",
        r["steps_missing_frames"],
        r["steps_stale_frames"],
        f(&r["camera_skew_us"]["p50"]),
        f(&r["camera_skew_us"]["p99"])
    );
    println!(
        "  recorded: {} episodes ({} successful), {} steps, {:.0} s; dropped frames {}, flagged episodes {}",
        r["recorded_episodes"],
        r["successes"],
        r["recorded_steps"],
        f(&r["recorded_seconds"]),
        r["dropped_frames"],
        r["flagged_episodes"]
    );
    println!(
        "  written: {:.1} MB, {:.2} MB/s over the run, {:.2} MB/s while recording",
        f(&r["mb_written"]),
        f(&r["mb_per_s"]),
        f(&r["mb_per_recorded_s"])
    );
    if let Some(cpu) = r["cpu_percent"].as_object() {
        for (n, p) in cpu {
            println!("  cpu {n}: {:.1}% of one core", f(p));
        }
    }
}
