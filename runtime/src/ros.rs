//! ROS 2 through ros2-client (RustDDS), the way every labrig node uses it.
//!
//! - DDS stays on 127.0.0.1 unless [`RosConfig::loopback_only`] is false.
//! - QoS is always explicit ([`qos`]); ros2-client's own defaults differ from rclpy's.
//! - Subscriptions decode with labrig-msgs' strict codec: a malformed message is an error item
//!   naming the type and topic, never a panic and never silently skipped.
//! - Reliable publishes wait at most [`qos::PUBLISH_WAIT`] for buffer space, so a slow peer
//!   cannot stall a control loop.

use crate::config::RosConfig;
use futures::{Stream, StreamExt};
use labrig_msgs::topics::{Service, Topic};
use labrig_msgs::{CodecError, Nanos, RosMessage, RosService, decode_payload};
use ros2_client::{
    Context, MessageTypeName, Name, Node, NodeName, NodeOptions, ServiceMapping, ServiceTypeName, qos::QosProfile,
};
use rustdds::no_key::{DeserializerAdapter, SimpleDataReader};
use rustdds::{DomainParticipant, DomainParticipantBuilder, QosPolicies, RepresentationIdentifier, TopicKind};
use serde::{Deserialize, Serialize};
use std::marker::PhantomData;
use std::net::Ipv4Addr;
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// Errors from the ROS 2 layer. Each names the topic or service involved.
#[derive(Debug, thiserror::Error)]
pub enum RosError {
    #[error("cannot create DDS participant (domain {domain_id}): {message}")]
    Participant { domain_id: u16, message: String },
    #[error("invalid ROS name {name:?}: {message}")]
    Name { name: String, message: String },
    #[error("cannot create {what} on {topic}: {message}")]
    Create { what: &'static str, topic: String, message: String },
    #[error("publish on {topic} failed: {message}")]
    Publish { topic: String, message: String },
    #[error("read on {topic} failed: {message}")]
    Read { topic: String, message: String },
    #[error("on {topic}: {source}")]
    Decode {
        topic: String,
        #[source]
        source: CodecError,
    },
    #[error("service {service}: {message}")]
    Service { service: String, message: String },
    #[error("service {service}: no response within {timeout:?}")]
    Timeout { service: String, timeout: Duration },
}

/// QoS presets. Pick one per topic; never rely on a library default.
pub mod qos {
    use ros2_client::qos::{Durability, History, QosProfile, Reliability, WhenFull};
    use std::time::Duration;

    /// The longest a reliable publish may block waiting for a slow reader.
    pub const PUBLISH_WAIT: Duration = Duration::from_millis(5);

    /// Reliable, volatile, keep last `depth` (commands, states, events).
    pub fn reliable(depth: usize) -> QosProfile {
        QosProfile::subscription_default()
            .reliability(Reliability::Reliable { when_full: WhenFull::Wait(PUBLISH_WAIT) })
            .durability(Durability::Volatile)
            .history(History::KeepLast { depth })
    }

    /// Best effort, keep last `depth` (high-rate sensor data; matches any publisher).
    pub fn best_effort(depth: usize) -> QosProfile {
        QosProfile::subscription_default()
            .reliability(Reliability::BestEffort)
            .durability(Durability::Volatile)
            .history(History::KeepLast { depth })
    }

    /// Reliable + transient local: late joiners get the last `depth` samples
    /// (`/tf_static`, camera_info, episode metadata).
    pub fn latched(depth: usize) -> QosProfile {
        reliable(depth).durability(Durability::TransientLocal)
    }

    /// The profile of a contract topic's [`labrig_msgs::topics::Delivery`] with this endpoint's
    /// history `depth`.
    pub fn of(delivery: labrig_msgs::topics::Delivery, depth: usize) -> QosProfile {
        use labrig_msgs::topics::Delivery;
        match delivery {
            Delivery::Reliable => reliable(depth),
            Delivery::Latched => latched(depth),
            Delivery::BestEffort => best_effort(depth),
        }
    }
}

/// A topic seen on the DDS graph, in ROS form.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TopicInfo {
    /// `/chatter`, or for services `/add_two_ints` with `kind` = request/reply.
    pub name: String,
    /// `pkg/msg/Name` (or `pkg/srv/Name_Request`).
    pub type_name: String,
    pub kind: TopicKindInfo,
}

