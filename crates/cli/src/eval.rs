//! `flowmimic eval ...`: the paper's experiments as arguments (which protocol, models and
//! points), run by `flowmimic_eval::experiments` with a progress bar.

use crate::progress::Progress;
use crate::run::{DriveArgs, GuidanceArgs, recommended, start_clip};
use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use flowmimic_control::StepReport;
use flowmimic_eval::experiments::{Study, Trials};
use flowmimic_eval::protocols::{ForestSetup, Point, STANDING_HEIGHTS, TargetHeights};
use flowmimic_eval::sweep::{EvalModel, Rows};
use flowmimic_sim::Humanoid;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Args, Clone)]
pub struct Common {
    /// Models as LABEL=DIR or DIR (labelled by the folder's name; repeat); default the one `make
    /// run` trained, else the shipped guidance model. Each runs at its own recommended.toml's
    /// settings for the protocol's task where a flag leaves one out.
    #[arg(long = "model")]
    models: Vec<String>,
    /// Output directory for CSV, JSON, plots and report.md.
    #[arg(short, long, default_value = "runs/eval")]
    out: PathBuf,
    /// Few trials and short episodes: minutes on 2 cores, for development and CI.
    #[arg(long)]
    quick: bool,
    /// Trials per point (default: the protocol's, or its quick count).
    #[arg(long, value_parser = crate::args::count)]
    trials: Option<usize>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Write each point's rollout (every trial, for `flowmimic view` and `render --env`) in
    /// OUT/rollouts when its trials run (a point already in OUT's CSV is not run again: give a
    /// new --out).
    #[arg(long)]
    save_rollouts: bool,
    /// Actions of each sampled trajectory executed before sampling again (1 = the paper).
    #[arg(long, default_value_t = 1)]
    execute: usize,
    /// Start trials from this clip's frames (default: the generated straight walk).
    #[arg(long)]
    clip: Option<PathBuf>,
    #[command(flatten)]
    guidance: GuidanceArgs,
}

impl Common {
    /// Settings for a programmatic run (the pipeline): models as LABEL=DIR.
    pub fn new(models: Vec<String>, out: PathBuf, quick: bool) -> Self {
        let guidance = GuidanceArgs::default();
        Self { models, out, quick, trials: None, seed: 0, save_rollouts: false, execute: 1, clip: None, guidance }
    }
}

