//! labrig-droid: DROID's raw episode format (trajectory.h5 + one MP4 per camera + metadata
//! JSON), exported from labrig's MCAP episodes and imported back.
//!
//! - [`h5doc`]: an HDF5 file as plain data (hdf5-metno over Debian's libhdf5).
//! - [`droid`]: steps <-> DROID's trajectory.h5 keys, no I/O.
//! - [`meta`]: `metadata_<uuid>.json`.
//! - [`video`]: MP4 through ffmpeg.
//! - [`export`], [`import`]: whole episodes.

pub mod droid;
pub mod export;
pub mod h5doc;
pub mod import;
pub mod meta;
pub mod video;
