//! The receding-horizon controller: at each 30 Hz step, sample a trajectory from the model
//! given each environment's last N states and actions (one batched model call for all
//! environments), steer it with the task's cost, execute its first action, repeat.

use crate::adapt::{Adaptive, Recent};
use crate::executor::{DEFAULT_RESIDUAL, Executor};
use crate::history::{History, root_pose};
use crate::rollout::{Rollout, RolloutInfo};
use crate::task::{HeadingHold, SpeedRamp, Steer, Task};
use crate::{ControlError, Layout};
use flowmimic_data::window::reexpress;
use flowmimic_geom::{CharFrame, DVec3, heading, quat_from_wxyz};
use flowmimic_model::{Gradient, InverseDynamics, TaskGuidance, TrajectoryModel};
use flowmimic_motion::Clip;
use flowmimic_sim::{CONTROL_HZ, Env, Humanoid, NUM_DOFS, Obstacle, STATE_DIM};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The actions of the history an episode starts with: a clip holds poses, not the actions that
/// an expert took between them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StartActions {
    /// The PD targets of each following frame (its joint angles).
    #[default]
    PdTargets,
    /// What the model's inverse dynamics reads out of each pair of frames: actions like the
    /// experts' in the training data, whose PD targets lead the pose. From the generated straight walk it
    /// halves the arms models' falls in the first 3 s (docs/guidance.md, "A start in the data's actions").
    InverseDynamics,
}

impl StartActions {
    /// The inverse dynamics this start reads its actions with: none for PD targets; for
    /// inverse dynamics the model's, refused when it has none.
    pub fn inverse(self, model: &TrajectoryModel) -> Result<Option<&InverseDynamics>, ControlError> {
        match (self, model.inverse.as_ref()) {
            (Self::PdTargets, _) => Ok(None),
            (Self::InverseDynamics, Some(inverse)) => Ok(Some(inverse)),
            (Self::InverseDynamics, None) => Err(ControlError::Sampler(
                "a start in inverse dynamics' actions: the model directory has no inverse.safetensors (fit one on the model's dataset with `flowmimic inverse DATASET --model DIR`, or run with --start-actions pd-targets)".into(),
            )),
        }
    }
}

/// Sampler and episode settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControlConfig {
    /// Network evaluations per control step (solver steps; Heun takes two per step).
    pub nfe: usize,
    /// `w` in `v' = v - w grad G`; 0 runs the model unguided. Each task's gradient is scaled
    /// to its error (see [`crate::Sum::guidance_grad`]), so `w` means the same across tasks.
    pub guidance_scale: f32,
    /// How the gradient reaches the noisy sample: through the network (default) or of the
    /// cost only.
    #[serde(default)]
    pub gradient: Gradient,
    /// Adaptive guidance: each environment's scale follows its executed error
    /// ([`crate::adapt`]); `None`: `w` throughout.
    #[serde(default)]
    pub adaptive: Option<Adaptive>,
    /// Solver steps [start, end) that apply guidance; default: all but the last quarter (the
    /// paper guides 15 of 20).
    pub guidance_steps: Option<(usize, usize)>,
    /// Simulated seconds to run.
    pub seconds: f64,
    /// Actions of each sampled trajectory executed before sampling again (1: the paper's
    /// receding horizon; up to H + 1).
    pub execute: usize,
    /// The share `beta` of the executed action taken from inverse dynamics
    /// ([`flowmimic_model::InverseDynamics`]) of the current state and the plan's next state:
    /// `a_plan + beta (a_inverse - a_plan)`. 0: the plan's own action (the paper); above 0
    /// needs a model directory with inverse dynamics, and `execute` 1.
    #[serde(default)]
    pub inverse_dynamics: f32,
    /// The most the joystick velocity asked of guidance speeds up, m/s^2 per axis
    /// ([`SpeedRamp`]); 0: the command as given (the paper).
    #[serde(default)]
    pub acceleration: f32,
    /// For a labelled model ([`flowmimic_model::Label`]): how much its label, the command it is
    /// told, weighs in each sample, by classifier-free guidance: 0 as if told nothing, 1 as
    /// told, above 1 past it (two network calls a step). Rollouts saved before the setting
    /// existed were told (1).
    #[serde(default = "as_told")]
    pub label_scale: f32,
    /// The actions of the history an episode starts with ([`start_from_clip`]).
    #[serde(default)]
    pub start_actions: StartActions,
    /// A tracking policy's run directory ([`Executor`]) that executes each plan in place of
    /// its own action; `None`: the plan's action (the paper).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub executor: Option<PathBuf>,
    /// The share of the executor's residual that is added to the plan's action (1: all of it;
    /// rollouts saved before the share existed executed all of it).
    #[serde(default = "all_of_the_residual")]
    pub executor_residual: f32,
    /// Sleep so that steps happen at 30 Hz of wall-clock time.
    pub paced: bool,
    /// Seed of the controller's random stream: the sampler's noise and the kicks.
    pub seed: u64,
    /// A random planar root-velocity kick every this many seconds (0: none) ...
    pub kick_every: f64,
    /// ... of a speed uniform in [0, kick_max] m/s in a uniform direction.
    pub kick_max: f64,
}