/// Another participant's publisher or subscription (see [`Ros::remote_endpoints`]).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct EndpointInfo {
    pub topic: TopicInfo,
    pub kind: EndpointKind,
    /// The participant's GUID prefix (which process it is, for telling peers apart).
    pub participant: String,
    /// The type hash it announced (`RIHS01_...`), if any.
    pub type_hash: Option<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EndpointKind {
    Publisher,
    Subscription,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TopicKindInfo {
    Topic,
    ServiceRequest,
    ServiceReply,
    /// A DDS topic that is not mapped from ROS 2 (e.g. `ros_discovery_info`).
    Dds,
}

/// A node's handle on ROS 2: one DDS participant, one ros2-client node, its spinner.
pub struct Ros {
    context: Context,
    /// None only while the handle is dropped ([`Drop`] ends it before the spinner).
    node: Option<Node>,
    participant: DomainParticipant,
    subscriber: rustdds::Subscriber,
    spinner: Option<tokio::task::JoinHandle<()>>,
    watch: DdsWatch,
}

/// RustDDS announces itself (SPDP) on 127.0.0.1 to participant ids 0..11 only: two
/// participants of one domain that both have an id of 12 or more never discover each other.
/// A participant past the limit is refused (measured by `tests/tests/domains.rs`).
pub const MAX_PARTICIPANTS_PER_DOMAIN: u16 = 12;

/// Whether a process exits (status 1, the reason on stderr) when its DDS threads die: set by
/// the node skeleton for `run`, so the launcher restarts a node whose transport is gone
/// instead of it running on deaf and mute.
static EXIT_ON_DDS_DEATH: AtomicBool = AtomicBool::new(false);

/// Nodes call this once (`labrig_runtime::node_main` does, for `run`).
pub fn exit_on_dds_death(on: bool) {
    EXIT_ON_DDS_DEATH.store(on, Ordering::SeqCst);
}

/// The thread ids of this process's RustDDS threads (`/proc/self/task/<tid>/comm` starts
/// with "RustDDS": its discovery thread and each participant's event loop).
fn dds_threads() -> std::collections::BTreeSet<u32> {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return Default::default() };
    tasks
        .filter_map(|t| {
            let t = t.ok()?;
            let tid: u32 = t.file_name().to_str()?.parse().ok()?;
            let comm = std::fs::read_to_string(t.path().join("comm")).ok()?;
            comm.starts_with("RustDDS").then_some(tid)
        })
        .collect()
}

/// Watches a participant's RustDDS threads. They exit for good when `epoll_wait` is
/// interrupted (EINTR: the process was stopped and continued — Ctrl-Z, a debugger — or a
/// signal landed on them), and DDS is then dead while the node runs on.
struct DdsWatch {
    stop: Arc<AtomicBool>,
    dead: Arc<AtomicBool>,
}

impl DdsWatch {
    fn start(threads: std::collections::BTreeSet<u32>, domain_id: u16) -> DdsWatch {
        let stop = Arc::new(AtomicBool::new(false));
        let dead = Arc::new(AtomicBool::new(false));
        let (s, d) = (stop.clone(), dead.clone());
        let spawned = std::thread::Builder::new().name("labrig-dds-watch".into()).spawn(move || {
            while !s.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(100));
                let gone: Vec<u32> =
                    threads.iter().copied().filter(|t| !Path::new(&format!("/proc/self/task/{t}")).exists()).collect();
                if gone.is_empty() || s.load(Ordering::SeqCst) {
                    continue;
                }
                d.store(true, Ordering::SeqCst);
                let why = format!(
                    "DDS stopped (domain {domain_id}): {} of RustDDS's {} threads exited (an interrupted epoll_wait: the \
                     process was stopped and continued, e.g. Ctrl-Z or a debugger)",
                    gone.len(),
                    threads.len()
                );
                tracing::error!("{why}");
                if EXIT_ON_DDS_DEATH.load(Ordering::SeqCst) {
                    eprintln!("error: {why}; exiting so the launcher can restart the node");
                    std::process::exit(1);
                }
                break;
            }
        });
        if let Err(e) = spawned {
            tracing::warn!("cannot watch the DDS threads: {e}");
        }
        DdsWatch { stop, dead }
    }
}

