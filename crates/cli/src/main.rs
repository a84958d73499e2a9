//! `flowmimic`: walking motion capture to a fast, steerable humanoid controller.
//!
//! This file only parses arguments and calls the stage crates.

mod args;
mod config;
mod data;
mod demo;
mod eval;
mod export;
mod model;
mod motion;
mod paths;
mod pipeline;
mod progress;
mod run;
mod sim;
mod track;
mod viz;

use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use config::Config;
use flowmimic_control::ControlConfig;
use flowmimic_model::InverseConfig;
use flowmimic_sim::Humanoid;
use std::path::{Path, PathBuf};

/// mimalloc instead of the system allocator: glibc hands the model's per-step buffers (tapes of
/// hundreds of KB to MB) back to the kernel on every free and page-faults them in again on the
/// next step (README, Benchmarks).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(name = "flowmimic", version, about = "Fast, steerable humanoid control: motion capture -> tracking experts -> \
Flow Matching trajectory model -> guided controller.", long_about = None)]
struct Cli {
    #[command(flatten)]
    settings: Settings,
    #[command(subcommand)]
    command: Command,
}

#[derive(Args)]
struct Settings {
    /// Built-in settings to start from: tiny (tests), cpu (a laptop), paper (a GPU).
    #[arg(long, global = true, default_value = "cpu")]
    preset: String,
    /// A TOML file whose keys override the preset (`flowmimic config` prints every key);
    /// repeat it to layer files in order, a later file's keys winning.
    #[arg(long, global = true)]
    config: Vec<PathBuf>,
}

