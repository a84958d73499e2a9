//! Noise-augmented expert rollouts, the dataset the generative model learns from.
//!
//! - [`collect`]: run an expert with Gaussian action noise, record noisy states and clean actions;
//! - [`format`]: the sharded safetensors dataset with its JSON manifest and checksums;
//! - [`window`]: history/future windows in the current step's character frame, and
//!   normalisation statistics.

pub mod collect;
pub mod format;
pub mod window;

pub use collect::{CollectConfig, CollectStats, collect};
pub use format::{Dataset, Manifest, Shard, ShardInfo};
pub use window::{Moments, Stats, Window, WindowSpec, future_motion, motion, window, window_starts};

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: {message}")]
    Shard { path: std::path::PathBuf, message: String },
    #[error(transparent)]
    Io(#[from] flowmimic_io::FileError),
    #[error(transparent)]
    Tensors(#[from] flowmimic_io::tensors::TensorError),
    #[error(transparent)]
    Sim(#[from] flowmimic_sim::SimError),
    #[error(transparent)]
    Track(#[from] flowmimic_track::TrackError),
    #[error("{0}")]
    Invalid(String),
}
