//! One index row per episode.

use serde::{Deserialize, Serialize};

/// The cameras an index row has columns for: DROID's two external cameras, labrig's two more
/// (the RealSenses), and the wrist camera. External cameras are the ones camPose compares.
pub const CAMERAS: [&str; 5] = ["ext1", "ext2", "rs1", "rs2", "wrist"];
pub const EXTERNAL_CAMERAS: [&str; 4] = ["ext1", "ext2", "rs1", "rs2"];

/// A camera's pose in the robot base frame, and where it sits around the table centre.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct CameraRow {
    pub serial: Option<String>,
    /// Position (m) and orientation (DROID's extrinsic xyz Euler angles, rad).
    pub position: Option<[f64; 3]>,
    pub euler: Option<[f64; 3]>,
    /// Spherical coordinates around the table centre: radius (m), polar and azimuth (deg).
    pub radius_m: Option<f64>,
    pub polar_deg: Option<f64>,
    pub azimuth_deg: Option<f64>,
    /// The paper's camPose bin, or `none` when the pose is known but in no bin.
    pub bin: Option<String>,
    /// Where the pose came from: `metadata` (the episode's own) or `recalibrated` (an
    /// `--extrinsics` override file).
    pub extrinsics_from: Option<String>,
}

/// One episode, as the index has it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct IndexRow {
    pub index_version: u32,
    pub episode_id: String,
    pub source_path: String,
    /// `labrig`, `droid_raw`, `droid_mcap` or `rlds`.
    pub source_format: String,
    pub file_size: u64,
    pub file_mtime_ns: i64,
    pub success: Option<bool>,
    pub lab: String,
    pub building: String,
    pub scene_id: String,
    pub instruction: Option<String>,
    pub instruction_2: Option<String>,
    pub instruction_3: Option<String>,
    pub length: u64,
    /// By [`CAMERAS`] order.
    pub cameras: Vec<CameraRow>,
    /// The end effector's position at the first gripper close (null when it never closes).
    pub object_position: Option<[f64; 3]>,
    pub object: Option<String>,
    pub primitive: Option<String>,
    pub colour: Option<String>,
    /// A sim episode's scene values (JSON), the DVs it was generated with.
    pub sim_dv: Option<String>,
}

impl IndexRow {
    pub fn camera(&self, id: &str) -> Option<&CameraRow> {
        CAMERAS.iter().position(|c| *c == id).and_then(|i| self.cameras.get(i))
    }

    /// Positions of the external cameras whose pose is known.
    pub fn external_positions(&self) -> Vec<(&'static str, [f64; 3])> {
        EXTERNAL_CAMERAS.iter().filter_map(|c| Some((*c, self.camera(c)?.position?))).collect()
    }
}
