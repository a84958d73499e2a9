//! `flowmimic collect` and `flowmimic dataset ...`: noisy expert rollouts and their inspection.

use anyhow::{Result, bail};
use clap::Subcommand;
use flowmimic_data::{CollectConfig, Dataset, ShardInfo, Stats, WindowSpec, collect};
use flowmimic_motion::Coverage;
use flowmimic_motion::clip::{HAND_HIGH, HAND_LOW, HAND_OVERHEAD};
use flowmimic_plot::{Chart, Series};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::state::offset;
use flowmimic_sim::{CONTROL_HZ, Humanoid, NUM_DOFS, STATE_DIM};
use flowmimic_track::train::Checkpoint;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Subcommand)]
pub enum DatasetCommand {
    /// Compute (once) and store the per-slot normalisation statistics of the windows
    /// (history N, horizon H) as stats-N<N>-H<H>.safetensors in the dataset.
    Stats {
        dir: PathBuf,
        #[arg(long, default_value_t = 4)]
        history: usize,
        #[arg(long, default_value_t = 16)]
        horizon: usize,
    },
    /// Add the left-right mirror image of every collected clip's rollouts to the dataset, as
    /// `<clip>-mirrored`: a walk that turns left becomes one that turns right, so the data turns
    /// both ways alike. The collected shards are kept; clips mirrored before are skipped.
    Mirror {
        /// The dataset directory.
        dir: PathBuf,
    },
    /// Hours per clip and sigma, fall rates, feature ranges, and coverage plots (PNG/SVG).
    Inspect {
        /// The dataset directory.
        dir: PathBuf,
    },
}

/// `flowmimic collect`: every expert run on its clips (the run's own, or `clips` for a single
/// run), each appended to the dataset in `out`.
pub fn run_collect(
    humanoid: &Arc<Humanoid>,
    runs: Vec<PathBuf>,
    clips: &[PathBuf],
    out: PathBuf,
    cfg: CollectConfig,
) -> Result<()> {
    if !clips.is_empty() && runs.len() != 1 {
        bail!("--clip pairs clips with one expert run, and {} runs were given", runs.len());
    }
    // Every clip is read before the first rollout, so a bad one costs nothing.
    let clips =
        clips.iter().map(|path| Ok(flowmimic_motion::Clip::load(humanoid, path)?)).collect::<Result<Vec<_>>>()?;
    let mut dataset = Dataset::open_or_create(&out)?;
    for run in &runs {
        collect_run(humanoid, run, &clips, &mut dataset, &cfg)?;
    }
    println!("dataset {} now holds {} clips", out.display(), dataset.manifest.shards.len());
    Ok(())
}

/// One run: its expert (policy.safetensors) on `clips`, or on its own clips (clip.safetensors)
/// when there are none.
fn collect_run(
    humanoid: &Arc<Humanoid>,
    run: &std::path::Path,
    clips: &[flowmimic_motion::Clip],
    dataset: &mut Dataset,
    cfg: &CollectConfig,
) -> Result<()> {
    let expert = run.join(flowmimic_track::train::POLICY_FILE);
    let ck = Checkpoint::read(&expert)?;
    let (expert_cfg, policy) = (ck.config()?, ck.policy()?);
    let own;
    let clips = if clips.is_empty() {
        own = crate::track::run_clips(humanoid, run)?;
        &own
    } else {
        clips
    };
    for clip in clips {
        collect_clip(humanoid, &expert, clip, &policy, &expert_cfg, dataset, cfg)?;
    }
    Ok(())
}

/// One clip of a run: its noisy rollouts become the clip's shard.
fn collect_clip(
    humanoid: &Arc<Humanoid>,
    expert: &std::path::Path,
    clip: &flowmimic_motion::Clip,
    policy: &flowmimic_track::ppo::Policy,
    expert_cfg: &flowmimic_track::TrackConfig,
    dataset: &mut Dataset,
    cfg: &CollectConfig,
) -> Result<()> {
    let envs: usize = cfg.noise.iter().map(|n| n.1).sum();
    eprintln!(
        "collecting {} with {envs} noisy rollouts of {} steps",
        clip.name,
        if cfg.rollout_steps == 0 { clip.len() - 1 } else { cfg.rollout_steps }
    );
    let (shard, stats) = collect(humanoid, clip, policy, expert_cfg, cfg)?;
    let info = ShardInfo {
        file: format!("{}.rollouts.safetensors", clip.name),
        clip: clip.name.clone(),
        expert: expert.display().to_string(),
        seed: cfg.seed,
        steps: shard.steps(),
        rollouts: shard.rollout.last().map_or(0, |r| *r as usize + 1),
        sigmas: cfg.noise.clone(),
        falls: stats.falls.clone(),
        sha256: String::new(),
        mirror_of: None,
    };
    dataset.add(info, &shard)?;
    println!("{} steps in {:.1} s: {:.0} steps/s", stats.steps, stats.seconds, stats.steps as f64 / stats.seconds);
    println!("{:>6} {:>9} {:>6} {:>10}", "sigma", "episodes", "falls", "fall rate");
    for (sigma, episodes, falls) in &stats.falls {
        println!("{sigma:>6.2} {episodes:>9} {falls:>6} {:>9.0}%", 100.0 * *falls as f64 / (*episodes).max(1) as f64);
    }
    Ok(())
}

