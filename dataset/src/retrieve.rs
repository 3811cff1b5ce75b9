//! Retrieval by alignment, as the paper does it on DROID: the dimensions named in `--align`
//! are applied in the paper's order (object and skill from the instruction, then camera pose,
//! then object texture, then object position), each keeping the demos that pass, with the
//! count after each stage (the funnel).

use crate::row::IndexRow;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The dimensions retrieval can align, in the order they are applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub enum Dim {
    #[serde(rename = "object")]
    Object,
    #[serde(rename = "skill")]
    Skill,
    #[serde(rename = "camPose")]
    CamPose,
    #[serde(rename = "objTex")]
    ObjTex,
    #[serde(rename = "objSpat")]
    ObjSpat,
}

impl Dim {
    pub const ORDER: [Dim; 5] = [Dim::Object, Dim::Skill, Dim::CamPose, Dim::ObjTex, Dim::ObjSpat];

    pub fn name(self) -> &'static str {
        match self {
            Dim::Object => "object",
            Dim::Skill => "skill",
            Dim::CamPose => "camPose",
            Dim::ObjTex => "objTex",
            Dim::ObjSpat => "objSpat",
        }
    }

    pub fn parse(s: &str) -> Result<Dim, UnknownDim> {
        Dim::ORDER
            .into_iter()
            .find(|d| d.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| UnknownDim { name: s.to_owned() })
    }
}

/// A dimension name that is none of [`Dim::ORDER`]'s.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown dimension `{name}` (one of {})", Dim::ORDER.map(Dim::name).join(", "))]
pub struct UnknownDim {
    pub name: String,
}

/// The thresholds, with the paper's values by default.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Thresholds {
    /// camPose: a demo camera within this of a target camera in x and in y, and in z (m).
    pub cam_xy_m: f64,
    pub cam_z_m: f64,
    /// objSpat: the cuboid's size centred on the target's mean object position (m).
    pub obj_box_m: [f64; 3],
}

impl Default for Thresholds {
    fn default() -> Thresholds {
        Thresholds { cam_xy_m: 0.20, cam_z_m: 0.10, obj_box_m: [0.60, 0.60, 0.30] }
    }
}

/// What the demos are aligned to: from target episodes (means, most common words) or a spec.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Target {
    /// The target's external camera positions (base frame, m): one setup (a TOML spec's).
    #[serde(default)]
    pub cameras: Vec<[f64; 3]>,
    /// A target of several episodes: each episode's external camera positions. A demo is
    /// camera-aligned when its cameras match every camera of any one of them (the paper's
    /// target is one setup; a folder of target demos may hold several).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub setups: Vec<Vec<[f64; 3]>>,
    /// The centre of the object box (the target episodes' mean object position).
    pub object_position: Option<[f64; 3]>,
    pub object: Option<String>,
    pub skill: Option<String>,
    pub colour: Option<String>,
}

fn most_common<'a>(values: impl Iterator<Item = Option<&'a str>>) -> Option<String> {
    let mut n: BTreeMap<&str, usize> = BTreeMap::new();
    for v in values.flatten() {
        *n.entry(v).or_default() += 1;
    }
    n.into_iter().max_by_key(|(_, c)| *c).map(|(v, _)| v.to_owned())
}

fn mean(points: impl Iterator<Item = [f64; 3]>) -> Option<[f64; 3]> {
    let (mut s, mut k) = ([0.0; 3], 0usize);
    for p in points {
        for i in 0..3 {
            s[i] += p[i];
        }
        k += 1;
    }
    (k > 0).then(|| s.map(|v| v / k as f64))
}

impl Target {
    /// The target of some episodes: each episode's external cameras as a setup of its own (a
    /// demo aligned with any one is camera-aligned), the mean object position (the centre of
    /// the test distribution), the most common object, primitive and colour.
    pub fn of_episodes(rows: &[IndexRow]) -> Target {
        let mut setups: Vec<Vec<[f64; 3]>> = Vec::new();
        for r in rows {
            let set: Vec<[f64; 3]> =
                crate::row::EXTERNAL_CAMERAS.iter().filter_map(|c| r.camera(c)?.position).collect();
            if !set.is_empty() && !setups.contains(&set) {
                setups.push(set);
            }
        }
        Target {
            cameras: Vec::new(),
            setups,
            object_position: mean(rows.iter().filter_map(|r| r.object_position)),
            object: most_common(rows.iter().map(|r| r.object.as_deref())),
            skill: most_common(rows.iter().map(|r| r.primitive.as_deref())),
            colour: most_common(rows.iter().map(|r| r.colour.as_deref())),
        }
    }

