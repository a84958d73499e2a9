//! `flowmimic run`: the trained model drives the humanoid, optionally steered by a task.

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use flowmimic_control::controller::start_pose;
use flowmimic_control::recommended::{DEFAULT_NFE, DEFAULT_SCALE, Settings};
use flowmimic_control::{
    Adaptive, ControlConfig, Hand, JoystickSegment, Recommended, Rollout, StartActions, StepReport, Task,
};
use flowmimic_eval::HAND_REACHED;
use flowmimic_eval::outcome::{BEFORE_FALL, FOLLOWED_SPEED, FOLLOWED_YAW_RATE, Outcome};
use flowmimic_eval::protocols::{SEGMENT_SETTLE, setting_name};
use flowmimic_model::{Gradient, TrajectoryModel};
use flowmimic_motion::Clip;
use flowmimic_serve::play::PlayConfig;
use flowmimic_sim::{Humanoid, Obstacle};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum TaskKind {
    /// Unguided walking.
    Walk,
    /// Follow --schedule (default: forward, backward, turn left, turn right, 3 s each).
    Joystick,
    /// Reach --target with --hand while walking at --schedule's first velocity.
    Reach,
    /// Walk to --goal.
    Waypoint,
    /// Walk to --goal while reaching --target with --hand.
    Compose,
}

#[derive(Args)]
pub struct RunArgs {
    /// Model directory (`flowmimic train` writes it; default: the one `make run` trained, else
    /// the shipped guidance model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = TaskKind::Walk)]
    pub task: TaskKind,
    /// Joystick schedule: `seconds:vx,vy,yaw_rate` segments separated by `;` (character frame:
    /// x forward, y left, m/s; yaw rate rad/s).
    #[arg(long)]
    pub schedule: Option<String>,
    #[arg(long, value_enum, default_value_t = HandArg::Right)]
    pub hand: HandArg,
    /// Hand target in the world, `x,y,z` metres (the humanoid starts at the origin facing +x;
    /// with --envs N each environment is given its task as seen from where it starts;
    /// the shipped model's hand reaches 0.7-1.0 m high) [default: 2.0,-0.4,0.85].
    #[arg(long)]
    pub target: Option<String>,
    /// Pelvis goal in the world, `x,y` metres [default: 4.0,2.0].
    #[arg(long)]
    pub goal: Option<String>,
    /// Solid obstacles, walked around by any task: a .toml or .json file (examples/obstacles.toml
    /// says how) or inline cylinders `x,y,radius[@vx,vy];...` (world metres; @ moving at m/s).
    #[arg(long)]
    pub obstacles: Option<String>,
    #[command(flatten)]
    pub drive: DriveArgs,
    /// Simulated seconds (default: the joystick schedule's length, else 10 s).
    #[arg(long, allow_negative_numbers = true, value_parser = crate::args::seconds)]
    pub seconds: Option<f64>,
    /// Actions of each sampled trajectory to execute before sampling again (1 = the paper's
    /// receding horizon, up to H + 1).
    #[arg(long, default_value_t = 1)]
    pub execute: usize,
    /// Environments run at once (one batched model call per step).
    #[arg(long, default_value_t = 1, value_parser = crate::args::envs)]
    pub envs: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Pace the loop at 30 Hz of wall-clock time.
    #[arg(long)]
    pub paced: bool,
    /// Start from this clip's frames (default: the generated straight walk).
    #[arg(long)]
    pub clip: Option<PathBuf>,
    /// Rollout file; default runs/run/<task>.rollout.safetensors.
    #[arg(short, long)]
    pub out: Option<PathBuf>,
}

/// How the model is driven by `run`, `play` and `demo`. A setting left out comes from the
/// model directory's recommended settings for the task ([`flowmimic_control::recommended`]),
/// else from the built-in default.
#[derive(Args, Clone, Default)]
pub struct DriveArgs {
    /// Network evaluations per control step (default: the model's recommended.toml for the
    /// task, else 5).
    #[arg(long)]
    pub nfe: Option<usize>,
    /// Guidance scale w (v' = v - w grad G); each task's gradient is scaled to its error
    /// (m/s, rad/s, m) in the model's normalised coordinates, so w means the same for every
    /// task; 0 for none (default: the model's recommended.toml for the task, else 10).
    #[arg(long, allow_negative_numbers = true)]
    pub guidance_scale: Option<f32>,
    /// With a hand target: walk up to it (a pursuit command toward a point beside it that
    /// brings the hand there; with a waypoint, toward that point within 0.4 m of it) instead of
    /// walking on (true without a value; default: the model's recommended.toml for the task,
    /// else false).
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub approach: Option<bool>,
    #[command(flatten)]
    pub guidance: GuidanceArgs,
}

