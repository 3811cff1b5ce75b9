//! The rig's MJCF, composed from the extracted Menagerie models.

use crate::scene::{
    BIN_HALF, CABINET_HALF, CABINET_HEIGHT, DRAWER_TRAVEL, DrawerValues, HANDLE_LENGTH, OBJECT_SIZE, SceneValues,
    TABLE_CENTRE, TABLE_HALF,
};
use std::path::{Path, PathBuf};

/// Where `scripts/setup.sh` puts the models, relative to the repository root.
pub const DEFAULT_ASSETS: &str = ".labrig/mujoco/assets";

/// The rig's five cameras (see [`labrig_msgs::rig::RIG_CAMERAS`]).
pub use labrig_msgs::rig::RIG_CAMERAS as CAMERAS;

/// The FR3's joints and position actuators (same names in the model).
pub const ARM_JOINTS: [&str; 7] =
    ["fr3_joint1", "fr3_joint2", "fr3_joint3", "fr3_joint4", "fr3_joint5", "fr3_joint6", "fr3_joint7"];

/// The 2F-85's actuator after attaching it with prefix `gripper_`.
pub const GRIPPER_ACTUATOR: &str = "gripper_fingers_actuator";
/// One of the 2F-85's driver joints (0 open .. ~0.8 rad closed).
pub const GRIPPER_DRIVER_JOINT: &str = "gripper_right_driver_joint";

pub use labrig_msgs::rig::DROID_RESET_POSE as RESET_POSE;

/// Why the rig model could not be composed.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error("rig assets missing: cannot read {path}: {error} (run `bash scripts/setup.sh`)")]
    Missing { path: PathBuf, error: std::io::Error },
    #[error("{path} is not the FR3 model labrig expects: {what}")]
    Unexpected { path: PathBuf, what: String },
}

/// The `<body name="hand" ...>` subtree span (the Franka Hand), matched by nesting depth.
fn body_span(xml: &str, start: usize) -> Option<usize> {
    let mut depth = 0usize;
    let mut i = start;
    loop {
        let open = xml[i..].find("<body").map(|p| p + i);
        let close = xml[i..].find("</body>").map(|p| p + i);
        match (open, close) {
            (Some(o), Some(c)) if o < c => {
                let tag_end = xml[o..].find('>').map(|e| o + e)?;
                if !xml[..tag_end].ends_with('/') {
                    depth += 1;
                }
                i = tag_end + 1;
            }
            (_, Some(c)) => {
                depth = depth.checked_sub(1)?;
                i = c + 7;
                if depth == 0 {
                    return Some(i);
                }
            }
            _ => return None,
        }
    }
}

/// Removes every `<tag>...</tag>` block.
fn drop_blocks(xml: &str, tag: &str) -> String {
    let (open, close) = (format!("<{tag}>"), format!("</{tag}>"));
    let mut out = xml.to_owned();
    while let Some(s) = out.find(&open) {
        let Some(e) = out[s..].find(&close).map(|e| s + e + close.len()) else { break };
        out.replace_range(s..e, "");
    }
    out
}

/// Removes every self-closing element on its own line that contains all of `needles`.
fn drop_lines(xml: &str, needles: &[&str]) -> String {
    xml.lines().filter(|l| !needles.iter().all(|n| l.contains(n))).collect::<Vec<_>>().join("\n")
}

/// A calibration board in the scene (`labrig calibrate --sim`): its print, its size, where it is.
#[derive(Debug, Clone, PartialEq)]
pub struct Board {
    /// The print (a PNG of the whole board, as `labrig calibrate board` writes it), mapped
    /// edge to edge onto the board's face.
    pub texture: PathBuf,
    /// The print's width (along the board's x) and height (along its y), m.
    pub size_m: [f64; 2],
    pub mount: BoardMount,
}

/// What calibration adds to a scene.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Extras {
    pub board: Option<Board>,
    /// An external camera moved by (dx, dy, dz) m in the base frame from where the scene puts
    /// it (it still aims at the table centre): a camera knocked after calibration.
    pub move_camera: Option<(String, [f64; 3])>,
}

/// Where the board is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BoardMount {
    /// Held by the gripper for the external cameras (eye-to-hand): fixed to the flange below
    /// the fingers, its face tilted 45 deg up from the fingers' opening direction, so that with
    /// the gripper pointing down it faces a camera above the table.
    Gripper,
    /// Lying face up on the table for the wrist camera (eye-in-hand): its centre at (x, y) in
    /// the base frame, turned `yaw_deg` about z.
    Table { centre: [f64; 2], yaw_deg: f64 },
}

