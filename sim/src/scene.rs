//! Scenes from the paper's dimensions of variation (DVs): a TOML spec plus a seed fully
//! determines one scene; [`SceneSpec::sample`] returns the sampled values, which recordings store.
//!
//! - Camera pose (camPose): each external camera looks at the table centre from a position in
//!   spherical coordinates (physics convention: polar angle from +z, azimuth from +x, the robot
//!   base frame) around it, drawn from one of five named bins of 15 deg polar x 30 deg azimuth.
//! - Object and receptacle placement (objSpat, recepSpat): uniform over a union of axis-aligned
//!   boxes `[x0, y0, x1, y1]` on the table (robot base frame, metres), each box weighted by area.
//! - Textures (objTex, tableTex): a base colour drawn from HSV ranges; the object's texture is
//!   fractal value noise around it, the table's is the base colour jittered per texel in HSV.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// The table top's centre (robot base frame, m): cameras look here, boxes must lie on the table.
pub const TABLE_CENTRE: [f64; 3] = [0.5, 0.0, 0.0];
/// The table top's half extents in x and y (m).
pub const TABLE_HALF: [f64; 2] = [0.4, 0.6];
/// Cube edge (m) of the graspable object.
pub const OBJECT_SIZE: f64 = 0.05;
/// Receptacle (bin) outer half extents in x and y (m).
pub const BIN_HALF: [f64; 2] = [0.1, 0.08];
/// Side of the square textures generated for the object and the table (texels).
pub const TEXTURE_SIZE: usize = 64;
/// The drawer cabinet's outer half extents in x and y (m) and its height; its front (with the
/// drawer and its handle) faces the robot (-x).
pub const CABINET_HALF: [f64; 2] = [0.12, 0.15];
pub const CABINET_HEIGHT: f64 = 0.14;
/// How far the drawer slides out (m), and how far its handle stands off the drawer's front.
pub const DRAWER_TRAVEL: f64 = 0.14;
pub const HANDLE_LENGTH: f64 = 0.07;
/// drawer_open succeeds at this opening or more, drawer_close at [`DRAWER_CLOSED_M`] or less (m).
pub const DRAWER_OPEN_M: f64 = 0.10;
pub const DRAWER_CLOSED_M: f64 = 0.02;

/// The paper's five camera bins (shared with the dataset tools).
pub use labrig_msgs::dv::CameraBin;

/// A closed range `[min, max]`.
pub type Range = [f64; 2];

/// HSV ranges, each component in 0..1 (hue in turns).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HsvRange {
    pub h: Range,
    pub s: Range,
    pub v: Range,
}

/// Where one external camera may be.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Bins to draw from (uniformly). Either `bins`, or `polar_deg` + `azimuth_deg`.
    #[serde(default)]
    pub bins: Vec<CameraBin>,
    pub polar_deg: Option<Range>,
    pub azimuth_deg: Option<Range>,
    /// Distance from the table centre (m).
    pub radius: Range,
    /// Vertical field of view (deg).
    #[serde(default = "default_fovy")]
    pub fovy_deg: f64,
}

fn default_fovy() -> f64 {
    60.0
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    /// Union of boxes `[x0, y0, x1, y1]` (m, robot base frame) the object's centre is drawn from.
    pub boxes: Vec<[f64; 4]>,
    /// Yaw about z (deg).
    #[serde(default = "default_yaw")]
    pub yaw_deg: Range,
    pub hsv: HsvRange,
    /// Octaves of fractal noise in the object's texture (1 = plain value noise).
    #[serde(default = "default_octaves")]
    pub noise_octaves: u32,
}

fn default_yaw() -> Range {
    [-45.0, 45.0]
}

fn default_octaves() -> u32 {
    4
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReceptacleSpec {
    pub boxes: Vec<[f64; 4]>,
}

/// A cabinet with one drawer on the table, its front (drawer and handle) toward the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DrawerSpec {
    /// Union of boxes `[x0, y0, x1, y1]` the cabinet's centre is drawn from.
    pub boxes: Vec<[f64; 4]>,
    /// How far the drawer is open at the start (m, 0 = closed .. [`DRAWER_TRAVEL`]).
    #[serde(default)]
    pub opening_m: Range,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TableSpec {
    pub hsv: HsvRange,
    /// Per-texel jitter added to the base colour, per component (0..1).
    #[serde(default = "default_jitter")]
    pub jitter: [f64; 3],
}

fn default_jitter() -> [f64; 3] {
    [0.01, 0.05, 0.06]
}

/// Which task a scene is set up for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Task {
    /// Pick the object up and put it in the receptacle.
    PickPlace,
    /// Pull the drawer open (to at least [`DRAWER_OPEN_M`]).
    DrawerOpen,
    /// Push the drawer shut (to at most [`DRAWER_CLOSED_M`]).
    DrawerClose,
}

