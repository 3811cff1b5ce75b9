//! labrig-recorder: episodes as MCAP files in the rosbag2 layout, with DROID's metadata.
//!
//! - [`metadata`]: DROID's episode metadata record and directory layout.

pub mod metadata;
