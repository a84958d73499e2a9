//! `flowmimic._flowmimic`: the Python package's native module. Each class wraps the crate the
//! binary calls (no logic of its own beyond converting arguments), releases the GIL while it
//! simulates, samples or acts, and hands arrays over as NumPy without per-element copies.
//! `python/flowmimic/__init__.py` adds the Python-side conveniences (tasks as plain values).

use flowmimic_control::controller::{default_guidance_steps, start_frame, start_pose};
use flowmimic_control::costs::batch_guidance_grad;
use flowmimic_control::recommended::Settings;
use flowmimic_control::{ControlConfig, Controller as Driver, Layout, Recommended, Steer, Task};
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_model::{Gradient, TaskGuidance, TaskLabel, TrajectoryModel};
use flowmimic_motion::{Clip as Motion, GaitParams, ImportOptions};
use flowmimic_sim::{BODY_NAMES, Humanoid, NUM_BODIES, NUM_DOFS, Obstacle, STATE_DIM, SimConfig};
use flowmimic_track::TrackConfig;
use flowmimic_track::ppo::Policy;
use flowmimic_track::task::{Ending, Reference, Tracker, obs_dim};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use rand::{Rng, SeedableRng};
use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

/// Every error crosses into Python as a `ValueError` (bad input) or `RuntimeError` carrying the
/// crate's own message.
fn bad(e: impl std::fmt::Display) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// The simulated humanoid, compiled once per process.
fn humanoid() -> PyResult<Arc<Humanoid>> {
    static HUMANOID: OnceLock<Arc<Humanoid>> = OnceLock::new();
    if let Some(h) = HUMANOID.get() {
        return Ok(Arc::clone(h));
    }
    let h = Humanoid::new(SimConfig::default()).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(Arc::clone(HUMANOID.get_or_init(|| h)))
}

/// `values` as a NumPy array of `rows` rows of `width`, owning the vector (no copy).
fn matrix<T: numpy::Element>(
    py: Python<'_>,
    values: Vec<T>,
    rows: usize,
    width: usize,
) -> PyResult<Bound<'_, PyArray2<T>>> {
    Ok(numpy::ndarray::Array2::from_shape_vec((rows, width), values).map_err(bad)?.into_pyarray(py))
}

/// World positions of the 24 bodies of `rows` poses, `[rows, 24, 3]`, owning the vector.
fn body_array(py: Python<'_>, flat: Vec<f64>, rows: usize) -> PyResult<Bound<'_, PyArray3<f64>>> {
    Ok(numpy::ndarray::Array3::from_shape_vec((rows, NUM_BODIES, 3), flat).map_err(bad)?.into_pyarray(py))
}

/// A 2-d array's rows as one slice of its own memory (no copy), checked to have `width`
/// columns and to be C-contiguous.
fn rows<'a>(a: &'a PyReadonlyArray2<f32>, width: usize, what: &str) -> PyResult<(&'a [f32], usize)> {
    let [n, w] = [a.shape()[0], a.shape()[1]];
    if w != width {
        return Err(bad(format!("{what} has {w} columns; {width} are needed")));
    }
    let flat = a.as_slice().map_err(|_| bad(format!("{what} is not C-contiguous (numpy.ascontiguousarray)")))?;
    Ok((flat, n))
}

/// A trajectory model directory (`flowmimic train` writes one; `pretrained/models/fm` is the
/// shipped guidance model).
#[pyclass(frozen, module = "flowmimic._flowmimic")]
struct Model {
    inner: Arc<TrajectoryModel>,
    dir: PathBuf,
}

#[pymethods]
impl Model {
    #[new]
    fn new(path: PathBuf) -> PyResult<Self> {
        let inner = flowmimic_control::load_model(&path).map_err(|e| bad(format!("{}: {e}", path.display())))?;
        Ok(Self { inner: Arc::new(inner), dir: path })
    }