/// How guidance acts, beside its scale: shared by `run`, `play`, `demo` and `eval`; like
/// [`DriveArgs`], a setting left out comes from the model, else the default.
#[derive(Args, Clone, Default)]
pub struct GuidanceArgs {
    /// How guidance takes its gradient: through-network (a vector-Jacobian product through the
    /// denoiser, so a cost on states reaches the executed action) or cost-only.
    #[arg(long, value_parser = parse_gradient, default_value = "through-network")]
    pub gradient: Gradient,
    /// Solver steps that apply guidance, `start:end` (default: the model's recommended.toml for
    /// the task, else all but the last quarter).
    #[arg(long, value_parser = parse_interval)]
    pub guidance_interval: Option<(usize, usize)>,
    /// Adaptive guidance: each environment's scale becomes w times its executed joystick error
    /// over the last half second (m/s and rad/s) divided by this reference error, within w/4
    /// and w; other tasks keep w. 0: the fixed scale w throughout (default: the model's
    /// recommended.toml for the task, else 0).
    #[arg(long, allow_negative_numbers = true, value_parser = parse_adaptive)]
    pub adaptive: Option<f32>,
    /// Share BETA of the executed action taken from inverse dynamics, 0 to 1: the action that
    /// the model directory's inverse dynamics (`flowmimic inverse`) reads out of the current
    /// state and the plan's next state, blended as a_plan + BETA (a_inverse - a_plan). 0: the
    /// plan's own action (the paper; default: the model's recommended.toml for the task, else
    /// 0).
    #[arg(long, allow_negative_numbers = true, value_name = "BETA")]
    pub inverse_dynamics: Option<f32>,
    /// The most the joystick velocity asked of guidance speeds up, m/s^2 on each of the forward
    /// and sideways axes (the turn rate is asked as given); slowing down is not limited. 0: the
    /// command as given (the paper; default: the model's
    /// recommended.toml for the task, else 0).
    #[arg(long, allow_negative_numbers = true, value_name = "M_PER_S2")]
    pub acceleration: Option<f32>,
    /// For a model trained with labels (`[model] command_labels`: told the joystick's command
    /// or a waypoint's pursuit): how much the label weighs, by classifier-free guidance. 0: as
    /// if told nothing (the baseline the guidance scale's 0 is for other models), 1: as told
    /// (default: the model's recommended.toml for the task, else 1), above 1: past it, at two
    /// network calls a step.
    #[arg(long, allow_negative_numbers = true, value_name = "S")]
    pub label_scale: Option<f32>,
    /// The actions in the model's first history (the steps before the start frame, which the
    /// first plan is conditioned on; a clip holds poses only): pd-targets, each next frame's
    /// joint angles, or inverse-dynamics, what the model directory's inverse.safetensors reads
    /// out of each frame and the next, like the experts' actions in the data (halves the arms
    /// models' falls in the first 3 s of a walk; default: the model's recommended.toml for the
    /// task, else pd-targets).
    #[arg(long, value_parser = parse_start_actions, value_name = "pd-targets|inverse-dynamics")]
    pub start_actions: Option<StartActions>,
    #[command(flatten)]
    pub execution: ExecutorArgs,
}

/// Which settings a command drives a model with, and where each came from.
#[derive(Clone, Debug)]
pub struct Chosen {
    pub nfe: usize,
    pub guidance_scale: f32,
    pub adaptive: Option<Adaptive>,
    pub inverse_dynamics: f32,
    pub acceleration: f32,
    pub label_scale: f32,
    pub guidance_interval: Option<(usize, usize)>,
    pub approach: bool,
    pub start_actions: StartActions,
    /// The tracking run that executes the plans (checked), and the share of its residual.
    pub executor: Option<PathBuf>,
    pub executor_residual: f32,
}

impl DriveArgs {
    /// These flags over `model`'s recommended settings, over the defaults; prints each
    /// setting with where it came from (flag, model, default).
    pub fn choose(&self, model: &Settings, task: &str) -> Result<Chosen> {
        self.choose_over(model, "model", task)
    }

