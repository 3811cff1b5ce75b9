//! labrig-episode: the episode format, as a library any tool can read and write without a node.
//!
//! - [`metadata`]: DROID's episode metadata record and directory layout.
//! - [`bag`]: the rosbag2 description (QoS text, `rosbag2` record, `metadata.yaml`).
//! - [`episode`]: [`episode::EpisodeWriter`], one episode being written.
//! - [`inspect`]: one pass over an episode file (summary, steps, metadata).
//! - [`recover`]: an episode whose recorder died, made whole up to its last closed chunk.
//! - [`jpeg`]: camera frames as JPEG.
//! - [`judge`]: relabel (success <-> failure, `judged.json`) and trash, never rewriting a recording.
//! - [`sheet`]: an episode's contact sheet (PNG).
//! - [`progress`]: the progress bar every long-running tool shows.
//!
//! Depends on labrig-msgs, mcap, serde, chrono, jpeg-encoder, indicatif. Must never depend on tokio, DDS,
//! iceoryx2 or the heavy native crates (checked by `tests/tests/layering.rs`): the trainer and the
//! dataset tools read thousands of episodes with it.

pub mod bag;
pub mod calibration;
mod chunk;
mod durable;
pub mod episode;
pub mod font;
pub mod grey;
pub mod inspect;
pub mod jpeg;
pub mod judge;
pub mod metadata;
pub mod png;
pub mod progress;
pub mod recover;
pub mod sheet;

/// An MCAP log time (any u64) as the i64 nanoseconds the episode's times are: past i64::MAX
/// (year 2262) it saturates instead of turning negative.
pub(crate) fn log_ns(t: u64) -> i64 {
    i64::try_from(t).unwrap_or(i64::MAX)
}

pub use chunk::walk_records;
pub use episode::{EpisodeError, EpisodeSummary, EpisodeWriter};
pub use inspect::{EpisodeData, Gap, Inspection, Part, ReadError, inspect, read_episode};
pub use metadata::{EpisodeMetadata, MetadataError, Outcome, RigIdentity, episode_dir};
