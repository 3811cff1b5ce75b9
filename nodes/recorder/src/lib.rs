//! labrig-recorder: episodes as MCAP files in the rosbag2 layout, with DROID's metadata.
//!
//! - [`metadata`]: DROID's episode metadata record and directory layout.
//! - [`bag`]: the rosbag2 description (QoS text, `rosbag2` record, `metadata.yaml`).
//! - [`episode`]: [`episode::EpisodeWriter`], one episode being written.
//! - [`node`]: the recorder node (DDS topics + shared-memory frames -> episodes).
//! - [`recover`]: an episode whose recorder died, made whole up to its last closed chunk.

pub mod bag;
pub mod episode;
pub mod inspect;
pub mod jpeg;
pub mod metadata;
pub mod node;
pub mod recover;

pub use episode::{EpisodeSummary, EpisodeWriter, RecorderError};
pub use metadata::{EpisodeMetadata, Outcome, RigIdentity, episode_dir};
