//! The tracking task: one humanoid following a reference clip, with the rewards,
//! terminations, reference-state initialisation and pushes of BeyondMimic.
//!
//! The policy's action `u` is a residual in radians around the reference's next pose:
//! `q_des = q_ref(t+1) + action_scale * u`, handed to the environment as its normalised
//! action `a = (q_des - q_bar) / alpha` (clipped to [-1, 1]); `a` is the expert's action.

use crate::TrackConfig;
use flowmimic_geom::{CharFrame, DQuat, DVec3, rotvec};
use flowmimic_motion::Clip;
use flowmimic_sim::skeleton::{NUM_BODIES, body};
use flowmimic_sim::{BodyKinematics, Env, Humanoid, NUM_DOFS, SimError};
use rand::Rng;
use std::sync::Arc;

/// Observation width: proprioception (148) and the reference one step ahead (147).
pub const OBS_DIM: usize = 148 + 147;

/// Per-term rewards of one step, for logging.
#[derive(Clone, Copy, Debug, Default)]
pub struct RewardTerms {
    pub anchor_pos: f32,
    pub anchor_rot: f32,
    pub body_pos: f32,
    pub body_rot: f32,
    pub body_lin_vel: f32,
    pub body_ang_vel: f32,
    /// The pelvis's horizontal velocity against the reference's: without it a humanoid that
    /// steps in place where the reference walks backward loses almost nothing (the body terms
    /// are root-relative, the anchor term saturates once the root is 0.6 m off).
    pub root_vel: f32,
    pub action_rate: f32,
    pub joint_limit: f32,
    /// Mean body position error, m (the tracking metric).
    pub body_pos_error: f32,
}

impl RewardTerms {
    pub fn total(&self) -> f32 {
        0.5 * self.anchor_pos
            + 0.5 * self.anchor_rot
            + self.body_pos
            + self.body_rot
            + self.body_lin_vel
            + self.body_ang_vel
            + self.root_vel
            + self.action_rate
            + self.joint_limit
    }
}

/// The root velocity reward's width, m/s: a 0.3 m/s error (stepping in place where the
/// reference walks backward at 0.4 m/s) halves it, a gait's own 0.1 m/s ripple costs 6%.
const ROOT_VEL_SIGMA: f64 = 0.4;

/// Why an episode ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ending {
    /// Still running.
    None,
    /// Tracking failed (height, tilt or end-effector error too large): a true terminal state.
    Failed,
    /// The clip ran out: a time limit (the value is bootstrapped).
    ClipEnd,
    /// Physics diverged.
    Diverged,
}

/// One humanoid tracking the shared reference.
pub struct Tracker {
    env: Env,
    /// Reference frame the humanoid is at.
    pub frame: usize,
    pub start: usize,
    prev_residual: Vec<f32>,
    next_push: f64,
}

/// The reference: a clip and derived per-frame quantities.
pub struct Reference {
    pub clip: Clip,
    frames_ahead: Vec<CharFrame>,
}

impl Reference {
    pub fn new(clip: Clip) -> Self {
        let frames_ahead = clip.bodies.iter().map(BodyKinematics::frame).collect();
        Self { clip, frames_ahead }
    }

    pub fn len(&self) -> usize {
        self.clip.len()
    }

    pub fn is_empty(&self) -> bool {
        self.clip.is_empty()
    }

    fn hinges(&self, t: usize) -> &[f64] {
        &self.clip.qpos[t][7..]
    }
}

fn angle(a: DQuat, b: DQuat) -> f64 {
    2.0 * a.dot(b).abs().min(1.0).acos()
}

/// z of gravity seen in a body's frame (1 upright... -1 upside down), as BeyondMimic's tilt test.
fn gravity_z(r: DQuat) -> f64 {
    (r.conjugate() * DVec3::NEG_Z).z
}