    /// These flags over `settings` (from `source`), over the defaults.
    pub fn choose_over(&self, model: &Settings, source: &str, task: &str) -> Result<Chosen> {
        let g = &self.guidance;
        let mut said = Vec::new();
        let mut pick = |name: &str, flag: Option<String>, from_model: Option<String>, default: &str| {
            let (value, source) = match (flag, from_model) {
                (Some(v), _) => (v, "flag"),
                (None, Some(v)) => (v, source),
                (None, None) => (default.to_string(), "default"),
            };
            said.push(format!("{name} {value} ({source})"));
        };
        let fmt = |x: Option<f32>| x.map(|x| format!("{x}"));
        let interval = |i: Option<(usize, usize)>| i.map(|(a, b)| format!("{a}:{b}"));
        pick("NFE", self.nfe.map(|n| n.to_string()), model.nfe.map(|n| n.to_string()), &DEFAULT_NFE.to_string());
        // An unguided walk uses no guidance setting: naming them would suggest it does.
        let guided = task != "walk";
        if guided {
            pick("w", fmt(self.guidance_scale), fmt(model.guidance_scale), &DEFAULT_SCALE.to_string());
            pick("adaptive", fmt(g.adaptive), fmt(model.adaptive), "0");
        }
        pick("inverse dynamics", fmt(g.inverse_dynamics), fmt(model.inverse_dynamics), "0");
        if guided {
            pick("acceleration", fmt(g.acceleration), fmt(model.acceleration), "0");
            let model_interval = model.guidance_interval.map(|[a, b]| (a, b));
            pick("guidance steps", interval(g.guidance_interval), interval(model_interval), "all but the last quarter");
            pick("approach", self.approach.map(|a| a.to_string()), model.approach.map(|a| a.to_string()), "false");
        }
        // Only a labelled model has a label to weigh: named where a flag or the model sets it.
        if g.label_scale.is_some() || model.label_scale.is_some() {
            pick("label scale", fmt(g.label_scale), fmt(model.label_scale), "1");
        }
        let start = |a: Option<StartActions>| a.map(|a| setting_name(&a));
        pick("start actions", start(g.start_actions), start(model.start_actions), "pd-targets");
        let flag_executor = g.execution.executor();
        let executor = flag_executor.clone().unwrap_or_else(|| model.executor.clone());
        let shown = |e: &Option<PathBuf>| e.as_ref().map_or("none".into(), |e| e.display().to_string());
        pick(
            "executor",
            flag_executor.as_ref().map(shown),
            model.executor.as_ref().map(|e| e.display().to_string()),
            "none",
        );
        if executor.is_some() {
            let residual = flowmimic_control::executor::DEFAULT_RESIDUAL.to_string();
            pick("executor residual", fmt(g.execution.executor_residual), fmt(model.executor_residual), &residual);
        } else if g.execution.executor_residual.is_some() {
            eprintln!("note: --executor-residual is not used without an executor (--executor or the model's)");
        }
        eprintln!("settings for {task}: {}", said.join(", "));
        let flags = Settings {
            nfe: self.nfe,
            guidance_scale: self.guidance_scale,
            adaptive: g.adaptive,
            inverse_dynamics: g.inverse_dynamics,
            acceleration: g.acceleration,
            label_scale: g.label_scale,
            guidance_interval: g.guidance_interval.map(|(a, b)| [a, b]),
            approach: self.approach,
            start_actions: g.start_actions,
            executor: None,
            executor_residual: g.execution.executor_residual,
        };
        // The flag's "none" turns the model's executor off, which `or` would keep.
        let settings = Settings { executor, ..flags.or(model) };
        if let Some(run) = &settings.executor {
            check_executor(run)?;
        }
        let config = settings.control(g.gradient, 0.0).map_err(|e| anyhow::anyhow!("{e} (from flags or the model)"))?;
        if config.executor.is_some() && config.executor_residual == 0.0 {
            eprintln!(
                "note: executor residual 0 executes the plans' own actions, with the executor's policy still run every \
                 step; --executor none does the same without it"
            );
        }
        Ok(Chosen {
            nfe: config.nfe,
            guidance_scale: config.guidance_scale,
            adaptive: config.adaptive,
            inverse_dynamics: config.inverse_dynamics,
            acceleration: config.acceleration,
            label_scale: config.label_scale,
            guidance_interval: config.guidance_steps,
            approach: settings.approaches(),
            start_actions: config.start_actions,
            executor: config.executor,
            executor_residual: config.executor_residual,
        })
    }
}

impl Chosen {
    /// A control configuration with these settings for `seconds`.
    pub fn control(&self, gradient: Gradient, seconds: f64) -> ControlConfig {
        ControlConfig {
            gradient,
            guidance_steps: self.guidance_interval,
            adaptive: self.adaptive,
            inverse_dynamics: self.inverse_dynamics,
            acceleration: self.acceleration,
            label_scale: self.label_scale,
            start_actions: self.start_actions,
            executor: self.executor.clone(),
            executor_residual: self.executor_residual,
            ..ControlConfig::new(self.nfe, self.guidance_scale, seconds)
        }
    }
}

