//! The receding-horizon controller: at each 30 Hz step, sample a trajectory from the model
//! given each environment's last N states and actions (one batched model call for all
//! environments), steer it with the task's cost, execute its first action, repeat.

use crate::history::History;
use crate::rollout::{Rollout, RolloutInfo};
use crate::task::{COMMAND_DIM, Task};
use crate::{ControlError, Layout};
use flowmimic_geom::CharFrame;
use flowmimic_model::{Gradient, TaskGuidance, TrajectoryModel};
use flowmimic_motion::Clip;
use flowmimic_sim::{CONTROL_HZ, Env, Humanoid, NUM_BODIES, NUM_DOFS};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Sampler and episode settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlConfig {
    pub nfe: usize,
    /// `w` in `v' = v - w grad G`; 0 runs the model unguided. Each task's gradient is scaled
    /// to its error (see [`crate::Sum::guidance_grad`]), so `w` means the same across tasks.
    pub guidance_scale: f32,
    /// How the gradient reaches the noisy sample: through the network (default) or of the
    /// cost only.
    #[serde(default)]
    pub gradient: Gradient,
    /// Solver steps [start, end) that apply guidance; default: all but the last quarter (the
    /// paper guides 15 of 20).
    pub guidance_steps: Option<(usize, usize)>,
    pub seconds: f64,
    /// Actions of each sampled trajectory executed before sampling again (1: the paper's
    /// receding horizon; up to H + 1).
    pub execute: usize,
    /// Sleep so that steps happen at 30 Hz of wall-clock time.
    pub paced: bool,
    pub seed: u64,
    /// A random planar root-velocity kick every this many seconds (0: none) ...
    pub kick_every: f64,
    /// ... of a speed uniform in [0, kick_max] m/s in a uniform direction.
    pub kick_max: f64,
}

impl ControlConfig {
    pub fn guidance_steps(&self) -> (usize, usize) {
        self.guidance_steps.unwrap_or(default_guidance_steps(self.nfe))
    }
}

/// The solver steps guided by default: all but the last quarter (the paper guides 15 of 20).
pub fn default_guidance_steps(nfe: usize) -> (usize, usize) {
    (0, nfe - nfe / 4)
}

/// What one control step cost, for live status.
#[derive(Clone, Copy, Debug)]
pub struct StepReport {
    pub step: usize,
    pub alive: usize,
    pub model_ms: f32,
    pub physics_ms: f32,
}

/// Puts `env` at frame `frame` of `clip` and fills `history` with the N frames before it (their
/// states, and as actions the PD targets of the following frame), so the model starts inside
/// its training distribution.
pub fn start_from_clip(
    env: &mut Env,
    history: &mut History,
    clip: &Clip,
    frame: usize,
    n: usize,
) -> Result<(), ControlError> {
    let map = env.humanoid().actions().clone();
    for k in frame.saturating_sub(n)..frame {
        env.reset(&clip.qpos[k], &clip.qvel[k])?;
        history.observe(&env.bodies());
        history.act(&map.action_for(&clip.qpos[k + 1][7..]));
    }
    env.reset(&clip.qpos[frame], &clip.qvel[frame])?;
    history.observe(&env.bodies());
    Ok(())
}

/// The clip frame environment `e` starts from: spread over the gait cycle, 7 frames apart.
pub fn start_frame(clip_len: usize, history: usize, e: usize) -> usize {
    history + (e * 7) % (clip_len - history - 1)
}