/// Builds the participant with SIGINT and SIGTERM blocked, so the RustDDS threads it starts
/// inherit the mask and those signals (the node's shutdown) land on other threads instead of
/// interrupting RustDDS's event loops. Returns the participant and its RustDDS threads.
fn build_participant(
    builder: DomainParticipantBuilder,
    domain_id: u16,
) -> Result<(DomainParticipant, std::collections::BTreeSet<u32>), RosError> {
    use nix::sys::signal::{SigSet, SigmaskHow, Signal, pthread_sigmask};
    // One participant built at a time in a process: two built at once (a launcher's and a
    // command's, on two runtime threads) would each count the other's threads as theirs, and
    // the other's normal end would read as this one's DDS dying.
    static BUILDING: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one_at_a_time = BUILDING.lock().unwrap_or_else(|e| e.into_inner());
    let before = dds_threads();
    let mut block = SigSet::empty();
    block.add(Signal::SIGINT);
    block.add(Signal::SIGTERM);
    let mut old = SigSet::empty();
    let masked = pthread_sigmask(SigmaskHow::SIG_BLOCK, Some(&block), Some(&mut old)).is_ok();
    let built = builder.build();
    if masked {
        let _ = pthread_sigmask(SigmaskHow::SIG_SETMASK, Some(&old), None);
    }
    let participant = built.map_err(|e| RosError::Participant { domain_id, message: e.to_string() })?;
    let threads = dds_threads().difference(&before).copied().collect();
    Ok((participant, threads))
}

impl std::fmt::Debug for Ros {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros").field("node", &self.node().fully_qualified_name()).finish()
    }
}

impl Ros {
    /// Joins ROS 2 as node `name`. Must be called inside a tokio runtime (the spinner, which
    /// answers ROS graph queries and parameter services, runs as a task).
    pub fn new(cfg: &RosConfig, name: &str) -> Result<Ros, RosError> {
        let domain_id = cfg.domain_id;
        let mut builder = DomainParticipantBuilder::new(domain_id);
        if cfg.loopback_only {
            builder = builder.with_only_networks([Ipv4Addr::LOCALHOST]);
        } else {
            tracing::warn!("ros.loopback_only = false: DDS discovery will use every network interface");
        }
        let (participant, threads) = build_participant(builder, domain_id)?;
        let id = participant.participant_id();
        if id >= MAX_PARTICIPANTS_PER_DOMAIN {
            return Err(RosError::Participant {
                domain_id,
                message: format!(
                    "this would be DDS participant {id} on this machine, and RustDDS discovers only {MAX_PARTICIPANTS_PER_DOMAIN} \
                     per domain on loopback (ids 0..{}): stop another node or tool on domain {domain_id}, or use another \
                     domain (--domain-id)",
                    MAX_PARTICIPANTS_PER_DOMAIN - 1
                ),
            });
        }
        let watch = DdsWatch::start(threads, domain_id);
        let context = Context::from_domain_participant(participant.clone())
            .map_err(|e| RosError::Participant { domain_id, message: e.to_string() })?;
        let node_name = NodeName::new(&cfg.namespace, name)
            .map_err(|e| RosError::Name { name: name.to_owned(), message: format!("{e:?}") })?;
        let mut node = context
            .new_node(node_name, NodeOptions::new().enable_rosout(false))
            .map_err(|e| RosError::Participant { domain_id, message: e.to_string() })?;
        let spinner = node.spinner().map_err(|e| RosError::Participant { domain_id, message: e.to_string() })?;
        let spinner = tokio::spawn(async move {
            if let Err(e) = spinner.spin().await {
                tracing::error!("ROS 2 spinner stopped: {e}");
            }
        });
        let subscriber = participant
            .create_subscriber(&QosPolicies::qos_none())
            .map_err(|e| RosError::Participant { domain_id, message: e.to_string() })?;
        Ok(Ros { context, node: Some(node), participant, subscriber, spinner: Some(spinner), watch })
    }

    /// False once this participant's RustDDS threads have died (see [`exit_on_dds_death`]).
    pub fn dds_alive(&self) -> bool {
        !self.watch.dead.load(Ordering::SeqCst)
    }

    /// This participant's id on the machine (0..[`MAX_PARTICIPANTS_PER_DOMAIN`]).
    pub fn participant_id(&self) -> u16 {
        self.participant.participant_id()
    }

    pub fn domain_id(&self) -> u16 {
        self.context.domain_id()
    }

    pub fn node_name(&self) -> String {
        self.node().fully_qualified_name()
    }

    fn parse_name(&self, name: &str) -> Result<Name, RosError> {
        let full = if name.starts_with('/') { name.to_owned() } else { format!("/{name}") };
        Name::parse(&full).map_err(|e| RosError::Name { name: name.to_owned(), message: format!("{e:?}") })
    }

