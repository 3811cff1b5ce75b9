//! The diffusion noise schedule and the DDIM sampler, with the semantics of diffusers'
//! `DDPMScheduler` (training) and `DDIMScheduler` (inference) as LeRobot's Diffusion Policy
//! configures them: `squaredcos_cap_v2` betas, epsilon prediction (or `sample`, its
//! `prediction_type` alternative), samples clipped to [-1, 1],
//! `set_alpha_to_one`, eta 0, "leading" timestep spacing, no offset.
//!
//! The schedule is computed as diffusers computes it (betas in f64, then float32 from there on:
//! `alphas_cumprod` is a float32 cumulative product), so the same timesteps give the same
//! coefficients to the last bit.

use tch::Tensor;

/// A schedule or sampler asked for something it cannot be.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ScheduleError {
    #[error("the noise schedule needs at least one training step")]
    NoTrainSteps,
    #[error("DDIM with {inference} steps over a {train}-step schedule: 1..={train} steps are possible")]
    InferenceSteps { inference: usize, train: usize },
    #[error("timestep {t} is outside the {train}-step schedule")]
    Timestep { t: i64, train: usize },
}

/// The betas limit of diffusers' `betas_for_alpha_bar`.
const MAX_BETA: f64 = 0.999;

/// A discrete noise schedule: `alphas_cumprod[t]` is the signal kept after `t + 1` noising steps.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseSchedule {
    pub betas: Vec<f32>,
    pub alphas_cumprod: Vec<f32>,
}

impl NoiseSchedule {
    /// The squared-cosine schedule (Nichol & Dhariwal; diffusers' `squaredcos_cap_v2`) over
    /// `train_steps` steps: beta_i = min(1 - abar((i+1)/T) / abar(i/T), 0.999) with
    /// abar(t) = cos((t + 0.008) / 1.008 * pi / 2)^2.
    pub fn squared_cosine(train_steps: usize) -> Result<NoiseSchedule, ScheduleError> {
        if train_steps == 0 {
            return Err(ScheduleError::NoTrainSteps);
        }
        let abar = |t: f64| ((t + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2);
        let n = train_steps as f64;
        let betas: Vec<f32> = (0..train_steps)
            .map(|i| (1.0 - abar((i + 1) as f64 / n) / abar(i as f64 / n)).min(MAX_BETA) as f32)
            .collect();
        let mut acc = 1.0f32;
        let alphas_cumprod = betas
            .iter()
            .map(|b| {
                acc *= 1.0 - b;
                acc
            })
            .collect();
        Ok(NoiseSchedule { betas, alphas_cumprod })
    }

    pub fn train_steps(&self) -> usize {
        self.betas.len()
    }

    fn alpha_cumprod(&self, t: i64) -> Result<f32, ScheduleError> {
        usize::try_from(t)
            .ok()
            .and_then(|i| self.alphas_cumprod.get(i).copied())
            .ok_or(ScheduleError::Timestep { t, train: self.train_steps() })
    }

    /// Training's forward process q(x_t | x_0) for one timestep per batch row:
    /// sqrt(abar_t) x0 + sqrt(1 - abar_t) noise (`x0`, `noise`: (B, ...); `t`: B timesteps).
    pub fn add_noise(&self, x0: &Tensor, noise: &Tensor, t: &[i64]) -> Result<Tensor, ScheduleError> {
        let abar: Vec<f32> = t.iter().map(|&t| self.alpha_cumprod(t)).collect::<Result<_, _>>()?;
        let shape: Vec<i64> = std::iter::once(t.len() as i64).chain(std::iter::repeat_n(1, x0.dim() - 1)).collect();
        let abar = Tensor::from_slice(&abar).to_kind(x0.kind()).to_device(x0.device()).view(shape.as_slice());
        let keep = abar.sqrt();
        let add = (abar.neg() + 1.0).sqrt();
        Ok(keep * x0 + add * noise)
    }
}

/// What the network predicts (LeRobot's `prediction_type`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Prediction {
    /// The noise that was added (Diffusion Policy's choice).
    #[default]
    Epsilon,
    /// The clean chunk itself.
    Sample,
}

/// DDIM sampling (eta 0, deterministic given the initial noise) over a [`NoiseSchedule`].
#[derive(Debug, Clone, PartialEq)]
pub struct Ddim {
    schedule: NoiseSchedule,
    timesteps: Vec<i64>,
    step_ratio: i64,
    /// Predicted clean samples are clamped to [-clip, clip] (diffusers' `clip_sample_range`).
    clip: Option<f64>,
    prediction: Prediction,
}