impl Tracker {
    pub fn new(humanoid: &Arc<Humanoid>) -> Self {
        Self { env: humanoid.env(), frame: 0, start: 0, prev_residual: vec![0.0; NUM_DOFS], next_push: 0.0 }
    }

    pub fn env(&self) -> &Env {
        &self.env
    }

    /// Reference state initialisation at `frame`, with noise on hinges and root velocity.
    pub fn reset(
        &mut self,
        reference: &Reference,
        frame: usize,
        cfg: &TrackConfig,
        rng: &mut impl Rng,
    ) -> Result<(), SimError> {
        let mut q = reference.clip.qpos[frame].clone();
        let mut v = reference.clip.qvel[frame].clone();
        let n = cfg.init_noise;
        for x in &mut q[7..] {
            *x += rng.random_range(-n..=n);
        }
        for x in &mut v[..3] {
            *x += rng.random_range(-n..=n);
        }
        self.env.reset(&q, &v)?;
        self.frame = frame;
        self.start = frame;
        self.prev_residual.fill(0.0);
        self.next_push = self.env.time() + rng.random_range(cfg.push_interval[0]..=cfg.push_interval[1]);
        Ok(())
    }

    /// Writes the observation (unnormalised) into `out`.
    pub fn observe(&self, reference: &Reference, out: &mut [f32]) {
        let (q, v) = (self.env.qpos(), self.env.qvel());
        let k = self.env.bodies();
        let frame = k.frame();
        let root = k.rot[body::PELVIS];
        let mut at = 0;
        let mut put = |xs: &[f64], scale: f64| {
            for &x in xs {
                out[at] = (x * scale) as f32;
                at += 1;
            }
        };
        put(&[q[2]], 1.0);
        put(&rotvec(frame.rotation(root)).to_array(), 1.0);
        put(&frame.vector(k.lin_vel[body::PELVIS]).to_array(), 1.0);
        put(&v[3..6], 0.25);
        put(&q[7..], 1.0);
        put(&v[6..], 0.1);
        let t = (self.frame + 1).min(reference.len() - 1);
        let r = &reference.clip.bodies[t];
        put(reference.hinges(t), 1.0);
        put(&reference.clip.qvel[t][6..], 0.1);
        put(&frame.point(r.pos[body::PELVIS]).to_array(), 1.0);
        put(&rotvec(root.conjugate() * r.rot[body::PELVIS]).to_array(), 1.0);
        put(&frame.vector(r.lin_vel[body::PELVIS]).to_array(), 1.0);
        debug_assert_eq!(at, OBS_DIM);
    }

    /// The environment action for policy output `u`.
    pub fn action(&self, reference: &Reference, u: &[f32], cfg: &TrackConfig) -> Vec<f32> {
        let t = (self.frame + 1).min(reference.len() - 1);
        let target: Vec<f64> =
            reference.hinges(t).iter().zip(u).map(|(q, u)| q + cfg.action_scale * f64::from(*u)).collect();
        self.env.humanoid().actions().action_for(&target)
    }

    /// One control step with policy output `u`: returns the reward terms and how it ended.
    pub fn step(
        &mut self,
        reference: &Reference,
        u: &[f32],
        cfg: &TrackConfig,
        rng: &mut impl Rng,
    ) -> (RewardTerms, Ending) {
        let a = self.action(reference, u, cfg);
        if self.advance(&a, cfg, rng).is_err() {
            return (RewardTerms::default(), Ending::Diverged);
        }
        let k = self.env.bodies();
        let terms = self.rewards(&k, reference, u, cfg);
        self.prev_residual.copy_from_slice(u);
        (terms, self.ending(&k, reference, cfg))
    }

    /// One control step executing environment action `a` as given (data collection executes
    /// noisy actions this way); no rewards.
    pub fn step_action(&mut self, reference: &Reference, a: &[f32], cfg: &TrackConfig, rng: &mut impl Rng) -> Ending {
        match self.advance(a, cfg, rng) {
            Ok(()) => self.ending(&self.env.bodies(), reference, cfg),
            Err(_) => Ending::Diverged,
        }
    }

