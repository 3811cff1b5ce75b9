//! Training samples cut from an episode, as LeRobot's Diffusion Policy draws them: for every
//! step `t`, the observation steps `t - To + 1 ..= t` and the action steps
//! `t - To + 1 .. t - To + 1 + Tp`, indices past either end of the episode clamped to its
//! first or last step and flagged as padding (training may mask padded actions out of the
//! loss).

/// One sample's step indices within its episode.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Window {
    /// The step the sample is for.
    pub t: usize,
    pub obs: Vec<usize>,
    pub obs_pad: Vec<bool>,
    pub actions: Vec<usize>,
    pub action_pad: Vec<bool>,
}

fn clamped(len: usize, from: i64, count: usize) -> (Vec<usize>, Vec<bool>) {
    (0..count as i64)
        .map(|k| {
            let i = from + k;
            let c = i.clamp(0, len as i64 - 1);
            (c as usize, c != i)
        })
        .unzip()
}

/// Every sample of an episode of `len` steps (none for an empty one).
pub fn windows(len: usize, n_obs_steps: usize, horizon: usize) -> Vec<Window> {
    (0..len)
        .map(|t| {
            let first = t as i64 + 1 - n_obs_steps as i64;
            let (obs, obs_pad) = clamped(len, first, n_obs_steps);
            let (actions, action_pad) = clamped(len, first, horizon);
            Window { t, obs, obs_pad, actions, action_pad }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_take_to_steps_back_and_tp_steps_of_actions_padded_at_the_ends() {
        let w = windows(20, 2, 16);
        assert_eq!(w.len(), 20);
        // t = 0: the observation before the start is the first step again, padded.
        assert_eq!((w[0].obs.clone(), w[0].obs_pad.clone()), (vec![0, 0], vec![true, false]));
        assert_eq!(w[0].actions[..3], [0, 0, 1]);
        assert!(w[0].action_pad[0] && !w[0].action_pad[1]);
        // t = 5: steps 4, 5 observed; actions 4..=19, none padded.
        assert_eq!(w[5].obs, [4, 5]);
        assert_eq!(w[5].actions, (4..20).collect::<Vec<_>>());
        assert!(w[5].action_pad.iter().all(|p| !p));
        // The last step: its actions run past the end, repeated and padded.
        let last = &w[19];
        assert_eq!(last.obs, [18, 19]);
        assert_eq!(last.actions[..2], [18, 19]);
        assert!(last.actions[2..].iter().all(|&a| a == 19));
        assert_eq!(last.action_pad.iter().filter(|p| **p).count(), 14);
        assert!(windows(0, 2, 16).is_empty());
        // A one-step episode: everything is that step.
        let one = &windows(1, 2, 4)[0];
        assert_eq!((one.obs.clone(), one.actions.clone()), (vec![0, 0], vec![0, 0, 0, 0]));
    }
}
