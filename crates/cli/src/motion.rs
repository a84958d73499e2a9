//! `flowmimic motion ...`: import, generate and inspect clips.

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use flowmimic_motion::{
    Clip, CorpusParams, Coverage, GaitParams, ImportOptions, Segment, Units, UpAxis, WanderParams,
    clip::BODY_SPEED_JUMP,
    coverage, generator,
    reach::{Reaching, TargetHeights},
};
use flowmimic_plot::{Chart, Series, histogram};
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
        /// Print which joint became which landmark, and how sure that is (structure and name
        /// agree, structure only, name only, forced).
        #[arg(long)]
        print_map: bool,
        /// A TOML file forcing joints for landmarks, e.g. `L_Hip = "UpperLeg_L"`, `R_Toe =
        /// "Foot_R/end"` (a joint's End Site); the rest is found as usual.
        #[arg(long)]
        map: Option<PathBuf>,
    },
    /// Generate walking clips procedurally: one from the gait flags, `--count` diverse ones, or
    /// `--wander`ing walks whose command changes every 1.5-4 s (forward 0.3-1.6 m/s, backward to
    /// -0.7, sidesteps to 0.3, turns to 0.8 rad/s, stops).
    Generate {
        #[command(flatten)]
        gait: GaitArgs,
        /// Generate this many walks (seeded) instead of one from the flags: random constant
        /// walks, or with --wander wandering walks of seeds seed, seed+1, ...
        #[arg(long)]
        count: Option<usize>,
        /// One long walk whose command wanders (of --duration seconds; the gait flags other
        /// than --duration are not used).
        #[arg(long)]
        wander: bool,
        /// With --wander: a walk of transitions instead, its command changing every 1-2.5 s
        /// to a reversal (forward to backward or back), a stop or start, a sidestep (0.2-0.4
        /// m/s) or a turn on the spot (0.3-0.7 rad/s).
        #[arg(long, requires = "wander")]
        transitions: bool,
        /// Hands reach for targets and back while the walker stops (a third 0.4-0.9 m high, with a
        /// squat and a stoop, the rest 1.1-1.7 m; 0.2-0.7 m out from the shoulder, ahead and to
        /// the side; out 0.4-1.0 s, held 0.3-1.5 s): the share of the time a hand is out, 0.5
        /// when given without a value.
        #[arg(long, num_args = 0..=1, default_missing_value = "0.5", value_name = "SHARE")]
        reach: Option<f64>,
        /// With --reach: how the targets' heights are drawn, split (a third 0.4-0.9 m, the rest
        /// 1.1-1.7 m, as the corpus's reaching clips) or uniform (0.4-1.7 m, in front of the
        /// waist and chest too).
        #[arg(long, requires = "reach", value_parser = parse_heights, default_value = "split")]
        reach_heights: TargetHeights,
        /// One walk that follows a command schedule instead of the gait flags, `run`'s syntax:
        /// `seconds:vx,vy,yaw_rate` segments joined by `;` (forward, left m/s; rad/s), each
        /// blended into the next over 1 s, e.g. "2:1,0,0;3:-0.5,0,0;3:0.9,0,0".
        #[arg(long, conflicts_with_all = ["wander", "count", "reach"])]
        schedule: Option<String>,
        /// Seed of the random walks.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Clip name (default walk, reach with --reach, or wander_<seed>; with --count, names get a
        /// number).
        #[arg(long)]
        name: Option<String>,
        /// Output directory.
        #[arg(short, long, default_value = "runs/clips")]
        out: PathBuf,
    },
    /// The default corpus: wandering walks (seeds 1, 2, ...), a 10 s backward walk (walk_back),
    /// every walking capture (.bvh, DeepMimic .txt) in a folder and in its arms/ and walks/
    /// subfolders, with its quality table and coverage.
    Corpus {
        /// Wandering walks to generate.
        #[arg(long, default_value_t = flowmimic_motion::corpus::WANDERING_WALKS)]
        walks: usize,
        /// Length of each wandering walk, s.
        #[arg(long, default_value_t = flowmimic_motion::corpus::WANDERING_SECONDS)]
        duration: f64,
        /// Wandering walks whose hands reach for targets (reach_1, ...), beside 30 s of standing
        /// reaches (reach_stand) when there are any; none with --walking-only.
        #[arg(long, default_value_t = flowmimic_motion::corpus::REACHING_WALKS)]
        reaching: usize,
        /// Walks of transitions (transitions_1, ...: reversals, stops and starts, sidesteps,
        /// turns on the spot); none with --walking-only.
        #[arg(long, default_value_t = flowmimic_motion::corpus::TRANSITION_WALKS)]
        transitions: usize,
        /// Folder of captures to import (relative paths also from the checkout; skipped with a
        /// note when it does not exist).
        #[arg(long, default_value = crate::paths::MOCAP)]
        mocap: PathBuf,
        /// The walking corpus alone (the folder's top level, not arms/ and walks/): the clips
        /// the `corpus` expert and the `fm` model were made from.
        #[arg(long)]
        walking_only: bool,
        /// Output directory.
        #[arg(short, long, default_value = "runs/corpus")]
        out: PathBuf,
    },
    /// Write the left-right mirror image of clip files as `<out>/<name>-mirrored.clip.safetensors`
    /// (a walk that turns left turns right), e.g. to track or collect both sides of a capture.
    Mirror {
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Output directory.
        #[arg(short, long, default_value = "runs/clips")]
        out: PathBuf,
    },
    /// Print the quality table of clip files and their coverage: how much walks backward, turns
    /// and sidesteps, with histograms (coverage_*.png/svg in --out).
    Inspect {
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Directory for the histograms.
        #[arg(short, long, default_value = "runs/inspect")]
        out: PathBuf,
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
            reach: None,
        }
    }
}