pub fn run_dataset(cmd: DatasetCommand) -> Result<()> {
    let dir = match cmd {
        DatasetCommand::Stats { dir, history, horizon } => {
            let spec = WindowSpec { history, horizon };
            let stats = Stats::of_dataset(&Dataset::open(&dir)?, spec)?;
            println!("{} windows; wrote {}", stats.windows, dir.join(Stats::file_name(spec)).display());
            return Ok(());
        }
        DatasetCommand::Mirror { dir } => {
            let added = Dataset::open(&dir)?.add_mirror_images()?;
            println!("added {} mirrored clips to {}: {}", added.len(), dir.display(), added.join(" "));
            return Ok(());
        }
        DatasetCommand::Inspect { dir } => dir,
    };
    let dataset = Dataset::open(&dir)?;
    let shards = dataset.load_all()?;
    println!("{:<20} {:>6} {:>9} {:>8}", "clip", "sigma", "steps", "hours");
    let mut per_sigma: BTreeMap<String, (usize, usize, usize)> = BTreeMap::new();
    let (mut speeds, mut walking) = (Vec::new(), Vec::new());
    // Each step's left and right hand heights and the pelvis's (a crouch shows there).
    let (mut left, mut right, mut pelvis) = (Vec::new(), Vec::new(), Vec::new());
    let (mut s_lo, mut s_hi) = (vec![f32::MAX; STATE_DIM], vec![f32::MIN; STATE_DIM]);
    let (mut a_lo, mut a_hi) = (f32::MAX, f32::MIN);
    let mut per_clip = Vec::new();
    for (info, shard) in &shards {
        let mut steps: BTreeMap<String, usize> = BTreeMap::new();
        for &s in &shard.sigma {
            *steps.entry(format!("{s:.2}")).or_default() += 1;
        }
        for (sigma, n) in &steps {
            println!("{:<20} {sigma:>6} {n:>9} {:>8.3}", info.clip, *n as f64 / CONTROL_HZ / 3600.0);
        }
        let (mut clip_episodes, mut clip_falls) = (0, 0);
        for &(sigma, episodes, falls) in &info.falls {
            let e = per_sigma.entry(format!("{sigma:.2}")).or_default();
            e.0 += episodes;
            e.1 += falls;
            e.2 += 1;
            clip_episodes += episodes;
            clip_falls += falls;
        }
        for row in shard.state.chunks(STATE_DIM) {
            for (i, &x) in row.iter().enumerate() {
                s_lo[i] = s_lo[i].min(x);
                s_hi[i] = s_hi[i].max(x);
            }
            speeds.push(f64::from(row[offset::ROOT_VEL]).hypot(f64::from(row[offset::ROOT_VEL + 1])));
            let [l, r] = [body::L_HAND, body::R_HAND]
                .map(|h| f64::from(row[offset::ROOT_POS + 2] + row[offset::BODY_POS + 3 * h + 2]));
            left.push(l);
            right.push(r);
            pelvis.push(f64::from(row[offset::ROOT_POS + 2]));
        }
        for &a in &shard.action {
            a_lo = a_lo.min(a);
            a_hi = a_hi.max(a);
        }
        let clip_walking = walking_velocities(shard);
        walking.extend_from_slice(&clip_walking);
        per_clip.push((info.clip.clone(), Coverage::of_walks(clip_walking), clip_episodes, clip_falls));
    }
    // Per clip, so that one expert that steps in place or falls cannot hide behind the total.
    println!(
        "\n{:<20} {:>9} {:>9} {:>8} {:>13} {:>11} {:>10} {:>10}",
        "clip", "steps", "backward", "turning", "sidestepping", "aside L/R", "reversing", "fall rate"
    );
    for (clip, cov, episodes, falls) in &per_clip {
        println!(
            "{clip:<20} {:>9} {:>8.1}% {:>7.1}% {:>12.1}% {:>5.1}/{:>4.1}% {:>9.1}% {:>9.0}%",
            cov.steps,
            100.0 * cov.backward,
            100.0 * cov.turning,
            100.0 * cov.sidestep,
            100.0 * cov.aside[0],
            100.0 * cov.aside[1],
            100.0 * cov.reversing,
            100.0 * *falls as f64 / (*episodes).max(1) as f64
        );
    }
    println!("\n{:>6} {:>9} {:>6} {:>10}", "sigma", "episodes", "falls", "fall rate");
    for (sigma, (episodes, falls, _)) in &per_sigma {
        println!("{sigma:>6} {episodes:>9} {falls:>6} {:>9.0}%", 100.0 * *falls as f64 / (*episodes).max(1) as f64);
    }
    println!("\nfeature ranges (min .. max over all steps)");
    let block = |name: &str, from: usize, to: usize| {
        let lo = s_lo[from..to].iter().cloned().fold(f32::MAX, f32::min);
        let hi = s_hi[from..to].iter().cloned().fold(f32::MIN, f32::max);
        println!("  {name:<28} {lo:>8.3} .. {hi:>8.3}");
    };
    block("root height (m)", 2, 3);
    block("root velocity (m/s)", offset::ROOT_VEL, offset::ROOT_ROT);
    block("root rotation (rotvec)", offset::ROOT_ROT, offset::BODY_POS);
    block("body positions (m)", offset::BODY_POS, offset::BODY_VEL);
    block("body velocities (m/s)", offset::BODY_VEL, offset::END_ROT);
    block("hand/ankle rotations", offset::END_ROT, STATE_DIM);
    println!("  {:<28} {a_lo:>8.3} .. {a_hi:>8.3}", format!("actions ({NUM_DOFS}, normalised)"));
    Chart::new("state coverage: root speed", "root speed (m/s)", "fraction of steps")
        .series(Series::line("root speed", flowmimic_plot::histogram(&speeds, 0.0, 3.0, 30)))
        .save(&dir.join("coverage_root_speed"))?;
    Chart::new("state coverage: hand height", "hand height above ground (m)", "fraction of hand samples")
        .series(Series::line("hands", flowmimic_plot::histogram(&[left.as_slice(), &right].concat(), 0.0, 2.0, 40)))
        .save(&dir.join("coverage_hand_height"))?;
    print_hand_heights(&left, &right, &pelvis);
    println!("\nwrote coverage_root_speed and coverage_hand_height (.png, .svg) in {}", dir.display());
    crate::motion::print_coverage(&Coverage::of_walks(walking), &dir)
}