fn all_of_the_residual() -> f32 {
    1.0
}

fn as_told() -> f32 {
    1.0
}

impl ControlConfig {
    /// `nfe` solver steps at guidance scale `guidance_scale` (0: unguided) for `seconds`; the
    /// rest plain: gradient through the network, the default interval, the paper's receding
    /// horizon, not paced, seed 0, no kicks.
    pub fn new(nfe: usize, guidance_scale: f32, seconds: f64) -> Self {
        Self {
            nfe,
            guidance_scale,
            gradient: Gradient::ThroughNetwork,
            adaptive: None,
            guidance_steps: None,
            seconds,
            execute: 1,
            inverse_dynamics: 0.0,
            acceleration: 0.0,
            label_scale: 1.0,
            start_actions: StartActions::PdTargets,
            executor: None,
            executor_residual: DEFAULT_RESIDUAL,
            paced: false,
            seed: 0,
            kick_every: 0.0,
            kick_max: 0.0,
        }
    }

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

/// Puts `env` at frame `frame` of `clip` and fills `history` with the model's N frames before it
/// (their states, and as actions what `start` says), so the model starts inside its training
/// distribution.
pub fn start_from_clip(
    env: &mut Env,
    history: &mut History,
    clip: &Clip,
    frame: usize,
    model: &TrajectoryModel,
    start: StartActions,
) -> Result<(), ControlError> {
    let inverse = start.inverse(model)?;
    let first = frame.saturating_sub(model.layout().spec.history);
    let mut bodies = Vec::with_capacity(frame + 1 - first);
    for k in first..=frame {
        env.reset(&clip.qpos[k], &clip.qvel[k])?;
        bodies.push(env.bodies());
    }
    let actions: Vec<Vec<f32>> = match inverse {
        Some(inverse) => {
            // Each frame's state and the next one's in its frame, re-expressed as in the data
            // inverse dynamics was fitted on.
            let mut next = [0.0; STATE_DIM];
            let pairs: Vec<f32> = bodies
                .windows(2)
                .flat_map(|w| {
                    reexpress(&w[1].state(), root_pose(&w[1]), root_pose(&w[0]), &mut next);
                    [w[0].state(), next]
                })
                .flatten()
                .collect();
            inverse.actions(&pairs, bodies.len() - 1).chunks_exact(NUM_DOFS).map(<[f32]>::to_vec).collect()
        }
        None => {
            let map = env.humanoid().actions();
            (first..frame).map(|k| map.action_for(&clip.qpos[k + 1][7..])).collect()
        }
    };
    for (j, b) in bodies.iter().enumerate() {
        history.observe(b);
        if let Some(a) = actions.get(j) {
            history.act(a);
        }
    }
    Ok(())
}

/// Where environment `e` starts (its character frame on the ground) when started from `clip`
/// with a history of `history` states ([`start_frame`]).
pub fn start_pose(clip: &Clip, history: usize, e: usize) -> CharFrame {
    let q = &clip.qpos[start_frame(clip.len(), history, e)];
    CharFrame::new(DVec3::new(q[0], q[1], 0.0), heading(quat_from_wxyz([q[3], q[4], q[5], q[6]])))
}

/// The clip frame environment `e` starts from: spread over the gait cycle, 7 frames apart.
pub fn start_frame(clip_len: usize, history: usize, e: usize) -> usize {
    history + (e * 7) % (clip_len - history - 1)
}

/// A sampled trajectory being executed: its values (physical units), how many of its actions
/// ran, and the character frame it was planned in.
#[derive(Clone)]
struct Plan {
    tau: Vec<f32>,
    used: usize,
    frame: CharFrame,
}

/// The receding-horizon loop over a batch of environments, one control step at a time:
/// [`run`] drives it through an episode and records it, `flowmimic play` drives it live.
pub struct Controller<'m> {
    model: &'m TrajectoryModel,
    config: ControlConfig,
    envs: Vec<Env>,
    histories: Vec<History>,
    /// Each environment's last half second of pelvis poses, for adaptive guidance.
    recent: Vec<Recent>,
    /// Each environment's joystick heading.
    holds: Vec<HeadingHold>,
    /// Each environment's joystick velocity as last asked, when speed-ups are ramped.
    ramps: Vec<SpeedRamp>,
    /// Each environment's current plan.
    plans: Vec<Option<Plan>>,
    alive: Vec<bool>,
    /// Executes the plans in place of their own actions, when the config names one.
    executor: Option<Arc<Executor>>,
    rng: StdRng,
    step: usize,
}