impl Task {
    pub fn name(self) -> &'static str {
        match self {
            Task::PickPlace => "pick_place",
            Task::DrawerOpen => "drawer_open",
            Task::DrawerClose => "drawer_close",
        }
    }
}

/// A scene spec file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    pub name: String,
    pub task: Task,
    /// The language instruction recorded with episodes of this scene.
    pub instruction: String,
    pub table: TableSpec,
    pub object: ObjectSpec,
    pub receptacle: ReceptacleSpec,
    /// The cabinet and its drawer (required by the drawer tasks, a distractor otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drawer: Option<DrawerSpec>,
    /// The external cameras (`ext1`, `ext2`, `rs1`, `rs2`); the wrist camera rides the gripper.
    pub cameras: BTreeMap<String, CameraSpec>,
}

/// The external cameras a spec must place.
pub const EXTERNAL_CAMERAS: [&str; 4] = ["ext1", "ext2", "rs1", "rs2"];

/// A spec that cannot give a scene; `field` is the TOML path of the culprit.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("cannot read scene spec {path}: {error}")]
    Read { path: std::path::PathBuf, error: std::io::Error },
    #[error("invalid scene spec {origin}: {message}")]
    Parse { origin: String, message: String },
    #[error("invalid scene spec {origin}: `{field}` {reason}")]
    Invalid { origin: String, field: String, reason: String },
    #[error("scene `{name}` seed {seed}: {reason}")]
    Sample { name: String, seed: u64, reason: String },
}

/// One camera's sampled pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    /// The bin drawn (absent when the spec gave explicit ranges).
    pub bin: Option<CameraBin>,
    pub polar_deg: f64,
    pub azimuth_deg: f64,
    pub radius: f64,
    /// Position in the robot base frame (m).
    pub position: [f64; 3],
    /// Point looked at (the table centre).
    pub look_at: [f64; 3],
    pub fovy_deg: f64,
}

/// Everything a spec + seed determined: stored with each simulated episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneValues {
    pub spec_name: String,
    pub seed: u64,
    pub task: Task,
    pub instruction: String,
    pub cameras: BTreeMap<String, CameraPose>,
    /// Object centre (m) and yaw (deg).
    pub object_position: [f64; 3],
    pub object_yaw_deg: f64,
    /// Base colour of the object's texture (HSV, 0..1) and its RGB.
    pub object_hsv: [f64; 3],
    pub object_rgb: [f64; 3],
    pub receptacle_position: [f64; 3],
    pub table_hsv: [f64; 3],
    pub table_rgb: [f64; 3],
    /// The cabinet, when the spec has one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drawer: Option<DrawerValues>,
}

/// The sampled cabinet: its centre on the table top and the drawer's opening at the start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DrawerValues {
    pub position: [f64; 3],
    pub opening_m: f64,
}

impl DrawerValues {
    /// The handle's grip point (robot base frame) when the drawer is open by `opening` (m).
    pub fn handle_position(&self, opening: f64) -> [f64; 3] {
        let [x, y, _] = self.position;
        [x - CABINET_HALF[0] - HANDLE_LENGTH / 2.0 - opening, y, CABINET_HEIGHT / 2.0]
    }

    /// The area the cabinet, its open drawer and a gripper on the handle take on the table,
    /// `[x0, y0, x1, y1]`: other things are kept out of it.
    pub fn footprint(&self) -> [f64; 4] {
        let [x, y, _] = self.position;
        let reach = CABINET_HALF[0] + DRAWER_TRAVEL + HANDLE_LENGTH + 0.03;
        [x - reach, y - CABINET_HALF[1], x + CABINET_HALF[0], y + CABINET_HALF[1]]
    }
}

/// Whether two rectangles `[x0, y0, x1, y1]` are at least `gap` apart.
fn apart(a: [f64; 4], b: [f64; 4], gap: f64) -> bool {
    a[2] + gap <= b[0] || b[2] + gap <= a[0] || a[3] + gap <= b[1] || b[3] + gap <= a[1]
}

