//! `flowmimic eval ...`: the paper's experiments as arguments: which protocol, models, points,
//! and how each is written down (columns, table rows, notes). Running them, storing and reusing
//! trials and writing the report is `flowmimic_eval::sweep`'s.

use crate::progress::Progress;
use crate::run::start_clip;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use flowmimic_control::{Hand, JoystickSegment, StepReport, Task};
use flowmimic_data::Dataset;
use flowmimic_eval::protocols::{self, Point};
use flowmimic_eval::sweep::{EvalModel, Experiment, Rows, finish, sweep};
use flowmimic_eval::{frechet_distance, gaussian};
use flowmimic_model::Gradient;
use flowmimic_sim::{Humanoid, STATE_DIM};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Args, Clone)]
pub struct Common {
    /// Models as LABEL=DIR (repeat); default fm=runs/model/fm and ddpm=runs/model/ddpm.
    #[arg(long = "model")]
    models: Vec<String>,
    /// Output directory for CSV, JSON, plots and report.md.
    #[arg(short, long, default_value = "runs/eval")]
    out: PathBuf,
    /// Few trials and short episodes: minutes on 2 cores, for development and CI.
    #[arg(long)]
    quick: bool,
    /// Trials per point (default: the protocol's, or its quick count).
    #[arg(long)]
    trials: Option<usize>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Actions of each sampled trajectory executed before sampling again (1 = the paper).
    #[arg(long, default_value_t = 1)]
    execute: usize,
    /// Start trials from this clip's frames (default: the generated straight walk).
    #[arg(long)]
    clip: Option<PathBuf>,
    /// How guidance takes its gradient: through-network (a vector-Jacobian product through
    /// the denoiser) or cost-only.
    #[arg(long, value_parser = parse_gradient, default_value = "through-network")]
    gradient: Gradient,
}

/// `through-network` or `cost-only`.
pub(crate) fn parse_gradient(text: &str) -> Result<Gradient, String> {
    serde_json::from_str(&format!("\"{text}\"")).map_err(|_| format!("'{text}': use through-network or cost-only"))
}

impl Common {
    /// Settings for a programmatic run (the pipeline): models as LABEL=DIR.
    pub fn new(models: Vec<String>, out: PathBuf, quick: bool) -> Self {
        Self { models, out, quick, trials: None, seed: 0, execute: 1, clip: None, gradient: Gradient::default() }
    }
}

#[derive(Subcommand)]
pub enum EvalCommand {
    /// Unguided walking under a random 0-0.5 m/s kick every second (paper Fig. 2): steps
    /// survived against NFE for each model.
    Survival {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20")]
        nfe: Vec<usize>,
        /// Episode cap in seconds (default 1000 steps; quick 10 s).
        #[arg(long)]
        seconds: Option<f64>,
    },
    /// Forward, backward, turn left, turn right, 3 s each (paper Fig. 3): velocity RMSE
    /// against guidance scale for each model (give models of different horizons).
    Joystick {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "0,3,10,30")]
        scales: Vec<f32>,
        #[arg(long, default_value_t = 5)]
        nfe: usize,
    },
    /// Random right-hand targets while walking (paper Fig. 4): hand-target distance against
    /// guidance scale for each model.
    Reach {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "0,3,10,30")]
        scales: Vec<f32>,
        #[arg(long, default_value_t = 5)]
        nfe: usize,
    },
    /// Walk to a waypoint and touch a target there: success rate (pelvis within 0.5 m and hand
    /// within 0.15 m at once).
    Compose {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "10")]
        scales: Vec<f32>,
        #[arg(long, default_value_t = 5)]
        nfe: usize,
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
        #[arg(long, default_value_t = 5)]
        nfe: usize,
        /// Conditionings (start frames of the clip).
        #[arg(long, default_value_t = 32)]
        samples: usize,
    },
    /// Time per control step (model and physics, batch 1) against NFE.
    Latency {
        #[command(flatten)]
        common: Common,
        #[arg(long, value_delimiter = ',', default_value = "1,2,5,10,20")]
        nfe: Vec<usize>,
        /// Measure the guided control step at this scale (joystick schedule; the gradient as
        /// --gradient says) instead of unguided walking.
        #[arg(long)]
        guided: Option<f32>,
    },
}

