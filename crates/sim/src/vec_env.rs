//! Many independent environments stepped in parallel: one `MjData` each, one shared model.

use crate::humanoid::Humanoid;
use crate::skeleton::NUM_DOFS;
use crate::{Env, SimError};
use rayon::prelude::*;
use std::sync::Arc;

/// A batch of environments; `step` runs them across all cores with rayon.
#[derive(Debug)]
pub struct VecEnv {
    envs: Vec<Env>,
}

impl VecEnv {
    pub fn new(humanoid: &Arc<Humanoid>, count: usize) -> Self {
        Self { envs: (0..count).map(|_| humanoid.env()).collect() }
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    pub fn envs(&self) -> &[Env] {
        &self.envs
    }

    pub fn envs_mut(&mut self) -> &mut [Env] {
        &mut self.envs
    }

    /// Steps env `i` with `actions[i * 69..(i + 1) * 69]`, all in parallel. Returns the first
    /// failure with its env index; the other envs have still been stepped.
    pub fn step(&mut self, actions: &[f32]) -> Result<(), (usize, SimError)> {
        if actions.len() != self.envs.len() * NUM_DOFS {
            return Err((0, SimError::ActionShape { got: actions.len() / self.envs.len().max(1) }));
        }
        self.envs
            .par_iter_mut()
            .zip(actions.par_chunks(NUM_DOFS))
            .enumerate()
            .map(|(i, (env, a))| env.step(a).map_err(|e| (i, e)))
            .collect::<Vec<_>>()
            .into_iter()
            .collect()
    }
}
