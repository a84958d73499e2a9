//! A model directory's recommended settings, `recommended.toml`: how the model is best driven
//! for each task, measured with the command written above each section. `flowmimic run`,
//! `play`, `demo` and `eval` take them where a flag is absent.
//!
//! ```toml
//! # flowmimic eval joystick --model fm=DIR --nfe 2 --scales 0,50 --adaptive 1.5 ...: 0.60 times unguided
//! [joystick]
//! nfe = 2
//! guidance_scale = 50.0
//! adaptive = 1.5
//! inverse_dynamics = 0.2
//! ```
//!
//! An `executor` (a tracking run that executes the plans, [`crate::Executor`]) is a path
//! relative to the model directory, as `executor = "../../experts/executor-walks"`.

use crate::{Adaptive, ControlError, StartActions};
use serde::{Deserialize, Serialize};
use std::path::{Component, Path, PathBuf};

/// The file's name in a model directory.
pub const FILE: &str = "recommended.toml";

/// How to drive a model for one task; each setting absent where the model has no measured best.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    /// Network evaluations per control step.
    pub nfe: Option<usize>,
    /// Guidance scale w.
    pub guidance_scale: Option<f32>,
    /// Adaptive guidance's reference error (m/s and rad/s); 0 for the fixed scale.
    pub adaptive: Option<f32>,
    /// Share of the executed action read by inverse dynamics out of the plan, 0-1.
    pub inverse_dynamics: Option<f32>,
    /// The most the joystick velocity asked speeds up (m/s^2); 0 for the command as given.
    pub acceleration: Option<f32>,
    /// Solver steps that apply guidance, `[start, end)`.
    pub guidance_interval: Option<[usize; 2]>,
    /// Walk up to a hand target (reach and compose).
    pub approach: Option<bool>,
    /// How much a labelled model's label weighs (classifier-free guidance): 0 untold, 1 told.
    pub label_scale: Option<f32>,
    /// The actions of the history an episode starts with.
    pub start_actions: Option<StartActions>,
    /// A tracking run that executes the plans: relative to the model directory in the file,
    /// joined to it once loaded.
    pub executor: Option<PathBuf>,
    /// The share of the executor's residual added to each plan's action, 0-1.
    pub executor_residual: Option<f32>,
}

/// A model's recommended settings, per task.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Recommended {
    /// Unguided walking (and the survival protocol).
    pub walk: Settings,
    pub joystick: Settings,
    pub reach: Settings,
    pub waypoint: Settings,
    pub compose: Settings,
    /// A person at the keys (`flowmimic play`): commands held for seconds, not the joystick
    /// protocol's 3 s segments.
    pub play: Settings,
}

/// Network evaluations and guidance scale where neither the caller nor the model says.
pub const DEFAULT_NFE: usize = 5;
pub const DEFAULT_SCALE: f32 = 10.0;

impl Settings {
    /// Each setting from `self` where given, else from `under` (a flag over the model's).
    pub fn or(&self, under: &Settings) -> Settings {
        Settings {
            nfe: self.nfe.or(under.nfe),
            guidance_scale: self.guidance_scale.or(under.guidance_scale),
            adaptive: self.adaptive.or(under.adaptive),
            inverse_dynamics: self.inverse_dynamics.or(under.inverse_dynamics),
            acceleration: self.acceleration.or(under.acceleration),
            guidance_interval: self.guidance_interval.or(under.guidance_interval),
            approach: self.approach.or(under.approach),
            label_scale: self.label_scale.or(under.label_scale),
            start_actions: self.start_actions.or(under.start_actions),
            executor: self.executor.clone().or_else(|| under.executor.clone()),
            executor_residual: self.executor_residual.or(under.executor_residual),
        }
    }

    /// Whether to walk up to a hand target (default no).
    pub fn approaches(&self) -> bool {
        self.approach.unwrap_or(false)
    }

    /// The controller's settings for `seconds`, the defaults where absent ([`DEFAULT_NFE`],
    /// [`DEFAULT_SCALE`], the fixed scale, no inverse dynamics, the command's speed as given,
    /// a label as told, the default guidance interval, a start in PD targets, no executor).
    pub fn control(
        &self,
        gradient: flowmimic_model::Gradient,
        seconds: f64,
    ) -> Result<crate::ControlConfig, ControlError> {
        self.validate().map_err(ControlError::Sampler)?;
        let reference = self.adaptive.filter(|&r| r > 0.0);
        Ok(crate::ControlConfig {
            gradient,
            guidance_steps: self.guidance_interval.map(|[a, b]| (a, b)),
            adaptive: reference.map(Adaptive::new).transpose()?,
            inverse_dynamics: self.inverse_dynamics.unwrap_or(0.0),
            acceleration: self.acceleration.unwrap_or(0.0),
            label_scale: self.label_scale.unwrap_or(1.0),
            start_actions: self.start_actions.unwrap_or_default(),
            executor: self.executor.clone(),
            executor_residual: self.executor_residual.unwrap_or(crate::executor::DEFAULT_RESIDUAL),
            ..crate::ControlConfig::new(
                self.nfe.unwrap_or(DEFAULT_NFE),
                self.guidance_scale.unwrap_or(DEFAULT_SCALE),
                seconds,
            )
        })
    }

