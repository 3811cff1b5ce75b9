//! The FR3's kinematics from its URDF (franky-sim's `fr3.urdf`, parsed with urdf-rs): forward
//! kinematics to the flange and to the gripper's tool centre point, and the geometric Jacobian.
//!
//! Frames: the robot base (`base`), the flange (`fr3_link8`, 0.107 m past joint 7) and the TCP,
//! a fixed offset from the flange (for the Robotiq 2F-85: 0.1558 m along the flange's z, between
//! the finger pads; see [`TcpOffset::ROBOTIQ_2F85`]).

use nalgebra::{Isometry3, Matrix6, SMatrix, Translation3, Unit, UnitQuaternion, Vector3};
use std::path::Path;

/// Joints of the arm (revolute, in chain order).
pub const DOF: usize = 7;

/// The 6x7 geometric Jacobian: rows vx vy vz wx wy wz (base frame), one column per joint.
pub type Jacobian = SMatrix<f64, 6, DOF>;

/// Joint-space vector of the arm.
pub type Joints = [f64; DOF];

/// The FR3's joint position limits from its datasheet (rad; the same ranges as MuJoCo
/// Menagerie's fr3.xml). franky-sim's fr3.urdf carries wider ones (joint 1 +-2.9007 where the
/// datasheet says +-2.7437); [`Fr3Kinematics::limits`] uses the stricter of the two.
pub const FR3_POSITION_LIMITS: [[f64; 2]; DOF] = [
    [-2.7437, 2.7437],
    [-1.7837, 1.7837],
    [-2.9007, 2.9007],
    [-3.0421, -0.1518],
    [-2.8065, 2.8065],
    [0.5445, 4.5169],
    [-3.0159, 3.0159],
];

#[derive(Debug, thiserror::Error)]
pub enum KinematicsError {
    #[error("cannot read URDF {path}: {error} (run `bash scripts/setup.sh`)")]
    Read { path: std::path::PathBuf, error: std::io::Error },
    #[error("URDF {origin} does not parse: {message}")]
    Parse { origin: String, message: String },
    #[error("URDF {origin}: {message}")]
    Chain { origin: String, message: String },
}

/// One revolute joint of the chain: the fixed transform from the previous joint's frame (all
/// fixed joints in between folded in), its axis in its own frame, and its limits.
#[derive(Debug, Clone)]
pub struct ChainJoint {
    pub name: String,
    pub origin: Isometry3<f64>,
    pub axis: Unit<Vector3<f64>>,
    /// Position limits (rad).
    pub lower: f64,
    pub upper: f64,
    /// Velocity limit (rad/s).
    pub velocity: f64,
}

/// The flange -> TCP transform of the mounted tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TcpOffset {
    /// Translation in the flange frame (m).
    pub xyz: [f64; 3],
    /// Rotation as URDF-style roll, pitch, yaw (rad): R = Rz(yaw) Ry(pitch) Rx(roll).
    pub rpy: [f64; 3],
}

impl TcpOffset {
    /// Robotiq 2F-85 on the FR3 flange: the pinch point between the pads, 7 mm mount + 3.8 mm
    /// coupling + 145 mm to the pads (Menagerie's 2F-85), axes aligned with the flange.
    pub const ROBOTIQ_2F85: TcpOffset = TcpOffset { xyz: [0.0, 0.0, 0.1558], rpy: [0.0, 0.0, 0.0] };

    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z] = self.xyz;
        let [r, p, yaw] = self.rpy;
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, p, yaw))
    }
}

/// The FR3 as a serial chain from its URDF.
#[derive(Debug, Clone)]
pub struct Fr3Kinematics {
    joints: Vec<ChainJoint>,
    /// Last revolute joint's frame -> flange.
    flange: Isometry3<f64>,
    tcp: Isometry3<f64>,
}

fn pose(p: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = p.xyz.0;
    let [r, pi, yaw] = p.rpy.0;
    Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(r, pi, yaw))
}

impl Fr3Kinematics {
    /// The base link and flange link of franky-sim's fr3.urdf.
    pub const BASE_LINK: &'static str = "base";
    pub const FLANGE_LINK: &'static str = "fr3_link8";

    pub fn from_urdf_file(path: &Path, tcp: TcpOffset) -> Result<Fr3Kinematics, KinematicsError> {
        let text =
            std::fs::read_to_string(path).map_err(|error| KinematicsError::Read { path: path.to_owned(), error })?;
        Fr3Kinematics::from_urdf_str(&text, &path.display().to_string(), tcp)
    }