/// Below this height (m) the pelvis is in a crouch: it stands at about 0.9 m.
const PELVIS_LOW: f64 = 0.8;

/// The histogram of each hand's height over steps (and of the higher one), in 0.1 m bins, and
/// the shares above the reaching heights and below the bending ones.
fn print_hand_heights(left: &[f64], right: &[f64], pelvis: &[f64]) {
    let higher: Vec<f64> = left.iter().zip(right).map(|(l, r)| l.max(*r)).collect();
    let share = |heights: &[f64], within: &dyn Fn(f64) -> bool| {
        100.0 * heights.iter().filter(|&&x| within(x)).count() as f64 / heights.len().max(1) as f64
    };
    println!("\nhand height (m)   left    right   higher (share of steps)");
    for k in 0..20 {
        let (lo, hi) = (0.1 * k as f64, 0.1 * (k + 1) as f64);
        let [l, r, h] = [left, right, &higher].map(|x| share(x, &|v| (lo..hi).contains(&v)));
        if l + r > 0.0 {
            println!("  {lo:.1}-{hi:.1}  {l:>7.1}% {r:>7.1}% {h:>7.1}%  {}", "#".repeat(h.round() as usize));
        }
    }
    println!(
        "  a hand above {HAND_HIGH} m in {:.1}% of steps, above {HAND_OVERHEAD} m in {:.1}%",
        share(&higher, &|v| v > HAND_HIGH),
        share(&higher, &|v| v > HAND_OVERHEAD)
    );
    println!(
        "  the right hand below {HAND_LOW} m in {:.1}% of steps, the left in {:.1}%; the pelvis below {PELVIS_LOW} m in {:.1}%",
        share(right, &|v| v < HAND_LOW),
        share(left, &|v| v < HAND_LOW),
        share(pelvis, &|v| v < PELVIS_LOW)
    );
}

/// Walking velocities of every step of a shard, episode by episode, each episode's root path
/// measured on its own.
fn walking_velocities(shard: &flowmimic_data::Shard) -> Vec<Vec<[f64; 3]>> {
    let mut out = Vec::new();
    let mut path: Vec<[f64; 3]> = Vec::new();
    for k in 0..shard.steps() {
        let p = &shard.root_pose[3 * k..3 * k + 3];
        path.push([f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]);
        let last_of_rollout = k + 1 == shard.steps() || shard.rollout[k + 1] != shard.rollout[k];
        if shard.done[k] == 1 || last_of_rollout {
            out.push(flowmimic_motion::coverage::walking_velocities(&path));
            path.clear();
        }
    }
    out
}
