//! DROID's conventions as openpi's DROID policies (pi0-FAST-DROID, pi0.5-DROID) use them.
//!
//! - The observation: `observation/exterior_image_1_left` and `observation/wrist_image_left`
//!   (RGB uint8, resized with padding to 224 x 224 as openpi's `image_tools.resize_with_pad`
//!   does), `observation/joint_position` (7), `observation/gripper_position` (1), `prompt`.
//! - The answer: `actions`, N x 8 rows at DROID's 15 Hz from the observation on: 7 joint
//!   velocities and the gripper position (0 open, 1 closed). DROID clips a velocity to
//!   [-1, 1], scales the vector so its largest entry is at most 1 and moves each joint by
//!   `v * 0.2` rad per 1/15 s step; the gripper is binarised at 0.5.
//!
//! [`resample`] turns such a chunk into joint-position targets at the loop's own period, each
//! meant for its own tick: the joint path DROID's steps trace (piecewise linear in time through
//! the step ends) is read where each tick's command must have brought the arm, one period on.

use crate::codec::{self, Array, Value};

pub const EXTERIOR_IMAGE: &str = "observation/exterior_image_1_left";
pub const WRIST_IMAGE: &str = "observation/wrist_image_left";
pub const JOINT_POSITION: &str = "observation/joint_position";
pub const GRIPPER_POSITION: &str = "observation/gripper_position";
pub const PROMPT: &str = "prompt";

/// A DROID action mode or reply that labrig cannot execute, named.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum DroidActionError {
    #[error("action mode {mode:?}: expected \"joint_velocity\" (DROID's) or \"joint_position\"")]
    UnknownMode { mode: String },
    #[error(transparent)]
    Codec(#[from] codec::CodecError),
    #[error("actions of shape {shape:?}: expected (N, {width}) with N >= 1")]
    Shape { shape: Vec<usize>, width: usize },
    #[error("actions: row {row} column {column} is {value}")]
    NotFinite { row: usize, column: usize, value: f64 },
}

/// What a remote policy's action rows mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ActionMode {
    /// 7 joint velocities in [-1, 1] (DROID's scaling: 1.0 = `max_joint_delta_rad` per step).
    JointVelocity,
    /// 7 absolute joint positions (rad), row k the target at the end of step k.
    JointPosition,
}

impl ActionMode {
    pub fn parse(s: &str) -> Result<ActionMode, DroidActionError> {
        match s {
            "joint_velocity" => Ok(ActionMode::JointVelocity),
            "joint_position" => Ok(ActionMode::JointPosition),
            other => Err(DroidActionError::UnknownMode { mode: other.to_owned() }),
        }
    }
}

/// How a chunk's rows are meant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActionConvention {
    pub mode: ActionMode,
    /// The policy's step rate (DROID: 15 Hz).
    pub rate_hz: f64,
    /// `JointVelocity`: radians per step at velocity 1 (DROID: 0.2).
    pub max_joint_delta_rad: f64,
    /// The gripper closes at or above this (DROID's clients binarise at 0.5); `None` passes
    /// the value through (clipped to [0, 1]).
    pub gripper_threshold: Option<f64>,
}

impl Default for ActionConvention {
    fn default() -> Self {
        ActionConvention {
            mode: ActionMode::JointVelocity,
            rate_hz: 15.0,
            max_joint_delta_rad: 0.2,
            gripper_threshold: Some(0.5),
        }
    }
}

/// A chunk in the loop's time: joint targets + gripper, row m meant for the observation's tick
/// + m periods.
pub type Row = [f64; 8];

/// The joint positions at the end of each of the chunk's steps (index 0: `q0`, the start).
pub fn step_ends(chunk: &[Row], q0: &[f64; 7], c: &ActionConvention) -> Vec<[f64; 7]> {
    let mut ends = vec![*q0];
    for a in chunk {
        let last = *ends.last().expect("starts with q0");
        let next = match c.mode {
            ActionMode::JointVelocity => {
                let v: [f64; 7] = std::array::from_fn(|j| a[j].clamp(-1.0, 1.0));
                let peak = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                let scale = if peak > 1.0 { 1.0 / peak } else { 1.0 };
                std::array::from_fn(|j| last[j] + v[j] * scale * c.max_joint_delta_rad)
            }
            ActionMode::JointPosition => std::array::from_fn(|j| a[j]),
        };
        ends.push(next);
    }
    ends
}

