//! The rosbag2 side of an episode file: the QoS text every channel carries, and the bag
//! description rosbag2 keeps twice — as the `rosbag2` metadata record inside the MCAP and as
//! `metadata.yaml` beside it. rosbags drops a topic silently when the two QoS texts differ, so
//! both come from [`qos_yaml`].

use std::fmt::Write as _;

/// The reliability a topic was recorded with (how its publisher offered it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    Reliable,
    BestEffort,
}

/// rosbag2's `offered_qos_profiles` (metadata version 9: string enums; unknown history and
/// depth 0 and infinite durations, as `ros2 bag record` stores a discovered publisher).
pub fn qos_yaml(r: Reliability) -> String {
    let rel = match r {
        Reliability::Reliable => "reliable",
        Reliability::BestEffort => "best_effort",
    };
    let inf = "\n    sec: 9223372036\n    nsec: 854775807";
    format!(
        "- history: unknown\n  depth: 0\n  reliability: {rel}\n  durability: volatile\n  deadline:{inf}\n  lifespan:{inf}\n  liveliness: automatic\n  liveliness_lease_duration:{inf}\n  avoid_ros_namespace_conventions: false"
    )
}

/// One topic of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct TopicInfo {
    pub name: String,
    pub type_name: String,
    pub qos_yaml: String,
    pub count: u64,
}

/// What rosbag2 records about a finished bag.
#[derive(Debug, Clone, PartialEq)]
pub struct BagInfo {
    /// The MCAP's file name, relative to the bag directory.
    pub file_name: String,
    pub start_ns: i64,
    pub end_ns: i64,
    pub topics: Vec<TopicInfo>,
    /// `custom_data` (string values).
    pub custom: Vec<(String, String)>,
}

impl BagInfo {
    pub fn message_count(&self) -> u64 {
        self.topics.iter().map(|t| t.count).sum()
    }

    fn duration_ns(&self) -> i64 {
        (self.end_ns - self.start_ns).max(0)
    }

    /// The bag description without the `rosbag2_bagfile_information:` wrapper, indented by
    /// `indent` spaces (the record holds it at 0, metadata.yaml at 2).
    pub fn body(&self, indent: usize) -> String {
        let pad = " ".repeat(indent);
        let mut s = String::new();
        let mut line = |text: &str| {
            for l in text.lines() {
                s.push_str(&pad);
                s.push_str(l);
                s.push('\n');
            }
        };
        line(&format!(
            "version: 9\nstorage_identifier: mcap\nduration:\n  nanoseconds: {}\nstarting_time:\n  nanoseconds_since_epoch: {}\nmessage_count: {}",
            self.duration_ns(),
            self.start_ns,
            self.message_count()
        ));
        if self.topics.is_empty() {
            line("topics_with_message_count: []");
        } else {
            line("topics_with_message_count:");
            for t in &self.topics {
                let mut block = format!(
                    "  - topic_metadata:\n      name: {}\n      type: {}\n      serialization_format: cdr\n      offered_qos_profiles:\n",
                    t.name, t.type_name
                );
                for l in t.qos_yaml.lines() {
                    let _ = writeln!(block, "        {l}");
                }
                let _ = write!(block, "      type_description_hash: \"\"\n    message_count: {}", t.count);
                line(&block);
            }
        }
        line(&format!(
            "compression_format: \"\"\ncompression_mode: \"\"\nrelative_file_paths:\n  - {f}\nfiles:\n  - path: {f}\n    starting_time:\n      nanoseconds_since_epoch: {}\n    duration:\n      nanoseconds: {}\n    message_count: {}",
            self.start_ns,
            self.duration_ns(),
            self.message_count(),
            f = self.file_name
        ));
        if self.custom.is_empty() {
            line("custom_data: ~");
        } else {
            line("custom_data:");
            for (k, v) in &self.custom {
                line(&format!("  {k}: {}", serde_json::to_string(v).unwrap_or_default()));
            }
        }
        line("ros_distro: jazzy");
        s
    }

    /// metadata.yaml's text.
    pub fn metadata_yaml(&self) -> String {
        format!("rosbag2_bagfile_information:\n{}", self.body(2))
    }

    /// The `rosbag2` MCAP metadata record's map.
    pub fn record(&self) -> std::collections::BTreeMap<String, String> {
        [("serialized_metadata".to_owned(), self.body(0)), ("ROS_DISTRO".to_owned(), "jazzy".to_owned())]
            .into_iter()
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metadata_yaml_has_no_nulls_and_repeats_the_channel_qos() {
        let qos = qos_yaml(Reliability::BestEffort);
        let info = BagInfo {
            file_name: "episode_0.mcap".into(),
            start_ns: 10,
            end_ns: 30,
            topics: vec![TopicInfo {
                name: "/a".into(),
                type_name: "std_msgs/msg/String".into(),
                qos_yaml: qos.clone(),
                count: 3,
            }],
            custom: vec![("uuid".into(), "LAB+op+2026".into())],
        };
        let y = info.metadata_yaml();
        assert!(y.starts_with("rosbag2_bagfile_information:\n  version: 9\n"), "{y}");
        assert!(y.contains("  message_count: 3\n") && y.contains("nanoseconds: 20\n"), "{y}");
        for l in qos.lines() {
            assert!(y.contains(&format!("          {l}\n")), "QoS line {l:?} missing:\n{y}");
        }
        assert!(y.contains("custom_data:\n    uuid: \"LAB+op+2026\"\n"), "{y}");
        let empty = BagInfo { topics: vec![], custom: vec![], ..info };
        assert!(empty.metadata_yaml().contains("topics_with_message_count: []"));
        assert!(empty.metadata_yaml().contains("custom_data: ~"));
    }
}
