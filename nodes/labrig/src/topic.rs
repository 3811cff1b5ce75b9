//! `labrig topic list|echo|hz`: ROS 2 graph tools that work against any ROS 2 node, for labs
//! without a ROS installation. Every wait is bounded.

use json::{abbreviate, decode_to_json, to_yamlish};

mod json;
use anyhow::{Context, bail};
use clap::Args;
use futures::StreamExt;
use labrig_launch::programs::RosArgs;
use labrig_runtime::Shutdown;
use labrig_runtime::ros::{Ros, TopicInfo, TopicKindInfo, qos};
use serde_json::json;
use std::process::ExitCode;
use std::time::Duration;

/// Exit code when the topic was not found on the graph.
pub const EXIT_NOT_FOUND: u8 = 2;
/// Exit code when `--timeout` ended the command before `--count` messages arrived.
pub const EXIT_TIMEOUT: u8 = 3;

#[derive(Debug, Args)]
pub struct ListArgs {
    #[command(flatten)]
    pub ros: RosArgs,
    /// Seconds to listen for discovery before printing.
    #[arg(long, default_value_t = 2.0)]
    pub wait: f64,
    /// Also list service request/reply topics and plain DDS topics.
    #[arg(long)]
    pub all: bool,
    /// One JSON array instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// Topic name, e.g. /rig/step.
    pub topic: String,
    #[command(flatten)]
    pub ros: RosArgs,
    /// Seconds to listen for discovery before printing.
    #[arg(long, default_value_t = 2.0)]
    pub wait: f64,
    /// One JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct HashesArgs {
    /// Only this type (pkg/msg/Name); default: every type labrig knows.
    pub type_name: Option<String>,
    /// One JSON object (type -> hash) instead of text.
    #[arg(long)]
    pub json: bool,
}

/// How `echo` and `hz` join ROS 2 and subscribe.
#[derive(Debug, Args)]
pub struct SubscribeArgs {
    #[command(flatten)]
    pub ros: RosArgs,
    /// Message type (pkg/msg/Name); discovered from the graph when omitted.
    #[arg(long = "type")]
    pub type_name: Option<String>,
    /// Seconds to wait for the topic to be discovered (exit code 2 if it is not).
    #[arg(long, default_value_t = 5.0)]
    pub wait: f64,
    /// Subscribe reliable (default best effort, which matches every publisher).
    #[arg(long)]
    pub reliable: bool,
}

#[derive(Debug, Args)]
pub struct EchoArgs {
    /// Topic name, e.g. /joint_states.
    pub topic: String,
    #[command(flatten)]
    pub sub: SubscribeArgs,
    /// Stop after this many messages.
    #[arg(long)]
    pub count: Option<usize>,
    /// Stop after this many seconds (exit code 3 if --count was not reached).
    #[arg(long)]
    pub timeout: Option<f64>,
    /// One JSON object per line: topic, type, receive/source time, message.
    #[arg(long)]
    pub json: bool,
    /// Print long arrays (image data) in full.
    #[arg(long)]
    pub full: bool,
}

#[derive(Debug, Args)]
pub struct HzArgs {
    /// Topic name.
    pub topic: String,
    #[command(flatten)]
    pub sub: SubscribeArgs,
    /// Number of most recent periods the statistics cover.
    #[arg(long, default_value_t = 10_000)]
    pub window: usize,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Print one JSON summary at the end instead of text once a second.
    #[arg(long)]
    pub json: bool,
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().context("tokio runtime")
}

fn secs(s: f64, what: &str) -> anyhow::Result<Duration> {
    if !(s.is_finite() && s >= 0.0) {
        bail!("--{what} must be a non-negative number of seconds, got {s}");
    }
    Ok(Duration::from_secs_f64(s))
}

pub fn list(args: ListArgs) -> anyhow::Result<ExitCode> {
    let rt = runtime()?;
    rt.block_on(async {
        let ros = Ros::new(&args.ros.config()?, &format!("labrig_topic_list_{}", std::process::id()))?;
        tokio::time::sleep(secs(args.wait, "wait")?).await;
        let topics: Vec<TopicInfo> =
            ros.discovered_topics().into_iter().filter(|t| args.all || t.kind == TopicKindInfo::Topic).collect();
        if args.json {
            println!("{}", serde_json::to_string(&topics)?);
        } else {
            for t in &topics {
                match t.kind {
                    TopicKindInfo::Topic => println!("{} [{}]", t.name, t.type_name),
                    other => println!("{} [{}] ({other:?})", t.name, t.type_name),
                }
            }
        }
        Ok(ExitCode::SUCCESS)
    })
}

