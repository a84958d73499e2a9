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
use flowmimic_data::Dataset;
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

/// The clips the pipeline trains on: the given files, or the generated 10 s straight walk. They
/// replace the clips an earlier run left in `dir` (whose experts stay where they are, unused).
fn clips(humanoid: &Arc<Humanoid>, files: &[PathBuf], dir: &Path) -> Result<Vec<PathBuf>> {
    let clips = crate::track::load_clips(humanoid, files)?;
    if let Ok(entries) = std::fs::read_dir(dir) {
        for old in entries.filter_map(|e| e.ok().map(|e| e.path())) {
            if old.to_string_lossy().ends_with(".clip.safetensors") {
                std::fs::remove_file(&old).with_context(|| format!("removing {}", old.display()))?;
            }
        }
    }
    clips
        .iter()
        .map(|clip| {
            let path = dir.join(format!("{}.clip.safetensors", clip.name));
            clip.save(&path)?;
            Ok(path)
        })
        .collect()
}

/// One stage of the pipeline, to run alone (`--only`): on a cluster each is a task, the
/// per-clip ones (an expert and its rollouts) side by side. Its inputs must be done already.
#[derive(Clone, Debug, PartialEq)]
pub enum Only {
    Clips,
    /// The expert of one clip (by name).
    Expert(String),
    /// The noisy rollouts of one clip's expert, a dataset of its own in `rollouts/<clip>`.
    Rollouts(String),
    /// The dataset: the parts joined when every clip's are done, else collected here.
    Collect,
    /// One model (`fm` or `ddpm`).
    Train(String),
    Evaluate,
}

impl std::str::FromStr for Only {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let (stage, arg) = s.split_once(':').map_or((s, None), |(a, b)| (a, Some(b.to_string())));
        match (stage, arg) {
            ("clips", None) => Ok(Only::Clips),
            ("expert", Some(clip)) => Ok(Only::Expert(clip)),
            ("rollouts", Some(clip)) => Ok(Only::Rollouts(clip)),
            ("collect", None) => Ok(Only::Collect),
            ("train", Some(o)) if OBJECTIVES.contains(&o.as_str()) => Ok(Only::Train(o)),
            ("evaluate", None) => Ok(Only::Evaluate),
            _ => Err(format!(
                "'{s}' is not a stage: clips, expert:CLIP, rollouts:CLIP, collect, train:fm, train:ddpm or evaluate"
            )),
        }
    }
}

/// The models the pipeline trains.
const OBJECTIVES: [&str; 2] = ["fm", "ddpm"];

/// The stages' directories under one output directory, and what every stage needs.
struct Stages<'a> {
    config: &'a Config,
    humanoid: Arc<Humanoid>,
    out: &'a Path,
    quick: bool,
}

/// The key a finished stage left in `dir`: the input of the stages after it.
fn done(dir: &Path, stage: &str) -> Result<String> {
    stamp_of(dir).with_context(|| format!("{} is not done yet: run the {stage} stage first", dir.display()))
}

