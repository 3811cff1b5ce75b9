//! The noise network of the paper's Diffusion Policy: a 1-D temporal U-Net over the action
//! chunk, conditioned by FiLM on the diffusion step's embedding and the observation features
//! (global conditioning), as LeRobot's `DiffusionConditionalUnet1d` builds it. Parameter names
//! are LeRobot's (`diffusion_step_encoder.1`, `down_modules.0.0.conv1.block.0`,
//! `cond_encoder.1`, `residual_conv`, `mid_modules`, `up_modules`, `final_conv`), so its weights
//! load by name.

use tch::nn::{self, Module};
use tch::{Kind, Tensor};

/// The U-Net's shape (every number a config value; the paper's: down dims 256/512/1024, kernel
/// 5, 8 groups, step embedding 256, FiLM scale and bias).
#[derive(Debug, Clone, PartialEq)]
pub struct UnetConfig {
    pub action_dim: i64,
    pub global_cond_dim: i64,
    pub down_dims: Vec<i64>,
    pub kernel_size: i64,
    pub n_groups: i64,
    pub step_embed_dim: i64,
    /// FiLM with a scale and a bias per channel (else the bias only).
    pub film_scale: bool,
}

/// Sinusoidal embedding of the diffusion step: [sin(t w_i), cos(t w_i)], w_i = 10000^(-i/(h-1)).
pub fn step_embedding(t: &Tensor, dim: i64) -> Tensor {
    let half = dim / 2;
    let scale = (10000f64).ln() / (half - 1) as f64;
    let freqs = (Tensor::arange(half, (Kind::Float, t.device())) * -scale).exp();
    let args = t.to_kind(Kind::Float).unsqueeze(1) * freqs.unsqueeze(0);
    Tensor::cat(&[args.sin(), args.cos()], -1)
}

/// Conv1d -> GroupNorm -> Mish (`DiffusionConv1dBlock`, its layers at `block.0`, `block.1`).
#[derive(Debug)]
struct ConvBlock {
    conv: nn::Conv1D,
    norm: nn::GroupNorm,
}

impl ConvBlock {
    fn new(vs: &nn::Path<'_>, c_in: i64, c_out: i64, k: i64, groups: i64) -> ConvBlock {
        let cfg = nn::ConvConfig { padding: k / 2, ..Default::default() };
        ConvBlock {
            conv: nn::conv1d(vs / "block" / "0", c_in, c_out, k, cfg),
            norm: nn::group_norm(vs / "block" / "1", groups, c_out, Default::default()),
        }
    }
}

impl Module for ConvBlock {
    fn forward(&self, x: &Tensor) -> Tensor {
        x.apply(&self.conv).apply(&self.norm).mish()
    }
}

/// A residual block whose middle is modulated by the conditioning (FiLM).
#[derive(Debug)]
struct ResBlock {
    conv1: ConvBlock,
    conv2: ConvBlock,
    cond: nn::Linear,
    residual: Option<nn::Conv1D>,
    out_channels: i64,
    film_scale: bool,
}

impl ResBlock {
    fn new(vs: &nn::Path<'_>, c_in: i64, c_out: i64, cfg: &UnetConfig, cond_dim: i64) -> ResBlock {
        let cond_channels = if cfg.film_scale { 2 * c_out } else { c_out };
        ResBlock {
            conv1: ConvBlock::new(&(vs / "conv1"), c_in, c_out, cfg.kernel_size, cfg.n_groups),
            conv2: ConvBlock::new(&(vs / "conv2"), c_out, c_out, cfg.kernel_size, cfg.n_groups),
            cond: nn::linear(vs / "cond_encoder" / "1", cond_dim, cond_channels, Default::default()),
            residual: (c_in != c_out).then(|| nn::conv1d(vs / "residual_conv", c_in, c_out, 1, Default::default())),
            out_channels: c_out,
            film_scale: cfg.film_scale,
        }
    }

