//! The paper's camera-pose dimension of variation, shared by the sim (which samples camera
//! poses from it) and the dataset tools (which bin recorded extrinsics by it): a camera's
//! position in spherical coordinates around the table centre (physics convention: polar angle
//! from +z, azimuth from +x toward +y), and the five bins, each 15 deg of polar angle by
//! 30 deg of azimuth. The robot stands at the table's -x edge facing +x; "left" is +y.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CameraBin {
    ShoulderLeft,
    ShoulderRight,
    AgentLeft,
    AgentRight,
    AgentFront,
}

impl CameraBin {
    pub const ALL: [CameraBin; 5] = [
        CameraBin::ShoulderLeft,
        CameraBin::ShoulderRight,
        CameraBin::AgentLeft,
        CameraBin::AgentRight,
        CameraBin::AgentFront,
    ];

    /// (polar, azimuth) ranges in degrees. Shoulder bins are behind and beside the robot, agent
    /// bins across the table.
    pub fn ranges_deg(self) -> ([f64; 2], [f64; 2]) {
        let polar = [45.0, 60.0];
        let azimuth = match self {
            CameraBin::ShoulderLeft => [120.0, 150.0],
            CameraBin::ShoulderRight => [-150.0, -120.0],
            CameraBin::AgentLeft => [30.0, 60.0],
            CameraBin::AgentRight => [-60.0, -30.0],
            CameraBin::AgentFront => [-15.0, 15.0],
        };
        (polar, azimuth)
    }

    pub fn name(self) -> &'static str {
        match self {
            CameraBin::ShoulderLeft => "shoulder-left",
            CameraBin::ShoulderRight => "shoulder-right",
            CameraBin::AgentLeft => "agent-left",
            CameraBin::AgentRight => "agent-right",
            CameraBin::AgentFront => "agent-front",
        }
    }

    /// The bin whose ranges hold (polar, azimuth) in degrees (edges included), if any.
    pub fn of(polar_deg: f64, azimuth_deg: f64) -> Option<CameraBin> {
        CameraBin::ALL.into_iter().find(|b| {
            let ([p0, p1], [a0, a1]) = b.ranges_deg();
            (p0..=p1).contains(&polar_deg) && (a0..=a1).contains(&azimuth_deg)
        })
    }
}

/// A position's spherical coordinates around `centre`: (radius m, polar deg, azimuth deg in
/// (-180, 180]).
pub fn spherical(position: [f64; 3], centre: [f64; 3]) -> (f64, f64, f64) {
    let d = [position[0] - centre[0], position[1] - centre[1], position[2] - centre[2]];
    let r = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if r == 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let polar = (d[2] / r).clamp(-1.0, 1.0).acos().to_degrees();
    let azimuth = d[1].atan2(d[0]).to_degrees();
    (r, polar, azimuth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_bin_holds_its_own_centre_and_no_other() {
        for b in CameraBin::ALL {
            let ([p0, p1], [a0, a1]) = b.ranges_deg();
            assert_eq!(CameraBin::of((p0 + p1) / 2.0, (a0 + a1) / 2.0), Some(b));
        }
        assert_eq!(CameraBin::of(30.0, 0.0), None, "too high");
        assert_eq!(CameraBin::of(50.0, 90.0), None, "beside the table, no bin");
    }

    #[test]
    fn spherical_coordinates_follow_the_physics_convention() {
        let (r, polar, az) = spherical([0.5, 1.0, 1.0], [0.5, 0.0, 0.0]);
        assert!((r - 2f64.sqrt()).abs() < 1e-12 && (polar - 45.0).abs() < 1e-9 && (az - 90.0).abs() < 1e-9);
        let (_, polar, az) = spherical([-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]);
        assert!((polar - 90.0).abs() < 1e-9 && (az - 180.0).abs() < 1e-9);
    }
}