    /// The DDS topic name ROS 2 uses for a topic (`/a/b` -> `rt/a/b`).
    pub fn dds_topic_name(topic: &str) -> String {
        format!("rt/{}", topic.trim_start_matches('/'))
    }

    /// A typed publisher with explicit QoS.
    pub fn publisher<T: RosMessage>(&mut self, topic: &str, qos: QosProfile) -> Result<RosPublisher<T>, RosError> {
        let create = |message: String| RosError::Create { what: "publisher", topic: topic.to_owned(), message };
        let name = self.parse_name(topic)?;
        let ros_topic =
            self.node().create_topic(&name, message_type_name::<T>(), &qos).map_err(|e| create(e.to_string()))?;
        let publisher =
            self.node_mut().create_publisher::<T>(&ros_topic, Some(qos)).map_err(|e| create(e.to_string()))?;
        Ok(RosPublisher { publisher, topic: topic.to_owned() })
    }

    /// A publisher on a contract topic ([`labrig_msgs::topics`]): its name, type and delivery,
    /// with this endpoint's history `depth`.
    pub fn publisher_on<T: RosMessage>(&mut self, topic: &Topic<T>, depth: usize) -> Result<RosPublisher<T>, RosError> {
        self.publisher(topic.name, qos::of(topic.delivery, depth))
    }

    /// [`Ros::publisher_on`] under a prefix (`/sim` + `/arm/state`).
    pub fn publisher_at<T: RosMessage>(
        &mut self,
        prefix: &str,
        topic: &Topic<T>,
        depth: usize,
    ) -> Result<RosPublisher<T>, RosError> {
        self.publisher(&topic.at(prefix), qos::of(topic.delivery, depth))
    }

    /// A subscription to a contract topic, with this endpoint's history `depth`.
    pub fn subscription_on<T: RosMessage>(
        &mut self,
        topic: &Topic<T>,
        depth: usize,
    ) -> Result<RosSubscription<T>, RosError> {
        self.subscription(topic.name, qos::of(topic.delivery, depth))
    }

    /// [`Ros::subscription_on`] under a prefix.
    pub fn subscription_at<T: RosMessage>(
        &mut self,
        prefix: &str,
        topic: &Topic<T>,
        depth: usize,
    ) -> Result<RosSubscription<T>, RosError> {
        self.subscription(&topic.at(prefix), qos::of(topic.delivery, depth))
    }

    /// A server of a contract service.
    pub fn server_on<S: RosService>(&mut self, service: &Service<S>) -> Result<RosServer<S>, RosError> {
        self.server(service.name, qos::reliable(10))
    }

    /// A client of a contract service.
    pub fn client_on<S: RosService>(&mut self, service: &Service<S>) -> Result<RosClient<S>, RosError> {
        self.client(service.name, qos::reliable(10))
    }

    /// A typed subscription with explicit QoS, decoding with labrig-msgs' strict codec.
    pub fn subscription<T: RosMessage>(
        &mut self,
        topic: &str,
        qos: QosProfile,
    ) -> Result<RosSubscription<T>, RosError> {
        let raw = self.raw_subscription(topic, &labrig_msgs::dds_type_name(T::TYPE_NAME), qos)?;
        Ok(RosSubscription { raw, _type: PhantomData })
    }

    /// A subscription that hands over undecoded CDR payloads: for tools that learn a topic's
    /// type at run time (`labrig topic echo/hz`). `dds_type_name` as discovered
    /// (`pkg::msg::dds_::Name_`).
    pub fn raw_subscription(
        &mut self,
        topic: &str,
        dds_type_name: &str,
        qos: QosProfile,
    ) -> Result<RawSubscription, RosError> {
        let create = |message: String| RosError::Create { what: "subscription", topic: topic.to_owned(), message };
        let policies: QosPolicies = (&qos).into();
        let dds_topic = self
            .participant
            .create_topic(Self::dds_topic_name(topic), dds_type_name.to_owned(), &policies, TopicKind::NoKey)
            .map_err(|e| create(e.to_string()))?;
        let reader = self
            .subscriber
            .create_simple_datareader_no_key::<RawSample, RawAdapter>(&dds_topic, Some(policies))
            .map_err(|e| create(e.to_string()))?;
        Ok(RawSubscription { reader, topic: topic.to_owned() })
    }

