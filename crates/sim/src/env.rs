//! One simulated humanoid: reset, 30 Hz control steps, state, kicks and falls.

use crate::SimError;
use crate::humanoid::Humanoid;
use crate::skeleton::{NUM_BODIES, NUM_DOFS, body, hinge_names};
use crate::state::{BodyKinematics, STATE_DIM};
use flowmimic_geom::{DQuat, DVec3, quat_from_wxyz};
use mujoco_rs::mujoco_c::mjtWarning;
use mujoco_rs::prelude::*;
use std::sync::Arc;

/// Height of the head body below which the humanoid counts as fallen, metres (paper).
pub const FALL_HEAD_HEIGHT: f64 = 0.2;

/// One environment: its own `MjData` over the shared model.
pub struct Env {
    humanoid: Arc<Humanoid>,
    data: MjData<Arc<MjModel>>,
    steps: u64,
    /// Control steps since the reset in which the humanoid touched an obstacle, and whether
    /// the last one did.
    obstacle_steps: u64,
    touching: bool,
}

impl std::fmt::Debug for Env {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Env").field("time", &self.time()).field("steps", &self.steps).finish()
    }
}

impl Env {
    pub(crate) fn new(humanoid: Arc<Humanoid>) -> Self {
        let data = MjData::new(Arc::clone(humanoid.model()));
        let mut env = Self { humanoid, data, steps: 0, obstacle_steps: 0, touching: false };
        let (q, v) = (env.humanoid.standing_qpos(), vec![0.0; env.humanoid.nv()]);
        env.reset(&q, &v).expect("the nominal pose is a valid state");
        env
    }

    pub fn humanoid(&self) -> &Arc<Humanoid> {
        &self.humanoid
    }

    /// Sets the full state (`qpos`, `qvel` as MuJoCo lays them out) and zeroes time, the
    /// step counter and the controls' history. The root quaternion is normalised.
    pub fn reset(&mut self, qpos: &[f64], qvel: &[f64]) -> Result<(), SimError> {
        let (nq, nv) = (self.humanoid.nq(), self.humanoid.nv());
        if qpos.len() != nq || qvel.len() != nv {
            return Err(SimError::StateShape { qpos: qpos.len(), qvel: qvel.len(), nq, nv });
        }
        if let Some(i) = qpos.iter().position(|x| !x.is_finite()) {
            return Err(SimError::NonFiniteState { what: "qpos", index: i });
        }
        if let Some(i) = qvel.iter().position(|x| !x.is_finite()) {
            return Err(SimError::NonFiniteState { what: "qvel", index: i });
        }
        self.data.reset();
        self.data.qpos_mut().copy_from_slice(qpos);
        self.data.qvel_mut().copy_from_slice(qvel);
        if self.humanoid.has_free_root() {
            let q = quat_from_wxyz([qpos[3], qpos[4], qpos[5], qpos[6]]);
            if q.length() < 1e-9 {
                return Err(SimError::NonFiniteState { what: "qpos (zero root quaternion)", index: 3 });
            }
            let q = q.normalize();
            self.data.qpos_mut()[3..7].copy_from_slice(&[q.w, q.x, q.y, q.z]);
        }
        // Hold the current pose until the first action arrives.
        let hinges = self.hinge_angles().to_vec();
        self.data.ctrl_mut().copy_from_slice(&hinges);
        self.steps = 0;
        (self.obstacle_steps, self.touching) = (0, false);
        self.move_obstacles();
        self.refresh();
        Ok(())
    }

    /// Moves this environment into `humanoid`'s world (the same humanoid with other
    /// obstacles, [`Humanoid::with_obstacles`]), keeping its state, time, controls and counts.
    pub fn enter(&mut self, humanoid: Arc<Humanoid>) -> Result<(), SimError> {
        if (humanoid.nq(), humanoid.nv()) != (self.humanoid.nq(), self.humanoid.nv()) {
            return Err(SimError::Config("the new world's humanoid has other joints".into()));
        }
        let mut data = MjData::new(Arc::clone(humanoid.model()));
        data.qpos_mut().copy_from_slice(self.data.qpos());
        data.qvel_mut().copy_from_slice(self.data.qvel());
        data.ctrl_mut().copy_from_slice(self.data.ctrl());
        data.set_time(self.data.time());
        (self.humanoid, self.data) = (humanoid, data);
        self.move_obstacles();
        self.refresh();
        Ok(())
    }

    /// Puts each obstacle's mocap body where the obstacle is at the current time.
    fn move_obstacles(&mut self) {
        let time = self.data.time();
        let humanoid = Arc::clone(&self.humanoid);
        for (slot, o) in self.data.mocap_pos_mut().iter_mut().zip(humanoid.obstacles()) {
            let [x, y] = o.position(time);
            slot[0] = x;
            slot[1] = y;
        }
    }

