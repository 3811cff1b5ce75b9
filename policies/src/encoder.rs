//! The image encoder of the paper's Diffusion Policy (robomimic's, as LeRobot builds it): a
//! ResNet-18 trained from scratch with every BatchNorm replaced by a GroupNorm of
//! channels / 16 groups, its average pool and fc removed, then [`SpatialSoftmax`] (32
//! keypoints) and Linear(64 -> 64) + ReLU. One encoder per camera.
//!
//! Parameter names follow LeRobot's `DiffusionRgbEncoder` (torchvision's children numbered as
//! `nn.Sequential` numbers them: `backbone.0` conv1, `backbone.1` its norm, `backbone.4`..`7`
//! layer1..4, each block's `conv1`, `bn1`, `conv2`, `bn2`, `downsample.0`, `downsample.1`;
//! `pool.nets`; `out`), so LeRobot's weights load by name.

use crate::spatial_softmax::SpatialSoftmax;
use tch::Tensor;
use tch::nn::{self, Module};

fn conv(vs: nn::Path<'_>, c_in: i64, c_out: i64, k: i64, stride: i64, padding: i64) -> nn::Conv2D {
    let cfg = nn::ConvConfig { stride, padding, bias: false, ..Default::default() };
    nn::conv2d(vs, c_in, c_out, k, cfg)
}

/// GroupNorm in place of BatchNorm: channels / 16 groups (LeRobot's `use_group_norm`).
fn norm(vs: nn::Path<'_>, channels: i64) -> nn::GroupNorm {
    nn::group_norm(vs, channels / 16, channels, Default::default())
}

/// torchvision's BasicBlock with GroupNorm.
#[derive(Debug)]
struct Block {
    conv1: nn::Conv2D,
    bn1: nn::GroupNorm,
    conv2: nn::Conv2D,
    bn2: nn::GroupNorm,
    downsample: Option<(nn::Conv2D, nn::GroupNorm)>,
}

impl Block {
    fn new(vs: &nn::Path<'_>, c_in: i64, c_out: i64, stride: i64) -> Block {
        let downsample = (stride != 1 || c_in != c_out)
            .then(|| (conv(vs / "downsample" / "0", c_in, c_out, 1, stride, 0), norm(vs / "downsample" / "1", c_out)));
        Block {
            conv1: conv(vs / "conv1", c_in, c_out, 3, stride, 1),
            bn1: norm(vs / "bn1", c_out),
            conv2: conv(vs / "conv2", c_out, c_out, 3, 1, 1),
            bn2: norm(vs / "bn2", c_out),
            downsample,
        }
    }
}

impl Module for Block {
    fn forward(&self, x: &Tensor) -> Tensor {
        let y = x.apply(&self.conv1).apply(&self.bn1).relu().apply(&self.conv2).apply(&self.bn2);
        let skip = match &self.downsample {
            Some((c, n)) => x.apply(c).apply(n),
            None => x.shallow_clone(),
        };
        (y + skip).relu()
    }
}

/// The ResNet-18 trunk (no average pool, no fc): (B, 3, H, W) -> (B, 512, H/32, W/32).
#[derive(Debug)]
pub struct ResNet18Gn {
    conv1: nn::Conv2D,
    bn1: nn::GroupNorm,
    layers: Vec<Vec<Block>>,
}

impl ResNet18Gn {
    pub fn new(vs: nn::Path<'_>) -> ResNet18Gn {
        let conv1 = conv(&vs / "0", 3, 64, 7, 2, 3);
        let bn1 = norm(&vs / "1", 64);
        let widths = [(64, 64, 1), (64, 128, 2), (128, 256, 2), (256, 512, 2)];
        let layers = widths
            .iter()
            .enumerate()
            .map(|(i, &(c_in, c_out, stride))| {
                let layer = &vs / (4 + i).to_string();
                vec![Block::new(&(&layer / "0"), c_in, c_out, stride), Block::new(&(&layer / "1"), c_out, c_out, 1)]
            })
            .collect();
        ResNet18Gn { conv1, bn1, layers }
    }
}

impl Module for ResNet18Gn {
    fn forward(&self, x: &Tensor) -> Tensor {
        let mut x = x.apply(&self.conv1).apply(&self.bn1).relu().max_pool2d([3, 3], [2, 2], [1, 1], [1, 1], false);
        for layer in &self.layers {
            for block in layer {
                x = block.forward(&x);
            }
        }
        x
    }
}

/// A shallow conv trunk for small images on a CPU (robomimic's and DrQ's kind): three 3x3
/// convolutions of `width`, `2 width` and `2 width` channels, the first two of stride 2, each
/// with a GroupNorm (channels / 8 groups, at least 1) and a ReLU: (B, 3, H, W) -> (B, 2 width,
/// H/4, W/4). At 58x58 its map is 15x15 (a ResNet-18's is 2x2) for about 1% of a ResNet-18's
/// multiply-adds (3.5 M at width 16).
#[derive(Debug)]
pub struct ShallowConv {
    layers: Vec<(nn::Conv2D, nn::GroupNorm)>,
}

impl ShallowConv {
    pub fn new(vs: nn::Path<'_>, width: i64) -> ShallowConv {
        let plan = [(3, width, 2), (width, 2 * width, 2), (2 * width, 2 * width, 1)];
        let layers = plan
            .iter()
            .enumerate()
            .map(|(i, &(c_in, c_out, stride))| {
                let conv = conv(&vs / (2 * i).to_string(), c_in, c_out, 3, stride, 1);
                let norm = nn::group_norm(&vs / (2 * i + 1).to_string(), (c_out / 8).max(1), c_out, Default::default());
                (conv, norm)
            })
            .collect();
        ShallowConv { layers }
    }