    /// The training objective: `fm`, `ddpm` or `meanflow`.
    #[getter]
    fn objective(&self) -> &'static str {
        self.inner.objective.name()
    }

    /// Predicted steps H.
    #[getter]
    fn horizon(&self) -> usize {
        self.inner.layout().spec.horizon
    }

    /// Past states N in the conditioning.
    #[getter]
    fn history(&self) -> usize {
        self.inner.layout().spec.history
    }

    /// Length of one conditioning row: the history's states and actions interleaved
    /// (docs/conventions.md, the trajectory layout), then one entry per task label.
    #[getter]
    fn cond_len(&self) -> usize {
        self.inner.layout().cond_len()
    }

    /// The label entries that end a conditioning row, in order: for a model told each
    /// window's task, the tasks (a one-hot); for one told each window's motion, `given`, then
    /// `forward`, `left` (m/s) and `yaw_rate` (rad/s); all zeros says none. Empty for a model
    /// without labels.
    #[getter]
    fn task_labels(&self) -> Vec<String> {
        let config = &self.inner.config;
        if config.command_labels {
            return ["given", "forward", "left", "yaw_rate"].map(String::from).to_vec();
        }
        let name = |l: &TaskLabel| serde_json::to_value(l).ok().and_then(|v| v.as_str().map(String::from));
        let labels = if config.task_labels { &TaskLabel::ALL[..] } else { &[] };
        labels.iter().filter_map(name).collect()
    }

    /// Length of one sampled future: actions and states, H steps.
    #[getter]
    fn future_len(&self) -> usize {
        self.inner.layout().future_len()
    }

    /// Whether the model directory has inverse dynamics (`flowmimic inverse`).
    #[getter]
    fn has_inverse_dynamics(&self) -> bool {
        self.inner.inverse.is_some()
    }

    /// Normalisation mean and standard deviation of a whole window (conditioning, then future).
    #[getter]
    fn normalisation<'py>(&self, py: Python<'py>) -> (Bound<'py, PyArray1<f32>>, Bound<'py, PyArray1<f32>>) {
        (self.inner.norm.mean.clone().into_pyarray(py), self.inner.norm.std.clone().into_pyarray(py))
    }

    /// The model's recommended settings for `task` (`walk`, `joystick`, `reach`, `waypoint`,
    /// `compose`, `play`) as JSON, from its `recommended.toml`.
    fn recommended_json(&self, task: &str) -> PyResult<String> {
        let settings = Recommended::load(&self.dir).map_err(bad)?.for_task(task);
        serde_json::to_string(&settings).map_err(bad)
    }

    /// Futures (n x future_len, physical units) for conditionings `cond` (n x cond_len). With
    /// `task_json` and a `guidance` scale, each row is steered by the task, read in the current
    /// character frame (the walker at the origin facing +x).
    #[pyo3(signature = (cond, nfe = 5, guidance = 0.0, task_json = None, seed = 0))]
    fn sample<'py>(
        &self,
        py: Python<'py>,
        cond: PyReadonlyArray2<'py, f32>,
        nfe: usize,
        guidance: f32,
        task_json: Option<&str>,
        seed: u64,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        if nfe == 0 {
            return Err(bad("nfe must be at least 1"));
        }
        let (cond, n) = rows(&cond, self.cond_len(), "cond")?;
        let layout = Layout { horizon: self.horizon() };
        let task: Option<Task> = match task_json {
            Some(json) => {
                let task: Task = serde_json::from_str(json).map_err(|e| bad(format!("task: {e}")))?;
                task.validate().map_err(bad)?;
                Some(task)
            }
            None => None,
        };
        let model = Arc::clone(&self.inner);
        let futures = py
            .detach(move || -> Result<Vec<f32>, flowmimic_control::ControlError> {
                // One cost per row (the same task), in the frame of the walker at the origin.
                let here = CharFrame::new(DVec3::ZERO, 0.0);
                let cost = |_| task.as_ref().map_or(Ok(None), |t| t.cost(layout, 0.0, &here, Steer::default()));
                let costs = (0..n).map(cost).collect::<Result<Vec<_>, _>>()?;
                let std = &model.norm.std[model.layout().cond_len()..];
                let grad = |x: &[f32], k: usize| batch_guidance_grad(&costs, std, x, k);
                let (g0, g1) = default_guidance_steps(nfe);
                let steer =
                    TaskGuidance { weight: guidance, grad: &grad, steps: g0..g1, gradient: Gradient::default() };
                let guided = (guidance > 0.0 && costs.iter().any(Option::is_some)).then_some(&steer);
                Ok(model.sample(cond, n, nfe, guided, &mut rand::rngs::StdRng::seed_from_u64(seed)))
            })
            .map_err(bad)?;
        let width = self.future_len();
        matrix(py, futures, n, width)
    }

    fn __repr__(&self) -> String {
        format!("Model('{}', {}, H {}, N {})", self.dir.display(), self.objective(), self.horizon(), self.history())
    }
}