impl Stages<'_> {
    fn clips_dir(&self) -> PathBuf {
        self.out.join("clips")
    }

    fn expert_dir(&self, clip: &str) -> PathBuf {
        self.out.join("experts").join(clip)
    }

    fn data_dir(&self) -> PathBuf {
        self.out.join("data")
    }

    fn part_dir(&self, clip: &str) -> PathBuf {
        self.out.join("rollouts").join(clip)
    }

    fn model_dir(&self, objective: &str) -> PathBuf {
        self.out.join("model").join(objective)
    }

    fn clips(&self, clip_files: &[PathBuf]) -> Result<String> {
        let files: Vec<String> = clip_files.iter().map(|f| f.display().to_string()).collect();
        let dir = self.clips_dir();
        stage("clips", &dir, key(&[json(&self.config.sim), files.join(",")]), || {
            clips(&self.humanoid, clip_files, &dir).map(drop)
        })
    }

    /// The names of the clips the clips stage wrote, in name order.
    fn clip_names(&self) -> Result<Vec<String>> {
        let dir = self.clips_dir();
        let entries = std::fs::read_dir(&dir).with_context(|| format!("reading {}", dir.display()))?;
        let mut names: Vec<String> = entries
            .filter_map(|e| e.ok()?.file_name().to_str()?.strip_suffix(".clip.safetensors").map(String::from))
            .collect();
        names.sort();
        Ok(names)
    }

    fn expert(&self, clips_key: &str, name: &str) -> Result<String> {
        let path = self.clips_dir().join(format!("{name}.clip.safetensors"));
        if !path.exists() {
            anyhow::bail!("{}: no such clip in the clips stage's output", path.display());
        }
        let clip = Clip::load(&self.humanoid, &path)?;
        let dir = self.expert_dir(name);
        let k = key(&[clips_key.to_string(), json(&self.config.track)]);
        stage(&format!("expert '{name}'"), &dir, k, || {
            let start = if dir.join(crate::track::RUN_POLICY).exists() { Start::Resume } else { Start::Fresh };
            crate::track::train(&self.humanoid, vec![clip], &dir, &self.config.track, start)
        })
    }

    /// The key of a clip's rollouts and of the dataset, from their experts' keys.
    fn collect_key(&self, expert_keys: &[String]) -> String {
        key(&[expert_keys.join(","), json(&self.config.collect)])
    }

    fn rollouts(&self, name: &str) -> Result<String> {
        let expert_key = done(&self.expert_dir(name), &format!("expert:{name}"))?;
        let dir = self.part_dir(name);
        stage(&format!("rollouts '{name}'"), &dir, self.collect_key(&[expert_key]), || {
            fresh_dataset(&dir)?;
            crate::data::run_collect(
                &self.humanoid,
                vec![self.expert_dir(name)],
                &[],
                dir.clone(),
                self.config.collect.clone(),
            )
        })
    }

    /// The dataset from every clip's expert: joined from `rollouts/` when every clip's are
    /// done for these experts (the same shards, bit for bit), else collected here.
    fn collect(&self, names: &[String], expert_keys: &[String]) -> Result<String> {
        let data = self.data_dir();
        stage("collect", &data, self.collect_key(expert_keys), || {
            let parts: Vec<PathBuf> = names.iter().map(|n| self.part_dir(n)).collect();
            let joined = parts
                .iter()
                .zip(expert_keys)
                .all(|(dir, k)| stamp_of(dir).as_deref() == Some(self.collect_key(std::slice::from_ref(k)).as_str()));
            // A half-written dataset from an interrupted run is replaced, never appended to.
            let mut dataset = fresh_dataset(&data)?;
            if joined {
                eprintln!("joining the rollouts of {} clips from {}", parts.len(), self.out.join("rollouts").display());
                for part in &parts {
                    for (info, shard) in Dataset::open(part)?.load_all()? {
                        dataset.add(info, &shard)?;
                    }
                }
                return Ok(());
            }
            let experts = names.iter().map(|n| self.expert_dir(n)).collect();
            crate::data::run_collect(&self.humanoid, experts, &[], data.clone(), self.config.collect.clone())
        })
    }

    fn train(&self, data_key: &str, objective: &str) -> Result<String> {
        let (data, dir) = (self.data_dir(), self.model_dir(objective));
        // The FM model gets inverse dynamics beside it (`run --inverse-dynamics`).
        let fm = objective == "fm";
        let config = self.config;
        let mut parts = vec![data_key.to_string(), json(&config.model), json(&config.train), objective.into()];
        parts.extend(fm.then(|| json(&config.inverse)));
        let key = key(&parts);
        // A finished model made from other data or settings is the user's: never overwritten.
        if stamp_of(&dir).is_some_and(|k| k != key) {
            anyhow::bail!(
                "pipeline stage 'train {objective}': {} holds a model trained on other data or settings; \
                 move it away, or give the pipeline another output directory (-o)",
                dir.display()
            );
        }
        stage(&format!("train {objective}"), &dir, key, || {
            let resume = dir.join(flowmimic_model::train::CHECKPOINT_FILE).exists();
            crate::model::train(&data, objective, &dir, None, resume, config.model, config.train.clone())?;
            if fm {
                crate::model::fit_inverse(std::slice::from_ref(&data), &dir, &config.inverse)?;
            }
            Ok(())
        })
    }

    fn evaluate(&self, model_keys: &[String]) -> Result<String> {
        let eval_dir = self.out.join("eval");
        let models: Vec<String> = OBJECTIVES.iter().map(|o| format!("{o}={}", self.model_dir(o).display())).collect();
        let (quick, humanoid) = (self.quick, &self.humanoid);
        stage("evaluate", &eval_dir, key(&[model_keys.join(","), quick.to_string()]), || {
            let common = || Common::new(models.clone(), eval_dir.clone(), quick);
            eval::run(EvalCommand::Survival { common: common(), nfe: vec![1, 2, 5, 10, 20], seconds: None }, humanoid)?;
            eval::run(EvalCommand::Latency { common: common(), nfe: vec![1, 2, 5, 10, 20], guided: None }, humanoid)?;
            let fm_only = || Common::new(models[..1].to_vec(), eval_dir.clone(), quick);
            let sweep = || Sweep { scales: vec![0.0, 3.0, 10.0, 30.0], nfe: Some(5) };
            eval::run(EvalCommand::Joystick { common: fm_only(), sweep: sweep() }, humanoid)?;
            eval::run(
                EvalCommand::Reach {
                    common: fm_only(),
                    sweep: sweep(),
                    heights: eval::REACH_HEIGHTS.to_vec(),
                    approach: Some(false),
                },
                humanoid,
            )?;
            Ok(())
        })
    }
}

