//! Training the trajectory model on a dataset's windows, and the model directory.
//!
//! A model directory holds:
//! - `model.safetensors`: the Transformer's named tensors; metadata `format` =
//!   `flowmimic-model/1` and `model` = JSON of the [`ModelConfig`], [`Objective`], token layout,
//!   training step and the dataset's shard checksums;
//! - `stats.safetensors`: the dataset's window statistics the model normalises with;
//! - `checkpoint.safetensors`: parameters and Adam's moments for `--resume`;
//! - `log.csv`, `config.json` and loss plots (written by the CLI).
//!
//! Both objectives share everything here (network, optimiser, data, batches, budget); only the
//! training batch's noise and target differ.

use crate::inverse::{INVERSE_FILE, InverseDynamics};
use crate::trajectory::{Label, Normaliser, Objective, TaskLabel, TokenLayout, TrajectoryModel};
use crate::{ModelConfig, TrainingBatch, ddpm, fm, meanflow, path};
use flowmimic_data::{DataError, Dataset, Shard, Stats, future_motion, window, window_starts};
use flowmimic_io::tensors::{self, TensorError, TensorFile};
use flowmimic_nn::Adam;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error(transparent)]
    Tensors(#[from] TensorError),
    #[error(transparent)]
    Data(#[from] DataError),
    #[error("{0}")]
    Invalid(String),
}

/// Optimisation settings (a preset's `[train]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Optimiser steps.
    pub steps: usize,
    /// Windows per step.
    pub batch: usize,
    /// Adam's learning rate after warm-up.
    pub lr: f32,
    /// Steps of linear warm-up.
    pub warmup: usize,
    /// What the learning rate does after warm-up: `constant` (the paper) or `cosine` (down to 0
    /// at `steps`; a resumed run with more steps follows the longer curve from where it is).
    pub lr_schedule: LrSchedule,
    /// With `cosine`: the step before which the rate holds, as `constant` would; from it on the
    /// rate follows the whole run's cosine (dropping to its value there). 0: the cosine starts
    /// after warm-up. It equals a constant run resumed at this step with `cosine`, because a
    /// step's batch and noise come from (seed, step).
    pub decay_from: usize,
    /// Global gradient-norm clip.
    pub grad_clip: f32,
    /// Flow Matching's distribution of path times.
    pub fm_time: fm::TimeDistribution,
    /// Flow Matching's ODE solver.
    pub fm_solver: fm::Solver,
    /// MeanFlow's share of training samples with an interval (the rest regress FM's velocity).
    pub meanflow_share: f32,
    /// How MeanFlow's interval targets are made: `derivative` (the MeanFlow identity) or
    /// `split` (two jumps make one; see `meanflow::Consistency`).
    pub meanflow_consistency: meanflow::Consistency,
    /// What Flow Matching's and MeanFlow's network predicts: `velocity` (the paper) or
    /// `sample` (the clean sample, read as a velocity; see `path::Prediction`).
    pub flow_prediction: path::Prediction,
    /// DDPM's training steps T.
    pub ddpm_steps: usize,
    /// What DDPM's network predicts: `sample` (x_0) or `epsilon`.
    pub ddpm_prediction: ddpm::Prediction,
    /// DDPM's clip of clean predictions (in standard deviations of the data).
    pub ddpm_clip: f32,
    /// Share of rollouts held out for validation.
    pub validation_fraction: f64,
    /// Validation windows evaluated (with fixed noise) at each log line.
    pub validation_windows: usize,
    /// Steps between log lines (and validations).
    pub log_every: usize,
    /// Steps between checkpoints.
    pub checkpoint_every: usize,
    /// Seed of the initial weights, the batches and the noise.
    pub seed: u64,
    /// For a model with task labels: the clips (by name, or a name's beginning: `reach_`)
    /// whose windows are labelled `reach`; every other clip's are `walk`.
    pub reach_clips: Vec<String>,
    /// For a labelled model: the share of training windows whose label is left out (all
    /// zeros), so that the model also samples without one.
    pub label_dropout: f32,
}

/// The learning rate after warm-up.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    #[default]
    Constant,
    Cosine,
}

