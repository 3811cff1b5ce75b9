//! labrig-policies: the paper's Diffusion Policy in Rust on libtorch (tch 0.26.0, PyTorch
//! 2.13.0 libraries assembled from PyPI wheels by `scripts/setup.sh`), with the reference
//! implementation's semantics and parameter names (LeRobot's `DiffusionPolicy`, diffusers'
//! schedulers), so that a LeRobot checkpoint imports by name and samples the same chunk.
//!
//! - [`schedule`]: the squared-cosine noise schedule and the DDIM sampler;
//! - [`normalize`]: min-max normalisation to [-1, 1] (LeRobot's arithmetic);
//! - [`spatial_softmax`], [`encoder`]: one camera's GroupNorm ResNet-18 + keypoints + Linear;
//! - [`unet`]: the FiLM-conditioned 1-D U-Net noise network;
//! - [`policy`]: the policy assembled (conditioning, loss, traced DDIM sampling) and presets;
//! - [`data`], [`window`], [`sampler`]: labrig episodes as training tensors (frames decoded
//!   once and cached), LeRobot's sample windows, the paper's co-training sampler;
//! - [`train`]: `labrig train` (Adam, cosine warm-up, EMA, validation, checkpoints, resume);
//! - [`checkpoint`], [`infer`], [`lerobot`]: checkpoints on disk, one chunk from tensors in
//!   LeRobot's names, LeRobot 0.4 policy directories imported;
//! - [`bench`]: `labrig bench policy`.
//!
//! The program `labrig-policies` (src/main.rs) is what the CLI forwards `train`, `policy` and
//! `bench policy` to. The only crate that links libtorch besides the policy server (checked by
//! `tests/tests/layering.rs`).

pub mod bench;
pub mod checkpoint;
pub mod data;
pub mod dist;
pub mod encoder;
pub mod infer;
pub mod lerobot;
pub mod normalize;
pub mod policy;
pub mod rtc;
pub mod sampler;
pub mod schedule;
pub mod spatial_softmax;
pub mod train;
pub mod unet;
pub mod window;

/// A file operation that failed, naming the file and what was being done.
#[derive(Debug, thiserror::Error)]
#[error("{}: {what}: {source}", path.display())]
pub struct FileError {
    pub path: std::path::PathBuf,
    pub what: &'static str,
    #[source]
    pub source: std::io::Error,
}

impl FileError {
    /// For `map_err`: the error of `what` on `path`.
    pub fn at<'a>(path: &'a std::path::Path, what: &'static str) -> impl FnOnce(std::io::Error) -> FileError + 'a {
        move |source| FileError { path: path.to_owned(), what, source }
    }
}