/// Runs `tasks.len()` environments for `config.seconds` from frames of `clip`.
pub fn run(
    model: &TrajectoryModel,
    humanoid: &Arc<Humanoid>,
    clip: &Clip,
    tasks: Vec<Task>,
    config: &ControlConfig,
    model_name: &str,
    mut on_step: impl FnMut(&StepReport),
) -> Result<Rollout, ControlError> {
    if config.nfe == 0 {
        return Err(ControlError::BadCommand { what: "NFE (at least 1)", value: 0.0 });
    }
    if !config.guidance_scale.is_finite() || config.guidance_scale < 0.0 {
        return Err(ControlError::BadCommand { what: "guidance scale", value: f64::from(config.guidance_scale) });
    }
    // At least one control step, at most a day.
    if !(config.seconds.is_finite() && config.seconds * CONTROL_HZ >= 0.5 && config.seconds <= 86_400.0) {
        return Err(ControlError::BadCommand {
            what: "duration (s; one control step, 1/30 s, to a day)",
            value: config.seconds,
        });
    }
    for task in &tasks {
        task.validate()?;
    }
    let layout = model.layout();
    let (n_hist, horizon) = (layout.spec.history, layout.spec.horizon);
    let traj = Layout { horizon };
    let envs_n = tasks.len();
    let steps = (config.seconds * CONTROL_HZ).round() as usize;
    let nq = humanoid.nq();
    if clip.len() < n_hist + 2 {
        return Err(ControlError::Start(format!("clip '{}' is shorter than the history", clip.name)));
    }
    let mut envs: Vec<Env> = (0..envs_n).map(|_| humanoid.env()).collect();
    let mut histories: Vec<History> = (0..envs_n).map(|_| History::new(layout.spec)).collect();
    for (e, (env, history)) in envs.iter_mut().zip(&mut histories).enumerate() {
        start_from_clip(env, history, clip, start_frame(clip.len(), n_hist, e), n_hist)?;
    }
    let mut out = Rollout {
        info: RolloutInfo {
            model: model_name.to_string(),
            objective: model.objective.name().to_string(),
            nfe: config.nfe,
            horizon,
            guidance_scale: config.guidance_scale,
            guidance_steps: config.guidance_steps(),
            gradient: config.gradient,
            tasks: tasks.clone(),
            seed: config.seed,
            start: format!("clip '{}'", clip.name),
            kick_every: config.kick_every,
            kick_max: config.kick_max,
        },
        envs: envs_n,
        steps,
        nq,
        qpos: vec![0.0; envs_n * (steps + 1) * nq],
        state: vec![0.0; envs_n * (steps + 1) * flowmimic_sim::STATE_DIM],
        body_pos: vec![0.0; envs_n * (steps + 1) * NUM_BODIES * 3],
        action: vec![0.0; envs_n * steps * NUM_DOFS],
        command: vec![0.0; envs_n * steps * COMMAND_DIM],
        survived: vec![steps; envs_n],
        model_ms: Vec::with_capacity(steps),
        physics_ms: Vec::with_capacity(steps),
    };
    let record = |out: &mut Rollout, e: usize, k: usize, env: &Env| {
        let sd = flowmimic_sim::STATE_DIM;
        let at = e * (steps + 1) + k;
        out.state[at * sd..(at + 1) * sd].copy_from_slice(&env.state());
        for (o, q) in out.qpos[at * nq..(at + 1) * nq].iter_mut().zip(env.qpos()) {
            *o = *q as f32;
        }
        let bodies = env.bodies().pos;
        let b = &mut out.body_pos[at * NUM_BODIES * 3..(at + 1) * NUM_BODIES * 3];
        for (o, p) in b.chunks_exact_mut(3).zip(&bodies) {
            o.copy_from_slice(&[p.x as f32, p.y as f32, p.z as f32]);
        }
    };
    for (e, env) in envs.iter().enumerate() {
        record(&mut out, e, 0, env);
    }
    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut alive: Vec<usize> = (0..envs_n).collect();
    let (g0, g1) = config.guidance_steps();
    let future_std = &model.norm.std[layout.cond_len()..];
    // Each environment's current plan and how many of its actions have been executed.
    let every = config.execute.clamp(1, horizon + 1);
    let mut plans: Vec<Option<(Vec<f32>, usize)>> = vec![None; envs_n];
    let started = Instant::now();
    for step in 0..steps {
        let time = step as f64 / CONTROL_HZ;
        let t_model = Instant::now();
        // Environments whose plan is used up sample a new one, all in one batched call.
        let replan: Vec<usize> =
            alive.iter().copied().filter(|&e| plans[e].as_ref().is_none_or(|p| p.1 >= every)).collect();
        let mut cond = Vec::with_capacity(replan.len() * layout.cond_len());
        let mut costs: Vec<Option<crate::Sum>> = Vec::with_capacity(replan.len());
        for &e in &replan {
            let (states, actions) = histories[e].conditioning();
            cond.extend(layout.interleave(&states, &actions));
            let b = envs[e].bodies();
            costs.push(tasks[e].cost(traj, time, &CharFrame::from_root(b.pos[0], b.rot[0]))?);
        }
        let len = traj.len();
        if !replan.is_empty() {
            let grad = |x: &[f32], n: usize| crate::costs::batch_guidance_grad(&costs, future_std, x, n);
            let guided = config.guidance_scale > 0.0 && costs.iter().any(Option::is_some);
            let guidance = guided.then_some(TaskGuidance {
                weight: config.guidance_scale,
                grad: &grad,
                steps: g0..g1,
                gradient: config.gradient,
            });
            let futures = model.sample(&cond, replan.len(), config.nfe, guidance.as_ref(), &mut rng);
            for (i, &e) in replan.iter().enumerate() {
                plans[e] = Some((futures[i * len..(i + 1) * len].to_vec(), 0));
            }
        }
        let model_ms = t_model.elapsed().as_secs_f32() * 1e3;

        let t_physics = Instant::now();
        let mut actions: Vec<Vec<f32>> = Vec::with_capacity(alive.len());
        for &e in &alive {
            let (plan, used) = plans[e].as_mut().expect("planned above");
            let at = traj.action(*used);
            *used += 1;
            let a: Vec<f32> = plan[at..at + NUM_DOFS].iter().map(|a| a.clamp(-1.0, 1.0)).collect();
            if let Some(j) = a.iter().position(|a| !a.is_finite()) {
                return Err(ControlError::NonFinite { env: e, step, index: j });
            }
            let at = (e * steps + step) * NUM_DOFS;
            out.action[at..at + NUM_DOFS].copy_from_slice(&a);
            let c = tasks[e].command(time);
            out.command[(e * steps + step) * COMMAND_DIM..(e * steps + step + 1) * COMMAND_DIM].copy_from_slice(&c);
            actions.push(a);
        }
        let kick_due = config.kick_every > 0.0
            && step > 0
            && step.is_multiple_of(((config.kick_every * CONTROL_HZ).round() as usize).max(1));
        let kicks: Vec<Option<[f64; 2]>> = alive
            .iter()
            .map(|_| {
                kick_due.then(|| {
                    let (angle, speed) =
                        (rng.random::<f64>() * std::f64::consts::TAU, rng.random::<f64>() * config.kick_max);
                    [speed * angle.cos(), speed * angle.sin()]
                })
            })
            .collect();
        let mut stepping: Vec<(usize, &mut Env)> =
            envs.iter_mut().enumerate().filter(|(e, _)| alive.contains(e)).collect();
        let results: Vec<bool> = stepping
            .par_iter_mut()
            .zip(actions.par_iter().zip(&kicks))
            .map(|((_, env), (a, kick))| {
                // A physics blow-up ends the episode like a fall.
                let ok = env.step(a).is_ok() && kick.is_none_or(|k| env.kick(k).is_ok());
                ok && !env.fallen()
            })
            .collect();
        drop(stepping);
        let physics_ms = t_physics.elapsed().as_secs_f32() * 1e3;
        let mut still = Vec::with_capacity(alive.len());
        for (i, &e) in alive.iter().enumerate() {
            histories[e].act(&actions[i]);
            if results[i] {
                histories[e].observe(&envs[e].bodies());
                still.push(e);
            } else {
                out.survived[e] = step + 1;
            }
        }
        alive = still;
        for e in 0..envs_n {
            if alive.contains(&e) || out.survived[e] == step + 1 {
                record(&mut out, e, step + 1, &envs[e]);
            } else {
                out.repeat_row(e, step);
            }
        }
        out.model_ms.push(model_ms);
        out.physics_ms.push(physics_ms);
        on_step(&StepReport { step: step + 1, alive: alive.len(), model_ms, physics_ms });
        if config.paced {
            let due = Duration::from_secs_f64((step + 1) as f64 / CONTROL_HZ);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        if alive.is_empty() {
            // Everyone fell: pad the remaining steps with the last rows.
            for k in step + 1..steps {
                (0..envs_n).for_each(|e| out.repeat_row(e, k));
                out.model_ms.push(0.0);
                out.physics_ms.push(0.0);
            }
            break;
        }
    }
    Ok(out)
}
