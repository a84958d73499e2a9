//! `flowmimic track ...`: train and evaluate PPO tracking experts.

use crate::progress::{CsvLog, Progress};
use anyhow::{Context, Result};
use clap::Subcommand;
use flowmimic_motion::Clip;
use flowmimic_plot::{Chart, Series};
use flowmimic_sim::{CONTROL_HZ, Humanoid};
use flowmimic_track::plan::{PlanClipSetup, plan_clips};
use flowmimic_track::train::{Checkpoint, ClipLog, EvalReport, IterationLog, POLICY_FILE, policy_file};
use flowmimic_track::{EvalSetup, TrackConfig, Trainer, evaluate};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Subcommand)]
pub enum TrackCommand {
    /// Train a PPO expert that tracks a clip (a generated 10 s straight walk by default).
    /// Writes <out>/policy.safetensors (checkpointed atomically), clip.safetensors (the
    /// reference), log.csv, config.json and learning-curve plots.
    Train {
        /// Clip files to track (`flowmimic motion import|generate` writes them); several train
        /// one reference-conditioned policy (`--clip runs/corpus/*.clip.safetensors`).
        #[arg(long, num_args = 1..)]
        clip: Vec<PathBuf>,
        /// Run directory; default runs/track/<clip name>.
        #[arg(short, long)]
        out: Option<PathBuf>,
        /// Iterations (overrides the preset's track.iterations).
        #[arg(long, value_parser = crate::args::count)]
        iterations: Option<usize>,
        /// Continue from <out>/policy.safetensors with its optimiser state and counters, on the
        /// run's own clips unless --clip names them.
        #[arg(long, conflicts_with = "init")]
        resume: bool,
        /// Start from another run's policy (its directory or policy file): weights, action
        /// noise, observation statistics and learning rate, with fresh Adam moments and
        /// counters. Fine-tunes, for example, the corpus expert on one clip.
        #[arg(long)]
        init: Option<PathBuf>,
    },
    /// Clips that look like a guidance model's plans, to train a policy that executes plans
    /// (`--executor` of `run` and `eval`): the expert's rollouts with the data's action noise,
    /// whose hinges are its clean PD targets (each frame the next state's root and the action
    /// that leads to it). Writes <out>/<clip>_plan<n>.clip.safetensors.
    PlanClips {
        /// The expert's run directory (or policy file).
        expert: PathBuf,
        /// The clips the expert tracks (`--clip runs/corpus/wander_1.clip.safetensors ...`).
        #[arg(long, num_args = 1.., required = true)]
        clip: Vec<PathBuf>,
        /// Folder the clips are written in.
        #[arg(short, long)]
        out: PathBuf,
        /// Rollouts per clip, each from a random frame.
        #[arg(long, default_value_t = 16, value_parser = crate::args::count)]
        per_clip: usize,
        /// Seconds per rollout (shorter where it fails: the second before a failure is dropped).
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Seed of the rollouts' starts, noise levels and noise; clips are named from it
        /// (`_plan<seed * 1000 + n>`), so that two seeds' clips can share a folder.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Redraw a run's learning curves (reward, episode length, error) from its log.csv.
    Plot {
        /// The run directory.
        run: PathBuf,
    },
    /// Tracking metrics of a trained policy on its clips (one JSON line per clip, then a table
    /// with the clip seconds where episodes failed), or on other clips it was not trained on
    /// (`--clip`, repeatable): how well it tracks unseen walks.
    Eval {
        /// The run directory (policy.safetensors and clip.safetensors).
        run: PathBuf,
        #[arg(long, default_value_t = 100, value_parser = crate::args::count)]
        episodes: usize,
        /// Evaluate on these clip files instead of the run's own.
        #[arg(long, num_args = 1..)]
        clip: Vec<PathBuf>,
        /// Apply the survival protocol's kicks (0-0.5 m/s every second).
        #[arg(long)]
        kicks: bool,
        /// Start every episode at this frame of each clip instead of its first: whether a
        /// failure belongs to a part of the clip or to how long the episode has run.
        #[arg(long, default_value_t = 0)]
        start_frame: usize,
    },
}

/// The reference clips a run tracks, saved next to its policy: clip.safetensors, then
/// clip-1.safetensors, clip-2.safetensors, ... for a policy trained on several clips.
pub(crate) fn run_clip_file(k: usize) -> String {
    if k == 0 { "clip.safetensors".into() } else { format!("clip-{k}.safetensors") }
}

/// All clips of a run directory, in training order.
pub(crate) fn run_clips(humanoid: &Arc<Humanoid>, run: &Path) -> Result<Vec<Clip>> {
    if !run.join(run_clip_file(0)).exists() {
        anyhow::bail!(
            "{} has no {}: its clips are not shipped with it; pass them with --clip (the shipped corpus \
             experts' clips are made by `flowmimic motion corpus --walking-only -o runs/corpus`, e.g. \
             --clip runs/corpus/wander_3.clip.safetensors)",
            run.display(),
            run_clip_file(0)
        );
    }
    let mut clips = Vec::new();
    while clips.is_empty() || run.join(run_clip_file(clips.len())).exists() {
        clips.push(Clip::load(humanoid, &run.join(run_clip_file(clips.len())))?);
    }
    Ok(clips)
}

/// Learning curves from the CSV rows: reward, episode length and tracking error.
fn plot_curves(out: &Path, rows: &[String]) -> Result<()> {
    let column = |k: usize| crate::progress::column(rows, 1, k);
    for (stem, title, y, k) in [
        ("reward", "mean reward per step", "reward (max 5)", 2),
        ("episode_length", "mean length of ended episodes", "control steps", 5),
        ("body_error", "mean body position error (character frame)", "metres", 6),
    ] {
        let chart = Chart::new(title, "environment steps", y).series(Series::line(stem, column(k)));
        chart.save(&out.join(stem))?;
    }
    Ok(())
}

/// The clips a run tracks: files, or the default generated 10 s straight walk.
pub(crate) fn load_clips(humanoid: &Arc<Humanoid>, files: &[PathBuf]) -> Result<Vec<Clip>> {
    if files.is_empty() {
        return Ok(vec![flowmimic_motion::straight_walk(humanoid)?]);
    }
    files.iter().map(|f| Ok(Clip::load(humanoid, f)?)).collect()
}

pub fn run(cmd: TrackCommand, humanoid: &Arc<Humanoid>, mut cfg: TrackConfig) -> Result<()> {
    match cmd {
        TrackCommand::Train { clip, out, iterations, resume, init } => {
            let (clips, out) = match out {
                // A resumed run tracks the clips it saved, unless told otherwise.
                Some(out) if resume && clip.is_empty() => (run_clips(humanoid, &out)?, out),
                Some(out) => (load_clips(humanoid, &clip)?, out),
                None => {
                    let clips = load_clips(humanoid, &clip)?;
                    let out = PathBuf::from("runs/track").join(&clips[0].name);
                    (clips, out)
                }
            };
            if let Some(n) = iterations {
                cfg.iterations = n;
            }
            if cfg.iterations == 0 {
                anyhow::bail!("track.iterations is 0: a run needs at least one iteration");
            }
            let start = match (resume, init) {
                (true, _) => Start::Resume,
                (false, Some(run)) => Start::From(policy_file(&run)),
                (false, None) => Start::Fresh,
            };
            train(humanoid, clips, &out, &cfg, start)?;
        }
        TrackCommand::PlanClips { expert, clip, out, per_clip, seconds, seed } => {
            let file = policy_file(&expert);
            let ck = Checkpoint::read(&file)?;
            let sources = load_clips(humanoid, &clip)?;
            if !(seconds.is_finite() && seconds >= 3.0) {
                anyhow::bail!("--seconds is {seconds}: a plan clip needs at least 3 s");
            }
            let setup = PlanClipSetup { per_clip, seconds, seed };
            let clips = plan_clips(humanoid, &ck.policy()?, &ck.config()?, &sources, setup)?;
            if clips.is_empty() {
                anyhow::bail!(
                    "no rollout of {} lasted the 4 s a plan clip needs (3 s, and the second before a failure): \
                     is it an expert of these clips?",
                    file.display()
                );
            }
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            for c in &clips {
                c.save(&out.join(format!("{}.clip.safetensors", c.name)))?;
            }
            let wanted = per_clip * sources.len();
            eprintln!(
                "wrote {} clips of {wanted} rollouts in {} ({} failed within 4 s and are left out)",
                clips.len(),
                out.display(),
                wanted - clips.len()
            );
        }
        TrackCommand::Plot { run } => {
            let text = flowmimic_io::read_to_string(&run.join("log.csv"))?;
            let rows: Vec<String> = text.lines().skip(1).map(String::from).collect();
            plot_curves(&run, &rows)?;
            eprintln!("wrote reward, episode_length and body_error .png/.svg in {}", run.display());
        }
        TrackCommand::Eval { run, episodes, clip, kicks, start_frame } => {
            let ck = Checkpoint::read(&run.join(POLICY_FILE))?;
            let (cfg, policy_net) = (ck.config()?, ck.policy()?);
            let clips = if clip.is_empty() { run_clips(humanoid, &run)? } else { load_clips(humanoid, &clip)? };
            // One JSON line per clip, so that a failing clip cannot hide behind an average;
            // a table of them after (stderr, so that stdout stays JSON lines).
            let mut reports = Vec::new();
            for clip in clips {
                let setup = EvalSetup { episodes, start_frame, kicks, seed: 12345 };
                let report = evaluate(humanoid, &policy_net, &clip, &cfg, setup)?;
                println!("{}", serde_json::to_string(&report)?);
                reports.push(report);
            }
            print_eval_table(&reports, kicks);
        }
    }
    Ok(())
}

/// The per-clip reports as a table, worst completion first, with the backward and sidestep
/// shares beside the reference's, where the failures happen and how many clips meet the
/// tracking bar (95% of episodes complete, 90% with kicks; body error under 6 cm).
fn print_eval_table(reports: &[EvalReport], kicks: bool) {
    let bar = if kicks { 0.9 } else { 0.95 };
    let mut sorted: Vec<_> = reports.iter().collect();
    sorted.sort_by(|a, b| a.success_rate.total_cmp(&b.success_rate));
    eprintln!(
        "\n{:<20} {:>9} {:>10} {:>11} {:>12} {:>13} {:>13} {:>5}  fails at (clip second x episodes)",
        "clip", "completed", "body err", "steps", "root path", "backward", "sidestep", "bar"
    );
    let meets = |r: &EvalReport| r.success_rate >= bar && r.body_pos_error < 0.06;
    for r in &sorted {
        eprintln!(
            "{:<20} {:>8.0}% {:>7.1} cm {:>5.0} / {:<5} {:>7.2} m/s {:>13} {:>13} {:>5}  {}",
            r.clip,
            100.0 * r.success_rate,
            100.0 * r.body_pos_error,
            r.mean_steps,
            r.clip_steps,
            r.root_path_error,
            against(r.backward, r.reference_backward),
            against(r.sidestep, r.reference_sidestep),
            if meets(r) { "yes" } else { "no" },
            failure_seconds(&r.failure_frames)
        );
    }
    let met = sorted.iter().filter(|r| meets(r)).count();
    eprintln!("{met} of {} clips meet the bar ({:.0}% complete, body error under 6 cm)", reports.len(), 100.0 * bar);
}

/// A share of the episodes' steps beside the reference's, as `11.5 / 14.0%`.
fn against(ours: f64, reference: f64) -> String {
    format!("{:.1} / {:.1}%", 100.0 * ours, 100.0 * reference)
}

/// The commonest whole seconds of the clip at which episodes failed, most failures first (at
/// most three), e.g. `9 s x14, 30 s x3`: failures at one second from every start mark a part
/// of the clip the policy cannot track.
fn failure_seconds(frames: &[usize]) -> String {
    let mut counts = std::collections::BTreeMap::<usize, usize>::new();
    for &f in frames {
        *counts.entry(f / CONTROL_HZ as usize).or_default() += 1;
    }
    let mut counts: Vec<_> = counts.into_iter().collect();
    counts.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    counts.iter().take(3).map(|(s, n)| format!("{s} s x{n}")).collect::<Vec<_>>().join(", ")
}

const CLIPS_CSV_HEADER: &str = "iteration,clip,steps,episodes,failures,body_pos_error";

/// Per clip since the last checkpoint: failures per minute of tracked motion and the body
/// error, worst first (printed at each checkpoint of a multi-clip run).
fn print_clip_summary(names: &[String], recent: &[ClipLog]) {
    if names.len() < 2 {
        return;
    }
    let mut per_clip: Vec<(&String, &ClipLog)> = names.iter().zip(recent).collect();
    per_clip.sort_by(|a, b| b.1.failures_per_minute().total_cmp(&a.1.failures_per_minute()));
    let line: Vec<String> = per_clip
        .iter()
        .map(|(n, c)| format!("{n} {:.1}/min {:.1} cm", c.failures_per_minute(), 100.0 * c.body_pos_error))
        .collect();
    eprintln!("\rfailures per minute of motion, body error: {}", line.join(", "));
}

/// How a training run begins.
pub enum Start {
    /// New weights.
    Fresh,
    /// Continue the run in the output directory.
    Resume,
    /// A new run from the policy in this checkpoint file.
    From(PathBuf),
}

/// Trains (or continues) an expert on `clips` into the run directory `out`.
pub fn train(humanoid: &Arc<Humanoid>, clips: Vec<Clip>, out: &Path, cfg: &TrackConfig, start: Start) -> Result<()> {
    let policy_path = out.join(POLICY_FILE);
    let log_path = out.join("log.csv");
    let resume = matches!(start, Start::Resume);
    if !resume && policy_path.exists() {
        anyhow::bail!("{} exists: pass --resume to continue it, or choose another --out", policy_path.display());
    }
    let mut trainer = match start {
        Start::Resume => {
            let t = Trainer::resume(humanoid, clips, cfg.clone(), &policy_path)?;
            eprintln!("resumed {} at iteration {} ({} env steps)", policy_path.display(), t.iteration, t.env_steps);
            t
        }
        Start::From(init) => {
            eprintln!("starting from the policy of {}", init.display());
            Trainer::warm_start(humanoid, clips, cfg.clone(), &init)?
        }
        Start::Fresh => Trainer::new(humanoid, clips, cfg.clone())?,
    };
    let mut log = CsvLog::open(log_path.clone(), &IterationLog::csv_header(), resume.then_some(trainer.iteration));
    let mut clip_log = CsvLog::open(out.join("clips.csv"), CLIPS_CSV_HEADER, resume.then_some(trainer.iteration));
    let names: Vec<String> = trainer.references.iter().map(|r| r.clip.name.clone()).collect();
    let mut since_checkpoint = vec![ClipLog::default(); names.len()];
    flowmimic_io::write_atomic(&out.join("config.json"), serde_json::to_string_pretty(&cfg)?.as_bytes())?;
    for (k, reference) in trainer.references.iter().enumerate() {
        reference.clip.save(&out.join(run_clip_file(k)))?;
    }
    eprintln!(
        "tracking {} with {} envs x {} steps per iteration, policy {} parameters",
        trainer
            .references
            .iter()
            .map(|r| format!("'{}' ({} frames)", r.clip.name, r.len()))
            .collect::<Vec<_>>()
            .join(", "),
        cfg.envs,
        cfg.horizon,
        trainer.policy.num_params()
    );
    let progress = Progress::new(cfg.iterations, trainer.iteration);
    while trainer.iteration < cfg.iterations {
        let line: IterationLog = trainer.iterate().context("training stopped; the last checkpoint is intact")?;
        log.rows.push(line.csv_row());
        for ((name, c), recent) in names.iter().zip(&line.clips).zip(&mut since_checkpoint) {
            recent.merge(c);
            clip_log.rows.push(format!(
                "{},{name},{},{},{},{:.4}",
                line.iteration, c.steps, c.episodes, c.failures, c.body_pos_error
            ));
        }
        let last = trainer.iteration == cfg.iterations;
        if trainer.iteration % cfg.checkpoint_every.max(1) == 0 || last {
            // Logs first: a kill between the writes leaves rows past the checkpoint, which a
            // resume cuts, never a checkpoint past the logs (its rows would be lost).
            log.save()?;
            clip_log.save()?;
            trainer.save(&policy_path)?;
            print_clip_summary(&names, &since_checkpoint);
            since_checkpoint.fill(ClipLog::default());
            plot_curves(out, &log.rows)?;
        }
        let status = format!(
            "{:>9} steps  reward {:.3}  episode {:>5.1}  fails {:>3}/{:<3}  body err {:.3} m  kl {:.4}  lr {:.1e}  {:>5.0} steps/s",
            line.env_steps,
            line.mean_reward,
            line.episode_length,
            line.failures,
            line.episodes,
            line.body_pos_error,
            line.update.kl,
            line.update.learning_rate,
            line.steps_per_second,
        );
        progress.update(trainer.iteration, &status);
    }
    progress.finish();
    eprintln!("wrote {} and {}", policy_path.display(), log_path.display());
    Ok(())
}

/// `flowmimic bench track`: PPO's throughput on 1 and all cores, split into physics, network
/// and update, beside `VecEnv::step` of as many environments on as many threads timed before
/// each iteration (the physics alone: the rate PPO would reach with a free update), and the
/// share of each iteration that PPO's own physics takes.
pub fn bench(humanoid: &Arc<Humanoid>, cfg: &TrackConfig, iterations: usize) -> Result<()> {
    let clip = flowmimic_motion::generate(humanoid, "walk", &Default::default())?.0;
    println!(
        "PPO iteration: {} envs x {} steps, hidden {:?}, {} epochs x {} minibatches",
        cfg.envs, cfg.horizon, cfg.hidden, cfg.epochs, cfg.minibatches
    );
    let peak = flowmimic_nn::sgemm_gflops(512, 20);
    let mut rng = <rand::rngs::StdRng as rand::SeedableRng>::seed_from_u64(0);
    let params = flowmimic_track::ppo::Policy::new(
        flowmimic_track::task::obs_dim(cfg.observe_ahead),
        flowmimic_sim::NUM_DOFS,
        cfg,
        &mut rng,
    )
    .num_params() as f64;
    // An MLP forward pass costs 2 FLOPs per weight and sample; backward twice that.
    let update_flops = 6.0 * params * (cfg.envs * cfg.horizon * cfg.epochs) as f64;
    println!(
        "SGEMM peak (best of 20 products of 512^3, all threads): {peak:.1} GFLOP/s; one update: {:.1} GFLOP",
        update_flops / 1e9
    );
    println!(
        "{:>7} {:>12} {:>11} {:>11} {:>11} {:>12} {:>13} {:>10} {:>14}",
        "threads",
        "env steps/s",
        "physics s",
        "network s",
        "update s",
        "update/peak",
        "VecEnv /s",
        "PPO/VecEnv",
        "physics share"
    );
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    for threads in if all > 1 { vec![1, all] } else { vec![1] } {
        let report = flowmimic_track::train::bench(humanoid, vec![clip.clone()], cfg.clone(), iterations, threads)?;
        let log = &report.log;
        let fraction = update_flops / f64::from(log.update_seconds) / 1e9 / peak;
        println!(
            "{threads:>7} {:>12.0} {:>11.3} {:>11.3} {:>11.3} {:>11.0}% {:>13.0} {:>9.0}% {:>13.0}%",
            log.steps_per_second,
            log.physics_seconds,
            log.network_seconds,
            log.update_seconds,
            100.0 * fraction,
            report.vec_env_per_second,
            100.0 * report.ppo_over_vec_env,
            100.0 * report.physics_share
        );
    }
    Ok(())
}