/// The guidance scales a guided protocol is swept over, at one NFE.
#[derive(Args, Clone)]
pub struct Sweep {
    /// Guidance scales, for every model (default: each model's recommended w for the task, else
    /// 10, and 0 beside it where the protocol compares with unguided walking: joystick, reach,
    /// waypoint).
    #[arg(long, value_delimiter = ',')]
    pub scales: Vec<f32>,
    /// Network evaluations per step (default: each model's recommended, else 5).
    #[arg(long)]
    pub nfe: Option<usize>,
}

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Unguided walking under a random 0-0.5 m/s kick every second (paper Fig. 2): steps
    /// survived against NFE for each model.
    Survival {
        #[command(flatten)]
        common: Common,
        /// Network evaluations per step to measure, each model at every one (its recommended
        /// NFE is not used here).
        #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20")]
        nfe: Vec<usize>,
        /// Episode cap in seconds (default 1000 steps; quick 10 s).
        #[arg(long, allow_negative_numbers = true, value_parser = crate::args::seconds)]
        seconds: Option<f64>,
    },
    /// Forward, backward, turn left, turn right, 3 s each (paper Fig. 3): velocity RMSE
    /// against guidance scale for each model (give models of different horizons).
    Joystick {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        sweep: Sweep,
        /// Another schedule instead of the paper's, `run`'s syntax (`seconds:vx,vy,yaw_rate`
        /// segments joined by `;`, up to 8; quote it in a shell, and write `--schedule=-3:...`
        /// for a first value below 0): a row per segment, asked against achieved, and the share
        /// of trials that followed it (within 0.25 m/s and 0.25 rad/s, no fall; 8 trials).
        #[arg(long)]
        schedule: Option<String>,
    },
    /// Random right-hand targets while walking (paper Fig. 4): hand-target distance and the
    /// share of trials whose hand comes within 0.15 m, against guidance scale for each model.
    Reach {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        sweep: Sweep,
        /// Target heights `LOW,HIGH` (m), drawn uniformly (default 0.9,1.5; standing 0.5,1.6).
        /// The walking hand swings 0.74-0.85 m high; the default reaches above it, where
        /// walking-only data has no hand.
        #[arg(long, value_delimiter = ',')]
        heights: Vec<f64>,
        /// Reach while standing instead: targets 0.2-0.65 m out from the right shoulder, ahead
        /// to the side; within 0.10 m counts, with the median time to get there. Trials start
        /// from a generated standing clip unless --clip is given.
        #[arg(long, conflicts_with = "approach")]
        standing: bool,
        /// Walk up to each target (a pursuit command toward a point beside it that brings the
        /// hand there) instead of walking on with the hand's cost alone (true without a value;
        /// default: each model's recommended, else false; not with --standing).
        #[arg(long, num_args = 0..=1, default_missing_value = "true")]
        approach: Option<bool>,
    },
    /// Walk to a goal 3-4 m away at a bearing within 90 degrees: arrival rate (pelvis within
    /// 0.5 m), closest approach, time to arrive and distance at the end, against guidance scale.
    Waypoint {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        sweep: Sweep,
    },
    /// Walk to a goal 8-10 m ahead through standing cylinders (10-20 drawn, as many as fit 1 m
    /// apart) or, --moving, 2-3 crossing the way, in 20 s: success (arrived within 0.5 m, no
    /// contact, no fall), per trial too (--quick: 4 trials, still 20 s each).
    Forest {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        sweep: Sweep,
        /// 2-3 cylinders crossing the way at 0.5-1.0 m/s instead of a standing forest.
        #[arg(long)]
        moving: bool,
        /// The baseline: guidance ignores the obstacles (still solid), the waypoint alone.
        #[arg(long)]
        blind: bool,
    },
    /// Walk to a waypoint and touch a target there: success rate (pelvis within 0.5 m and hand
    /// within 0.15 m at once).
    Compose {
        #[command(flatten)]
        common: Common,
        #[command(flatten)]
        sweep: Sweep,
        /// Height of the hand target (m).
        #[arg(long, default_value_t = 1.2)]
        height: f64,
        /// Walk toward a point that brings the hand to the target, within 0.4 m of the waypoint,
        /// instead of to the waypoint itself (true without a value; default: each model's
        /// recommended, else false).
        #[arg(long, num_args = 0..=1, default_missing_value = "true")]
        approach: Option<bool>,
    },
    /// Fréchet distance between motion features of unguided generated walking and the
    /// dataset's expert rollouts (root height and velocity, head, hands and feet).
    Quality {
        #[command(flatten)]
        common: Common,
        /// The reference dataset.
        #[arg(long, default_value = "runs/data")]
        dataset: PathBuf,
        #[arg(long, value_delimiter = ',', default_value = "1,5,20")]
        nfe: Vec<usize>,
    },
    /// How far guidance moves the executed action `a_t` against the later predicted actions,
    /// and the task's error, for a backward joystick command, a left turn and a hand target,
    /// through the network and of the cost only (the model's output alone, no physics).
    Guidance {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "1,3,10,30")]
        scales: Vec<f32>,
        /// Network evaluations per step (default: each model's recommended, else 5).
        #[arg(long)]
        nfe: Option<usize>,
        /// Conditionings (start frames of the clip).
        #[arg(long, default_value_t = 32)]
        samples: usize,
    },
    /// Time per control step (model and physics, batch 1) against NFE.
    Latency {
        #[command(flatten)]
        common: Common,
        /// Network evaluations per step to time, each model at every one.
        #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20")]
        nfe: Vec<usize>,
        /// Measure the guided control step at this scale (joystick schedule; the gradient as
        /// --gradient says) instead of unguided walking.
        #[arg(long)]
        guided: Option<f32>,
    },
    /// What a saved rollout (`flowmimic run`, `play`'s record button, `demo`, `eval
    /// --save-rollouts`) achieved: each joystick segment's speeds against the asked ones and in
    /// how many environments it was followed, the hand's closest approach, the way to the goal,
    /// the obstacles touched, the falls.
    Outcome {
        /// A .rollout.safetensors file.
        rollout: PathBuf,
    },
}