impl TrainConfig {
    /// The learning rate at (0-based) step `step`: linear warm-up, then the schedule.
    pub fn lr_at(&self, step: usize) -> f32 {
        let warm = ((step + 1) as f32 / self.warmup.max(1) as f32).min(1.0);
        let decay = match self.lr_schedule {
            LrSchedule::Constant => 1.0,
            LrSchedule::Cosine if step < self.decay_from => 1.0,
            LrSchedule::Cosine => {
                let span = self.steps.saturating_sub(self.warmup).max(1) as f32;
                let done = (step.saturating_sub(self.warmup) as f32 / span).min(1.0);
                0.5 * (1.0 + (std::f32::consts::PI * done).cos())
            }
        };
        self.lr * warm * decay
    }
}

impl Default for TrainConfig {
    /// The `cpu` preset.
    fn default() -> Self {
        Self {
            steps: 6000,
            batch: 256,
            lr: 1e-3,
            warmup: 500,
            lr_schedule: LrSchedule::Constant,
            decay_from: 0,
            grad_clip: 1.0,
            fm_time: fm::TimeDistribution::Uniform,
            fm_solver: fm::Solver::Euler,
            meanflow_share: 0.5,
            meanflow_consistency: meanflow::Consistency::Derivative,
            flow_prediction: path::Prediction::Velocity,
            ddpm_steps: 100,
            ddpm_prediction: ddpm::Prediction::Sample,
            ddpm_clip: 6.0,
            validation_fraction: 0.05,
            validation_windows: 1024,
            log_every: 50,
            checkpoint_every: 500,
            seed: 0,
            reach_clips: Vec::new(),
            label_dropout: 0.1,
        }
    }
}

impl TrainConfig {
    /// Refuses values training cannot use, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.steps == 0 || self.batch == 0 || self.log_every == 0 || self.checkpoint_every == 0 {
            return Err("train.steps, batch, log_every and checkpoint_every must be positive".into());
        }
        if !(self.lr.is_finite() && self.lr > 0.0 && self.grad_clip.is_finite() && self.grad_clip > 0.0) {
            return Err(format!("train.lr ({}) and grad_clip ({}) must be positive", self.lr, self.grad_clip));
        }
        if self.decay_from > 0 && self.lr_schedule == LrSchedule::Constant {
            return Err(format!("train.decay_from ({}) needs lr_schedule = \"cosine\"", self.decay_from));
        }
        if self.decay_from >= self.steps {
            return Err(format!(
                "train.decay_from ({}) must be below train.steps ({}): the rate would never decay",
                self.decay_from, self.steps
            ));
        }
        if !(0.0..1.0).contains(&self.label_dropout) {
            return Err(format!("train.label_dropout is {}; it must be in [0, 1)", self.label_dropout));
        }
        if !(0.0..1.0).contains(&self.validation_fraction) {
            return Err(format!("train.validation_fraction is {}; it must be in [0, 1)", self.validation_fraction));
        }
        for name in ["fm", "meanflow", "ddpm"] {
            self.objective(name).and_then(|o| o.validate().map_err(ModelError::Invalid)).map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    pub fn objective(&self, name: &str) -> Result<Objective, ModelError> {
        match name {
            "fm" => Ok(Objective::Fm { time: self.fm_time, solver: self.fm_solver, prediction: self.flow_prediction }),
            "meanflow" => Ok(Objective::MeanFlow {
                share: self.meanflow_share,
                prediction: self.flow_prediction,
                consistency: self.meanflow_consistency,
            }),
            "ddpm" => {
                Ok(Objective::Ddpm { steps: self.ddpm_steps, prediction: self.ddpm_prediction, clip: self.ddpm_clip })
            }
            other => Err(ModelError::Invalid(format!("unknown objective '{other}'; choose fm, meanflow or ddpm"))),
        }
    }
}

/// A dataset's windows (interleaved and normalised when a batch takes them), split by rollout
/// into training and validation sets.
pub struct WindowSet {
    pub layout: TokenLayout,
    norm: Normaliser,
    shards: Vec<Shard>,
    /// Each shard's task label.
    labels: Vec<TaskLabel>,
    /// For command labels: the steps ahead whose motion labels a window.
    command_steps: usize,
    /// (shard, current step) of every window, by side of the split.
    train: Vec<(usize, usize)>,
    validation: Vec<(usize, usize)>,
}