impl BoardMount {
    /// The wrist camera's board: lying across the table in front of the robot, its long side
    /// along y (what `labrig calibrate` puts in the scene for the wrist camera).
    pub fn on_table() -> BoardMount {
        let c = crate::scene::TABLE_CENTRE;
        BoardMount::Table { centre: [c[0] - 0.05, c[1]], yaw_deg: 90.0 }
    }
}

/// The body whose frame is the board's (OpenCV's ChArUco frame: origin at the print's top-left
/// corner, x right, y down, z into the board).
pub const BOARD_BODY: &str = labrig_msgs::calibration::BOARD_FRAME;
/// Where the gripper mount puts the board's top edge: this far along the flange's z (the
/// approach axis), past the 2F-85's fingertips.
pub const BOARD_GRIPPER_OFFSET_M: f64 = 0.17;
const BOARD_THICKNESS_M: f64 = 0.003;
/// The gripper mount's tilt (deg): 0 hangs the board in the plane of the approach axis.
pub const BOARD_TILT_DEG: f64 = 0.0;

/// The board's body (the frame) with its face: a thin box behind the frame's z = 0 plane whose
/// -z face carries the print.
fn board_body(board: &Board, pos: [f64; 3], xyaxes: [f64; 6]) -> String {
    let [w, h] = board.size_m;
    let t = BOARD_THICKNESS_M / 2.0;
    format!(
        r#"
              <body name="{BOARD_BODY}" pos="{}" xyaxes="{}">
                <geom name="calib_board" type="box" pos="{} {} {t}" size="{} {} {t}" material="board_mat" contype="0" conaffinity="0" mass="0.001"/>
              </body>"#,
        v3(pos),
        xyaxes.map(|v| v.to_string()).join(" "),
        w / 2.0,
        h / 2.0,
        w / 2.0,
        h / 2.0,
    )
}

/// The gripper mount in the flange's frame: the print's x along the flange's -x, its face
/// normal (out of the print) `-(cos t y_f + sin t z_f)` with t = [`BOARD_TILT_DEG`], its y
/// running down the approach axis.
fn gripper_board(board: &Board) -> String {
    let (st, ct) = BOARD_TILT_DEG.to_radians().sin_cos();
    let [w, _] = board.size_m;
    // Board axes in the flange frame: x = -x_f, y = -sin t y_f + cos t z_f, z = cos t y_f + sin t z_f.
    board_body(board, [w / 2.0, 0.0, BOARD_GRIPPER_OFFSET_M], [-1.0, 0.0, 0.0, 0.0, -st, ct])
}

fn table_board(board: &Board, centre: [f64; 2], yaw_deg: f64) -> String {
    let (s, c) = yaw_deg.to_radians().sin_cos();
    let [w, h] = board.size_m;
    // z = down (into the table); x = (c, s, 0); y = z x x = (s, -c, 0).
    let origin = [centre[0] - c * w / 2.0 - s * h / 2.0, centre[1] - s * w / 2.0 + c * h / 2.0, 0.0005];
    board_body(board, origin, [c, s, 0.0, s, -c, 0.0])
}

/// Composes the rig's MJCF for one scene from the assets folder (absolute paths inside, so the
/// text loads from anywhere). Textures are declared flat here and filled by [`crate::Sim`].
pub fn compose(assets: &Path, scene: &SceneValues) -> Result<String, RigError> {
    compose_with_board(assets, scene, None)
}