/// A model directory's recommended settings for a task (`walk`, `joystick`, `reach`,
/// `waypoint`, `compose`, `play`).
pub fn recommended(dir: &Path, task: &str) -> Result<Settings> {
    Ok(Recommended::load(dir)?.for_task(task))
}

/// A setting by the name `recommended.toml` uses (`pd-targets`), else an error listing `choices`.
pub(crate) fn parse_named<T: serde::de::DeserializeOwned>(text: &str, choices: &str) -> Result<T, String> {
    serde_json::from_str(&format!("\"{text}\"")).map_err(|_| format!("'{text}': use {choices}"))
}

fn parse_start_actions(text: &str) -> Result<StartActions, String> {
    parse_named(text, "pd-targets or inverse-dynamics")
}

/// `start:end` with start < end: the solver steps guidance acts on.
fn parse_interval(text: &str) -> Result<(usize, usize), String> {
    let parsed = text.split_once(':').and_then(|(a, b)| Some((a.parse().ok()?, b.parse().ok()?)));
    parsed.filter(|(a, b)| a < b).ok_or_else(|| format!("'{text}': use start:end with start < end"))
}

/// A reference error for adaptive guidance (> 0), or 0 for the fixed scale.
fn parse_adaptive(text: &str) -> Result<f32, String> {
    let value: f32 = text.parse().map_err(|_| format!("'{text}': not a number"))?;
    if value == 0.0 {
        return Ok(0.0);
    }
    Adaptive::new(value).map(|a| a.reference).map_err(|e| e.to_string())
}

/// `through-network` or `cost-only`.
fn parse_gradient(text: &str) -> Result<Gradient, String> {
    parse_named(text, "through-network or cost-only")
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum HandArg {
    Left,
    Right,
}

/// Comma-separated numbers, exactly `n` of them, every one finite.
fn numbers(text: &str, n: usize, what: &str) -> Result<Vec<f64>> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>().with_context(|| format!("{what}: '{v}' is not a number")))
        .collect::<Result<_>>()?;
    if values.len() != n {
        bail!("{what}: expected {n} numbers, got '{text}'");
    }
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        bail!("{what}: {v} is not finite");
    }
    Ok(values)
}

pub(crate) fn schedule(text: &str) -> Result<Vec<JoystickSegment>> {
    text.split(';')
        .enumerate()
        .map(|(i, seg)| {
            let what = format!("schedule segment {} '{seg}'", i + 1);
            if seg.trim().is_empty() {
                bail!("{what} is empty (a ';' too many?): use seconds:vx,vy,yaw_rate");
            }
            let (secs, v) = seg.split_once(':').with_context(|| format!("{what}: use seconds:vx,vy,yaw_rate"))?;
            let seconds = numbers(secs, 1, &format!("{what}: duration"))?[0];
            if seconds <= 0.0 {
                bail!("{what}: the duration must be above 0 s, not {seconds}");
            }
            let v = numbers(v, 3, &format!("{what}: velocity"))?;
            Ok(JoystickSegment { seconds, vx: v[0], vy: v[1], yaw_rate: v[2] })
        })
        .collect()
}