fn around(centre: [f64; 2], half: [f64; 2]) -> [f64; 4] {
    [centre[0] - half[0], centre[1] - half[1], centre[0] + half[0], centre[1] + half[1]]
}

fn invalid(origin: &str, field: impl Into<String>, reason: impl Into<String>) -> SceneError {
    SceneError::Invalid { origin: origin.to_owned(), field: field.into(), reason: reason.into() }
}

fn check_range(origin: &str, field: &str, r: Range, lo: f64, hi: f64) -> Result<(), SceneError> {
    if !r[0].is_finite() || !r[1].is_finite() {
        return Err(invalid(origin, field, format!("{r:?} is not finite")));
    }
    if r[0] > r[1] {
        return Err(invalid(origin, field, format!("min {} > max {}: the range is empty", r[0], r[1])));
    }
    if r[0] < lo || r[1] > hi {
        return Err(invalid(origin, field, format!("{r:?} leaves the possible range [{lo}, {hi}]")));
    }
    Ok(())
}

fn check_hsv(origin: &str, field: &str, hsv: &HsvRange) -> Result<(), SceneError> {
    check_range(origin, &format!("{field}.h"), hsv.h, 0.0, 1.0)?;
    check_range(origin, &format!("{field}.s"), hsv.s, 0.0, 1.0)?;
    check_range(origin, &format!("{field}.v"), hsv.v, 0.0, 1.0)
}

/// Boxes must be non-empty, ordered, and keep a footprint of half-size `margin` on the table.
fn check_boxes(origin: &str, field: &str, boxes: &[[f64; 4]], margin: [f64; 2]) -> Result<(), SceneError> {
    if boxes.is_empty() {
        return Err(invalid(origin, field, "is an empty union of boxes: nothing to sample from"));
    }
    let (x_lo, x_hi) = (TABLE_CENTRE[0] - TABLE_HALF[0] + margin[0], TABLE_CENTRE[0] + TABLE_HALF[0] - margin[0]);
    let (y_lo, y_hi) = (TABLE_CENTRE[1] - TABLE_HALF[1] + margin[1], TABLE_CENTRE[1] + TABLE_HALF[1] - margin[1]);
    for (i, b) in boxes.iter().enumerate() {
        let f = format!("{field}[{i}]");
        if b.iter().any(|v| !v.is_finite()) {
            return Err(invalid(origin, f, format!("{b:?} is not finite")));
        }
        if b[0] >= b[2] || b[1] >= b[3] {
            return Err(invalid(origin, f, format!("{b:?} is empty: need x0 < x1 and y0 < y1")));
        }
        if b[0] < x_lo || b[2] > x_hi || b[1] < y_lo || b[3] > y_hi {
            return Err(invalid(
                origin,
                f,
                format!("{b:?} is not on the table (x in [{x_lo:.3}, {x_hi:.3}], y in [{y_lo:.3}, {y_hi:.3}])"),
            ));
        }
    }
    Ok(())
}

