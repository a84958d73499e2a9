//! The simulated SMPL humanoid in MuJoCo: the only crate that touches MuJoCo.
//!
//! - [`skeleton`]: body names and order, proportions, joint groups, ranges;
//! - [`mjcf`]: the generated MJCF and the PD gains `kp = I wn^2`, `kd = 2 I zeta wn`;
//! - [`Humanoid`]: the compiled model shared by all environments, and the action map
//!   `q_des = q_bar + alpha * a`;
//! - [`Env`]: reset to a full state, 30 Hz control steps, the 165-d [`state`], kicks, falls;
//! - [`VecEnv`]: many environments stepped in parallel on all cores;
//! - [`Mirror`]: the left-right mirror image of states and actions;
//! - [`obstacle`]: solid cylinders and boxes, standing or moving, that the humanoid can touch.

pub mod bench;
mod env;
mod humanoid;
pub mod mirror;
pub mod mjcf;
pub mod obstacle;
#[cfg(feature = "render")]
pub mod render;
pub mod skeleton;
pub mod state;
mod vec_env;

pub use env::{Env, FALL_HEAD_HEIGHT};
pub use humanoid::{ActionMap, CONTROL_HZ, Humanoid, STANDING_PELVIS_HEIGHT, SimConfig, check_body_order};
pub use mirror::Mirror;
pub use obstacle::{Footprint, Obstacle};
pub use skeleton::{BODY_NAMES, NUM_BODIES, NUM_DOFS, NUM_JOINTS};
pub use state::{BodyKinematics, STATE_DIM};
pub use vec_env::VecEnv;

/// Everything that can go wrong in the simulator, with enough context to act on.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("MuJoCo rejected the humanoid model: {0}")]
    Model(String),
    #[error("invalid simulator setting: {0}")]
    Config(String),
    #[error("action has {got} entries; the humanoid has 69 hinges")]
    ActionShape { got: usize },
    #[error("action entry {index} ({hinge}) is {value}; actions must be finite")]
    NonFiniteAction { index: usize, hinge: String, value: f32 },
    #[error("state has qpos of length {qpos} and qvel of length {qvel}; the model needs {nq} and {nv}")]
    StateShape { qpos: usize, qvel: usize, nq: usize, nv: usize },
    #[error("non-finite value in {what} at index {index}")]
    NonFiniteState { what: &'static str, index: usize },
    #[error("physics diverged at control step {step} (MuJoCo flagged bad accelerations or produced NaN)")]
    Diverged { step: u64 },
    #[error("rendering: {0}")]
    Render(String),
}