    /// Whether any of the humanoid's geoms touches an obstacle's, in MuJoCo's last contacts.
    fn touches_obstacle(&self) -> bool {
        let model = self.humanoid.model();
        let is_obstacle = |g: i32| self.humanoid.is_obstacle_geom(g as usize);
        let is_humanoid = |g: i32| !is_obstacle(g) && model.geom_bodyid()[g as usize] > 0;
        self.data.contact().iter().any(|c| {
            let [a, b] = [c.geom[0], c.geom[1]];
            (is_obstacle(a) && is_humanoid(b)) || (is_obstacle(b) && is_humanoid(a))
        })
    }

    /// One 30 Hz control step with normalised action `a` (69 entries). Entries outside
    /// `[-1, 1]` are clipped; a non-finite entry is an error and nothing is simulated.
    pub fn step(&mut self, action: &[f32]) -> Result<(), SimError> {
        if action.len() != NUM_DOFS {
            return Err(SimError::ActionShape { got: action.len() });
        }
        if let Some(i) = action.iter().position(|a| !a.is_finite()) {
            return Err(SimError::NonFiniteAction { index: i, hinge: hinge_names()[i].clone(), value: action[i] });
        }
        let map = self.humanoid.actions();
        for (i, (c, &a)) in self.data.ctrl_mut().iter_mut().zip(action).enumerate() {
            *c = map.target(i, f64::from(a).clamp(-1.0, 1.0));
        }
        self.advance()
    }

    fn advance(&mut self) -> Result<(), SimError> {
        let bad_before = self.bad_physics_warnings();
        let obstacles = !self.humanoid.obstacles().is_empty();
        self.touching = false;
        for _ in 0..self.humanoid.config().substeps {
            if obstacles {
                self.move_obstacles();
            }
            self.data.step();
            self.touching |= obstacles && self.touches_obstacle();
        }
        self.steps += 1;
        self.obstacle_steps += u64::from(self.touching);
        // MuJoCo resets the data itself when the accelerations blow up; catch that and any NaN.
        if self.bad_physics_warnings() != bad_before
            || !self.data.qpos().iter().chain(self.data.qvel()).all(|x| x.is_finite())
        {
            return Err(SimError::Diverged { step: self.steps });
        }
        self.refresh();
        Ok(())
    }

    fn bad_physics_warnings(&self) -> i32 {
        let w = self.data.warning();
        [mjtWarning::mjWARN_BADQACC, mjtWarning::mjWARN_BADQPOS, mjtWarning::mjWARN_BADQVEL]
            .iter()
            .map(|&k| w[k as usize].number)
            .sum()
    }

    /// After `mj_step`, MuJoCo's derived quantities (body poses, velocities) lag the state by
    /// one physics step; recompute them so reads are exact. Cheaper than `mj_forward`.
    fn refresh(&mut self) {
        self.data.kinematics();
        self.data.com_pos();
        self.data.com_vel();
    }

    /// Adds a planar velocity change `(dvx, dvy)` (m/s, world frame) to the root.
    pub fn kick(&mut self, dv: [f64; 2]) -> Result<(), SimError> {
        if !self.humanoid.has_free_root() {
            return Err(SimError::Config("cannot kick a humanoid whose root is welded".into()));
        }
        if !dv.iter().all(|x| x.is_finite()) {
            return Err(SimError::NonFiniteState { what: "kick", index: 0 });
        }
        let qvel = self.data.qvel_mut();
        qvel[0] += dv[0];
        qvel[1] += dv[1];
        self.refresh();
        Ok(())
    }

    /// World-frame kinematics of the 24 bodies.
    pub fn bodies(&self) -> BodyKinematics {
        let (xpos, xquat, cvel) = (self.data.xpos(), self.data.xquat(), self.data.cvel());
        // cvel is the spatial velocity (angular; linear at the tree's centre of mass).
        let com = DVec3::from_array(self.data.subtree_com()[body::PELVIS + 1]);
        let mut k = BodyKinematics {
            pos: [DVec3::ZERO; NUM_BODIES],
            rot: [DQuat::IDENTITY; NUM_BODIES],
            lin_vel: [DVec3::ZERO; NUM_BODIES],
            ang_vel: [DVec3::ZERO; NUM_BODIES],
        };
        for b in 0..NUM_BODIES {
            let (p, c) = (DVec3::from_array(xpos[b + 1]), cvel[b + 1]);
            let w = DVec3::new(c[0], c[1], c[2]);
            k.pos[b] = p;
            k.rot[b] = quat_from_wxyz(xquat[b + 1]);
            k.ang_vel[b] = w;
            k.lin_vel[b] = DVec3::new(c[3], c[4], c[5]) + w.cross(p - com);
        }
        k
    }