impl SceneSpec {
    pub fn load(path: &Path) -> Result<SceneSpec, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|error| SceneError::Read { path: path.to_owned(), error })?;
        SceneSpec::parse(&text, &path.display().to_string())
    }

    /// Parses and validates a spec; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<SceneSpec, SceneError> {
        let spec: SceneSpec = toml::from_str(text).map_err(|e| SceneError::Parse {
            origin: origin.to_owned(),
            message: e.to_string().trim_end().to_owned(),
        })?;
        spec.validate(origin)?;
        Ok(spec)
    }

    /// The scene labrig uses when none is given (`sim/scenes/pick_place.toml`).
    pub fn default_pick_place() -> SceneSpec {
        SceneSpec::builtin("pick_place").expect("pick_place is built in")
    }

    /// A built-in scene by name (see [`BUILTIN_SCENES`]).
    pub fn builtin(name: &str) -> Option<SceneSpec> {
        let (_, text) = BUILTIN_SCENES.iter().find(|(n, _)| *n == name)?;
        Some(SceneSpec::parse(text, &format!("built-in {name}")).expect("the built-in specs are valid"))
    }

    pub fn validate(&self, origin: &str) -> Result<(), SceneError> {
        check_hsv(origin, "table.hsv", &self.table.hsv)?;
        for (i, j) in self.table.jitter.iter().enumerate() {
            if !(0.0..=0.5).contains(j) {
                return Err(invalid(origin, format!("table.jitter[{i}]"), format!("{j} is outside 0..0.5")));
            }
        }
        check_hsv(origin, "object.hsv", &self.object.hsv)?;
        check_range(origin, "object.yaw_deg", self.object.yaw_deg, -180.0, 180.0)?;
        if !(1..=8).contains(&self.object.noise_octaves) {
            return Err(invalid(
                origin,
                "object.noise_octaves",
                format!("{} is outside 1..8", self.object.noise_octaves),
            ));
        }
        let half = OBJECT_SIZE / 2.0;
        check_boxes(origin, "object.boxes", &self.object.boxes, [half, half])?;
        check_boxes(origin, "receptacle.boxes", &self.receptacle.boxes, BIN_HALF)?;
        match (&self.drawer, self.task) {
            (None, Task::DrawerOpen | Task::DrawerClose) => {
                return Err(invalid(
                    origin,
                    "drawer",
                    format!("is missing: task {} needs a [drawer] section", self.task.name()),
                ));
            }
            (None, Task::PickPlace) => {}
            (Some(d), task) => {
                check_boxes(origin, "drawer.boxes", &d.boxes, CABINET_HALF)?;
                check_range(origin, "drawer.opening_m", d.opening_m, 0.0, DRAWER_TRAVEL)?;
                // The open drawer and its handle must stay over the table.
                let table_x0 = TABLE_CENTRE[0] - TABLE_HALF[0];
                for (i, b) in d.boxes.iter().enumerate() {
                    let front = b[0] - CABINET_HALF[0] - DRAWER_TRAVEL - HANDLE_LENGTH;
                    if front < table_x0 {
                        return Err(invalid(
                            origin,
                            format!("drawer.boxes[{i}]"),
                            format!("puts the open drawer's handle off the table (x = {front:.3} < {table_x0:.3})"),
                        ));
                    }
                }
                if task == Task::DrawerOpen && d.opening_m[1] >= DRAWER_OPEN_M {
                    return Err(invalid(
                        origin,
                        "drawer.opening_m",
                        format!("reaches {} m: drawer_open would start solved (>= {DRAWER_OPEN_M} m)", d.opening_m[1]),
                    ));
                }
                if task == Task::DrawerClose && d.opening_m[0] <= DRAWER_CLOSED_M {
                    return Err(invalid(
                        origin,
                        "drawer.opening_m",
                        format!(
                            "starts at {} m: drawer_close would start solved (<= {DRAWER_CLOSED_M} m)",
                            d.opening_m[0]
                        ),
                    ));
                }
            }
        }
        for id in self.cameras.keys() {
            if !EXTERNAL_CAMERAS.contains(&id.as_str()) {
                return Err(invalid(
                    origin,
                    format!("cameras.{id}"),
                    format!("is not an external camera of the rig (expected one of {EXTERNAL_CAMERAS:?})"),
                ));
            }
        }
        for id in EXTERNAL_CAMERAS {
            let Some(cam) = self.cameras.get(id) else {
                return Err(invalid(origin, format!("cameras.{id}"), "is missing: every external camera needs a pose"));
            };
            let f = |k: &str| format!("cameras.{id}.{k}");
            match (cam.bins.is_empty(), cam.polar_deg, cam.azimuth_deg) {
                (false, None, None) => {}
                (true, Some(p), Some(a)) => {
                    // Above the table top and no further round than a full turn.
                    check_range(origin, &f("polar_deg"), p, 0.0, 85.0)?;
                    check_range(origin, &f("azimuth_deg"), a, -180.0, 180.0)?;
                }
                (true, _, _) => {
                    return Err(invalid(origin, f("bins"), "is empty and polar_deg + azimuth_deg are not both given"));
                }
                (false, _, _) => {
                    return Err(invalid(origin, f("bins"), "is given together with polar_deg/azimuth_deg: use one"));
                }
            }
            check_range(origin, &f("radius"), cam.radius, 0.3, 3.0)?;
            check_range(origin, &f("fovy_deg"), [cam.fovy_deg, cam.fovy_deg], 10.0, 120.0)?;
        }
        Ok(())
    }

    /// Draws the scene for `seed`. Deterministic: same spec and seed, same values. The spec is
    /// checked first: one that did not come through [`SceneSpec::parse`] (a recording's, read
    /// back from JSON) is refused naming its field instead of panicking on a missing camera or
    /// an empty range.
    pub fn sample(&self, seed: u64) -> Result<SceneValues, SceneError> {
        self.validate(&format!("`{}`", self.name))?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut uniform = |r: Range| if r[0] == r[1] { r[0] } else { rng.random_range(r[0]..=r[1]) };
        let mut cameras = BTreeMap::new();
        for id in EXTERNAL_CAMERAS {
            let cam = &self.cameras[id];
            let (bin, polar_r, azimuth_r) = if cam.bins.is_empty() {
                (None, cam.polar_deg.expect("validated"), cam.azimuth_deg.expect("validated"))
            } else {
                let pick = uniform([0.0, cam.bins.len() as f64]).floor() as usize;
                let bin = cam.bins[pick.min(cam.bins.len() - 1)];
                let (p, a) = bin.ranges_deg();
                (Some(bin), p, a)
            };
            let polar_deg = uniform(polar_r);
            let azimuth_deg = uniform(azimuth_r);
            let radius = uniform(cam.radius);
            let (p, a) = (polar_deg.to_radians(), azimuth_deg.to_radians());
            let position = [
                TABLE_CENTRE[0] + radius * p.sin() * a.cos(),
                TABLE_CENTRE[1] + radius * p.sin() * a.sin(),
                TABLE_CENTRE[2] + radius * p.cos(),
            ];
            cameras.insert(
                id.to_owned(),
                CameraPose {
                    bin,
                    polar_deg,
                    azimuth_deg,
                    radius,
                    position,
                    look_at: TABLE_CENTRE,
                    fovy_deg: cam.fovy_deg,
                },
            );
        }
        let table_hsv = [uniform(self.table.hsv.h), uniform(self.table.hsv.s), uniform(self.table.hsv.v)];
        let object_hsv = [uniform(self.object.hsv.h), uniform(self.object.hsv.s), uniform(self.object.hsv.v)];
        let object_yaw_deg = uniform(self.object.yaw_deg);
        // Object, receptacle (and cabinet) must not overlap: redraw (bounded) until apart.
        for _ in 0..200 {
            let [ox, oy] = sample_union(&self.object.boxes, &mut uniform);
            let [rx, ry] = sample_union(&self.receptacle.boxes, &mut uniform);
            let gap = OBJECT_SIZE;
            let object = around([ox, oy], [OBJECT_SIZE / 2.0; 2]);
            let bin = around([rx, ry], BIN_HALF);
            let drawer = self.drawer.as_ref().map(|d| {
                let [dx, dy] = sample_union(&d.boxes, &mut uniform);
                DrawerValues { position: [dx, dy, 0.0], opening_m: uniform(d.opening_m) }
            });
            let clear =
                drawer.as_ref().is_none_or(|d| apart(d.footprint(), object, gap) && apart(d.footprint(), bin, gap));
            if apart(object, bin, gap - OBJECT_SIZE / 2.0) && clear {
                return Ok(SceneValues {
                    spec_name: self.name.clone(),
                    seed,
                    task: self.task,
                    instruction: self.instruction.clone(),
                    cameras,
                    object_position: [ox, oy, OBJECT_SIZE / 2.0],
                    object_yaw_deg,
                    object_rgb: hsv_to_rgb(object_hsv),
                    object_hsv,
                    receptacle_position: [rx, ry, 0.0],
                    table_rgb: hsv_to_rgb(table_hsv),
                    table_hsv,
                    drawer,
                });
            }
        }
        Err(SceneError::Sample {
            name: self.name.clone(),
            seed,
            reason: "the object, receptacle and drawer boxes leave no room to place them apart (200 draws)".into(),
        })
    }
}

