//! The episode state machine: idle -> recording -> (success | failure | discarded) ->
//! resetting -> idle. Events come from buttons (teleop), the CLI or a UI; the machine says
//! what the loop must do (start/stop the recorder, send the arm home) and refuses events that
//! make no sense in the current state, naming both.

use labrig_msgs::rig::EpisodeEventKind;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    Idle,
    Recording,
    /// The episode ended (how) and the arm is going back to the home pose.
    Resetting(Ending),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    Success,
    Failure,
    Discarded,
    /// No episode: the operator sent the arm home while idle.
    Homing,
}

/// What the loop does on a transition.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Effect {
    /// Tell the recorder to start an episode.
    StartRecording,
    /// Tell the recorder how it ended; then send the arm home.
    EndRecording(Ending),
    /// The arm is home: ready for the next episode.
    Ready,
    /// Idle, the operator asked for home: send the arm there (no episode, nothing recorded).
    GoHome,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("episode event {event:?} does not apply while {state:?}")]
pub struct Refused {
    pub event: EpisodeEventKind,
    pub state: State,
}

#[derive(Debug, Clone)]
pub struct Episodes {
    state: State,
    /// Steps recorded in the current episode.
    pub steps: u64,
    pub recorded: u64,
}

impl Default for Episodes {
    fn default() -> Self {
        Episodes { state: State::Idle, steps: 0, recorded: 0 }
    }
}

impl Episodes {
    pub fn state(&self) -> State {
        self.state
    }

    pub fn recording(&self) -> bool {
        self.state == State::Recording
    }

    /// Applies an event; returns what the loop must do.
    pub fn on(&mut self, event: EpisodeEventKind) -> Result<Effect, Refused> {
        use EpisodeEventKind as E;
        let refused = Refused { event, state: self.state };
        let (next, effect) = match (self.state, event) {
            (State::Idle, E::Start) => {
                self.steps = 0;
                (State::Recording, Effect::StartRecording)
            }
            (State::Recording, E::Success) => {
                (State::Resetting(Ending::Success), Effect::EndRecording(Ending::Success))
            }
            // Stop without a label is a failure, as in DROID.
            (State::Recording, E::Failure | E::Stop) => {
                (State::Resetting(Ending::Failure), Effect::EndRecording(Ending::Failure))
            }
            (State::Recording, E::Discard) => {
                (State::Resetting(Ending::Discarded), Effect::EndRecording(Ending::Discarded))
            }
            // The arm reached home (the loop sends Reset when it has).
            (State::Resetting(_), E::Reset) => (State::Idle, Effect::Ready),
            // An operator's Reset while idle: home first, then idle again.
            (State::Idle, E::Reset) => (State::Resetting(Ending::Homing), Effect::GoHome),
            _ => return Err(refused),
        };
        if matches!(effect, Effect::EndRecording(Ending::Success | Ending::Failure)) {
            self.recorded += 1;
        }
        self.state = next;
        Ok(effect)
    }

    /// A tick of the loop while recording.
    pub fn tick(&mut self) {
        if self.state == State::Recording {
            self.steps += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use EpisodeEventKind as E;

    #[test]
    fn an_episode_goes_round() {
        let mut e = Episodes::default();
        assert_eq!(e.on(E::Start), Ok(Effect::StartRecording));
        e.tick();
        e.tick();
        assert_eq!(e.steps, 2);
        assert_eq!(e.on(E::Success), Ok(Effect::EndRecording(Ending::Success)));
        assert_eq!(e.state(), State::Resetting(Ending::Success));
        assert_eq!(e.on(E::Reset), Ok(Effect::Ready));
        assert_eq!(e.on(E::Start), Ok(Effect::StartRecording));
        assert_eq!(e.steps, 0, "a new episode counts from 0");
        assert_eq!(e.on(E::Stop), Ok(Effect::EndRecording(Ending::Failure)), "stop = failure");
        e.on(E::Reset).unwrap();
        e.on(E::Start).unwrap();
        assert_eq!(e.on(E::Discard), Ok(Effect::EndRecording(Ending::Discarded)));
        assert_eq!(e.recorded, 2, "discarded episodes are not counted");
    }

    #[test]
    fn events_out_of_place_are_refused_by_name() {
        let mut e = Episodes::default();
        let err = e.on(E::Success).unwrap_err();
        assert_eq!(err.to_string(), "episode event Success does not apply while Idle");
        e.on(E::Start).unwrap();
        assert_eq!(e.on(E::Start).unwrap_err().state, State::Recording);
        assert_eq!(e.on(E::Reset).unwrap_err().event, E::Reset);
        assert!(e.recording());
    }

    #[test]
    fn a_reset_while_idle_goes_home_without_an_episode() {
        let mut e = Episodes::default();
        assert_eq!(e.on(E::Reset), Ok(Effect::GoHome));
        assert_eq!(e.state(), State::Resetting(Ending::Homing));
        assert_eq!(e.on(E::Start).unwrap_err().state, State::Resetting(Ending::Homing));
        assert_eq!(e.on(E::Reset), Ok(Effect::Ready), "home: idle again");
        assert_eq!(e.recorded, 0);
    }
}