    /// The whole humanoid's centre of mass, world frame, m.
    pub fn centre_of_mass(&self) -> DVec3 {
        DVec3::from_array(self.data.subtree_com()[body::PELVIS + 1])
    }

    /// The 165-d state in the current character frame (see [`crate::state`]).
    pub fn state(&self) -> [f32; STATE_DIM] {
        self.bodies().state()
    }

    /// Raw generalised positions (76 with a free root: position, quaternion w x y z, hinges).
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }

    /// Raw generalised velocities (75 with a free root: world linear, local angular, hinges).
    pub fn qvel(&self) -> &[f64] {
        self.data.qvel()
    }

    /// The 69 hinge angles.
    pub fn hinge_angles(&self) -> &[f64] {
        let q = self.data.qpos();
        &q[q.len() - NUM_DOFS..]
    }

    /// Actuator torques applied in the last physics step, N m.
    pub fn torques(&self) -> &[f64] {
        self.data.actuator_force()
    }

    /// Height of the lowest point of each foot (ankle and toe geoms), left then right, metres.
    /// Negative means the sole is below the ground.
    pub fn sole_heights(&self) -> [f64; 2] {
        self.foot_bottoms().map(|[heel, toe]| heel.min(toe))
    }

    /// Lowest point of the foot (ankle body) and of the toes, for each foot, metres.
    pub fn foot_bottoms(&self) -> [[f64; 2]; 2] {
        [[body::L_ANKLE, body::L_TOE], [body::R_ANKLE, body::R_TOE]]
            .map(|parts| parts.map(|b| self.geom_bottom(self.humanoid.body_geom(b))))
    }

    /// Lowest world z of a box, sphere or capsule geom.
    fn geom_bottom(&self, geom: usize) -> f64 {
        let (centre, frame) = (self.data.geom_xpos()[geom], self.data.geom_xmat()[geom]);
        let size = self.humanoid.model().geom_size()[geom];
        // Row 2 of the geom's rotation matrix holds the world z of its local axes.
        let extent = match self.humanoid.model().geom_type()[geom] {
            MjtGeomBase::mjGEOM_BOX => (0..3).map(|k| frame[6 + k].abs() * size[k]).sum::<f64>(),
            MjtGeomBase::mjGEOM_CAPSULE => size[0] + frame[8].abs() * size[1],
            _ => size[0],
        };
        centre[2] - extent
    }

    /// Pairs of the humanoid's bodies whose geoms touch or overlap in the current pose (body
    /// indices in our order, lower first), by MuJoCo's own collision detection. Pairs the model
    /// excludes (neighbours that overlap in the rest pose) are never reported.
    pub fn self_contacts(&mut self) -> Vec<(usize, usize)> {
        self.data.collision();
        let body_of = |g: i32| self.humanoid.model().geom_bodyid()[g as usize] as usize;
        let mut pairs: Vec<(usize, usize)> = self
            .data
            .contact()
            .iter()
            .map(|c| (body_of(c.geom[0]), body_of(c.geom[1])))
            // Body 0 is MuJoCo's world (the ground); ours are numbered from 1, obstacles after.
            .filter(|&(a, b)| (1..=NUM_BODIES).contains(&a) && (1..=NUM_BODIES).contains(&b))
            .map(|(a, b)| (a.min(b) - 1, a.max(b) - 1))
            .collect();
        pairs.sort_unstable();
        pairs.dedup();
        pairs
    }

    /// Whether the humanoid touched an obstacle during the last control step (MuJoCo contacts).
    pub fn touching_obstacle(&self) -> bool {
        self.touching
    }

    /// Control steps since the reset in which the humanoid touched an obstacle.
    pub fn obstacle_steps(&self) -> u64 {
        self.obstacle_steps
    }

    /// Height of the head body, metres.
    pub fn head_height(&self) -> f64 {
        self.data.xpos()[body::HEAD + 1][2]
    }

    /// The paper's failure test: head below 0.2 m.
    pub fn fallen(&self) -> bool {
        self.head_height() < FALL_HEAD_HEIGHT
    }

    /// Simulated time since the last reset, seconds.
    pub fn time(&self) -> f64 {
        self.data.time()
    }

    /// Control steps since the last reset.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// One raw MuJoCo physics step with the current controls (for benchmarks).
    pub fn physics_step(&mut self) {
        self.data.step();
    }
}
