//! Real-time chunking (Black, Galliker, Levine 2025, arXiv 2506.07339) in the DDIM sampler.
//!
//! The next chunk is computed while the loop executes the current one. The loop sends the
//! current chunk's rows from the new observation's tick on (the *prefix*) and how many of them
//! it will execute before the new chunk can start (`d`, the inference delay in ticks). The new
//! chunk's first `d` rows are those rows exactly ([`freeze`]); the rest of the overlap is
//! inpainted during sampling by guidance toward the prefix, under a soft mask that decays to 0
//! where the prefix ends ([`prefix_weights`]).
//!
//! # The guidance, for DDIM
//! The paper derives it for flow matching (PiGDM's training-free guidance on the velocity).
//! Here the same idea is written for a DDIM (variance-preserving) sampler. At timestep `t` the
//! network's output gives the clean-chunk estimate `x0_hat(x_t)` and its noise `eps_hat`
//! ([`Ddim::estimate`]). PiGDM treats `p(x0 | x_t)` as a Gaussian around `x0_hat` with
//! variance `r_t^2`; for a variance-preserving process it takes `r_t^2 = sigma_t^2 /
//! (1 + sigma_t^2)` with `sigma_t^2 = (1 - abar_t) / abar_t`, that is `r_t^2 = 1 - abar_t`.
//! The score of the masked target `Y` (weights `W`) is then
//! `g = J^T W (Y - x0_hat) / r_t^2`, `J = d x0_hat / d x_t` (a vector-Jacobian product
//! through the U-Net). Added to the model's score `s = -(x_t - sqrt(abar) x0_hat) / (1 -
//! abar)`, it moves the clean estimate by `dx0 = (1 - abar) / sqrt(abar) g =
//! J^T W (Y - x0_hat) / sqrt(abar)`, and the noise estimate consistently by
//! `deps = -sqrt(abar) / sqrt(1 - abar) dx0` (so `x_t = sqrt(abar) x0 + sqrt(1 - abar) eps`
//! still holds); the DDIM step then proceeds from the guided pair. As in the paper the weight
//! `1 / sqrt(abar_t)`, which grows without bound at the noisiest steps, is clipped to
//! `beta` (`max_weight`): `dx0 = min(beta, 1 / sqrt(abar_t)) J^T W (Y - x0_hat)`.
//!
//! For a Gaussian prior this is exact (PiGDM's premise); a trained network only approximates
//! the ideal denoiser's Jacobian, so the corrected clean chunk is kept in the clip range (the
//! move of the clipped estimate), which bounds what a poor Jacobian can do.
//!
//! With `beta = 0` the correction is exactly zero and the sampler is plain DDIM, bit for bit
//! (the same arithmetic with `+ 0`), which the tests check.

use crate::schedule::{Ddim, ScheduleError};
use tch::{Kind, Tensor};

/// A prefix the sampler cannot use.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum RtcError {
    #[error("the prefix has {values} values, not a whole number of {width}-wide rows")]
    Width { values: usize, width: usize },
    #[error("the prefix has {rows} rows; the chunk has only {horizon}")]
    TooLong { rows: usize, horizon: usize },
    #[error("{frozen} frozen rows (the inference delay d) but the prefix has only {rows}")]
    Frozen { frozen: usize, rows: usize },
}

/// How the clean-chunk estimate is moved toward the prefix at each DDIM step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// PiGDM's guidance through the U-Net's vector-Jacobian product (the paper's):
    /// `dx0 = min(beta, 1/sqrt(abar_t)) J^T W (Y - x0_hat)`.
    Vjp,
    /// In the clean estimate's own space (the Jacobian taken as the identity):
    /// `dx0 = min(1, beta abar_t) W (Y - x0_hat)`, a soft inpainting of the overlap that is
    /// weak while the estimate is mostly noise and whole once the chunk has formed. The
    /// network then denoises the rest of the chunk around the moved overlap.
    #[default]
    X0,
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Vjp => "vjp",
            Method::X0 => "x0",
        }
    }
}