    /// The first setting out of range, as `name = value: why`.
    fn validate(&self) -> Result<(), String> {
        let bad = |what: &str, value: String| Err(format!("{what} = {value}"));
        if let Some(n) = self.nfe.filter(|&n| n == 0) {
            return bad("nfe", format!("{n}: at least 1"));
        }
        if let Some(w) = self.guidance_scale.filter(|w| !(w.is_finite() && *w >= 0.0)) {
            return bad("guidance_scale", format!("{w}: a finite scale, 0 or more"));
        }
        if let Some(a) = self.adaptive.filter(|&a| a != 0.0 && Adaptive::new(a).is_err()) {
            return bad("adaptive", format!("{a}: a reference error above 0, or 0 for the fixed scale"));
        }
        if let Some(b) = self.inverse_dynamics.filter(|b| !(0.0..=1.0).contains(b)) {
            return bad("inverse_dynamics", format!("{b}: a share from 0 to 1"));
        }
        if let Some(a) = self.acceleration.filter(|a| !(a.is_finite() && *a >= 0.0)) {
            return bad("acceleration", format!("{a}: m/s^2, 0 or more (0 for the command as given)"));
        }
        if let Some(s) = self.label_scale.filter(|s| !(s.is_finite() && *s >= 0.0)) {
            return bad("label_scale", format!("{s}: 0 or more (0 untold, 1 told)"));
        }
        if let Some(r) = self.executor_residual.filter(|r| !(0.0..=1.0).contains(r)) {
            return bad("executor_residual", format!("{r}: a share from 0 to 1"));
        }
        if let Some([a, b]) = self.guidance_interval.filter(|[a, b]| a >= b) {
            return bad("guidance_interval", format!("[{a}, {b}]: start before end"));
        }
        Ok(())
    }
}

impl Recommended {
    /// The recommended settings of a model directory; none when it has no [`FILE`]. A file
    /// that does not parse, or holds a value out of range, is an error naming it.
    pub fn load(dir: &Path) -> Result<Self, ControlError> {
        let path = dir.join(FILE);
        if !path.exists() {
            return Ok(Self::default());
        }
        let bad = |m: String| ControlError::Start(format!("{}: {m}", path.display()));
        let text = flowmimic_io::read_to_string(&path).map_err(|e| ControlError::Start(e.to_string()))?;
        let mut r: Self = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
        for (task, s) in r.tasks_mut() {
            s.validate().map_err(|m| bad(format!("[{task}] {m}")))?;
            if let Some(executor) = &mut s.executor {
                *executor = beside(dir, executor);
                if !executor.exists() {
                    return Err(bad(format!("[{task}] executor: no tracking run at {}", executor.display())));
                }
            }
        }
        Ok(r)
    }

    /// Each task's settings, by the task's name (the file's table).
    fn tasks_mut(&mut self) -> [(&'static str, &mut Settings); 6] {
        [
            ("walk", &mut self.walk),
            ("joystick", &mut self.joystick),
            ("reach", &mut self.reach),
            ("waypoint", &mut self.waypoint),
            ("compose", &mut self.compose),
            ("play", &mut self.play),
        ]
    }

    /// The settings of the task named `task` (`walk`, `joystick`, `reach`, `waypoint`,
    /// `compose`, `play`); none for another name.
    pub fn for_task(&self, task: &str) -> Settings {
        // A copy, so that the names are read from the one table `tasks_mut` keeps.
        let mut all = self.clone();
        all.tasks_mut().into_iter().find(|(name, _)| *name == task).map(|(_, s)| std::mem::take(s)).unwrap_or_default()
    }
}

/// `relative` from the directory `dir`, its `..` taken out where they can be
/// (`pretrained/models/fm-walks` and `../../experts/x`: `pretrained/experts/x`), as a user
/// would write it.
fn beside(dir: &Path, relative: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for part in dir.join(relative).components() {
        match part {
            Component::ParentDir if matches!(out.components().next_back(), Some(Component::Normal(_))) => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}
