//! The dimensions of variation derived from an episode.

use crate::row::CameraRow;
use labrig_msgs::dv::{CameraBin, spherical};
use std::collections::BTreeMap;

/// The default vocabulary (`dataset/vocabulary.toml`).
pub const DEFAULT_VOCABULARY: &str = include_str!("../vocabulary.toml");

/// The object position's parameters: the gripper signal (0 open .. 1 closed; the commanded
/// gripper where an episode has it, as a closed gripper stalls part-way on the object) is averaged over
/// `window` steps from each step on; the first step whose average passes `threshold` starts
/// the grasp, and the object is where the end effector is at the first step from there whose
/// own signal passes it. A close shorter than about half the window is never a grasp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GraspParams {
    pub window: usize,
    pub threshold: f64,
}

impl Default for GraspParams {
    fn default() -> GraspParams {
        GraspParams { window: 15, threshold: 0.5 }
    }
}

/// The step of the first real grasp, if the gripper ever closes.
pub fn first_grasp(gripper: &[f64], p: GraspParams) -> Option<usize> {
    let w = p.window.max(1);
    // Running sums: sum[k] = gripper[0..k].
    let mut sum = vec![0.0; gripper.len() + 1];
    for (i, g) in gripper.iter().enumerate() {
        sum[i + 1] = sum[i] + g;
    }
    let start = (0..gripper.len()).find(|&t| {
        let end = (t + w).min(gripper.len());
        // Near the end the window holds fewer steps: it is still averaged over `w`, so a close
        // at the very end must last as long as anywhere else.
        (sum[end] - sum[t]) / w as f64 > p.threshold
    })?;
    (start..gripper.len()).find(|&t| gripper[t] > p.threshold)
}

/// The words of an instruction, lower case, letters only.
fn words(text: &str) -> impl Iterator<Item = String> + '_ {
    text.split(|c: char| !c.is_alphanumeric()).filter(|w| !w.is_empty()).map(str::to_lowercase)
}

/// What the instruction's words say (the first word found in each table decides).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Vocabulary {
    pub primitives: BTreeMap<String, String>,
    pub objects: BTreeMap<String, String>,
    pub colours: BTreeMap<String, String>,
}

impl Vocabulary {
    pub fn default_words() -> Vocabulary {
        toml::from_str(DEFAULT_VOCABULARY).expect("the default vocabulary parses")
    }

    pub fn parse(text: &str) -> Result<Vocabulary, toml::de::Error> {
        toml::from_str(text)
    }

    fn first(table: &BTreeMap<String, String>, text: &str) -> Option<String> {
        words(text).find_map(|w| table.get(&w).cloned())
    }

    pub fn primitive(&self, text: &str) -> Option<String> {
        Vocabulary::first(&self.primitives, text)
    }

    pub fn object(&self, text: &str) -> Option<String> {
        Vocabulary::first(&self.objects, text)
    }

    pub fn colour(&self, text: &str) -> Option<String> {
        Vocabulary::first(&self.colours, text)
    }
}

/// A colour name for an HSV colour (each 0..1, hue in turns): grey shades by value where the
/// saturation is low, else the hue's name.
pub fn colour_of_hsv([h, s, v]: [f64; 3]) -> &'static str {
    if s < 0.2 {
        return if v < 0.25 {
            "black"
        } else if v > 0.8 {
            "white"
        } else {
            "grey"
        };
    }
    if v < 0.15 {
        return "black";
    }
    let deg = h.rem_euclid(1.0) * 360.0;
    match deg {
        d if !(15.0..345.0).contains(&d) => "red",
        d if d < 45.0 => "orange",
        d if d < 70.0 => "yellow",
        d if d < 165.0 => "green",
        d if d < 260.0 => "blue",
        d if d < 290.0 => "purple",
        _ => "pink",
    }
}

/// A camera's row from its DROID extrinsics (xyz + extrinsic xyz Euler), around `centre`.
pub fn camera_row(serial: Option<String>, extrinsics: Option<[f64; 6]>, centre: [f64; 3]) -> CameraRow {
    let Some(e) = extrinsics else { return CameraRow { serial, ..CameraRow::default() } };
    let position = [e[0], e[1], e[2]];
    let (r, polar, azimuth) = spherical(position, centre);
    CameraRow {
        serial,
        position: Some(position),
        euler: Some([e[3], e[4], e[5]]),
        radius_m: Some(r),
        polar_deg: Some(polar),
        azimuth_deg: Some(azimuth),
        bin: Some(CameraBin::of(polar, azimuth).map(|b| b.name()).unwrap_or("none").to_owned()),
        extrinsics_from: Some("metadata".to_owned()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_accidental_three_step_close_before_the_grasp_is_ignored() {
        let mut g = vec![0.0; 80];
        for v in &mut g[20..23] {
            *v = 1.0; // accidental
        }
        for v in &mut g[40..70] {
            *v = 0.9;
        }
        assert_eq!(first_grasp(&g, GraspParams::default()), Some(40));
        // With no window the accidental close counts.
        assert_eq!(first_grasp(&g, GraspParams { window: 1, threshold: 0.5 }), Some(20));
    }

    #[test]
    fn the_window_decides_how_long_a_close_must_last() {
        // 7 of 15 closed: average 0.47, not a grasp; 8 of 15: 0.53, a grasp.
        let mut g = vec![0.0; 40];
        g[10..17].fill(1.0);
        assert_eq!(first_grasp(&g, GraspParams::default()), None);
        g[17] = 1.0;
        assert_eq!(first_grasp(&g, GraspParams::default()), Some(10));
        assert_eq!(first_grasp(&[], GraspParams::default()), None);
        assert_eq!(first_grasp(&[0.0; 30], GraspParams::default()), None);
    }

    #[test]
    fn the_vocabulary_reads_the_first_word_of_each_kind() {
        let v = Vocabulary::default_words();
        let text = "Put the red cube in the blue bowl";
        assert_eq!(v.primitive(text).as_deref(), Some("place"));
        assert_eq!(v.object(text).as_deref(), Some("cube"));
        assert_eq!(v.colour(text).as_deref(), Some("red"));
        assert_eq!(v.primitive("pull the drawer open").as_deref(), Some("pull"));
        assert_eq!(v.object("wave at the camera"), None);
        assert_eq!(v.object("pick up the Cubes").as_deref(), Some("cube"));
    }

    #[test]
    fn hsv_colours_have_names() {
        assert_eq!(colour_of_hsv([0.0, 0.8, 0.8]), "red");
        assert_eq!(colour_of_hsv([0.33, 0.8, 0.8]), "green");
        assert_eq!(colour_of_hsv([0.6, 0.8, 0.8]), "blue");
        assert_eq!(colour_of_hsv([0.6, 0.05, 0.9]), "white");
    }
}