self_cell::self_cell!(
    /// The controller borrows its model; this cell keeps both together.
    struct Cell {
        owner: Arc<TrajectoryModel>,
        #[covariant]
        dependent: Driver,
    }
);

/// The guided controller driving `envs` simulated humanoids (MuJoCo), as `flowmimic run` does.
#[pyclass(unsendable, subclass, module = "flowmimic._flowmimic")]
struct Controller {
    cell: Cell,
    clip: Motion,
    /// Obstacles placed in each environment's world.
    placed: Vec<Vec<Obstacle>>,
    time: f64,
    settings: Settings,
}

#[pymethods]
impl Controller {
    /// `settings_json`: settings over the model's recommended ones for `task` (JSON of
    /// `nfe`, `guidance_scale`, `adaptive`, `inverse_dynamics`, `acceleration`, `label_scale`,
    /// `guidance_interval`, `approach`, `start_actions`, `executor`, `executor_residual`).
    #[new]
    #[pyo3(signature = (model, envs = 1, task = "walk", settings_json = None, clip = None, seed = 0))]
    fn new(
        model: &Model,
        envs: usize,
        task: &str,
        settings_json: Option<&str>,
        clip: Option<&Clip>,
        seed: u64,
    ) -> PyResult<Self> {
        if !(1..=4096).contains(&envs) {
            return Err(bad(format!("{envs} environments: 1 to 4096")));
        }
        let given: Settings = match settings_json {
            Some(json) => serde_json::from_str(json).map_err(|e| bad(format!("settings: {e}")))?,
            None => Settings::default(),
        };
        let settings = given.or(&Recommended::load(&model.dir).map_err(bad)?.for_task(task));
        let config = ControlConfig { seed, ..settings.control(Gradient::default(), 0.0).map_err(bad)? };
        let h = humanoid()?;
        let clip = match clip {
            Some(c) => c.inner.clone(),
            None => flowmimic_motion::straight_walk(&h).map_err(bad)?,
        };
        let cell =
            Cell::try_new(Arc::clone(&model.inner), |m| Driver::new(m, &h, &clip, envs, &config)).map_err(bad)?;
        Ok(Self { cell, clip, placed: vec![Vec::new(); envs], time: 0.0, settings })
    }

    /// Environments.
    #[getter]
    fn envs(&self) -> usize {
        self.placed.len()
    }

    /// Seconds since the last reset.
    #[getter]
    fn time(&self) -> f64 {
        self.time
    }

