//! labrig-dataset: the paper's dataset tools over DROID-format data.
//!
//! - [`row`]: one index row per episode (the dimensions of variation the paper retrieves by);
//! - [`dv`]: what is derived from an episode's low-dimensional data and words: camera pose
//!   bins, the object position at the first gripper close, object / motion primitive / colour
//!   from the instruction through an editable vocabulary;
//! - [`source`]: readers by auto-detection: labrig MCAP episodes and DROID raw episodes
//!   (trajectory.h5 + metadata JSON), DROID's RLDS TFRecord shards ([`rlds`]), low-dimensional
//!   data only; [`recal`]: DROID's re-calibrated extrinsics as an override;
//! - [`table`]: the index as a directory of Parquet parts (columns any Parquet reader queries);
//! - [`retrieve`]: the paper's alignment rules, in its order, with the funnel, and the manifest
//!   `labrig train --cotrain` reads.
//!
//! A library with no transport (no tokio, DDS, iceoryx2) and none of mujoco, tch or OpenCV.

pub mod bench;
pub mod dv;
pub mod lerobot;
pub mod lerobot_import;
pub mod recal;
pub mod retrieve;
pub mod rlds;
pub mod row;
pub mod source;
pub mod stats;
pub mod table;

/// The index's schema version (a column of every row; readers refuse another).
pub const INDEX_VERSION: u32 = 2;
