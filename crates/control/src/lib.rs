//! Guided control: the trajectory model drives the humanoid, steered by task costs at test time.
//!
//! - [`controller`]: the receding-horizon loop over a batch of environments;
//! - [`task`]: joystick schedules, hand targets and waypoints in the world, turned into costs;
//! - [`rollout`]: the file a run writes (`flowmimic-rollout/1`);
//! - [`layout`]: where the predicted actions and states sit in a trajectory;
//! - [`history`]: the live conditioning `O_t`, built exactly as the training windows are;
//! - [`adapt`]: adaptive guidance, a scale that follows the executed error;
//! - [`recommended`]: a model directory's measured best settings per task;
//! - [`costs`]: joystick velocity (paper eq. 7) and heading, end-effector reach (eq. 8),
//!   waypoint navigation (BeyondMimic), and weighted sums;
//! - [`obstacles`]: keeping plans clear of obstacles, and the detour a waypoint takes around them.

pub mod adapt;
pub mod controller;
pub mod costs;
pub mod executor;
pub mod history;
pub mod layout;
pub mod obstacles;
pub mod recommended;
pub mod rollout;
pub mod task;

pub use adapt::Adaptive;
pub use controller::{ControlConfig, Controller, StartActions, StepOutcome, StepReport, run, start_from_clip};
pub use costs::{Cost, Heading, Joystick, Pursuit, Reach, Sum};
pub use executor::Executor;
pub use history::History;
pub use layout::Layout;
pub use recommended::Recommended;
pub use rollout::{Rollout, RolloutInfo, Row};
pub use task::{Hand, HeadingHold, JoystickSegment, SpeedRamp, Steer, Task};

/// The trajectory model in `dir`, refused when its states and actions are not this humanoid's.
pub fn load_model(dir: &std::path::Path) -> Result<flowmimic_model::TrajectoryModel, ControlError> {
    let model = flowmimic_model::TrajectoryModel::load(dir)?;
    model.check_layout(&humanoid_layout(&model.config), "this humanoid")?;
    Ok(model)
}

/// The token layout of this humanoid's states and actions for `config`'s window.
pub fn humanoid_layout(config: &flowmimic_model::ModelConfig) -> flowmimic_model::TokenLayout {
    flowmimic_model::TokenLayout {
        state_dim: flowmimic_sim::STATE_DIM,
        action_dim: flowmimic_sim::NUM_DOFS,
        spec: config.spec(),
        labels: config.labels(),
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    #[error("bad command: {what} is {value}")]
    BadCommand { what: &'static str, value: f64 },
    #[error("cannot start: {0}")]
    Start(String),
    #[error("{0}")]
    Sampler(String),
    #[error("the model produced a non-finite action (environment {env}, step {step}, hinge {index})")]
    NonFinite { env: usize, step: usize, index: usize },
    #[error("bad obstacle: {0}")]
    Obstacle(String),
    #[error(transparent)]
    Model(#[from] flowmimic_model::ModelError),
    #[error(transparent)]
    Sim(#[from] flowmimic_sim::SimError),
}