    /// The settings in force (JSON): the ones given over the model's recommended ones; absent
    /// ones take the defaults (NFE 5, w 10, the rest off).
    #[getter]
    fn settings_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.settings).map_err(bad)
    }

    /// Puts every environment back at its start frame of the clip, standing.
    fn reset(&mut self) -> PyResult<()> {
        let (clip, envs, history) = (&self.clip, self.envs(), self.cell.borrow_owner().layout().spec.history);
        self.cell
            .with_dependent_mut(|_, c| {
                (0..envs).try_for_each(|e| c.restart(e, clip, start_frame(clip.len(), history, e)))
            })
            .map_err(bad)?;
        self.time = 0.0;
        Ok(())
    }

    /// Where environment `e` starts, `(x, y, heading)` in the world: tasks are given in the
    /// world, and the environments start 7 clip frames apart.
    fn start_pose(&self, e: usize) -> PyResult<(f64, f64, f64)> {
        if e >= self.envs() {
            return Err(bad(format!("environment {e} of {}", self.envs())));
        }
        let f = start_pose(&self.clip, self.cell.borrow_owner().layout().spec.history, e);
        Ok((f.origin.x, f.origin.y, f.yaw))
    }

    /// One control step (1/30 s) with each environment's task (JSON, one per environment):
    /// `(states [E, 165], actions [E, 69], fell [E], alive [E], touching [E])`; a fallen
    /// environment's action row is NaN.
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        tasks_json: Vec<String>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray1<bool>>,
        Bound<'py, PyArray1<bool>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        let envs = self.envs();
        if tasks_json.len() != envs {
            return Err(bad(format!("{} tasks for {envs} environments", tasks_json.len())));
        }
        let tasks = tasks_json
            .iter()
            .enumerate()
            .map(|(e, json)| {
                let task: Task = serde_json::from_str(json).map_err(|err| bad(format!("task {e}: {err}")))?;
                task.validate().map_err(|err| bad(format!("task {e}: {err}")))?;
                Ok(task)
            })
            .collect::<PyResult<Vec<Task>>>()?;
        for (e, task) in tasks.iter().enumerate() {
            if task.obstacles != self.placed[e] {
                self.cell.with_dependent_mut(|_, c| c.place_obstacles(e, &task.obstacles)).map_err(bad)?;
                self.placed[e] = task.obstacles.clone();
            }
        }
        let time = self.time;
        let outcome = {
            let cell = &mut self.cell;
            py.detach(|| cell.with_dependent_mut(|_, c| c.step(&tasks, time)))
        }
        .map_err(bad)?;
        self.time += 1.0 / flowmimic_sim::CONTROL_HZ;
        let (mut states, mut actions) = (Vec::with_capacity(envs * STATE_DIM), Vec::with_capacity(envs * NUM_DOFS));
        let (mut alive, mut touching) = (Vec::with_capacity(envs), Vec::with_capacity(envs));
        self.cell.with_dependent(|_, c| {
            for e in 0..envs {
                states.extend_from_slice(&c.env(e).state());
                match &outcome.actions[e] {
                    Some(a) => actions.extend_from_slice(a),
                    None => actions.extend(std::iter::repeat_n(f32::NAN, NUM_DOFS)),
                }
                alive.push(c.is_alive(e));
                touching.push(c.env(e).touching_obstacle());
            }
        });
        let fell: Vec<bool> = (0..envs).map(|e| outcome.fell.contains(&e)).collect();
        Ok((
            matrix(py, states, envs, STATE_DIM)?,
            matrix(py, actions, envs, NUM_DOFS)?,
            fell.into_pyarray(py),
            alive.into_pyarray(py),
            touching.into_pyarray(py),
        ))
    }

    /// World positions of the 24 bodies of every environment, `[E, 24, 3]`.
    fn body_positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<f64>>> {
        let envs = self.envs();
        let flat: Vec<f64> = self.cell.with_dependent(|_, c| {
            (0..envs).flat_map(|e| c.env(e).bodies().pos.into_iter().flat_map(|p| p.to_array())).collect()
        });
        body_array(py, flat, envs)
    }

    /// What each environment's current plan asks, `[E, 3]`: its mean velocity over the horizon
    /// in its own heading (forward, left; m/s) and its turn rate (rad/s), the numbers to set
    /// beside the body's; NaN before the first step and after a fall.
    fn planned<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let envs = self.envs();
        let flat: Vec<f32> = self.cell.with_dependent(|_, c| {
            (0..envs).flat_map(|e| c.intent(e).filter(|_| c.is_alive(e)).unwrap_or([f32::NAN; 3])).collect()
        });
        matrix(py, flat, envs, 3)
    }
}

/// A motion clip retargeted to the humanoid (`flowmimic-clip/1` safetensors).
#[pyclass(frozen, module = "flowmimic._flowmimic")]
struct Clip {
    inner: Motion,
}

