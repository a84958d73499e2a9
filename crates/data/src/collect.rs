//! Noise-augmented rollouts of a tracking expert (PDP style, paper section III-E): execute a
//! noisy action but record the expert's clean action for the state reached.
//!
//! The noise is added where the paper adds it, to the expert policy's own action, in the
//! physical units the paper's sigmas imply: BeyondMimic's policies (the paper's experts) output
//! joint offsets of `0.25 * effort / kp` per unit, about 0.5 rad on a G1 hip (88 N m / 41 N m
//! per rad), less on smaller joints. `noise_unit_rad` (default 0.4) is that unit here: the PD
//! target gets `N(0, (sigma * noise_unit_rad)^2)` radians on every hinge, so sigma = 0.12 is
//! about 0.05 rad and sigma = 0.36 about 0.14 rad. (Adding sigma to the environment's normalised
//! action instead would mean 0.12-0.94 rad, since its unit spans each joint's whole range.)
//! Both the clean and the executed action are stored in the environment's normalised space.

use crate::DataError;
use crate::format::Shard;
use flowmimic_geom::heading;
use flowmimic_motion::Clip;
use flowmimic_sim::{Humanoid, NUM_DOFS, STATE_DIM};
use flowmimic_track::TrackConfig;
use flowmimic_track::ppo::Policy;
use flowmimic_track::task::{Ending, Reference, Tracker};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Collection settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CollectConfig {
    /// (sigma, environments): the paper's allocation, 40 rollouts per clip.
    pub noise: Vec<(f32, usize)>,
    /// Steps per rollout; 0 means as long as the clip.
    pub rollout_steps: usize,
    /// Radians of PD-target noise per unit of sigma (see the module docs).
    pub noise_unit_rad: f64,
    /// Steps dropped from the end of an episode that ends in a tracking failure (0 keeps
    /// them): what an expert does while it is failing is not worth imitating.
    #[serde(default)]
    pub drop_before_failure: usize,
    /// Seed of the rollouts' starts and action noise.
    pub seed: u64,
}

impl Default for CollectConfig {
    fn default() -> Self {
        Self {
            noise: vec![(0.12, 16), (0.16, 12), (0.24, 6), (0.36, 6)],
            rollout_steps: 0,
            noise_unit_rad: 0.4,
            drop_before_failure: 0,
            seed: 0,
        }
    }
}

impl CollectConfig {
    /// Refuses values a collection cannot use, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.noise.is_empty() || self.noise.iter().map(|n| n.1).sum::<usize>() == 0 {
            return Err("collect.noise allocates no environments".into());
        }
        if let Some((sigma, _)) = self.noise.iter().find(|(s, _)| !(s.is_finite() && *s >= 0.0)) {
            return Err(format!("collect.noise has sigma {sigma}; sigmas must be finite and not negative"));
        }
        if self.noise.iter().map(|n| n.1).sum::<usize>() > 100_000
            || self.rollout_steps > 10_000_000
            || self.drop_before_failure > 10_000_000
        {
            return Err("collect.noise or rollout_steps asks for more than a machine holds".into());
        }
        if !(self.noise_unit_rad.is_finite() && self.noise_unit_rad > 0.0) {
            return Err(format!("collect.noise_unit_rad is {}; it must be positive", self.noise_unit_rad));
        }
        Ok(())
    }
}

/// What a collection did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct CollectStats {
    pub steps: usize,
    pub seconds: f64,
    /// (sigma, episodes, falls).
    pub falls: Vec<(f32, usize, usize)>,
}

/// Per-environment buffer; concatenated afterwards so each rollout is contiguous.
struct Lane {
    tracker: Tracker,
    rng: StdRng,
    sigma: f32,
    noise: Normal<f32>,
    shard: Shard,
    /// Where the current episode starts in `shard`.
    episode_start: usize,
    episodes: usize,
    falls: usize,
}