    fn forward(&self, x: &Tensor, cond: &Tensor) -> Tensor {
        let out = self.conv1.forward(x);
        let embed = cond.mish().apply(&self.cond).unsqueeze(-1);
        let out = if self.film_scale {
            let scale = embed.narrow(1, 0, self.out_channels);
            let bias = embed.narrow(1, self.out_channels, self.out_channels);
            scale * out + bias
        } else {
            out + embed
        };
        let out = self.conv2.forward(&out);
        let skip = match &self.residual {
            Some(c) => x.apply(c),
            None => x.shallow_clone(),
        };
        out + skip
    }
}

/// One level of the U-Net: two residual blocks and a resampling layer (none at the bottom).
#[derive(Debug)]
struct Level {
    blocks: [ResBlock; 2],
    down: Option<nn::Conv1D>,
    up: Option<nn::ConvTranspose1D>,
}

/// The noise network: (B, T, action_dim) noisy chunk, (B,) steps, (B, global_cond_dim)
/// observation features -> (B, T, action_dim) predicted noise.
#[derive(Debug)]
pub struct ConditionalUnet1d {
    step_in: nn::Linear,
    step_out: nn::Linear,
    step_dim: i64,
    down: Vec<Level>,
    mid: [ResBlock; 2],
    up: Vec<Level>,
    final_block: ConvBlock,
    final_conv: nn::Conv1D,
}

impl ConditionalUnet1d {
    pub fn new(vs: nn::Path<'_>, cfg: &UnetConfig) -> ConditionalUnet1d {
        let dsed = cfg.step_embed_dim;
        let cond_dim = dsed + cfg.global_cond_dim;
        let mut in_out = vec![(cfg.action_dim, cfg.down_dims[0])];
        in_out.extend(cfg.down_dims.windows(2).map(|w| (w[0], w[1])));
        let down = in_out
            .iter()
            .enumerate()
            .map(|(i, &(c_in, c_out))| {
                let p = &vs / "down_modules" / i.to_string();
                let last = i + 1 == in_out.len();
                let down_cfg = nn::ConvConfig { stride: 2, padding: 1, ..Default::default() };
                Level {
                    blocks: [
                        ResBlock::new(&(&p / "0"), c_in, c_out, cfg, cond_dim),
                        ResBlock::new(&(&p / "1"), c_out, c_out, cfg, cond_dim),
                    ],
                    down: (!last).then(|| nn::conv1d(&p / "2", c_out, c_out, 3, down_cfg)),
                    up: None,
                }
            })
            .collect();
        let bottom = *cfg.down_dims.last().expect("at least one down dim");
        let mid = [
            ResBlock::new(&(&vs / "mid_modules" / "0"), bottom, bottom, cfg, cond_dim),
            ResBlock::new(&(&vs / "mid_modules" / "1"), bottom, bottom, cfg, cond_dim),
        ];
        let up = in_out[1..]
            .iter()
            .rev()
            .enumerate()
            .map(|(i, &(c_out, c_in))| {
                let p = &vs / "up_modules" / i.to_string();
                let up_cfg = nn::ConvTransposeConfig { stride: 2, padding: 1, ..Default::default() };
                Level {
                    blocks: [
                        ResBlock::new(&(&p / "0"), 2 * c_in, c_out, cfg, cond_dim),
                        ResBlock::new(&(&p / "1"), c_out, c_out, cfg, cond_dim),
                    ],
                    down: None,
                    up: Some(nn::conv_transpose1d(&p / "2", c_out, c_out, 4, up_cfg)),
                }
            })
            .collect();
        let d0 = cfg.down_dims[0];
        ConditionalUnet1d {
            step_in: nn::linear(&vs / "diffusion_step_encoder" / "1", dsed, 4 * dsed, Default::default()),
            step_out: nn::linear(&vs / "diffusion_step_encoder" / "3", 4 * dsed, dsed, Default::default()),
            step_dim: dsed,
            down,
            mid,
            up,
            final_block: ConvBlock::new(&(&vs / "final_conv" / "0"), d0, d0, cfg.kernel_size, cfg.n_groups),
            final_conv: nn::conv1d(&vs / "final_conv" / "1", d0, cfg.action_dim, 1, Default::default()),
        }
    }

