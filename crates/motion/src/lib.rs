//! Motion clips for the humanoid: import (BVH of any skeleton, DeepMimic), retargeting, a
//! procedural walking generator, and the clip file format.
//!
//! Every source becomes [`landmarks::LandmarkClip`] (world positions of 17 joints) and goes
//! through the same [`retarget::retarget`], so imported and generated clips are treated alike.

pub mod bvh;
pub mod clip;
pub mod corpus;
pub mod coverage;
pub mod generator;
pub mod joint_map;
pub mod landmarks;
pub mod reach;
pub mod retarget;

pub use clip::{Clip, Quality};
pub use corpus::{Corpus, CorpusParams, corpus};
pub use coverage::Coverage;
pub use generator::{
    Command, GaitParams, Schedule, Segment, WanderParams, generate, scheduled, standing, straight_walk, wander,
};

pub use landmarks::{Units, UpAxis};
pub use retarget::RetargetReport;

use flowmimic_sim::Humanoid;
use landmarks::{Landmark, LandmarkClip};
use std::path::{Path, PathBuf};
use std::sync::Arc;

#[derive(Debug, thiserror::Error)]
pub enum MotionError {
    // Not `source`: the message already carries the BVH error (a chain would print it twice).
    #[error("{path}: {error}")]
    Bvh { path: PathBuf, error: bvh::BvhError },
    #[error("{path}: {message}")]
    File { path: PathBuf, message: String },
    #[error(transparent)]
    Io(#[from] flowmimic_io::FileError),
    #[error("{0}")]
    Invalid(String),
}

impl MotionError {
    pub(crate) fn file(path: &Path, message: impl Into<String>) -> Self {
        Self::File { path: path.to_path_buf(), message: message.into() }
    }
}

/// Overrides for what [`import`] would otherwise detect.
#[derive(Clone, Debug, Default)]
pub struct ImportOptions {
    pub units: Option<Units>,
    pub up: Option<UpAxis>,
    /// Mark the clip cyclic (DeepMimic files say so themselves).
    pub cyclic: Option<bool>,
    /// Clip name; the file stem by default.
    pub name: Option<String>,
    /// Joints forced for landmarks (BVH only; see [`joint_map::ForcedMap`]).
    pub map: Option<joint_map::ForcedMap>,
}

/// What [`import`] found and did.
#[derive(Clone, Debug)]
pub struct Imported {
    pub clip: Clip,
    pub report: RetargetReport,
    pub family: String,
    pub units: Option<Units>,
    pub up: UpAxis,
    pub source_fps: f64,
    /// Leading frames dropped (an artificial T-pose, as CMU's cgspeed files start with).
    pub dropped_frames: usize,
    /// For BVH files: which joint became which landmark and how sure that is, a line each.
    pub joint_map: Vec<String>,
}

/// Whether both arms are horizontal: the pose of a T-pose calibration frame, never of walking.
fn is_t_pose(p: &landmarks::Pose) -> bool {
    [(Landmark::LShoulder, Landmark::LWrist), (Landmark::RShoulder, Landmark::RWrist)].iter().all(|&(s, w)| {
        let d = p[w] - p[s];
        d.z.abs() < 0.25 * d.length()
    })
}

/// Imports a BVH (`.bvh`) or DeepMimic (`.txt`/`.json`) file and retargets it.
pub fn import(humanoid: &Arc<Humanoid>, path: &Path, options: &ImportOptions) -> Result<Imported, MotionError> {
    let text = String::from_utf8(flowmimic_io::read(path)?).map_err(|_| {
        MotionError::file(path, format!("not a BVH or DeepMimic motion: it is {}", flowmimic_io::describe(path)))
    })?;
    let name = options
        .name
        .clone()
        .unwrap_or_else(|| path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "clip".into()));
    let is_bvh = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("bvh"));
    let mut joint_map = Vec::new();
    let (mut source, family, units, up, mut cyclic): (LandmarkClip, String, Option<Units>, UpAxis, bool) = if is_bvh {
        let bvh = bvh::Bvh::parse(&text).map_err(|error| MotionError::Bvh { path: path.into(), error })?;
        let reading = landmarks::from_bvh(&bvh, options.units, options.up, options.map.as_ref())
            .map_err(|e| MotionError::file(path, e.to_string()))?;
        joint_map = reading.map.describe(&bvh);
        if let Some(why) = &reading.map.note {
            joint_map.push(format!("(the structure could not be read: {why}; names alone)"));
        }
        (reading.clip, reading.family.to_string(), Some(reading.units), reading.up, false)
    } else {
        let dm = landmarks::deepmimic::parse(&text).map_err(|e| MotionError::file(path, e.to_string()))?;
        (dm.clip, "DeepMimic humanoid3d".into(), None, UpAxis::Y, dm.cyclic)
    };
    let dropped_frames =
        usize::from(source.frames.len() > 2 && is_t_pose(&source.frames[0]) && !is_t_pose(&source.frames[1]));
    source.frames.drain(..dropped_frames);
    cyclic = options.cyclic.unwrap_or(cyclic);
    let origin = format!("{} ({family})", path.display());
    let (clip, report) = retarget::retarget(humanoid, &source, &name, &origin, cyclic)?;
    Ok(Imported { clip, report, family, units, up, source_fps: source.fps, dropped_frames, joint_map })
}