impl WindowSet {
    /// Splits the dataset's windows into training and validation. For task labels, labelled
    /// `reach` where their clip's name begins with one of `reach_clips` and `walk` elsewhere;
    /// for command labels, with the motion of the `command_steps` steps after them. Windows are cut from
    /// the shards when a batch asks for them, not stored: at H = 16 three hours of rollouts
    /// would take 6.5 GB as windows, 0.4 GB as shards.
    pub fn from_dataset(
        dataset: &Dataset,
        layout: TokenLayout,
        stats: &Stats,
        validation_fraction: f64,
        reach_clips: &[String],
        command_steps: usize,
    ) -> Result<Self, ModelError> {
        let (mut train, mut validation) = (Vec::new(), Vec::new());
        let (infos, shards): (Vec<_>, Vec<Shard>) = dataset.load_all()?.into_iter().unzip();
        let is_reach = |clip: &str| reach_clips.iter().any(|r| clip.starts_with(r.as_str()));
        let labels: Vec<TaskLabel> =
            infos.iter().map(|i| if is_reach(&i.clip) { TaskLabel::Reach } else { TaskLabel::Walk }).collect();
        if layout.labels == Label::TASK && !labels.contains(&TaskLabel::Reach) {
            return Err(ModelError::Invalid(format!(
                "{}: a model with task labels needs reaching clips, and no clip begins with one of train.reach_clips {reach_clips:?}",
                dataset.dir.display()
            )));
        }
        for (s, shard) in shards.iter().enumerate() {
            for t in window_starts(shard, layout.spec) {
                // A rollout goes wholly to one side, so overlapping windows never straddle it.
                if held_out(s, shard.rollout[t], validation_fraction) { &mut validation } else { &mut train }
                    .push((s, t));
            }
        }
        if train.is_empty() {
            return Err(ModelError::Invalid(format!(
                "{}: no training windows of history {} and horizon {} (episodes too short?)",
                dataset.dir.display(),
                layout.spec.history,
                layout.spec.horizon
            )));
        }
        Ok(Self { norm: Normaliser::new(&layout, stats), layout, shards, labels, command_steps, train, validation })
    }

    pub fn train_len(&self) -> usize {
        self.train.len()
    }

    pub fn validation_len(&self) -> usize {
        self.validation.len()
    }

    /// How many shards are labelled `reach`, and their share of the training windows.
    pub fn reach(&self) -> (usize, f64) {
        let is_reach = |&(s, _): &(usize, usize)| self.labels[s] == TaskLabel::Reach;
        let windows = self.train.iter().filter(|w| is_reach(w)).count();
        (self.labels.iter().filter(|&&l| l == TaskLabel::Reach).count(), windows as f64 / self.train.len() as f64)
    }

    /// The normalised, interleaved windows `rows` of a side, one after another.
    fn windows(&self, side: &[(usize, usize)], rows: &[usize]) -> Vec<f32> {
        let w = self.layout.window_len();
        let mut out = Vec::with_capacity(rows.len() * w);
        for &r in rows {
            let (s, t) = side[r];
            let win = window(&self.shards[s], self.layout.spec, t);
            let label = match self.layout.labels {
                Label::COMMAND => Label::Command(
                    future_motion(&self.shards[s], t, self.command_steps).expect("a window's horizon lies ahead"),
                ),
                _ => Label::Task(self.labels[s]),
            };
            let mut row = self.layout.window(&win.states, &win.actions, Some(label));
            self.norm.normalise(&mut row, 0, w);
            out.extend(row);
        }
        out
    }
}

/// A well-mixed 64-bit hash (SplitMix64's finaliser).
fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The model, its optimiser and where training stands.
pub struct Trainer {
    pub model: TrajectoryModel,
    pub config: TrainConfig,
    pub adam: Adam,
    pub step: usize,
    /// Checksums of the dataset's shards (a resume must see the same data).
    pub dataset_key: String,
    data: WindowSet,
}

const FORMAT: &str = "flowmimic-model/1";
pub const MODEL_FILE: &str = "model.safetensors";
pub const STATS_FILE: &str = "stats.safetensors";
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";

/// What `model.safetensors` records besides the weights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct ModelMeta {
    config: ModelConfig,
    objective: Objective,
    layout: TokenLayout,
    step: usize,
    dataset: String,
    /// The run's `[train]` settings (absent in files written before they were recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    train: Option<TrainConfig>,
}

