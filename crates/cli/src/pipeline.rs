//! `flowmimic pipeline`: every stage in order, each skipped when its output is already there
//! for the same settings and inputs, resumed when it was interrupted.
//!
//! A finished stage leaves `stage.json` in its directory: a SHA-256 over the stage's settings
//! and its inputs' stamps. A rerun with the same key skips the stage; a different key reruns
//! it (trainers resume from their checkpoints when the settings allow it).

use crate::config::Config;
use crate::eval::{self, Common, EvalCommand, Sweep};
use crate::motion::clip_path;
use crate::track::Start;
use anyhow::{Context, Result};
use flowmimic_data::Dataset;
use flowmimic_motion::{Clip, CorpusParams, corpus};
use flowmimic_sim::Humanoid;
use serde::{Deserialize, Serialize};
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

/// What `flowmimic pipeline` makes from what (`[pipeline]`): the clips when no `--clip` is
/// given, whether each clip gets its own expert or one policy tracks them all, and the models.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineConfig {
    /// `walk`: the generated 10 s straight walk; `walking-corpus`: `flowmimic motion corpus
    /// --walking-only` (4 wandering walks of 40 s, the backward walk and the walking captures of
    /// `../shared/data/mocap`); `generated`: the corpus's generated clips (the wandering walks,
    /// the backward walk, 4 reaching walks and the standing reaches, 2 walks of transitions);
    /// `generated-walks`: those without the reaches.
    pub clips: ClipSource,
    /// `each`: one expert per clip; `one`: one policy over every clip (`experts/all`).
    pub experts: Experts,
    /// The models, in order: `fm` and `ddpm`, or either.
    pub objectives: Vec<String>,
    /// With `experts = "one"`: an expert run directory (or policy file) the policy starts from,
    /// trained `init_iterations` more instead of `track.iterations` from new weights.
    /// `init_iterations = 0` trains from new weights, so that a file layered on a preset that
    /// sets `init` can turn it off.
    pub init: Option<PathBuf>,
    pub init_iterations: usize,
    /// A model directory whose `recommended.toml` settings (its comments left out: they measure
    /// that model) the FM model gets, so that commands driving it without flags use them.
    /// Changing them re-evaluates a finished model; it is not trained again.
    pub recommended: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ClipSource {
    Walk,
    WalkingCorpus,
    Generated,
    GeneratedWalks,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Experts {
    Each,
    One,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self {
            clips: ClipSource::Walk,
            experts: Experts::Each,
            objectives: OBJECTIVES.map(String::from).to_vec(),
            init: None,
            init_iterations: 0,
            recommended: None,
        }
    }
}

impl PipelineConfig {
    pub fn validate(&self) -> Result<(), String> {
        let known = self.objectives.iter().all(|o| OBJECTIVES.contains(&o.as_str()));
        let once = self.objectives.iter().enumerate().all(|(i, o)| !self.objectives[..i].contains(o));
        if self.objectives.is_empty() || !known || !once {
            return Err(format!("pipeline.objectives is {:?}: give fm, ddpm or both, once each", self.objectives));
        }
        if self.init_iterations > 0 && (self.init.is_none() || self.experts != Experts::One) {
            return Err("pipeline.init_iterations continues the one policy from pipeline.init: \
                 set experts = \"one\" and init"
                .into());
        }
        Ok(())
    }
}

/// The one policy's name when `[pipeline] experts = "one"`.
const ALL: &str = "all";

/// The clips the pipeline trains on: the given files, else those of `source`. They replace the
/// clips an earlier run left in `dir` (whose experts stay where they are, unused).
fn clips(humanoid: &Arc<Humanoid>, files: &[PathBuf], source: ClipSource, dir: &Path) -> Result<()> {
    let clips = match source {
        ClipSource::WalkingCorpus | ClipSource::Generated | ClipSource::GeneratedWalks if files.is_empty() => None,
        _ => Some(crate::track::load_clips(humanoid, files)?),
    };
    for old in clip_files(dir).unwrap_or_default() {
        std::fs::remove_file(&old).with_context(|| format!("removing {}", old.display()))?;
    }
    let Some(clips) = clips else {
        let (walks, duration) = (corpus::WANDERING_WALKS, corpus::WANDERING_SECONDS);
        let generated = |reaching| {
            let transitions = corpus::TRANSITION_WALKS;
            CorpusParams { walks, duration, reaching, transitions, mocap: None, walking_only: false }
        };
        let params = match source {
            ClipSource::Generated => generated(corpus::REACHING_WALKS),
            ClipSource::GeneratedWalks => generated(0),
            _ => {
                let mocap = Some(crate::paths::resolve(Path::new(crate::paths::MOCAP)));
                CorpusParams { walks, duration, reaching: 0, transitions: 0, mocap, walking_only: true }
            }
        };
        return crate::motion::corpus(humanoid, params, dir).map(drop);
    };
    for clip in &clips {
        clip.save(&clip_path(dir, &clip.name))?;
    }
    Ok(())
}