/// Resamples a chunk of `rate_hz` rows to the loop's `period_s`: row m (for the tick m periods
/// after the observation) holds the joint path's position at (m + 1) periods and the gripper
/// of the step under way at m periods. As many rows as the chunk's time covers.
pub fn resample(chunk: &[Row], q0: &[f64; 7], c: &ActionConvention, period_s: f64) -> Vec<Row> {
    if chunk.is_empty() {
        return Vec::new();
    }
    let ends = step_ends(chunk, q0, c);
    let step_s = 1.0 / c.rate_hz;
    let span = chunk.len() as f64 * step_s;
    let rows = ((span / period_s) + 1e-9).floor() as usize;
    (0..rows)
        .map(|m| {
            let t = (m + 1) as f64 * period_s;
            let x = (t / step_s).min(chunk.len() as f64);
            let k = (x.floor() as usize).min(chunk.len() - 1);
            let f = x - k as f64;
            let mut row = [0.0; 8];
            for j in 0..7 {
                row[j] = ends[k][j] + f * (ends[k + 1][j] - ends[k][j]);
            }
            let g_step = (((m as f64 * period_s) / step_s + 1e-9).floor() as usize).min(chunk.len() - 1);
            let g = chunk[g_step][7];
            row[7] = match c.gripper_threshold {
                Some(th) => f64::from(u8::from(g >= th)),
                None => g.clamp(0.0, 1.0),
            };
            row
        })
        .collect()
}

/// The `actions` of a reply as N x `width` rows, its shape checked.
pub fn action_rows(reply: &Value, width: usize) -> Result<Vec<Vec<f64>>, DroidActionError> {
    let (shape, values) = codec::numbers(reply, "actions")?;
    if shape.len() != 2 || shape[1] != width || shape[0] == 0 {
        return Err(DroidActionError::Shape { shape, width });
    }
    if let Some(i) = values.iter().position(|x| !x.is_finite()) {
        return Err(DroidActionError::NotFinite { row: i / width, column: i % width, value: values[i] });
    }
    Ok(values.chunks_exact(width).map(<[f64]>::to_vec).collect())
}

/// An RGB image resized to fit `width` x `height` keeping its aspect, bilinear with
/// antialiasing (PIL's `BILINEAR`, as openpi's `image_tools.resize_with_pad`), centred on
/// black. Sizes and offsets truncate as openpi's do.
pub fn resize_with_pad(rgb: &[u8], w: u32, h: u32, width: u32, height: u32) -> Vec<u8> {
    if (w, h) == (width, height) {
        return rgb.to_vec();
    }
    let ratio = (f64::from(w) / f64::from(width)).max(f64::from(h) / f64::from(height));
    let (rw, rh) = (((f64::from(w) / ratio) as u32).max(1), ((f64::from(h) / ratio) as u32).max(1));
    let src = image::RgbImage::from_raw(w, h, rgb.to_vec()).expect("w * h * 3 bytes");
    let resized = image::imageops::resize(&src, rw, rh, image::imageops::FilterType::Triangle);
    let mut out = image::RgbImage::new(width, height);
    let (px, py) = ((width.saturating_sub(rw)) / 2, (height.saturating_sub(rh)) / 2);
    image::imageops::replace(&mut out, &resized, i64::from(px), i64::from(py));
    out.into_raw()
}