impl ModelMeta {
    /// The metadata of a model or checkpoint file, every value checked.
    fn read(file: &TensorFile) -> Result<Self, ModelError> {
        let bad = |e: serde_json::Error| file.error(format!("metadata 'model': {e}"));
        let mut json: serde_json::Value = serde_json::from_str(file.meta("model")?).map_err(bad)?;
        // Models written before the pairing was a choice paired each state with its action.
        if let Some(config) = json.get_mut("config").and_then(|c| c.as_object_mut()) {
            config.entry("pairing").or_insert_with(|| "state-action".into());
        }
        let meta: ModelMeta = serde_json::from_value(json).map_err(bad)?;
        meta.config.validate().and_then(|()| meta.objective.validate()).map_err(|e| file.error(e))?;
        let expected = TokenLayout { spec: meta.config.spec(), labels: meta.config.labels(), ..meta.layout };
        let sizes = (1..=4096).contains(&meta.layout.state_dim) && (1..=4096).contains(&meta.layout.action_dim);
        if meta.layout != expected || !sizes {
            let message = format!("the token layout {:?} does not fit the model's window", meta.layout);
            return Err(file.error(message).into());
        }
        Ok(meta)
    }
}

impl Trainer {
    /// Training of `model` (fresh: [`TrajectoryModel::new`]) on the windows of the dataset
    /// whose shard checksums are `dataset_key`.
    pub fn new(model: TrajectoryModel, train: TrainConfig, data: WindowSet, dataset_key: String) -> Self {
        let adam = Adam::new(model.net.net.num_params());
        Self { model, config: train, adam, step: 0, dataset_key, data }
    }

    /// Continues from `dir`'s checkpoint; refuses a checkpoint of another model, objective or
    /// dataset.
    pub fn resume(dir: &Path, fresh: Trainer) -> Result<Self, ModelError> {
        let file = TensorFile::open(&dir.join(CHECKPOINT_FILE))?;
        let meta = ModelMeta::read(&file)?;
        let mut t = fresh;
        let ours = t.meta();
        let differs = |what: &str, a: String, b: String| {
            file.error(format!("was trained with {what} {a}, this run asks for {b}; use another output directory"))
        };
        if meta.config != ours.config || meta.layout != ours.layout {
            return Err(differs("model", format!("{:?}", meta.config), format!("{:?}", ours.config)).into());
        }
        if meta.objective != ours.objective {
            let describe = |o: &Objective| format!("{} ({o:?})", o.name());
            return Err(differs("objective", describe(&meta.objective), describe(&ours.objective)).into());
        }
        if meta.dataset != ours.dataset {
            return Err(file.error("was trained on another dataset (shard checksums differ)").into());
        }
        if let Some(saved) = &meta.train {
            let changed = changed_train_keys(saved, &t.config);
            if !changed.is_empty() {
                let message =
                    format!("was trained with other settings: {}; use another output directory", changed.join(", "));
                return Err(file.error(message).into());
            }
        }
        let n = t.model.net.net.num_params();
        t.model.net.net.params = file.f32("params", &[n])?;
        t.adam.m = file.f32("adam_m", &[n])?;
        t.adam.v = file.f32("adam_v", &[n])?;
        t.adam.t = meta.step as u64;
        t.step = meta.step;
        Ok(t)
    }

    fn meta(&self) -> ModelMeta {
        ModelMeta {
            config: self.model.config,
            objective: self.model.objective,
            layout: *self.model.layout(),
            step: self.step,
            dataset: self.dataset_key.clone(),
            train: Some(self.config.clone()),
        }
    }

    /// Learning rate at the current step.
    pub fn lr(&self) -> f32 {
        self.config.lr_at(self.step)
    }

    /// Conditioning and clean futures of consecutive windows.
    fn split(&self, windows: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let layout = self.model.layout();
        let (w, c) = (layout.window_len(), layout.cond_len());
        let (mut cond, mut future) = (Vec::new(), Vec::new());
        for row in windows.chunks_exact(w) {
            cond.extend_from_slice(&row[..c]);
            future.extend_from_slice(&row[c..]);
        }
        (cond, future)
    }