    /// A service server (`ServiceMapping::Enhanced`, the mapping rmw_fastrtps uses).
    pub fn server<S: RosService>(&mut self, service: &str, qos: QosProfile) -> Result<RosServer<S>, RosError> {
        let name = self.parse_name(service)?;
        let server = self
            .node_mut()
            .create_server::<Wire<S::Request>, Wire<S::Response>>(
                ServiceMapping::Enhanced,
                &name,
                &service_type_name::<S>(),
                qos.clone(),
                qos,
            )
            .map_err(|e| RosError::Create {
                what: "service server",
                topic: service.to_owned(),
                message: e.to_string(),
            })?;
        Ok(RosServer { server, service: service.to_owned() })
    }

    /// A service client (`ServiceMapping::Enhanced`).
    pub fn client<S: RosService>(&mut self, service: &str, qos: QosProfile) -> Result<RosClient<S>, RosError> {
        let name = self.parse_name(service)?;
        let client = self
            .node_mut()
            .create_client::<Wire<S::Request>, Wire<S::Response>>(
                ServiceMapping::Enhanced,
                &name,
                &service_type_name::<S>(),
                qos.clone(),
                qos,
            )
            .map_err(|e| RosError::Create {
                what: "service client",
                topic: service.to_owned(),
                message: e.to_string(),
            })?;
        Ok(RosClient { client, service: service.to_owned() })
    }

    /// Topics discovered on the DDS graph so far (ours included), in ROS form, sorted.
    pub fn discovered_topics(&self) -> Vec<TopicInfo> {
        let mut topics: Vec<TopicInfo> =
            self.context.discovered_topics().into_iter().map(|t| ros_topic_info(&t.name, &t.type_name)).collect();
        topics.sort();
        topics.dedup();
        topics
    }

    /// The other participants' publishers and subscriptions seen on the DDS graph so far, each
    /// with the type hash it announced (REP 2016: `typehash=RIHS01_...;` in the endpoint's
    /// USER_DATA, as rmw implementations since Iron write it). labrig's own endpoints announce
    /// none: RustDDS 0.15 writes no USER_DATA for local endpoints.
    pub fn remote_endpoints(&self) -> Vec<EndpointInfo> {
        use rustdds::RTPSEntity;
        let own = self.participant.guid().prefix;
        let writers = self.participant.discovered_writers().into_iter().map(|w| {
            let t = &w.publication_topic_data;
            (t.key, t.topic_name.clone(), t.type_name.clone(), EndpointKind::Publisher, w.user_data)
        });
        let readers = self.participant.discovered_readers().into_iter().map(|r| {
            let t = &r.subscription_topic_data;
            (t.key(), t.topic_name().clone(), t.type_name().clone(), EndpointKind::Subscription, r.user_data)
        });
        let mut out: Vec<EndpointInfo> = writers
            .chain(readers)
            .filter(|(guid, ..)| guid.prefix != own)
            .map(|(guid, topic, ty, kind, user_data)| EndpointInfo {
                topic: ros_topic_info(&topic, &ty),
                kind,
                participant: format!("{:?}", guid.prefix),
                type_hash: labrig_msgs::type_hash::from_user_data(&user_data),
            })
            .collect();
        out.sort();
        out
    }

    /// Number of matched remote readers of a topic we publish, as the ROS graph reports it.
    pub fn subscription_count(&self, topic: &str) -> usize {
        self.node().subscription_count(topic)
    }

    /// Number of known publishers of a topic, as the ROS graph reports it.
    pub fn publisher_count(&self, topic: &str) -> usize {
        self.node().publisher_count(topic)
    }