fn header() {
    println!(
        "{:<24} {:>6} {:>6} {:>6} {:>6} {:>7} {:>7} {:>6} {:>6} {:>6} {:>6} {:>6} {:>6} {:>6} {:>6} {:>7}",
        "clip",
        "frames",
        "sec",
        "m/s",
        "root z",
        "pen cm",
        "skate",
        "1-sup",
        "2-sup",
        "back",
        "turn",
        "side",
        "h>1.1",
        "h>1.4",
        "h<0.7",
        "v max"
    );
}

fn row(humanoid: &Arc<Humanoid>, clip: &Clip) {
    let q = clip.quality(humanoid);
    let cov = Coverage::of(clip.walking_velocities());
    println!(
        "{:<24} {:>6} {:>6.2} {:>6.2} {:>6.3} {:>7.2} {:>7.3} {:>5.0}% {:>5.0}% {:>5.0}% {:>5.0}% {:>5.0}% {:>5.0}% {:>5.0}% {:>5.0}% {:>6.1}{}",
        clip.name,
        q.frames,
        q.duration,
        q.speed,
        q.root_height_mean,
        100.0 * q.penetration_max,
        q.skating,
        100.0 * q.single_support,
        100.0 * q.double_support,
        100.0 * cov.backward,
        100.0 * cov.turning,
        100.0 * cov.sidestep,
        100.0 * q.hand_high,
        100.0 * q.hand_overhead,
        100.0 * q.hand_low,
        q.body_speed_max,
        // A clip whose bodies jump between frames: no expert can follow it.
        if q.body_speed_max > BODY_SPEED_JUMP { "  JUMPS" } else { "" }
    );
}

/// Where the clip `name` is written in `out`.
pub(crate) fn clip_path(out: &Path, name: &str) -> PathBuf {
    out.join(format!("{name}.clip.safetensors"))
}

