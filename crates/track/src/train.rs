//! The training loop: collection on all cores, PPO updates, logs, atomic checkpoints, resume,
//! and evaluation of tracking quality.

use crate::TrackError;
use crate::ppo::{self, Normaliser, Optimiser, Policy, RolloutBuffer, UpdateStats};
use crate::task::{self, Ending, Reference, RewardConfig, RewardTerms, Tracker};
use flowmimic_io::le;
use flowmimic_motion::coverage::walking_velocities;
use flowmimic_motion::{Clip, Coverage};
use flowmimic_nn::Adam;
use flowmimic_sim::{CONTROL_HZ, Humanoid, NUM_DOFS};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// PPO and task settings (defaults: BeyondMimic's recipe at CPU scale).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackConfig {
    /// Parallel environments.
    pub envs: usize,
    /// Control steps per environment per iteration.
    pub horizon: usize,
    /// Training iterations.
    pub iterations: usize,
    /// Hidden layer widths of actor and critic (ELU).
    pub hidden: Vec<usize>,
    /// Adam's initial learning rate; the adaptive-KL rule then moves it within 1e-5 to 1e-2.
    pub learning_rate: f64,
    /// The KL divergence (nats, summed over the action's dimensions) from the acting policy that
    /// the learning rate aims at: above twice it the rate falls by 1.5, below half it rises.
    pub kl_target: f64,
    /// PPO's clip on the probability ratio, and on the value's change (in return units).
    pub clip: f64,
    /// Entropy bonus per nat of the policy's entropy.
    pub entropy: f64,
    /// The value loss's weight beside the surrogate.
    pub value_coef: f64,
    /// Discount per control step, and GAE's lambda.
    pub gamma: f64,
    pub lambda: f64,
    /// Passes over each iteration's steps, and minibatches per pass.
    pub epochs: usize,
    pub minibatches: usize,
    /// Largest norm of the whole gradient; larger ones are scaled down to it.
    pub max_grad_norm: f64,
    /// Initial log standard deviation of the policy (in units of `action_scale`).
    pub init_log_std: f64,
    /// Radians of PD-target residual per unit of policy output.
    pub action_scale: f64,
    /// Uniform noise on hinge angles (rad) and root velocity (m/s) at reset.
    pub init_noise: f64,
    /// Largest standard deviation of Gaussian noise on the executed action, in policy output
    /// units (`action_scale` rad; 0 disables it): each episode draws its own from 0 to this. The
    /// data's rollouts execute noisy actions (a collection sigma is `sigma * noise_unit_rad /
    /// action_scale` of these units: 0.43 at sigma 0.16), so the experts practise them.
    pub action_noise: f64,
    /// Largest random push, m/s (0 disables pushes).
    pub push_max: f64,
    /// Seconds between pushes, drawn uniformly.
    pub push_interval: [f64; 2],
    /// Termination: pelvis or end-effector height error, m.
    pub max_height_error: f64,
    /// Termination: difference of gravity's z in the pelvis frame (-1 to 1: 0.8 is about 53
    /// degrees of tilt off the reference's).
    pub max_tilt_error: f64,
    /// Adaptive start sampling: bin length (s), the smoothing of each bin's failure count per
    /// iteration (0-1), and the share of starts drawn evenly (0-1).
    pub bin_seconds: f64,
    pub bin_smoothing: f64,
    pub uniform_share: f64,
    /// Adaptive start sampling: how far before a failure its credit reaches (s), and the
    /// credit's decay per bin back from the failing one (0-1; BeyondMimic's kernel). A fall
    /// that follows seconds of drift is practised only if starts land where the drift begins.
    pub failure_lookback_seconds: f64,
    pub failure_decay: f64,
    /// With several clips: the share of resets that pick a clip in proportion to its length;
    /// the rest pick one evenly. Long clips get practice in proportion to their motion, short
    /// ones keep a floor.
    pub clip_length_share: f64,
    /// With several clips: the share of resets that pick a clip in proportion to its recent
    /// failures (the smoothed counts of the start sampler), before the length and even draws
    /// share the rest: clips that fail get practice, however short.
    pub clip_failure_share: f64,
    /// The share of resets that start at the clip's first frame instead of an adaptively drawn
    /// one. Adaptive starts credit a failure to the frames where it happens, so a fall that
    /// follows seconds of drift is practised from a fresh start there, without the drift;
    /// episodes from the first frame carry it, as `track eval` does.
    pub first_frame_share: f64,
    /// Whether a new policy also observes the reference 1/3 s and 1 s ahead
    /// ([`crate::task::AHEAD_FRAMES`]), not only its next frame. A policy started (`--init`) from
    /// one that does not gets the new inputs with zero weights, so it acts as before until PPO
    /// moves them. A trained policy's width says which it is wherever it is loaded.
    pub observe_ahead: bool,
    /// A policy started (`--init`) on another kind of reference (the plans' clips of `track
    /// plan-clips`) starts from a zero residual: its output layer zeroed, so that it first
    /// executes the reference's hinges as they are; its log-std raised to at least
    /// `init_log_std` and the configured learning rate, so that it explores again; and its
    /// observation statistics weighted as [`FRESH_OBSERVATIONS`] steps, so that they move to
    /// the new references within tens of iterations instead of never.
    pub fresh_output: bool,
    /// Seed of the policy's initial weights, the episodes' draws and the action noise.
    pub seed: u64,
    /// Iterations between checkpoints.
    pub checkpoint_every: usize,
    /// The reward's weights and widths (`[track.reward]`).
    pub reward: RewardConfig,
}

impl Default for TrackConfig {
    fn default() -> Self {
        Self {
            envs: 64,
            horizon: 32,
            iterations: 1500,
            hidden: vec![256, 128, 64],
            learning_rate: 1e-3,
            // BeyondMimic's 0.01 is for the G1's 29 actions; the KL sums over dimensions, so
            // the same trust region per dimension is about 0.02 for our 69.
            kl_target: 0.02,
            clip: 0.2,
            entropy: 0.005,
            value_coef: 1.0,
            gamma: 0.99,
            lambda: 0.95,
            epochs: 5,
            minibatches: 4,
            max_grad_norm: 1.0,
            init_log_std: -0.5,
            action_scale: 0.15,
            init_noise: 0.05,
            action_noise: 0.0,
            push_max: 0.5,
            push_interval: [1.0, 3.0],
            max_height_error: 0.25,
            max_tilt_error: 0.8,
            bin_seconds: 1.0,
            bin_smoothing: 0.1,
            uniform_share: 0.3,
            failure_lookback_seconds: 1.0,
            failure_decay: 0.5,
            clip_length_share: 0.5,
            clip_failure_share: 0.0,
            first_frame_share: 0.0,
            observe_ahead: false,
            fresh_output: false,
            seed: 0,
            checkpoint_every: 25,
            reward: RewardConfig::default(),
        }
    }
}