    fn training_batch(&self, clean: &[f32], cond: &[f32], rng: &mut StdRng) -> TrainingBatch {
        let dim = self.model.layout().future_len();
        let batch = match self.model.objective {
            Objective::Fm { time, .. } => fm::training_batch(clean, dim, time, rng),
            // The target reads the network as the velocity it stands for.
            Objective::MeanFlow { share, consistency, .. } => self
                .model
                .with_flow_net(|net| meanflow::training_batch(net, cond, clean, dim, (share, consistency), rng)),
            Objective::Ddpm { steps, prediction, .. } => {
                ddpm::training_batch(&ddpm::Schedule::cosine(steps), prediction, clean, dim, rng)
            }
        };
        if self.model.objective.predicts_clean_flow() { path::clean_sample_target(batch, dim) } else { batch }
    }

    /// Mean squared error of the prediction on `rows` of a side, and the parameter gradient
    /// when asked.
    fn loss(&self, side: &[(usize, usize)], rows: &[usize], rng: &mut StdRng, grads: bool) -> (f32, Option<Vec<f32>>) {
        let net = &self.model.net;
        let (mut cond, clean) = self.split(&self.data.windows(side, rows));
        let layout = self.model.layout();
        if grads && layout.labels > 0 {
            for row in cond.chunks_exact_mut(layout.cond_len()) {
                if rng.random::<f32>() < self.config.label_dropout {
                    row[layout.label_range()].fill(0.0);
                }
            }
        }
        let batch = self.training_batch(&clean, &cond, rng);
        let n = rows.len();
        let tape = net.forward(&batch.x, &batch.t, &cond, n);
        let pred = net.future(&tape.output);
        let count = pred.len() as f32;
        let loss = pred.iter().zip(&batch.target).map(|(p, t)| (p - t) * (p - t)).sum::<f32>() / count;
        let grads = grads.then(|| {
            // d loss / d output: zero on the conditioning tokens' entries and the padding.
            let d_future: Vec<f32> = pred.iter().zip(&batch.target).map(|(p, t)| 2.0 * (p - t) / count).collect();
            let d = net.output_cotangent(&d_future, n);
            let mut g = vec![0.0; net.net.num_params()];
            net.net.backward(&tape, &d, &mut g);
            g
        });
        (loss, grads)
    }

