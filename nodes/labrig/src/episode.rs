//! `labrig episode start|success|failure|discard|stop|reset`: an operator's episode event for the rig
//! loop (on `/rig/request`). The loop applies it if it makes sense in its state (a Success
//! while idle is refused) and publishes what happened on `/rig/episode`. The request carries
//! its send time in its header, and the loop's status says what became of the request with
//! that stamp: this command waits for that verdict and exits 0 when the loop took it, 1 when it
//! refused it (printing why), 2 when no loop (or no verdict) came within `--wait`.

use clap::{Args, ValueEnum};
use labrig_launch::programs::RosArgs;
use labrig_msgs::rig::{EpisodeEvent, EpisodeEventKind};
use labrig_msgs::topics;
use labrig_runtime::ros::Ros;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Kind {
    Start,
    Success,
    Failure,
    Discard,
    /// End without a label (recorded as a failure, as in DROID).
    Stop,
    /// Idle: send the arm home (after an episode it goes there by itself).
    Reset,
}

#[derive(Debug, Args)]
pub struct EpisodeArgs {
    #[arg(value_enum)]
    kind: Kind,
    /// The task instruction (for `start`).
    #[arg(long, default_value = "")]
    note: String,
    /// How long to wait for the rig loop (s).
    #[arg(long, default_value_t = 10.0)]
    wait: f64,
    #[command(flatten)]
    ros: RosArgs,
}

pub fn run(a: EpisodeArgs) -> anyhow::Result<ExitCode> {
    let kind = match a.kind {
        Kind::Start => EpisodeEventKind::Start,
        Kind::Success => EpisodeEventKind::Success,
        Kind::Failure => EpisodeEventKind::Failure,
        Kind::Discard => EpisodeEventKind::Discard,
        Kind::Stop => EpisodeEventKind::Stop,
        Kind::Reset => EpisodeEventKind::Reset,
    };
    let cfg = a.ros.config()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    rt.block_on(async {
        let mut ros = Ros::new(&cfg, "labrig_episode")?;
        let publisher = ros.publisher_on(&topics::RIG_REQUEST, 10)?;
        let status = ros.subscription_on(&topics::CONTROL_STATUS, 1)?;
        // The loop is running (its latched status is out) and listens for requests.
        let deadline = std::time::Instant::now() + Duration::from_secs_f64(a.wait.max(0.1));
        let mut running = false;
        while std::time::Instant::now() < deadline {
            running |= status.try_take()?.is_some();
            if running && ros.subscription_count(topics::RIG_REQUEST.name) > 0 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        if !running || ros.subscription_count(topics::RIG_REQUEST.name) == 0 {
            eprintln!("no rig loop (labrig-control) on domain {} within {} s", cfg.domain_id, a.wait);
            return Ok(ExitCode::from(2));
        }
        // The ROS graph shows the reader a little before this writer has matched it (SEDP is
        // processed on DDS's own thread); a volatile sample sent in between is lost.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let stamp = labrig_runtime::Clock::Wall.now();
        let header = labrig_msgs::std_msgs::Header { stamp: stamp.into(), frame_id: String::new() };
        publisher.publish(EpisodeEvent { header, kind: kind as u8, note: a.note.clone(), ..Default::default() })?;
        // The loop's verdict on this request (its status names the stamp it decided).
        let deadline = std::time::Instant::now() + Duration::from_secs_f64(a.wait.max(0.1));
        while std::time::Instant::now() < deadline {
            while let Some(s) = status.try_take()? {
                let Ok(v) = serde_json::from_str::<serde_json::Value>(&s.msg.data) else { continue };
                let r = &v["last_request"];
                if r["stamp_ns"].as_i64() != Some(stamp.0) {
                    continue;
                }
                if r["accepted"] == true {
                    println!("the rig loop took {kind:?}");
                    return Ok(ExitCode::SUCCESS);
                }
                let why = r["reason"].as_str().unwrap_or("no reason given");
                eprintln!("the rig loop refused {kind:?}: {why}");
                return Ok(ExitCode::from(1));
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        eprintln!("sent {kind:?}, but the rig loop said nothing of it within {} s", a.wait);
        Ok(ExitCode::from(2))
    })
}