#[pymethods]
impl Clip {
    /// A `.clip.safetensors` file.
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        Ok(Self { inner: Motion::load(&humanoid()?, &path).map_err(bad)? })
    }

    /// A BVH (any human skeleton) or DeepMimic file, retargeted (as `flowmimic motion import`).
    #[staticmethod]
    #[pyo3(signature = (path, name = None))]
    fn import_motion(py: Python<'_>, path: PathBuf, name: Option<String>) -> PyResult<Self> {
        let h = humanoid()?;
        let options = ImportOptions { name, ..Default::default() };
        let imported = py.detach(|| flowmimic_motion::import(&h, &path, &options)).map_err(bad)?;
        Ok(Self { inner: imported.clip })
    }

    /// A procedural walk (as `flowmimic motion generate`); `gait_json` holds any of the gait's
    /// keys (`speed`, `lateral`, `turn_rate`, `heading`, `step_frequency`, `step_height`,
    /// `arm_swing`, `duration`), the rest at their defaults.
    #[staticmethod]
    #[pyo3(signature = (name = "walk", gait_json = "{}"))]
    fn generate(py: Python<'_>, name: &str, gait_json: &str) -> PyResult<Self> {
        let gait: GaitParams = serde_json::from_str(gait_json).map_err(|e| bad(format!("gait: {e}")))?;
        let h = humanoid()?;
        let (clip, _) = py.detach(|| flowmimic_motion::generate(&h, name, &gait)).map_err(bad)?;
        Ok(Self { inner: clip })
    }

    /// Writes the clip (atomically).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        self.inner.save(&path).map_err(bad)
    }

    #[getter]
    fn name(&self) -> &str {
        &self.inner.name
    }

    /// Frames (30 per second).
    fn __len__(&self) -> usize {
        self.inner.len()
    }

    /// MuJoCo positions per frame, `[T, 76]`: root xyz, quaternion wxyz, 69 hinge angles.
    #[getter]
    fn qpos<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let flat: Vec<f64> = self.inner.qpos.iter().flatten().copied().collect();
        let width = self.inner.qpos.first().map_or(0, Vec::len);
        matrix(py, flat, self.inner.len(), width)
    }

    /// World positions of the 24 bodies per frame, `[T, 24, 3]`.
    #[getter]
    fn body_positions<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray3<f64>>> {
        let flat: Vec<f64> =
            self.inner.bodies.iter().flat_map(|b| b.pos.into_iter().flat_map(|p| p.to_array())).collect();
        body_array(py, flat, self.inner.len())
    }

    /// The model's 165-d state per frame, `[T, 165]`.
    #[getter]
    fn states<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let flat: Vec<f32> = self.inner.bodies.iter().flat_map(|b| b.state()).collect();
        matrix(py, flat, self.inner.len(), STATE_DIM)
    }

    fn __repr__(&self) -> String {
        format!("Clip('{}', {} frames)", self.inner.name, self.inner.len())
    }
}

/// The tracking task that `flowmimic track train` learns, over `envs` humanoids stepped in
/// Rust threads: observations, rewards, terminations (a failed tracking, as BeyondMimic's
/// tests) and truncations (the clip's end). `flowmimic.gym` wraps it for Gymnasium.
#[pyclass(unsendable, module = "flowmimic._flowmimic")]
struct Tracking {
    reference: Reference,
    trackers: Vec<Tracker>,
    rngs: Vec<rand::rngs::StdRng>,
    cfg: TrackConfig,
    random_start: bool,
}

#[pymethods]
impl Tracking {
    /// `kicks`: a random push of up to 0.5 m/s every second (the kick protocol); `random_start`:
    /// episodes start at a random frame (reference state initialisation) instead of the first;
    /// `observe_ahead`: observations hold the reference 1/3 s and 1 s ahead too, as for an
    /// expert trained with `track.observe_ahead`.
    #[new]
    #[pyo3(signature = (clip, envs = 1, kicks = false, random_start = false, seed = 0, observe_ahead = false))]
    fn new(
        clip: &Clip,
        envs: usize,
        kicks: bool,
        random_start: bool,
        seed: u64,
        observe_ahead: bool,
    ) -> PyResult<Self> {
        if !(1..=4096).contains(&envs) {
            return Err(bad(format!("{envs} environments: 1 to 4096")));
        }
        if clip.inner.len() < 3 {
            return Err(bad(format!(
                "clip '{}' has {} frames; tracking needs 3 or more",
                clip.inner.name,
                clip.inner.len()
            )));
        }
        let h = humanoid()?;
        let cfg = TrackConfig {
            push_max: if kicks { 0.5 } else { 0.0 },
            push_interval: [1.0, 1.0],
            observe_ahead,
            ..TrackConfig::default()
        };
        Ok(Self {
            reference: Reference::new(clip.inner.clone()),
            trackers: (0..envs).map(|_| Tracker::new(&h)).collect(),
            rngs: (0..envs).map(|e| rand::rngs::StdRng::seed_from_u64(seed.wrapping_add(e as u64))).collect(),
            cfg,
            random_start,
        })
    }

    #[getter]
    fn envs(&self) -> usize {
        self.trackers.len()
    }

    /// Length of one observation.
    #[getter]
    fn obs_dim(&self) -> usize {
        obs_dim(self.cfg.observe_ahead)
    }

    /// Frames of the reference clip.
    #[getter]
    fn clip_len(&self) -> usize {
        self.reference.len()
    }

    /// The reference frame each environment is at.
    #[getter]
    fn frames<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<usize>> {
        self.trackers.iter().map(|t| t.frame).collect::<Vec<_>>().into_pyarray(py)
    }