fn load_models(specs: &[String]) -> Result<Vec<EvalModel>> {
    let defaults = ["fm", "ddpm"].map(|o| format!("{o}={}", crate::model::default_out(o).display()));
    let specs = if specs.is_empty() { &defaults[..] } else { specs };
    specs
        .iter()
        .map(|s| {
            let (label, dir) = s.split_once('=').with_context(|| format!("--model {s}: use LABEL=DIR"))?;
            let model = crate::run::load_model(Path::new(dir))?;
            lib(EvalModel::new(label, Path::new(dir), model))
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

/// The library's boxed error as the command line's.
fn lib<T>(r: flowmimic_eval::sweep::Result<T>) -> Result<T> {
    r.map_err(|e| anyhow::anyhow!(e))
}

/// `1.0` for true, so falls and successes average into rates.
fn rate(b: bool) -> f64 {
    f64::from(u8::from(b))
}

/// Runs a protocol with a progress bar over its control steps.
fn with_progress(steps: usize, f: impl FnOnce(&dyn Fn(&StepReport)) -> Rows) -> Rows {
    let (p, report) = progress_for(steps);
    let rows = f(&|r| report(&p, r));
    p.finish();
    rows
}

pub fn run(cmd: EvalCommand, humanoid: &Arc<Humanoid>) -> Result<()> {
    let common = match &cmd {
        EvalCommand::Survival { common, .. }
        | EvalCommand::Joystick { common, .. }
        | EvalCommand::Reach { common, .. }
        | EvalCommand::Compose { common, .. }
        | EvalCommand::Quality { common, .. }
        | EvalCommand::Guidance { common, .. }
        | EvalCommand::Latency { common, .. } => common.clone(),
    };
    let models = load_models(&common.models)?;
    let clip = start_clip(humanoid, common.clip.as_deref())?;
    let out = &common.out;
    let seed = common.seed;
    let trials = |full: usize, quick: usize| common.trials.unwrap_or(if common.quick { quick } else { full }).max(1);
    let execute = common.execute;
    let gradient = common.gradient;
    let point = |nfe: usize, scale: f32| Point { nfe, scale, execute, seed, gradient };
    let by_nfe = |nfe: &[usize]| nfe.iter().map(|&n| point(n, 0.0)).collect::<Vec<_>>();
    let by_scale = |scales: &[f32], nfe: usize| scales.iter().map(|&w| point(nfe, w)).collect::<Vec<_>>();
    // Trials, episode lengths and targets are fixed by each protocol; what else can change
    // the results goes into the stored points' key.
    let settings = match &cmd {
        EvalCommand::Survival { seconds, .. } => {
            format!("clip {} {}; seconds {seconds:?}; quick {}", clip.name, clip.len(), common.quick)
        }
        EvalCommand::Quality { dataset, .. } => format!(
            "clip {} {}; dataset {}; quick {}",
            clip.name,
            clip.len(),
            Dataset::open(dataset).map(|d| d.shards_key()).unwrap_or_default(),
            common.quick
        ),
        _ => format!("clip {} {}", clip.name, clip.len()),
    };
    match cmd {
        EvalCommand::Guidance { scales, nfe, samples, .. } => {
            guidance_effect(&models, humanoid, &clip, &scales, nfe, samples, out)?
        }
        EvalCommand::Survival { nfe, seconds, .. } => {
            let trials = trials(50, 8);
            let seconds = seconds.unwrap_or(if common.quick { 10.0 } else { 1000.0 / flowmimic_sim::CONTROL_HZ });
            let steps = (seconds * flowmimic_sim::CONTROL_HZ).round() as usize;
            let exp = Experiment {
                name: "survival",
                settings: settings.clone(),
                title: "Survival against NFE (paper Fig. 2)",
                columns: &["steps"],
                plot: "steps",
                x_label: "NFE",
                y_label: "control steps survived",
                header: "| model | objective | NFE | steps survived (mean ± std) | paper FM / DDPM |\n|---|---|---|---|---|",
            };
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&by_nfe(&nfe), trials, true),
                |m, point| {
                    with_progress(steps, |report| {
                        let survived = protocols::survival(&m.bench(humanoid, &clip), point, trials, seconds, report)?;
                        Ok(survived.iter().map(|&s| vec![s as f64]).collect())
                    })
                },
                |m, s| {
                    let paper = match s.nfe {
                        1 => "280 / 30",
                        5 => "820 / 280",
                        20 => "≈470 / ≈470",
                        _ => "",
                    };
                    format!(
                        "| {} | {} | {} | {:.0} ± {:.0} | {paper} |",
                        m.label, s.objective, s.nfe, s.mean["steps"], s.std["steps"]
                    )
                },
            ))?;
            let notes = format!(
                "Unguided walking, a random planar root-velocity kick of uniform 0-0.5 m/s in a uniform direction every 1 s, \
                 failure when the head is below 0.2 m; {trials} trials per point, episode cap {seconds:.1} s ({steps} steps), seed {seed}."
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
        EvalCommand::Joystick { scales, nfe, .. } => {
            let trials = trials(10, 2);
            let exp = Experiment {
                name: "joystick",
                settings: settings.clone(),
                title: "Joystick tracking against guidance (paper Fig. 3)",
                columns: &["velocity_rmse", "yaw_rate_rmse", "fell"],
                plot: "velocity_rmse",
                x_label: "guidance scale w",
                y_label: "velocity RMSE (m/s)",
                header: "| model | H | w | velocity RMSE (m/s) | yaw-rate RMSE (rad/s) | falls |\n|---|---|---|---|---|---|",
            };
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&by_scale(&scales, nfe), trials, false),
                |m, point| {
                    with_progress(360, |report| {
                        let r = protocols::joystick(&m.bench(humanoid, &clip), point, trials, report)?;
                        Ok(r.iter().map(|t| vec![t.velocity_rmse, t.yaw_rate_rmse, rate(t.fell)]).collect())
                    })
                },
                |m, s| {
                    format!(
                        "| {} | {} | {} | {:.3} ± {:.3} | {:.3} | {:.0}% |",
                        m.label,
                        s.horizon,
                        s.scale,
                        s.mean["velocity_rmse"],
                        s.std["velocity_rmse"],
                        s.mean["yaw_rate_rmse"],
                        100.0 * s.mean["fell"]
                    )
                },
            ))?;
            let notes = format!(
                "Forward 1.0 m/s, backward 0.5 m/s, turn left and right (0.8 m/s at 0.6 rad/s), 3 s each; RMSE between commanded \
                 and achieved planar root velocity (character frame) over the steps before any fall; NFE {nfe}, {trials} trials. \
                 Paper: RMSE ≈ 0.55 at w = 40; 1.05 at H = 2 to 0.70 at H = 16."
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
        EvalCommand::Reach { scales, nfe, .. } => {
            let trials = trials(20, 4);
            let exp = Experiment {
                name: "reach",
                settings: settings.clone(),
                title: "Hand reaching against guidance (paper Fig. 4)",
                columns: &["mean", "rms", "min", "fell"],
                plot: "mean",
                x_label: "guidance scale w",
                y_label: "hand-target distance (m)",
                header: "| model | H | w | mean distance (m) | RMS (m) | closest (m) | falls |\n|---|---|---|---|---|---|---|",
            };
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&by_scale(&scales, nfe), trials, false),
                |m, point| {
                    with_progress(120, |report| {
                        let r = protocols::reach(&m.bench(humanoid, &clip), point, trials, report)?;
                        Ok(r.iter().map(|t| vec![t.mean, t.rms, t.min, rate(t.fell)]).collect())
                    })
                },
                |m, s| {
                    format!(
                        "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.0}% |",
                        m.label,
                        s.horizon,
                        s.scale,
                        s.mean["mean"],
                        s.mean["rms"],
                        s.mean["min"],
                        100.0 * s.mean["fell"]
                    )
                },
            ))?;
            let notes = format!(
                "Right-hand targets 1.5-3 m ahead of each trial's start, within 0.5 m to either side, 0.9-1.5 m high; 4 s of guided \
                 walking; distance averaged over the trial (mean, RMS) and the closest approach; NFE {nfe}, {trials} trials. \
                 Paper: RMSE ≈ 1.1 at w = 100."
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
        EvalCommand::Compose { scales, nfe, .. } => {
            let trials = trials(20, 4);
            let exp = Experiment {
                name: "compose",
                settings: settings.clone(),
                title: "Composition: waypoint and reach",
                columns: &["success", "pelvis_min", "hand_min", "fell"],
                plot: "success",
                x_label: "guidance scale w",
                y_label: "success rate",
                header: "| model | w | success | closest pelvis (m) | closest hand (m) | falls |\n|---|---|---|---|---|---|",
            };
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&by_scale(&scales, nfe), trials, false),
                |m, point| {
                    with_progress(300, |report| {
                        let r = protocols::compose(&m.bench(humanoid, &clip), point, trials, report)?;
                        Ok(r.iter().map(|t| vec![rate(t.success), t.pelvis_min, t.hand_min, rate(t.fell)]).collect())
                    })
                },
                |m, s| {
                    format!(
                        "| {} | {} | {:.0}% | {:.2} | {:.2} | {:.0}% |",
                        m.label,
                        s.scale,
                        100.0 * s.mean["success"],
                        s.mean["pelvis_min"],
                        s.mean["hand_min"],
                        100.0 * s.mean["fell"]
                    )
                },
            ))?;
            let notes = format!(
                "Waypoint 3-4 m ahead and up to 1.5 m aside; right-hand target 0.4 m right of it at 1.2 m; 10 s; success when the \
                 pelvis is within 0.5 m of the waypoint and the hand within 0.15 m of the target at the same step; NFE {nfe}, \
                 {trials} trials."
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
        EvalCommand::Quality { dataset, nfe, .. } => {
            let trials = trials(16, 4);
            let seconds = if common.quick { 4.0 } else { 10.0 };
            let reference = dataset_features(&dataset)?;
            let (rm, rs) = gaussian(&reference);
            // The floor: alternate 10 s blocks of the reference against each other.
            let (even, odd): (Vec<_>, Vec<_>) = reference.iter().enumerate().partition(|(i, _)| (i / 300) % 2 == 0);
            let half =
                |v: Vec<(usize, &Vec<f64>)>| gaussian(&v.into_iter().map(|(_, f)| f.clone()).collect::<Vec<_>>());
            let ((am, a_s), (bm, bs)) = (half(even), half(odd));
            let floor = frechet_distance(&am, &a_s, &bm, &bs);
            let exp = Experiment {
                name: "quality",
                settings: settings.clone(),
                title: "Motion quality (Fréchet distance to the data)",
                columns: &["frechet"],
                plot: "frechet",
                x_label: "NFE",
                y_label: "Fréchet distance",
                header: "| model | NFE | Fréchet distance |\n|---|---|---|",
            };
            let steps = (seconds * flowmimic_sim::CONTROL_HZ) as usize;
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&by_nfe(&nfe), 1, true),
                |m, point| {
                    with_progress(steps, |report| {
                        let f =
                            protocols::generated_features(&m.bench(humanoid, &clip), point, trials, seconds, report)?;
                        let (gm, gs) = gaussian(&f);
                        Ok(vec![vec![frechet_distance(&gm, &gs, &rm, &rs)]])
                    })
                },
                |m, s| format!("| {} | {} | {:.4} |", m.label, s.nfe, s.mean["frechet"]),
            ))?;
            let table = format!("{table}| reference against itself (floor) | – | {floor:.4} |\n");
            let notes = format!(
                "Features per control step: root height, root velocity (character frame), and head, hand and foot positions \
                 relative to the root (19 numbers); Gaussian fits of unguided generated walking ({trials} trials x {seconds} s, \
                 steps before any fall) against every state of `{}`; the floor compares alternate 10 s blocks of the data.",
                dataset.display()
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
        EvalCommand::Latency { nfe, guided, .. } => {
            let scale = guided.unwrap_or(0.0);
            let points: Vec<Point> = nfe.iter().map(|&n| point(n, scale)).collect();
            let exp = Experiment {
                name: if guided.is_some() { "latency_guided" } else { "latency" },
                settings: settings.clone(),
                title: if guided.is_some() {
                    "Latency per guided control step (batch 1)"
                } else {
                    "Latency per control step (batch 1)"
                },
                columns: &["model_ms", "physics_ms", "total_ms"],
                plot: "total_ms",
                x_label: "NFE",
                y_label: "milliseconds",
                header: "| model | objective | NFE | model ms | physics ms | control Hz |\n|---|---|---|---|---|---|",
            };
            let (summaries, table) = lib(sweep(
                &exp,
                out,
                &models,
                (&points, 1, true),
                |m, point| {
                    let (model_ms, physics_ms) = protocols::latency(&m.bench(humanoid, &clip), point, 3.0)?;
                    Ok(vec![vec![model_ms, physics_ms, model_ms + physics_ms]])
                },
                |m, s| {
                    format!(
                        "| {} | {} | {} | {:.2} | {:.2} | {:.0} |",
                        m.label,
                        s.objective,
                        s.nfe,
                        s.mean["model_ms"],
                        s.mean["physics_ms"],
                        1e3 / s.mean["total_ms"]
                    )
                },
            ))?;
            let walking = match guided {
                Some(w) => format!("walking guided at w = {w} on the joystick schedule ({gradient:?} gradient)"),
                None => "unguided walking".into(),
            };
            let notes = format!(
                "Median over 3 s of {walking} with one environment; model = one sampling call (all NFE steps), \
                 physics = one 30 Hz step. Paper: FM about 4x faster than DDPM for the same robustness (NFE 5 vs 20)."
            );
            lib(finish(out, &models, (exp.name, exp.title), &notes, &summaries, table))?;
        }
    }
    Ok(())
}

