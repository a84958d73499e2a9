//! Inverse dynamics: the action that takes the humanoid from state `s_t` to state `s_{t+1}`,
//! an MLP fitted on a dataset's executed transitions.
//!
//! The trajectory model's actions are the expert's clean actions, while the states that follow
//! them were reached under the executed, noisy ones. So the model learns that `a_t` barely
//! depends on `s_{t+1}`: a guided next state is explained by noise, and the executed action
//! follows the plan's turn at a third of its rate (README, "Planned against executed motion").
//! This model is fitted on the noisy actions and the states they led to, so it reads the action
//! out of a planned next state; the controller can execute it instead of the plan's own action.

use crate::ModelError;
use crate::train::held_out;
use crate::trajectory::Normaliser;
use flowmimic_data::window::reexpress;
use flowmimic_data::{Dataset, Moments};
use flowmimic_io::tensors::{self, TensorFile};
use flowmimic_nn::{Adam, Mlp};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

/// The file an inverse-dynamics model is saved to, inside a trajectory model's directory.
pub const INVERSE_FILE: &str = "inverse.safetensors";
const FORMAT: &str = "flowmimic-inverse-dynamics/1";

/// Fitting settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InverseConfig {
    /// Hidden layer widths of the MLP.
    pub hidden: Vec<usize>,
    /// Optimiser steps, transitions per step and Adam's learning rate.
    pub steps: usize,
    pub batch: usize,
    pub lr: f32,
    /// Share of rollouts held out to measure the fit.
    pub validation_fraction: f64,
    /// Seed of the initial weights and the batches.
    pub seed: u64,
}

impl Default for InverseConfig {
    /// The `cpu` preset's: how the shipped `fm`'s inverse dynamics was fitted (7 min on 2 cores).
    fn default() -> Self {
        Self { hidden: vec![512, 512], steps: 30_000, batch: 512, lr: 1e-3, validation_fraction: 0.05, seed: 0 }
    }
}

impl InverseConfig {
    /// Every value in range (a preset's `[inverse]` table).
    pub fn validate(&self) -> Result<(), String> {
        if self.steps == 0 || self.batch == 0 || self.hidden.contains(&0) || self.hidden.len() > 8 {
            return Err(format!(
                "inverse.steps ({}), inverse.batch ({}) and every width of inverse.hidden ({:?}, at most 8 layers) must be positive",
                self.steps, self.batch, self.hidden
            ));
        }
        if !self.lr.is_finite() || self.lr <= 0.0 {
            return Err(format!("inverse.lr is {}; it must be positive", self.lr));
        }
        if !(0.0..1.0).contains(&self.validation_fraction) {
            return Err(format!("inverse.validation_fraction is {}; it must be in [0, 1)", self.validation_fraction));
        }
        Ok(())
    }
}

/// Rows of inputs `[s_t, s_{t+1}]` and of the executed actions.
type Rows = (Vec<f32>, Vec<f32>);

/// Every transition of `datasets` whose two steps lie in the same episode: `s_t` and `s_{t+1}`
/// (re-expressed in the frame of step t) side by side, and the executed action between them, in
/// two parts: the rollouts kept for fitting, and those held out (a fixed share, by the
/// trajectory model's hash).
fn split(datasets: &[Dataset], state_dim: usize, action_dim: usize, fraction: f64) -> Result<[Rows; 2], ModelError> {
    let mut parts = [(Vec::new(), Vec::new()), (Vec::new(), Vec::new())];
    let mut shards = Vec::new();
    for dataset in datasets {
        shards.extend(dataset.load_all()?.into_iter().map(|(_, shard)| shard));
    }
    let mut next = vec![0.0; state_dim];
    for (s, shard) in shards.iter().enumerate() {
        let pose = |k: usize| [shard.root_pose[3 * k], shard.root_pose[3 * k + 1], shard.root_pose[3 * k + 2]];
        for t in 0..shard.steps().saturating_sub(1) {
            if shard.done[t] != 0 || shard.rollout[t] != shard.rollout[t + 1] {
                continue;
            }
            let (xs, ys) = &mut parts[usize::from(held_out(s, shard.rollout[t], fraction))];
            xs.extend_from_slice(&shard.state[t * state_dim..(t + 1) * state_dim]);
            reexpress(&shard.state[(t + 1) * state_dim..(t + 2) * state_dim], pose(t + 1), pose(t), &mut next);
            xs.extend_from_slice(&next);
            ys.extend_from_slice(&shard.noisy_action[t * action_dim..(t + 1) * action_dim]);
        }
    }
    if parts[0].1.is_empty() {
        let dirs: Vec<String> = datasets.iter().map(|d| d.dir.display().to_string()).collect();
        return Err(ModelError::Invalid(format!(
            "{}: no transitions to fit inverse dynamics to (episodes of one step?)",
            dirs.join(", ")
        )));
    }
    Ok(parts)
}

