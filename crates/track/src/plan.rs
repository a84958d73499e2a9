//! References that look like a guidance model's plans, for a policy that executes plans
//! (`flowmimic_control::Executor`): clips of an expert's rollouts with the data's action noise,
//! whose hinges are the expert's clean PD targets, the actions the model learns. Frame k holds
//! the root of the rollout's state k and the targets of action k-1, as a plan holds its next
//! state and the action that leads to it; frame 0 is the rollout's own state, velocities
//! included, where episodes start (a pose of PD targets presses the feet into the floor).
//!
//! An expert trained on motion capture does not track these: it fails its own rollout, replayed
//! as a reference, within 2 s (docs/guidance.md, "A tracking policy that executes the plan").

use crate::TrackError;
use crate::ppo::Policy;
use crate::task::{Ending, Reference, Tracker};
use crate::train::TrackConfig;
use flowmimic_motion::Clip;
use flowmimic_sim::{CONTROL_HZ, Humanoid, NUM_DOFS};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use std::sync::Arc;

/// The collection sigmas a rollout draws from, about in the data's proportions (16 : 12 : 6 : 6).
const SIGMAS: [f64; 7] = [0.12, 0.12, 0.12, 0.16, 0.16, 0.24, 0.36];
/// Radians of PD-target noise per unit of sigma (`collect.noise_unit_rad`'s default).
const NOISE_UNIT_RAD: f64 = 0.4;
/// Frames dropped before a failure: the stumble that leads to it is no plan's.
const BEFORE_FAILURE: usize = CONTROL_HZ as usize;
/// The shortest clip kept, frames.
const MIN_FRAMES: usize = 3 * CONTROL_HZ as usize;

/// How [`plan_clips`] draws its rollouts.
#[derive(Clone, Copy, Debug)]
pub struct PlanClipSetup {
    /// Rollouts per source clip, each from a random frame.
    pub per_clip: usize,
    pub seconds: f64,
    pub seed: u64,
}

/// Plan-like clips from `expert` tracking each of `sources` (named `<source>_plan<n>`, n from
/// `seed * 1000`); rollouts that fail before [`MIN_FRAMES`] are left out.
pub fn plan_clips(
    humanoid: &Arc<Humanoid>,
    expert: &Policy,
    cfg: &TrackConfig,
    sources: &[Clip],
    setup: PlanClipSetup,
) -> Result<Vec<Clip>, TrackError> {
    let mut cfg = cfg.clone();
    cfg.push_max = 0.0;
    cfg.action_noise = 0.0;
    let map = humanoid.actions();
    let mut rng = StdRng::seed_from_u64(setup.seed);
    let steps = (setup.seconds * CONTROL_HZ) as usize;
    let mut raw = vec![0f32; expert.obs_dim()];
    let mut clips = Vec::new();
    for source in sources {
        let reference = Reference::new(source.clone());
        for r in 0..setup.per_clip {
            let sigma = SIGMAS[rng.random_range(0..SIGMAS.len())];
            let noise = Normal::new(0.0, sigma * NOISE_UNIT_RAD / cfg.action_scale).expect("a positive deviation");
            let start = rng.random_range(0..source.len().saturating_sub(steps + 2).max(1));
            let mut tracker = Tracker::new(humanoid);
            tracker.reset(&reference, start, &cfg, &mut rng)?;
            let (q0, v0) = (tracker.env().qpos().to_vec(), tracker.env().qvel().to_vec());
            let mut qpos = vec![q0.clone()];
            let mut failed = false;
            for _ in 0..steps {
                tracker.observe(&reference, &mut raw);
                let u = expert.act(&raw, 1);
                let clean = tracker.action(&reference, &u, &cfg);
                let noisy_u: Vec<f32> = u.iter().map(|x| x + noise.sample(&mut rng) as f32).collect();
                let noisy = tracker.action(&reference, &noisy_u, &cfg);
                let ending = tracker.step_action(&reference, &noisy, &cfg, &mut rng);
                if matches!(ending, Ending::Failed | Ending::Diverged) {
                    failed = true;
                    break;
                }
                let mut q = tracker.env().qpos().to_vec();
                for (i, a) in clean.iter().enumerate().take(NUM_DOFS) {
                    q[7 + i] = map.target(i, f64::from(*a));
                }
                qpos.push(q);
                if ending == Ending::ClipEnd {
                    break;
                }
            }
            if failed {
                qpos.truncate(qpos.len().saturating_sub(BEFORE_FAILURE));
            }
            if qpos.len() < MIN_FRAMES {
                continue;
            }
            let name = format!("{}_plan{}", source.name, r as u64 + setup.seed * 1000);
            let mut clip =
                Clip::from_qpos(humanoid, &name, &format!("plans of an expert on {}", source.name), false, qpos)
                    .map_err(|e| TrackError::Invalid(e.to_string()))?;
            let mut env = humanoid.env();
            env.reset(&q0, &v0)?;
            clip.qvel[0] = v0;
            clip.bodies[0] = env.bodies();
            clips.push(clip);
        }
    }
    Ok(clips)
}
