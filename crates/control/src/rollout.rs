//! The record of a controlled run, `flowmimic-rollout/1` in safetensors (E environments, T
//! control steps, readable with `safetensors.numpy.load_file`):
//!
//! | tensor    | shape            | meaning                                                     |
//! |-----------|------------------|-------------------------------------------------------------|
//! | `qpos`    | E x (T+1) x 76   | MuJoCo positions (root xyz, quaternion wxyz, 69 hinges)     |
//! | `state`   | E x (T+1) x 165  | the model's state features (docs/conventions.md, 2)         |
//! | `body_pos`| E x (T+1) x 24 x 3 | world positions of the 24 bodies (pelvis first)           |
//! | `action`  | E x T x 69       | executed normalised actions                                 |
//! | `command` | E x T x 8        | joystick (vx, vy, yaw rate), hand target xyz, waypoint xy   |
//! | `contact` | E x T            | 1 where the humanoid touched an obstacle during the step     |
//! | `plan`    | E x T x 3        | what the plan in force asked over its horizon: velocity in its own heading (forward, left m/s), turn rate (rad/s) |
//! | `plan_hand` | E x T x 3      | where the plan in force put the task's hand at its horizon's end (world m; NaN without a hand target) |
//! | `steps`   | E                | control steps survived (T unless the humanoid fell)         |
//! | `model_ms`, `physics_ms` | T | wall time per control step for the whole batch            |
//!
//! After a fall an environment's rows repeat its last state. Metadata `info` is JSON of
//! [`RolloutInfo`].

use flowmimic_io::tensors::{self, TensorError, TensorFile};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::{Env, NUM_BODIES, NUM_DOFS, STATE_DIM};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::Path;

use crate::task::{COMMAND_DIM, Task};

const FORMAT: &str = "flowmimic-rollout/1";

fn cost_only() -> flowmimic_model::Gradient {
    flowmimic_model::Gradient::CostOnly
}

/// What produced a rollout.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RolloutInfo {
    pub model: String,
    pub objective: String,
    pub nfe: usize,
    pub horizon: usize,
    pub guidance_scale: f32,
    pub guidance_steps: (usize, usize),
    /// How the guidance gradient was taken (files written before the choice: cost only).
    #[serde(default = "cost_only")]
    pub gradient: flowmimic_model::Gradient,
    /// Adaptive guidance's reference error (`None`: the fixed scale).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<crate::Adaptive>,
    /// Share of the executed action taken from inverse dynamics (files before it: none).
    #[serde(default)]
    pub inverse_dynamics: f32,
    pub tasks: Vec<Task>,
    pub seed: u64,
    pub start: String,
    /// Kicks: every this many seconds (0: none), up to this speed (m/s).
    pub kick_every: f64,
    pub kick_max: f64,
}

impl RolloutInfo {
    /// The record of `model` (labelled `model_name`) driving `tasks` under `config`, started
    /// from `start`.
    pub fn new(
        model_name: &str,
        model: &flowmimic_model::TrajectoryModel,
        config: &crate::ControlConfig,
        tasks: Vec<Task>,
        start: String,
    ) -> Self {
        Self {
            model: model_name.to_string(),
            objective: model.objective.name().to_string(),
            nfe: config.nfe,
            horizon: model.layout().spec.horizon,
            guidance_scale: config.guidance_scale,
            guidance_steps: config.guidance_steps(),
            gradient: config.gradient,
            adaptive: config.adaptive,
            inverse_dynamics: config.inverse_dynamics,
            tasks,
            seed: config.seed,
            start,
            kick_every: config.kick_every,
            kick_max: config.kick_max,
        }
    }
}

/// One environment's record of one step, as a rollout stores it.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub qpos: Vec<f32>,
    pub state: [f32; STATE_DIM],
    /// World positions of the 24 bodies, flat.
    pub body_pos: Vec<f32>,
}