/// What one control step did.
#[derive(Clone, Debug)]
pub struct StepOutcome {
    /// The action each environment executed (`None`: it had fallen before this step).
    pub actions: Vec<Option<Vec<f32>>>,
    /// Environments that fell (or whose physics diverged) during this step.
    pub fell: Vec<usize>,
    pub model_ms: f32,
    pub physics_ms: f32,
}

/// Refuses sampler settings that cannot run: no solver steps, a negative or NaN scale,
/// inverse-dynamics actions (or a start in them) without the model or with several actions per
/// plan. [`run`] checks too; a command line checks first, before it says the run began.
pub fn check_sampler(model: &TrajectoryModel, config: &ControlConfig) -> Result<(), ControlError> {
    if config.nfe == 0 {
        return Err(ControlError::BadCommand { what: "NFE (at least 1)", value: 0.0 });
    }
    if !config.guidance_scale.is_finite() || config.guidance_scale < 0.0 {
        return Err(ControlError::BadCommand { what: "guidance scale", value: f64::from(config.guidance_scale) });
    }
    if !(config.acceleration.is_finite() && config.acceleration >= 0.0) {
        let value = f64::from(config.acceleration);
        return Err(ControlError::BadCommand { what: "joystick acceleration (m/s^2, 0 for none)", value });
    }
    let scale = config.label_scale;
    if !(scale.is_finite() && scale >= 0.0) {
        return Err(ControlError::BadCommand { what: "label scale (0 or more)", value: f64::from(scale) });
    }
    if scale != 1.0 && model.layout().labels == 0 {
        return Err(ControlError::Sampler(format!(
            "label scale {scale}: the model has no labels to weigh (it is trained without [model] command_labels or task_labels)"
        )));
    }
    let residual = config.executor_residual;
    if !(0.0..=1.0).contains(&residual) {
        return Err(ControlError::BadCommand { what: "executor residual share (0 to 1)", value: f64::from(residual) });
    }
    let beta = config.inverse_dynamics;
    if !(0.0..=1.0).contains(&beta) {
        return Err(ControlError::BadCommand { what: "inverse-dynamics share (0 to 1)", value: f64::from(beta) });
    }
    config.start_actions.inverse(model)?;
    if beta > 0.0 && model.inverse.is_none() {
        return Err(ControlError::Sampler(
            "inverse-dynamics actions: the model directory has no inverse.safetensors (fit one on the model's dataset with `flowmimic inverse DATASET --model DIR`, or run with --inverse-dynamics 0)".into(),
        ));
    }
    if beta > 0.0 && config.execute != 1 {
        return Err(ControlError::Sampler(format!(
            "inverse-dynamics actions (share {beta}, from --inverse-dynamics or the model's recommended.toml) need \
             execute 1 (the plan's next state is for the current step), not {}: run with --inverse-dynamics 0 to execute \
             more actions of each plan",
            config.execute
        )));
    }
    config.guidance_steps.map_or(Ok(()), |steps| check_guidance_steps(steps, config.nfe))
}