/// [`compose`] with a calibration board in the scene.
pub fn compose_with_board(assets: &Path, scene: &SceneValues, board: Option<&Board>) -> Result<String, RigError> {
    let fr3_path = assets.join("fr3/fr3.xml");
    let gripper = assets.join("robotiq_2f85/2f85.xml");
    let fr3 =
        std::fs::read_to_string(&fr3_path).map_err(|error| RigError::Missing { path: fr3_path.clone(), error })?;
    if !gripper.exists() {
        return Err(RigError::Missing {
            path: gripper,
            error: std::io::Error::new(std::io::ErrorKind::NotFound, "not found"),
        });
    }
    let unexpected = |what: &str| RigError::Unexpected { path: fr3_path.clone(), what: what.to_owned() };
    let meshes = assets.join("fr3/meshes");
    let mut xml = fr3;
    // The wheel's meshdir names a folder that does not exist; point at the real one.
    xml = xml.replace(r#"meshdir="assets""#, &format!(r#"meshdir="{}" autolimits="true""#, meshes.display()));
    // The Franka Hand comes off; a flange with the 2F-85 and the wrist camera goes on.
    let hand = xml.find(r#"<body name="hand""#).ok_or_else(|| unexpected("no body `hand`"))?;
    let end = body_span(&xml, hand).ok_or_else(|| unexpected("unbalanced <body> tags"))?;
    let flange = match board {
        Some(b @ Board { mount: BoardMount::Gripper, .. }) => {
            let close = FLANGE.rfind("</body>").expect("FLANGE ends its body");
            format!("{}{}\n            {}", &FLANGE[..close], gripper_board(b), &FLANGE[close..])
        }
        _ => FLANGE.to_owned(),
    };
    xml.replace_range(hand..end, &flange);
    xml = drop_blocks(&xml, "tendon");
    xml = drop_blocks(&xml, "equality");
    xml = drop_blocks(&xml, "keyframe");
    xml = drop_lines(&xml, &["<general", r#"name="hand""#]);
    xml = drop_lines(&xml, &["<mesh", r#"name="hand_"#]);
    xml = drop_lines(&xml, &["<mesh", r#"name="finger_"#]);
    let option = xml.find("<option").ok_or_else(|| unexpected("no <option>"))?;
    let option_end = xml[option..].find("/>").map(|e| option + e + 2).ok_or_else(|| unexpected("unclosed <option>"))?;
    xml.replace_range(option_end..option_end, VISUAL);
    xml.replace_range(option..option_end, OPTION);
    let asset_tag = xml.find("<asset>").ok_or_else(|| unexpected("no <asset>"))?;
    let mut gripper_model =
        format!("\n    <model name=\"robotiq_2f85\" file=\"{}\"/>{SCENE_ASSETS}", gripper.display());
    if let Some(b) = board {
        if !b.texture.exists() {
            return Err(RigError::Missing {
                path: b.texture.clone(),
                error: std::io::Error::new(std::io::ErrorKind::NotFound, "the board's print is not there"),
            });
        }
        gripper_model.push_str(&format!(
            r#"
    <texture name="board_tex" type="2d" file="{}" vflip="true"/>
    <material name="board_mat" texture="board_tex" specular="0" shininess="0"/>"#,
            b.texture.display()
        ));
    }
    xml.insert_str(asset_tag + "<asset>".len(), &gripper_model);
    let wb_end = xml.rfind("</worldbody>").ok_or_else(|| unexpected("no </worldbody>"))?;
    let mut bodies = scene_bodies(scene);
    if let Some(b @ Board { mount: BoardMount::Table { centre, yaw_deg }, .. }) = board {
        bodies.push_str(&table_board(b, *centre, *yaw_deg));
        bodies.push_str("\n  ");
    }
    xml.insert_str(wb_end, &bodies);
    let end = xml.rfind("</mujoco>").ok_or_else(|| unexpected("no </mujoco>"))?;
    xml.insert_str(end, &tail(scene));
    Ok(xml)
}

fn v3(v: [f64; 3]) -> String {
    format!("{} {} {}", v[0], v[1], v[2])
}

/// The object's orientation: `yaw_deg` about z, as a MuJoCo quaternion (w x y z).
pub fn yaw_quat(yaw_deg: f64) -> [f64; 4] {
    let h = yaw_deg.to_radians() / 2.0;
    [h.cos(), 0.0, 0.0, h.sin()]
}

/// Table, object, bin and the four external cameras, placed as the scene says.
fn scene_bodies(scene: &SceneValues) -> String {
    let [cx, cy, _] = TABLE_CENTRE;
    let [hx, hy] = TABLE_HALF;
    let half = OBJECT_SIZE / 2.0;
    let [bx, by] = BIN_HALF;
    let wall = 0.005;
    let wall_h = 0.04;
    let mut out = format!(
        r#"
    <light name="sun" pos="0.5 0 2.0" dir="0 0 -1" directional="true" castshadow="false" diffuse="0.6 0.6 0.6"/>
    <geom name="floor" type="plane" size="3 3 0.1" pos="0 0 -0.75" material="floor_mat"/>
    <geom name="table" type="box" pos="{cx} {cy} -0.025" size="{hx} {hy} 0.025" material="table_mat"/>
    <body name="cam_target" pos="{look}"/>
    <body name="object" pos="{obj}">
      <freejoint name="object_joint"/>
      <geom name="object" type="box" size="{half} {half} {half}" mass="0.05" material="object_mat" friction="1.5 0.01 0.001"/>
    </body>
    <body name="bin" pos="{bin}">
      <geom name="bin_floor" type="box" pos="0 0 {wall}" size="{bx} {by} {wall}" material="bin_mat"/>
      <geom name="bin_wall_px" type="box" pos="{bxw} 0 {wall_h}" size="{wall} {by} {wall_h}" material="bin_mat"/>
      <geom name="bin_wall_nx" type="box" pos="-{bxw} 0 {wall_h}" size="{wall} {by} {wall_h}" material="bin_mat"/>
      <geom name="bin_wall_py" type="box" pos="0 {byw} {wall_h}" size="{bx} {wall} {wall_h}" material="bin_mat"/>
      <geom name="bin_wall_ny" type="box" pos="0 -{byw} {wall_h}" size="{bx} {wall} {wall_h}" material="bin_mat"/>
    </body>"#,
        look = v3(TABLE_CENTRE),
        obj = v3(scene.object_position),
        bin = v3(scene.receptacle_position),
        bxw = bx - wall,
        byw = by - wall,
    );
    if let Some(drawer) = &scene.drawer {
        out.push_str(&cabinet(drawer));
    }
    for (id, pose) in &scene.cameras {
        out.push_str(&format!(
            r#"
    <camera name="{id}" pos="{}" mode="targetbody" target="cam_target" fovy="{}"/>"#,
            v3(pose.position),
            pose.fovy_deg
        ));
    }
    out.push_str("\n  ");
    out
}

/// The drawer's slide joint and the handle's grip site.
pub const DRAWER_JOINT: &str = "drawer_slide";
pub const HANDLE_SITE: &str = "drawer_handle";

/// A cabinet (open-fronted shell) with a drawer on a slide joint along -x (toward the robot;
/// qpos = opening in m) and a bar handle along x on the drawer's front, gripped from above.
/// The shell and the drawer do not collide with each other (contype bits 2 and 4; everything
/// else collides with both), the joint's range keeps the drawer in its shell.
fn cabinet(d: &DrawerValues) -> String {
    let [hx, hy] = CABINET_HALF;
    let h = CABINET_HEIGHT;
    let t = 0.01; // wall
    let (ht, hh) = (t / 2.0, h / 2.0);
    // The drawer: front panel flush with the shell's front, a tray behind it.
    let depth = 2.0 * hx - 2.0 * t - 0.01;
    let tray_x = -hx + t + depth / 2.0;
    let (iy, wall_h) = (hy - t - 0.003, 0.035);
    let handle_x = -hx - HANDLE_LENGTH / 2.0;
    format!(
        r#"
    <body name="cabinet" pos="{pos}">
      <geom name="cabinet_bottom" type="box" pos="0 0 {ht}" size="{hx} {hy} {ht}" material="cabinet_mat" contype="2" conaffinity="1"/>
      <geom name="cabinet_top" type="box" pos="0 0 {top}" size="{hx} {hy} {ht}" material="cabinet_mat" contype="2" conaffinity="1"/>
      <geom name="cabinet_side_py" type="box" pos="0 {side} {hh}" size="{hx} {ht} {hh}" material="cabinet_mat" contype="2" conaffinity="1"/>
      <geom name="cabinet_side_ny" type="box" pos="0 -{side} {hh}" size="{hx} {ht} {hh}" material="cabinet_mat" contype="2" conaffinity="1"/>
      <geom name="cabinet_back" type="box" pos="{back} 0 {hh}" size="{ht} {hy} {hh}" material="cabinet_mat" contype="2" conaffinity="1"/>
      <body name="drawer" pos="0 0 0">
        <joint name="{DRAWER_JOINT}" type="slide" axis="-1 0 0" range="0 {DRAWER_TRAVEL}" damping="4" frictionloss="0.5" armature="0.05"/>
        <geom name="drawer_front" type="box" pos="{front} 0 {hh}" size="{ht} {iy} {front_h}" material="drawer_mat" mass="0.3" contype="4" conaffinity="1"/>
        <geom name="drawer_floor" type="box" pos="{tray_x} 0 {floor}" size="{tray_hx} {iy} 0.003" material="drawer_mat" mass="0.2" contype="4" conaffinity="1"/>
        <geom name="drawer_back" type="box" pos="{tray_back} 0 {wall_z}" size="0.003 {iy} {wall_hh}" material="drawer_mat" mass="0.05" contype="4" conaffinity="1"/>
        <geom name="drawer_side_py" type="box" pos="{tray_x} {iy_w} {wall_z}" size="{tray_hx} 0.003 {wall_hh}" material="drawer_mat" mass="0.05" contype="4" conaffinity="1"/>
        <geom name="drawer_side_ny" type="box" pos="{tray_x} -{iy_w} {wall_z}" size="{tray_hx} 0.003 {wall_hh}" material="drawer_mat" mass="0.05" contype="4" conaffinity="1"/>
        <geom name="drawer_handle" type="box" pos="{handle_x} 0 {hh}" size="{hl} 0.008 0.01" material="handle_mat" mass="0.05" friction="1.5 0.01 0.001" contype="4" conaffinity="1"/>
        <site name="{HANDLE_SITE}" pos="{handle_x} 0 {hh}" size="0.005"/>
      </body>
    </body>"#,
        pos = v3(d.position),
        top = h - ht,
        side = hy - ht,
        back = hx - ht,
        front = -hx + ht,
        front_h = hh - t - 0.003,
        floor = t + 0.006,
        tray_hx = depth / 2.0,
        tray_back = -hx + t + depth - 0.003,
        wall_z = t + 0.006 + wall_h / 2.0,
        wall_hh = wall_h / 2.0,
        iy_w = iy - 0.003,
        hl = HANDLE_LENGTH / 2.0,
    )
}

const OPTION: &str = r#"<option timestep="0.002" integrator="implicitfast" cone="elliptic" impratio="10"/>"#;

// Shadows off (mujoco-rs's renderer cannot switch them off, and they cost ~27 ms a frame).
const VISUAL: &str = r#"
  <visual>
    <global offwidth="1280" offheight="720"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.4 0.4 0.4" diffuse="0.6 0.6 0.6" specular="0.1 0.1 0.1"/>
  </visual>"#;

// +90 deg about link7's z: at q7 = 0 the fingers open along the base's y axis.
const FLANGE: &str = r#"<body name="flange" pos="0 0 0.107" quat="0.7071068 0 0 0.7071068">
              <site name="attachment_site"/>
              <attach model="robotiq_2f85" body="base_mount" prefix="gripper_"/>
              <camera name="wrist" pos="0 0.09 0.03" xyaxes="-1 0 0 0 0.966 0.259" fovy="80"/>
            </body>"#;

const SCENE_ASSETS: &str = r#"
    <texture name="floor_tex" type="2d" builtin="checker" rgb1="0.3 0.3 0.35" rgb2="0.4 0.4 0.45" width="256" height="256"/>
    <material name="floor_mat" texture="floor_tex" texrepeat="8 8"/>
    <texture name="table_tex" type="2d" builtin="flat" rgb1="0.5 0.4 0.3" width="64" height="64"/>
    <material name="table_mat" texture="table_tex" texuniform="true" texrepeat="6 6"/>
    <material name="bin_mat" rgba="0.2 0.35 0.7 1"/>
    <material name="cabinet_mat" rgba="0.55 0.42 0.3 1"/>
    <material name="drawer_mat" rgba="0.7 0.58 0.42 1"/>
    <material name="handle_mat" rgba="0.3 0.3 0.32 1" specular="0.6"/>
    <texture name="object_tex" type="cube" builtin="flat" rgb1="0.8 0.2 0.2" width="64" height="64"/>
    <material name="object_mat" texture="object_tex"/>"#;

/// Texture names [`crate::Sim`] fills from the scene.
pub const OBJECT_TEXTURE: &str = "object_tex";
pub const TABLE_TEXTURE: &str = "table_tex";

// DROID's reset pose as keyframe `reset`: qpos = 7 arm + 8 gripper + object free joint (7)
// (+ the drawer's opening).
fn tail(scene: &SceneValues) -> String {
    let arm = RESET_POSE.map(|q| q.to_string()).join(" ");
    let [w, x, y, z] = yaw_quat(scene.object_yaw_deg);
    let drawer = scene.drawer.as_ref().map_or(String::new(), |d| format!("  {}", d.opening_m));
    format!(
        r#"
  <sensor>
    <framepos name="pinch_pos" objtype="site" objname="gripper_pinch"/>
    <framepos name="object_pos" objtype="body" objname="object"/>
  </sensor>
  <keyframe>
    <key name="reset" qpos="{arm}  0 0 0 0 0 0 0 0  {obj} {w} {x} {y} {z}{drawer}" ctrl="{arm}  0"/>
  </keyframe>
"#,
        obj = v3(scene.object_position),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn body_span_matches_nested_bodies() {
        let xml = r#"<a><body name="hand"><body name="x"></body><body name="y"/></body><b/></a>"#;
        let start = xml.find("<body").unwrap();
        let end = body_span(xml, start).unwrap();
        assert_eq!(&xml[end..], "<b/></a>");
    }

    #[test]
    fn missing_assets_name_the_file_and_the_fix() {
        let scene = crate::scene::SceneSpec::default_pick_place().sample(0).unwrap();
        let err = compose(Path::new("/nonexistent"), &scene).unwrap_err();
        let text = err.to_string();
        assert!(text.contains("/nonexistent/fr3/fr3.xml") && text.contains("scripts/setup.sh"), "{text}");
    }
}
