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

/// One storage file of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct BagFile {
    /// Relative to the bag directory.
    pub path: String,
    pub start_ns: i64,
    pub end_ns: i64,
    pub message_count: u64,
}

/// What rosbag2 records about a finished bag: one file, or an episode recorded in parts
/// (`episode_0.mcap`, `episode_1.mcap`, ... after a recorder restart), merged by [`BagInfo::merged`].
#[derive(Debug, Clone, PartialEq)]
pub struct BagInfo {
    /// The storage files, in order (one per recorded part).
    pub files: Vec<BagFile>,
    pub start_ns: i64,
    pub end_ns: i64,
    pub topics: Vec<TopicInfo>,
    /// `custom_data` (string values).
    pub custom: Vec<(String, String)>,
}

impl BagInfo {
    /// A bag of one file, `file_name`, covering the whole bag.
    pub fn single(
        file_name: &str,
        start_ns: i64,
        end_ns: i64,
        topics: Vec<TopicInfo>,
        custom: Vec<(String, String)>,
    ) -> BagInfo {
        let message_count = topics.iter().fold(0u64, |n, t| n.saturating_add(t.count));
        let files = vec![BagFile { path: file_name.to_owned(), start_ns, end_ns, message_count }];
        BagInfo { files, start_ns, end_ns, topics, custom }
    }

    /// The parts of one bag as one description: files in order, topic counts summed, the
    /// time span of all of them; `custom` from the last part that has any.
    pub fn merged(parts: &[BagInfo]) -> BagInfo {
        let mut topics: Vec<TopicInfo> = Vec::new();
        for t in parts.iter().flat_map(|p| &p.topics) {
            match topics.iter_mut().find(|m| m.name == t.name) {
                Some(m) => m.count = m.count.saturating_add(t.count),
                None => topics.push(t.clone()),
            }
        }
        topics.sort_by(|a, b| a.name.cmp(&b.name));
        let spans = parts.iter().filter(|p| p.message_count() > 0);
        let start_ns = spans.clone().map(|p| p.start_ns).min().or(parts.first().map(|p| p.start_ns)).unwrap_or(0);
        let end_ns = spans.map(|p| p.end_ns).max().unwrap_or(start_ns);
        BagInfo {
            files: parts.iter().flat_map(|p| p.files.iter().cloned()).collect(),
            start_ns,
            end_ns,
            topics,
            custom: parts.iter().rev().find(|p| !p.custom.is_empty()).map(|p| p.custom.clone()).unwrap_or_default(),
        }
    }

    pub fn message_count(&self) -> u64 {
        self.topics.iter().fold(0u64, |n, t| n.saturating_add(t.count))
    }

    fn duration_ns(&self) -> i64 {
        self.end_ns.saturating_sub(self.start_ns).max(0)
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
        line("compression_format: \"\"\ncompression_mode: \"\"\nrelative_file_paths:");
        for f in &self.files {
            line(&format!("  - {}", f.path));
        }
        line("files:");
        for f in &self.files {
            line(&format!(
                "  - path: {}\n    starting_time:\n      nanoseconds_since_epoch: {}\n    duration:\n      nanoseconds: {}\n    message_count: {}",
                f.path,
                f.start_ns,
                (f.end_ns - f.start_ns).max(0),
                f.message_count
            ));
        }
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
        let info = BagInfo::single(
            "episode_0.mcap",
            10,
            30,
            vec![TopicInfo {
                name: "/a".into(),
                type_name: "std_msgs/msg/String".into(),
                qos_yaml: qos.clone(),
                count: 3,
            }],
            vec![("uuid".into(), "LAB+op+2026".into())],
        );
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

    #[test]
    fn parts_merge_into_one_bag_listing_every_file() {
        let topic = |name: &str, count| TopicInfo {
            name: name.into(),
            type_name: "std_msgs/msg/String".into(),
            qos_yaml: qos_yaml(Reliability::Reliable),
            count,
        };
        let a = BagInfo::single("episode_0.mcap", 100, 200, vec![topic("/a", 3), topic("/b", 1)], vec![]);
        let b = BagInfo::single("episode_1.mcap", 500, 900, vec![topic("/a", 5)], vec![("uuid".into(), "x".into())]);
        let m = BagInfo::merged(&[a, b]);
        assert_eq!((m.start_ns, m.end_ns, m.message_count()), (100, 900, 9));
        assert_eq!(m.topics.iter().map(|t| (t.name.as_str(), t.count)).collect::<Vec<_>>(), [("/a", 8), ("/b", 1)]);
        let y = m.metadata_yaml();
        assert!(y.contains("relative_file_paths:\n    - episode_0.mcap\n    - episode_1.mcap\n"), "{y}");
        assert!(
            y.contains("  - path: episode_1.mcap\n      starting_time:\n        nanoseconds_since_epoch: 500\n"),
            "{y}"
        );
        assert!(y.contains("custom_data:\n    uuid: \"x\"\n"), "{y}");
    }
}