/// One DROID observation as openpi's DROID client sends it.
#[derive(Debug, Clone)]
pub struct Observation<'a> {
    /// (pixels, width, height), already 224 x 224 (see [`resize_with_pad`]).
    pub exterior: (&'a [u8], u32, u32),
    pub wrist: (&'a [u8], u32, u32),
    pub joint_position: [f64; 7],
    pub gripper_position: f64,
    pub prompt: &'a str,
}

impl Observation<'_> {
    pub fn to_value(&self) -> Value {
        let img = |(p, w, h): (&[u8], u32, u32)| Array::u8(&[h as usize, w as usize, 3], p.to_vec()).to_value();
        codec::map([
            (EXTERIOR_IMAGE, img(self.exterior)),
            (WRIST_IMAGE, img(self.wrist)),
            (JOINT_POSITION, Array::f64(&[7], &self.joint_position).to_value()),
            (GRIPPER_POSITION, Array::f64(&[1], &[self.gripper_position]).to_value()),
            (PROMPT, Value::from(self.prompt)),
        ])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn droid_velocities_become_joint_targets_at_the_loops_own_ticks() {
        let c = ActionConvention::default();
        // Joint 0 at full speed, joint 1 at half, for 3 steps of 1/15 s (0.2 s); gripper
        // 0.2, 0.7, 0.4.
        let chunk: Vec<Row> = [0.2, 0.7, 0.4].iter().map(|&g| [1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, g]).collect();
        let q0 = [0.1, 0.0, 0.0, -2.0, 0.0, 2.0, 0.8];
        let rows = resample(&chunk, &q0, &c, 0.05);
        // 0.2 s of chunk: 4 ticks of 50 ms.
        assert_eq!(rows.len(), 4);
        for (m, r) in rows.iter().enumerate() {
            let t = (m + 1) as f64 * 0.05;
            // 0.2 rad per 1/15 s = 3 rad/s on joint 0, 1.5 on joint 1.
            assert!((r[0] - (0.1 + 3.0 * t)).abs() < 1e-12, "{m}: {r:?}");
            assert!((r[1] - 1.5 * t).abs() < 1e-12);
            assert_eq!(r[3], -2.0);
        }
        // The gripper of the step under way at each tick (0, 50, 100, 150 ms: steps 0, 0, 1, 2).
        assert_eq!(rows.iter().map(|r| r[7]).collect::<Vec<_>>(), vec![0.0, 0.0, 1.0, 0.0]);
        // Over-range velocities: clipped to 1 (DROID's client), so the vector's peak is 1.
        let fast = resample(&[[3.0, -2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]; 3], &[0.0; 7], &c, 0.05);
        assert!((fast[0][0] - 0.15).abs() < 1e-12 && (fast[0][1] + 0.15).abs() < 1e-12, "{:?}", fast[0]);
        // 8 steps (DROID's open-loop horizon) cover 10 ticks of 20 Hz; 15 steps, 20.
        assert_eq!(resample(&[[0.0; 8]; 8], &q0, &c, 0.05).len(), 10);
        assert_eq!(resample(&[[0.0; 8]; 15], &q0, &c, 0.05).len(), 20);
    }

    #[test]
    fn joint_position_rows_are_targets_at_each_steps_end() {
        let c = ActionConvention { mode: ActionMode::JointPosition, gripper_threshold: None, ..Default::default() };
        let chunk = vec![[0.3; 8], [0.6; 8], [0.9; 8]];
        let rows = resample(&chunk, &[0.0; 7], &c, 0.05);
        // At 50 ms: 0.75 of the way to step 0's end (0.3).
        assert!((rows[0][0] - 0.225).abs() < 1e-12, "{:?}", rows[0]);
        assert!((rows[3][0] - 0.9).abs() < 1e-12);
        assert_eq!(rows[0][7], 0.3);
    }

    #[test]
    fn the_actions_shape_is_checked() {
        let ok = codec::map([("actions", Array::f32(&[2, 8], &[0.5; 16]).to_value())]);
        assert_eq!(action_rows(&ok, 8).unwrap().len(), 2);
        let wide = codec::map([("actions", Array::f32(&[2, 7], &[0.5; 14]).to_value())]);
        assert_eq!(
            action_rows(&wide, 8).unwrap_err().to_string(),
            "actions of shape [2, 7]: expected (N, 8) with N >= 1"
        );
        let nan =
            codec::map([("actions", Array::f32(&[1, 8], &[0.0, f32::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).to_value())]);
        assert_eq!(action_rows(&nan, 8).unwrap_err().to_string(), "actions: row 0 column 1 is NaN");
        assert_eq!(action_rows(&codec::map([("x", Value::Nil)]), 8).unwrap_err().to_string(), "actions: missing");
    }

    #[test]
    fn resize_with_pad_keeps_the_aspect_on_black() {
        // 320 x 180 (16:9) into 224 x 224: 224 x 126, 49 rows of black above.
        let img = vec![200u8; 320 * 180 * 3];
        let out = resize_with_pad(&img, 320, 180, 224, 224);
        assert_eq!(out.len(), 224 * 224 * 3);
        let px = |x: usize, y: usize| out[(y * 224 + x) * 3];
        assert_eq!(px(100, 48), 0);
        assert_eq!(px(100, 49), 200);
        assert_eq!(px(100, 49 + 125), 200);
        assert_eq!(px(100, 49 + 126), 0);
    }
}