    fn advance(&mut self, a: &[f32], cfg: &TrackConfig, rng: &mut impl Rng) -> Result<(), SimError> {
        self.env.step(a)?;
        self.frame += 1;
        if cfg.push_max > 0.0 && self.env.time() >= self.next_push {
            let (speed, dir) = (rng.random_range(0.0..=cfg.push_max), rng.random_range(0.0..std::f64::consts::TAU));
            self.env.kick([speed * dir.cos(), speed * dir.sin()])?;
            self.next_push = self.env.time() + rng.random_range(cfg.push_interval[0]..=cfg.push_interval[1]);
        }
        Ok(())
    }

    /// Failure (pelvis height, tilt or end-effector height off the reference), clip end, or on.
    fn ending(&self, k: &BodyKinematics, reference: &Reference, cfg: &TrackConfig) -> Ending {
        let r = &reference.clip.bodies[self.frame];
        let p = body::PELVIS;
        let failed = (k.pos[p].z - r.pos[p].z).abs() > cfg.max_height_error
            || (gravity_z(k.rot[p]) - gravity_z(r.rot[p])).abs() > cfg.max_tilt_error
            || [body::L_ANKLE, body::R_ANKLE, body::L_HAND, body::R_HAND]
                .iter()
                .any(|&b| (k.pos[b].z - r.pos[b].z).abs() > cfg.max_height_error);
        if failed {
            Ending::Failed
        } else if self.frame + 1 >= reference.len() {
            Ending::ClipEnd
        } else {
            Ending::None
        }
    }

    fn rewards(&self, k: &BodyKinematics, reference: &Reference, u: &[f32], cfg: &TrackConfig) -> RewardTerms {
        let r = &reference.clip.bodies[self.frame];
        let (own, theirs) = (k.frame(), reference.frames_ahead[self.frame]);
        let p = body::PELVIS;
        let g = |err2: f64, sigma: f64| (-err2 / (sigma * sigma)).exp() as f32;
        let nb = NUM_BODIES as f64;
        let (mut pos, mut rot, mut lin, mut ang, mut pos_err) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for b in 0..NUM_BODIES {
            let e = own.point(k.pos[b]) - theirs.point(r.pos[b]);
            pos += e.length_squared() / nb;
            pos_err += e.length() / nb;
            rot += angle(own.rotation(k.rot[b]), theirs.rotation(r.rot[b])).powi(2) / nb;
            lin += (k.lin_vel[b] - r.lin_vel[b]).length_squared() / nb;
            ang += (k.ang_vel[b] - r.ang_vel[b]).length_squared() / nb;
        }
        let rate: f64 =
            u.iter().zip(&self.prev_residual).map(|(a, b)| (cfg.action_scale * f64::from(a - b)).powi(2)).sum();
        let map = self.env.humanoid().actions();
        let limit: f64 = self
            .env
            .hinge_angles()
            .iter()
            .enumerate()
            .map(|(i, q)| {
                let (lo, hi) = (map.lower[i], map.upper[i]);
                let margin = 0.05 * (hi - lo);
                (lo + margin - q).max(0.0) + (q - hi + margin).max(0.0)
            })
            .sum();
        RewardTerms {
            anchor_pos: g((k.pos[p] - r.pos[p]).length_squared(), 0.3),
            anchor_rot: g(angle(k.rot[p], r.rot[p]).powi(2), 0.4),
            body_pos: g(pos, 0.3),
            body_rot: g(rot, 0.4),
            body_lin_vel: g(lin, 1.0),
            body_ang_vel: g(ang, std::f64::consts::PI),
            root_vel: g((k.lin_vel[p] - r.lin_vel[p]).truncate().length_squared(), ROOT_VEL_SIGMA),
            action_rate: (-0.1 * rate) as f32,
            joint_limit: (-10.0 * limit) as f32,
            body_pos_error: pos_err as f32,
        }
    }
}