pub fn run(cmd: MotionCommand, humanoid: &Arc<Humanoid>) -> Result<()> {
    match cmd {
        MotionCommand::Import { files, out, units, up, cyclic, print_map, map } => {
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
            let map = match map {
                None => None,
                Some(file) => Some(
                    toml::from_str(&flowmimic_io::read_to_string(&file)?)
                        .with_context(|| format!("{}: a map is lines of LANDMARK = \"joint name\"", file.display()))?,
                ),
            };
            let options = ImportOptions { units, up, cyclic: cyclic.then_some(true), name: None, map };
            // A bad file is reported and skipped: the others are still imported.
            let (mut clips, mut failed) = (Vec::new(), Vec::new());
            for file in &files {
                let im = match flowmimic_motion::import(humanoid, file, &options) {
                    Ok(im) => im,
                    Err(e) if files.len() == 1 => return Err(e.into()),
                    Err(e) => {
                        eprintln!("error: {e}");
                        failed.push(file.display().to_string());
                        continue;
                    }
                };
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
                if print_map {
                    im.joint_map.iter().for_each(|line| println!("  {line}"));
                }
                clips.push(im.clip);
            }
            if !clips.is_empty() {
                header();
                clips.iter().for_each(|c| row(humanoid, c));
            }
            if !failed.is_empty() {
                bail!("{} of {} files could not be imported: {}", failed.len(), files.len(), failed.join(", "));
            }
        }
        MotionCommand::Generate {
            gait,
            count,
            wander,
            transitions,
            reach,
            reach_heights,
            schedule,
            seed,
            name,
            out,
        } => {
            let reaching = |seed| reach.map(|share| Reaching { share, seed, heights: reach_heights });
            header();
            let mut clips = Vec::new();
            if let Some(text) = schedule {
                let segments: Vec<Segment> = crate::run::schedule(&text)?
                    .into_iter()
                    .map(|s| Segment { seconds: s.seconds, speed: s.vx, lateral: s.vy, turn_rate: s.yaw_rate })
                    .collect();
                let name = name.unwrap_or_else(|| "walk".into());
                clips.push(flowmimic_motion::scheduled(humanoid, &name, &segments)?.0);
            } else if wander {
                let seeds: Vec<u64> = (0..count.unwrap_or(1) as u64).map(|k| seed + k).collect();
                for s in seeds {
                    let clip_name = match (&name, count) {
                        (Some(n), None) => n.clone(),
                        (Some(n), Some(_)) => format!("{n}_{s}"),
                        (None, _) => format!("wander_{s}"),
                    };
                    let p = WanderParams { seed: s, duration: gait.duration, reach: reaching(s), transitions };
                    clips.push(flowmimic_motion::wander(humanoid, &clip_name, &p)?.0);
                }
            } else {
                let name = name.unwrap_or_else(|| if reach.is_some() { "reach".into() } else { "walk".into() });
                let set: Vec<(String, GaitParams)> = match count {
                    None => vec![(name, GaitParams { reach: reaching(seed), ..gait.params() })],
                    Some(n) => generator::sample_set(n, seed, gait.duration)?
                        .into_iter()
                        .enumerate()
                        .map(|(i, p)| (format!("{name}_{i:03}"), GaitParams { reach: reaching(seed + i as u64), ..p }))
                        .collect(),
                };
                for (clip_name, p) in set {
                    clips.push(flowmimic_motion::generate(humanoid, &clip_name, &p)?.0);
                }
            }
            for clip in &clips {
                clip.save(&clip_path(&out, &clip.name))?;
                row(humanoid, clip);
            }
            let files: Vec<String> = clips.iter().map(|c| clip_path(&out, &c.name).display().to_string()).collect();
            println!("wrote {}", files.join(", "));
        }
        MotionCommand::Corpus { walks, duration, reaching, transitions, mocap, walking_only, out } => {
            let (reaching, transitions) = if walking_only { (0, 0) } else { (reaching, transitions) };
            let mocap = Some(crate::paths::resolve(&mocap));
            let params = CorpusParams { walks, duration, reaching, transitions, mocap, walking_only };
            let clips = corpus(humanoid, params, &out)?;
            header();
            clips.iter().for_each(|c| row(humanoid, c));
            print_coverage(&Coverage::of_walks(clips.iter().map(|c| c.walking_velocities()).collect()), &out)?;
            println!("{} clips written to {}", clips.len(), out.display());
        }
        MotionCommand::Mirror { files, out } => {
            header();
            for file in &files {
                let clip = Clip::load(humanoid, file)?.mirror_image(humanoid)?;
                clip.save(&clip_path(&out, &clip.name))?;
                row(humanoid, &clip);
            }
            println!("written to {}", out.display());
        }
        MotionCommand::Inspect { files, out } => {
            header();
            let mut velocities = Vec::new();
            for file in &files {
                let clip = Clip::load(humanoid, file)?;
                row(humanoid, &clip);
                velocities.push(clip.walking_velocities());
            }
            print_coverage(&Coverage::of_walks(velocities), &out)?;
        }
    }
    Ok(())
}