/// Quality features of every state in a dataset.
fn dataset_features(dir: &Path) -> Result<Vec<Vec<f64>>> {
    let dataset = Dataset::open(dir)?;
    let mut out = Vec::new();
    for (_, shard) in dataset.load_all()? {
        out.extend(shard.state.chunks_exact(STATE_DIM).map(protocols::quality_features));
    }
    if out.len() < 100 {
        bail!("{}: only {} states, too few for a reference", dir.display(), out.len());
    }
    Ok(out)
}

/// `flowmimic eval guidance`: the executed action's change against the later actions'.
fn guidance_effect(
    models: &[EvalModel],
    humanoid: &Arc<Humanoid>,
    clip: &flowmimic_motion::Clip,
    scales: &[f32],
    nfe: usize,
    samples: usize,
    out: &Path,
) -> Result<()> {
    let walk = |vx, yaw_rate| JoystickSegment { seconds: 1.0, vx, vy: 0.0, yaw_rate };
    let tasks = [
        ("backward -0.5 m/s", Task { joystick: vec![walk(-0.5, 0.0)], ..Task::walk() }),
        ("turn left 0.6 rad/s", Task { joystick: vec![walk(0.8, 0.6)], ..Task::walk() }),
        ("right hand 0.5 m ahead, 1.3 m high", Task { reach: Some((Hand::Right, [0.5, -0.3, 1.3])), ..Task::walk() }),
    ];
    println!(
        "{:<10} {:<36} {:<16} {:>6} {:>10} {:>10} {:>7} {:>10} {:>10}",
        "model", "task", "gradient", "w", "|da_t|", "|da_t+k|", "ratio", "error", "unguided"
    );
    let mut rows = Vec::new();
    for m in models {
        for (name, task) in &tasks {
            for gradient in [Gradient::ThroughNetwork, Gradient::CostOnly] {
                for &scale in scales {
                    let point = Point { nfe, scale, execute: 1, seed: 0, gradient };
                    let e = protocols::guidance_effect(&m.bench(humanoid, clip), task, point, samples)?;
                    let g = serde_json::to_string(&gradient)?;
                    println!(
                        "{:<10} {:<36} {:<16} {:>6} {:>10.4} {:>10.4} {:>7.2} {:>10.3} {:>10.3}",
                        m.label,
                        name,
                        g.trim_matches('"'),
                        scale,
                        e.first_action,
                        e.later_actions,
                        e.first_action / e.later_actions.max(1e-12),
                        e.error_guided,
                        e.error_unguided
                    );
                    rows.push(serde_json::json!({"model": m.label, "task": name, "gradient": gradient, "scale": scale, "nfe": nfe, "samples": samples, "effect": e}));
                }
            }
        }
    }
    flowmimic_io::write_atomic(&out.join("guidance.json"), serde_json::to_string_pretty(&rows)?.as_bytes())?;
    eprintln!("wrote {}", out.join("guidance.json").display());
    Ok(())
}
