//! The compiled humanoid: MuJoCo model, action mapping and body ids, shared by every env.

use crate::mjcf::{MjcfOptions, Root, humanoid_xml};
use crate::obstacle::Obstacle;
use crate::skeleton::{BODY_NAMES, NUM_BODIES, NUM_DOFS, bodies, body};
use crate::{Env, SimError};
use mujoco_rs::prelude::*;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Control rate of every stage, Hz (docs/conventions.md, section 2).
pub const CONTROL_HZ: f64 = 30.0;

/// Physics settings. The control rate is fixed at 30 Hz; physics runs `substeps` times faster.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimConfig {
    /// Physics steps per 30 Hz control step: 4 gives 120 Hz physics (the default and the least
    /// the conventions allow, docs/conventions.md, section 2), 8 gives 240 Hz at half the speed.
    pub substeps: usize,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self { substeps: 4 }
    }
}

impl SimConfig {
    /// Physics time step, seconds.
    pub fn timestep(&self) -> f64 {
        1.0 / (CONTROL_HZ * self.substeps as f64)
    }
}

/// Maps normalised actions `a` in `[-1, 1]^69` to PD targets `q_des = q_bar + alpha * a`.
///
/// `q_bar` is the nominal standing pose (arms lowered 75 degrees from the T-pose, elbows bent
/// 15 degrees, everything else zero). `alpha_j = max(hi_j - q_bar_j, q_bar_j - lo_j)`: the
/// smallest scale whose range `[-1, 1]` reaches both joint limits, so any pose inside the
/// limits is an action and the nominal pose is `a = 0`.
#[derive(Clone, Debug, PartialEq)]
pub struct ActionMap {
    pub q_bar: [f64; NUM_DOFS],
    pub alpha: [f64; NUM_DOFS],
    pub lower: [f64; NUM_DOFS],
    pub upper: [f64; NUM_DOFS],
}

impl ActionMap {
    fn from_skeleton() -> Self {
        let specs = bodies();
        let mut map =
            Self { q_bar: [0.0; NUM_DOFS], alpha: [0.0; NUM_DOFS], lower: [0.0; NUM_DOFS], upper: [0.0; NUM_DOFS] };
        for (j, spec) in specs[1..].iter().enumerate() {
            for k in 0..3 {
                let i = 3 * j + k;
                let [lo, hi] = spec.range[k];
                map.q_bar[i] = spec.nominal[k];
                map.lower[i] = lo;
                map.upper[i] = hi;
                map.alpha[i] = (hi - spec.nominal[k]).max(spec.nominal[k] - lo);
            }
        }
        map
    }

    /// PD target of hinge `i` for the (already clipped) normalised action `a`.
    pub fn target(&self, i: usize, a: f64) -> f64 {
        self.q_bar[i] + self.alpha[i] * a
    }

    /// The normalised action whose targets are the hinge angles `q` (clipped to `[-1, 1]`).
    pub fn action_for(&self, q: &[f64]) -> Vec<f32> {
        q.iter().enumerate().map(|(i, &q)| ((q - self.q_bar[i]) / self.alpha[i]).clamp(-1.0, 1.0) as f32).collect()
    }
}

/// The compiled humanoid model, shared (read-only) by all environments.
pub struct Humanoid {
    pub(crate) model: Arc<MjModel>,
    xml: String,
    config: SimConfig,
    options: MjcfOptions,
    actions: ActionMap,
}

impl std::fmt::Debug for Humanoid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Humanoid")
            .field("config", &self.config)
            .field("root", &self.options.root)
            .field("obstacles", &self.options.obstacles.len())
            .finish()
    }
}

fn compile(xml: &str) -> Result<MjModel, SimError> {
    MjModel::from_xml_string(xml).map_err(|e| SimError::Model(e.to_string()))
}