    /// Waits (bounded) until a topic with this name is discovered; returns its info.
    pub async fn wait_for_topic(&self, topic: &str, timeout: Duration) -> Option<TopicInfo> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            if let Some(t) =
                self.discovered_topics().into_iter().find(|t| t.name == topic && t.kind == TopicKindInfo::Topic)
            {
                return Some(t);
            }
            if tokio::time::Instant::now() >= deadline {
                return None;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Waits (bounded) until at least `n` remote readers subscribe to `topic`.
    pub async fn wait_for_subscribers(&self, topic: &str, n: usize, timeout: Duration) -> bool {
        let deadline = tokio::time::Instant::now() + timeout;
        while self.subscription_count(topic) < n {
            if tokio::time::Instant::now() >= deadline {
                return false;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        true
    }
}

impl Ros {
    fn node(&self) -> &Node {
        self.node.as_ref().expect("the ROS 2 node is there until the handle is dropped")
    }

    fn node_mut(&mut self) -> &mut Node {
        self.node.as_mut().expect("the ROS 2 node is there until the handle is dropped")
    }
}

impl Drop for Ros {
    fn drop(&mut self) {
        // Before the participant goes (its threads end with it).
        self.watch.stop.store(true, Ordering::SeqCst);
        // The node first: dropping it tells the spinner to stop, which ros2-client logs as an
        // error ("Cannot notify spin task to stop") once the spinner is gone.
        drop(self.node.take());
        if let Some(s) = self.spinner.take() {
            s.abort();
        }
    }
}

fn message_type_name<T: RosMessage>() -> MessageTypeName {
    let (pkg, name) = split_type_name(T::TYPE_NAME);
    MessageTypeName::new(pkg, name)
}

fn service_type_name<S: RosService>() -> ServiceTypeName {
    let (pkg, name) = split_type_name(S::TYPE_NAME);
    ServiceTypeName::new(pkg, name)
}

/// `pkg/msg/Name` -> (`pkg`, `Name`).
fn split_type_name(type_name: &str) -> (&str, &str) {
    let pkg = type_name.split('/').next().unwrap_or(type_name);
    let name = type_name.rsplit('/').next().unwrap_or(type_name);
    (pkg, name)
}

/// DDS names -> ROS names: `rt/x` topics, `rq/xRequest` / `rr/xReply` services.
fn ros_topic_info(dds_name: &str, dds_type: &str) -> TopicInfo {
    let type_name = dds_type_to_ros(dds_type);
    let (name, kind) = if let Some(t) = dds_name.strip_prefix("rt/") {
        (format!("/{t}"), TopicKindInfo::Topic)
    } else if let Some(s) = dds_name.strip_prefix("rq/") {
        (format!("/{}", s.strip_suffix("Request").unwrap_or(s)), TopicKindInfo::ServiceRequest)
    } else if let Some(s) = dds_name.strip_prefix("rr/") {
        (format!("/{}", s.strip_suffix("Reply").unwrap_or(s)), TopicKindInfo::ServiceReply)
    } else {
        (dds_name.to_owned(), TopicKindInfo::Dds)
    };
    TopicInfo { name, type_name, kind }
}

/// `pkg::msg::dds_::Name_` -> `pkg/msg/Name`; anything else unchanged.
pub fn dds_type_to_ros(dds_type: &str) -> String {
    match dds_type.split_once("::dds_::") {
        Some((prefix, name)) => format!("{}/{}", prefix.replace("::", "/"), name.strip_suffix('_').unwrap_or(name)),
        None => dds_type.to_owned(),
    }
}

/// A typed publisher.
pub struct RosPublisher<T: RosMessage> {
    publisher: ros2_client::Publisher<T>,
    topic: String,
}

impl<T: RosMessage> std::fmt::Debug for RosPublisher<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RosPublisher<{}>({})", T::TYPE_NAME, self.topic)
    }
}

impl<T: RosMessage> RosPublisher<T> {
    /// Publishes; blocks at most [`qos::PUBLISH_WAIT`] on a full reliable window.
    pub fn publish(&self, msg: T) -> Result<(), RosError> {
        self.publisher
            .publish(msg)
            .map_err(|e| RosError::Publish { topic: self.topic.clone(), message: format!("{e:?}") })
    }

    pub fn topic(&self) -> &str {
        &self.topic
    }
}

/// One undecoded sample: CDR representation id and body (encapsulation header stripped).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawSample {
    pub encoding: [u8; 2],
    pub payload: Vec<u8>,
}

impl RawSample {
    /// The bytes with their 4-byte encapsulation header, as rclpy's `serialize_message` and
    /// MCAP `cdr` messages hold them.
    pub fn to_cdr_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(4 + self.payload.len());
        out.extend_from_slice(&self.encoding);
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&self.payload);
        out
    }
}

/// RustDDS adapter that keeps the payload bytes as they came.
#[derive(Debug)]
pub struct RawAdapter;

/// The decoder [`RawAdapter`] uses: copies the bytes.
#[derive(Debug, Clone, Copy)]
pub struct RawDecoder;

impl<'de> rustdds::no_key::Decode<'de, RawSample> for RawDecoder {
    type Error = std::convert::Infallible;
    fn decode_bytes(
        self,
        input_bytes: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawSample, Self::Error> {
        Ok(RawSample { encoding: encoding.to_bytes(), payload: input_bytes.to_vec() })
    }
}

impl DeserializerAdapter<RawSample> for RawAdapter {
    type Error = std::convert::Infallible;
    type Decoded = RawSample;
    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &[RepresentationIdentifier::CDR_LE, RepresentationIdentifier::CDR_BE]
    }
    fn transform_decoded(decoded: RawSample) -> RawSample {
        decoded
    }
}

