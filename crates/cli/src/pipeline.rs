//! `flowmimic pipeline`: every stage in order, each skipped when its output is already there
//! for the same settings and inputs, resumed when it was interrupted.
//!
//! A finished stage leaves `stage.json` in its directory: a SHA-256 over the stage's settings
//! and its inputs' stamps. A rerun with the same key skips the stage; a different key reruns
//! it (trainers resume from their checkpoints when the settings allow it).

use crate::config::Config;
use crate::eval::{self, Common, EvalCommand, Sweep};
use crate::track::Start;
use anyhow::{Context, Result};
use flowmimic_motion::Clip;
use flowmimic_sim::Humanoid;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

const STAMP: &str = "stage.json";

/// A stage's key: its settings and what it was made from.
fn key(parts: &[String]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update(p.as_bytes());
        h.update([0]);
    }
    format!("{:x}", h.finalize())
}

fn stamp_of(dir: &Path) -> Option<String> {
    let text = std::fs::read_to_string(dir.join(STAMP)).ok()?;
    serde_json::from_str::<serde_json::Value>(&text).ok()?.get("key")?.as_str().map(String::from)
}

/// Settings as JSON text (for stage keys).
fn json(settings: &impl serde::Serialize) -> String {
    serde_json::to_string(settings).expect("settings serialise")
}

/// Runs `work` unless `dir` holds a stamp with `key`; returns the key (the next stage's input).
fn stage(name: &str, dir: &Path, key: String, work: impl FnOnce() -> Result<()>) -> Result<String> {
    if stamp_of(dir).as_deref() == Some(key.as_str()) {
        eprintln!("== {name}: up to date in {} (skipped)", dir.display());
        return Ok(key);
    }
    eprintln!("== {name} -> {}", dir.display());
    let started = Instant::now();
    work().with_context(|| format!("pipeline stage '{name}' ({})", dir.display()))?;
    let stamp = serde_json::json!({ "stage": name, "key": key, "seconds": started.elapsed().as_secs_f64() });
    flowmimic_io::write_atomic(&dir.join(STAMP), serde_json::to_string_pretty(&stamp)?.as_bytes())?;
    eprintln!("== {name}: done in {:.0} s", started.elapsed().as_secs_f64());
    Ok(key)
}

/// The clips the pipeline trains on: the given files, or the generated 10 s straight walk.
fn clips(humanoid: &Arc<Humanoid>, files: &[PathBuf], dir: &Path) -> Result<Vec<PathBuf>> {
    crate::track::load_clips(humanoid, files)?
        .iter()
        .map(|clip| {
            let path = dir.join(format!("{}.clip.safetensors", clip.name));
            clip.save(&path)?;
            Ok(path)
        })
        .collect()
}

pub fn run(config: &Config, preset: &str, out: &Path, clip_files: &[PathBuf]) -> Result<()> {
    let humanoid = Humanoid::new(config.sim)?;
    let started = Instant::now();
    let clips_dir = out.join("clips");
    let files: Vec<String> = clip_files.iter().map(|f| f.display().to_string()).collect();
    let mut clip_paths = Vec::new();
    let clips_key = stage("clips", &clips_dir, key(&[json(&config.sim), files.join(",")]), || {
        clip_paths = clips(&humanoid, clip_files, &clips_dir)?;
        Ok(())
    })?;
    if clip_paths.is_empty() {
        clip_paths = std::fs::read_dir(&clips_dir)?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.to_string_lossy().ends_with(".clip.safetensors"))
            .collect();
        clip_paths.sort();
    }
    let mut experts = Vec::new();
    let mut expert_keys = Vec::new();
    for path in &clip_paths {
        let clip = Clip::load(&humanoid, path)?;
        let dir = out.join("experts").join(&clip.name);
        let k =
            stage(&format!("expert '{}'", clip.name), &dir, key(&[clips_key.clone(), json(&config.track)]), || {
                let start = if dir.join(crate::track::RUN_POLICY).exists() { Start::Resume } else { Start::Fresh };
                crate::track::train(&humanoid, vec![clip.clone()], &dir, &config.track, start)
            })?;
        experts.push(dir);
        expert_keys.push(k);
    }
    let data = out.join("data");
    let data_key = stage("collect", &data, key(&[expert_keys.join(","), json(&config.collect)]), || {
        // A half-written dataset from an interrupted run is replaced, never appended to.
        if data.exists() {
            std::fs::remove_dir_all(&data).with_context(|| format!("removing {}", data.display()))?;
        }
        crate::data::run_collect(&humanoid, experts.clone(), &[], data.clone(), config.collect.clone())
    })?;
    let mut model_keys = Vec::new();
    for objective in ["fm", "ddpm"] {
        let dir = out.join("model").join(objective);
        // The FM model gets inverse dynamics beside it (`run --inverse-dynamics`).
        let fm = objective == "fm";
        let mut parts = vec![data_key.clone(), json(&config.model), json(&config.train), objective.into()];
        parts.extend(fm.then(|| json(&config.inverse)));
        model_keys.push(stage(&format!("train {objective}"), &dir, key(&parts), || {
            let resume = dir.join(flowmimic_model::train::CHECKPOINT_FILE).exists();
            crate::model::train(&data, objective, &dir, None, resume, config.model, config.train.clone())?;
            if fm {
                crate::model::fit_inverse(std::slice::from_ref(&data), &dir, &config.inverse)?;
            }
            Ok(())
        })?);
    }
    let eval_dir = out.join("eval");
    let models: Vec<String> =
        ["fm", "ddpm"].iter().map(|o| format!("{o}={}", out.join("model").join(o).display())).collect();
    let quick = preset != "paper";
    stage("evaluate", &eval_dir, key(&[model_keys.join(","), quick.to_string()]), || {
        let common = || Common::new(models.clone(), eval_dir.clone(), quick);
        eval::run(EvalCommand::Survival { common: common(), nfe: vec![1, 2, 5, 10, 20], seconds: None }, &humanoid)?;
        eval::run(EvalCommand::Latency { common: common(), nfe: vec![1, 2, 5, 10, 20], guided: None }, &humanoid)?;
        let fm_only = || Common::new(models[..1].to_vec(), eval_dir.clone(), quick);
        let sweep = || Sweep { scales: vec![0.0, 3.0, 10.0, 30.0], nfe: Some(5) };
        eval::run(EvalCommand::Joystick { common: fm_only(), sweep: sweep() }, &humanoid)?;
        eval::run(
            EvalCommand::Reach {
                common: fm_only(),
                sweep: sweep(),
                heights: eval::REACH_HEIGHTS.to_vec(),
                approach: Some(false),
            },
            &humanoid,
        )?;
        Ok(())
    })?;
    eprintln!(
        "pipeline finished in {:.1} min: report {}, models in {}",
        started.elapsed().as_secs_f64() / 60.0,
        eval_dir.join("report.md").display(),
        out.join("model").display()
    );
    Ok(())
}