/// The guidance toward a prefix: where the sampler is pulled, how hard, per model row.
#[derive(Debug)]
pub struct Guide {
    /// (B, Tp, action_dim), normalised; rows with weight 0 are not read.
    pub target: Tensor,
    /// (Tp) in [0, 1].
    pub weights: Vec<f32>,
    /// beta: the clip of the guidance weight (see [`Method`]).
    pub max_weight: f64,
    pub method: Method,
}

/// The soft mask over the model's `horizon` rows, whose row `offset` is the chunk's row 0 (the
/// newest observation's tick): 1 on the `frozen` rows the loop executes from the old chunk
/// before the new one starts, then decaying as the paper's exponential schedule
/// `c (e^c - 1) / (e - 1)`, `c = (rows - i) / (rows - frozen + 1)`, to 0 where the prefix's
/// `rows` end (the old chunk has nothing to say past them). Rows before `offset` (older
/// observations' ticks) get 0.
pub fn prefix_weights(horizon: usize, offset: usize, frozen: usize, rows: usize) -> Vec<f32> {
    (0..horizon)
        .map(|j| {
            let Some(i) = j.checked_sub(offset) else { return 0.0 };
            if i < frozen {
                1.0
            } else if i < rows {
                let c = (rows - i) as f64 / (rows - frozen + 1) as f64;
                (c * (c.exp() - 1.0) / (std::f64::consts::E - 1.0)) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Checks a prefix of `values` numbers against a chunk of `horizon` rows `width` wide from the
/// newest observation on; its row count.
pub fn prefix_rows(values: usize, width: usize, horizon: usize, frozen: usize) -> Result<usize, RtcError> {
    if width == 0 || !values.is_multiple_of(width) {
        return Err(RtcError::Width { values, width });
    }
    let rows = values / width;
    if rows > horizon {
        return Err(RtcError::TooLong { rows, horizon });
    }
    if frozen > rows {
        return Err(RtcError::Frozen { frozen, rows });
    }
    Ok(rows)
}

/// DDIM from `noise` with the guidance toward `guide` (module docs); `predict(x, t)` is the
/// network's output. Gradients flow through `predict` for the vector-Jacobian product only
/// (the caller may hold `no_grad`; it is lifted here).
pub fn sample_guided(
    ddim: &Ddim,
    noise: &Tensor,
    guide: &Guide,
    mut predict: impl FnMut(&Tensor, i64) -> Tensor,
) -> Result<Tensor, ScheduleError> {
    let w = Tensor::from_slice(&guide.weights).to_kind(noise.kind()).to_device(noise.device()).view([1, -1, 1]);
    let mut x = noise.shallow_clone();
    for &t in ddim.timesteps() {
        let abar = f64::from(ddim.alpha_cumprod(t)?);
        let (x0, eps, dx0) = match guide.method {
            Method::Vjp => {
                let weight = guide.max_weight.min(1.0 / abar.sqrt());
                let x_in = x.detach().set_requires_grad(true);
                tch::with_grad(|| -> Result<(Tensor, Tensor, Tensor), ScheduleError> {
                    let out = predict(&x_in, t);
                    let (x0_hat, eps_hat) = ddim.estimate(&out, t, &x_in)?;
                    let err = ((&guide.target - x0_hat.detach()) * &w).detach();
                    let vjp = Tensor::run_backward(&[(&x0_hat * &err).sum(Kind::Float)], &[&x_in], false, false);
                    Ok((x0_hat.detach(), eps_hat.detach(), vjp[0].detach() * weight))
                })?
            }
            Method::X0 => {
                let out = tch::no_grad(|| predict(&x, t));
                let (x0_hat, eps_hat) = ddim.estimate(&out, t, &x)?;
                let weight = (guide.max_weight * abar).min(1.0);
                let dx0 = (&guide.target - &x0_hat) * &w * weight;
                (x0_hat, eps_hat, dx0)
            }
        };
        // The guided clean chunk stays in the clip range (the actions' normalised range): the
        // correction is the move of the clipped estimate, so a network whose Jacobian is far
        // from the ideal denoiser's cannot push the chunk past it (and 0 stays exactly 0).
        let dx0 = match ddim.clip() {
            Some(c) => (&x0 + &dx0).clamp(-c, c) - x0.clamp(-c, c),
            None => dx0,
        };
        let to_eps = abar.sqrt() / (1.0 - abar).sqrt();
        let eps = eps - &dx0 * to_eps;
        x = tch::no_grad(|| ddim.advance(x0 + dx0, &eps, t))?;
    }
    Ok(x)
}

/// The chunk's first `frozen` rows set to the prefix's, exactly (robot units, row-major,
/// `width` wide): the rows the loop executes from the old chunk meanwhile.
pub fn freeze(actions: &mut [f64], prefix: &[f64], frozen: usize, width: usize) {
    let n = (frozen * width).min(prefix.len()).min(actions.len());
    actions[..n].copy_from_slice(&prefix[..n]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schedule::{NoiseSchedule, Prediction};
    use tch::Device;

    #[test]
    fn the_mask_is_one_on_the_frozen_rows_and_decays_to_zero_where_the_prefix_ends() {
        let w = prefix_weights(16, 1, 3, 11);
        assert_eq!(w[0], 0.0, "the older observation's row");
        assert_eq!(&w[1..4], &[1.0, 1.0, 1.0]);
        assert!(w[4] < 1.0 && w[4] > 0.5, "{w:?}");
        assert!(w[4..12].windows(2).all(|p| p[0] > p[1]), "decreasing: {w:?}");
        assert!(w[11] > 0.0 && w[12..].iter().all(|&v| v == 0.0), "{w:?}");
        // No prefix: no weight anywhere.
        assert!(prefix_weights(16, 1, 0, 0).iter().all(|&v| v == 0.0));
    }

    #[test]
    fn a_prefix_that_does_not_fit_is_refused_by_name() {
        assert_eq!(prefix_rows(21, 7, 15, 2), Ok(3));
        assert_eq!(prefix_rows(20, 7, 15, 2), Err(RtcError::Width { values: 20, width: 7 }));
        assert_eq!(prefix_rows(7 * 16, 7, 15, 2), Err(RtcError::TooLong { rows: 16, horizon: 15 }));
        assert_eq!(prefix_rows(14, 7, 15, 3), Err(RtcError::Frozen { frozen: 3, rows: 2 }));
        assert!(RtcError::Frozen { frozen: 3, rows: 2 }.to_string().contains("inference delay"));
    }

    /// The ideal denoiser of a Gaussian prior (mean `m`, variance 0.3 per value), as the
    /// network's output for `prediction`: the posterior mean
    /// x0_hat = m + sqrt(abar) s^2 / (abar s^2 + 1 - abar) (x - sqrt(abar) m), or its noise.
    fn ideal(prediction: Prediction, m: &Tensor) -> impl Fn(&Tensor, i64) -> Tensor {
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let m = m.shallow_clone();
        move |x: &Tensor, t: i64| {
            let a = f64::from(s.alphas_cumprod[t as usize]);
            let var = 0.3;
            let gain = a.sqrt() * var / (a * var + 1.0 - a);
            let x0 = &m + (x - &m * a.sqrt()) * gain;
            match prediction {
                Prediction::Sample => x0,
                Prediction::Epsilon => (x - x0 * a.sqrt()) / (1.0 - a).sqrt(),
            }
        }
    }

    /// A network far from any denoiser (its x0 Jacobian is large at every noise level).
    fn rough(x: &Tensor, t: i64) -> Tensor {
        (x * 0.7 + 0.1 * (t as f64 / 100.0)).tanh() * 0.9
    }

    fn setup(prediction: Prediction) -> (Ddim, Tensor, Tensor, Tensor) {
        let s = NoiseSchedule::squared_cosine(100).unwrap();
        let d = Ddim::new(s, 16, Some(1.0)).unwrap().predicting(prediction);
        tch::manual_seed(3);
        let noise = Tensor::randn([1, 16, 7], (Kind::Float, Device::Cpu));
        let mean = Tensor::rand([1, 16, 7], (Kind::Float, Device::Cpu)) * 1.0 - 0.5;
        let target = Tensor::rand([1, 16, 7], (Kind::Float, Device::Cpu)) * 1.6 - 0.8;
        (d, noise, mean, target)
    }

    #[test]
    fn with_zero_guidance_the_sampler_is_plain_ddim_bit_for_bit() {
        for prediction in [Prediction::Epsilon, Prediction::Sample] {
            let (d, noise, mean, target) = setup(prediction);
            for (name, net) in [
                ("ideal", Box::new(ideal(prediction, &mean)) as Box<dyn Fn(&Tensor, i64) -> Tensor>),
                ("rough", Box::new(rough)),
            ] {
                let plain = d.sample(&noise, &net).unwrap();
                for method in [Method::Vjp, Method::X0] {
                    let weights = prefix_weights(16, 1, 4, 10);
                    let guide = Guide { target: target.shallow_clone(), weights, max_weight: 0.0, method };
                    let guided = tch::no_grad(|| sample_guided(&d, &noise, &guide, &net)).unwrap();
                    let diff = (&plain - &guided).abs().max().double_value(&[]);
                    assert!(plain.equal(&guided), "{prediction:?}, {name} network, {method:?}: {diff}");
                }
            }
        }
    }

    /// With the ideal denoiser of a Gaussian prior (where PiGDM's guidance is exact) the frozen
    /// rows land on the prefix, the decaying rows move toward it, and rows of weight 0 are left
    /// alone (the denoiser acts value by value). A network far from a denoiser is held in the
    /// clip range instead of diverging.
    #[test]
    fn guidance_pulls_the_overlap_toward_the_prefix_and_leaves_the_rest_free() {
        for prediction in [Prediction::Epsilon, Prediction::Sample] {
            let (d, noise, mean, target) = setup(prediction);
            let net = ideal(prediction, &mean);
            let plain = d.sample(&noise, &net).unwrap();
            let dist = |x: &Tensor, rows: std::ops::Range<i64>| {
                (x.narrow(1, rows.start, rows.end - rows.start) - target.narrow(1, rows.start, rows.end - rows.start))
                    .abs()
                    .mean(Kind::Float)
                    .double_value(&[])
            };
            for method in [Method::Vjp, Method::X0] {
                let weights = prefix_weights(16, 1, 4, 10);
                let guide = Guide { target: target.shallow_clone(), weights, max_weight: 5.0, method };
                let guided = tch::no_grad(|| sample_guided(&d, &noise, &guide, &net)).unwrap();
                let (before, after) = (dist(&plain, 1..5), dist(&guided, 1..5));
                assert!(after < 0.05 * before, "{prediction:?} {method:?}: frozen rows {before:.3} -> {after:.4}");
                let (before, after) = (dist(&plain, 5..11), dist(&guided, 5..11));
                assert!(after < 0.7 * before, "{prediction:?} {method:?}: decaying rows {before:.3} -> {after:.3}");
                let free = plain.narrow(1, 11, 5).equal(&guided.narrow(1, 11, 5));
                assert!(free, "{prediction:?} {method:?}: unguided rows moved");
                let wild = tch::no_grad(|| sample_guided(&d, &noise, &guide, rough)).unwrap();
                let top = wild.abs().max().double_value(&[]);
                assert!(top <= 1.0 + 1e-6, "{prediction:?} {method:?}: a rough network's chunk reached {top}");
            }
        }
    }

    #[test]
    fn frozen_rows_are_the_prefix_exactly() {
        let prefix: Vec<f64> = (0..21).map(|i| 0.1 * i as f64 + 1e-9).collect();
        let mut chunk = vec![7.0; 15 * 7];
        freeze(&mut chunk, &prefix, 2, 7);
        assert_eq!(&chunk[..14], &prefix[..14]);
        assert!(chunk[14..].iter().all(|&v| v == 7.0));
    }
}
