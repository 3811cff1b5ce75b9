//! The one clock of a node: wall time on hardware, sim time (`/clock`) against the sim bridge,
//! or a manually advanced mock in tests. Always integer nanoseconds ([`Nanos`]).

use labrig_msgs::Nanos;
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, Ordering};

#[derive(Debug, Clone)]
pub enum Clock {
    /// System time since the Unix epoch.
    Wall,
    /// Time set from outside: by `/clock` messages (sim) or by a test (mock).
    Manual(Arc<AtomicI64>),
}

impl Clock {
    /// A clock that only moves when [`Clock::set`] or [`Clock::advance`] is called.
    pub fn manual(start: Nanos) -> Clock {
        Clock::Manual(Arc::new(AtomicI64::new(start.0)))
    }

    pub fn now(&self) -> Nanos {
        match self {
            Clock::Wall => {
                let d = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
                Nanos(d.as_nanos() as i64)
            }
            Clock::Manual(t) => Nanos(t.load(Ordering::Acquire)),
        }
    }

    /// Sets a manual clock; time never runs backwards (older values are ignored, as ROS does
    /// for out-of-order `/clock`). Returns false on a wall clock.
    pub fn set(&self, t: Nanos) -> bool {
        match self {
            Clock::Wall => false,
            Clock::Manual(cur) => {
                cur.fetch_max(t.0, Ordering::AcqRel);
                true
            }
        }
    }

    /// Sets a manual clock to `t` even if that is earlier (the time source restarted).
    /// Returns false on a wall clock.
    pub fn reset(&self, t: Nanos) -> bool {
        match self {
            Clock::Wall => false,
            Clock::Manual(cur) => {
                cur.store(t.0, Ordering::Release);
                true
            }
        }
    }

    /// Advances a manual clock by `d`. Returns false on a wall clock.
    pub fn advance(&self, d: Nanos) -> bool {
        match self {
            Clock::Wall => false,
            Clock::Manual(cur) => {
                cur.fetch_add(d.0, Ordering::AcqRel);
                true
            }
        }
    }

    pub fn is_wall(&self) -> bool {
        matches!(self, Clock::Wall)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_clock_moves_only_forward_and_only_when_told() {
        let c = Clock::manual(Nanos(100));
        assert_eq!(c.now(), Nanos(100));
        c.advance(Nanos(50));
        assert_eq!(c.now(), Nanos(150));
        c.set(Nanos(120));
        assert_eq!(c.now(), Nanos(150), "time must not run backwards");
        c.set(Nanos(1_000));
        assert_eq!(c.now(), Nanos(1_000));
    }

    #[test]
    fn wall_clock_is_near_unix_time() {
        let now = Clock::Wall.now();
        assert!(now.0 > 1_700_000_000_000_000_000);
        assert!(!Clock::Wall.set(Nanos(0)));
    }
}
