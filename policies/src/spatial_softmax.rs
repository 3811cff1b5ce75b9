//! The image encoder's keypoint head (robomimic's SpatialSoftmax, as LeRobot's Diffusion
//! Policy uses it): a 1x1 convolution to `K` keypoint maps, a softmax over each map's H x W
//! positions, and each keypoint's expected (x, y) on a grid spanning [-1, 1] (x along the
//! width, y along the height, row-major like numpy's `meshgrid(linspace_w, linspace_h)`).

use tch::Tensor;
use tch::nn::{self, Module};

/// The expected (x, y) of each map: `logits` (B, K, H, W) -> (B, K, 2).
pub fn keypoints(logits: &Tensor) -> Tensor {
    let (b, k, h, w) = logits.size4().expect("keypoint logits are (B, K, H, W)");
    let attention = logits.reshape([b * k, h * w]).softmax(-1, logits.kind());
    attention.matmul(&grid(h, w, logits)).view([b, k, 2])
}

/// (H * W, 2): row-major positions, x = linspace(-1, 1, W)[col], y = linspace(-1, 1, H)[row].
fn grid(h: i64, w: i64, like: &Tensor) -> Tensor {
    let opts = (like.kind(), like.device());
    let xs = Tensor::linspace(-1.0, 1.0, w, opts);
    let ys = Tensor::linspace(-1.0, 1.0, h, opts);
    let x = xs.view([1, w]).expand([h, w], false).reshape([h * w, 1]);
    let y = ys.view([h, 1]).expand([h, w], false).reshape([h * w, 1]);
    Tensor::cat(&[x, y], 1)
}

/// SpatialSoftmax over a (B, C, H, W) feature map: (B, K, 2) keypoints.
#[derive(Debug)]
pub struct SpatialSoftmax {
    conv: nn::Conv2D,
}

impl SpatialSoftmax {
    /// `in_channels` -> `keypoints` maps (robomimic and the paper: 32).
    pub fn new(vs: nn::Path<'_>, in_channels: i64, keypoints: i64) -> SpatialSoftmax {
        SpatialSoftmax { conv: nn::conv2d(vs / "nets", in_channels, keypoints, 1, Default::default()) }
    }
}

impl Module for SpatialSoftmax {
    fn forward(&self, features: &Tensor) -> Tensor {
        keypoints(&self.conv.forward(features))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    /// A map with one sharp peak puts its keypoint on the peak's grid position.
    #[test]
    fn a_sharp_peak_is_its_keypoint() {
        let (h, w) = (5i64, 9i64);
        let logits = Tensor::zeros([2, 3, h, w], (Kind::Float, tch::Device::Cpu));
        let peaks = [(0, 0, 0, 0), (0, 1, 4, 8), (0, 2, 2, 4), (1, 0, 1, 6), (1, 1, 3, 2), (1, 2, 4, 0)];
        for &(b, k, r, c) in &peaks {
            let _ = logits.get(b).get(k).get(r).get(c).fill_(60.0);
        }
        let kp = keypoints(&logits);
        assert_eq!(kp.size(), [2, 3, 2]);
        for &(b, k, r, c) in &peaks {
            let x = -1.0 + 2.0 * c as f64 / (w - 1) as f64;
            let y = -1.0 + 2.0 * r as f64 / (h - 1) as f64;
            let got = (kp.double_value(&[b, k, 0]), kp.double_value(&[b, k, 1]));
            assert!((got.0 - x).abs() < 1e-5 && (got.1 - y).abs() < 1e-5, "peak ({r}, {c}): {got:?} vs ({x}, {y})");
        }
        // A flat map's keypoint is the centre.
        let flat = keypoints(&Tensor::zeros([1, 1, h, w], (Kind::Float, tch::Device::Cpu)));
        assert!(flat.abs().max().double_value(&[]) < 1e-6);
    }

    #[test]
    fn the_head_maps_channels_to_keypoints() {
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let head = SpatialSoftmax::new(vs.root(), 512, 32);
        let out = head.forward(&Tensor::randn([4, 512, 4, 4], (Kind::Float, tch::Device::Cpu)));
        assert_eq!(out.size(), [4, 32, 2]);
        assert!(out.abs().max().double_value(&[]) <= 1.0 + 1e-6, "inside the grid");
        // LeRobot's parameter names: `nets.weight`, `nets.bias`.
        let mut names: Vec<String> = vs.variables().into_keys().collect();
        names.sort();
        assert_eq!(names, ["nets.bias", "nets.weight"]);
    }
}
