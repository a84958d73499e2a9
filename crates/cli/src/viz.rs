//! `flowmimic render` and `flowmimic view`: pictures of clip and rollout files.

use anyhow::{Result, bail};
use flowmimic_control::Rollout;
use flowmimic_motion::Clip;
use flowmimic_serve::view::ViewData;
use flowmimic_sim::Humanoid;
use flowmimic_viz::Frames;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A clip or one environment of a rollout, told apart by the file's `format` metadata.
enum Source {
    Clip(Clip),
    Rollout(Box<Rollout>, usize),
}

fn open(humanoid: &Arc<Humanoid>, file: &Path, env: usize) -> Result<(Source, String)> {
    let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stem = name.trim_end_matches(".safetensors").to_string();
    let format = flowmimic_io::tensors::TensorFile::open(file)?.meta("format")?.to_string();
    if format == flowmimic_motion::clip::FORMAT {
        return Ok((Source::Clip(Clip::load(humanoid, file)?), stem));
    }
    let rollout = Rollout::load(file)?;
    if env >= rollout.envs {
        bail!("{}: --env {env}, but the rollout has {} environments", file.display(), rollout.envs);
    }
    Ok((Source::Rollout(Box::new(rollout), env), stem))
}

pub fn render(
    humanoid: &Arc<Humanoid>,
    file: &Path,
    out: Option<PathBuf>,
    env: usize,
    size: (usize, usize),
    fps: usize,
) -> Result<()> {
    let (source, stem) = open(humanoid, file, env)?;
    let frames = match &source {
        Source::Clip(clip) => Frames::from_clip(clip),
        Source::Rollout(r, env) => Frames::from_rollout(r, *env, &stem),
    };
    let out = out.unwrap_or_else(|| PathBuf::from("runs/render").join(format!("{stem}.gif")));
    let r = flowmimic_viz::render(humanoid, &frames, &out, size, fps)?;
    let files: Vec<String> = r.files.iter().map(|f| f.display().to_string()).collect();
    println!(
        "rendered {} frames in {:.1} s ({:.0} ms per frame): {}",
        r.frames,
        r.seconds,
        1e3 * r.seconds / r.frames as f64,
        files.join(", ")
    );
    Ok(())
}

pub fn view(humanoid: &Arc<Humanoid>, file: &Path, env: usize, port: u16) -> Result<()> {
    let (source, stem) = open(humanoid, file, env)?;
    let data = match &source {
        Source::Clip(clip) => ViewData::from_clip(clip),
        Source::Rollout(r, env) => ViewData::from_rollout(r, *env, &stem),
    };
    flowmimic_serve::serve(flowmimic_serve::view::router(&data), port, |url| {
        println!("viewer: {url} (Ctrl-C stops it)")
    })?;
    Ok(())
}