/// The models given as LABEL=DIR or DIR (default the one `make run` trained, else the shipped one),
/// each with its settings for `task`: the flags in `drive` over its recommended.toml.
fn load_models(common: &Common, drive: &DriveArgs, task: &str) -> Result<Vec<EvalModel>> {
    let defaults;
    let specs = if common.models.is_empty() {
        defaults = [format!("fm={}", crate::paths::model_or_default(None).display())];
        &defaults[..]
    } else {
        &common.models[..]
    };
    specs
        .iter()
        .map(|s| {
            // A bare folder is labelled by its name.
            let (label, dir) = match s.split_once('=') {
                Some((label, dir)) => (label.to_string(), Path::new(dir)),
                None => {
                    let dir = Path::new(s);
                    let name = dir.file_name().with_context(|| format!("--model {s}: give LABEL=DIR or a folder"))?;
                    (name.to_string_lossy().into_owned(), dir)
                }
            };
            let dir = crate::paths::resolve(dir);
            let model = crate::run::load_model(&dir)?;
            eprint!("{label}: ");
            let chosen = drive.choose(&recommended(&dir, task)?, task)?;
            let sampler = Point {
                nfe: chosen.nfe,
                scale: chosen.guidance_scale,
                execute: common.execute,
                seed: common.seed,
                gradient: drive.guidance.gradient,
                guidance_steps: chosen.guidance_interval,
                adaptive: chosen.adaptive,
                inverse_dynamics: chosen.inverse_dynamics,
                acceleration: chosen.acceleration,
                label_scale: chosen.label_scale,
                start_actions: chosen.start_actions,
                approach: chosen.approach,
            };
            crate::run::check_sampler(&model, &dir, &sampler.control(0.0))?;
            let mut m = lib(EvalModel::new(&label, &dir, model, sampler))?;
            if let Some(executor) = &chosen.executor {
                let residual = chosen.executor_residual;
                m = lib(m.with_executor(executor, residual))?;
                eprintln!("{label}: {}", crate::run::executed_by(executor, residual));
            }
            Ok(m)
        })
        .collect()
}

fn progress_for(total_steps: usize) -> (Progress, impl Fn(&Progress, &StepReport)) {
    (Progress::new(total_steps, 0), |p: &Progress, r: &StepReport| {
        if r.step.is_multiple_of(30) {
            p.update(
                r.step,
                &format!("alive {:>3}  model {:>6.1} ms  physics {:>5.1} ms", r.alive, r.model_ms, r.physics_ms),
            );
        }
    })
}

/// `eval reach`'s default target heights (m): this project's first protocol.
pub const REACH_HEIGHTS: [f64; 2] = [0.9, 1.5];

/// `--heights LOW,HIGH`: finite, ordered, within the hand targets' 0-2.5 m.
fn reach_heights(h: &[f64]) -> Result<TargetHeights> {
    match *h {
        [low, high] if (0.0..=2.5).contains(&low) && (low..=2.5).contains(&high) => Ok(TargetHeights { low, high }),
        _ => anyhow::bail!("--heights {h:?}: give LOW,HIGH in metres with 0 <= LOW <= HIGH <= 2.5"),
    }
}

/// The library's boxed error as the command line's.
fn lib<T>(r: flowmimic_eval::sweep::Result<T>) -> Result<T> {
    r.map_err(|e| anyhow::anyhow!(e))
}

/// Runs a protocol with a progress bar over its control steps.
fn with_progress(steps: usize, f: &Trials) -> Rows {
    let (p, report) = progress_for(steps);
    let rows = f(&|r| report(&p, r));
    p.finish();
    rows
}