/// Obstacles from `--obstacles`: a file (`.toml`: `[[obstacle]]` tables; `.json`: a list) or
/// inline cylinders `x,y,radius[@vx,vy]` separated by `;`.
pub(crate) fn obstacles(spec: &str) -> Result<Vec<Obstacle>> {
    // A file that is not here is looked up in the checkout (examples/obstacles.toml from anywhere).
    let resolved = crate::paths::resolve(Path::new(spec));
    let path = resolved.as_path();
    let list: Vec<serde_json::Value> = match path.extension().and_then(|e| e.to_str()) {
        Some("toml") => {
            let text = flowmimic_io::read_to_string(path)?;
            let file: toml::Table = toml::from_str(&text).with_context(|| format!("{spec}: not TOML"))?;
            let keys: Vec<&String> = file.keys().filter(|k| *k != "obstacle").collect();
            if !keys.is_empty() {
                bail!("{spec}: unknown table or key {keys:?}: the file holds [[obstacle]] tables only");
            }
            let tables = file.get("obstacle").cloned().unwrap_or(toml::Value::Array(Vec::new()));
            serde_json::to_value(tables)?
                .as_array()
                .cloned()
                .with_context(|| format!("{spec}: use [[obstacle]] tables"))?
        }
        Some("json") => serde_json::from_str(&flowmimic_io::read_to_string(path)?)
            .with_context(|| format!("{spec}: not a JSON list of obstacles"))?,
        _ => {
            return spec
                .split(';')
                .filter(|one| !one.trim().is_empty())
                .enumerate()
                .map(|(i, one)| {
                    let (place, velocity) = match one.split_once('@') {
                        Some((p, v)) => (p, numbers(v, 2, "obstacle velocity")?),
                        None => (one, vec![0.0, 0.0]),
                    };
                    let c = numbers(place, 3, "obstacle (x,y,radius[@vx,vy], or a .toml or .json file)")?;
                    let o = Obstacle::cylinder([c[0], c[1]], c[2]).moving([velocity[0], velocity[1]]);
                    o.validate().map_err(|e| anyhow::anyhow!("--obstacles {spec}: obstacle {}: {e}", i + 1))?;
                    Ok(o)
                })
                .collect();
        }
    };
    list.into_iter()
        .enumerate()
        .map(|(i, v)| {
            let at = || format!("{spec}: obstacle {}", i + 1);
            let Some(table) = v.as_object() else { bail!("{}: not a table of an obstacle's keys", at()) };
            let kind = table.get("type").and_then(|t| t.as_str()).unwrap_or("");
            let keys = Obstacle::keys(kind);
            let unknown: Vec<&String> = table.keys().filter(|k| !keys.contains(&k.as_str())).collect();
            if !unknown.is_empty() {
                bail!("{}: unknown key {unknown:?} for a {kind:?} obstacle (it has {keys:?})", at());
            }
            let o: Obstacle = serde_json::from_value(v).with_context(at)?;
            o.validate().map_err(|e| anyhow::anyhow!("{}: {e}", at()))?;
            Ok(o)
        })
        .collect()
}

impl RunArgs {
    /// The task's name, as its recommended settings are filed.
    pub fn task_name(&self) -> String {
        format!("{:?}", self.task).to_lowercase()
    }

    pub fn task(&self, approach: bool) -> Result<Task> {
        let hand = match self.hand {
            HandArg::Left => Hand::Left,
            HandArg::Right => Hand::Right,
        };
        let target = || -> Result<[f64; 3]> {
            Ok(numbers(self.target.as_deref().unwrap_or("2.0,-0.4,0.85"), 3, "--target")?.try_into().expect("3"))
        };
        let goal = || -> Result<[f64; 2]> {
            Ok(numbers(self.goal.as_deref().unwrap_or("4.0,2.0"), 2, "--goal")?.try_into().expect("2"))
        };
        let joystick = match &self.schedule {
            Some(s) => schedule(s)?,
            None => Task::joystick_eval().joystick,
        };
        let walk_on = vec![JoystickSegment { seconds: self.seconds(), ..joystick[0] }];
        let task = match self.task {
            TaskKind::Walk => Task::walk(),
            TaskKind::Joystick => Task { joystick, ..Task::walk() },
            TaskKind::Reach if approach => Task { reach: Some((hand, target()?)), approach: true, ..Task::walk() },
            TaskKind::Reach => Task { joystick: walk_on, reach: Some((hand, target()?)), ..Task::walk() },
            TaskKind::Waypoint => Task { waypoint: Some(goal()?), ..Task::walk() },
            TaskKind::Compose => {
                Task { waypoint: Some(goal()?), reach: Some((hand, target()?)), approach, ..Task::walk() }
            }
        };
        let obstacles = match &self.obstacles {
            Some(spec) => obstacles(spec)?,
            None => Vec::new(),
        };
        let task = Task { obstacles, ..task };
        task.validate()?;
        let unused = |given: bool, flag: &str, uses: &[TaskKind]| {
            if given && !uses.contains(&self.task) {
                eprintln!("note: --{flag} is not used by --task {}", self.task_name());
            }
        };
        unused(self.target.is_some(), "target", &[TaskKind::Reach, TaskKind::Compose]);
        unused(self.goal.is_some(), "goal", &[TaskKind::Waypoint, TaskKind::Compose]);
        unused(self.schedule.is_some(), "schedule", &[TaskKind::Joystick, TaskKind::Reach]);
        Ok(task)
    }

    /// How long to run: `--seconds`, else the joystick schedule's length for a joystick task,
    /// else 10 s.
    pub fn seconds(&self) -> f64 {
        let joystick = || match &self.schedule {
            Some(s) => schedule(s).ok().map(|joystick| Task { joystick, ..Task::walk() }),
            None => Some(Task::joystick_eval()),
        };
        match (self.seconds, self.task) {
            (Some(s), _) => s,
            (None, TaskKind::Joystick) => joystick().map_or(10.0, |t| t.schedule_seconds()),
            (None, _) => 10.0,
        }
    }