impl Row {
    pub fn of(env: &Env) -> Self {
        Self {
            qpos: env.qpos().iter().map(|&q| q as f32).collect(),
            state: env.state(),
            body_pos: env.bodies().pos.iter().flat_map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Rollout {
    pub info: RolloutInfo,
    pub envs: usize,
    pub steps: usize,
    pub nq: usize,
    pub qpos: Vec<f32>,
    pub state: Vec<f32>,
    pub body_pos: Vec<f32>,
    pub action: Vec<f32>,
    pub command: Vec<f32>,
    /// 1 where the humanoid touched an obstacle during the step (E x T; files before it: 0).
    pub contact: Vec<f32>,
    /// What the plan in force at each step asked (E x T x 3, [`crate::Layout::intent`]; NaN
    /// after a fall and in files from before plans were kept).
    pub plan: Vec<f32>,
    /// Where the plan in force at each step put the task's hand at its horizon's end (E x T x
    /// 3, world; NaN without a hand target, after a fall and in files from before it was kept).
    pub plan_hand: Vec<f32>,
    pub survived: Vec<usize>,
    pub model_ms: Vec<f32>,
    pub physics_ms: Vec<f32>,
}

impl Rollout {
    /// An empty record of `envs` environments over `steps` control steps (every environment
    /// assumed to survive until [`Rollout::survived`] says otherwise).
    pub fn new(info: RolloutInfo, envs: usize, steps: usize, nq: usize) -> Self {
        Self {
            info,
            envs,
            steps,
            nq,
            qpos: vec![0.0; envs * (steps + 1) * nq],
            state: vec![0.0; envs * (steps + 1) * STATE_DIM],
            body_pos: vec![0.0; envs * (steps + 1) * NUM_BODIES * 3],
            action: vec![0.0; envs * steps * NUM_DOFS],
            command: vec![0.0; envs * steps * COMMAND_DIM],
            contact: vec![0.0; envs * steps],
            plan: vec![f32::NAN; envs * steps * 3],
            plan_hand: vec![f32::NAN; envs * steps * 3],
            survived: vec![steps; envs],
            model_ms: Vec::with_capacity(steps),
            physics_ms: Vec::with_capacity(steps),
        }
    }

    /// Writes row `k` (0..=T) of environment `e` from the simulator.
    pub fn record(&mut self, e: usize, k: usize, env: &Env) {
        self.put_row(e, k, &Row::of(env));
    }

    /// Writes row `k` (0..=T) of environment `e`.
    pub fn put_row(&mut self, e: usize, k: usize, row: &Row) {
        let at = e * (self.steps + 1) + k;
        self.state[at * STATE_DIM..(at + 1) * STATE_DIM].copy_from_slice(&row.state);
        self.qpos[at * self.nq..(at + 1) * self.nq].copy_from_slice(&row.qpos);
        self.body_pos[at * NUM_BODIES * 3..(at + 1) * NUM_BODIES * 3].copy_from_slice(&row.body_pos);
    }

    /// Writes the action executed, the command in force and what the plan asked at step `k`
    /// (0..T) of environment `e`, and whether it touched an obstacle.
    pub fn record_action(
        &mut self,
        e: usize,
        k: usize,
        action: &[f32],
        command: &[f32; COMMAND_DIM],
        plan: [f32; 3],
        touched: bool,
    ) {
        let at = e * self.steps + k;
        self.contact[at] = f32::from(u8::from(touched));
        self.plan[at * 3..(at + 1) * 3].copy_from_slice(&plan);
        self.action[at * NUM_DOFS..(at + 1) * NUM_DOFS].copy_from_slice(action);
        self.command[at * COMMAND_DIM..(at + 1) * COMMAND_DIM].copy_from_slice(command);
    }

    /// Writes where the plan in force at step `k` (0..T) of environment `e` put the task's hand.
    pub fn record_planned_hand(&mut self, e: usize, k: usize, hand: [f64; 3]) {
        let at = (e * self.steps + k) * 3;
        self.plan_hand[at..at + 3].copy_from_slice(&hand.map(|x| x as f32));
    }

    /// State `k` (0..=T) of environment `e`.
    pub fn state(&self, e: usize, k: usize) -> &[f32] {
        let at = (e * (self.steps + 1) + k) * STATE_DIM;
        &self.state[at..at + STATE_DIM]
    }

    /// World position of body `b` at step `k` of environment `e`.
    pub fn body(&self, e: usize, k: usize, b: usize) -> [f64; 3] {
        let at = ((e * (self.steps + 1) + k) * NUM_BODIES + b) * 3;
        [0, 1, 2].map(|i| f64::from(self.body_pos[at + i]))
    }

    /// Planar distance of the pelvis from `goal` (world x, y) at each step 1..=survived of
    /// environment `e`.
    pub fn pelvis_distances(&self, e: usize, goal: [f64; 2]) -> Vec<f64> {
        (1..=self.survived[e])
            .map(|k| {
                let p = self.body(e, k, body::PELVIS);
                (p[0] - goal[0]).hypot(p[1] - goal[1])
            })
            .collect()
    }

    pub fn qpos(&self, e: usize, k: usize) -> &[f32] {
        let at = (e * (self.steps + 1) + k) * self.nq;
        &self.qpos[at..at + self.nq]
    }

    /// The root's heading (rad, world) at step `k` of environment `e`.
    pub fn heading(&self, e: usize, k: usize) -> f64 {
        let q = self.qpos(e, k);
        flowmimic_geom::heading(flowmimic_geom::quat_from_wxyz([q[3], q[4], q[5], q[6]].map(f64::from)))
    }

    pub fn command(&self, e: usize, k: usize) -> &[f32] {
        let at = (e * self.steps + k) * COMMAND_DIM;
        &self.command[at..at + COMMAND_DIM]
    }

    /// What the plan in force at step `k` (0..T) of environment `e` asked: forward and left
    /// velocity (m/s) and heading rate (rad/s); NaN where none was recorded.
    pub fn plan(&self, e: usize, k: usize) -> [f32; 3] {
        let at = (e * self.steps + k) * 3;
        [self.plan[at], self.plan[at + 1], self.plan[at + 2]]
    }

    /// Where the plan in force at step `k` (0..T) of environment `e` put the task's hand (world
    /// m; NaN where none was recorded).
    pub fn planned_hand(&self, e: usize, k: usize) -> [f64; 3] {
        let at = (e * self.steps + k) * 3;
        [0, 1, 2].map(|i| f64::from(self.plan_hand[at + i]))
    }

    /// Control steps in which environment `e` touched an obstacle.
    pub fn contact_steps(&self, e: usize) -> usize {
        self.contact[e * self.steps..(e + 1) * self.steps].iter().filter(|&&c| c > 0.0).count()
    }

    /// Whether environment `e` fell before the end.
    pub fn fell(&self, e: usize) -> bool {
        self.survived[e] < self.steps
    }

    /// Median milliseconds per control step of the model and of the physics, over the steps
    /// taken (the padding after everyone fell excluded); NaN when none was.
    pub fn median_ms(&self) -> (f32, f32) {
        let median = |v: &[f32]| {
            let mut v: Vec<f32> = v.iter().copied().filter(|x| *x > 0.0).collect();
            v.sort_by(f32::total_cmp);
            v.get(v.len() / 2).copied().unwrap_or(f32::NAN)
        };
        (median(&self.model_ms), median(&self.physics_ms))
    }

    /// Copies environment `e`'s row `k` to row `k + 1` (a fallen environment stays put).
    pub fn repeat_row(&mut self, e: usize, k: usize) {
        let (from, to) = (e * (self.steps + 1) + k, e * (self.steps + 1) + k + 1);
        self.state.copy_within(from * STATE_DIM..(from + 1) * STATE_DIM, to * STATE_DIM);
        self.qpos.copy_within(from * self.nq..(from + 1) * self.nq, to * self.nq);
        let b = NUM_BODIES * 3;
        self.body_pos.copy_within(from * b..(from + 1) * b, to * b);
    }

    pub fn save(&self, path: &Path) -> Result<(), TensorError> {
        let (e, t) = (self.envs, self.steps);
        let survived: Vec<f32> = self.survived.iter().map(|&s| s as f32).collect();
        let meta = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("info".to_string(), serde_json::to_string(&self.info).expect("serialisable")),
        ]);
        tensors::save(
            path,
            &[
                ("qpos", vec![e, t + 1, self.nq], &self.qpos),
                ("state", vec![e, t + 1, STATE_DIM], &self.state),
                ("body_pos", vec![e, t + 1, NUM_BODIES, 3], &self.body_pos),
                ("action", vec![e, t, NUM_DOFS], &self.action),
                ("command", vec![e, t, COMMAND_DIM], &self.command),
                ("contact", vec![e, t], &self.contact),
                ("plan", vec![e, t, 3], &self.plan),
                ("plan_hand", vec![e, t, 3], &self.plan_hand),
                ("steps", vec![e], &survived),
                ("model_ms", vec![t], &self.model_ms),
                ("physics_ms", vec![t], &self.physics_ms),
            ],
            meta,
        )
    }

    pub fn load(path: &Path) -> Result<Self, TensorError> {
        let file = TensorFile::open(path)?;
        if file.meta("format")? != FORMAT {
            return Err(file.error(format!("not a {FORMAT} file")));
        }
        let info: RolloutInfo =
            serde_json::from_str(file.meta("info")?).map_err(|e| file.error(format!("metadata 'info': {e}")))?;
        let envs = info.tasks.len();
        let shape = file.shape("qpos")?;
        let [e, t1, nq] = shape[..] else {
            return Err(file.error(format!("tensor 'qpos' has shape {shape:?}, expected E x (T+1) x nq")));
        };
        if e != envs || t1 < 2 || envs == 0 {
            return Err(file.error(format!(
                "tensor 'qpos' has shape {shape:?} for {envs} tasks: a rollout has at least one environment and one step"
            )));
        }
        if nq != 76 {
            return Err(file.error(format!("tensor 'qpos' has {nq} coordinates per pose; the humanoid has 76")));
        }
        let t = t1 - 1;
        let survived: Vec<usize> = file
            .f32("steps", &[envs])?
            .iter()
            .map(|&s| if s.is_finite() && s >= 0.0 && s as usize <= t { Ok(s as usize) } else { Err(s) })
            .collect::<Result<_, _>>()
            .map_err(|s| file.error(format!("tensor 'steps' holds {s}, outside the rollout's 0-{t} steps")))?;
        Ok(Self {
            envs,
            steps: t,
            nq,
            qpos: file.f32("qpos", &[envs, t + 1, nq])?,
            state: file.f32("state", &[envs, t + 1, STATE_DIM])?,
            body_pos: file.f32("body_pos", &[envs, t + 1, NUM_BODIES, 3])?,
            action: file.f32("action", &[envs, t, NUM_DOFS])?,
            command: file.f32("command", &[envs, t, COMMAND_DIM])?,
            contact: match file.shape("contact") {
                Ok(_) => file.f32("contact", &[envs, t])?,
                Err(_) => vec![0.0; envs * t],
            },
            plan: match file.shape("plan") {
                Ok(_) => file.f32("plan", &[envs, t, 3])?,
                Err(_) => vec![f32::NAN; envs * t * 3],
            },
            plan_hand: match file.shape("plan_hand") {
                Ok(_) => file.f32("plan_hand", &[envs, t, 3])?,
                Err(_) => vec![f32::NAN; envs * t * 3],
            },
            survived,
            model_ms: file.f32("model_ms", &[t])?,
            physics_ms: file.f32("physics_ms", &[t])?,
            info,
        })
    }
}