/// Refuses guided solver steps `start..end` that are empty or run past the sampler's `nfe`.
pub fn check_guidance_steps((start, end): (usize, usize), nfe: usize) -> Result<(), ControlError> {
    if start < end && end <= nfe {
        Ok(())
    } else {
        Err(ControlError::Sampler(format!("guidance interval {start}:{end}: need start < end <= NFE ({nfe})")))
    }
}

impl<'m> Controller<'m> {
    /// `envs` environments started from frames of `clip` (see [`start_frame`]).
    pub fn new(
        model: &'m TrajectoryModel,
        humanoid: &Arc<Humanoid>,
        clip: &Clip,
        envs: usize,
        config: &ControlConfig,
    ) -> Result<Self, ControlError> {
        check_sampler(model, config)?;
        let n_hist = model.layout().spec.history;
        if clip.len() < n_hist + 2 {
            return Err(ControlError::Start(format!("clip '{}' is shorter than the history", clip.name)));
        }
        let mut this = Self {
            model,
            config: config.clone(),
            envs: (0..envs).map(|_| humanoid.env()).collect(),
            histories: (0..envs).map(|_| History::new(model.layout().spec)).collect(),
            recent: vec![Recent::default(); envs],
            holds: vec![HeadingHold::default(); envs],
            ramps: vec![SpeedRamp::default(); envs],
            plans: vec![None; envs],
            alive: vec![true; envs],
            executor: config.executor.as_deref().map(Executor::load).transpose()?.map(Arc::new),
            rng: StdRng::seed_from_u64(config.seed),
            step: 0,
        };
        for e in 0..envs {
            this.restart(e, clip, start_frame(clip.len(), n_hist, e))?;
        }
        Ok(this)
    }

    /// Puts environment `e` back at `frame` of `clip`, standing, with a fresh history.
    pub fn restart(&mut self, e: usize, clip: &Clip, frame: usize) -> Result<(), ControlError> {
        let n_hist = self.model.layout().spec.history;
        if frame < n_hist || frame + 1 >= clip.len() {
            return Err(ControlError::Start(format!(
                "frame {frame} of clip '{}' leaves no room for the history",
                clip.name
            )));
        }
        self.histories[e] = History::new(self.model.layout().spec);
        start_from_clip(&mut self.envs[e], &mut self.histories[e], clip, frame, self.model, self.config.start_actions)?;
        self.recent[e] = Recent::default();
        self.recent[e].observe(&self.envs[e].bodies());
        self.holds[e] = HeadingHold::default();
        self.ramps[e] = SpeedRamp::default();
        self.plans[e] = None;
        self.alive[e] = true;
        Ok(())
    }

    /// Changes the sampler (NFE, scale, gradient, interval) from the next step on.
    pub fn set_config(&mut self, config: ControlConfig) -> Result<(), ControlError> {
        check_sampler(self.model, &config)?;
        if config.executor != self.config.executor {
            self.executor = config.executor.as_deref().map(Executor::load).transpose()?.map(Arc::new);
        }
        self.config = config;
        Ok(())
    }

    pub fn config(&self) -> &ControlConfig {
        &self.config
    }

    pub fn env(&self, e: usize) -> &Env {
        &self.envs[e]
    }