impl Ddim {
    /// `inference_steps` steps with "leading" spacing: t = k * (T / n) for k = n-1 .. 0
    /// (100 training steps, 16 inference steps: 90, 84, ..., 6, 0).
    pub fn new(schedule: NoiseSchedule, inference_steps: usize, clip: Option<f64>) -> Result<Ddim, ScheduleError> {
        let train = schedule.train_steps();
        if inference_steps == 0 || inference_steps > train {
            return Err(ScheduleError::InferenceSteps { inference: inference_steps, train });
        }
        let step_ratio = (train / inference_steps) as i64;
        let timesteps = (0..inference_steps as i64).rev().map(|k| k * step_ratio).collect();
        Ok(Ddim { schedule, timesteps, step_ratio, clip, prediction: Prediction::Epsilon })
    }

    /// The same sampler for a network that predicts `prediction`.
    pub fn predicting(self, prediction: Prediction) -> Ddim {
        Ddim { prediction, ..self }
    }

    /// The timesteps the sampler visits, first to last.
    pub fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    /// One DDIM step from `sample` at timestep `t` given the network's output `out`: with
    /// epsilon prediction eps = out and x0 = (x - sqrt(1 - abar_t) eps) / sqrt(abar_t); with
    /// sample prediction x0 = out and eps = (x - sqrt(abar_t) x0) / sqrt(1 - abar_t); x0
    /// clipped (after eps is derived, as diffusers does); then
    /// x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps (abar_prev = 1 past the start).
    pub fn step(&self, out: &Tensor, t: i64, sample: &Tensor) -> Result<Tensor, ScheduleError> {
        let (x0, eps) = self.estimate(out, t, sample)?;
        self.advance(x0, &eps, t)
    }

    /// The clean chunk and the noise the network's output `out` at `sample`, timestep `t`,
    /// stands for (x0 not yet clipped).
    pub fn estimate(&self, out: &Tensor, t: i64, sample: &Tensor) -> Result<(Tensor, Tensor), ScheduleError> {
        let a_t = self.schedule.alpha_cumprod(t)?;
        let b_t = 1.0 - a_t;
        Ok(match self.prediction {
            Prediction::Epsilon => {
                ((sample - out * f64::from(b_t.sqrt())) / f64::from(a_t.sqrt()), out.shallow_clone())
            }
            Prediction::Sample => (out.shallow_clone(), (sample - out * f64::from(a_t.sqrt())) / f64::from(b_t.sqrt())),
        })
    }

    /// The rest of a step from the estimate: x0 clipped, then
    /// x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev) eps.
    pub fn advance(&self, x0: Tensor, eps: &Tensor, t: i64) -> Result<Tensor, ScheduleError> {
        let prev = t - self.step_ratio;
        let a_prev = if prev >= 0 { self.schedule.alpha_cumprod(prev)? } else { 1.0 };
        let b_prev = 1.0 - a_prev;
        let x0 = match self.clip {
            Some(c) => x0.clamp(-c, c),
            None => x0,
        };
        Ok(x0 * f64::from(a_prev.sqrt()) + eps * f64::from(b_prev.sqrt()))
    }

    /// The clip of the predicted clean sample, if any.
    pub fn clip(&self) -> Option<f64> {
        self.clip
    }

    /// abar_t, the signal kept at timestep `t`.
    pub fn alpha_cumprod(&self, t: i64) -> Result<f32, ScheduleError> {
        self.schedule.alpha_cumprod(t)
    }

