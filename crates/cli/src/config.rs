//! Run configuration: a preset (`tiny`, `cpu`, `paper`) with optional TOML files on top.
//!
//! A user file only needs the keys it changes; everything else comes from the preset (or the
//! files before it). Unknown keys are errors, so a typo never silently falls back to a default.

use anyhow::{Context, Result, bail};
use flowmimic_data::CollectConfig;
use flowmimic_model::{InverseConfig, ModelConfig, TrainConfig};
use flowmimic_sim::SimConfig;
use flowmimic_track::TrackConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Every stage's settings.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// The simulated humanoid (`[sim]`).
    pub sim: SimConfig,
    /// PPO tracking experts (`[track]`, `[track.reward]`).
    #[serde(default)]
    pub track: TrackConfig,
    /// Noisy expert rollouts (`[collect]`).
    #[serde(default)]
    pub collect: CollectConfig,
    /// The trajectory model's network (`[model]`).
    #[serde(default)]
    pub model: ModelConfig,
    /// Its training (`[train]`).
    #[serde(default)]
    pub train: TrainConfig,
    /// Inverse dynamics beside the FM model (`flowmimic inverse`).
    #[serde(default)]
    pub inverse: InverseConfig,
    /// What `flowmimic pipeline` makes (`[pipeline]`).
    #[serde(default)]
    pub pipeline: crate::pipeline::PipelineConfig,
}

/// The built-in presets, embedded from `configs/`.
pub const PRESETS: [(&str, &str); 3] = [
    ("tiny", include_str!("../../../configs/tiny.toml")),
    ("cpu", include_str!("../../../configs/cpu.toml")),
    ("paper", include_str!("../../../configs/paper.toml")),
];

/// Overlays `top` onto `base`, table by table.
fn merge(base: &mut toml::Table, top: toml::Table) {
    for (key, value) in top {
        match (base.get_mut(&key), value) {
            (Some(toml::Value::Table(b)), toml::Value::Table(t)) => merge(b, t),
            (_, v) => {
                base.insert(key, v);
            }
        }
    }
}

impl Config {
    /// The preset `name`, overlaid with the TOML `files` in order (a later file's keys win).
    pub fn load(preset: &str, files: &[&Path]) -> Result<Self> {
        let Some((_, text)) = PRESETS.iter().find(|(n, _)| *n == preset) else {
            bail!("unknown preset '{preset}'; choose one of tiny, cpu, paper");
        };
        let mut table: toml::Table = text.parse().with_context(|| format!("built-in preset {preset}"))?;
        let read = |table: &toml::Table, what: &str| -> Result<Config> {
            toml::Value::Table(table.clone()).try_into().with_context(|| format!("{what}: invalid settings"))
        };
        let mut config = read(&table, &format!("preset {preset}"))?;
        for path in files {
            let user = flowmimic_io::read_to_string(path)?;
            let user: toml::Table = user.parse().with_context(|| format!("{}: not valid TOML", path.display()))?;
            merge(&mut table, user);
            // Read after each file, so that an unknown key or a wrong type names the file that brings it.
            config = read(&table, &path.display().to_string())?;
        }
        let what = if files.is_empty() {
            format!("preset {preset}")
        } else {
            files.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" + ")
        };
        config.validate().map_err(|e| anyhow::anyhow!("{what}: {e}"))?;
        Ok(config)
    }

    /// Every value in range, so that no stage meets an impossible one.
    fn validate(&self) -> std::result::Result<(), String> {
        if !(1..=1000).contains(&self.sim.substeps) {
            return Err(format!("sim.substeps is {}; it must be 1-1000", self.sim.substeps));
        }
        self.track.validate().map_err(|e| e.to_string())?;
        self.collect.validate()?;
        self.model.validate()?;
        self.train.validate()?;
        self.inverse.validate()?;
        self.pipeline.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_parse_and_files_override_them() {
        for (name, _) in PRESETS {
            Config::load(name, &[]).unwrap();
        }
        let dir = std::env::temp_dir().join(format!("flowmimic-cfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("mine.toml");
        std::fs::write(&path, "[sim]\nsubsteps = 6\n").unwrap();
        assert_eq!(Config::load("cpu", &[&path]).unwrap().sim.substeps, 6);
        // Values are checked, not only keys.
        for (bad, key) in [
            ("[model]\nheads = 0\n", "model.heads"),
            ("[model]\nheads = 3\n", "multiple of model.heads"),
            ("[model]\nd_model = 1099511627776\n", "model.d_model"),
            ("[train]\nddpm_steps = 0\n", "DDPM"),
            ("[track]\nhidden = [0]\n", "hidden"),
            ("[collect]\nnoise = [[-0.1, 4]]\n", "sigma"),
            ("[inverse]\nlr = -1.0\n", "inverse.lr"),
            ("[track]\nclip = -0.2\n", "positive"),
            ("[pipeline]\nobjectives = [\"fm\", \"fm\"]\n", "pipeline.objectives"),
        ] {
            std::fs::write(&path, bad).unwrap();
            let err = format!("{:#}", Config::load("cpu", &[&path]).unwrap_err());
            assert!(err.contains("mine.toml") && err.contains(key), "{bad}: {err}");
        }
        std::fs::write(&path, "[sim]\nsubstep = 6\n").unwrap();
        let err = format!("{:#}", Config::load("cpu", &[&path]).unwrap_err());
        assert!(err.contains("mine.toml") && err.contains("substep"), "{err}");
        assert!(Config::load("huge", &[]).is_err());
        // Files layer in order; a later file's keys win, and an error names the file.
        let top = dir.join("top.toml");
        std::fs::write(&path, "[sim]\nsubsteps = 6\n[track]\nenvs = 7\n").unwrap();
        std::fs::write(&top, "[track]\nenvs = 9\n").unwrap();
        let both = Config::load("cpu", &[&path, &top]).unwrap();
        assert_eq!((both.sim.substeps, both.track.envs), (6, 9));
        std::fs::write(&top, "[track]\nenv = 9\n").unwrap();
        let err = format!("{:#}", Config::load("cpu", &[&path, &top]).unwrap_err());
        assert!(err.contains("top.toml") && !err.contains("mine.toml") && err.contains("env"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The README's commands pass `configs/*.toml` over the cpu preset: each must load.
    #[test]
    fn every_shipped_config_loads_over_the_cpu_preset() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
        let mut loaded = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                Config::load("cpu", &[&path]).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
                loaded += 1;
            }
        }
        assert!(loaded >= 4, "found {loaded} configs in {}", dir.display());
    }
}
