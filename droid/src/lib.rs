//! labrig-droid: DROID's raw episode format (trajectory.h5 + one MP4 per camera + metadata
//! JSON), exported from labrig's MCAP episodes and imported back.
//!
//! - [`h5doc`]: an HDF5 file as plain data (hdf5-metno over Debian's libhdf5).
//! - [`droid`]: steps <-> DROID's trajectory.h5 keys, no I/O.
//! - [`meta`]: the metadata JSON (`metadata_<uuid>.json`).
//! - [`video`]: MP4 through ffmpeg.
//! - [`export`], [`import`]: whole episodes.
//! - [`droid_mcap`]: DROID's own MCAP layout (`trajectory.mcap`), exported and imported.

pub mod droid;
pub mod droid_mcap;
pub mod export;
pub mod h5doc;
pub mod import;
pub mod meta;
pub mod video;

use std::path::{Path, PathBuf};

pub use labrig_episode::episode::dirs_holding;

/// Why an export or import failed; every variant names the file or directory.
#[derive(Debug, thiserror::Error)]
pub enum DroidError {
    #[error(transparent)]
    Read(#[from] labrig_episode::ReadError),
    #[error(transparent)]
    Write(#[from] labrig_episode::EpisodeError),
    #[error(transparent)]
    Video(#[from] video::VideoError),
    #[error(transparent)]
    H5(#[from] h5doc::H5Error),
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: {source}", path.display())]
    Mcap {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    /// The input is not what DROID's or labrig's format says; `reason` names what is wrong.
    #[error("{}: {reason}", path.display())]
    Bad { path: PathBuf, reason: String },
    /// A DROID-layout MCAP's content does not fit the layout.
    #[error("{}: {source}", path.display())]
    Layout {
        path: PathBuf,
        #[source]
        source: droid_mcap::DroidMcapError,
    },
    #[error("{} holds this episode already: pass --overwrite to replace it", dir.display())]
    Exists { dir: PathBuf },
}

/// `map_err` for an I/O error on `path`.
pub(crate) fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DroidError + '_ {
    move |source| DroidError::Io { path: path.to_owned(), source }
}

/// A [`DroidError::Bad`] for `path`.
pub(crate) fn bad(path: &Path, reason: impl Into<String>) -> DroidError {
    DroidError::Bad { path: path.to_owned(), reason: reason.into() }
}

/// Where an episode goes: DROID's directory `base` (named to the second), or `base_2`,
/// `base_3` ... when another episode started in the same second (as the recorder does).
/// The directory already holding this same episode (`is_same`) is an error unless
/// `overwrite`, then it is removed and reused.
pub(crate) fn destination(
    base: &Path,
    is_same: impl Fn(&Path) -> bool,
    overwrite: bool,
) -> Result<PathBuf, DroidError> {
    let name = base.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    for k in 1.. {
        let dir = if k == 1 { base.to_owned() } else { base.with_file_name(format!("{name}_{k}")) };
        if !dir.exists() {
            return Ok(dir);
        }
        if is_same(&dir) {
            if !overwrite {
                return Err(DroidError::Exists { dir });
            }
            std::fs::remove_dir_all(&dir).map_err(io(&dir))?;
            return Ok(dir);
        }
    }
    unreachable!("an unbounded search")
}

/// An export or import written into `partial`: renamed to `dir` when it succeeded, removed when
/// it failed (so a failure leaves no half episode behind).
pub(crate) fn settle<T>(partial: &Path, dir: &Path, result: Result<T, DroidError>) -> Result<T, DroidError> {
    match result {
        Ok(v) => {
            std::fs::rename(partial, dir).map_err(io(dir))?;
            Ok(v)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(partial);
            Err(e)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::destination;

    #[test]
    fn episodes_of_the_same_second_get_a_suffix_and_the_same_one_is_kept() {
        let t = tempfile::tempdir().unwrap();
        let base = t.path().join("Fri_Jul__7_09:42:23_2023");
        assert_eq!(destination(&base, |_| false, false).unwrap(), base);
        std::fs::create_dir_all(base.join("x")).unwrap();
        let other = destination(&base, |d| d.join("mine").exists(), false).unwrap();
        assert_eq!(other, t.path().join("Fri_Jul__7_09:42:23_2023_2"));
        std::fs::create_dir_all(other.join("mine")).unwrap();
        let e = destination(&base, |d| d.join("mine").exists(), false).unwrap_err().to_string();
        assert!(e.contains("_2 holds this episode already: pass --overwrite"), "{e}");
        assert_eq!(destination(&base, |d| d.join("mine").exists(), true).unwrap(), other);
        assert!(!other.exists() && base.join("x").exists(), "only the same episode's directory is replaced");
    }
}