impl TrackConfig {
    pub fn validate(&self) -> Result<(), TrackError> {
        let bad = |m: &str| Err(TrackError::Invalid(format!("track: {m}")));
        if self.envs == 0 || self.horizon == 0 || self.epochs == 0 || self.minibatches == 0 {
            return bad("envs, horizon, epochs and minibatches must be positive");
        }
        if self.envs * self.horizon < self.minibatches {
            return bad("envs * horizon must be at least the number of minibatches");
        }
        if self.hidden.is_empty() || self.hidden.iter().any(|&h| !(1..=65536).contains(&h)) || self.hidden.len() > 16 {
            return bad("hidden must list 1-16 layer widths of 1-65536");
        }
        if self.envs > 100_000 || self.horizon > 100_000 {
            return bad("envs and horizon must be at most 100000");
        }
        let positive =
            [self.learning_rate, self.kl_target, self.clip, self.max_grad_norm, self.action_scale, self.bin_seconds];
        if positive.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return bad("learning_rate, kl_target, clip, max_grad_norm, action_scale and bin_seconds must be positive");
        }
        let unit = [
            self.gamma,
            self.lambda,
            self.bin_smoothing,
            self.uniform_share,
            self.clip_length_share,
            self.clip_failure_share,
            self.first_frame_share,
            self.failure_decay,
        ];
        if unit.iter().any(|v| !(0.0..=1.0).contains(v)) {
            return bad("gamma, lambda, bin_smoothing, uniform_share, clip_length_share, clip_failure_share, \
                 first_frame_share and failure_decay must be in [0, 1]");
        }
        let rest = [
            self.entropy,
            self.value_coef,
            self.init_noise,
            self.action_noise,
            self.push_max,
            self.max_height_error,
            self.max_tilt_error,
            self.failure_lookback_seconds,
        ];
        if rest.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || !self.init_log_std.is_finite() {
            return bad(
                "entropy, value_coef, init_noise, action_noise, push_max, failure_lookback_seconds and the termination \
                 limits must be finite and not negative",
            );
        }
        if !(self.push_interval[0] > 0.0
            && self.push_interval[0] <= self.push_interval[1]
            && self.push_interval[1].is_finite())
        {
            return bad("push_interval must be [a, b] with 0 < a <= b");
        }
        let r = &self.reward;
        let kernels = [r.anchor_pos, r.anchor_rot, r.body_pos, r.body_rot, r.body_lin_vel, r.body_ang_vel, r.root_vel];
        let mut weights = kernels.iter().map(|k| k.weight).chain([r.action_rate, r.joint_limit]);
        if kernels.iter().any(|k| !(k.sigma.is_finite() && k.sigma > 0.0))
            || weights.any(|w| !(w.is_finite() && w >= 0.0))
        {
            return bad("reward: every sigma must be positive, every weight finite and not negative");
        }
        Ok(())
    }
}

/// Start-frame sampling weighted by where episodes fail (BeyondMimic's adaptive sampling).
#[derive(Clone, Debug)]
pub struct StartSampler {
    bin_frames: usize,
    frames: usize,
    /// The credit a failure gives its own bin and each one before it (1, decay, decay^2, ...).
    credit: Vec<f64>,
    /// Smoothed failure counts per bin.
    pub failures: Vec<f64>,
    pending: Vec<f64>,
}

impl StartSampler {
    fn new(frames: usize, cfg: &TrackConfig) -> Self {
        let bin_frames = ((cfg.bin_seconds * CONTROL_HZ) as usize).max(1);
        // The last frame cannot start an episode (there is no next reference frame).
        let bins = (frames - 1).div_ceil(bin_frames);
        let lookback = (cfg.failure_lookback_seconds / cfg.bin_seconds).round() as usize;
        let credit = (0..=lookback).map(|k| cfg.failure_decay.powi(k as i32)).collect();
        Self { bin_frames, frames, credit, failures: vec![0.0; bins], pending: vec![0.0; bins] }
    }

    fn record_failure(&mut self, frame: usize) {
        let b = (frame / self.bin_frames).min(self.pending.len() - 1);
        for (k, c) in self.credit.iter().enumerate().take(b + 1) {
            self.pending[b - k] += c;
        }
    }

    fn end_iteration(&mut self, cfg: &TrackConfig) {
        for (f, p) in self.failures.iter_mut().zip(&mut self.pending) {
            *f = (1.0 - cfg.bin_smoothing) * *f + cfg.bin_smoothing * *p;
            *p = 0.0;
        }
    }

    fn sample(&self, cfg: &TrackConfig, rng: &mut impl Rng) -> usize {
        let bins = self.failures.len();
        let total: f64 = self.failures.iter().sum();
        let weight = |b: usize| {
            let fail = if total > 0.0 { self.failures[b] / total } else { 1.0 / bins as f64 };
            (1.0 - cfg.uniform_share) * fail + cfg.uniform_share / bins as f64
        };
        let mut x = rng.random::<f64>();
        let mut bin = bins - 1;
        for b in 0..bins {
            x -= weight(b);
            if x <= 0.0 {
                bin = b;
                break;
            }
        }
        let lo = bin * self.bin_frames;
        let hi = ((bin + 1) * self.bin_frames).min(self.frames - 1);
        rng.random_range(lo..hi.max(lo + 1))
    }
}

/// What one iteration did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct IterationLog {
    pub iteration: usize,
    pub env_steps: u64,
    pub mean_reward: f32,
    /// Each reward term's mean over the iteration's steps (a kernel before its weight, a
    /// penalty with it).
    pub rewards: RewardTerms,
    pub episodes: usize,
    pub failures: usize,
    /// Mean length of the episodes that ended this iteration, in control steps.
    pub episode_length: f32,
    /// Mean root-relative body position error, m.
    pub body_pos_error: f32,
    /// Losses and diagnostics of the PPO update.
    pub update: UpdateStats,
    pub physics_seconds: f32,
    pub network_seconds: f32,
    pub update_seconds: f32,
    pub steps_per_second: f32,
    /// The same per clip, in training order, so that one failing clip cannot hide behind the
    /// average.
    pub clips: Vec<ClipLog>,
}

/// One clip's share of an iteration.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ClipLog {
    pub steps: usize,
    pub episodes: usize,
    pub failures: usize,
    /// Mean root-relative body position error over the clip's steps, m.
    pub body_pos_error: f32,
}

impl ClipLog {
    /// Adds another stretch of the same clip's training (the error weighted by steps).
    pub fn merge(&mut self, other: &ClipLog) {
        let steps = self.steps + other.steps;
        let weighted = self.body_pos_error * self.steps as f32 + other.body_pos_error * other.steps as f32;
        self.body_pos_error = weighted / steps.max(1) as f32;
        self.steps = steps;
        self.episodes += other.episodes;
        self.failures += other.failures;
    }

    /// Failures per minute of tracked motion (0 when nothing fails).
    pub fn failures_per_minute(&self) -> f32 {
        self.failures as f32 / (self.steps.max(1) as f32 / (60.0 * flowmimic_sim::CONTROL_HZ as f32))
    }
}