/// Rolls `expert` out on `clip` with the configured noise; one lane per environment, all
/// lanes stepped in parallel with one batched expert forward pass per step.
pub fn collect(
    humanoid: &Arc<Humanoid>,
    clip: &Clip,
    expert: &Policy,
    expert_cfg: &TrackConfig,
    cfg: &CollectConfig,
) -> Result<(Shard, CollectStats), DataError> {
    let reference = Reference::new(clip.clone());
    let steps = if cfg.rollout_steps == 0 { clip.len() - 1 } else { cfg.rollout_steps };
    // No pushes: the action noise is the perturbation.
    let run_cfg = TrackConfig { push_max: 0.0, ..expert_cfg.clone() };
    let mut lanes: Vec<Lane> = cfg
        .noise
        .iter()
        .flat_map(|&(sigma, count)| std::iter::repeat_n(sigma, count))
        .enumerate()
        .map(|(i, sigma)| {
            Ok(Lane {
                tracker: Tracker::new(humanoid),
                rng: StdRng::seed_from_u64(cfg.seed.wrapping_mul(7919).wrapping_add(i as u64)),
                sigma,
                noise: Normal::new(0.0, sigma)
                    .map_err(|e| DataError::Invalid(format!("collect.noise sigma {sigma}: {e}")))?,
                shard: Shard::default(),
                episode_start: 0,
                episodes: 1,
                falls: 0,
            })
        })
        .collect::<Result<_, DataError>>()?;
    if lanes.is_empty() {
        return Err(DataError::Invalid("collect.noise allocates no environments".into()));
    }
    // Lanes start spread evenly over the clip and restart at a random frame after a failure, so
    // that a long clip is covered to its end even when the expert sometimes fails.
    let n = lanes.len();
    let frames = reference.len().saturating_sub(1).max(1);
    for (i, lane) in lanes.iter_mut().enumerate() {
        lane.tracker.reset(&reference, i * frames / n, &run_cfg, &mut lane.rng)?;
    }
    let started = std::time::Instant::now();
    let mut obs = vec![0.0f32; n * expert.obs_dim()];
    for step in 0..steps {
        lanes.par_iter().zip(obs.par_chunks_mut(expert.obs_dim())).for_each(|(l, o)| l.tracker.observe(&reference, o));
        let u = expert.act(&obs, n);
        let last = step + 1 == steps;
        let endings: Vec<Result<(), DataError>> = lanes
            .par_iter_mut()
            .zip(u.par_chunks(NUM_DOFS))
            .map(|(lane, u)| {
                let clean = lane.tracker.action(&reference, u, &run_cfg);
                // The expert's output u is in units of action_scale radians.
                let per_unit = (cfg.noise_unit_rad / run_cfg.action_scale) as f32;
                let noisy_u: Vec<f32> = u.iter().map(|x| x + per_unit * lane.noise.sample(&mut lane.rng)).collect();
                let noisy = lane.tracker.action(&reference, &noisy_u, &run_cfg);
                let env = lane.tracker.env();
                let k = env.bodies();
                let root = k.pos[0];
                let s = &mut lane.shard;
                s.state.extend_from_slice(&k.state());
                s.action.extend_from_slice(&clean);
                s.noisy_action.extend_from_slice(&noisy);
                s.root_pose.extend_from_slice(&[root.x as f32, root.y as f32, heading(k.rot[0]) as f32]);
                s.sigma.push(lane.sigma);
                s.frame.push(lane.tracker.frame as u32);
                let ending = lane.tracker.step_action(&reference, &noisy, &run_cfg, &mut lane.rng);
                let done = ending != Ending::None || last;
                s.done.push(u8::from(done));
                if matches!(ending, Ending::Failed | Ending::Diverged) {
                    lane.falls += 1;
                    let keep = s.steps().saturating_sub(cfg.drop_before_failure).max(lane.episode_start);
                    s.truncate(keep);
                    if let Some(d) = s.done.last_mut().filter(|_| keep > lane.episode_start) {
                        *d = 1;
                    }
                }
                if done {
                    lane.episode_start = lane.shard.steps();
                }
                if done && !last {
                    lane.episodes += 1;
                    let start = if ending == Ending::ClipEnd { 0 } else { lane.rng.random_range(0..frames) };
                    lane.tracker.reset(&reference, start, &run_cfg, &mut lane.rng)?;
                }
                Ok(())
            })
            .collect();
        endings.into_iter().collect::<Result<(), _>>()?;
    }
    let kept = lanes.iter().map(|l| l.shard.steps()).sum();
    let mut stats = CollectStats { steps: kept, seconds: started.elapsed().as_secs_f64(), falls: Vec::new() };
    for &(sigma, _) in &cfg.noise {
        let group = lanes.iter().filter(|l| l.sigma == sigma);
        let (episodes, falls) = group.fold((0, 0), |(e, f), l| (e + l.episodes, f + l.falls));
        stats.falls.push((sigma, episodes, falls));
    }
    let mut shard = Shard::default();
    for lane in lanes {
        debug_assert!(lane.shard.state.len() <= steps * STATE_DIM);
        shard.extend_lane(lane.shard);
    }
    // Rollout ids: one per episode, in order.
    let mut id = 0;
    shard.rollout = shard
        .done
        .iter()
        .map(|&d| {
            let this = id;
            id += u32::from(d);
            this
        })
        .collect();
    Ok((shard, stats))
}