impl rustdds::no_key::DefaultDecoder<RawSample> for RawAdapter {
    type Decoder = RawDecoder;
    const DECODER: RawDecoder = RawDecoder;
}

/// A received message with its times.
#[derive(Debug, Clone, PartialEq)]
pub struct Received<T> {
    pub msg: T,
    /// The writer's source timestamp (DDS), if it sent one.
    pub source_time: Option<Nanos>,
    /// Wall time when this process took it from DDS.
    pub receive_time: Nanos,
}

/// Undecoded samples of one topic.
pub struct RawSubscription {
    reader: SimpleDataReader<RawSample, RawAdapter>,
    topic: String,
}

impl std::fmt::Debug for RawSubscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RawSubscription({})", self.topic)
    }
}

fn wall_now() -> Nanos {
    crate::Clock::Wall.now()
}

/// RTPS time (seconds + 2^-32 s fractions since the Unix epoch) -> ns.
fn rtps_time_to_nanos(t: rustdds::Timestamp) -> Nanos {
    let ticks = t.to_ticks();
    let secs = (ticks >> 32) as i64;
    let frac = ((ticks & 0xFFFF_FFFF) * 1_000_000_000) >> 32;
    Nanos(secs * 1_000_000_000 + frac as i64)
}

fn to_received(dcc: rustdds::no_key::DeserializedCacheChange<RawSample>) -> Received<RawSample> {
    let source_time = dcc.source_timestamp().map(rtps_time_to_nanos);
    Received { msg: dcc.into_value(), source_time, receive_time: wall_now() }
}

impl RawSubscription {
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// Takes one sample if any is waiting.
    pub fn try_take(&self) -> Result<Option<Received<RawSample>>, RosError> {
        self.reader
            .try_take_one()
            .map(|o| o.map(to_received))
            .map_err(|e| RosError::Read { topic: self.topic.clone(), message: e.to_string() })
    }

    /// All samples as they arrive.
    pub fn stream(&self) -> impl Stream<Item = Result<Received<RawSample>, RosError>> + '_ {
        self.reader.as_async_stream().map(move |r| {
            r.map(to_received).map_err(|e| RosError::Read { topic: self.topic.clone(), message: e.to_string() })
        })
    }
}

/// A typed subscription over [`RawSubscription`] + labrig-msgs' strict decoder.
pub struct RosSubscription<T: RosMessage> {
    raw: RawSubscription,
    _type: PhantomData<fn() -> T>,
}

impl<T: RosMessage> std::fmt::Debug for RosSubscription<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RosSubscription<{}>({})", T::TYPE_NAME, self.raw.topic)
    }
}

impl<T: RosMessage> RosSubscription<T> {
    fn decode(&self, r: Received<RawSample>) -> Result<Received<T>, RosError> {
        let msg = decode_payload::<T>(r.msg.encoding, &r.msg.payload)
            .map_err(|source| RosError::Decode { topic: self.raw.topic.clone(), source })?;
        Ok(Received { msg, source_time: r.source_time, receive_time: r.receive_time })
    }

    /// Takes one message if any is waiting. A malformed message is an `Err` (the next call
    /// goes on with the following message).
    pub fn try_take(&self) -> Result<Option<Received<T>>, RosError> {
        match self.raw.try_take()? {
            None => Ok(None),
            Some(r) => self.decode(r).map(Some),
        }
    }

    /// All messages as they arrive; malformed ones appear as `Err` items.
    pub fn stream(&self) -> impl Stream<Item = Result<Received<T>, RosError>> + '_ {
        self.raw.stream().map(move |r| r.and_then(|r| self.decode(r)))
    }

    pub fn topic(&self) -> &str {
        &self.raw.topic
    }
}

/// Wraps a labrig message for ros2-client's service API (which needs its own `Message` trait).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Wire<T>(pub T);
impl<T: RosMessage> ros2_client::Message for Wire<T> {}

/// A service server.
pub struct RosServer<S: RosService> {
    server: ros2_client::Server<Wire<S::Request>, Wire<S::Response>>,
    service: String,
}

impl<S: RosService> std::fmt::Debug for RosServer<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RosServer<{}>({})", S::TYPE_NAME, self.service)
    }
}

