//! The paper's co-training sampler: each sample of a batch comes from the target set with
//! probability `w` and from the co-training set with `1 - w` (0.5 by default; 0.3 and 0.7 are
//! the paper's ablations), whatever the sets' sizes, uniformly within the set drawn from. It
//! counts what each set contributed, for the run's record.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Which set a sample was drawn from, and its index there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Draw {
    Target(usize),
    Cotrain(usize),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SamplerError {
    #[error("the target set is empty: nothing to train on")]
    EmptyTarget,
    #[error("co-training weight w = {0} must be in [0, 1]")]
    Weight(f64),
    #[error("w = {0} asks for co-training samples but the co-training set is empty")]
    EmptyCotrain(f64),
}

/// Draws sample indices from a target and a co-training set (sizes in samples).
#[derive(Debug)]
pub struct CotrainSampler {
    target: usize,
    cotrain: usize,
    w: f64,
    rng: ChaCha8Rng,
    /// Samples drawn from each set so far.
    pub drawn_target: u64,
    pub drawn_cotrain: u64,
}

impl CotrainSampler {
    /// `w` = the probability of the target set; no co-training set (`cotrain` = 0) needs w = 1
    /// (what `labrig train` uses without `--cotrain`).
    pub fn new(target: usize, cotrain: usize, w: f64, seed: u64) -> Result<CotrainSampler, SamplerError> {
        if target == 0 {
            return Err(SamplerError::EmptyTarget);
        }
        if !(0.0..=1.0).contains(&w) {
            return Err(SamplerError::Weight(w));
        }
        if cotrain == 0 && w < 1.0 {
            return Err(SamplerError::EmptyCotrain(w));
        }
        Ok(CotrainSampler {
            target,
            cotrain,
            w,
            rng: ChaCha8Rng::seed_from_u64(seed),
            drawn_target: 0,
            drawn_cotrain: 0,
        })
    }

    /// One sample's draw.
    pub fn draw(&mut self) -> Draw {
        if self.rng.random_bool(self.w) {
            self.drawn_target += 1;
            Draw::Target(self.rng.random_range(0..self.target))
        } else {
            self.drawn_cotrain += 1;
            Draw::Cotrain(self.rng.random_range(0..self.cotrain))
        }
    }

    /// A batch of draws.
    pub fn batch(&mut self, size: usize) -> Vec<Draw> {
        (0..size).map(|_| self.draw()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// w = 0.5 over a target of 10 samples and a co-training set of 10,000: half of the draws
    /// from each (within 4 standard deviations over 12,800), not 0.1% from the target as a
    /// uniform draw over both would give; every index in range.
    #[test]
    fn the_weight_not_the_sizes_sets_the_mix() {
        for w in [0.3, 0.5, 0.7] {
            let mut s = CotrainSampler::new(10, 10_000, w, 42).unwrap();
            let n = 12_800usize;
            let draws: Vec<Draw> = (0..100).flat_map(|_| s.batch(128)).collect();
            assert_eq!(draws.len(), n);
            let target = draws.iter().filter(|d| matches!(d, Draw::Target(_))).count() as f64;
            let sd = (n as f64 * w * (1.0 - w)).sqrt();
            assert!((target - w * n as f64).abs() < 4.0 * sd, "w {w}: {target} of {n} from the target");
            assert_eq!((s.drawn_target + s.drawn_cotrain) as usize, n);
            assert_eq!(s.drawn_target as f64, target);
            assert!(draws.iter().all(|d| match d {
                Draw::Target(i) => *i < 10,
                Draw::Cotrain(i) => *i < 10_000,
            }));
        }
    }

    #[test]
    fn target_only_and_bad_weights() {
        let mut s = CotrainSampler::new(5, 0, 1.0, 1).unwrap();
        assert!(s.batch(64).iter().all(|d| matches!(d, Draw::Target(i) if *i < 5)));
        assert_eq!(CotrainSampler::new(5, 0, 0.5, 1).unwrap_err(), SamplerError::EmptyCotrain(0.5));
        assert_eq!(CotrainSampler::new(0, 9, 0.5, 1).unwrap_err(), SamplerError::EmptyTarget);
        assert_eq!(CotrainSampler::new(5, 9, 1.5, 1).unwrap_err(), SamplerError::Weight(1.5));
        assert!(CotrainSampler::new(5, 9, f64::NAN, 1).is_err());
        // The same seed draws the same batches.
        let a = CotrainSampler::new(7, 7, 0.5, 9).unwrap().batch(32);
        assert_eq!(a, CotrainSampler::new(7, 7, 0.5, 9).unwrap().batch(32));
    }
}