    pub fn is_alive(&self, e: usize) -> bool {
        self.alive[e]
    }

    /// Control steps taken so far.
    pub fn steps(&self) -> usize {
        self.step
    }

    /// Environment `e`'s current plan (the trajectory being executed, physical units).
    pub fn plan(&self, e: usize) -> Option<&[f32]> {
        self.plans[e].as_ref().map(|p| p.tau.as_slice())
    }

    /// Puts environment `e` in a world with `obstacles` (world frame; they replace any it had),
    /// keeping its state: a model of its own is compiled (milliseconds).
    pub fn place_obstacles(&mut self, e: usize, obstacles: &[Obstacle]) -> Result<(), ControlError> {
        let world = self.envs[e].humanoid().with_obstacles(obstacles)?;
        Ok(self.envs[e].enter(world)?)
    }

    /// What environment `e`'s current plan asks ([`Layout::intent`]).
    pub fn intent(&self, e: usize) -> Option<[f32; 3]> {
        let traj = Layout { horizon: self.model.layout().spec.horizon };
        self.plan(e).map(|tau| traj.intent(tau))
    }

    /// Where environment `e`'s current plan puts body `b` at its horizon's end (world frame):
    /// set beside where the body went, it tells a plan that misses a hand target from an
    /// execution that misses a plan that reaches it.
    pub fn planned_body(&self, e: usize, b: usize) -> Option<DVec3> {
        let traj = Layout { horizon: self.model.layout().spec.horizon };
        self.plans[e].as_ref().map(|p| {
            // The plan's heights are above the ground, not above the frame's origin.
            let ([x, y, z], _) = traj.body_in_frame(&p.tau, traj.horizon, b);
            let w = p.frame.point_to_world(DVec3::new(f64::from(x), f64::from(y), 0.0));
            DVec3::new(w.x, w.y, f64::from(z))
        })
    }

    /// A planar root-velocity push on environment `e` now (m/s, world frame).
    pub fn kick(&mut self, e: usize, velocity: [f64; 2]) -> Result<(), ControlError> {
        Ok(self.envs[e].kick(velocity)?)
    }