/// A point uniform over a union of boxes (each box weighted by its area).
fn sample_union(boxes: &[[f64; 4]], uniform: &mut impl FnMut(Range) -> f64) -> [f64; 2] {
    let areas: Vec<f64> = boxes.iter().map(|b| (b[2] - b[0]) * (b[3] - b[1])).collect();
    let mut pick = uniform([0.0, areas.iter().sum()]);
    let mut chosen = boxes[boxes.len() - 1];
    for (b, a) in boxes.iter().zip(&areas) {
        if pick < *a {
            chosen = *b;
            break;
        }
        pick -= a;
    }
    [uniform([chosen[0], chosen[2]]), uniform([chosen[1], chosen[3]])]
}

/// HSV (0..1 each, hue in turns) to RGB (0..1).
pub fn hsv_to_rgb([h, s, v]: [f64; 3]) -> [f64; 3] {
    let h6 = (h.rem_euclid(1.0)) * 6.0;
    let c = v * s;
    let x = c * (1.0 - ((h6 % 2.0) - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// Lattice value noise in 0..1 at (x, y), from a hash of the lattice corners and `seed`.
fn value_noise(x: f64, y: f64, period: u32, seed: u64) -> f64 {
    let lattice = |i: i64, j: i64| -> f64 {
        let (i, j) = (i.rem_euclid(period as i64) as u64, j.rem_euclid(period as i64) as u64);
        let mut h = seed ^ i.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ j.wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        h ^= h >> 33;
        h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
        h ^= h >> 33;
        (h >> 11) as f64 / (1u64 << 53) as f64
    };
    let (xi, yi) = (x.floor() as i64, y.floor() as i64);
    let (fx, fy) = (x - x.floor(), y - y.floor());
    let smooth = |t: f64| t * t * (3.0 - 2.0 * t);
    let (sx, sy) = (smooth(fx), smooth(fy));
    let top = lattice(xi, yi) * (1.0 - sx) + lattice(xi + 1, yi) * sx;
    let bottom = lattice(xi, yi + 1) * (1.0 - sx) + lattice(xi + 1, yi + 1) * sx;
    top * (1.0 - sy) + bottom * sy
}

/// RGB texels (`TEXTURE_SIZE`^2 x 3) of the object: fractal (fBm) value noise that tiles,
/// modulating the base colour's value and, slightly, its hue.
pub fn object_texture(values: &SceneValues, octaves: u32) -> Vec<u8> {
    let n = TEXTURE_SIZE;
    let mut out = Vec::with_capacity(n * n * 3);
    for y in 0..n {
        for x in 0..n {
            let (mut sum, mut norm, mut amp, mut period) = (0.0, 0.0, 1.0, 4u32);
            for o in 0..octaves {
                let scale = period as f64 / n as f64;
                sum +=
                    amp * value_noise(x as f64 * scale, y as f64 * scale, period, values.seed.wrapping_add(o as u64));
                norm += amp;
                amp *= 0.5;
                period *= 2;
            }
            let noise = sum / norm - 0.5; // -0.5..0.5
            let [h, s, v] = values.object_hsv;
            let rgb = hsv_to_rgb([h + 0.04 * noise, s, (v + 0.5 * noise).clamp(0.0, 1.0)]);
            out.extend(rgb.map(|c| (c * 255.0).round() as u8));
        }
    }
    out
}

/// RGB texels of the table: the base colour jittered per texel in HSV (seeded).
pub fn table_texture(values: &SceneValues, jitter: [f64; 3]) -> Vec<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(values.seed ^ 0x7AB1E);
    let n = TEXTURE_SIZE;
    let mut out = Vec::with_capacity(n * n * 3);
    for _ in 0..n * n {
        let [h, s, v] = values.table_hsv;
        let mut j = |k: usize| if jitter[k] > 0.0 { rng.random_range(-jitter[k]..=jitter[k]) } else { 0.0 };
        let hsv = [h + j(0), (s + j(1)).clamp(0.0, 1.0), (v + j(2)).clamp(0.0, 1.0)];
        out.extend(hsv_to_rgb(hsv).map(|c| (c * 255.0).round() as u8));
    }
    out
}

/// The built-in pick-and-place spec (also `sim/scenes/pick_place.toml`).
pub const DEFAULT_SPEC: &str = include_str!("../scenes/pick_place.toml");

/// The scenes built into the binary, by name (`--scene drawer_open`); the files are in
/// `sim/scenes/`.
pub const BUILTIN_SCENES: [(&str, &str); 3] = [
    ("pick_place", DEFAULT_SPEC),
    ("drawer_open", include_str!("../scenes/drawer_open.toml")),
    ("drawer_close", include_str!("../scenes/drawer_close.toml")),
];

#[cfg(test)]
mod tests {
    use super::*;

    fn spec_with(edit: impl FnOnce(&mut toml::Table)) -> Result<SceneSpec, SceneError> {
        let mut table: toml::Table = toml::from_str(DEFAULT_SPEC).unwrap();
        edit(&mut table);
        SceneSpec::parse(&toml::to_string(&table).unwrap(), "test")
    }

    #[test]
    fn the_default_spec_samples_deterministically() {
        let spec = SceneSpec::default_pick_place();
        let a = spec.sample(7).unwrap();
        assert_eq!(a, spec.sample(7).unwrap());
        assert_ne!(a, spec.sample(8).unwrap());
        assert_eq!(a.cameras.len(), 4);
    }

    #[test]
    fn samples_stay_inside_their_bins_and_boxes() {
        let spec = SceneSpec::default_pick_place();
        for seed in 0..300 {
            let v = spec.sample(seed).unwrap();
            for (id, pose) in &v.cameras {
                let (p, a) = pose.bin.expect("default spec uses bins").ranges_deg();
                assert!((p[0]..=p[1]).contains(&pose.polar_deg), "{id} {pose:?}");
                assert!((a[0]..=a[1]).contains(&pose.azimuth_deg), "{id} {pose:?}");
                let d: f64 = (0..3).map(|k| (pose.position[k] - TABLE_CENTRE[k]).powi(2)).sum::<f64>().sqrt();
                assert!((d - pose.radius).abs() < 1e-9);
                assert!(pose.position[2] > 0.2, "camera below the table: {pose:?}");
            }
            let [x, y, _] = v.object_position;
            assert!(spec.object.boxes.iter().any(|b| x >= b[0] && x <= b[2] && y >= b[1] && y <= b[3]));
            let [rx, ry, _] = v.receptacle_position;
            assert!(spec.receptacle.boxes.iter().any(|b| rx >= b[0] && rx <= b[2] && ry >= b[1] && ry <= b[3]));
        }
    }

    #[test]
    fn union_sampling_weights_boxes_by_area() {
        let boxes = [[0.0, 0.0, 1.0, 1.0], [2.0, 0.0, 5.0, 1.0]];
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut uniform = |r: Range| rng.random_range(r[0]..=r[1]);
        let n = 20_000;
        let in_big = (0..n).filter(|_| sample_union(&boxes, &mut uniform)[0] >= 2.0).count();
        let share = in_big as f64 / n as f64;
        assert!((share - 0.75).abs() < 0.02, "share in the 3x-larger box: {share}");
    }

    #[test]
    fn unknown_keys_are_rejected_by_name() {
        let err = spec_with(|t| {
            t["object"].as_table_mut().unwrap().insert("colour".into(), toml::Value::Integer(1));
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("unknown field `colour`"), "{err}");
    }

    #[test]
    fn an_empty_box_union_names_the_field() {
        let err = spec_with(|t| {
            t["receptacle"].as_table_mut().unwrap().insert("boxes".into(), toml::Value::Array(vec![]));
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`receptacle.boxes`") && err.contains("empty union"), "{err}");
    }

    #[test]
    fn impossible_camera_ranges_name_the_field() {
        let err = spec_with(|t| {
            let cam = t["cameras"]["rs1"].as_table_mut().unwrap();
            cam.insert("radius".into(), toml::Value::try_from([1.2, 0.8]).unwrap());
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`cameras.rs1.radius`") && err.contains("min 1.2 > max 0.8"), "{err}");
        let err = spec_with(|t| {
            let cam = t["cameras"]["ext2"].as_table_mut().unwrap();
            cam.remove("bins");
            cam.insert("polar_deg".into(), toml::Value::try_from([80.0, 100.0]).unwrap());
            cam.insert("azimuth_deg".into(), toml::Value::try_from([0.0, 10.0]).unwrap());
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`cameras.ext2.polar_deg`"), "{err}");
    }

    #[test]
    fn a_box_off_the_table_names_its_index() {
        let err = spec_with(|t| {
            let boxes = toml::Value::try_from(vec![[0.3, -0.1, 0.4, 0.1], [0.3, 0.5, 0.4, 0.9]]).unwrap();
            t["object"].as_table_mut().unwrap().insert("boxes".into(), boxes);
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`object.boxes[1]`") && err.contains("not on the table"), "{err}");
    }

    #[test]
    fn hsv_conversion_hits_the_primaries() {
        assert_eq!(hsv_to_rgb([0.0, 1.0, 1.0]), [1.0, 0.0, 0.0]);
        let g = hsv_to_rgb([1.0 / 3.0, 1.0, 1.0]);
        assert!((g[1] - 1.0).abs() < 1e-12 && g[0].abs() < 1e-12 && g[2].abs() < 1e-12);
        assert_eq!(hsv_to_rgb([0.5, 0.0, 0.25]), [0.25, 0.25, 0.25]);
    }

    #[test]
    fn textures_are_seeded_and_vary() {
        let spec = SceneSpec::default_pick_place();
        let v = spec.sample(3).unwrap();
        let t = object_texture(&v, 4);
        assert_eq!(t.len(), TEXTURE_SIZE * TEXTURE_SIZE * 3);
        assert_eq!(t, object_texture(&v, 4));
        let distinct: std::collections::BTreeSet<_> = t.chunks(3).collect();
        assert!(distinct.len() > 50, "fractal noise gives many shades, got {}", distinct.len());
        assert_eq!(table_texture(&v, [0.01, 0.05, 0.06]), table_texture(&v, [0.01, 0.05, 0.06]));
    }

    fn drawer_spec_with(name: &str, edit: impl FnOnce(&mut toml::Table)) -> Result<SceneSpec, SceneError> {
        let text = BUILTIN_SCENES.iter().find(|(n, _)| *n == name).unwrap().1;
        let mut table: toml::Table = toml::from_str(text).unwrap();
        edit(&mut table);
        SceneSpec::parse(&toml::to_string(&table).unwrap(), "test")
    }

    #[test]
    fn the_built_in_scenes_parse_and_keep_the_cabinet_clear() {
        for (name, _) in BUILTIN_SCENES {
            let spec = SceneSpec::builtin(name).unwrap();
            assert_eq!(spec.task.name(), name);
            for seed in 0..200 {
                let v = spec.sample(seed).unwrap();
                let Some(d) = &v.drawer else {
                    assert_eq!(spec.task, Task::PickPlace);
                    continue;
                };
                let range = spec.drawer.as_ref().unwrap().opening_m;
                assert!((range[0]..=range[1]).contains(&d.opening_m));
                let [ox, oy, _] = v.object_position;
                let [rx, ry, _] = v.receptacle_position;
                assert!(apart(d.footprint(), around([ox, oy], [OBJECT_SIZE / 2.0; 2]), 0.0), "{name} {seed}");
                assert!(apart(d.footprint(), around([rx, ry], BIN_HALF), 0.0), "{name} {seed}");
                // The handle is in front of the cabinet, at mid height, in the footprint.
                let h = d.handle_position(d.opening_m);
                let f = d.footprint();
                assert!(h[0] > f[0] && h[0] < d.position[0] - CABINET_HALF[0] && (h[1] - d.position[1]).abs() < 1e-12);
            }
        }
        assert!(SceneSpec::builtin("no_such_scene").is_none());
    }

    #[test]
    fn a_drawer_task_without_a_drawer_names_the_section() {
        let err = drawer_spec_with("drawer_open", |t| {
            t.remove("drawer");
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`drawer`") && err.contains("drawer_open needs a [drawer] section"), "{err}");
    }

    #[test]
    fn a_drawer_task_that_would_start_solved_is_refused() {
        let err = drawer_spec_with("drawer_open", |t| {
            let d = t["drawer"].as_table_mut().unwrap();
            d.insert("opening_m".into(), toml::Value::try_from([0.05, 0.12]).unwrap());
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`drawer.opening_m`") && err.contains("start solved"), "{err}");
        let err = drawer_spec_with("drawer_close", |t| {
            let d = t["drawer"].as_table_mut().unwrap();
            d.insert("opening_m".into(), toml::Value::try_from([0.0, 0.1]).unwrap());
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`drawer.opening_m`") && err.contains("start solved"), "{err}");
        let err = drawer_spec_with("drawer_close", |t| {
            let d = t["drawer"].as_table_mut().unwrap();
            d.insert("opening_m".into(), toml::Value::try_from([0.05, 0.3]).unwrap());
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`drawer.opening_m`") && err.contains("leaves the possible range"), "{err}");
    }

    #[test]
    fn a_cabinet_whose_open_drawer_leaves_the_table_is_refused() {
        let err = drawer_spec_with("drawer_open", |t| {
            let boxes = toml::Value::try_from(vec![[0.30, -0.1, 0.40, 0.1]]).unwrap();
            t["drawer"].as_table_mut().unwrap().insert("boxes".into(), boxes);
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("`drawer.boxes[0]`") && err.contains("off the table"), "{err}");
    }
}