    /// Parses a URDF and extracts the chain from [`Self::BASE_LINK`] to [`Self::FLANGE_LINK`]; it
    /// must hold exactly seven revolute joints (fixed joints are folded into the origins).
    pub fn from_urdf_str(text: &str, origin: &str, tcp: TcpOffset) -> Result<Fr3Kinematics, KinematicsError> {
        let robot = urdf_rs::read_from_string(text)
            .map_err(|e| KinematicsError::Parse { origin: origin.to_owned(), message: e.to_string() })?;
        let chain_err = |message: String| KinematicsError::Chain { origin: origin.to_owned(), message };
        // Walk from the flange up to the base through each link's parent joint.
        let mut path = Vec::new();
        let mut link = Self::FLANGE_LINK.to_owned();
        while link != Self::BASE_LINK {
            let joint = robot
                .joints
                .iter()
                .find(|j| j.child.link == link)
                .ok_or_else(|| chain_err(format!("link `{link}` has no parent joint on the way to `base`")))?;
            if path.len() > robot.joints.len() {
                return Err(chain_err("the joint tree has a cycle".into()));
            }
            path.push(joint);
            link = joint.parent.link.clone();
        }
        path.reverse();
        let mut joints = Vec::new();
        let mut acc = Isometry3::identity();
        for j in path {
            acc *= pose(&j.origin);
            match j.joint_type {
                urdf_rs::JointType::Fixed => {}
                urdf_rs::JointType::Revolute => {
                    let axis = Vector3::from(j.axis.xyz.0);
                    let axis = Unit::try_new(axis, 1e-9)
                        .ok_or_else(|| chain_err(format!("joint `{}` has a zero axis", j.name)))?;
                    if j.limit.lower.partial_cmp(&j.limit.upper) != Some(std::cmp::Ordering::Less)
                        || j.limit.velocity <= 0.0
                    {
                        return Err(chain_err(format!("joint `{}` has no usable limits", j.name)));
                    }
                    joints.push(ChainJoint {
                        name: j.name.clone(),
                        origin: acc,
                        axis,
                        lower: j.limit.lower,
                        upper: j.limit.upper,
                        velocity: j.limit.velocity,
                    });
                    acc = Isometry3::identity();
                }
                ref other => {
                    return Err(chain_err(format!("joint `{}` is {other:?}: only revolute and fixed", j.name)));
                }
            }
        }
        if joints.len() != DOF {
            return Err(chain_err(format!("{} revolute joints from base to flange, the FR3 has {DOF}", joints.len())));
        }
        Ok(Fr3Kinematics { joints, flange: acc, tcp: tcp.isometry() })
    }

    pub fn joints(&self) -> &[ChainJoint] {
        &self.joints
    }

    pub fn joint_names(&self) -> [&str; DOF] {
        std::array::from_fn(|i| self.joints[i].name.as_str())
    }

    /// [lower, upper] per joint (rad): the stricter of the URDF's and the datasheet's.
    pub fn limits(&self) -> [[f64; 2]; DOF] {
        std::array::from_fn(|i| {
            let [lo, hi] = FR3_POSITION_LIMITS[i];
            [self.joints[i].lower.max(lo), self.joints[i].upper.min(hi)]
        })
    }

    /// [lower, upper] per joint as the URDF gives them (rad).
    pub fn urdf_limits(&self) -> [[f64; 2]; DOF] {
        std::array::from_fn(|i| [self.joints[i].lower, self.joints[i].upper])
    }

    /// Velocity limit per joint (rad/s).
    pub fn velocity_limits(&self) -> Joints {
        std::array::from_fn(|i| self.joints[i].velocity)
    }

    pub fn tcp_offset(&self) -> &Isometry3<f64> {
        &self.tcp
    }

    /// Each joint's frame (after its rotation) in the base frame, and the flange's.
    fn frames(&self, q: &Joints) -> ([Isometry3<f64>; DOF], Isometry3<f64>) {
        let mut t = Isometry3::identity();
        let frames = std::array::from_fn(|i| {
            let j = &self.joints[i];
            t = t * j.origin * UnitQuaternion::from_axis_angle(&j.axis, q[i]);
            t
        });
        (frames, t * self.flange)
    }

    /// The flange's pose in the base frame.
    pub fn flange_pose(&self, q: &Joints) -> Isometry3<f64> {
        self.frames(q).1
    }

    /// The TCP's pose in the base frame.
    pub fn tcp_pose(&self, q: &Joints) -> Isometry3<f64> {
        self.flange_pose(q) * self.tcp
    }