    pub fn control(&self, chosen: &Chosen) -> ControlConfig {
        let plain = chosen.control(self.drive.guidance.gradient, self.seconds());
        ControlConfig { execute: self.execute, paced: self.paced, seed: self.seed, ..plain }
    }
}

/// A model directory, refused when its states and actions are not this humanoid's, or when it
/// is not a model at all.
pub fn load_model(dir: &Path) -> Result<TrajectoryModel> {
    if !dir.join("model.safetensors").exists() {
        if dir.join(flowmimic_track::train::POLICY_FILE).exists() {
            bail!(
                "{} is a tracking expert (`flowmimic track train` writes those), not a trajectory model \
                 (`flowmimic train` writes model.safetensors): e.g. --model {}",
                dir.display(),
                crate::paths::SHIPPED_MODEL
            );
        }
        if !dir.is_dir() {
            bail!(
                "{}: no such model directory (`flowmimic train` makes one; the shipped one is --model {}, \
                 found from the checkout or beside the binary)",
                dir.display(),
                crate::paths::shipped(crate::paths::SHIPPED_MODEL).display()
            );
        }
    }
    flowmimic_control::load_model(dir).with_context(|| format!("loading model {}", dir.display()))
}

/// Refuses settings the model in `dir` cannot run, naming the folder, before a run begins.
pub fn check_sampler(model: &TrajectoryModel, dir: &Path, control: &ControlConfig) -> Result<()> {
    flowmimic_control::controller::check_sampler(model, control).with_context(|| format!("{}", dir.display()))
}

/// The clip a run starts from: a file, or the generated 10 s straight walk.
pub fn start_clip(humanoid: &Arc<Humanoid>, file: Option<&Path>) -> Result<Clip> {
    Ok(match file {
        Some(f) => Clip::load(humanoid, f)?,
        None => flowmimic_motion::straight_walk(humanoid)?,
    })
}