/// An inverse-dynamics model: `(s_t, s_{t+1} in frame t) -> a_t`.
#[derive(Clone, Debug)]
pub struct InverseDynamics {
    pub state_dim: usize,
    pub action_dim: usize,
    mlp: Mlp,
    input_norm: Normaliser,
    output_norm: Normaliser,
}

/// What one logged step of fitting measured: mean squared error in standardised action units
/// (1.0 is predicting the mean action), on a training batch and on the held-out rollouts (none
/// when a small dataset has no rollout held out).
#[derive(Clone, Copy, Debug)]
pub struct FitProgress {
    pub step: usize,
    pub train_mse: f32,
    pub validation_mse: Option<f32>,
}

impl InverseDynamics {
    /// Fits a model to every transition of `datasets`, holding out a share of each shard's
    /// rollouts; `on_progress` hears about every 100th step and the last.
    pub fn fit(
        datasets: &[Dataset],
        state_dim: usize,
        action_dim: usize,
        config: &InverseConfig,
        mut on_progress: impl FnMut(&FitProgress),
    ) -> Result<Self, ModelError> {
        config.validate().map_err(ModelError::Invalid)?;
        let width = 2 * state_dim;
        let mut rng = StdRng::seed_from_u64(config.seed);
        let [(mut train_x, mut train_y), (mut val_x, mut val_y)] =
            split(datasets, state_dim, action_dim, config.validation_fraction)?;
        let moments = |rows: &[f32], width: usize| {
            let mut m = Moments::new(width);
            m.add(rows);
            let (mean, std) = m.finish();
            Normaliser { mean, std }
        };
        let input_norm = moments(&train_x, width);
        let output_norm = moments(&train_y, action_dim);
        for (x, y) in [(&mut train_x, &mut train_y), (&mut val_x, &mut val_y)] {
            input_norm.normalise(x, 0, width);
            output_norm.normalise(y, 0, action_dim);
        }
        let sizes: Vec<usize> =
            std::iter::once(width).chain(config.hidden.iter().copied()).chain([action_dim]).collect();
        let mut mlp = Mlp::new(&sizes, 1.0, &mut rng);
        let mut params = mlp.params();
        let mut adam = Adam::new(params.len());
        let mut order: Vec<usize> = (0..train_y.len() / action_dim).collect();
        let mut cursor = order.len();
        let mut grads = vec![0.0; params.len()];
        for step in 1..=config.steps {
            let (mut xb, mut yb) =
                (Vec::with_capacity(config.batch * width), Vec::with_capacity(config.batch * action_dim));
            for _ in 0..config.batch {
                if cursor == order.len() {
                    order.shuffle(&mut rng);
                    cursor = 0;
                }
                let k = order[cursor];
                cursor += 1;
                xb.extend_from_slice(&train_x[k * width..(k + 1) * width]);
                yb.extend_from_slice(&train_y[k * action_dim..(k + 1) * action_dim]);
            }
            let tape = mlp.forward(&xb, config.batch);
            let scale = 2.0 / yb.len() as f32;
            let d: Vec<f32> = tape.output.iter().zip(&yb).map(|(p, y)| scale * (p - y)).collect();
            let train_mse = tape.output.iter().zip(&yb).map(|(p, y)| (p - y) * (p - y)).sum::<f32>() / yb.len() as f32;
            grads.fill(0.0);
            mlp.backward(&tape, &d, &mut grads);
            // Cosine decay to a tenth: the fit settles instead of hovering at Adam's noise floor.
            let progress = step as f32 / config.steps as f32;
            let lr = config.lr * (0.55 + 0.45 * (std::f32::consts::PI * progress).cos());
            adam.step(&mut params, &grads, lr);
            mlp.set_params(&params);
            if step % 100 == 0 || step == config.steps {
                let validation_mse = (!val_y.is_empty()).then(|| mse(&mlp, &val_x, &val_y, width, action_dim));
                on_progress(&FitProgress { step, train_mse, validation_mse });
            }
        }
        Ok(Self { state_dim, action_dim, mlp, input_norm, output_norm })
    }

    /// The actions for `n` rows of `[s_t, s_{t+1} in frame t]` (physical units).
    pub fn actions(&self, inputs: &[f32], n: usize) -> Vec<f32> {
        let mut x = inputs.to_vec();
        self.input_norm.normalise(&mut x, 0, 2 * self.state_dim);
        let mut y = self.mlp.predict(&x, n);
        self.output_norm.denormalise(&mut y, 0, self.action_dim);
        y
    }

