//! The default varied-walking corpus (`flowmimic motion corpus`): wandering walks, a steady
//! backward walk and the walking captures of a folder.

use crate::generator::{GaitParams, WanderParams, generate, wander};
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

/// What goes into the corpus.
#[derive(Clone, Debug)]
pub struct CorpusParams {
    /// Wandering walks, seeds 1..=walks, named `wander_<seed>`.
    pub walks: usize,
    /// Length of each wandering walk, s.
    pub duration: f64,
    /// Folder of captures (.bvh, DeepMimic .txt); `None` for generated walks only.
    pub mocap: Option<PathBuf>,
}

/// The corpus's clips and the captures it left out, with why.
pub struct Corpus {
    pub clips: Vec<Clip>,
    pub left_out: Vec<(PathBuf, String)>,
}

/// Builds the corpus: the wandering walks, the backward walk ([`backward_walk`]), then every
/// capture of the folder in name order that walks (mean speed at most [`MAX_WALKING_SPEED`]).
pub fn corpus(humanoid: &Arc<Humanoid>, p: &CorpusParams) -> Result<Corpus, MotionError> {
    let mut clips = Vec::new();
    for seed in 1..=p.walks as u64 {
        clips.push(wander(humanoid, &format!("wander_{seed}"), &WanderParams { seed, duration: p.duration })?.0);
    }
    clips.push(generate(humanoid, BACKWARD_WALK, &backward_walk())?.0);
    let mut left_out = Vec::new();
    if let Some(mocap) = &p.mocap {
        for file in captures(mocap)? {
            let clip = import(humanoid, &file, &ImportOptions::default())?.clip;
            let speed = clip.quality(humanoid).speed;
            if speed > MAX_WALKING_SPEED {
                left_out.push((file, format!("moves at {speed:.1} m/s, not a walk")));
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
