//! The default corpus (`flowmimic motion corpus`): wandering walks, a steady backward walk, the
//! walking captures of a folder and, unless walking only, the captures of its `arms/` (hands
//! busy, 0.1-1.9 m high) and `walks/` subfolders.

use crate::clip::BODY_SPEED_JUMP;
use crate::generator::{GaitParams, WanderParams, generate, wander};
use crate::reach::Reaching;
use crate::{Clip, ImportOptions, MotionError, import};
use flowmimic_sim::Humanoid;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Mean speed above which a capture is not walking (DeepMimic's run is 3.2 m/s), m/s.
pub const MAX_WALKING_SPEED: f64 = 2.0;

/// Name of the corpus's generated backward walk.
pub const BACKWARD_WALK: &str = "walk_back";

/// The backward walk: 10 s at 0.6 m/s. The wandering walks walk backward only in short
/// stretches between other commands, and experts over them step in place there; this clip's
/// expert walks backward, which is what gives a dataset of the corpus its backward share.
pub fn backward_walk() -> GaitParams {
    GaitParams { speed: -0.6, duration: 10.0, ..GaitParams::default() }
}

/// The corpus's wandering walks by default: how many, and how long each is, s.
pub const WANDERING_WALKS: usize = 4;
pub const WANDERING_SECONDS: f64 = 40.0;

/// The corpus's reaching walks and walks of transitions by default.
pub const REACHING_WALKS: usize = 4;
pub const TRANSITION_WALKS: usize = 2;

/// Share of the time a hand is out in the corpus's reaching walks (`reach_<seed>`), and in its
/// standing reaches (`reach_stand`). The walker stops for each reach, 0.6 s before and after it
/// as well: at 0.6 the reaching walks stood 95% of the time, at 0.45 they walk faster than 0.3
/// m/s in 8-19% of their frames (docs/data.md, "Feet planted while a hand is out").
pub const REACH_SHARE: f64 = 0.45;
pub const STAND_REACH_SHARE: f64 = 0.9;

/// The standing reaches: 30 s in place, a hand out 90% of the time.
pub fn standing_reaches() -> GaitParams {
    let reach = Some(Reaching { share: STAND_REACH_SHARE, seed: 0, heights: Default::default() });
    GaitParams { speed: 0.0, duration: 30.0, reach, ..GaitParams::default() }
}

/// What goes into the corpus.
#[derive(Clone, Debug)]
pub struct CorpusParams {
    /// Wandering walks, seeds 1..=walks, named `wander_<seed>`.
    pub walks: usize,
    /// Length of each wandering walk, s.
    pub duration: f64,
    /// Wandering walks whose hands reach for targets, seeds 1..=reaching, named
    /// `reach_<seed>`, and 30 s of standing reaches (`reach_stand`) when there are any.
    pub reaching: usize,
    /// Walks of transitions (reversals, stops and starts, sidesteps, turns on the spot), seeds
    /// 1..=transitions, named `transitions_<seed>`.
    pub transitions: usize,
    /// Folder of captures (.bvh, DeepMimic .txt); `None` for generated walks only.
    pub mocap: Option<PathBuf>,
    /// Only the walking corpus (the folder's top level), without its [`SUBFOLDERS`].
    pub walking_only: bool,
}

/// Subfolders of the capture folder read beside its top level: captures with the arms busy,
/// and more walks.
pub const SUBFOLDERS: [&str; 2] = ["arms", "walks"];

/// The corpus's clips and the captures it left out, with why.
pub struct Corpus {
    pub clips: Vec<Clip>,
    pub left_out: Vec<(PathBuf, String)>,
}

/// Builds the corpus: the wandering walks, the backward walk ([`backward_walk`]), the reaching
/// walks and standing reaches, the walks of transitions, then every
/// capture of the folder in name order that walks (mean speed at most [`MAX_WALKING_SPEED`])
/// and does not jump (no body faster than [`BODY_SPEED_JUMP`] between two frames),
/// then those of its [`SUBFOLDERS`] that exist, each in name order.
pub fn corpus(humanoid: &Arc<Humanoid>, p: &CorpusParams) -> Result<Corpus, MotionError> {
    let mut clips = Vec::new();
    for seed in 1..=p.walks as u64 {
        clips.push(
            wander(
                humanoid,
                &format!("wander_{seed}"),
                &WanderParams { seed, duration: p.duration, ..Default::default() },
            )?
            .0,
        );
    }
    clips.push(generate(humanoid, BACKWARD_WALK, &backward_walk())?.0);
    for seed in 1..=p.reaching as u64 {
        let reach = Some(Reaching { share: REACH_SHARE, seed, heights: Default::default() });
        let walk = WanderParams { seed, duration: p.duration, reach, ..Default::default() };
        clips.push(wander(humanoid, &format!("reach_{seed}"), &walk)?.0);
    }
    if p.reaching > 0 {
        clips.push(generate(humanoid, "reach_stand", &standing_reaches())?.0);
    }
    for seed in 1..=p.transitions as u64 {
        let walk = WanderParams { seed, duration: p.duration, transitions: true, ..Default::default() };
        clips.push(wander(humanoid, &format!("transitions_{seed}"), &walk)?.0);
    }
    let mut left_out = Vec::new();
    if let Some(mocap) = &p.mocap {
        let mut files = captures(mocap)?;
        if !p.walking_only {
            for sub in SUBFOLDERS.iter().map(|s| mocap.join(s)).filter(|d| d.is_dir()) {
                files.extend(captures(&sub)?);
            }
        }
        for file in files {
            let clip = import(humanoid, &file, &ImportOptions::default())?.clip;
            let quality = clip.quality(humanoid);
            if quality.speed > MAX_WALKING_SPEED {
                left_out.push((file, format!("moves at {:.1} m/s, not a walk", quality.speed)));
            } else if quality.body_speed_max > BODY_SPEED_JUMP {
                let why = format!("jumps: a body moves {:.1} m/s between two frames", quality.body_speed_max);
                left_out.push((file, why));
            } else {
                clips.push(clip);
            }
        }
    }
    Ok(Corpus { clips, left_out })
}

/// The .bvh and .txt files of a folder, sorted by name.
fn captures(dir: &Path) -> Result<Vec<PathBuf>, MotionError> {
    let entries = std::fs::read_dir(dir).map_err(|e| MotionError::file(dir, format!("cannot read the folder: {e}")))?;
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("bvh") || e.eq_ignore_ascii_case("txt")))
        .collect();
    files.sort();
    Ok(files)
}
