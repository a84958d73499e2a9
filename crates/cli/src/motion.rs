//! `flowmimic motion ...`: import, generate and inspect clips.

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use flowmimic_motion::{Clip, GaitParams, ImportOptions, Units, UpAxis, generator};
use flowmimic_sim::Humanoid;
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Subcommand)]
pub enum MotionCommand {
    /// Import BVH (any skeleton: LAFAN1, CMU, others by joint names) or DeepMimic clips,
    /// retarget them to the humanoid and write `<out>/<name>.clip.safetensors`.
    Import {
        /// Files to import (.bvh, or DeepMimic .txt/.json).
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Output directory.
        #[arg(short, long, default_value = "runs/clips")]
        out: PathBuf,
        /// Length unit of BVH files: auto, m, cm, mm, in, cmu (0.056444 m).
        #[arg(long, default_value = "auto")]
        units: String,
        /// Up axis of BVH files: auto, y, z.
        #[arg(long, default_value = "auto")]
        up: String,
        /// Mark the clips cyclic (loopable); DeepMimic files say so themselves.
        #[arg(long)]
        cyclic: bool,
    },
    /// Generate walking clips procedurally: one from the gait flags, or `--count` diverse ones.
    Generate {
        #[command(flatten)]
        gait: GaitArgs,
        /// Generate this many random walks (seeded) instead of one from the flags.
        #[arg(long)]
        count: Option<usize>,
        /// Seed for --count.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Clip name (with --count, names get a number).
        #[arg(long, default_value = "walk")]
        name: String,
        /// Output directory.
        #[arg(short, long, default_value = "runs/clips")]
        out: PathBuf,
    },
    /// Print the quality table of clip files.
    Inspect {
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
}

/// Gait parameters as flags (defaults: a straight 1 m/s walk for 6 s).
#[derive(Args)]
pub struct GaitArgs {
    /// Forward speed, m/s (negative: backward).
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    speed: f64,
    /// Sideways speed, m/s (positive: left).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    lateral: f64,
    /// Turn rate, rad/s (positive: left).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    turn_rate: f64,
    /// Steps per second.
    #[arg(long, default_value_t = 1.8)]
    step_frequency: f64,
    /// Swing foot clearance, m.
    #[arg(long, default_value_t = 0.08)]
    step_height: f64,
    /// Arm swing amplitude, rad.
    #[arg(long, default_value_t = 0.35)]
    arm_swing: f64,
    /// Length, s.
    #[arg(long, default_value_t = 6.0)]
    duration: f64,
}

impl GaitArgs {
    fn params(&self) -> GaitParams {
        GaitParams {
            speed: self.speed,
            lateral: self.lateral,
            turn_rate: self.turn_rate,
            heading: 0.0,
            step_frequency: self.step_frequency,
            step_height: self.step_height,
            arm_swing: self.arm_swing,
            duration: self.duration,
        }
    }
}

fn header() {
    println!(
        "{:<24} {:>6} {:>6} {:>6} {:>6} {:>7} {:>7} {:>6} {:>6}",
        "clip", "frames", "sec", "m/s", "root z", "pen cm", "skate", "1-sup", "2-sup"
    );
}

fn row(humanoid: &Arc<Humanoid>, clip: &Clip) {
    let q = clip.quality(humanoid);
    println!(
        "{:<24} {:>6} {:>6.2} {:>6.2} {:>6.3} {:>7.2} {:>7.3} {:>5.0}% {:>5.0}%",
        clip.name,
        q.frames,
        q.duration,
        q.speed,
        q.root_height_mean,
        100.0 * q.penetration_max,
        q.skating,
        100.0 * q.single_support,
        100.0 * q.double_support
    );
}

fn clip_path(out: &Path, name: &str) -> PathBuf {
    out.join(format!("{name}.clip.safetensors"))
}

pub fn run(cmd: MotionCommand, humanoid: &Arc<Humanoid>) -> Result<()> {
    match cmd {
        MotionCommand::Import { files, out, units, up, cyclic } => {
            let units = match units.as_str() {
                "auto" => None,
                u => Some(Units::parse(u).with_context(|| format!("unknown unit '{u}' (auto, m, cm, mm, in, cmu)"))?),
            };
            let up = match up.to_ascii_lowercase().as_str() {
                "auto" => None,
                "y" => Some(UpAxis::Y),
                "z" => Some(UpAxis::Z),
                other => bail!("unknown up axis '{other}' (auto, y, z)"),
            };
            let options = ImportOptions { units, up, cyclic: cyclic.then_some(true), name: None };
            let mut clips = Vec::new();
            for file in &files {
                let im = flowmimic_motion::import(humanoid, file, &options)?;
                let path = clip_path(&out, &im.clip.name);
                im.clip.save(&path)?;
                println!(
                    "{} -> {}: {}, units {}, {:?}-up, {:.0} fps{}, scale {:.3}, {:.2}% hinge values clamped{}",
                    file.display(),
                    path.display(),
                    im.family,
                    im.units.map_or("m".to_string(), |u| format!("{u:?}")),
                    im.up,
                    im.source_fps,
                    if im.dropped_frames > 0 { ", T-pose frame dropped" } else { "" },
                    im.report.scale,
                    100.0 * im.report.clamped,
                    if im.clip.cyclic { ", cyclic" } else { "" },
                );
                clips.push(im.clip);
            }
            header();
            clips.iter().for_each(|c| row(humanoid, c));
        }
        MotionCommand::Generate { gait, count, seed, name, out } => {
            let set: Vec<(String, GaitParams)> = match count {
                None => vec![(name, gait.params())],
                Some(n) => generator::sample_set(n, seed, gait.duration)
                    .into_iter()
                    .enumerate()
                    .map(|(i, p)| (format!("{name}_{i:03}"), p))
                    .collect(),
            };
            header();
            for (clip_name, p) in set {
                let (clip, _) = flowmimic_motion::generate(humanoid, &clip_name, &p)?;
                clip.save(&clip_path(&out, &clip_name))?;
                row(humanoid, &clip);
            }
            println!("written to {}", out.display());
        }
        MotionCommand::Inspect { files } => {
            header();
            for file in &files {
                row(humanoid, &Clip::load(humanoid, file)?);
            }
        }
    }
    Ok(())
}