    /// Writes the model to `path` atomically.
    pub fn save(&self, path: &Path) -> Result<(), ModelError> {
        let names: Vec<(String, String)> =
            (0..self.mlp.layers.len()).map(|l| (format!("layer{l}.weight"), format!("layer{l}.bias"))).collect();
        let mut list: Vec<(&str, Vec<usize>, &[f32])> = vec![
            ("input_mean", vec![2 * self.state_dim], &self.input_norm.mean),
            ("input_std", vec![2 * self.state_dim], &self.input_norm.std),
            ("output_mean", vec![self.action_dim], &self.output_norm.mean),
            ("output_std", vec![self.action_dim], &self.output_norm.std),
        ];
        for (layer, (w, b)) in self.mlp.layers.iter().zip(&names) {
            list.push((w, vec![layer.outputs, layer.inputs], &layer.weight));
            list.push((b, vec![layer.outputs], &layer.bias));
        }
        let hidden: Vec<String> = self.mlp.layers[1..].iter().map(|l| l.inputs.to_string()).collect();
        let meta = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("state_dim".to_string(), self.state_dim.to_string()),
            ("action_dim".to_string(), self.action_dim.to_string()),
            ("hidden".to_string(), hidden.join(",")),
        ]);
        Ok(tensors::save(path, &list, meta)?)
    }

    /// Reads a model [`InverseDynamics::save`] wrote, refusing one for other state or action
    /// sizes than `state_dim` and `action_dim`.
    pub fn load(path: &Path, state_dim: usize, action_dim: usize) -> Result<Self, ModelError> {
        let file = TensorFile::open(path)?;
        if file.meta("format")? != FORMAT {
            return Err(file.error(format!("not a {FORMAT} file")).into());
        }
        let number = |key: &str| -> Result<usize, ModelError> {
            let v = file.meta(key)?;
            v.parse().map_err(|_| file.error(format!("metadata '{key}' is '{v}', not a size")).into())
        };
        let (s, a) = (number("state_dim")?, number("action_dim")?);
        if (s, a) != (state_dim, action_dim) {
            return Err(file
                .error(format!(
                    "is for states of {s} and actions of {a}; this humanoid has {state_dim} and {action_dim}"
                ))
                .into());
        }
        let hidden = file.meta("hidden")?;
        let hidden: Vec<usize> = hidden
            .split(',')
            .map(|h| h.parse().map_err(|_| file.error(format!("metadata 'hidden' is '{hidden}', not sizes"))))
            .collect::<Result<_, _>>()?;
        let sizes: Vec<usize> = std::iter::once(2 * s).chain(hidden).chain([a]).collect();
        let mut mlp = Mlp::new(&sizes, 1.0, &mut StdRng::seed_from_u64(0));
        for (l, layer) in mlp.layers.iter_mut().enumerate() {
            layer.weight = file.f32(&format!("layer{l}.weight"), &[layer.outputs, layer.inputs])?;
            layer.bias = file.f32(&format!("layer{l}.bias"), &[layer.outputs])?;
        }
        let model = Self {
            state_dim: s,
            action_dim: a,
            input_norm: Normaliser { mean: file.f32("input_mean", &[2 * s])?, std: file.f32("input_std", &[2 * s])? },
            output_norm: Normaliser { mean: file.f32("output_mean", &[a])?, std: file.f32("output_std", &[a])? },
            mlp,
        };
        let finite =
            model.mlp.params().iter().chain(&model.input_norm.std).chain(&model.output_norm.std).all(|v| v.is_finite());
        if !finite || model.input_norm.std.iter().any(|s| *s <= 0.0) {
            return Err(file.error("weights or statistics contain NaN, infinity or a zero deviation").into());
        }
        Ok(model)
    }
}

/// Mean squared error of `mlp` on standardised rows, in batches.
fn mse(mlp: &Mlp, x: &[f32], y: &[f32], width: usize, action_dim: usize) -> f32 {
    let rows = y.len() / action_dim;
    let mut sum = 0.0f64;
    for start in (0..rows).step_by(4096) {
        let n = (rows - start).min(4096);
        let p = mlp.predict(&x[start * width..(start + n) * width], n);
        sum += p
            .iter()
            .zip(&y[start * action_dim..(start + n) * action_dim])
            .map(|(p, y)| f64::from((p - y) * (p - y)))
            .sum::<f64>();
    }
    (sum / y.len() as f64) as f32
}