pub fn run(args: RunArgs, humanoid: &Arc<Humanoid>) -> Result<()> {
    let model_dir = crate::paths::model_or_default(args.model.clone());
    let model = load_model(&model_dir)?;
    let name = args.task_name();
    let chosen = args.drive.choose(&recommended(&model_dir, &name)?, &name)?;
    let task = args.task(chosen.approach)?;
    let control = args.control(&chosen);
    check_sampler(&model, &model_dir, &control)?;
    if args.task == TaskKind::Joystick {
        let length = task.schedule_seconds();
        if control.seconds < length - 1e-9 {
            eprintln!(
                "note: the schedule is {length} s long; --seconds {} runs its first {} s",
                control.seconds, control.seconds
            );
        } else if control.seconds > length + 1e-9 {
            eprintln!(
                "note: the schedule is {length} s long; its last segment holds for the {:.1} s after",
                control.seconds - length
            );
        }
    }
    let clip = start_clip(humanoid, args.clip.as_deref())?;
    let out = args.out.clone().unwrap_or_else(|| PathBuf::from("runs/run").join(format!("{name}.rollout.safetensors")));
    // A task that asks nothing (unguided walking) is not guided, whatever the scale.
    let guidance = if args.task == TaskKind::Walk || control.guidance_scale == 0.0 {
        // A model told the command is steered by it without a guidance gradient.
        if model.config.command_labels && args.task != TaskKind::Walk { "no guidance gradient" } else { "unguided" }
            .to_string()
    } else {
        format!("guidance {} on steps {:?}", control.guidance_scale, control.guidance_steps())
    };
    let label = if model.config.task_labels {
        format!(", task label {}", setting_name(&task.task_label()))
    } else if model.config.command_labels {
        ", told the command".to_string()
    } else {
        String::new()
    };
    let executed = control
        .executor
        .as_ref()
        .map(|r| format!(", {}", executed_by(r, control.executor_residual)))
        .unwrap_or_default();
    eprintln!(
        "{} model (H {}{label}), NFE {}, {guidance}{executed}, task {name}, {} env(s), {} s",
        model.objective.label(),
        model.layout().spec.horizon,
        control.nfe,
        args.envs,
        control.seconds
    );
    let status = |r: &StepReport| {
        if r.step.is_multiple_of(30) {
            eprintln!(
                "t {:>5.1} s  alive {:>3}  model {:>6.1} ms  physics {:>5.1} ms  ({:.0} Hz possible)",
                r.step as f64 / flowmimic_sim::CONTROL_HZ,
                r.alive,
                r.model_ms,
                r.physics_ms,
                1e3 / (r.model_ms + r.physics_ms)
            );
        }
    };
    // Environments start at different frames of the clip, so at different places: each gets the
    // task as the first one sees it from where it starts.
    let history = model.layout().spec.history;
    let first = start_pose(&clip, history, 0);
    let tasks: Vec<_> = (0..args.envs).map(|e| task.moved(&first, &start_pose(&clip, history, e))).collect();
    // An obstacle on the humanoid where it starts is a fall waiting: say so.
    for (i, o) in task.obstacles.iter().enumerate() {
        if o.distance([first.origin.x, first.origin.y], 0.0).0 < 0.3 {
            eprintln!(
                "note: obstacle {} stands within 0.3 m of where the humanoid starts ({:.2}, {:.2})",
                i + 1,
                first.origin.x,
                first.origin.y
            );
        }
    }
    let rollout =
        flowmimic_control::run(&model, humanoid, &clip, tasks, &control, &model_dir.display().to_string(), status)?;
    rollout.save(&out)?;
    print_outcome(&Outcome::of(&rollout));
    print_timing(&rollout);
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// Which tracking policy executes the plans, and how much of its residual (`run`, `play`,
/// `demo` and `eval`); each from the model's recommended.toml where not given.
#[derive(Args, Clone, Debug, Default)]
pub struct ExecutorArgs {
    /// Execute each plan with this tracking policy (a `track train` run on `track plan-clips`'
    /// clips) in place of the plan's own action: it steers the body back to the plan's next
    /// state after a push. An executor suits the plans of the model whose data its clips'
    /// expert made: pretrained/experts/executor-fm executes fm's plans, executor-walks
    /// fm-walks', and each model's recommended.toml names its own for walking and the joystick
    /// (not for play). `none`: the plan's own action (default: the model's recommended.toml for
    /// the task, else none).
    #[arg(long, value_name = "RUN|none")]
    pub executor: Option<PathBuf>,
    /// How much of the executor's residual (the correction it adds to each plan's action) is
    /// added, 0 to 1 (default: the model's recommended.toml for the task, else 0.5: half of
    /// executor-walks' residual held kicks about as well as all of it, and steered better).
    #[arg(long, value_name = "SHARE", allow_negative_numbers = true, value_parser = crate::args::share)]
    pub executor_residual: Option<f32>,
}

impl ExecutorArgs {
    /// The flag's executor: `None` without the flag, `Some(None)` for `none`, else the run,
    /// found under the checkout from any folder as models are.
    pub fn executor(&self) -> Option<Option<PathBuf>> {
        self.executor.as_deref().map(|e| (e != Path::new("none")).then(|| crate::paths::resolve(e)))
    }
}

/// Loads the executor `run` to refuse a bad one before anything starts, and says so when it
/// looks like an expert of clips rather than an executor.
pub(crate) fn check_executor(run: &Path) -> Result<()> {
    if !flowmimic_control::Executor::load(run)?.started_on_plans() {
        eprintln!(
            "note: executor {} was not trained as one (track.fresh_output is off, as in an expert of clips, which \
             fails plans within 2 s); an executor is trained with configs/executor.toml on `track plan-clips`' clips",
            run.display()
        );
    }
    Ok(())
}

/// "plans executed by RUN (residual x SHARE)", as `run` and `eval` name an executor.
pub(crate) fn executed_by(run: &Path, residual: f32) -> String {
    format!("plans executed by {} (residual x {residual})", run.display())
}

/// Per joystick segment, the speeds asked and achieved (the range over environments) and how
/// many environments followed it; the hand's closest approach; the way to the goal; falls.
pub(crate) fn print_outcome(o: &Outcome) {
    if !o.segments.is_empty() || o.unreached_segments > 0 {
        println!(
            "joystick, after {SEGMENT_SETTLE} s into each segment (followed: within {FOLLOWED_SPEED} m/s and \
             {FOLLOWED_YAW_RATE} rad/s, no fall)"
        );
        println!(
            "  {:<22} {:<17} {:<17} {:<17} {:>8}",
            "asked (fwd, left, yaw)", "forward m/s", "sideways m/s", "yaw rate rad/s", "followed"
        );
        // The range over environments (NaN ones, fallen before the segment, left out).
        let range = |values: &[[f64; 3]], i: usize| {
            let (lo, hi) = values
                .iter()
                .filter(|a| a[i].is_finite())
                .fold((f64::MAX, f64::MIN), |(lo, hi), a| (lo.min(a[i]), hi.max(a[i])));
            if lo > hi {
                "-".to_string()
            } else if lo == hi {
                format!("{lo:+.2}")
            } else {
                format!("{lo:+.2} to {hi:+.2}")
            }
        };
        for s in &o.segments {
            println!(
                "  {:<22} {:<17} {:<17} {:<17} {:>8}",
                format!("{:+.1}, {:+.1}, {:+.1}", s.asked[0], s.asked[1], s.asked[2]),
                range(&s.achieved, 0),
                range(&s.achieved, 1),
                range(&s.achieved, 2),
                format!("{}/{}", s.followed, s.achieved.len())
            );
            // What the model planned beside what the body did: a plan that already misses the
            // command is the model's (or guidance's) failure, a right plan missed the executor's.
            if s.planned.iter().flatten().any(|v| v.is_finite()) {
                let p = &s.planned;
                let row = format!("  {:<22} {:<17} {:<17} {:<17}", "  planned", range(p, 0), range(p, 1), range(p, 2));
                println!("{}", row.trim_end());
            }
        }
        if o.unreached_segments > 0 {
            let n = o.unreached_segments;
            let which = if n == 1 { "its last segment".to_string() } else { format!("its last {n} segments") };
            println!("  (the run ended before {which} began to count: --seconds sets its length)");
        }
    }
    if !o.reach.is_empty() {
        let min: Vec<f64> = o.reach.iter().map(|t| t.min).collect();
        let reached = o.reach.iter().filter(|t| t.reached()).count();
        println!(
            "reach: the hand came within {HAND_REACHED} m of its target in {reached} of {}; closest {}",
            min.len(),
            list(&min, "m")
        );
        // Where the plans put the hand beside where it went: a plan that reaches a target the
        // hand misses is the execution's miss, a plan that misses it the model's.
        let planned: Vec<f64> = o.reach.iter().map(|t| t.planned_min).collect();
        if planned.iter().any(|p| p.is_finite()) {
            println!("  planned (the hand at each plan's horizon's end): closest {}", list(&planned, "m"));
        }
    }
    if !o.waypoint.is_empty() {
        let arrived = o.waypoint.iter().filter(|t| t.arrival.is_some()).count();
        let closest: Vec<f64> = o.waypoint.iter().map(|t| t.closest).collect();
        let last: Vec<f64> = o.waypoint.iter().map(|t| t.last).collect();
        println!(
            "waypoint: the pelvis came within 0.5 m of the goal in {arrived} of {}; closest {}; at the end {}",
            last.len(),
            list(&closest, "m"),
            list(&last, "m")
        );
    }
    if let Some(touched) = &o.touched {
        let n = touched.iter().filter(|&&t| t > 0).count();
        println!("obstacles: touched in {n} of {} environments (control steps touching: {touched:?})", touched.len());
    }
    println!("{} of {} environments fell", o.falls.len(), o.envs);
    let (from, to) = BEFORE_FALL;
    for f in &o.falls {
        let [x, y, z] = f.achieved;
        let planned = if f.planned.iter().all(|v| v.is_finite()) {
            let [px, py, pz] = f.planned;
            format!("; its plans asked {px:+.2}, {py:+.2}, {pz:+.2}")
        } else {
            String::new()
        };
        println!(
            "  environment {} fell at {:.1} s; {from} to {to} s before, it moved {x:+.2} m/s forward, {y:+.2} sideways, \
             turning {z:+.2} rad/s{planned}",
            f.env, f.seconds
        );
    }
}

/// Values with a unit, all of them for a few, else their range.
fn list(values: &[f64], unit: &str) -> String {
    if values.len() <= 8 {
        values.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>().join(", ") + " " + unit
    } else {
        let (lo, hi) = values.iter().fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(*v), hi.max(*v)));
        format!("{lo:.2} to {hi:.2} {unit}")
    }
}

/// Timing medians of a rollout.
fn print_timing(r: &Rollout) {
    let (m, p) = r.median_ms();
    println!(
        "per control step (median, whole batch): model {m:.1} ms, physics {p:.1} ms, {:.0} Hz achievable ({})",
        1e3 / (m + p),
        if f64::from(1e3 / (m + p)) >= flowmimic_sim::CONTROL_HZ { "real time" } else { "slower than real time" }
    );
}

/// `flowmimic play`: the live session on 127.0.0.1:`port`.
pub fn play(
    humanoid: &Arc<Humanoid>,
    model_dir: &Path,
    port: u16,
    control: ControlConfig,
    clip: Option<&Path>,
    record_dir: PathBuf,
) -> Result<()> {
    let model = load_model(model_dir)?;
    let clip = start_clip(humanoid, clip)?;
    let model_name = model_dir.display().to_string();
    let session = flowmimic_serve::play::Session::start(
        model,
        Arc::clone(humanoid),
        clip,
        PlayConfig { control, record_dir, model_name },
    )?;
    flowmimic_serve::serve(session.router(), port, |url| println!("play: {url} (Ctrl-C stops it)"))?;
    Ok(())
}
