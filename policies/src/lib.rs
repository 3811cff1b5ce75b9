//! labrig-policies: the paper's Diffusion Policy in Rust on libtorch (tch 0.26.0, PyTorch
//! 2.13.0 libraries assembled from PyPI wheels by `scripts/setup.sh`).
//!
//! Built so far (issue 17, first part): the pieces whose numbers must equal the reference
//! implementation's (LeRobot's `DiffusionPolicy`, diffusers' schedulers) before the networks
//! are put together —
//! - [`schedule`]: the squared-cosine noise schedule of training and the DDIM sampler of
//!   inference (epsilon prediction, clipped samples, eta 0, "leading" timesteps);
//! - [`normalize`]: min-max normalisation of actions and low-dimensional observations to
//!   [-1, 1] from the training data's statistics;
//! - [`spatial_softmax`]: the image encoder's keypoint head (robomimic's SpatialSoftmax);
//! - [`encoder`]: one camera's encoder, the GroupNorm ResNet-18 trunk + keypoints + Linear,
//!   with LeRobot's parameter names;
//! - [`unet`]: the noise network, a 1-D U-Net over the action chunk with FiLM conditioning on
//!   the diffusion step and the observation features, with LeRobot's parameter names.
//!
//! - [`policy`]: the policy assembled (observation -> conditioning, training's loss, DDIM
//!   sampling of a chunk), with the paper's and a small preset.
//!
//! To come: checkpoints
//! (safetensors), the trainer with the co-training sampler (`labrig train`) and the LeRobot
//! fixture comparison.
//!
//! The only crate that links libtorch besides the policy server (checked by
//! `tests/tests/layering.rs`).

pub mod encoder;
pub mod normalize;
pub mod policy;
pub mod schedule;
pub mod spatial_softmax;
pub mod unet;