/// The RIHS01 type hash labrig computes for a type it knows (its `.msg` text, as rosidl does).
struct Hash;
impl labrig_msgs::TypeVisitor for Hash {
    type Output = String;
    fn visit<T: labrig_msgs::RosMessage>(self) -> String {
        labrig_msgs::type_hash::<T>()
    }
}

/// `labrig topic hashes`: the RIHS01 type hash of every type labrig knows.
pub fn hashes(args: HashesArgs) -> anyhow::Result<ExitCode> {
    let hashes: Vec<(&str, String)> = match &args.type_name {
        Some(t) => match labrig_msgs::visit_type(t, Hash) {
            Some(h) => vec![(t.as_str(), h)],
            None => bail!("labrig does not know type {t} (`labrig topic hashes` lists the ones it does)"),
        },
        None => labrig_msgs::known_types()
            .iter()
            .map(|n| (*n, labrig_msgs::visit_type(n, Hash).expect("a known type")))
            .collect(),
    };
    if args.json {
        let map: serde_json::Map<String, serde_json::Value> =
            hashes.into_iter().map(|(n, h)| (n.to_owned(), h.into())).collect();
        println!("{}", serde_json::Value::Object(map));
    } else {
        for (n, h) in hashes {
            println!("{n:<36} {h}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `labrig topic info`: the topic's publishers and subscriptions in other processes, each with
/// the type hash it announced and whether that is labrig's for the type (exit code 3 when one
/// differs: the peer was built from another definition).
pub fn info(args: InfoArgs) -> anyhow::Result<ExitCode> {
    let topic = if args.topic.starts_with('/') { args.topic.clone() } else { format!("/{}", args.topic) };
    let rt = runtime()?;
    rt.block_on(async {
        let ros = Ros::new(&args.ros.config()?, &format!("labrig_topic_info_{}", std::process::id()))?;
        tokio::time::sleep(secs(args.wait, "wait")?).await;
        let endpoints: Vec<_> = ros
            .remote_endpoints()
            .into_iter()
            .filter(|e| e.topic.name == topic && e.topic.kind == TopicKindInfo::Topic)
            .collect();
        let mut differs = false;
        let rows: Vec<serde_json::Value> = endpoints
            .iter()
            .map(|e| {
                let labrig = labrig_msgs::visit_type(&e.topic.type_name, Hash);
                let matches = match (&e.type_hash, &labrig) {
                    (Some(a), Some(b)) => Some(a == b),
                    _ => None,
                };
                differs |= matches == Some(false);
                json!({"kind": e.kind, "type": e.topic.type_name, "participant": e.participant,
                       "type_hash": e.type_hash, "labrig_type_hash": labrig, "matches": matches})
            })
            .collect();
        if args.json {
            println!("{}", json!({"topic": topic, "endpoints": rows}));
        } else if rows.is_empty() {
            println!("{topic}: no publisher or subscription in another process (domain {})", ros.domain_id());
        } else {
            println!("{topic}");
            for r in &rows {
                let verdict = match (r["matches"].as_bool(), r["type_hash"].as_str()) {
                    (Some(true), _) => "= labrig's".to_owned(),
                    (Some(false), _) => format!(
                        "DIFFERS from labrig's {} (built from another definition of the type)",
                        r["labrig_type_hash"].as_str().unwrap_or_default()
                    ),
                    (None, Some(_)) => "(a type labrig does not know)".to_owned(),
                    (None, None) => "(no type hash announced)".to_owned(),
                };
                println!(
                    "  {:<12} {} [{}] {} {verdict}",
                    r["kind"].as_str().unwrap_or_default(),
                    r["participant"].as_str().unwrap_or_default(),
                    r["type"].as_str().unwrap_or_default(),
                    r["type_hash"].as_str().unwrap_or("-"),
                );
            }
        }
        Ok(if differs { ExitCode::from(3) } else { ExitCode::SUCCESS })
    })
}

/// A subscription opened for `echo`/`hz`: the node, the topic's type and its raw samples.
struct Opened {
    shutdown: Shutdown,
    // Kept alive for the subscription's lifetime (dropping it stops the node).
    _ros: Ros,
    type_name: String,
    sub: labrig_runtime::ros::RawSubscription,
}

/// Joins ROS 2 as `labrig_topic_<role>`, resolves the topic's type (given or discovered within
/// `wait`) and subscribes to its raw samples. `None` (after saying why) if the topic is not found.
async fn open(role: &str, topic: &str, args: &SubscribeArgs) -> anyhow::Result<Option<Opened>> {
    let (ros_args, type_name, reliable) = (&args.ros, args.type_name.as_deref(), args.reliable);
    let wait = secs(args.wait, "wait")?;
    let shutdown = Shutdown::new();
    shutdown.trigger_on_signals()?;
    let mut ros = Ros::new(&ros_args.config()?, &format!("labrig_topic_{role}_{}", std::process::id()))?;
    let topic = if topic.starts_with('/') { topic.to_owned() } else { format!("/{topic}") };
    let type_name = match type_name {
        Some(t) => t.to_owned(),
        None => match ros.wait_for_topic(&topic, wait).await {
            Some(info) => info.type_name,
            None => {
                let seen: Vec<String> = ros
                    .discovered_topics()
                    .into_iter()
                    .filter(|t| t.kind == TopicKindInfo::Topic)
                    .map(|t| t.name)
                    .collect();
                eprintln!(
                    "topic {topic} not found on domain {} within {:.1} s (DDS on loopback unless --allow-network); topics seen: {}",
                    ros.domain_id(),
                    wait.as_secs_f64(),
                    if seen.is_empty() { "none".to_owned() } else { seen.join(", ") }
                );
                return Ok(None);
            }
        },
    };
    let q = if reliable { qos::reliable(100) } else { qos::best_effort(100) };
    let sub = ros.raw_subscription(&topic, &labrig_msgs::dds_type_name(&type_name), q)?;
    Ok(Some(Opened { shutdown, _ros: ros, type_name, sub }))
}

pub fn echo(args: EchoArgs) -> anyhow::Result<ExitCode> {
    let rt = runtime()?;
    rt.block_on(async {
        let Some(Opened { shutdown, _ros, type_name, sub }) = open("echo", &args.topic, &args.sub).await? else {
            return Ok(ExitCode::from(EXIT_NOT_FOUND));
        };
        let known = labrig_msgs::visit_type(&type_name, KnownType).is_some();
        if !known {
            eprintln!("note: labrig does not know {type_name}; printing sizes and raw bytes only");
        }
        let timeout = match args.timeout {
            Some(t) => Some(tokio::time::Instant::now() + secs(t, "timeout")?),
            None => None,
        };
        let mut stream = Box::pin(sub.stream());
        let mut received = 0usize;
        loop {
            if args.count.is_some_and(|n| received >= n) {
                return Ok(ExitCode::SUCCESS);
            }
            let next = async {
                match timeout {
                    Some(t) => tokio::time::timeout_at(t, stream.next()).await.ok(),
                    None => Some(stream.next().await),
                }
            };
            let item = tokio::select! {
                _ = shutdown.wait() => return Ok(ExitCode::SUCCESS),
                item = next => item,
            };
            let sample = match item {
                None => {
                    if let Some(n) = args.count {
                        eprintln!("timeout: received {received} of {n} messages on {}", args.topic);
                        return Ok(ExitCode::from(EXIT_TIMEOUT));
                    }
                    return Ok(ExitCode::SUCCESS);
                }
                Some(None) => bail!("subscription to {} ended", args.topic),
                Some(Some(Err(e))) => {
                    tracing::warn!("{e}");
                    continue;
                }
                Some(Some(Ok(s))) => s,
            };
            received += 1;
            let decoded = decode_to_json(&type_name, sample.msg.encoding, &sample.msg.payload);
            let mut value = match decoded {
                Some(Ok(v)) => v,
                Some(Err(e)) => {
                    // Malformed message: say so, keep going.
                    eprintln!("{}: {e}", args.topic);
                    continue;
                }
                None => json!({ "bytes": sample.msg.payload.len(), "hex": hex(&sample.msg.to_cdr_bytes()) }),
            };
            if args.json {
                let line = json!({
                    "topic": args.topic,
                    "type": type_name,
                    "receive_ns": sample.receive_time.0,
                    "source_ns": sample.source_time.map(|t| t.0),
                    "msg": value,
                });
                println!("{line}");
            } else {
                if !args.full {
                    abbreviate(&mut value, 32);
                }
                let mut text = String::new();
                to_yamlish(&value, 0, &mut text);
                println!("{text}---");
            }
        }
    })
}

struct KnownType;
impl labrig_msgs::TypeVisitor for KnownType {
    type Output = ();
    fn visit<T: labrig_msgs::RosMessage>(self) {}
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Period statistics over receive times.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RateStats {
    pub messages: usize,
    pub rate_hz: f64,
    pub period_mean_ms: f64,
    pub period_min_ms: f64,
    pub period_max_ms: f64,
    pub period_std_ms: f64,
    pub period_p50_ms: f64,
    pub period_p99_ms: f64,
}

/// Statistics of the periods between consecutive receive times (ns). `None` below 2 samples.
pub fn rate_stats(times_ns: &[i64], messages: usize) -> Option<RateStats> {
    if times_ns.len() < 2 {
        return None;
    }
    let mut periods: Vec<f64> = times_ns.windows(2).map(|w| (w[1] - w[0]) as f64 * 1e-6).collect();
    let n = periods.len() as f64;
    let mean = periods.iter().sum::<f64>() / n;
    let var = periods.iter().map(|p| (p - mean).powi(2)).sum::<f64>() / n;
    periods.sort_by(f64::total_cmp);
    let pct = |q: f64| periods[((q * (periods.len() - 1) as f64).round() as usize).min(periods.len() - 1)];
    Some(RateStats {
        messages,
        rate_hz: if mean > 0.0 { 1000.0 / mean } else { f64::INFINITY },
        period_mean_ms: mean,
        period_min_ms: periods[0],
        period_max_ms: periods[periods.len() - 1],
        period_std_ms: var.sqrt(),
        period_p50_ms: pct(0.5),
        period_p99_ms: pct(0.99),
    })
}

pub fn hz(args: HzArgs) -> anyhow::Result<ExitCode> {
    if args.window < 2 {
        bail!("--window must be at least 2, got {}", args.window);
    }
    let rt = runtime()?;
    rt.block_on(async {
        let Some(Opened { shutdown, _ros, type_name, sub }) = open("hz", &args.topic, &args.sub).await? else {
            return Ok(ExitCode::from(EXIT_NOT_FOUND));
        };
        let end = match args.duration {
            Some(d) => Some(tokio::time::Instant::now() + secs(d, "duration")?),
            None => None,
        };
        let mut stream = Box::pin(sub.stream());
        let mut times: std::collections::VecDeque<i64> = std::collections::VecDeque::new();
        let mut messages = 0usize;
        let mut report = tokio::time::interval(Duration::from_secs(1));
        report.tick().await;
        let finished = async {
            match end {
                Some(t) => tokio::time::sleep_until(t).await,
                None => std::future::pending().await,
            }
        };
        tokio::pin!(finished);
        loop {
            tokio::select! {
                _ = shutdown.wait() => break,
                _ = &mut finished => break,
                _ = report.tick(), if !args.json => {
                    let t: Vec<i64> = times.iter().copied().collect();
                    match rate_stats(&t, messages) {
                        Some(s) => println!(
                            "average rate: {:.3} Hz\n\tmin: {:.3} ms max: {:.3} ms std dev: {:.3} ms window: {}",
                            s.rate_hz, s.period_min_ms, s.period_max_ms, s.period_std_ms, t.len()
                        ),
                        None => println!("no new messages on {}", args.topic),
                    }
                }
                item = stream.next() => match item {
                    None => break,
                    Some(Err(e)) => tracing::warn!("{e}"),
                    Some(Ok(s)) => {
                        messages += 1;
                        times.push_back(s.receive_time.0);
                        while times.len() > args.window {
                            times.pop_front();
                        }
                    }
                },
            }
        }
        let t: Vec<i64> = times.iter().copied().collect();
        let stats = rate_stats(&t, messages);
        if args.json {
            println!("{}", json!({ "topic": args.topic, "type": type_name, "stats": stats }));
        }
        Ok(ExitCode::SUCCESS)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rate_stats_of_a_steady_100hz_stream() {
        let times: Vec<i64> = (0..101).map(|i| i * 10_000_000).collect();
        let s = rate_stats(&times, 101).unwrap();
        assert!((s.rate_hz - 100.0).abs() < 1e-9);
        assert_eq!((s.period_min_ms, s.period_max_ms, s.period_p99_ms), (10.0, 10.0, 10.0));
        assert!(s.period_std_ms < 1e-9);
        assert!(rate_stats(&times[..1], 1).is_none());
    }
}
