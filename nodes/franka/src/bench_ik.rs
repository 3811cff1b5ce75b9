//! `labrig bench ik`: what the franka node's command path costs per 20 Hz tick — the URDF
//! kinematics (FK + Jacobian), one IK solve, and the whole safety filter (checks, IK, limits)
//! — on a cartesian circle (r = 8 cm, 5 s a turn) and on DROID velocity commands.

use clap::Args;
use labrig_arm::ik::{self, Ik, IkConfig};
use labrig_arm::safety::{ArmView, SafetyConfig, SafetyFilter};
use labrig_arm::{Fr3Kinematics, TcpOffset};
use labrig_msgs::Nanos;
use labrig_msgs::rig::{ArmCommand, ArmCommandMode, DROID_RESET_POSE};
use nalgebra::Vector3;
use serde_json::json;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct IkArgs {
    /// Ticks (commands) per measured series.
    #[arg(long, default_value_t = 2000)]
    ticks: usize,
    /// The FR3 URDF (default: from setup, see `labrig_arm::urdf_path`).
    #[arg(long)]
    urdf: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

pub fn run(a: IkArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(a.ticks >= 10, "--ticks must be at least 10");
    let kin = Fr3Kinematics::from_urdf_file(&labrig_arm::urdf_path(a.urdf.as_deref()), TcpOffset::ROBOTIQ_2F85)?;
    let ik = Ik::new(kin.clone(), IkConfig::default());
    let filter = SafetyFilter::new(ik.clone(), SafetyConfig { max_command_age_s: 0.0, ..SafetyConfig::default() })
        .map_err(|e| anyhow::anyhow!(e))?;
    let start = kin.tcp_pose(&DROID_RESET_POSE);
    let centre = start.translation.vector - Vector3::new(0.08, 0.0, 0.0);
    let target_at = |t: usize| {
        let ang = t as f64 / 100.0 * std::f64::consts::TAU;
        let mut p = start;
        p.translation.vector = centre + Vector3::new(0.08 * ang.cos(), 0.08 * ang.sin(), 0.03 * ang.sin());
        p
    };
    let (mut fk_us, mut ik_us, mut filter_us, mut vel_us) = (vec![], vec![], vec![], vec![]);
    let (mut iterations, mut worst_residual) = (0u64, 0.0f64);
    let mut q = DROID_RESET_POSE;
    for t in 1..=a.ticks {
        let t0 = Instant::now();
        std::hint::black_box(kin.tcp_pose_and_jacobian(std::hint::black_box(&q)));
        fk_us.push(t0.elapsed().as_secs_f64() * 1e6);
        let target = target_at(t);
        let t0 = Instant::now();
        let sol = ik.solve(&q, &target);
        ik_us.push(t0.elapsed().as_secs_f64() * 1e6);
        iterations += sol.iterations as u64;
        worst_residual = worst_residual.max(sol.position_error_m);
        let cmd = ArmCommand {
            mode: ArmCommandMode::CartesianPosition as u8,
            cartesian_position: ik::xyz_euler(&target),
            ..ArmCommand::default()
        };
        let view = ArmView { measured: q, commanded: q };
        let t0 = Instant::now();
        let ok = filter.filter(&cmd, &view, Nanos::ZERO).map_err(|e| anyhow::anyhow!("tick {t}: {e}"))?;
        filter_us.push(t0.elapsed().as_secs_f64() * 1e6);
        q = ok.joints;
    }
    let mut q = DROID_RESET_POSE;
    for t in 0..a.ticks {
        let ang = t as f64 * 0.05;
        let cmd = ArmCommand {
            mode: ArmCommandMode::CartesianVelocity as u8,
            cartesian_velocity: [0.3 * ang.cos(), 0.3 * ang.sin(), 0.1 * (2.0 * ang).sin(), 0.0, 0.0, 0.2 * ang.sin()],
            ..ArmCommand::default()
        };
        let view = ArmView { measured: q, commanded: q };
        let t0 = Instant::now();
        let ok = filter.filter(&cmd, &view, Nanos::ZERO).map_err(|e| anyhow::anyhow!("velocity tick {t}: {e}"))?;
        vel_us.push(t0.elapsed().as_secs_f64() * 1e6);
        q = ok.joints;
    }
    let report = json!({
        "ticks": a.ticks,
        "fk_and_jacobian": labrig_runtime::bench::summary(fk_us, "us"),
        "ik_solve": labrig_runtime::bench::summary(ik_us, "us"),
        "ik_mean_iterations": iterations as f64 / a.ticks as f64,
        "ik_worst_residual_m": worst_residual,
        "safety_filter_cartesian_position": labrig_runtime::bench::summary(filter_us, "us"),
        "safety_filter_cartesian_velocity": labrig_runtime::bench::summary(vel_us, "us"),
        "tick_budget_us": 50_000,
    });
    if a.json {
        println!("{report}");
    } else {
        println!("labrig bench ik: {} ticks per series (shared 2-core machine: read as ranges)", a.ticks);
        for (name, key) in [
            ("FK + Jacobian (URDF)", "fk_and_jacobian"),
            ("IK solve (DLS, to 10 um)", "ik_solve"),
            ("safety filter, cartesian position", "safety_filter_cartesian_position"),
            ("safety filter, cartesian velocity", "safety_filter_cartesian_velocity"),
        ] {
            let s = &report[key];
            println!(
                "  {name:36} p50 {:7.1} us  p99 {:7.1} us  max {:7.1} us",
                s["p50_us"].as_f64().unwrap_or(0.0),
                s["p99_us"].as_f64().unwrap_or(0.0),
                s["max_us"].as_f64().unwrap_or(0.0)
            );
        }
        println!(
            "  IK: {:.1} iterations per tick on average, worst residual {:.1e} m; the tick is 50,000 us",
            report["ik_mean_iterations"].as_f64().unwrap_or(0.0),
            worst_residual
        );
    }
    Ok(ExitCode::SUCCESS)
}
