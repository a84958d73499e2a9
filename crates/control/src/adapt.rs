//! Adaptive guidance, the paper's suggested extension (its "Limitations": a strength that
//! follows the current tracking error): each environment's guidance scale is `w` times its
//! executed joystick error over the last half second ([`crate::Task::executed_error`]) divided
//! by a reference error, within [`Adaptive::MIN_FACTOR`, `Adaptive::MAX_FACTOR`]. The error is
//! what the humanoid did, not what the model predicts: the predicted error is already in every
//! gradient's length ([`crate::Sum::guidance_grad`]), and a prediction can promise a motion
//! that the executed actions do not deliver.

use flowmimic_geom::{heading, wrap_angle};
use flowmimic_sim::{BodyKinematics, CONTROL_HZ};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

use crate::ControlError;

/// Control steps over which the executed motion is measured: half a second, a gait cycle.
pub const WINDOW: usize = 15;

/// The executed joystick error (m/s and rad/s, root-sum-square) at which an environment is
/// guided at `w`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Adaptive {
    pub reference: f32,
}

impl Adaptive {
    /// Guidance fades to a quarter of `w` when on track ...
    pub const MIN_FACTOR: f64 = 0.25;
    /// ... and is `w` at most: with up to 2w, large errors toppled the humanoid (`eval joystick
    /// --adaptive 1.0 --seed 1`, 20 trials: 10 and 25% falls at w 30 and 40, where the fixed
    /// scale has none; README, "Adaptive guidance").
    pub const MAX_FACTOR: f64 = 1.0;

    pub fn new(reference: f32) -> Result<Self, ControlError> {
        if reference.is_finite() && reference > 0.0 {
            Ok(Self { reference })
        } else {
            Err(ControlError::BadCommand {
                what: "adaptive guidance reference error (> 0)",
                value: f64::from(reference),
            })
        }
    }

    /// The multiplier of `w` for an executed error (`None`: not measured yet, `w` itself).
    pub fn factor(&self, error: Option<f64>) -> f32 {
        error.map_or(1.0, |e| (e / f64::from(self.reference)).clamp(Self::MIN_FACTOR, Self::MAX_FACTOR) as f32)
    }
}

/// The pelvis's last [`WINDOW`] + 1 world poses (x, y, heading), to measure what was executed.
#[derive(Clone, Debug, Default)]
pub struct Recent {
    poses: VecDeque<[f64; 3]>,
}

impl Recent {
    pub fn push(&mut self, pose: [f64; 3]) {
        if self.poses.len() == WINDOW + 1 {
            self.poses.pop_front();
        }
        self.poses.push_back(pose);
    }

    /// Records the pelvis pose of the current step's kinematics.
    pub fn observe(&mut self, bodies: &BodyKinematics) {
        let (p, r) = (bodies.pos[0], bodies.rot[0]);
        self.push([p.x, p.y, heading(r)]);
    }

    /// Mean planar velocity over the window in the character frame of its middle (x forward,
    /// y left, m/s) and mean yaw rate (rad/s); `None` until the window is full.
    pub fn velocity(&self) -> Option<([f64; 2], f64)> {
        if self.poses.len() < WINDOW + 1 {
            return None;
        }
        let (first, last) = (self.poses[0], self.poses[WINDOW]);
        let seconds = WINDOW as f64 / CONTROL_HZ;
        let turned = wrap_angle(last[2] - first[2]);
        let (s, c) = (first[2] + turned / 2.0).sin_cos();
        let (dx, dy) = ((last[0] - first[0]) / seconds, (last[1] - first[1]) / seconds);
        Some(([c * dx + s * dy, -s * dx + c * dy], turned / seconds))
    }
}