    /// The camera setups a demo may be aligned with: each target episode's, or the spec's one.
    pub fn camera_sets(&self) -> Vec<&[[f64; 3]]> {
        let mut sets: Vec<&[[f64; 3]]> = self.setups.iter().map(Vec::as_slice).filter(|s| !s.is_empty()).collect();
        if !self.cameras.is_empty() {
            sets.push(&self.cameras);
        }
        sets
    }

    /// Whether `row` passes `dim`'s rule (through the same columnar path as [`retrieve`]).
    pub fn passes(&self, dim: Dim, row: &IndexRow, t: &Thresholds) -> bool {
        let (kept, _) = select(&Columns::of(std::slice::from_ref(row)), self, &[dim], t);
        !kept.is_empty()
    }

    /// What the target lacks for `dims`, named.
    pub fn missing(&self, dims: &[Dim]) -> Vec<String> {
        dims.iter()
            .filter_map(|d| {
                let lacks = match d {
                    Dim::Object => self.object.is_none(),
                    Dim::Skill => self.skill.is_none(),
                    Dim::ObjTex => self.colour.is_none(),
                    Dim::CamPose => self.camera_sets().is_empty(),
                    Dim::ObjSpat => self.object_position.is_none(),
                };
                lacks.then(|| {
                    format!(
                        "{}: the target has no {}",
                        d.name(),
                        match d {
                            Dim::Object => "object (no instruction word of the vocabulary)",
                            Dim::Skill => "motion primitive (no instruction word of the vocabulary)",
                            Dim::ObjTex => "object colour",
                            Dim::CamPose => "external camera pose",
                            Dim::ObjSpat => "object position (the gripper never closes)",
                        }
                    )
                })
            })
            .collect()
    }
}

/// A rule and the episodes left after it; a retrieved episode (shared with the manifest's
/// readers, `labrig experiment` among them).
pub use labrig_reports::{Retrieved, Stage};

/// The manifest `labrig dataset retrieve` writes and `labrig train --cotrain` reads.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub manifest_version: u32,
    pub index_version: u32,
    pub align: Vec<Dim>,
    pub thresholds: Thresholds,
    pub target: Target,
    pub funnel: Vec<Stage>,
    pub episodes: Vec<Retrieved>,
}

pub const MANIFEST_VERSION: u32 = 1;

/// The index as retrieval scans it: words as codes of one dictionary, positions as arrays
/// with NaN where unknown (a NaN never passes a threshold), one entry per row.
#[derive(Debug, Clone, Default)]
pub struct Columns {
    dict: BTreeMap<String, u32>,
    object: Vec<u32>,
    primitive: Vec<u32>,
    colour: Vec<u32>,
    /// The external cameras' positions (ext1, ext2, rs1, rs2).
    cameras: Vec<[[f64; 3]; 4]>,
    object_position: Vec<[f64; 3]>,
}

/// The code of a word no row has, and of no word.
const NONE: u32 = u32::MAX;

impl Columns {
    pub fn of(rows: &[IndexRow]) -> Columns {
        let mut c = Columns::default();
        let code = |dict: &mut BTreeMap<String, u32>, w: &Option<String>| match w {
            None => NONE,
            Some(w) => {
                let next = dict.len() as u32;
                *dict.entry(w.clone()).or_insert(next)
            }
        };
        for r in rows {
            c.object.push(code(&mut c.dict, &r.object));
            c.primitive.push(code(&mut c.dict, &r.primitive));
            c.colour.push(code(&mut c.dict, &r.colour));
            let mut cams = [[f64::NAN; 3]; 4];
            for (k, id) in crate::row::EXTERNAL_CAMERAS.iter().enumerate() {
                if let Some(p) = r.camera(id).and_then(|c| c.position) {
                    cams[k] = p;
                }
            }
            c.cameras.push(cams);
            c.object_position.push(r.object_position.unwrap_or([f64::NAN; 3]));
        }
        c
    }

    pub fn len(&self) -> usize {
        self.object.len()
    }

    pub fn is_empty(&self) -> bool {
        self.object.is_empty()
    }

    fn code(&self, w: &Option<String>) -> u32 {
        w.as_ref().and_then(|w| self.dict.get(w).copied()).unwrap_or(NONE)
    }
}