impl IterationLog {
    /// log.csv's columns, named: the header and the rows come from this one list. The reward
    /// terms come last, so that logs written before them keep their columns' places.
    fn columns(&self) -> Vec<(String, String)> {
        let mut columns: Vec<(String, String)> = [
            ("iteration", self.iteration.to_string()),
            ("env_steps", self.env_steps.to_string()),
            ("mean_reward", format!("{:.4}", self.mean_reward)),
            ("episodes", self.episodes.to_string()),
            ("failures", self.failures.to_string()),
            ("episode_length", format!("{:.1}", self.episode_length)),
            ("body_pos_error", format!("{:.4}", self.body_pos_error)),
            ("surrogate", format!("{:.5}", self.update.surrogate)),
            ("value_loss", format!("{:.5}", self.update.value_loss)),
            ("entropy", format!("{:.3}", self.update.entropy)),
            ("kl", format!("{:.5}", self.update.kl)),
            ("clip_fraction", format!("{:.3}", self.update.clip_fraction)),
            ("learning_rate", format!("{:.2e}", self.update.learning_rate)),
            ("physics_seconds", format!("{:.3}", self.physics_seconds)),
            ("network_seconds", format!("{:.3}", self.network_seconds)),
            ("update_seconds", format!("{:.3}", self.update_seconds)),
            ("steps_per_second", format!("{:.0}", self.steps_per_second)),
        ]
        .into_iter()
        .map(|(name, value)| (name.to_string(), value))
        .collect();
        columns.extend(self.rewards.named().map(|(name, value)| (format!("reward_{name}"), format!("{value:.4}"))));
        columns
    }

    /// log.csv's header line.
    pub fn csv_header() -> String {
        Self::default().columns().into_iter().map(|(name, _)| name).collect::<Vec<_>>().join(",")
    }

    /// One row of log.csv.
    pub fn csv_row(&self) -> String {
        self.columns().into_iter().map(|(_, value)| value).collect::<Vec<_>>().join(",")
    }
}

/// A PPO run: one reference-conditioned policy tracking one clip (the paper's per-clip experts)
/// or several (each episode draws its clip: see [`TrackConfig::clip_length_share`]).
pub struct Trainer {
    pub cfg: TrackConfig,
    pub references: Vec<Arc<Reference>>,
    pub policy: Policy,
    opt: Optimiser,
    trackers: Vec<Tracker>,
    rngs: Vec<StdRng>,
    rng: StdRng,
    /// One adaptive start sampler per clip.
    samplers: Vec<StartSampler>,
    pub iteration: usize,
    pub env_steps: u64,
    episode_steps: Vec<usize>,
    /// The clip each environment's episode tracks.
    env_clips: Vec<usize>,
}

impl Trainer {
    pub fn new(humanoid: &Arc<Humanoid>, clips: Vec<Clip>, cfg: TrackConfig) -> Result<Self, TrackError> {
        cfg.validate()?;
        if clips.is_empty() {
            return Err(TrackError::Invalid("no clips to track".into()));
        }
        if let Some(clip) = clips.iter().find(|c| c.len() < 3) {
            return Err(TrackError::Invalid(format!(
                "clip {} has {} frames; tracking needs 3 or more",
                clip.name,
                clip.len()
            )));
        }
        let mut rng = StdRng::seed_from_u64(cfg.seed);
        let policy = Policy::new(task::obs_dim(cfg.observe_ahead), NUM_DOFS, &cfg, &mut rng);
        let opt = Optimiser { adam: Adam::new(policy.num_params()), lr: cfg.learning_rate as f32 };
        let references: Vec<Arc<Reference>> = clips.into_iter().map(|c| Arc::new(Reference::new(c))).collect();
        let samplers = references.iter().map(|r| StartSampler::new(r.len(), &cfg)).collect();
        let rngs = (0..cfg.envs)
            .map(|i| StdRng::seed_from_u64(cfg.seed.wrapping_mul(1_000_003).wrapping_add(i as u64 + 1)))
            .collect();
        let trackers = (0..cfg.envs).map(|_| Tracker::new(humanoid)).collect();
        let mut trainer = Self {
            episode_steps: vec![0; cfg.envs],
            env_clips: vec![0; cfg.envs],
            cfg,
            references,
            policy,
            opt,
            trackers,
            rngs,
            rng,
            samplers,
            iteration: 0,
            env_steps: 0,
        };
        trainer.reset_all()?;
        Ok(trainer)
    }

    /// The clip environment `i` tracks.
    fn clip_of(&self, i: usize) -> usize {
        self.env_clips[i]
    }

    fn reset_env(&mut self, i: usize) -> Result<(), TrackError> {
        // Drawn only when asked for, so that runs without it keep their random stream.
        let by_failures = self.cfg.clip_failure_share > 0.0 && self.rng.random::<f64>() < self.cfg.clip_failure_share;
        let c = if by_failures {
            let failures: Vec<f64> = self.samplers.iter().map(|s| s.failures.iter().sum()).collect();
            draw_weighted(&failures, &mut self.rng).unwrap_or_else(|| self.rng.random_range(0..failures.len()))
        } else {
            let lengths: Vec<usize> = self.references.iter().map(|r| r.len()).collect();
            draw_clip(&lengths, self.cfg.clip_length_share, &mut self.rng)
        };
        self.env_clips[i] = c;
        // Drawn only when asked for, so that runs without it keep their random stream.
        let first = self.cfg.first_frame_share > 0.0 && self.rng.random::<f64>() < self.cfg.first_frame_share;
        let start = if first { 0 } else { self.samplers[c].sample(&self.cfg, &mut self.rng) };
        self.trackers[i].reset(&self.references[c], start, &self.cfg, &mut self.rngs[i])?;
        Ok(())
    }

    fn reset_all(&mut self) -> Result<(), TrackError> {
        for i in 0..self.trackers.len() {
            self.reset_env(i)?;
            self.episode_steps[i] = 0;
        }
        Ok(())
    }

    fn observe_all(&self, out: &mut [f32]) {
        let (refs, clips) = (&self.references, &self.env_clips);
        self.trackers
            .par_iter()
            .zip(out.par_chunks_mut(self.policy.obs_dim()))
            .zip(clips)
            .for_each(|((t, o), &c)| t.observe(&refs[c], o));
    }