    pub fn forward(&self, sample: &Tensor, steps: &Tensor, global_cond: &Tensor) -> Tensor {
        let t = step_embedding(steps, self.step_dim).apply(&self.step_in).mish().apply(&self.step_out);
        let cond = Tensor::cat(&[t, global_cond.shallow_clone()], -1);
        let mut x = sample.transpose(1, 2);
        let mut skips = Vec::new();
        for level in &self.down {
            x = level.blocks[1].forward(&level.blocks[0].forward(&x, &cond), &cond);
            skips.push(x.shallow_clone());
            if let Some(d) = &level.down {
                x = x.apply(d);
            }
        }
        for block in &self.mid {
            x = block.forward(&x, &cond);
        }
        for level in &self.up {
            let skip = skips.pop().expect("a skip per level");
            x = Tensor::cat(&[x, skip], 1);
            x = level.blocks[1].forward(&level.blocks[0].forward(&x, &cond), &cond);
            if let Some(u) = &level.up {
                x = x.apply(u);
            }
        }
        x.apply(&self.final_block).apply(&self.final_conv).transpose(1, 2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn small() -> UnetConfig {
        UnetConfig {
            action_dim: 7,
            global_cond_dim: 2 * (64 + 7),
            down_dims: vec![32, 64, 128],
            kernel_size: 5,
            n_groups: 8,
            step_embed_dim: 32,
            film_scale: true,
        }
    }

    #[test]
    fn the_step_embedding_is_sin_then_cos() {
        let e = step_embedding(&Tensor::from_slice(&[0i64, 10]), 8);
        assert_eq!(e.size(), [2, 8]);
        // t = 0: sin 0 = 0, cos 0 = 1; t = 10, first frequency 1: sin 10, cos 10.
        let v: Vec<f32> = e.flatten(0, -1).try_into().unwrap();
        assert_eq!(&v[..8], &[0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0]);
        assert!((v[8] - 10f32.sin()).abs() < 1e-6 && (v[12] - 10f32.cos()).abs() < 1e-6, "{v:?}");
        // The last frequency is 10000^-1.
        assert!((v[11] - (10.0f32 / 10000.0).sin()).abs() < 1e-6, "{v:?}");
    }

    /// A chunk of 16 steps goes down 16 -> 8 -> 4 and back up to its own shape; LeRobot's
    /// parameter names are where its weights will be looked for.
    #[test]
    fn the_unet_maps_a_chunk_to_its_noise_shape_with_lerobots_names() {
        let vs = nn::VarStore::new(Device::Cpu);
        let net = ConditionalUnet1d::new(vs.root(), &small());
        tch::manual_seed(1);
        let x = Tensor::randn([3, 16, 7], (Kind::Float, Device::Cpu));
        let cond = Tensor::randn([3, 142], (Kind::Float, Device::Cpu));
        let t = Tensor::from_slice(&[0i64, 50, 99]);
        let eps = tch::no_grad(|| net.forward(&x, &t, &cond));
        assert_eq!(eps.size(), [3, 16, 7]);
        assert!(eps.isfinite().all().int64_value(&[]) == 1);
        let vars = vs.variables();
        for name in [
            "diffusion_step_encoder.1.weight",
            "diffusion_step_encoder.3.bias",
            "down_modules.0.0.conv1.block.0.weight",
            "down_modules.0.0.conv1.block.1.weight",
            "down_modules.0.0.cond_encoder.1.weight",
            "down_modules.0.0.residual_conv.weight",
            "down_modules.1.2.weight",
            "mid_modules.1.conv2.block.0.bias",
            "up_modules.0.0.residual_conv.weight",
            "up_modules.1.2.weight",
            "final_conv.0.block.0.weight",
            "final_conv.1.weight",
        ] {
            assert!(vars.contains_key(name), "{name} missing");
        }
        assert!(!vars.contains_key("down_modules.2.2.weight"), "no downsampling at the bottom");
        assert!(!vars.contains_key("down_modules.0.1.residual_conv.weight"), "same width: identity skip");
        // FiLM: the conditioning gives a scale and a bias per channel.
        assert_eq!(vars["down_modules.1.0.cond_encoder.1.weight"].size(), [2 * 64, 32 + 142]);
        // The conditioning matters: another observation, another noise estimate.
        let other = tch::no_grad(|| net.forward(&x, &t, &(cond + 1.0)));
        assert!((other - eps).abs().max().double_value(&[]) > 1e-4);
    }
}