    pub fn out_channels(width: i64) -> i64 {
        2 * width
    }
}

impl Module for ShallowConv {
    fn forward(&self, x: &Tensor) -> Tensor {
        self.layers.iter().fold(x.shallow_clone(), |x, (c, n)| x.apply(c).apply(n).relu())
    }
}

/// The trunk an encoder runs before its keypoints.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Backbone {
    /// The paper's (LeRobot's names, so LeRobot's weights load).
    #[default]
    Resnet18,
    /// [`ShallowConv`] of a width (`encoder_width`).
    Shallow,
}

#[derive(Debug)]
enum Trunk {
    Resnet18(Box<ResNet18Gn>),
    Shallow(ShallowConv),
}

/// One camera's encoder: image (B, 3, H, W) in [0, 1] -> (B, 2 * keypoints) features.
#[derive(Debug)]
pub struct RgbEncoder {
    backbone: Trunk,
    pool: SpatialSoftmax,
    out: nn::Linear,
}

impl RgbEncoder {
    /// The paper's encoder: 32 keypoints, 64 features.
    pub fn new(vs: nn::Path<'_>, keypoints: i64) -> RgbEncoder {
        RgbEncoder::with_backbone(vs, keypoints, Backbone::Resnet18, 0)
    }

    /// An encoder on `backbone` (`width`: the shallow trunk's first width; unused by the
    /// ResNet-18).
    pub fn with_backbone(vs: nn::Path<'_>, keypoints: i64, backbone: Backbone, width: i64) -> RgbEncoder {
        let features = 2 * keypoints;
        let (trunk, channels) = match backbone {
            Backbone::Resnet18 => (Trunk::Resnet18(Box::new(ResNet18Gn::new(&vs / "backbone"))), 512),
            Backbone::Shallow => {
                (Trunk::Shallow(ShallowConv::new(&vs / "backbone", width)), ShallowConv::out_channels(width))
            }
        };
        RgbEncoder {
            backbone: trunk,
            pool: SpatialSoftmax::new(&vs / "pool", channels, keypoints),
            out: nn::linear(&vs / "out", features, features, Default::default()),
        }
    }

    /// The trunk's feature map (B, C, h, w).
    pub fn trunk(&self, image: &Tensor) -> Tensor {
        match &self.backbone {
            Trunk::Resnet18(r) => r.forward(image),
            Trunk::Shallow(s) => s.forward(image),
        }
    }
}

impl Module for RgbEncoder {
    fn forward(&self, image: &Tensor) -> Tensor {
        self.pool.forward(&self.trunk(image)).flatten(1, -1).apply(&self.out).relu()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    /// The trunk is torchvision's ResNet-18 without its fc: 11,176,512 parameters (GroupNorm's
    /// affine weights in place of BatchNorm's); the head adds 16,416 + 4,160.
    #[test]
    fn the_encoder_has_resnet18s_parameters_and_shapes() {
        let vs = nn::VarStore::new(Device::Cpu);
        let enc = RgbEncoder::new(vs.root(), 32);
        let vars = vs.variables();
        let count: i64 = vars.values().map(|t| t.numel() as i64).sum();
        assert_eq!(count, 11_176_512 + 512 * 32 + 32 + 64 * 64 + 64);
        for name in [
            "backbone.0.weight",
            "backbone.1.weight",
            "backbone.4.0.conv1.weight",
            "backbone.5.0.downsample.0.weight",
            "backbone.7.1.bn2.bias",
            "pool.nets.weight",
            "out.weight",
        ] {
            assert!(vars.contains_key(name), "{name} missing: {:?}", vars.keys().take(8).collect::<Vec<_>>());
        }
        assert!(!vars.contains_key("backbone.4.0.downsample.0.weight"), "layer1 keeps its width: no downsample");
        tch::manual_seed(0);
        let image = Tensor::rand([2, 3, 128, 128], (Kind::Float, Device::Cpu));
        let trunk = tch::no_grad(|| enc.trunk(&image));
        assert_eq!(trunk.size(), [2, 512, 4, 4]);
        let f = tch::no_grad(|| enc.forward(&image));
        assert_eq!(f.size(), [2, 64]);
        assert!(f.min().double_value(&[]) >= 0.0, "ReLU output");
    }

    /// The shallow trunk keeps a 15x15 map of 2 x width channels at 58x58 with a fraction of
    /// a percent of the ResNet-18's parameters.
    #[test]
    fn the_shallow_encoder_keeps_a_large_map() {
        let vs = nn::VarStore::new(Device::Cpu);
        let enc = RgbEncoder::with_backbone(vs.root(), 32, Backbone::Shallow, 16);
        let count: i64 = vs.variables().values().map(|t| t.numel() as i64).sum();
        let trunk = 3 * 16 * 9 + 16 * 32 * 9 + 32 * 32 * 9 + 2 * (16 + 32 + 32);
        assert_eq!(count, trunk + 32 * 32 + 32 + 64 * 64 + 64);
        let image = Tensor::rand([2, 3, 58, 58], (Kind::Float, Device::Cpu));
        assert_eq!(tch::no_grad(|| enc.trunk(&image)).size(), [2, 32, 15, 15]);
        assert_eq!(tch::no_grad(|| enc.forward(&image)).size(), [2, 64]);
        assert!(vs.variables().contains_key("backbone.4.weight"));
        assert!(!vs.variables().contains_key("backbone.6.weight"));
    }
}