const CLIP_SUFFIX: &str = ".clip.safetensors";

/// The clip files in `dir`, in name order.
fn clip_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(CLIP_SUFFIX))
        .collect();
    files.sort();
    Ok(files)
}

/// One stage of the pipeline, to run alone (`--only`): on a cluster each is a task, the
/// per-clip ones (an expert and its rollouts) side by side. Its inputs must be done already.
#[derive(Clone, Debug, PartialEq)]
pub enum Only {
    Clips,
    /// An expert by name: a clip's own, or `all` with one policy over every clip.
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
            ("train", Some(o)) => Ok(Only::Train(o)),
            ("evaluate", None) => Ok(Only::Evaluate),
            _ => Err(format!(
                "'{s}' is not a stage: clips, expert:CLIP (expert:all with one policy), rollouts:CLIP, collect, \
                 train:fm, train:ddpm or evaluate"
            )),
        }
    }
}

/// The models the pipeline can train.
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
        let (dir, source) = (self.clips_dir(), self.config.pipeline.clips);
        stage("clips", &dir, key(&[json(&self.config.sim), files.join(","), json(&source)]), || {
            clips(&self.humanoid, clip_files, source, &dir)
        })
    }

    /// The expert that tracks a clip: its own, or the one policy.
    fn expert_of<'n>(&self, clip: &'n str) -> &'n str {
        match self.config.pipeline.experts {
            Experts::Each => clip,
            Experts::One => ALL,
        }
    }

    /// The experts to train, for these clips.
    fn expert_names(&self, clips: &[String]) -> Vec<String> {
        match self.config.pipeline.experts {
            Experts::Each => clips.to_vec(),
            Experts::One => vec![ALL.to_string()],
        }
    }

    /// The names of the clips the clips stage wrote, in name order.
    fn clip_names(&self) -> Result<Vec<String>> {
        let dir = self.clips_dir();
        let files = clip_files(&dir).with_context(|| format!("reading {}", dir.display()))?;
        Ok(files.iter().filter_map(|f| f.file_name()?.to_str()?.strip_suffix(CLIP_SUFFIX).map(String::from)).collect())
    }

    /// The expert `name`: a clip's own, or with one policy, `all` over every clip.
    fn expert(&self, clips_key: &str, name: &str) -> Result<String> {
        let clips = match self.config.pipeline.experts {
            Experts::One if name == ALL => self.clip_names()?,
            Experts::Each => vec![name.to_string()],
            Experts::One => anyhow::bail!("[pipeline] experts = \"one\": the one expert is '{ALL}', not '{name}'"),
        };
        let clips = clips
            .iter()
            .map(|clip| {
                let path = clip_path(&self.clips_dir(), clip);
                if !path.exists() {
                    anyhow::bail!("{}: no such clip in the clips stage's output", path.display());
                }
                Ok(Clip::load(&self.humanoid, &path)?)
            })
            .collect::<Result<Vec<_>>>()?;
        let dir = self.expert_dir(name);
        let p = &self.config.pipeline;
        // `init_iterations = 0` turns a preset's `init` off: the policy from new weights.
        let init = p
            .init
            .as_deref()
            .filter(|_| p.init_iterations > 0)
            .map(crate::paths::resolve)
            .map(|run| flowmimic_track::train::policy_file(&run));
        let mut track = self.config.track.clone();
        let mut parts = vec![clips_key.to_string(), json(&track)];
        if let Some(init) = &init {
            track.iterations = p.init_iterations;
            let policy = std::fs::read(init).with_context(|| format!("pipeline.init: reading {}", init.display()))?;
            parts.extend([format!("{:x}", Sha256::digest(&policy)), track.iterations.to_string()]);
        }
        stage(&format!("expert '{name}'"), &dir, key(&parts), || {
            let start = match init {
                _ if dir.join(flowmimic_track::train::POLICY_FILE).exists() => Start::Resume,
                Some(init) => Start::From(init),
                None => Start::Fresh,
            };
            crate::track::train(&self.humanoid, clips, &dir, &track, start)
        })
    }

    /// The key of a clip's rollouts and of the dataset, from their experts' keys.
    fn collect_key(&self, expert_keys: &[String]) -> String {
        key(&[expert_keys.join(","), json(&self.config.collect)])
    }

    fn rollouts(&self, name: &str) -> Result<String> {
        let expert = self.expert_of(name);
        let expert_key = done(&self.expert_dir(expert), &format!("expert:{expert}"))?;
        let clip = clip_path(&self.clips_dir(), name);
        let dir = self.part_dir(name);
        stage(&format!("rollouts '{name}'"), &dir, self.collect_key(&[expert_key]), || {
            fresh_dataset(&dir)?;
            let (runs, collect) = (vec![self.expert_dir(expert)], self.config.collect.clone());
            crate::data::run_collect(&self.humanoid, runs, &[clip], dir.clone(), collect)
        })
    }

    /// The dataset from every clip's expert: joined from `rollouts/` when every clip's are
    /// done for these experts (the same shards, bit for bit), else collected here.
    /// `names` are the clips, `experts` and `expert_keys` the experts and their stamps.
    fn collect(&self, names: &[String], experts: &[String], expert_keys: &[String]) -> Result<String> {
        let data = self.data_dir();
        stage("collect", &data, self.collect_key(expert_keys), || {
            let parts: Vec<PathBuf> = names.iter().map(|n| self.part_dir(n)).collect();
            let key_of = |clip: &String| {
                let k = &expert_keys[experts.iter().position(|e| e == self.expert_of(clip)).expect("its expert")];
                self.collect_key(std::slice::from_ref(k))
            };
            let joined = parts.iter().zip(names).all(|(dir, clip)| stamp_of(dir) == Some(key_of(clip)));
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
            let runs = experts.iter().map(|e| self.expert_dir(e)).collect();
            crate::data::run_collect(&self.humanoid, runs, &[], data.clone(), self.config.collect.clone())
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
        let key = stage(&format!("train {objective}"), &dir, key, || {
            let resume = dir.join(flowmimic_model::train::CHECKPOINT_FILE).exists();
            crate::model::train(&data, objective, &dir, None, resume, config.model, config.train.clone())?;
            if fm {
                crate::model::fit_inverse(std::slice::from_ref(&data), &dir, &config.inverse)?;
            }
            Ok(())
        })?;
        if let Some(text) = self.recommended()?.filter(|_| fm) {
            self.write_recommended(&text)?;
        }
        Ok(key)
    }

    /// The `[pipeline] recommended` settings, copied beside the FM model. Outside the train
    /// stage's key, so that editing them re-evaluates the model instead of refusing it.
    fn recommended(&self) -> Result<Option<String>> {
        let file = self.config.pipeline.recommended.as_deref();
        file.map(|f| recommended_settings(&crate::paths::resolve(f))).transpose()
    }

    /// Writes `text` as the FM model's `recommended.toml` where it differs from what is there.
    fn write_recommended(&self, text: &str) -> Result<()> {
        let file = self.model_dir("fm").join(flowmimic_control::recommended::FILE);
        if std::fs::read_to_string(&file).ok().as_deref() != Some(text) {
            flowmimic_io::write_atomic(&file, text.as_bytes())?;
        }
        Ok(())
    }

    fn evaluate(&self, model_keys: &[String]) -> Result<String> {
        let eval_dir = self.out.join("eval");
        let objectives = &self.config.pipeline.objectives;
        let models: Vec<String> = objectives.iter().map(|o| format!("{o}={}", self.model_dir(o).display())).collect();
        let (quick, humanoid) = (self.quick, &self.humanoid);
        let recommended = self.recommended()?;
        if let Some(text) = recommended.as_deref().filter(|_| objectives.iter().any(|o| o == "fm")) {
            self.write_recommended(text)?;
        }
        let mut parts = vec![model_keys.join(","), quick.to_string()];
        parts.extend(recommended);
        stage("evaluate", &eval_dir, key(&parts), || {
            // The protocols append to the report: it starts again, so that it shows this
            // evaluation only (the points already run stay in their CSV files and are reused).
            let report = eval_dir.join("report.md");
            if report.exists() {
                std::fs::remove_file(&report).with_context(|| format!("removing the old {}", report.display()))?;
            }
            let common = || Common::new(models.clone(), eval_dir.clone(), quick);
            eval::run(EvalCommand::Survival { common: common(), nfe: vec![1, 2, 5, 10, 20], seconds: None }, humanoid)?;
            eval::run(EvalCommand::Latency { common: common(), nfe: vec![1, 2, 5, 10, 20], guided: None }, humanoid)?;
            // Guidance at the first model's recommended settings when it has them (against
            // unguided), with every trial of the protocols: they say whether the model steers;
            // else over a sweep of scales.
            let tuned = self.config.pipeline.recommended.is_some() && objectives[0] == "fm";
            let fm_only = || Common::new(models[..1].to_vec(), eval_dir.clone(), quick && !tuned);
            let sweep = || match tuned {
                true => Sweep { scales: Vec::new(), nfe: None },
                false => Sweep { scales: vec![0.0, 3.0, 10.0, 30.0], nfe: Some(5) },
            };
            eval::run(EvalCommand::Joystick { common: fm_only(), sweep: sweep(), schedule: None }, humanoid)?;
            eval::run(
                EvalCommand::Reach {
                    common: fm_only(),
                    sweep: sweep(),
                    heights: eval::REACH_HEIGHTS.to_vec(),
                    standing: false,
                    approach: (!tuned).then_some(false),
                },
                humanoid,
            )?;
            Ok(())
        })
    }
}

/// The settings of a `recommended.toml` for a model of the pipeline's own: its keys, checked,
/// under a header that says where they come from (the file's comments measure its own model),
/// without its executor, which executes the plans of that model's data alone.
fn recommended_settings(model: &Path) -> Result<String> {
    use flowmimic_control::recommended::{FILE, Recommended};
    Recommended::load(model).context("pipeline.recommended")?;
    let file = model.join(FILE);
    let text =
        std::fs::read_to_string(&file).with_context(|| format!("pipeline.recommended: reading {}", file.display()))?;
    let keys: Vec<&str> =
        text.lines().filter(|l| !l.trim_start().starts_with('#') && !l.trim_start().starts_with("executor")).collect();
    Ok(format!(
        "# The settings of {} ([pipeline] recommended), measured on that model, whose recipe this\n\
         # pipeline follows; what this model does with them: the pipeline's eval/report.md.\n{}\n",
        file.display(),
        keys.join("\n").trim()
    ))
}

/// An empty dataset in `dir`, whatever was there.
fn fresh_dataset(dir: &Path) -> Result<Dataset> {
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    Ok(Dataset::open_or_create(dir)?)
}

/// Runs every stage in order, or only the stage `only` (whose inputs must be done), or with
/// `plan`, prints the stages after the clips as JSON and runs nothing.
pub fn run(
    config: &Config,
    preset: &str,
    out: &Path,
    clip_files: &[PathBuf],
    only: Option<Only>,
    plan: bool,
) -> Result<()> {
    let stages = Stages { config, humanoid: Humanoid::new(config.sim)?, out, quick: preset != "paper" };
    let started = Instant::now();
    let objectives = &config.pipeline.objectives;
    let experts_done = |experts: &[String]| -> Result<Vec<String>> {
        experts.iter().map(|e| done(&stages.expert_dir(e), &format!("expert:{e}"))).collect()
    };
    let models_done = || -> Result<Vec<String>> {
        objectives.iter().map(|o| done(&stages.model_dir(o), &format!("train:{o}"))).collect()
    };
    if plan {
        done(&stages.clips_dir(), "clips")?;
        let names = stages.clip_names()?;
        let plan = serde_json::json!({
            "experts": stages.expert_names(&names),
            "rollouts": names.iter().map(|n| [n.as_str(), stages.expert_of(n)]).collect::<Vec<_>>(),
            "models": objectives,
        });
        println!("{plan}");
        return Ok(());
    }
    match only {
        Some(Only::Clips) => stages.clips(clip_files).map(drop),
        Some(Only::Expert(name)) => stages.expert(&done(&stages.clips_dir(), "clips")?, &name).map(drop),
        Some(Only::Rollouts(name)) => stages.rollouts(&name).map(drop),
        Some(Only::Collect) => {
            let names = stages.clip_names()?;
            let experts = stages.expert_names(&names);
            stages.collect(&names, &experts, &experts_done(&experts)?).map(drop)
        }
        Some(Only::Train(objective)) if !objectives.contains(&objective) => {
            anyhow::bail!("train:{objective}: the models of this pipeline are {objectives:?} ([pipeline] objectives)")
        }
        Some(Only::Train(objective)) => stages.train(&done(&stages.data_dir(), "collect")?, &objective).map(drop),
        Some(Only::Evaluate) => stages.evaluate(&models_done()?).map(drop),
        None => {
            let clips_key = stages.clips(clip_files)?;
            let names = stages.clip_names()?;
            let experts = stages.expert_names(&names);
            let expert_keys = experts.iter().map(|e| stages.expert(&clips_key, e)).collect::<Result<Vec<_>>>()?;
            let data_key = stages.collect(&names, &experts, &expert_keys)?;
            let model_keys = objectives.iter().map(|o| stages.train(&data_key, o)).collect::<Result<Vec<_>>>()?;
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