    /// One control step: every environment still standing samples a plan if its last one is
    /// used up (all in one batched model call, steered by its task's cost at `time`),
    /// executes the next action, and is checked for a fall.
    pub fn step(&mut self, tasks: &[Task], time: f64) -> Result<StepOutcome, ControlError> {
        let model = self.model;
        let layout = model.layout();
        let traj = Layout { horizon: layout.spec.horizon };
        let every = self.config.execute.clamp(1, traj.horizon + 1);
        let alive: Vec<usize> = (0..self.envs.len()).filter(|&e| self.alive[e]).collect();
        let t_model = Instant::now();
        let replan: Vec<usize> =
            alive.iter().copied().filter(|&e| self.plans[e].as_ref().is_none_or(|p| p.used >= every)).collect();
        if !replan.is_empty() {
            let mut cond = Vec::with_capacity(replan.len() * layout.cond_len());
            let mut costs: Vec<Option<crate::Sum>> = Vec::with_capacity(replan.len());
            let mut frames = Vec::with_capacity(replan.len());
            for &e in &replan {
                let b = self.envs[e].bodies();
                let frame = CharFrame::from_root(b.pos[0], b.rot[0]);
                let segment = tasks[e].joystick_at(time);
                let acceleration = f64::from(self.config.acceleration);
                let steer = Steer {
                    heading_lag: self.holds[e].lag(segment, time, frame.yaw),
                    velocity: (acceleration > 0.0)
                        .then(|| self.ramps[e].velocity(segment, time, acceleration))
                        .flatten(),
                };
                let (states, actions) = self.histories[e].conditioning();
                let label = tasks[e].label(&model.config, time, &frame, steer)?;
                cond.extend(layout.conditioning(&states, &actions, label));
                let cost = tasks[e].cost(traj, time, &frame, steer)?;
                let factor =
                    self.config.adaptive.map_or(1.0, |a| a.factor(tasks[e].executed_error(time, &self.recent[e])));
                costs.push(cost.map(|c| c.scaled(factor)));
                frames.push(frame);
            }
            let future_std = &model.norm.std[layout.cond_len()..];
            let grad = |x: &[f32], n: usize| crate::costs::batch_guidance_grad(&costs, future_std, x, n);
            let guided = self.config.guidance_scale > 0.0 && costs.iter().any(Option::is_some);
            let (g0, g1) = self.config.guidance_steps();
            let guidance = guided.then_some(TaskGuidance {
                weight: self.config.guidance_scale,
                grad: &grad,
                steps: g0..g1,
                gradient: self.config.gradient,
            });
            let mut futures = model.sample_told(
                &cond,
                replan.len(),
                self.config.nfe,
                self.config.label_scale,
                guidance.as_ref(),
                &mut self.rng,
            );
            let len = traj.len();
            if self.config.inverse_dynamics > 0.0 {
                blend_inverse_dynamics(model, self.config.inverse_dynamics, &cond, &mut futures);
            }
            for (i, &e) in replan.iter().enumerate() {
                self.plans[e] = Some(Plan { tau: futures[i * len..(i + 1) * len].to_vec(), used: 0, frame: frames[i] });
            }
        }
        let model_ms = t_model.elapsed().as_secs_f32() * 1e3;

        let t_physics = Instant::now();
        let mut actions: Vec<Option<Vec<f32>>> = vec![None; self.envs.len()];
        for &e in &alive {
            let plan = self.plans[e].as_ref().expect("planned above");
            let at = traj.action(plan.used);
            let a: Vec<f32> = plan.tau[at..at + NUM_DOFS].iter().map(|a| a.clamp(-1.0, 1.0)).collect();
            if let Some(j) = a.iter().position(|a| !a.is_finite()) {
                return Err(ControlError::NonFinite { env: e, step: self.step, index: j });
            }
            actions[e] = Some(a);
        }
        if let (Some(executor), Some(&first)) = (&self.executor, alive.first()) {
            let plans: Vec<_> = alive
                .iter()
                .map(|&e| {
                    let plan = self.plans[e].as_ref().expect("planned above");
                    (&self.envs[e], plan.tau.as_slice(), plan.used, plan.frame)
                })
                .collect();
            let map = self.envs[first].humanoid().actions();
            for (&e, a) in alive.iter().zip(executor.actions(map, traj, &plans, self.config.executor_residual)) {
                actions[e] = Some(a);
            }
        }
        for &e in &alive {
            self.plans[e].as_mut().expect("planned above").used += 1;
        }
        let kick_due = self.config.kick_every > 0.0
            && self.step > 0
            && self.step.is_multiple_of(((self.config.kick_every * CONTROL_HZ).round() as usize).max(1));
        let kick_max = self.config.kick_max;
        let rng = &mut self.rng;
        let kicks: Vec<Option<[f64; 2]>> = alive
            .iter()
            .map(|_| {
                kick_due.then(|| {
                    let (angle, speed) = (rng.random::<f64>() * std::f64::consts::TAU, rng.random::<f64>() * kick_max);
                    [speed * angle.cos(), speed * angle.sin()]
                })
            })
            .collect();
        let mut stepping: Vec<(&mut Env, &Vec<f32>)> =
            self.envs.iter_mut().zip(&actions).filter_map(|(env, a)| a.as_ref().map(|a| (env, a))).collect();
        let standing: Vec<bool> = stepping
            .par_iter_mut()
            .zip(&kicks)
            .map(|((env, a), kick)| {
                // A physics blow-up ends the episode like a fall.
                let ok = env.step(a).is_ok() && kick.is_none_or(|k| env.kick(k).is_ok());
                ok && !env.fallen()
            })
            .collect();
        drop(stepping);
        let physics_ms = t_physics.elapsed().as_secs_f32() * 1e3;
        let mut fell = Vec::new();
        for (&e, standing) in alive.iter().zip(standing) {
            self.histories[e].act(actions[e].as_ref().expect("acted above"));
            if standing {
                let bodies = self.envs[e].bodies();
                self.histories[e].observe(&bodies);
                self.recent[e].observe(&bodies);
            } else {
                self.alive[e] = false;
                fell.push(e);
            }
        }
        self.step += 1;
        Ok(StepOutcome { actions, fell, model_ms, physics_ms })
    }
}