/// The corpus of `flowmimic_motion::corpus`, written to `out` (its capture folder is skipped
/// with a note when it is not a folder).
pub(crate) fn corpus(humanoid: &Arc<Humanoid>, mut params: CorpusParams, out: &Path) -> Result<Vec<Clip>> {
    if let Some(mocap) = params.mocap.take_if(|m| !m.is_dir()) {
        eprintln!(
            "note: {} is not a folder; the corpus has generated walks only (--mocap DIR: the \
             captures, ../shared/data/mocap beside the checkout)",
            mocap.display()
        );
    }
    let corpus = flowmimic_motion::corpus(humanoid, &params)?;
    for (file, why) in &corpus.left_out {
        eprintln!("note: {} {why}: left out", file.display());
    }
    for clip in &corpus.clips {
        clip.save(&clip_path(out, &clip.name))?;
    }
    Ok(corpus.clips)
}

/// Prints what a set of walking velocities covers and plots its histograms into `dir`.
pub(crate) fn print_coverage(cov: &Coverage, dir: &Path) -> Result<()> {
    let names = ["forward speed (m/s)", "sideways speed (m/s)", "yaw rate (rad/s)"];
    println!("\ncoverage of {} steps (velocities averaged over 1 s)", cov.steps);
    for (name, (lo, hi)) in names.iter().zip(cov.ranges) {
        println!("  {name:<22} {lo:>7.2} .. {hi:>6.2}");
    }
    println!(
        "  backward (forward < {} m/s) {:.1}%, turning (|yaw rate| > {} rad/s) {:.1}%, sidestepping (|sideways| > {} m/s) {:.1}%",
        coverage::BACKWARD,
        100.0 * cov.backward,
        coverage::TURNING,
        100.0 * cov.turning,
        coverage::SIDESTEP,
        100.0 * cov.sidestep
    );
    println!(
        "  sidestepping more than walking forward or back: {:.1}% to the left, {:.1}% to the right",
        100.0 * cov.aside[0],
        100.0 * cov.aside[1]
    );
    println!(
        "  reversing (1 s windows whose forward speed goes from beyond +{r} to beyond -{r} m/s, or back) {:.1}%",
        100.0 * cov.reversing,
        r = coverage::REVERSING
    );
    for (k, (stem, lo, hi)) in
        [("coverage_forward", -1.0, 2.0), ("coverage_sideways", -0.8, 0.8), ("coverage_yaw_rate", -1.5, 1.5)]
            .into_iter()
            .enumerate()
    {
        Chart::new(&format!("coverage: {}", names[k]), names[k], "fraction of steps")
            .series(Series::line(stem, histogram(&cov.velocities.iter().map(|v| v[k]).collect::<Vec<_>>(), lo, hi, 30)))
            .save(&dir.join(stem))?;
    }
    println!("wrote coverage_forward, coverage_sideways and coverage_yaw_rate (.png, .svg) in {}", dir.display());
    Ok(())
}

fn parse_heights(text: &str) -> Result<TargetHeights, String> {
    crate::run::parse_named(text, "split or uniform")
}