    /// One optimiser step on a random batch; returns the batch loss. Each step's randomness
    /// comes from (seed, step), so a resumed run continues exactly as an uninterrupted one.
    pub fn train_step(&mut self) -> Result<f32, ModelError> {
        let mut rng = StdRng::seed_from_u64(self.config.seed ^ (self.step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let rows: Vec<usize> = (0..self.config.batch).map(|_| rng.random_range(0..self.data.train_len())).collect();
        let (loss, grads) = self.loss(&self.data.train, &rows, &mut rng, true);
        let mut grads = grads.expect("asked for gradients");
        if !loss.is_finite() {
            return Err(ModelError::Invalid(format!("training loss is {loss} at step {}", self.step)));
        }
        let norm = grads.iter().map(|g| g * g).sum::<f32>().sqrt();
        if norm > self.config.grad_clip {
            grads.iter_mut().for_each(|g| *g *= self.config.grad_clip / norm);
        }
        let lr = self.lr();
        self.adam.step(&mut self.model.net.net.params, &grads, lr);
        self.step += 1;
        Ok(loss)
    }

    /// Loss on (up to `validation_windows`) held-out windows spread evenly over the held-out
    /// set, with fixed noise, comparable across steps; `None` without a validation set.
    pub fn validation_loss(&self) -> Option<f32> {
        let len = self.data.validation_len();
        let n = len.min(self.config.validation_windows);
        if n == 0 {
            return None;
        }
        let mut rng = StdRng::seed_from_u64(self.config.seed.wrapping_add(1));
        let chunk = 256;
        // Spread over every held-out rollout: the first windows alone are one rollout of one clip.
        let rows: Vec<usize> = (0..n).map(|i| i * len / n).collect();
        let total: f32 =
            rows.chunks(chunk).map(|r| self.loss(&self.data.validation, r, &mut rng, false).0 * r.len() as f32).sum();
        Some(total / n as f32)
    }

    /// Writes the model, its statistics and the checkpoint into `dir`, atomically each.
    pub fn save(&self, dir: &Path) -> Result<(), ModelError> {
        let meta = serde_json::to_string(&self.meta()).expect("serialisable");
        let net = &self.model.net.net;
        let tensors: Vec<(&str, Vec<usize>, &[f32])> = net
            .tensors()
            .iter()
            .map(|s| (s.name.as_str(), s.shape.clone(), &net.params[s.at..s.at + s.len()]))
            .collect();
        let info = HashMap::from([("format".to_string(), FORMAT.to_string()), ("model".to_string(), meta.clone())]);
        tensors::save(&dir.join(MODEL_FILE), &tensors, info.clone())?;
        self.model.stats.save(&dir.join(STATS_FILE), &self.dataset_key)?;
        let n = vec![net.num_params()];
        let state =
            [("params", n.clone(), &net.params[..]), ("adam_m", n.clone(), &self.adam.m), ("adam_v", n, &self.adam.v)];
        tensors::save(&dir.join(CHECKPOINT_FILE), &state, info)?;
        Ok(())
    }
}

/// The `[train]` keys whose values differ between a checkpoint's run and this one, as
/// `train.KEY SAVED (now NEW)`; a resumed run may change only its length and how often it logs,
/// validates and checkpoints.
fn changed_train_keys(saved: &TrainConfig, ours: &TrainConfig) -> Vec<String> {
    let free = ["steps", "log_every", "checkpoint_every", "validation_windows"];
    // Through text, so that an f32 reads as written (0.001, not 0.0010000000474974513).
    let table = |c: &TrainConfig| -> serde_json::Map<String, serde_json::Value> {
        serde_json::from_str(&serde_json::to_string(c).expect("serialisable")).expect("a table")
    };
    let (a, b) = (table(saved), table(ours));
    a.iter()
        .filter(|(k, v)| !free.contains(&k.as_str()) && b.get(k.as_str()) != Some(v))
        .map(|(k, v)| format!("train.{k} {v} (now {})", b.get(k.as_str()).unwrap_or(&serde_json::Value::Null)))
        .collect()
}

/// Whether rollout `rollout` of shard `s` is held out for validation: a fixed hash of both,
/// so the split is the same on every run.
pub(crate) fn held_out(s: usize, rollout: u32, fraction: f64) -> bool {
    let key = splitmix((s as u64) << 32 | u64::from(rollout));
    ((key >> 11) as f64 / (1u64 << 53) as f64) < fraction
}

impl TrajectoryModel {
    /// Loads a model directory written by [`Trainer::save`].
    pub fn load(dir: &Path) -> Result<Self, ModelError> {
        let file = TensorFile::open(&dir.join(MODEL_FILE))?;
        if file.meta("format")? != FORMAT {
            return Err(file.error(format!("not a {FORMAT} file")).into());
        }
        let meta = ModelMeta::read(&file)?;
        let (stats, _) = Stats::load(&dir.join(STATS_FILE))?;
        if stats.spec != meta.layout.spec {
            return Err(ModelError::Invalid(format!(
                "{}: statistics are for {:?}, the model for {:?}",
                dir.display(),
                stats.spec,
                meta.layout.spec
            )));
        }
        let mut model = Self::new(meta.layout, meta.config, meta.objective, stats, 0);
        let net = &mut model.net.net;
        for slot in net.tensors().to_vec() {
            let values = file.f32(&slot.name, &slot.shape)?;
            net.params[slot.at..slot.at + slot.len()].copy_from_slice(&values);
        }
        if net.params.iter().any(|p| !p.is_finite()) {
            return Err(file.error("weights contain NaN or infinity").into());
        }
        let inverse = dir.join(INVERSE_FILE);
        if inverse.exists() {
            let layout = model.layout();
            model.inverse = Some(InverseDynamics::load(&inverse, layout.state_dim, layout.action_dim)?);
        }
        Ok(model)
    }

    /// Refuses a model whose state, action or window sizes differ from `layout`'s.
    pub fn check_layout(&self, layout: &TokenLayout, what: &str) -> Result<(), ModelError> {
        let ours = self.layout();
        if ours.state_dim != layout.state_dim || ours.action_dim != layout.action_dim || ours.spec != layout.spec {
            return Err(ModelError::Invalid(format!(
                "the model has states of {}, actions of {}, history {} and horizon {}; {what} has {}, {}, {} and {}",
                ours.state_dim,
                ours.action_dim,
                ours.spec.history,
                ours.spec.horizon,
                layout.state_dim,
                layout.action_dim,
                layout.spec.history,
                layout.spec.horizon
            )));
        }
        Ok(())
    }
}