/// The rows (indices) that pass `align` in the paper's order, and the funnel.
pub fn select(c: &Columns, target: &Target, align: &[Dim], t: &Thresholds) -> (Vec<u32>, Vec<Stage>) {
    let dims: Vec<Dim> = Dim::ORDER.into_iter().filter(|d| align.contains(d)).collect();
    let mut kept: Vec<u32> = (0..c.len() as u32).collect();
    let mut funnel = vec![Stage { stage: "all".into(), kept: kept.len() }];
    for d in &dims {
        match d {
            Dim::Object | Dim::Skill | Dim::ObjTex => {
                let (col, want) = match d {
                    Dim::Object => (&c.object, c.code(&target.object)),
                    Dim::Skill => (&c.primitive, c.code(&target.skill)),
                    _ => (&c.colour, c.code(&target.colour)),
                };
                kept.retain(|&i| want != NONE && col[i as usize] == want);
            }
            Dim::CamPose => {
                let sets = target.camera_sets();
                kept.retain(|&i| {
                    let demo = &c.cameras[i as usize];
                    sets.iter().any(|set| {
                        set.iter().all(|tc| {
                            demo.iter().any(|d| {
                                (d[0] - tc[0]).abs() <= t.cam_xy_m
                                    && (d[1] - tc[1]).abs() <= t.cam_xy_m
                                    && (d[2] - tc[2]).abs() <= t.cam_z_m
                            })
                        })
                    })
                })
            }
            Dim::ObjSpat => {
                let centre = target.object_position.unwrap_or([f64::NAN; 3]);
                let half = t.obj_box_m.map(|v| v / 2.0);
                kept.retain(|&i| {
                    let p = &c.object_position[i as usize];
                    (0..3).all(|k| (p[k] - centre[k]).abs() <= half[k])
                });
            }
        }
        funnel.push(Stage { stage: d.name().into(), kept: kept.len() });
    }
    (kept, funnel)
}

/// The manifest of a selection.
pub fn manifest(
    rows: &[IndexRow],
    target: &Target,
    align: &[Dim],
    t: &Thresholds,
    kept: &[u32],
    funnel: Vec<Stage>,
) -> Manifest {
    let dims: Vec<Dim> = Dim::ORDER.into_iter().filter(|d| align.contains(d)).collect();
    let passed: Vec<String> = dims.iter().map(|d| d.name().to_owned()).collect();
    Manifest {
        manifest_version: MANIFEST_VERSION,
        index_version: crate::INDEX_VERSION,
        align: dims,
        thresholds: *t,
        target: target.clone(),
        funnel,
        episodes: kept
            .iter()
            .map(|&i| {
                let r = &rows[i as usize];
                Retrieved {
                    id: r.episode_id.clone(),
                    format: r.source_format.clone(),
                    path: r.source_path.clone(),
                    passed: passed.clone(),
                }
            })
            .collect(),
    }
}

