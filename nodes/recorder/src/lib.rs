//! labrig-recorder: episodes as MCAP files in the rosbag2 layout, with DROID's metadata.
//!
//! - [`metadata`]: DROID's episode metadata record and directory layout.
//! - [`bag`]: the rosbag2 description (QoS text, `rosbag2` record, `metadata.yaml`).
//! - [`episode`]: [`episode::EpisodeWriter`], one episode being written.

pub mod bag;
pub mod episode;
pub mod metadata;

pub use episode::{EpisodeSummary, EpisodeWriter, RecorderError};
pub use metadata::{EpisodeMetadata, Outcome, RigIdentity, episode_dir};