/// Moves each plan's first action the share `beta` of the way to what the model's inverse
/// dynamics reads out of the current state (the last of each conditioning's) and the plan's next
/// state. The model's actions are clean expert actions, nearly independent of the states that
/// follow them in the data, so a guided next state barely moves them (README, "Inverse
/// dynamics").
fn blend_inverse_dynamics(model: &TrajectoryModel, beta: f32, cond: &[f32], futures: &mut [f32]) {
    let inverse = model.inverse.as_ref().expect("check_sampler refuses a model without one");
    let (layout, sd) = (model.layout(), model.layout().state_dim);
    let traj = Layout { horizon: layout.spec.horizon };
    let mut pairs = Vec::with_capacity(2 * sd * futures.len() / traj.len());
    for (c, future) in cond.chunks_exact(layout.cond_len()).zip(futures.chunks_exact(traj.len())) {
        pairs.extend_from_slice(layout.current_state(c));
        pairs.extend_from_slice(&future[traj.state(1)..][..sd]);
    }
    let actions = inverse.actions(&pairs, futures.len() / traj.len());
    for (future, a) in futures.chunks_exact_mut(traj.len()).zip(actions.chunks_exact(NUM_DOFS)) {
        for (p, q) in future[traj.action(0)..][..NUM_DOFS].iter_mut().zip(a) {
            *p += beta * (q - *p);
        }
    }
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
    let mut controller = Controller::new(model, humanoid, clip, tasks.len(), config)?;
    for (e, task) in tasks.iter().enumerate().filter(|(_, t)| !t.obstacles.is_empty()) {
        controller.place_obstacles(e, &task.obstacles)?;
    }
    let envs_n = tasks.len();
    let steps = (config.seconds * CONTROL_HZ).round() as usize;
    let mut out = Rollout::new(
        RolloutInfo::new(model_name, model, config, tasks.clone(), format!("clip '{}'", clip.name)),
        envs_n,
        steps,
        humanoid.nq(),
    );
    for e in 0..envs_n {
        out.record(e, 0, controller.env(e));
    }
    let started = Instant::now();
    for step in 0..steps {
        let time = step as f64 / CONTROL_HZ;
        let outcome = controller.step(&tasks, time)?;
        for (e, a) in outcome.actions.iter().enumerate() {
            if let Some(a) = a {
                let (plan, touched) =
                    (controller.intent(e).expect("acted on a plan"), controller.env(e).touching_obstacle());
                out.record_action(e, step, a, &tasks[e].command(time), plan, touched);
                if let Some((hand, _)) = tasks[e].reach {
                    let at = controller.planned_body(e, hand.body()).expect("acted on a plan");
                    out.record_planned_hand(e, step, at.to_array());
                }
            }
        }
        for &e in &outcome.fell {
            out.survived[e] = step + 1;
        }
        for e in 0..envs_n {
            if controller.is_alive(e) || out.survived[e] == step + 1 {
                out.record(e, step + 1, controller.env(e));
            } else {
                out.repeat_row(e, step);
            }
        }
        let alive = (0..envs_n).filter(|&e| controller.is_alive(e)).count();
        out.model_ms.push(outcome.model_ms);
        out.physics_ms.push(outcome.physics_ms);
        on_step(&StepReport { step: step + 1, alive, model_ms: outcome.model_ms, physics_ms: outcome.physics_ms });
        if config.paced {
            let due = Duration::from_secs_f64((step + 1) as f64 / CONTROL_HZ);
            if let Some(wait) = due.checked_sub(started.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        if alive == 0 {
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