/// Applies `align` (in the paper's order, whatever order it was given in) to `rows`.
pub fn retrieve(rows: &[IndexRow], target: &Target, align: &[Dim], t: &Thresholds) -> Manifest {
    let (kept, funnel) = select(&Columns::of(rows), target, align, t);
    manifest(rows, target, align, t, &kept, funnel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::row::{CAMERAS, CameraRow};

    fn demo(cam: [f64; 3], object: [f64; 3]) -> IndexRow {
        let mut cameras: Vec<CameraRow> = CAMERAS.iter().map(|_| CameraRow::default()).collect();
        cameras[1].position = Some(cam); // ext2
        IndexRow {
            episode_id: format!("{cam:?} {object:?}"),
            cameras,
            object_position: Some(object),
            object: Some("cube".into()),
            primitive: Some("place".into()),
            colour: Some("red".into()),
            ..IndexRow::default()
        }
    }

    fn target() -> Target {
        Target {
            cameras: vec![[0.5, 0.8, 0.6]],
            setups: vec![],
            object_position: Some([0.5, 0.0, 0.05]),
            object: Some("cube".into()),
            skill: Some("place".into()),
            colour: Some("red".into()),
        }
    }

    #[test]
    fn cam_pose_keeps_19_9_cm_and_drops_20_1_cm_on_each_axis() {
        let (t, th) = (target(), Thresholds::default());
        for (d, keep) in [(0.199, true), (0.201, false), (-0.199, true), (-0.201, false)] {
            assert_eq!(t.passes(Dim::CamPose, &demo([0.5 + d, 0.8, 0.6], [0.5, 0.0, 0.05]), &th), keep, "x {d}");
            assert_eq!(t.passes(Dim::CamPose, &demo([0.5, 0.8 + d, 0.6], [0.5, 0.0, 0.05]), &th), keep, "y {d}");
        }
        for (d, keep) in [(0.099, true), (0.101, false)] {
            assert_eq!(t.passes(Dim::CamPose, &demo([0.5, 0.8, 0.6 + d], [0.5, 0.0, 0.05]), &th), keep, "z {d}");
        }
        // A demo with no known camera pose is not aligned.
        let mut none = demo([0.5, 0.8, 0.6], [0.5, 0.0, 0.05]);
        none.cameras[1].position = None;
        assert!(!t.passes(Dim::CamPose, &none, &th));
    }

    #[test]
    fn obj_spat_keeps_the_inside_of_the_60_60_30_cm_cuboid() {
        let (t, th) = (target(), Thresholds::default());
        let cam = [0.5, 0.8, 0.6];
        for (i, half) in [(0usize, 0.30), (1, 0.30), (2, 0.15)] {
            for sign in [1.0, -1.0] {
                let mut inside = [0.5, 0.0, 0.05];
                inside[i] += sign * (half - 0.001);
                let mut outside = [0.5, 0.0, 0.05];
                outside[i] += sign * (half + 0.001);
                assert!(t.passes(Dim::ObjSpat, &demo(cam, inside), &th), "{inside:?}");
                assert!(!t.passes(Dim::ObjSpat, &demo(cam, outside), &th), "{outside:?}");
            }
        }
    }

    #[test]
    fn the_funnel_counts_each_stage_in_the_papers_order() {
        let mut rows = vec![demo([0.5, 0.8, 0.6], [0.5, 0.0, 0.05]); 3];
        rows[1].object = Some("cup".into());
        rows[2].cameras[1].position = Some([0.0, 0.0, 0.0]);
        rows.push(demo([0.5, 0.8, 0.6], [0.9, 0.9, 0.05]));
        let m = retrieve(&rows, &target(), &[Dim::ObjSpat, Dim::Object, Dim::CamPose], &Thresholds::default());
        let funnel: Vec<(&str, usize)> = m.funnel.iter().map(|s| (s.stage.as_str(), s.kept)).collect();
        assert_eq!(funnel, [("all", 4), ("object", 3), ("camPose", 2), ("objSpat", 1)]);
        assert_eq!(m.episodes.len(), 1);
        assert_eq!(m.episodes[0].passed, ["object", "camPose", "objSpat"]);
        assert_eq!(m.align, [Dim::Object, Dim::CamPose, Dim::ObjSpat]);
    }

    /// A folder of target demos set up in two places (the four merged into a mean no
    /// demo matched): each is a setup, so the folder's own episodes are retrieved, and a demo
    /// aligned with either setup is; one with a camera between them is not.
    #[test]
    fn a_target_of_several_episodes_retrieves_each_of_them() {
        let (a, b) = (demo([0.5, 0.8, 0.6], [0.5, 0.0, 0.05]), demo([0.5, -0.8, 0.6], [0.5, 0.1, 0.05]));
        let t = Target::of_episodes(&[a.clone(), b.clone()]);
        assert_eq!(t.setups, [vec![[0.5, 0.8, 0.6]], vec![[0.5, -0.8, 0.6]]]);
        assert!(t.missing(&[Dim::CamPose, Dim::ObjSpat]).is_empty());
        let between = demo([0.5, 0.0, 0.6], [0.5, 0.05, 0.05]);
        let near_b = demo([0.55, -0.7, 0.62], [0.5, 0.05, 0.05]);
        let rows = [a, b, between, near_b];
        let m = retrieve(&rows, &t, &[Dim::Object, Dim::CamPose, Dim::ObjSpat], &Thresholds::default());
        let ids: Vec<&str> = m.episodes.iter().map(|e| e.id.as_str()).collect();
        assert_eq!(ids, [rows[0].episode_id.as_str(), &rows[1].episode_id, &rows[3].episode_id]);
    }

    #[test]
    fn a_target_without_what_a_dimension_needs_is_named() {
        let t = Target { cameras: vec![], ..target() };
        assert_eq!(t.missing(&[Dim::Object, Dim::CamPose]), ["camPose: the target has no external camera pose"]);
    }
}