    /// Starts environment `e` anew (its random stream reseeded when `seed` is given); returns
    /// its observation.
    #[pyo3(signature = (e, seed = None))]
    fn reset_env<'py>(&mut self, py: Python<'py>, e: usize, seed: Option<u64>) -> PyResult<Bound<'py, PyArray1<f32>>> {
        if e >= self.envs() {
            return Err(bad(format!("environment {e} of {}", self.envs())));
        }
        if let Some(s) = seed {
            self.rngs[e] = rand::rngs::StdRng::seed_from_u64(s);
        }
        let rng = &mut self.rngs[e];
        let frame = if self.random_start { rng.random_range(0..self.reference.len() - 2) } else { 0 };
        self.trackers[e].reset(&self.reference, frame, &self.cfg, rng).map_err(bad)?;
        let mut obs = vec![0.0; self.obs_dim()];
        self.trackers[e].observe(&self.reference, &mut obs);
        Ok(obs.into_pyarray(py))
    }

    /// One control step of every environment with policy outputs `actions` `[E, 69]` (residuals
    /// on the reference's next pose, scaled by the task's action scale):
    /// `(observations [E, obs_dim], rewards [E], terminated [E], truncated [E])`. An ended
    /// environment stays ended until `reset_env`.
    #[allow(clippy::type_complexity)]
    fn step<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<(
        Bound<'py, PyArray2<f32>>,
        Bound<'py, PyArray1<f32>>,
        Bound<'py, PyArray1<bool>>,
        Bound<'py, PyArray1<bool>>,
    )> {
        use rayon::prelude::*;
        let envs = self.envs();
        let (u, n) = rows(&actions, NUM_DOFS, "actions")?;
        if n != envs {
            return Err(bad(format!("{n} action rows for {envs} environments")));
        }
        let width = self.obs_dim();
        let (reference, cfg) = (&self.reference, &self.cfg);
        let ended: Vec<(f32, Ending, Vec<f32>)> = py.detach(|| {
            self.trackers
                .par_iter_mut()
                .zip(self.rngs.par_iter_mut())
                .zip(u.par_chunks(NUM_DOFS))
                .map(|((t, rng), u)| {
                    let (terms, ending) = t.step(reference, u, cfg, rng);
                    let mut obs = vec![0.0; width];
                    t.observe(reference, &mut obs);
                    (terms.total(&cfg.reward), ending, obs)
                })
                .collect()
        });
        let mut obs = Vec::with_capacity(envs * width);
        let (mut reward, mut terminated, mut truncated) = (Vec::new(), Vec::new(), Vec::new());
        for (r, ending, o) in ended {
            obs.extend(o);
            reward.push(r);
            terminated.push(matches!(ending, Ending::Failed | Ending::Diverged));
            truncated.push(ending == Ending::ClipEnd);
        }
        Ok((
            matrix(py, obs, envs, width)?,
            reward.into_pyarray(py),
            terminated.into_pyarray(py),
            truncated.into_pyarray(py),
        ))
    }
}

/// A PPO tracking expert (`flowmimic track train` writes its run directory).
#[pyclass(frozen, module = "flowmimic._flowmimic")]
struct Expert {
    policy: Policy,
}

#[pymethods]
impl Expert {
    #[new]
    fn new(run: PathBuf) -> PyResult<Self> {
        let file = if run.is_dir() { run.join("policy.safetensors") } else { run.clone() };
        let checkpoint = flowmimic_track::train::Checkpoint::read(&file).map_err(bad)?;
        Ok(Self { policy: checkpoint.policy().map_err(bad)? })
    }

    /// Length of one observation (proprioception and the reference ahead).
    #[getter]
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }

    /// Deterministic normalised actions `[n, 69]` for raw observations `[n, obs_dim]`.
    fn act<'py>(
        &self,
        py: Python<'py>,
        observations: PyReadonlyArray2<'py, f32>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (obs, n) = rows(&observations, self.policy.obs_dim(), "observations")?;
        let actions = py.detach(|| self.policy.act(obs, n));
        matrix(py, actions, n, NUM_DOFS)
    }
}

#[pymodule]
fn _flowmimic(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<Model>()?;
    m.add_class::<Controller>()?;
    m.add_class::<Clip>()?;
    m.add_class::<Expert>()?;
    m.add_class::<Tracking>()?;
    m.add("STATE_DIM", STATE_DIM)?;
    m.add("NUM_DOFS", NUM_DOFS)?;
    m.add("BODY_NAMES", BODY_NAMES.to_vec())?;
    m.add("CONTROL_HZ", flowmimic_sim::CONTROL_HZ)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