/// An empty dataset in `dir`, whatever was there.
fn fresh_dataset(dir: &Path) -> Result<Dataset> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    Ok(Dataset::open_or_create(dir)?)
}

/// Runs every stage in order, or only the stage `only` (whose inputs must be done).
pub fn run(config: &Config, preset: &str, out: &Path, clip_files: &[PathBuf], only: Option<Only>) -> Result<()> {
    let stages = Stages { config, humanoid: Humanoid::new(config.sim)?, out, quick: preset != "paper" };
    let started = Instant::now();
    let experts_done = |names: &[String]| -> Result<Vec<String>> {
        names.iter().map(|n| done(&stages.expert_dir(n), &format!("expert:{n}"))).collect()
    };
    let models_done = || -> Result<Vec<String>> {
        OBJECTIVES.iter().map(|o| done(&stages.model_dir(o), &format!("train:{o}"))).collect()
    };
    match only {
        Some(Only::Clips) => stages.clips(clip_files).map(drop),
        Some(Only::Expert(name)) => stages.expert(&done(&stages.clips_dir(), "clips")?, &name).map(drop),
        Some(Only::Rollouts(name)) => stages.rollouts(&name).map(drop),
        Some(Only::Collect) => {
            let names = stages.clip_names()?;
            stages.collect(&names, &experts_done(&names)?).map(drop)
        }
        Some(Only::Train(objective)) => stages.train(&done(&stages.data_dir(), "collect")?, &objective).map(drop),
        Some(Only::Evaluate) => stages.evaluate(&models_done()?).map(drop),
        None => {
            let clips_key = stages.clips(clip_files)?;
            let names = stages.clip_names()?;
            let expert_keys = names.iter().map(|n| stages.expert(&clips_key, n)).collect::<Result<Vec<_>>>()?;
            let data_key = stages.collect(&names, &expert_keys)?;
            let model_keys = OBJECTIVES.iter().map(|o| stages.train(&data_key, o)).collect::<Result<Vec<_>>>()?;
            stages.evaluate(&model_keys)?;
            eprintln!(
                "pipeline finished in {:.1} min: report {}, models in {}",
                started.elapsed().as_secs_f64() / 60.0,
                out.join("eval").join("report.md").display(),
                out.join("model").display()
            );
            Ok(())
        }
    }
}
