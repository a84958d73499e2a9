//! PPO tracking experts: a policy per clip (or one for several clips) that makes the
//! simulated humanoid follow the reference, trained with PPO as BeyondMimic does.
//!
//! - [`plan`]: plan-like references, for a policy that executes a guidance model's plans;
//! - [`ppo`]: rollouts, GAE, the clipped PPO update, observation normalisation;
//! - [`task`]: observations, rewards, terminations, resets and pushes;
//! - [`train`]: the training loop, logs, checkpoints, resume and evaluation.

pub mod plan;
pub mod ppo;
pub mod task;
pub mod train;

pub use train::{EvalReport, EvalSetup, TrackConfig, Trainer, evaluate};

#[derive(Debug, thiserror::Error)]
pub enum TrackError {
    #[error("{path}: {message}")]
    Checkpoint { path: std::path::PathBuf, message: String },
    #[error(transparent)]
    Io(#[from] flowmimic_io::FileError),
    #[error(transparent)]
    Sim(#[from] flowmimic_sim::SimError),
    #[error("training diverged at iteration {iteration}: {what}")]
    NonFinite { iteration: usize, what: String },
    #[error("{0}")]
    Invalid(String),
}