#[derive(Subcommand)]
enum Command {
    /// The shipped FM guidance model walks on a joystick schedule, then reaches with its right
    /// hand while walking: rollouts, plots and metrics in seconds.
    Demo {
        /// Model directory (default: the one `make run` trained, else the shipped one).
        #[arg(long)]
        model: Option<PathBuf>,
        #[arg(short, long, default_value = "runs/demo")]
        out: PathBuf,
        /// The model's recommended joystick and reach settings where these are left out.
        #[command(flatten)]
        drive: run::DriveArgs,
    },
    /// The whole job on the preset's `[pipeline]` (`flowmimic config` prints it): clips -> PPO
    /// experts -> noisy rollouts -> models -> evaluations and report. On the cpu preset: the
    /// walking corpus, one policy over it from the shipped corpus expert, a Flow Matching
    /// guidance model and its inverse dynamics, about an hour on 2 cores. Stages already done
    /// for the same settings are skipped; interrupted training resumes.
    Pipeline {
        /// Output directory of every stage.
        #[arg(short, long, default_value = "runs/pipeline")]
        out: PathBuf,
        /// Clips to train on (BVH/DeepMimic imports or generated clips); default those of
        /// `[pipeline] clips`. Takes several files (`--clip runs/corpus/*.clip.safetensors`).
        #[arg(long, num_args = 1..)]
        clip: Vec<PathBuf>,
        /// Run one stage alone, its inputs already done (`python -m flowmimic.cluster` runs the
        /// stages as tasks this way): clips, expert:CLIP, rollouts:CLIP (into rollouts/CLIP),
        /// collect (joins the parts when every clip's are done), train:fm, train:ddpm, evaluate.
        #[arg(long, value_name = "STAGE")]
        only: Option<pipeline::Only>,
        /// Print the stages after the clips (the experts, each clip with its expert, the
        /// models) as JSON, and run nothing: what the cluster driver schedules.
        #[arg(long, conflicts_with = "only")]
        plan: bool,
    },
    /// The simulated humanoid: inspect the model, export its MJCF, watch it stand.
    #[command(subcommand)]
    Sim(sim::SimCommand),
    /// Motion clips: import BVH/DeepMimic files, generate walks, inspect clip files.
    #[command(subcommand)]
    Motion(motion::MotionCommand),
    /// PPO tracking experts: train on a clip, evaluate tracking quality.
    #[command(subcommand)]
    Track(track::TrackCommand),
    /// Roll an expert out with action noise (`collect.noise`: on the cpu preset sigma 0.12 and
    /// 0.16 on 20 envs each, the shipped fm's; the paper's 0.12/0.16/0.24/0.36 on 16/12/6/6) and
    /// add the noisy states with the clean expert actions to a dataset.
    Collect {
        /// Expert runs (directories written by `flowmimic track train`, holding
        /// policy.safetensors and clip.safetensors).
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// Clips to collect on instead of the run's own, repeatable, with exactly one run: a
        /// shipped expert on its clip from `flowmimic motion corpus`
        /// (`collect pretrained/experts/09_12 --clip runs/corpus/09_12.clip.safetensors`).
        #[arg(long)]
        clip: Vec<PathBuf>,
        /// Dataset directory (created, or appended to).
        #[arg(short, long, default_value = "runs/data")]
        out: PathBuf,
    },
    /// Train the trajectory model (a Transformer over history and future state-action tokens)
    /// on a dataset with Flow Matching or DDPM. Writes <out>/model.safetensors, stats.safetensors,
    /// checkpoint.safetensors (atomically, every train.checkpoint_every steps), log.csv,
    /// config.json and loss.png/svg.
    Train {
        /// Dataset directory (`flowmimic collect` writes it).
        #[arg(default_value = "runs/data")]
        dataset: PathBuf,
        /// Generative objective: fm (Flow Matching), meanflow (one-step capable: average velocity
        /// over an interval) or ddpm.
        #[arg(long, default_value = "fm")]
        objective: String,
        /// Model directory; default runs/model/<objective>.
        #[arg(short, long)]
        out: Option<PathBuf>,
        /// Optimiser steps (overrides the preset's train.steps).
        #[arg(long)]
        steps: Option<usize>,
        /// Continue from <out>/checkpoint.safetensors.
        #[arg(long)]
        resume: bool,
    },
    /// Fit inverse dynamics (an MLP from a state and the next one to the executed action) to a
    /// dataset's transitions, into <model>/inverse.safetensors, with inverse-log.csv. `run`,
    /// `eval` and `play` then blend its action for the plan's next state into the executed one
    /// with `--inverse-dynamics BETA`.
    Inverse {
        /// Dataset directories (`flowmimic collect` writes them); their transitions pool.
        #[arg(default_value = "runs/data")]
        datasets: Vec<PathBuf>,
        /// The trajectory model directory to add it to.
        #[arg(long)]
        model: PathBuf,
        /// Optimiser steps (overrides the preset's inverse.steps).
        #[arg(long)]
        steps: Option<usize>,
    },
    /// Drive the humanoid with a trained model, optionally steered by a task (joystick, reach,
    /// waypoint, or walk-to-a-point-while-reaching). Settings left out (NFE, guidance scale,
    /// adaptive guidance, inverse dynamics, acceleration, approach, guidance interval, start
    /// actions, executor) come from the model directory's recommended.toml for the task, and each is
    /// printed with its source. Writes the rollout (states, actions, commands, timings) for
    /// `flowmimic eval` and the viewers, and prints what the task achieved.
    Run(run::RunArgs),
    /// Render a clip (.clip.safetensors) or a rollout (.rollout.safetensors) with MuJoCo,
    /// offscreen, to an animated GIF or an MP4 (needs ffmpeg), plus a contact sheet PNG.
    Render {
        file: PathBuf,
        /// Output .gif or .mp4; default runs/render/<name>.gif.
        #[arg(short, long)]
        out: Option<PathBuf>,
        /// Which environment of a rollout.
        #[arg(long, default_value_t = 0)]
        env: usize,
        #[arg(long, default_value_t = 480)]
        width: usize,
        #[arg(long, default_value_t = 360)]
        height: usize,
        /// Frames per second of the video (the simulation runs at 30).
        #[arg(long, default_value_t = 15)]
        fps: usize,
    },
    /// Play a clip or a rollout in the browser: serves a self-contained page on 127.0.0.1
    /// (orbit camera, timeline, speed, trails, commanded vs achieved velocity). Ctrl-C stops it.
    View {
        file: PathBuf,
        /// Which environment of a rollout.
        #[arg(long, default_value_t = 0)]
        env: usize,
        /// Port on 127.0.0.1 (0: any free one).
        #[arg(long, default_value_t = 8000)]
        port: u16,
    },
    /// Steer the humanoid live from the browser: the guided controller runs paced at 30 Hz and
    /// serves a page on 127.0.0.1 (WASD or arrows walk, Q/E turn, a gamepad's sticks do the same;
    /// click the ground for a waypoint; place a hand target; push, reset, record). Ctrl-C stops it.
    Play {
        /// Model directory (`flowmimic train` writes it; default: the one `make run` trained,
        /// else the shipped guidance model).
        #[arg(long)]
        model: Option<PathBuf>,
        /// Port on 127.0.0.1 (0: any free one).
        #[arg(long, default_value_t = 8000)]
        port: u16,
        /// The settings at the start (the page changes them); the model's recommended play
        /// settings where these are left out.
        #[command(flatten)]
        drive: run::DriveArgs,
        /// Start from this clip's frames (default: the generated straight walk).
        #[arg(long)]
        clip: Option<PathBuf>,
        /// Where the record button writes rollouts.
        #[arg(long, default_value = "runs/play")]
        record_dir: PathBuf,
    },
    /// The paper's experiments and a few more: survival, joystick, reach, waypoint, compose,
    /// forest, quality, guidance, latency. Each writes CSV, JSON and plots and appends to
    /// <out>/report.md; `eval outcome` reads a saved rollout.
    #[command(subcommand)]
    Eval(eval::EvalCommand),
    /// Rollout datasets: inspect them, compute window statistics.
    #[command(subcommand)]
    Dataset(data::DatasetCommand),
    /// Measure throughput and print a table of medians.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Export a trajectory model (a `train` directory) or an expert (a `track train` run) as an
    /// ONNX graph (opset 17) for ONNX Runtime, TensorRT and the like.
    Export {
        /// The model directory or expert run.
        path: PathBuf,
        /// The .onnx file to write.
        #[arg(short, long)]
        out: PathBuf,
        /// Also write inputs and flowmimic's own outputs to this safetensors file, to check another
        /// runtime against (`python3 examples/onnx_check.py OUT CHECK`).
        #[arg(long)]
        check: Option<PathBuf>,
        /// With --check, for a trajectory model: also the conditioning the controller builds at
        /// step --step of this rollout's first environment, and samples from it.
        #[arg(long, requires = "check")]
        rollout: Option<PathBuf>,
        #[arg(long, default_value_t = 10)]
        step: usize,
    },
    /// Print the settings in force (preset plus --config) as TOML.
    Config,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Trajectory-model sampling latency (batch 1 and 64, NFE 1-20, FM and DDPM) for the
    /// preset's model and the paper's, with FLOPs and the fraction of measured SGEMM peak.
    Model {
        /// Timed calls per row (the median is reported).
        #[arg(long, default_value_t = 5)]
        repeats: usize,
    },
    /// PPO training throughput on 1 and all cores, split into physics, network and update.
    Track {
        /// Timed iterations per row (the median is reported).
        #[arg(long, default_value_t = 5)]
        iterations: usize,
    },
    /// Physics and environment throughput.
    Sim {
        /// Environments stepped in parallel for the batched row.
        #[arg(long, default_value_t = 16)]
        envs: usize,
        /// Timed repeats per row (the median is reported).
        #[arg(long, default_value_t = 7)]
        repeats: usize,
    },
}