    /// The whole chunk: from `noise` through every timestep, `predict(sample, t)` giving the
    /// network's noise estimate.
    pub fn sample(
        &self,
        noise: &Tensor,
        mut predict: impl FnMut(&Tensor, i64) -> Tensor,
    ) -> Result<Tensor, ScheduleError> {
        let mut x = noise.shallow_clone();
        for &t in &self.timesteps {
            let eps = predict(&x, t);
            x = self.step(&eps, t, &x)?;
        }
        Ok(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    #[test]
    fn squared_cosine_betas_follow_the_formula_and_the_cap() {
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        assert_eq!(s.train_steps(), 100);
        let abar = |t: f64| ((t + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2);
        // The first beta by hand, and the last one capped at 0.999 (abar(1) is ~0).
        let b0 = 1.0 - abar(0.01) / abar(0.0);
        assert!((f64::from(s.betas[0]) - b0).abs() < 1e-9, "{} vs {b0}", s.betas[0]);
        assert!((s.betas[0] - 6.3128e-4).abs() < 1e-8, "{}", s.betas[0]);
        assert_eq!(s.betas[99], 0.999);
        assert!(s.betas.windows(2).all(|w| w[0] < w[1]), "increasing");
        // abar is the float32 running product of (1 - beta).
        let mut acc = 1.0f32;
        for (b, a) in s.betas.iter().zip(&s.alphas_cumprod) {
            acc *= 1.0 - b;
            assert_eq!(*a, acc);
        }
        assert!(s.alphas_cumprod[99] < 1e-4);
        assert_eq!(NoiseSchedule::squared_cosine(0).unwrap_err(), ScheduleError::NoTrainSteps);
    }

    #[test]
    fn leading_timesteps_are_diffusers() {
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let d = Ddim::new(s.clone(), 16, Some(1.0)).unwrap();
        let want: Vec<i64> = (0..16).rev().map(|k| k * 6).collect();
        assert_eq!(d.timesteps(), want.as_slice());
        assert_eq!(d.timesteps()[0], 90);
        assert_eq!(Ddim::new(s.clone(), 100, None).unwrap().timesteps().len(), 100);
        assert_eq!(
            Ddim::new(s.clone(), 0, None).unwrap_err(),
            ScheduleError::InferenceSteps { inference: 0, train: 100 }
        );
        assert!(Ddim::new(s, 101, None).is_err());
    }

    /// With the true noise as the network's answer, each DDIM step lands exactly on the
    /// forward process of the same clean sample one step earlier, and the last on the sample.
    #[test]
    fn a_ddim_step_with_the_true_noise_follows_the_forward_process_to_the_clean_sample() {
        tch::manual_seed(7);
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let d = Ddim::new(s.clone(), 16, None).unwrap();
        let x0 = Tensor::rand([3, 16, 7], (Kind::Float, tch::Device::Cpu)) * 1.6 - 0.8;
        let eps = Tensor::randn([3, 16, 7], (Kind::Float, tch::Device::Cpu));
        let mut x = s.add_noise(&x0, &eps, &[90, 90, 90]).unwrap();
        for &t in d.timesteps() {
            x = d.step(&eps, t, &x).unwrap();
            let prev = t - 6;
            let want = if prev >= 0 { s.add_noise(&x0, &eps, &[prev; 3]).unwrap() } else { x0.shallow_clone() };
            let err = (&x - &want).abs().max().double_value(&[]);
            assert!(err < 1e-4, "t {t}: max error {err}");
        }
    }

    /// The same with a network that predicts the clean sample: given the true x0 every step
    /// lands on the forward process too, and the two predictions agree step by step.
    #[test]
    fn a_ddim_step_with_the_true_clean_sample_follows_the_forward_process() {
        tch::manual_seed(8);
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let by_eps = Ddim::new(s.clone(), 16, None).unwrap();
        let by_x0 = by_eps.clone().predicting(Prediction::Sample);
        let x0 = Tensor::rand([3, 16, 7], (Kind::Float, tch::Device::Cpu)) * 1.6 - 0.8;
        let eps = Tensor::randn([3, 16, 7], (Kind::Float, tch::Device::Cpu));
        let mut x = s.add_noise(&x0, &eps, &[90, 90, 90]).unwrap();
        for &t in by_x0.timesteps() {
            let other = by_eps.step(&eps, t, &x).unwrap();
            x = by_x0.step(&x0, t, &x).unwrap();
            let prev = t - 6;
            let want = if prev >= 0 { s.add_noise(&x0, &eps, &[prev; 3]).unwrap() } else { x0.shallow_clone() };
            let err = (&x - &want).abs().max().double_value(&[]);
            assert!(err < 1e-3, "t {t}: max error {err}");
            assert!((&x - &other).abs().max().double_value(&[]) < 1e-3, "t {t}");
        }
        // A wrong clean sample does not: the step follows what the network says.
        let wrong = by_x0.step(&(&x0 + 0.5), 12, &s.add_noise(&x0, &eps, &[12; 3]).unwrap()).unwrap();
        assert!((&wrong - s.add_noise(&x0, &eps, &[6; 3]).unwrap()).abs().max().double_value(&[]) > 0.1);
    }

    #[test]
    fn clipping_bounds_the_predicted_clean_sample() {
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let d = Ddim::new(s, 100, Some(1.0)).unwrap();
        // At the last step (t = 0 -> abar_prev = 1) the output is the clipped x0 itself.
        let x = Tensor::from_slice(&[5.0f32, -5.0, 0.5]);
        let out = d.step(&Tensor::zeros([3], (Kind::Float, tch::Device::Cpu)), 0, &x).unwrap();
        let v: Vec<f32> = out.try_into().unwrap();
        let a0 = NoiseSchedule::squared_cosine(100).unwrap().alphas_cumprod[0];
        assert_eq!(v[0], 1.0);
        assert_eq!(v[1], -1.0);
        assert!((v[2] - 0.5 / a0.sqrt()).abs() < 1e-6, "{v:?}");
        assert_eq!(d.step(&x, 100, &x).unwrap_err(), ScheduleError::Timestep { t: 100, train: 100 });
    }
}