    /// One iteration: collect `envs x horizon` steps, then update.
    pub fn iterate(&mut self) -> Result<IterationLog, TrackError> {
        let (e, horizon) = (self.cfg.envs, self.cfg.horizon);
        let gamma = self.cfg.gamma as f32;
        let mut rollout = RolloutBuffer {
            envs: e,
            obs: Vec::with_capacity(e * horizon * self.policy.obs_dim()),
            actions: Vec::with_capacity(e * horizon * NUM_DOFS),
            log_probs: Vec::new(),
            means: Vec::with_capacity(e * horizon * NUM_DOFS),
            log_std: self.policy.log_std.clone(),
            values: Vec::new(),
            rewards: Vec::new(),
            dones: Vec::new(),
            last_values: Vec::new(),
        };
        let mut log = IterationLog {
            iteration: self.iteration + 1,
            clips: vec![ClipLog::default(); self.references.len()],
            ..Default::default()
        };
        let (mut physics, mut network) = (0.0f64, 0.0f64);
        let (mut reward_sum, mut error_sum, mut ended_lengths) = (0.0f64, 0.0f64, 0usize);
        let mut term_means = RewardTerms::default();
        let step_weight = 1.0 / (e * horizon) as f32;
        let mut raw = vec![0.0f32; e * self.policy.obs_dim()];
        self.observe_all(&mut raw);
        let started = Instant::now();
        for _ in 0..horizon {
            let t0 = Instant::now();
            self.policy.normaliser.update(&raw);
            let obs = self.policy.normalise(&raw);
            let ppo::Sampled { actions, means, log_probs, values } = ppo::sample(&self.policy, &obs, e, &mut self.rng);
            network += t0.elapsed().as_secs_f64();
            let t1 = Instant::now();
            let (refs, clips, cfg) = (&self.references, &self.env_clips, &self.cfg);
            let results: Vec<(RewardTerms, Ending)> = self
                .trackers
                .par_iter_mut()
                .zip(self.rngs.par_iter_mut())
                .zip(actions.par_chunks(NUM_DOFS))
                .enumerate()
                .map(|(i, ((tracker, rng), u))| tracker.step(&refs[clips[i]], u, cfg, rng))
                .collect();
            for (i, (terms, ending)) in results.iter().enumerate() {
                let total = terms.total(&self.cfg.reward);
                if !total.is_finite() {
                    return Err(TrackError::NonFinite {
                        iteration: log.iteration,
                        what: format!("reward of env {i} is {total}: {terms:?}"),
                    });
                }
                reward_sum += f64::from(total);
                term_means.add_weighted(terms, step_weight);
                // Rewards are weighted by the step length, as Isaac Lab does: returns stay
                // O(1-10), the scale rsl_rl's value clipping (0.2) is meant for.
                let mut reward = total * REWARD_DT;
                error_sum += f64::from(terms.body_pos_error);
                let clip_log = &mut log.clips[self.clip_of(i)];
                clip_log.steps += 1;
                clip_log.body_pos_error += terms.body_pos_error;
                self.episode_steps[i] += 1;
                if *ending == Ending::ClipEnd {
                    // A time limit, not a failure: bootstrap with the value estimate.
                    reward += gamma * values[i];
                }
                rollout.rewards.push(reward);
                rollout.dones.push(*ending != Ending::None);
                if *ending != Ending::None {
                    let c = self.clip_of(i);
                    log.episodes += 1;
                    log.clips[c].episodes += 1;
                    ended_lengths += self.episode_steps[i];
                    if matches!(ending, Ending::Failed | Ending::Diverged) {
                        log.failures += 1;
                        log.clips[c].failures += 1;
                        self.samplers[c].record_failure(self.trackers[i].frame);
                    }
                    self.reset_env(i)?;
                    self.episode_steps[i] = 0;
                }
            }
            self.observe_all(&mut raw);
            physics += t1.elapsed().as_secs_f64();
            rollout.obs.extend_from_slice(&obs);
            rollout.actions.extend_from_slice(&actions);
            rollout.means.extend_from_slice(&means);
            rollout.log_probs.extend_from_slice(&log_probs);
            rollout.values.extend_from_slice(&values);
        }
        rollout.last_values = self.policy.critic.predict(&self.policy.normalise(&raw), e);
        let collect = started.elapsed().as_secs_f64();
        let t2 = Instant::now();
        let stats: UpdateStats = ppo::update(&mut self.policy, &mut self.opt, &rollout, &self.cfg, &mut self.rng);
        if !self.policy.params().iter().all(|p| p.is_finite()) || !stats.value_loss.is_finite() {
            return Err(TrackError::NonFinite {
                iteration: log.iteration,
                what: format!(
                    "non-finite parameters after the update (value loss {}, kl {})",
                    stats.value_loss, stats.kl
                ),
            });
        }
        self.samplers.iter_mut().for_each(|s| s.end_iteration(&self.cfg));
        self.iteration += 1;
        self.env_steps += (e * horizon) as u64;
        let n = (e * horizon) as f64;
        log.env_steps = self.env_steps;
        log.mean_reward = (reward_sum / n) as f32;
        log.rewards = term_means;
        log.body_pos_error = (error_sum / n) as f32;
        for c in &mut log.clips {
            c.body_pos_error /= c.steps.max(1) as f32;
        }
        log.episode_length = if log.episodes > 0 { ended_lengths as f32 / log.episodes as f32 } else { 0.0 };
        log.update = stats;
        log.physics_seconds = physics as f32;
        log.network_seconds = network as f32;
        log.update_seconds = t2.elapsed().as_secs_f32();
        log.steps_per_second = (n / (collect + t2.elapsed().as_secs_f64())) as f32;
        Ok(log)
    }

