//! Time on the wire (`builtin_interfaces`) and the integer-nanosecond [`Nanos`] used inside labrig.

use serde::{Deserialize, Serialize};

/// A point in time (or a duration) as signed integer nanoseconds since the clock's epoch:
/// the Unix epoch for wall time, the simulation start for sim time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
pub struct Nanos(pub i64);

impl Nanos {
    pub const ZERO: Nanos = Nanos(0);

    pub const fn from_secs_f64(s: f64) -> Nanos {
        Nanos((s * 1e9) as i64)
    }
    /// Seconds (a config value) to the nearest nanosecond.
    pub fn from_secs_rounded(s: f64) -> Nanos {
        Nanos((s * 1e9).round() as i64)
    }
    pub const fn from_millis(ms: i64) -> Nanos {
        Nanos(ms * 1_000_000)
    }
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }
    pub fn saturating_sub(self, other: Nanos) -> Nanos {
        Nanos(self.0.saturating_sub(other.0))
    }
}

impl std::ops::Add for Nanos {
    type Output = Nanos;
    fn add(self, rhs: Nanos) -> Nanos {
        Nanos(self.0 + rhs.0)
    }
}

impl std::ops::Sub for Nanos {
    type Output = Nanos;
    fn sub(self, rhs: Nanos) -> Nanos {
        Nanos(self.0 - rhs.0)
    }
}

impl std::fmt::Display for Nanos {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.9}s", self.as_secs_f64())
    }
}

pub mod builtin_interfaces {
    //! `builtin_interfaces`: ROS time mirrored exactly (`sec: i32, nanosec: u32`).
    use super::Nanos;
    use crate::ros_message;
    use serde::{Deserialize, Serialize};

    /// builtin_interfaces/msg/Time.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
    pub struct Time {
        pub sec: i32,
        pub nanosec: u32,
    }
    ros_message!(Time, "builtin_interfaces/msg/Time", [], "int32 sec\nuint32 nanosec\n");

    /// builtin_interfaces/msg/Duration.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default, Serialize, Deserialize)]
    pub struct Duration {
        pub sec: i32,
        pub nanosec: u32,
    }
    ros_message!(Duration, "builtin_interfaces/msg/Duration", [], "int32 sec\nuint32 nanosec\n");

    impl From<Nanos> for Time {
        /// Floors to whole seconds so that `nanosec` is always in `0..1e9`, as ROS does.
        /// Times beyond the `i32` seconds range saturate.
        fn from(t: Nanos) -> Time {
            let sec = t.0.div_euclid(1_000_000_000);
            let nanosec = t.0.rem_euclid(1_000_000_000) as u32;
            Time { sec: sec.clamp(i32::MIN as i64, i32::MAX as i64) as i32, nanosec }
        }
    }

    impl From<Time> for Nanos {
        fn from(t: Time) -> Nanos {
            Nanos(t.sec as i64 * 1_000_000_000 + t.nanosec as i64)
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn time_round_trips_through_nanos_including_negative() {
            for ns in [0i64, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789, -1, -1_500_000_000] {
                let t = Time::from(Nanos(ns));
                assert!(t.nanosec < 1_000_000_000);
                assert_eq!(Nanos::from(t), Nanos(ns), "{t:?}");
            }
        }
    }
}
