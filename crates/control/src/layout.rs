//! Where things are in a predicted trajectory `tau_t = [a_t, s_{t+1}, a_{t+1}, ..., s_{t+H}, a_{t+H}]`
//! (docs/conventions.md, section 2), stored flat in that order: action 0, then (state k, action k) for k = 1..=H.
//! States are in the character frame of step t (global part) and their own frame (local part),
//! in physical units (the model's normalisation undone).

use flowmimic_sim::state::offset;
use flowmimic_sim::{NUM_DOFS, STATE_DIM};

/// The layout of a trajectory of horizon H.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    pub horizon: usize,
}

impl Layout {
    /// Length of the flat trajectory: (H + 1) actions and H states.
    pub fn len(&self) -> usize {
        (self.horizon + 1) * NUM_DOFS + self.horizon * STATE_DIM
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Start of state k (1..=H).
    pub fn state(&self, k: usize) -> usize {
        debug_assert!((1..=self.horizon).contains(&k));
        NUM_DOFS + (k - 1) * (STATE_DIM + NUM_DOFS)
    }

    /// Start of action k (0..=H).
    pub fn action(&self, k: usize) -> usize {
        if k == 0 { 0 } else { self.state(k) + STATE_DIM }
    }

    /// Start of state k's root position (x, y in frame t; z the height).
    pub fn root_pos(&self, k: usize) -> usize {
        self.state(k) + offset::ROOT_POS
    }

    /// Start of state k's root velocity (frame t).
    pub fn root_vel(&self, k: usize) -> usize {
        self.state(k) + offset::ROOT_VEL
    }

    /// Start of state k's root rotation vector (frame t).
    pub fn root_rot(&self, k: usize) -> usize {
        self.state(k) + offset::ROOT_ROT
    }

    /// Start of body `b`'s position in state k's own frame.
    pub fn body_pos(&self, k: usize, b: usize) -> usize {
        self.state(k) + offset::BODY_POS + 3 * b
    }

    /// Body `b`'s position in state k in the current step's character frame (x, y; z the
    /// height above the ground): `(root_x, root_y, root_z) + R_z(yaw_k) * body_k`, with
    /// `body_k` its position in state k's own frame. Also the offset rotated into the current
    /// frame, `R_z(yaw_k) * body_k` (x, y), which the reach cost's gradient needs.
    pub fn body_in_frame(&self, tau: &[f32], k: usize, b: usize) -> ([f32; 3], [f32; 2]) {
        let (p, at) = (self.root_pos(k), self.body_pos(k, b));
        let (s, c) = tau[self.root_rot(k) + 2].sin_cos();
        let (x, y) = (tau[at], tau[at + 1]);
        let rotated = [c * x - s * y, s * x + c * y];
        ([tau[p] + rotated[0], tau[p + 1] + rotated[1], tau[p + 2] + tau[at + 2]], rotated)
    }

    /// What plan `tau` asks of the body ([`flowmimic_data::motion`] of its states): set
    /// beside the body's achieved motion, it tells a model that plans the wrong motion from an
    /// executed action that misses a right plan.
    pub fn intent(&self, tau: &[f32]) -> [f32; 3] {
        flowmimic_data::motion((1..=self.horizon).map(|k| {
            // Each state's velocity, in the current frame, turned into its own heading.
            let (yaw, v) = (tau[self.root_rot(k) + 2], self.root_vel(k));
            let (s, c) = yaw.sin_cos();
            ([c * tau[v] + s * tau[v + 1], c * tau[v + 1] - s * tau[v]], yaw)
        }))
    }
}
