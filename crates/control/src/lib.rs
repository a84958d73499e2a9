//! Guided control: the task costs that steer the walking-only trajectory model at test time.
//!
//! - [`layout`]: where the predicted actions and states sit in a trajectory;
//! - [`history`]: the live conditioning `O_t`, built exactly as the training windows are;
//! - [`costs`]: joystick velocity (paper eq. 7) and turn rate, end-effector reach (eq. 8),
//!   waypoint navigation (BeyondMimic), weighted sums, and the map onto the model's normalised
//!   coordinates.

pub mod costs;
pub mod history;
pub mod layout;

pub use costs::{Cost, Joystick, Normalised, Reach, Sum, TurnRate, Waypoint};
pub use history::History;
pub use layout::Layout;

#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    #[error("bad command: {what} is {value}")]
    BadCommand { what: &'static str, value: f64 },
}