    /// Writes the policy, optimiser state and counters atomically.
    pub fn save(&self, path: &Path) -> Result<(), TrackError> {
        let f32s = |v: &[f32]| le::bytes(v.iter().copied());
        let f64s = |v: &[f64]| le::bytes(v.iter().copied());
        let p = &self.policy;
        let tensors: Vec<(&str, Dtype, Vec<u8>)> = vec![
            ("actor", Dtype::F32, f32s(&p.actor.params())),
            ("critic", Dtype::F32, f32s(&p.critic.params())),
            ("log_std", Dtype::F32, f32s(&p.log_std)),
            ("obs_mean", Dtype::F64, f64s(&p.normaliser.mean)),
            ("obs_var", Dtype::F64, f64s(&p.normaliser.var)),
            ("adam_m", Dtype::F32, f32s(&self.opt.adam.m)),
            ("adam_v", Dtype::F32, f32s(&self.opt.adam.v)),
            (
                "start_failures",
                Dtype::F64,
                f64s(&self.samplers.iter().flat_map(|s| s.failures.clone()).collect::<Vec<_>>()),
            ),
        ];
        let views: Vec<(&str, TensorView)> = tensors
            .iter()
            .map(|(name, dtype, bytes)| {
                let width = if *dtype == Dtype::F64 { 8 } else { 4 };
                (*name, TensorView::new(*dtype, vec![bytes.len() / width], bytes).expect("1-d tensor"))
            })
            .collect();
        let meta: HashMap<String, String> = [
            ("format", POLICY_FORMAT.to_string()),
            ("config", serde_json::to_string(&self.cfg).expect("json")),
            ("clip", self.clip_names()),
            ("clip_frames", self.clip_frames()),
            ("obs_dim", p.obs_dim().to_string()),
            ("act_dim", NUM_DOFS.to_string()),
            ("iteration", self.iteration.to_string()),
            ("env_steps", self.env_steps.to_string()),
            ("learning_rate", self.opt.lr.to_string()),
            ("adam_t", self.opt.adam.t.to_string()),
            ("obs_count", p.normaliser.count.to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let bytes = safetensors::serialize(views, Some(meta))
            .map_err(|e| TrackError::Checkpoint { path: path.into(), message: e.to_string() })?;
        flowmimic_io::write_atomic(path, &bytes)?;
        Ok(())
    }

    /// Clip names, comma-separated (checkpoint metadata).
    fn clip_names(&self) -> String {
        self.references.iter().map(|r| r.clip.name.clone()).collect::<Vec<_>>().join(",")
    }

    fn clip_frames(&self) -> String {
        self.references.iter().map(|r| r.len().to_string()).collect::<Vec<_>>().join(",")
    }

    /// Starts a new run on `clips` from the policy of another run's checkpoint: its weights,
    /// action noise, observation statistics and learning rate, with fresh Adam moments and
    /// counters (to fine-tune a corpus expert on one clip, or under other settings). The
    /// learning rate is kept because the configured initial one would undo a trained policy
    /// in the first update, before the KL rule lowers it.
    pub fn warm_start(
        humanoid: &Arc<Humanoid>,
        clips: Vec<Clip>,
        cfg: TrackConfig,
        path: &Path,
    ) -> Result<Self, TrackError> {
        Self::from_checkpoint(humanoid, clips, cfg, &Checkpoint::read(path)?)
    }

    /// A new trainer with the checkpoint's policy and learning rate.
    fn from_checkpoint(
        humanoid: &Arc<Humanoid>,
        clips: Vec<Clip>,
        cfg: TrackConfig,
        ck: &Checkpoint,
    ) -> Result<Self, TrackError> {
        let saved = ck.config()?;
        if saved.hidden != cfg.hidden {
            return Err(ck.bad(format!(
                "checkpoint has hidden layers {:?}; the config asks for {:?}",
                saved.hidden, cfg.hidden
            )));
        }
        let fresh = cfg.fresh_output.then_some((cfg.init_log_std as f32, cfg.learning_rate as f32));
        let mut trainer = Self::new(humanoid, clips, cfg)?;
        ck.load_policy(&mut trainer.policy)?;
        trainer.opt.lr = ck.number("learning_rate")? as f32;
        if let Some((log_std, lr)) = fresh {
            let policy = &mut trainer.policy;
            policy.actor.zero_outputs();
            policy.log_std.iter_mut().for_each(|s| *s = s.max(log_std));
            policy.normaliser.count = policy.normaliser.count.min(FRESH_OBSERVATIONS);
            trainer.opt.lr = lr;
        }
        Ok(trainer)
    }

    /// Continues a run from a checkpoint written by [`Trainer::save`] for the same clips and
    /// network shape; anything else is refused with the reason.
    pub fn resume(
        humanoid: &Arc<Humanoid>,
        clips: Vec<Clip>,
        cfg: TrackConfig,
        path: &Path,
    ) -> Result<Self, TrackError> {
        let ck = Checkpoint::read(path)?;
        let bad = |m: String| TrackError::Checkpoint { path: path.into(), message: m };
        let names = clips.iter().map(|c| c.name.clone()).collect::<Vec<_>>().join(",");
        let frames = clips.iter().map(|c| c.len().to_string()).collect::<Vec<_>>().join(",");
        if ck.meta("clip")? != names || ck.meta("clip_frames")? != frames {
            return Err(bad(format!(
                "checkpoint is for clip '{}' ({} frames), not '{names}' ({frames} frames)",
                ck.meta("clip")?,
                ck.meta("clip_frames")?
            )));
        }
        let saved = ck.config()?;
        if saved.envs != cfg.envs {
            return Err(bad(format!("checkpoint has {} envs; the config asks for {}", saved.envs, cfg.envs)));
        }
        if saved.observe_ahead != cfg.observe_ahead {
            return Err(bad(format!(
                "checkpoint has track.observe_ahead = {}; the config asks for {}",
                saved.observe_ahead, cfg.observe_ahead
            )));
        }
        let mut trainer = Self::from_checkpoint(humanoid, clips, cfg, &ck)?;
        trainer.opt.adam.m = ck.f32s("adam_m", trainer.policy.num_params())?;
        trainer.opt.adam.v = ck.f32s("adam_v", trainer.policy.num_params())?;
        trainer.opt.adam.t = ck.number("adam_t")? as u64;
        let total = trainer.samplers.iter().map(|s| s.failures.len()).sum();
        let mut failures = ck.f64s("start_failures", total)?.into_iter();
        for sampler in &mut trainer.samplers {
            sampler.failures = failures.by_ref().take(sampler.failures.len()).collect();
        }
        trainer.iteration = ck.number("iteration")? as usize;
        trainer.env_steps = ck.number("env_steps")? as u64;
        // Fresh episodes, with random streams advanced by the iteration count.
        trainer.rng = StdRng::seed_from_u64(trainer.cfg.seed ^ (trainer.iteration as u64).wrapping_mul(0x9E37_79B9));
        trainer.reset_all()?;
        Ok(trainer)
    }
}

/// A clip for a new episode, given the clips' lengths: in proportion to length with
/// probability `length_share`, else evenly.
fn draw_clip(lengths: &[usize], length_share: f64, rng: &mut impl Rng) -> usize {
    let k = lengths.len();
    if k == 1 {
        return 0;
    }
    if rng.random::<f64>() >= length_share {
        return rng.random_range(0..k);
    }
    let mut at = rng.random_range(0..lengths.iter().sum::<usize>());
    for (c, &len) in lengths.iter().enumerate() {
        if at < len {
            return c;
        }
        at -= len;
    }
    k - 1
}

/// An index drawn in proportion to `weights`; `None` when they sum to 0.
fn draw_weighted(weights: &[f64], rng: &mut impl Rng) -> Option<usize> {
    let total: f64 = weights.iter().sum();
    if total <= 0.0 {
        return None;
    }
    let mut at = rng.random::<f64>() * total;
    for (i, &w) in weights.iter().enumerate() {
        if at < w {
            return Some(i);
        }
        at -= w;
    }
    Some(weights.len() - 1)
}

/// The steps a policy's observation statistics count as when it starts from a zero residual
/// ([`TrackConfig::fresh_output`]): about 35 iterations of the corpus preset.
pub const FRESH_OBSERVATIONS: f64 = 2e5;

pub const POLICY_FORMAT: &str = "flowmimic-policy/1";

/// The policy file of a run directory.
pub const POLICY_FILE: &str = "policy.safetensors";

/// The policy file that `run` names: a run directory's, or the file itself.
pub fn policy_file(run: &Path) -> std::path::PathBuf {
    if run.is_dir() { run.join(POLICY_FILE) } else { run.to_path_buf() }
}

/// The control step, seconds: the weight of each step's reward in the return.
const REWARD_DT: f32 = (1.0 / CONTROL_HZ) as f32;

/// A policy checkpoint read from disk and checked.
pub struct Checkpoint {
    path: std::path::PathBuf,
    bytes: Vec<u8>,
    meta: HashMap<String, String>,
}

impl Checkpoint {
    pub fn read(path: &Path) -> Result<Self, TrackError> {
        let bytes = flowmimic_io::read(path)?;
        let bad = |m: String| TrackError::Checkpoint { path: path.into(), message: m };
        let (_, meta) =
            SafeTensors::read_metadata(&bytes).map_err(|e| bad(format!("not a policy checkpoint ({e})")))?;
        let meta = meta.metadata().clone().unwrap_or_default();
        if meta.get("format").map(String::as_str) != Some(POLICY_FORMAT) {
            return Err(bad(format!("format is {:?}, expected {POLICY_FORMAT}", meta.get("format"))));
        }
        SafeTensors::deserialize(&bytes).map_err(|e| bad(format!("corrupt tensors: {e}")))?;
        Ok(Self { path: path.into(), bytes, meta })
    }

    fn bad(&self, m: String) -> TrackError {
        TrackError::Checkpoint { path: self.path.clone(), message: m }
    }

    pub fn meta(&self, key: &str) -> Result<String, TrackError> {
        self.meta.get(key).cloned().ok_or_else(|| self.bad(format!("metadata has no '{key}'")))
    }

    fn number(&self, key: &str) -> Result<f64, TrackError> {
        self.meta(key)?.parse().map_err(|_| self.bad(format!("metadata '{key}' is not a number")))
    }

    fn raw(&self, name: &str, dtype: Dtype, len: usize) -> Result<Vec<u8>, TrackError> {
        let st = SafeTensors::deserialize(&self.bytes).map_err(|e| self.bad(e.to_string()))?;
        let t = st.tensor(name).map_err(|e| self.bad(format!("tensor '{name}': {e}")))?;
        let width = if dtype == Dtype::F64 { 8 } else { 4 };
        if t.dtype() != dtype || t.data().len() != len * width {
            return Err(self.bad(format!(
                "tensor '{name}' has {} bytes of {:?}; expected {len} values of {dtype:?}",
                t.data().len(),
                t.dtype()
            )));
        }
        Ok(t.data().to_vec())
    }

    fn f32s(&self, name: &str, len: usize) -> Result<Vec<f32>, TrackError> {
        let v: Vec<f32> = le::values(&self.raw(name, Dtype::F32, len)?);
        if v.iter().any(|x| !x.is_finite()) {
            return Err(self.bad(format!("tensor '{name}' holds non-finite values")));
        }
        Ok(v)
    }

    fn f64s(&self, name: &str, len: usize) -> Result<Vec<f64>, TrackError> {
        Ok(le::values(&self.raw(name, Dtype::F64, len)?))
    }

    /// The stored policy's observation width, one this version writes.
    fn obs_dim(&self) -> Result<usize, TrackError> {
        let obs_dim = self.number("obs_dim")? as usize;
        if ![task::obs_dim(false), task::obs_dim(true)].contains(&obs_dim)
            || self.number("act_dim")? as usize != NUM_DOFS
        {
            return Err(self.bad("observation or action size differs from this version's".into()));
        }
        Ok(obs_dim)
    }

    /// The config stored with the policy.
    pub fn config(&self) -> Result<TrackConfig, TrackError> {
        let cfg: TrackConfig =
            serde_json::from_str(&self.meta("config")?).map_err(|e| self.bad(format!("config: {e}")))?;
        cfg.validate().map_err(|e| self.bad(e.to_string()))?;
        Ok(cfg)
    }

    /// Loads weights and observation statistics into a policy of the stored shape.
    /// A policy that observes the frames ahead can be loaded from one that does not (widened:
    /// [`Policy::widened`]), not the other way round.
    pub fn load_policy(&self, policy: &mut Policy) -> Result<(), TrackError> {
        let stored = self.obs_dim()?;
        if stored < policy.obs_dim() {
            let mut narrow = Policy::new(stored, NUM_DOFS, &self.config()?, &mut StdRng::seed_from_u64(0));
            self.load_policy(&mut narrow)?;
            *policy = narrow.widened(&task::ahead_counterparts());
            return Ok(());
        }
        if stored != policy.obs_dim() {
            return Err(self.bad(
                "the policy observes the reference ahead (track.observe_ahead); the config asks for one that does not"
                    .into(),
            ));
        }
        policy.actor.set_params(&self.f32s("actor", policy.actor.num_params())?);
        policy.critic.set_params(&self.f32s("critic", policy.critic.num_params())?);
        policy.log_std = self.f32s("log_std", NUM_DOFS)?;
        let normaliser = Normaliser {
            mean: self.f64s("obs_mean", stored)?,
            var: self.f64s("obs_var", stored)?,
            count: self.number("obs_count")?,
        };
        let valid = normaliser.mean.iter().all(|m| m.is_finite())
            && normaliser.var.iter().all(|v| v.is_finite() && *v >= 0.0)
            && normaliser.count.is_finite()
            && normaliser.count > 0.0;
        if !valid {
            return Err(
                self.bad("observation statistics are not finite, or a variance or the count is negative".into())
            );
        }
        policy.normaliser = normaliser;
        Ok(())
    }

    /// A policy with the stored weights.
    pub fn policy(&self) -> Result<Policy, TrackError> {
        let cfg = self.config()?;
        // The stored tensors must have the configured shape before a network of it is allocated.
        let obs_dim = self.obs_dim()?;
        for (name, out) in [("actor", NUM_DOFS), ("critic", 1)] {
            let sizes = [&[obs_dim][..], &cfg.hidden, &[out]].concat();
            let params: usize = sizes.windows(2).map(|w| w[0] * w[1] + w[1]).sum();
            self.raw(name, Dtype::F32, params)?;
        }
        let mut policy = Policy::new(obs_dim, NUM_DOFS, &cfg, &mut StdRng::seed_from_u64(0));
        self.load_policy(&mut policy)?;
        Ok(policy)
    }
}

/// Tracking quality over whole-clip episodes with the deterministic policy.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    pub clip: String,
    pub episodes: usize,
    /// Episodes that reached the end of the clip without a tracking failure.
    pub success_rate: f64,
    /// Mean root-relative body position error over all steps, m.
    pub body_pos_error: f64,
    /// Mean control steps survived, from the start frame.
    pub mean_steps: f64,
    /// Control steps of the whole clip.
    pub clip_steps: usize,
    /// How far the root's path strays from the reference's, m/s: over every 1 s window, the
    /// distance between the humanoid's and the reference's horizontal displacement, each in its
    /// heading at the window's start. The body error is root-relative, so a humanoid that steps
    /// in place while the reference walks shows here, not there.
    pub root_path_error: f64,
    /// The frame episodes started from.
    pub start_frame: usize,
    /// Where each episode ended (clip end or failure), averaged: the pelvis's horizontal
    /// distance from the reference's, m, and the difference of their headings, rad. Drift that
    /// the root-relative errors cannot see accumulates here over a long episode.
    pub end_offset: f64,
    pub end_heading_error: f64,
    /// The reference frame each failed episode ended at, ascending: a clip that fails at the
    /// same frames from every start has a part the policy cannot track.
    pub failure_frames: Vec<usize>,
    /// Shares of the episodes' steps that walk backward and that sidestep, and the same shares
    /// of the reference from the start frame (`flowmimic_motion::Coverage`'s thresholds on the
    /// root's 1 s velocities): an expert that steps in place where the reference walks back
    /// shows here.
    pub backward: f64,
    pub reference_backward: f64,
    pub sidestep: f64,
    pub reference_sidestep: f64,
}

/// How [`evaluate`] runs: `episodes` deterministic episodes from frame `start_frame` (with the
/// reset noise, seeded from `seed`), pushes off, or the survival protocol's kicks (0-0.5 m/s
/// every second) when `kicks`.
#[derive(Clone, Copy, Debug)]
pub struct EvalSetup {
    pub episodes: usize,
    pub start_frame: usize,
    pub kicks: bool,
    pub seed: u64,
}

/// Control steps in a root-path window (1 s).
const PATH_WINDOW: usize = CONTROL_HZ as usize;

/// Root x, y and heading of a qpos.
fn root_pose(qpos: &[f64]) -> [f64; 3] {
    let rot = flowmimic_geom::quat_from_wxyz([qpos[3], qpos[4], qpos[5], qpos[6]]);
    [qpos[0], qpos[1], flowmimic_geom::heading(rot)]
}

/// The horizontal displacement from `a` to `b` in `a`'s heading.
fn displacement(a: [f64; 3], b: [f64; 3]) -> [f64; 2] {
    let (s, c) = a[2].sin_cos();
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    [c * dx + s * dy, -s * dx + c * dy]
}

/// Runs the deterministic policy on `clip` as `setup` says.
pub fn evaluate(
    humanoid: &Arc<Humanoid>,
    policy: &Policy,
    clip: &Clip,
    cfg: &TrackConfig,
    setup: EvalSetup,
) -> Result<EvalReport, TrackError> {
    let EvalSetup { episodes, start_frame, kicks, seed } = setup;
    let reference = Reference::new(clip.clone());
    if start_frame + 1 >= reference.len() {
        return Err(TrackError::Invalid(format!(
            "start frame {start_frame} is not before the last frame of clip {} ({} frames)",
            clip.name,
            reference.len()
        )));
    }
    let mut eval_cfg = cfg.clone();
    eval_cfg.push_max = if kicks { 0.5 } else { 0.0 };
    eval_cfg.action_noise = 0.0;
    eval_cfg.push_interval = [1.0, 1.0];
    let mut trackers: Vec<Tracker> = (0..episodes).map(|_| Tracker::new(humanoid)).collect();
    let mut rngs: Vec<StdRng> = (0..episodes).map(|i| StdRng::seed_from_u64(seed.wrapping_add(i as u64))).collect();
    for (t, rng) in trackers.iter_mut().zip(&mut rngs) {
        t.reset(&reference, start_frame, &eval_cfg, rng)?;
    }
    let mut alive = vec![true; episodes];
    let mut survived = vec![0usize; episodes];
    let (mut error_sum, mut error_n, mut successes) = (0.0, 0usize, 0usize);
    // Per episode, the root pose and the reference frame of every step so far.
    let mut paths: Vec<Vec<([f64; 3], usize)>> =
        trackers.iter().map(|t| vec![(root_pose(t.env().qpos()), t.frame)]).collect();
    let (mut path_error_sum, mut path_n) = (0.0, 0usize);
    let (mut offset_sum, mut heading_sum) = (0.0, 0.0);
    let mut failure_frames = Vec::new();
    let mut raw = vec![0.0f32; episodes * policy.obs_dim()];
    for _ in start_frame..reference.len() - 1 {
        trackers.par_iter().zip(raw.par_chunks_mut(policy.obs_dim())).for_each(|(t, o)| t.observe(&reference, o));
        let actions = policy.act(&raw, episodes);
        let results: Vec<(RewardTerms, Ending)> =
            trackers
                .par_iter_mut()
                .zip(rngs.par_iter_mut())
                .zip(actions.par_chunks(NUM_DOFS))
                .zip(alive.par_iter())
                .map(|(((t, rng), u), &live)| {
                    if live { t.step(&reference, u, &eval_cfg, rng) } else { (RewardTerms::default(), Ending::Failed) }
                })
                .collect();
        for (i, (terms, ending)) in results.into_iter().enumerate() {
            if !alive[i] {
                continue;
            }
            survived[i] += 1;
            error_sum += f64::from(terms.body_pos_error);
            error_n += 1;
            // The root pose now and the reference frame it tracks.
            let now = (root_pose(trackers[i].env().qpos()), trackers[i].frame.min(reference.len() - 1));
            let path = &mut paths[i];
            path.push(now);
            if path.len() > PATH_WINDOW {
                let ((start, f0), (end, f1)) = (path[path.len() - 1 - PATH_WINDOW], path[path.len() - 1]);
                let ours = displacement(start, end);
                let theirs = displacement(root_pose(&clip.qpos[f0]), root_pose(&clip.qpos[f1]));
                path_error_sum += (ours[0] - theirs[0]).hypot(ours[1] - theirs[1]);
                path_n += 1;
            }
            match ending {
                Ending::None => {}
                Ending::ClipEnd => {
                    successes += 1;
                    alive[i] = false;
                }
                Ending::Failed | Ending::Diverged => {
                    alive[i] = false;
                    failure_frames.push(now.1);
                }
            }
            if !alive[i] {
                let (ours, theirs) = (now.0, root_pose(&clip.qpos[now.1]));
                offset_sum += (ours[0] - theirs[0]).hypot(ours[1] - theirs[1]);
                heading_sum += flowmimic_geom::wrap_angle(ours[2] - theirs[2]).abs();
            }
        }
    }
    let poses = |path: &[([f64; 3], usize)]| path.iter().map(|(pose, _)| *pose).collect::<Vec<_>>();
    let ours = Coverage::of_walks(paths.iter().map(|p| walking_velocities(&poses(p))).collect());
    let reference_path: Vec<[f64; 3]> = clip.qpos[start_frame..].iter().map(|q| root_pose(q)).collect();
    let theirs = Coverage::of(walking_velocities(&reference_path));
    Ok(EvalReport {
        clip: clip.name.clone(),
        episodes,
        success_rate: successes as f64 / episodes as f64,
        body_pos_error: error_sum / error_n.max(1) as f64,
        mean_steps: survived.iter().sum::<usize>() as f64 / episodes as f64,
        clip_steps: reference.len() - 1,
        root_path_error: path_error_sum / path_n.max(1) as f64,
        start_frame,
        end_offset: offset_sum / episodes as f64,
        end_heading_error: heading_sum / episodes as f64,
        failure_frames: {
            failure_frames.sort_unstable();
            failure_frames
        },
        backward: ours.backward,
        reference_backward: theirs.backward,
        sidestep: ours.sidestep,
        reference_sidestep: theirs.sidestep,
    })
}

/// PPO's throughput beside the physics alone, from [`bench`]: medians over the iterations.
#[derive(Clone, Debug)]
pub struct BenchReport {
    /// Medians of environment steps per second and of the seconds per iteration spent in
    /// physics (stepping, rewards, observations), the policy's forward passes and the update.
    pub log: IterationLog,
    /// `VecEnv::step` of as many environments on the same threads, control steps per second.
    pub vec_env_per_second: f64,
    /// PPO's rate over the `VecEnv` rate timed just before the same iteration.
    pub ppo_over_vec_env: f64,
    /// The share of each iteration spent in PPO's own physics.
    pub physics_share: f64,
}

/// Training throughput on `threads` cores over `iterations` iterations (after one warm-up).
/// Before each iteration a burst of `VecEnv::step` of as many environments runs on the same
/// threads, so that the machine's drift (it moves by a fifth within minutes on shared cores)
/// reaches both sides of each ratio alike.
pub fn bench(
    humanoid: &Arc<Humanoid>,
    clips: Vec<Clip>,
    cfg: TrackConfig,
    iterations: usize,
    threads: usize,
) -> Result<BenchReport, TrackError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| TrackError::Invalid(format!("thread pool: {e}")))?;
    pool.install(|| {
        let mut vec_env = flowmimic_sim::bench::VecEnvTimer::new(humanoid, cfg.envs);
        let mut trainer = Trainer::new(humanoid, clips, cfg)?;
        vec_env.per_second();
        trainer.iterate()?;
        let mut rounds = Vec::new();
        for _ in 0..iterations.max(1) {
            let physics_rate = vec_env.per_second();
            rounds.push((physics_rate, trainer.iterate()?));
        }
        let median = |f: &dyn Fn(&(f64, IterationLog)) -> f64| {
            let mut v: Vec<f64> = rounds.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let n = (trainer.cfg.envs * trainer.cfg.horizon) as f64;
        Ok(BenchReport {
            log: IterationLog {
                steps_per_second: median(&|(_, l)| f64::from(l.steps_per_second)) as f32,
                physics_seconds: median(&|(_, l)| f64::from(l.physics_seconds)) as f32,
                network_seconds: median(&|(_, l)| f64::from(l.network_seconds)) as f32,
                update_seconds: median(&|(_, l)| f64::from(l.update_seconds)) as f32,
                ..rounds[0].1.clone()
            },
            vec_env_per_second: median(&|(v, _)| *v),
            ppo_over_vec_env: median(&|(v, l)| f64::from(l.steps_per_second) / v),
            physics_share: median(&|(_, l)| f64::from(l.physics_seconds) * f64::from(l.steps_per_second) / n),
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failure_credits_the_seconds_before_it() {
        // One iteration's failures at `frames` of a 30 s clip, then the bins they credited.
        let credited = |cfg: &TrackConfig, frames: &[usize]| {
            let mut sampler = StartSampler::new(901, cfg);
            frames.iter().for_each(|&f| sampler.record_failure(f));
            sampler.end_iteration(cfg);
            let bins: Vec<(usize, f64)> =
                sampler.failures.iter().copied().enumerate().filter(|&(_, f)| f > 0.0).collect();
            (sampler, bins)
        };
        // A fall 22.5 s in, credited 4 s back with a decay of 0.8 per second.
        let cfg =
            TrackConfig { failure_lookback_seconds: 4.0, failure_decay: 0.8, bin_smoothing: 1.0, ..Default::default() };
        let (sampler, bins) = credited(&cfg, &[675]);
        let expected = [(18, 0.4096), (19, 0.512), (20, 0.64), (21, 0.8), (22, 1.0)];
        assert_eq!(bins.len(), expected.len(), "{bins:?}");
        for ((bin, f), (want_bin, want)) in bins.iter().zip(expected) {
            assert!(*bin == want_bin && (f - want).abs() < 1e-12, "{bins:?}");
        }
        // Without uniform starts, every start lands in the credited seconds.
        let cfg = TrackConfig { uniform_share: 0.0, ..cfg };
        let mut rng = StdRng::seed_from_u64(0);
        let starts: Vec<usize> = (0..1000).map(|_| sampler.sample(&cfg, &mut rng)).collect();
        assert!(starts.iter().all(|s| (540..690).contains(s)), "{:?}", starts.iter().min());
        assert!(starts.iter().filter(|&&s| s < 600).count() > 100, "the drift's first seconds are practised");

        // The defaults credit the failing second and half the one before, as before the key.
        let cfg = TrackConfig { bin_smoothing: 1.0, ..Default::default() };
        assert_eq!(credited(&cfg, &[0, 675]).1, [(0, 1.0), (21, 0.5), (22, 1.0)]);
    }

    #[test]
    fn displacements_are_in_the_starting_heading() {
        // Facing +y and moving 2 m along +y is 2 m forward; along -x is 3 m to the left.
        let start = [1.0, 1.0, std::f64::consts::FRAC_PI_2];
        let [f, s] = displacement(start, [1.0, 3.0, 0.0]);
        assert!((f - 2.0).abs() < 1e-12 && s.abs() < 1e-12, "{f} {s}");
        let [f, s] = displacement(start, [-2.0, 1.0, 0.0]);
        assert!(f.abs() < 1e-12 && (s - 3.0).abs() < 1e-12, "{f} {s}");
    }

    #[test]
    fn clips_are_drawn_by_length_and_evenly_in_the_configured_shares() {
        let mut rng = StdRng::seed_from_u64(3);
        let share_of_long = |length_share: f64, rng: &mut StdRng| {
            let n = 20_000;
            (0..n).filter(|_| draw_clip(&[900, 100], length_share, rng) == 0).count() as f64 / n as f64
        };
        // By length only: 0.9; evenly only: 0.5; half and half: 0.7.
        for (share, expected) in [(1.0, 0.9), (0.0, 0.5), (0.5, 0.7)] {
            let got = share_of_long(share, &mut rng);
            assert!((got - expected).abs() < 0.015, "share {share}: {got} of episodes on the long clip");
        }
        assert_eq!(draw_clip(&[5], 1.0, &mut rng), 0);
    }

    #[test]
    fn clips_that_fail_are_drawn_in_proportion_to_their_failures() {
        let mut rng = StdRng::seed_from_u64(4);
        let n = 20_000;
        let draws: Vec<usize> = (0..n).map(|_| draw_weighted(&[3.0, 0.0, 1.0], &mut rng).unwrap()).collect();
        let share = |c: usize| draws.iter().filter(|&&d| d == c).count() as f64 / n as f64;
        assert!((share(0) - 0.75).abs() < 0.015 && share(1) == 0.0, "{} {}", share(0), share(1));
        assert_eq!(draw_weighted(&[0.0, 0.0], &mut rng), None, "no failures yet: no weights");
    }

    #[test]
    fn episodes_start_at_the_first_frame_in_the_configured_share() {
        let h = Humanoid::new(flowmimic_sim::SimConfig::default()).unwrap();
        let params = flowmimic_motion::GaitParams { duration: 4.0, ..Default::default() };
        let clip = flowmimic_motion::generate(&h, "walk", &params).unwrap().0;
        let cfg = TrackConfig { envs: 400, hidden: vec![8], ..Default::default() };
        let at_first = |share: f64| {
            let t =
                Trainer::new(&h, vec![clip.clone()], TrackConfig { first_frame_share: share, ..cfg.clone() }).unwrap();
            t.trackers.iter().filter(|t| t.start == 0).count()
        };
        // Adaptive starts alone (uniform before any failure) put about 1 in 120 frames at 0.
        let (none, half, all) = (at_first(0.0), at_first(0.5), at_first(1.0));
        assert!(none < 20 && (160..240).contains(&half) && all == 400, "{none} {half} {all} of 400 at frame 0");
    }
}
