//! The controller's view of the past: the last N + 1 states (with their root poses) and N
//! actions, re-expressed into the current step's character frame exactly as the training
//! windows are (the same function does both), so the model sees at run time what it saw in
//! training.

use flowmimic_data::window::{WindowSpec, reexpress};
use flowmimic_geom::heading;
use flowmimic_sim::{BodyKinematics, NUM_DOFS, STATE_DIM};
use std::collections::VecDeque;

/// One remembered control step.
#[derive(Clone, Debug)]
struct Step {
    /// The state in its own character frame.
    state: [f32; STATE_DIM],
    /// Root x, y and heading in the world.
    root_pose: [f32; 3],
    /// The action executed from this state, once known.
    action: Option<Vec<f32>>,
}

/// The root's pose (x, y, heading) as the history and the data store it beside each state.
pub(crate) fn root_pose(bodies: &BodyKinematics) -> [f32; 3] {
    let root = bodies.pos[0];
    [root.x as f32, root.y as f32, heading(bodies.rot[0]) as f32]
}

/// A rolling buffer of the last N + 1 steps.
#[derive(Clone, Debug)]
pub struct History {
    spec: WindowSpec,
    steps: VecDeque<Step>,
}

impl History {
    pub fn new(spec: WindowSpec) -> Self {
        Self { spec, steps: VecDeque::with_capacity(spec.history + 1) }
    }

    /// Records the current step's kinematics (call once per control step, before acting).
    pub fn observe(&mut self, bodies: &BodyKinematics) {
        self.push(bodies.state(), root_pose(bodies));
    }

    /// Records a state (own frame) and its root pose directly.
    pub fn push(&mut self, state: [f32; STATE_DIM], root_pose: [f32; 3]) {
        if self.steps.len() == self.spec.history + 1 {
            self.steps.pop_front();
        }
        self.steps.push_back(Step { state, root_pose, action: None });
    }

    /// Records the action executed from the latest state.
    pub fn act(&mut self, action: &[f32]) {
        if let Some(last) = self.steps.back_mut() {
            last.action = Some(action.to_vec());
        }
    }

    /// Whether N + 1 states (and the N actions between them) have been seen.
    pub fn is_full(&self) -> bool {
        self.steps.len() == self.spec.history + 1
            && self.steps.iter().take(self.spec.history).all(|s| s.action.is_some())
    }

    /// The conditioning `O_t`: N + 1 states in the current frame, then N actions. Before the
    /// buffer is full the oldest entry is repeated (a standing start).
    pub fn conditioning(&self) -> (Vec<f32>, Vec<f32>) {
        let n = self.spec.history;
        let current = self.steps.back().expect("observe before asking for the history").root_pose;
        let missing = n + 1 - self.steps.len();
        let entry = |j: usize| &self.steps[j.saturating_sub(missing)];
        let mut states = vec![0.0; (n + 1) * STATE_DIM];
        for (j, out) in states.chunks_mut(STATE_DIM).enumerate() {
            let step = entry(j);
            reexpress(&step.state, step.root_pose, current, out);
        }
        let zero = vec![0.0; NUM_DOFS];
        let actions = (0..n).flat_map(|j| entry(j).action.clone().unwrap_or_else(|| zero.clone())).collect();
        (states, actions)
    }
}