    /// The TCP pose and its geometric Jacobian (base frame) at `q`.
    pub fn tcp_pose_and_jacobian(&self, q: &Joints) -> (Isometry3<f64>, Jacobian) {
        let (frames, flange) = self.frames(q);
        let tcp = flange * self.tcp;
        let p = tcp.translation.vector;
        let mut jac = Jacobian::zeros();
        for (i, f) in frames.iter().enumerate() {
            let z = f.rotation * self.joints[i].axis.into_inner();
            let v = z.cross(&(p - f.translation.vector));
            jac.fixed_view_mut::<3, 1>(0, i).copy_from(&v);
            jac.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
        }
        (tcp, jac)
    }

    /// Manipulability sqrt(det(J J^T)) at `q`: near 0 close to a singularity.
    pub fn manipulability(&self, q: &Joints) -> f64 {
        let (_, j) = self.tcp_pose_and_jacobian(q);
        let jjt: Matrix6<f64> = j * j.transpose();
        jjt.determinant().max(0.0).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A two-link planar stand-in for parsing checks (the FR3 itself is tested against MuJoCo).
    fn toy(extra: &str) -> String {
        let mut joints = String::new();
        let mut links = String::from(r#"<link name="base"/>"#);
        let mut parent = "base".to_owned();
        for i in 1..=7 {
            let child = format!("fr3_link{i}");
            links.push_str(&format!(r#"<link name="{child}"/>"#));
            joints.push_str(&format!(
                r#"<joint name="j{i}" type="revolute"><origin xyz="0 0 0.1"/><parent link="{parent}"/><child link="{child}"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="2"/></joint>"#
            ));
            parent = child;
        }
        links.push_str(r#"<link name="fr3_link8"/>"#);
        joints.push_str(r#"<joint name="j8" type="fixed"><origin xyz="0 0 0.1"/><parent link="fr3_link7"/><child link="fr3_link8"/></joint>"#);
        format!(r#"<robot name="toy">{links}{joints}{extra}</robot>"#)
    }

    #[test]
    fn a_straight_chain_reaches_its_length_and_bends_about_y() {
        let k = Fr3Kinematics::from_urdf_str(&toy(""), "toy", TcpOffset { xyz: [0.0; 3], rpy: [0.0; 3] }).unwrap();
        let p = k.tcp_pose(&[0.0; 7]);
        assert!((p.translation.vector - Vector3::new(0.0, 0.0, 0.8)).norm() < 1e-12);
        // Joint 1 at +90 deg about y lays everything after it along +x.
        let p = k.tcp_pose(&[std::f64::consts::FRAC_PI_2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert!((p.translation.vector - Vector3::new(0.7, 0.0, 0.1)).norm() < 1e-12, "{p}");
    }

    #[test]
    fn the_jacobian_matches_finite_differences() {
        let k = Fr3Kinematics::from_urdf_str(&toy(""), "toy", TcpOffset::ROBOTIQ_2F85).unwrap();
        let q = [0.1, -0.3, 0.2, 0.5, -0.4, 0.3, 0.2];
        let (p0, j) = k.tcp_pose_and_jacobian(&q);
        for c in 0..7 {
            let mut q1 = q;
            q1[c] += 1e-7;
            let p1 = k.tcp_pose(&q1);
            let dv = (p1.translation.vector - p0.translation.vector) / 1e-7;
            let dw = (p1.rotation * p0.rotation.inverse()).scaled_axis() / 1e-7;
            for r in 0..3 {
                assert!((j[(r, c)] - dv[r]).abs() < 1e-5, "v col {c}");
                assert!((j[(r + 3, c)] - dw[r]).abs() < 1e-5, "w col {c}");
            }
        }
    }

    #[test]
    fn a_urdf_without_the_flange_or_with_a_wrong_joint_count_is_refused() {
        let no_flange = toy("").replace("fr3_link8", "tool0");
        let err = Fr3Kinematics::from_urdf_str(&no_flange, "toy", TcpOffset::ROBOTIQ_2F85).unwrap_err().to_string();
        assert!(err.contains("`fr3_link8` has no parent joint"), "{err}");
        let six = toy("").replacen(r#"name="j3" type="revolute""#, r#"name="j3" type="fixed""#, 1);
        let err = Fr3Kinematics::from_urdf_str(&six, "toy", TcpOffset::ROBOTIQ_2F85).unwrap_err().to_string();
        assert!(err.contains("6 revolute joints"), "{err}");
        let err = Fr3Kinematics::from_urdf_str("<robot", "toy", TcpOffset::ROBOTIQ_2F85).unwrap_err().to_string();
        assert!(err.contains("does not parse"), "{err}");
    }
}