/// Identifies a request so its response goes to the right client.
pub type RequestId = ros2_client::service::RmwRequestId;

impl<S: RosService> RosServer<S> {
    /// Waits for the next request.
    pub async fn receive(&self) -> Result<(RequestId, S::Request), RosError> {
        self.server
            .async_receive_request()
            .await
            .map(|(id, Wire(req))| (id, req))
            .map_err(|e| RosError::Service { service: self.service.clone(), message: e.to_string() })
    }

    pub async fn respond(&self, id: RequestId, response: S::Response) -> Result<(), RosError> {
        self.server
            .async_send_response(id, Wire(response))
            .await
            .map_err(|e| RosError::Service { service: self.service.clone(), message: format!("{e:?}") })
    }
}

/// A request a node's control loop answers: reply through `respond`.
#[derive(Debug)]
pub struct Served<S: RosService> {
    pub request: S::Request,
    respond: tokio::sync::oneshot::Sender<S::Response>,
}

impl<S: RosService> Served<S> {
    pub fn respond(self, response: S::Response) {
        // The client may have given up; nothing to do then.
        let _ = self.respond.send(response);
    }
}

impl<S: RosService> RosServer<S>
where
    S: Send + Sync + 'static,
    S::Request: Send + Sync + 'static,
    S::Response: Send + Sync + Default + 'static,
{
    /// Serves on a task of its own and hands each request to the caller's loop (`try_recv`
    /// between ticks, or `recv` in a `select!`); the loop answers with [`Served::respond`]. A
    /// request dropped unanswered gets the default response. The task ends with the receiver.
    pub fn forward(self) -> tokio::sync::mpsc::Receiver<Served<S>> {
        let (tx, rx) = tokio::sync::mpsc::channel::<Served<S>>(4);
        tokio::spawn(async move {
            loop {
                let (id, request) = match self.receive().await {
                    Ok(r) => r,
                    Err(e) => {
                        // A malformed request: reported, the service goes on.
                        tracing::warn!("{}: {e}", self.service);
                        if tx.is_closed() {
                            break;
                        }
                        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
                        continue;
                    }
                };
                let (respond, answer) = tokio::sync::oneshot::channel();
                if tx.send(Served { request, respond }).await.is_err() {
                    break;
                }
                let response = answer.await.unwrap_or_default();
                if let Err(e) = self.respond(id, response).await {
                    tracing::warn!("{}: {e}", self.service);
                }
            }
        });
        rx
    }
}

/// A service client.
pub struct RosClient<S: RosService> {
    client: ros2_client::Client<Wire<S::Request>, Wire<S::Response>>,
    service: String,
}

impl<S: RosService> std::fmt::Debug for RosClient<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RosClient<{}>({})", S::TYPE_NAME, self.service)
    }
}

impl<S: RosService> RosClient<S> {
    /// Waits (bounded) until a server is matched.
    pub async fn wait_for_service(&self, ros: &Ros, timeout: Duration) -> Result<(), RosError> {
        tokio::time::timeout(timeout, self.client.wait_for_service(ros.node()))
            .await
            .map_err(|_| RosError::Timeout { service: self.service.clone(), timeout })
    }

    /// Sends a request and waits (bounded) for its response.
    pub async fn call(&self, request: S::Request, timeout: Duration) -> Result<S::Response, RosError> {
        match tokio::time::timeout(timeout, self.client.async_call_service(Wire(request))).await {
            Err(_) => Err(RosError::Timeout { service: self.service.clone(), timeout }),
            Ok(Err(e)) => Err(RosError::Service { service: self.service.clone(), message: format!("{e:?}") }),
            Ok(Ok(Wire(resp))) => Ok(resp),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dds_names_map_back_to_ros_names() {
        assert_eq!(
            ros_topic_info("rt/joint_states", "sensor_msgs::msg::dds_::JointState_"),
            TopicInfo {
                name: "/joint_states".into(),
                type_name: "sensor_msgs/msg/JointState".into(),
                kind: TopicKindInfo::Topic
            }
        );
        let rq = ros_topic_info("rq/set_flagRequest", "std_srvs::srv::dds_::SetBool_Request_");
        assert_eq!((rq.name.as_str(), rq.kind), ("/set_flag", TopicKindInfo::ServiceRequest));
        assert_eq!(rq.type_name, "std_srvs/srv/SetBool_Request");
        assert_eq!(ros_topic_info("ros_discovery_info", "x").kind, TopicKindInfo::Dds);
    }
}