fn main() {
    // Die quietly on a closed pipe (`flowmimic ... | head`), as command-line tools do, instead
    // of panicking in println!: Rust ignores SIGPIPE by default.
    // SAFETY: sets the default disposition of one signal before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let files: Vec<&Path> = cli.settings.config.iter().map(PathBuf::as_path).collect();
    let config = Config::load(&cli.settings.preset, &files)?;
    match cli.command {
        Command::Collect { runs, clip, out } => {
            data::run_collect(&Humanoid::new(config.sim)?, runs, &clip, out, config.collect.clone())?
        }
        Command::Dataset(cmd) => data::run_dataset(cmd)?,
        Command::Demo { model, out, drive } => {
            demo::run(&paths::model_or_default(model), &out, &drive, &Humanoid::new(config.sim)?)?
        }
        Command::Pipeline { out, clip, only, plan } => {
            pipeline::run(&config, &cli.settings.preset, &out, &clip, only, plan)?
        }
        Command::Render { file, out, env, width, height, fps } => {
            viz::render(&Humanoid::new(config.sim)?, &file, out, env, (width, height), fps)?
        }
        Command::View { file, env, port } => viz::view(&Humanoid::new(config.sim)?, &file, env, port)?,
        Command::Play { model, port, drive, clip, record_dir } => {
            let model = paths::model_or_default(model);
            let chosen = drive.choose(&run::recommended(&model, "play")?, "play")?;
            let control = ControlConfig { paced: true, ..chosen.control(drive.guidance.gradient, 0.0) };
            run::play(&Humanoid::new(config.sim)?, &model, port, control, clip.as_deref(), record_dir)?
        }
        Command::Eval(cmd) => eval::run(cmd, &Humanoid::new(config.sim)?)?,
        Command::Run(args) => run::run(args, &Humanoid::new(config.sim)?)?,
        Command::Train { dataset, objective, out, steps, resume } => {
            let out = out.unwrap_or_else(|| model::default_out(&objective));
            model::train(&dataset, &objective, &out, steps, resume, config.model, config.train.clone())?
        }
        Command::Inverse { datasets, model, steps } => {
            let steps = steps.unwrap_or(config.inverse.steps);
            model::fit_inverse(&datasets, &model, &InverseConfig { steps, ..config.inverse.clone() })?
        }
        Command::Bench(BenchCommand::Model { repeats }) => {
            let paper = Config::load("paper", &[])?.model;
            model::bench(&[(cli.settings.preset.as_str(), config.model), ("paper", paper)], repeats)?
        }
        Command::Export { path, out, check, rollout, step } => {
            export::run(&Humanoid::new(config.sim)?, &path, &out, check.as_deref(), rollout.as_deref(), step)?
        }
        Command::Config => print!("{}", toml::to_string(&config)?),
        Command::Sim(cmd) => sim::run(cmd, &config)?,
        Command::Motion(cmd) => motion::run(cmd, &Humanoid::new(config.sim)?)?,
        Command::Track(cmd) => track::run(cmd, &Humanoid::new(config.sim)?, config.track.clone())?,
        Command::Bench(BenchCommand::Track { iterations }) => {
            track::bench(&Humanoid::new(config.sim)?, &config.track, iterations)?
        }
        Command::Bench(BenchCommand::Sim { envs, repeats }) => sim::bench(&config, envs, repeats)?,
    }
    Ok(())
}