/// Body pairs whose geoms touch in `qpos` (the floor excluded).
fn touching_pairs(model: &MjModel, qpos: &[f64]) -> Vec<(usize, usize)> {
    let mut data = MjData::new(model);
    data.qpos_mut().copy_from_slice(qpos);
    data.forward();
    let geom_body = model.geom_bodyid();
    let mut pairs: Vec<(usize, usize)> = data
        .contact()
        .iter()
        .filter_map(|c| {
            let (a, b) = (geom_body[c.geom[0] as usize], geom_body[c.geom[1] as usize]);
            // MuJoCo body 0 is the world (floor); ours are shifted by one.
            (a > 0 && b > 0).then(|| ((a.min(b) - 1) as usize, (a.max(b) - 1) as usize))
        })
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

impl Humanoid {
    /// The free-floating humanoid (the walking character).
    pub fn new(config: SimConfig) -> Result<Arc<Self>, SimError> {
        Self::build(config, Root::Free)
    }

    /// The humanoid with its pelvis welded at `height` metres: for testing the PD controller.
    pub fn with_fixed_root(config: SimConfig, height: f64) -> Result<Arc<Self>, SimError> {
        Self::build(config, Root::Fixed { height })
    }

    fn build(config: SimConfig, root: Root) -> Result<Arc<Self>, SimError> {
        if config.substeps == 0 {
            return Err(SimError::Config("sim.substeps must be at least 1".into()));
        }
        let mut options = MjcfOptions { root, timestep: config.timestep(), exclude: Vec::new(), obstacles: Vec::new() };
        let actions = ActionMap::from_skeleton();
        // Self-collision is on, except for body pairs whose capsules already overlap in the
        // T-pose or the nominal pose (e.g. chest and upper arm): those would fight forever.
        let probe = compile(&humanoid_xml(&options))?;
        let mut exclude = Vec::new();
        for hinges in [vec![0.0; NUM_DOFS], actions.q_bar.to_vec()] {
            let qpos = pose_qpos(root, [0.0, 0.0, 2.0], &hinges);
            exclude.extend(touching_pairs(&probe, &qpos));
        }
        exclude.sort_unstable();
        exclude.dedup();
        options.exclude = exclude;
        Self::compiled(config, options, actions)
    }

    fn compiled(config: SimConfig, options: MjcfOptions, actions: ActionMap) -> Result<Arc<Self>, SimError> {
        let xml = humanoid_xml(&options);
        let model = compile(&xml)?;
        Ok(Arc::new(Self { model: Arc::new(model), xml, config, options, actions }))
    }

    /// The same humanoid in a world with `obstacles` (they replace any it had). Each call
    /// compiles a model of its own: environments with different obstacles do not share one.
    pub fn with_obstacles(&self, obstacles: &[Obstacle]) -> Result<Arc<Self>, SimError> {
        if let Some(e) = obstacles.iter().find_map(|o| o.validate().err()) {
            return Err(SimError::Config(e));
        }
        let options = MjcfOptions { obstacles: obstacles.to_vec(), ..self.options.clone() };
        Self::compiled(self.config, options, self.actions.clone())
    }

    /// The obstacles of its world, where they stand at time 0.
    pub fn obstacles(&self) -> &[Obstacle] {
        &self.options.obstacles
    }

    /// Whether MuJoCo geom `g` is an obstacle's (they come after the humanoid's).
    pub(crate) fn is_obstacle_geom(&self, g: usize) -> bool {
        g >= self.model.ffi().ngeom as usize - self.options.obstacles.len()
    }

    /// A new environment (one `MjData`) in the nominal standing pose.
    pub fn env(self: &Arc<Self>) -> Env {
        Env::new(Arc::clone(self))
    }

    /// The MJCF that MuJoCo compiled.
    pub fn xml(&self) -> &str {
        &self.xml
    }

    pub fn config(&self) -> SimConfig {
        self.config
    }

    /// The action normalisation `q_des = q_bar + alpha * a`.
    pub fn actions(&self) -> &ActionMap {
        &self.actions
    }

    /// Whether the pelvis is free (`true`) or welded.
    pub fn has_free_root(&self) -> bool {
        self.options.root == Root::Free
    }

    /// Length of `qpos` (76 with a free root).
    pub fn nq(&self) -> usize {
        self.model.ffi().nq as usize
    }

    /// Length of `qvel` (75 with a free root).
    pub fn nv(&self) -> usize {
        self.model.ffi().nv as usize
    }

    /// Total mass, kg.
    pub fn mass(&self) -> f64 {
        self.body_masses().iter().sum()
    }

    /// Mass of each body, kg, in skeleton order.
    pub fn body_masses(&self) -> [f64; NUM_BODIES] {
        std::array::from_fn(|b| self.model.body_mass()[b + 1])
    }

    /// MuJoCo's body names in its own order (world first): for checking the body order.
    pub fn mujoco_body_names(&self) -> Vec<String> {
        (0..self.model.ffi().nbody as usize)
            .map(|i| self.model.id_to_name(MjtObjBase::mjOBJ_BODY, i).unwrap_or_default().to_string())
            .collect()
    }

    /// `qpos` of a pose: root position, root quaternion `(w, x, y, z)` and 69 hinge angles.
    /// With a welded root only the hinges are used.
    pub fn qpos(&self, root_pos: [f64; 3], root_quat: [f64; 4], hinges: &[f64]) -> Vec<f64> {
        let mut q = pose_qpos(self.options.root, root_pos, hinges);
        if self.options.root == Root::Free {
            q[3..7].copy_from_slice(&root_quat);
        }
        q
    }

    /// The nominal standing pose at the origin, feet on the ground, facing +x.
    pub fn standing_qpos(&self) -> Vec<f64> {
        self.qpos([0.0, 0.0, STANDING_PELVIS_HEIGHT], [1.0, 0.0, 0.0, 0.0], &self.actions.q_bar)
    }

    /// The standing height (top of the head, metres) in the T-pose.
    pub fn height(&self) -> f64 {
        let mut data = MjData::new(&*self.model);
        let q = self.qpos([0.0, 0.0, STANDING_PELVIS_HEIGHT], [1.0, 0.0, 0.0, 0.0], &[0.0; NUM_DOFS]);
        data.qpos_mut().copy_from_slice(&q);
        data.forward();
        (0..self.model.ffi().ngeom as usize)
            .filter(|&g| self.model.geom_bodyid()[g] as usize == body::HEAD + 1)
            .map(|g| data.geom_xpos()[g][2] + self.model.geom_size()[g][0])
            .fold(f64::MIN, f64::max)
    }

    /// The geom of body `b` (each body has exactly one).
    pub(crate) fn body_geom(&self, b: usize) -> usize {
        self.model.body_geomadr()[b + 1] as usize
    }

    pub(crate) fn model(&self) -> &Arc<MjModel> {
        &self.model
    }
}

/// Pelvis height in the standing T-pose with the soles on the ground, metres.
pub const STANDING_PELVIS_HEIGHT: f64 = 0.93;

fn pose_qpos(root: Root, root_pos: [f64; 3], hinges: &[f64]) -> Vec<f64> {
    match root {
        Root::Free => {
            let mut q = vec![root_pos[0], root_pos[1], root_pos[2], 1.0, 0.0, 0.0, 0.0];
            q.extend_from_slice(hinges);
            q
        }
        Root::Fixed { .. } => hinges.to_vec(),
    }
}

/// The body names in MuJoCo order must be ours (the obstacles' after them): every array is
/// indexed by this order.
pub fn check_body_order(humanoid: &Humanoid) -> Result<(), SimError> {
    let names = humanoid.mujoco_body_names();
    let ours: Vec<&str> = BODY_NAMES.to_vec();
    if names.len() != NUM_BODIES + 1 + humanoid.obstacles().len()
        || names[1..=NUM_BODIES].iter().map(String::as_str).ne(ours.iter().copied())
    {
        return Err(SimError::Model(format!("body order {names:?} differs from {ours:?}")));
    }
    Ok(())
}
