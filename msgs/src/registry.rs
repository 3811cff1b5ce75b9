//! Dispatch from a ROS 2 type name (as discovered on the wire or stored in a file) to the
//! Rust type, without this crate knowing what the caller does with it (decode to JSON, fuzz,
//! build an MCAP schema ...).

use crate::RosMessage;

/// Something to do with one message type, chosen at run time by name.
pub trait TypeVisitor {
    type Output;
    fn visit<T: RosMessage>(self) -> Self::Output;
}

macro_rules! registry {
    ($($ty:ty),* $(,)?) => {
        /// Every message type labrig knows, by ROS 2 type name (`pkg/msg/Name`).
        pub fn known_types() -> &'static [&'static str] {
            &[$(<$ty as RosMessage>::TYPE_NAME),*]
        }

        /// Calls `visitor.visit::<T>()` for the type named `type_name`, accepting both
        /// `pkg/msg/Name` and the DDS form `pkg::msg::dds_::Name_`. `None` if labrig does not
        /// know the type.
        pub fn visit_type<V: TypeVisitor>(type_name: &str, visitor: V) -> Option<V::Output> {
            let name = normalise(type_name);
            $(
                if name == <$ty as RosMessage>::TYPE_NAME {
                    return Some(visitor.visit::<$ty>());
                }
            )*
            None
        }
    };
}

registry!(
    crate::builtin_interfaces::Time,
    crate::builtin_interfaces::Duration,
    crate::std_msgs::Header,
    crate::std_msgs::StringMsg,
    crate::sensor_msgs::JointState,
    crate::sensor_msgs::Image,
    crate::sensor_msgs::CompressedImage,
    crate::sensor_msgs::RegionOfInterest,
    crate::sensor_msgs::CameraInfo,
    crate::geometry_msgs::Point,
    crate::geometry_msgs::Vector3,
    crate::geometry_msgs::Quaternion,
    crate::geometry_msgs::Pose,
    crate::geometry_msgs::PoseStamped,
    crate::geometry_msgs::Transform,
    crate::geometry_msgs::TransformStamped,
    crate::geometry_msgs::Twist,
    crate::tf2_msgs::TFMessage,
    crate::rosgraph_msgs::Clock,
    crate::std_srvs::SetBoolRequest,
    crate::std_srvs::SetBoolResponse,
    crate::std_srvs::TriggerRequest,
    crate::std_srvs::TriggerResponse,
    crate::rig::ArmCommand,
    crate::rig::ActionDict,
    crate::rig::RobotState,
    crate::rig::GripperCommand,
    crate::rig::GripperState,
    crate::rig::TeleopState,
    crate::rig::EpisodeEvent,
    crate::rig::ActionChunk,
    crate::rig::PolicyObservation,
    crate::rig::PolicyRequest,
    crate::rig::CameraFrameRef,
    crate::rig::ControlTiming,
    crate::rig::Step,
);

/// `pkg::msg::dds_::Name_` -> `pkg/msg/Name`; `pkg/msg/Name` unchanged.
fn normalise(type_name: &str) -> std::borrow::Cow<'_, str> {
    if let Some((prefix, name)) = type_name.split_once("::dds_::") {
        let name = name.strip_suffix('_').unwrap_or(name);
        std::borrow::Cow::Owned(format!("{}/{}", prefix.replace("::", "/"), name))
    } else {
        std::borrow::Cow::Borrowed(type_name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Name;
    impl TypeVisitor for Name {
        type Output = &'static str;
        fn visit<T: RosMessage>(self) -> &'static str {
            T::TYPE_NAME
        }
    }

    #[test]
    fn every_known_type_resolves_by_ros_and_dds_name() {
        for &name in known_types() {
            assert_eq!(visit_type(name, Name), Some(name));
            assert_eq!(visit_type(&crate::dds_type_name(name), Name), Some(name));
        }
        assert_eq!(visit_type("nope_msgs/msg/Nope", Name), None);
    }
}
