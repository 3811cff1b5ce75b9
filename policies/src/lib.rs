//! labrig-policies: the paper's Diffusion Policy in Rust on libtorch (tch 0.26.0, PyTorch
//! 2.13.0 libraries assembled from PyPI wheels by `scripts/setup.sh`).
//!
//! Built so far (issue 17, first part), with the reference implementation's semantics and
//! parameter names (LeRobot's `DiffusionPolicy`, diffusers' schedulers):
//! - [`schedule`]: the squared-cosine noise schedule of training and the DDIM sampler of
//!   inference (epsilon prediction, clipped samples, eta 0, "leading" timesteps);
//! - [`normalize`]: min-max normalisation of actions and low-dimensional observations to
//!   [-1, 1] from the training data's statistics;
//! - [`spatial_softmax`]: the image encoder's keypoint head (robomimic's SpatialSoftmax);
//! - [`encoder`]: one camera's encoder, the GroupNorm ResNet-18 trunk + keypoints + Linear,
//!   with LeRobot's parameter names;
//! - [`unet`]: the noise network, a 1-D U-Net over the action chunk with FiLM conditioning on
//!   the diffusion step and the observation features, with LeRobot's parameter names;
//! - [`policy`]: the policy assembled (observation -> conditioning, training's loss, DDIM
//!   sampling of a chunk), with the paper's and a small preset;
//! - [`checkpoint`]: a trained policy on disk (safetensors weights and EMA weights, the
//!   config, normaliser statistics and data manifest as JSON).
//!
//! - [`sampler`]: the paper's co-training sampler (target with probability w, whatever the
//!   sets' sizes);
//! - [`window`]: the training samples of an episode (To observation steps, Tp action steps,
//!   padded at the ends).
//!
//! To come: the trainer (`labrig train`), the LeRobot fixture
//! comparison, `labrig policy infer` and `labrig bench policy`.
//!
//! The only crate that links libtorch besides the policy server (checked by
//! `tests/tests/layering.rs`).

pub mod bench;
pub mod checkpoint;
pub mod data;
pub mod encoder;
pub mod infer;
pub mod lerobot;
pub mod normalize;
pub mod policy;
pub mod sampler;
pub mod schedule;
pub mod spatial_softmax;
pub mod train;
pub mod unet;
pub mod window;