pub fn run(cmd: EvalCommand, humanoid: &Arc<Humanoid>) -> Result<()> {
    let common = match &cmd {
        EvalCommand::Outcome { rollout } => {
            let r = flowmimic_control::Rollout::load(rollout)?;
            crate::run::print_outcome(&flowmimic_eval::outcome::Outcome::of(&r));
            return Ok(());
        }

        EvalCommand::Survival { common, .. }
        | EvalCommand::Joystick { common, .. }
        | EvalCommand::Reach { common, .. }
        | EvalCommand::Waypoint { common, .. }
        | EvalCommand::Forest { common, .. }
        | EvalCommand::Compose { common, .. }
        | EvalCommand::Quality { common, .. }
        | EvalCommand::Guidance { common, .. }
        | EvalCommand::Latency { common, .. } => common.clone(),
    };
    // Settings left out come from each model's recommended ones for the protocol's task.
    let (task, nfe, approach) = match &cmd {
        EvalCommand::Joystick { sweep, .. } => ("joystick", sweep.nfe, None),
        EvalCommand::Guidance { nfe, .. } => ("joystick", *nfe, None),
        // Standing, there is nothing to walk up to.
        EvalCommand::Reach { sweep, standing: true, .. } => ("reach", sweep.nfe, Some(false)),
        EvalCommand::Reach { sweep, approach, .. } => ("reach", sweep.nfe, *approach),
        EvalCommand::Waypoint { sweep, .. } | EvalCommand::Forest { sweep, .. } => ("waypoint", sweep.nfe, None),
        EvalCommand::Compose { sweep, approach, .. } => ("compose", sweep.nfe, *approach),
        EvalCommand::Latency { guided: Some(_), .. } => ("joystick", None, None),
        _ => ("walk", None, None),
    };
    let drive = DriveArgs { nfe, guidance_scale: None, approach, guidance: common.guidance.clone() };
    let models = load_models(&common, &drive, task)?;
    let swept = match &cmd {
        EvalCommand::Guidance { scales, .. } => scales,
        EvalCommand::Joystick { sweep, .. }
        | EvalCommand::Reach { sweep, .. }
        | EvalCommand::Waypoint { sweep, .. }
        | EvalCommand::Forest { sweep, .. }
        | EvalCommand::Compose { sweep, .. } => &sweep.scales,
        _ => &Vec::new(),
    };
    if !swept.is_empty() {
        let w: Vec<String> = swept.iter().map(ToString::to_string).collect();
        eprintln!("every model at w {} (flag), not the w above", w.join(", "));
    }
    if let EvalCommand::Survival { nfe, .. } | EvalCommand::Latency { nfe, .. } = &cmd {
        let n: Vec<String> = nfe.iter().map(ToString::to_string).collect();
        eprintln!("every model at NFE {} (--nfe), not the NFE above", n.join(", "));
    }
    let clip = match &cmd {
        EvalCommand::Reach { standing: true, .. } if common.clip.is_none() => flowmimic_motion::standing(humanoid)?,
        _ => start_clip(humanoid, common.clip.as_deref())?,
    };
    let rollouts = common.save_rollouts.then(|| common.out.join("rollouts"));
    let study = Study {
        models: &models,
        humanoid,
        clip: &clip,
        out: &common.out,
        quick: common.quick,
        trials: common.trials,
        rollouts: rollouts.as_deref(),
        progress: &with_progress,
    };
    lib(match &cmd {
        EvalCommand::Survival { nfe, seconds, .. } => study.survival(nfe, *seconds),
        EvalCommand::Joystick { sweep, schedule: None, .. } => study.joystick(&sweep.scales),
        EvalCommand::Joystick { sweep, schedule: Some(text), .. } => {
            study.joystick_schedule(&sweep.scales, &crate::run::schedule(text)?)
        }
        EvalCommand::Reach { sweep, heights, standing: true, .. } => {
            let heights =
                if heights.is_empty() { STANDING_HEIGHTS } else { reach_heights(heights).map(|h| (h.low, h.high))? };
            study.reach_standing(&sweep.scales, heights)
        }
        EvalCommand::Reach { sweep, heights, .. } => {
            let heights = if heights.is_empty() { &REACH_HEIGHTS[..] } else { heights };
            study.reach(&sweep.scales, reach_heights(heights)?)
        }
        EvalCommand::Waypoint { sweep, .. } => study.waypoint(&sweep.scales),
        EvalCommand::Forest { sweep, moving, blind, .. } => {
            study.forest(&sweep.scales, ForestSetup { moving: *moving, blind: *blind })
        }
        EvalCommand::Compose { sweep, height, .. } => study.compose(&sweep.scales, reach_heights(&[*height, *height])?),
        EvalCommand::Quality { dataset, nfe, .. } => study.quality(dataset, nfe),
        EvalCommand::Latency { nfe, guided, .. } => study.latency(nfe, *guided),
        EvalCommand::Guidance { scales, samples, .. } => study.guidance(scales, *samples),
        EvalCommand::Outcome { .. } => unreachable!("printed above, without models"),
    })
}
