//! Which camera frame a tick uses: per camera the capture times of the recent frames; at a
//! tick, the newest frame captured at or before the tick (frames from the future are not
//! used: they were not there when the action was chosen), and the skew across cameras.

use labrig_msgs::Nanos;
use labrig_msgs::rig::CameraFrameRef;
use std::collections::{BTreeMap, VecDeque};

/// Frames kept per camera (a second at 30 Hz).
const KEEP: usize = 32;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameTimes {
    pub sequence: u64,
    pub capture_ns: i64,
    pub arrival_ns: i64,
}

/// What a tick saw of the cameras.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TickFrames {
    /// One reference per camera that had a frame (in camera order).
    pub refs: Vec<CameraFrameRef>,
    /// Newest minus oldest capture time among `refs`.
    pub skew_ns: i64,
    /// Cameras with no frame at or before the tick.
    pub missing: Vec<String>,
    /// Cameras whose frame is older than `stale_ns` at the tick.
    pub stale: Vec<String>,
}

/// The recent frames of every camera.
#[derive(Debug, Clone, Default)]
pub struct FrameBook {
    cameras: BTreeMap<String, VecDeque<FrameTimes>>,
    order: Vec<String>,
}

impl FrameBook {
    pub fn new(cameras: &[&str]) -> FrameBook {
        FrameBook {
            cameras: cameras.iter().map(|c| (c.to_string(), VecDeque::with_capacity(KEEP))).collect(),
            order: cameras.iter().map(|c| c.to_string()).collect(),
        }
    }

    /// Notes a frame. Frames out of capture order are kept in order; unknown cameras ignored.
    pub fn push(&mut self, camera: &str, f: FrameTimes) {
        let Some(q) = self.cameras.get_mut(camera) else { return };
        let at = q.iter().rposition(|g| g.capture_ns <= f.capture_ns).map_or(0, |i| i + 1);
        q.insert(at, f);
        while q.len() > KEEP {
            q.pop_front();
        }
    }

    /// Cameras that kept pace with the last tick (their newest frame was captured at or after
    /// `prev_tick_ns`) but have nothing yet for the tick at `tick_ns`: on the sim's clock
    /// their frame of this tick is on its way.
    pub fn keeping_pace(&self, prev_tick: Nanos, tick: Nanos) -> Vec<&str> {
        let (prev_tick_ns, tick_ns) = (prev_tick.0, tick.0);
        self.order
            .iter()
            .filter(|c| self.cameras[*c].back().is_some_and(|f| f.capture_ns >= prev_tick_ns && f.capture_ns < tick_ns))
            .map(String::as_str)
            .collect()
    }

    /// The frames for a tick at `tick_ns`: per camera the newest captured at or before it.
    pub fn at(&self, tick: Nanos, stale: Nanos) -> TickFrames {
        let (tick_ns, stale_ns) = (tick.0, stale.0);
        let mut refs = Vec::new();
        let (mut missing, mut stale) = (Vec::new(), Vec::new());
        for cam in &self.order {
            let q = &self.cameras[cam];
            match q.iter().rev().find(|f| f.capture_ns <= tick_ns) {
                Some(f) => {
                    if tick_ns - f.capture_ns > stale_ns {
                        stale.push(cam.clone());
                    }
                    refs.push(CameraFrameRef {
                        camera_id: cam.clone(),
                        sequence: f.sequence,
                        capture_ns: f.capture_ns,
                        arrival_ns: f.arrival_ns,
                        ..Default::default()
                    });
                }
                None => missing.push(cam.clone()),
            }
        }
        let skew_ns = match (refs.iter().map(|r| r.capture_ns).min(), refs.iter().map(|r| r.capture_ns).max()) {
            (Some(lo), Some(hi)) => hi - lo,
            _ => 0,
        };
        TickFrames { refs, skew_ns, missing, stale }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn f(seq: u64, t: i64) -> FrameTimes {
        FrameTimes { sequence: seq, capture_ns: t, arrival_ns: t + 1_000 }
    }

    #[test]
    fn a_tick_takes_each_cameras_newest_past_frame_and_reports_skew() {
        let mut b = FrameBook::new(&["ext1", "wrist", "rs1"]);
        for k in 0..10 {
            b.push("ext1", f(k, k as i64 * 33_000_000));
            b.push("wrist", f(k, k as i64 * 33_000_000 + 5_000_000));
        }
        // A frame from after the tick is not used.
        let t = b.at(Nanos(100_000_000), Nanos(50_000_000));
        assert_eq!(t.refs.len(), 2);
        assert_eq!((t.refs[0].camera_id.as_str(), t.refs[0].sequence), ("ext1", 3)); // 99 ms
        assert_eq!((t.refs[1].camera_id.as_str(), t.refs[1].sequence), ("wrist", 2)); // 71 ms
        assert_eq!(t.skew_ns, 99_000_000 - 71_000_000);
        assert_eq!(t.missing, vec!["rs1".to_string()]);
        assert!(t.stale.is_empty());
        // Long after the last frames: stale.
        let t = b.at(Nanos(1_000_000_000), Nanos(50_000_000));
        assert_eq!(t.stale, vec!["ext1".to_string(), "wrist".to_string()]);
    }

    #[test]
    fn cameras_that_kept_pace_are_waited_for_slow_ones_not() {
        let mut b = FrameBook::new(&["ext1", "wrist", "rs1"]);
        b.push("ext1", f(0, 50));
        b.push("wrist", f(0, 50));
        b.push("rs1", f(0, 0)); // a slower camera: behind the last tick already
        assert_eq!(b.keeping_pace(Nanos(50), Nanos(100)), vec!["ext1", "wrist"]);
        b.push("ext1", f(1, 100));
        assert_eq!(b.keeping_pace(Nanos(50), Nanos(100)), vec!["wrist"]);
        b.push("wrist", f(1, 100));
        assert!(b.keeping_pace(Nanos(50), Nanos(100)).is_empty());
    }

    #[test]
    fn out_of_order_frames_are_kept_in_capture_order() {
        let mut b = FrameBook::new(&["ext1"]);
        b.push("ext1", f(2, 20));
        b.push("ext1", f(1, 10));
        b.push("ext1", f(3, 30));
        assert_eq!(b.at(Nanos(25), Nanos(100)).refs[0].sequence, 2);
        assert_eq!(b.at(Nanos(15), Nanos(100)).refs[0].sequence, 1);
        for k in 0..100 {
            b.push("ext1", f(10 + k, 100 + k as i64));
        }
        assert!(b.at(Nanos(15), Nanos(100)).refs.is_empty(), "old frames age out");
    }
}
