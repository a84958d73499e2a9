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
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// Observation width: proprioception and the reference one step ahead (147).
pub const OBS_DIM: usize = PROPRIOCEPTION + 147;
/// Root height, tilt, linear and angular velocity, hinge angles and velocities.
const PROPRIOCEPTION: usize = 10 + 2 * NUM_DOFS;

/// Reference frames ahead (1/3 s and 1 s) whose pose a policy trained with
/// `track.observe_ahead` observes too: seeing only the next frame, a policy cannot shift its
/// weight before a bend or a reversal begins.
pub const AHEAD_FRAMES: [usize; 2] = [10, 30];
/// Observation entries per frame ahead: the reference's hinges and its root's position and
/// orientation relative to the character.
pub const AHEAD_DIM: usize = NUM_DOFS + 6;

/// Observation width of a policy that observes the frames ahead or not.
pub fn obs_dim(observe_ahead: bool) -> usize {
    if observe_ahead { OBS_DIM + AHEAD_FRAMES.len() * AHEAD_DIM } else { OBS_DIM }
}

/// For each entry of the frames-ahead block, its counterpart for the next frame (hinges, root
/// position and orientation): a policy widened to observe ahead starts their statistics there.
pub fn ahead_counterparts() -> Vec<usize> {
    let hinges = PROPRIOCEPTION..PROPRIOCEPTION + NUM_DOFS;
    let root = OBS_DIM - 9..OBS_DIM - 3;
    AHEAD_FRAMES.iter().flat_map(|_| hinges.clone().chain(root.clone())).collect()
}

/// One term of the tracking reward: `weight * exp(-err^2 / sigma^2)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Kernel {
    pub weight: f64,
    /// The error at which the term falls to 1/e of its weight, in the term's unit.
    pub sigma: f64,
}

/// The tracking reward's weights and widths (BeyondMimic's): `[track.reward]` in a config, one
/// table per term.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RewardConfig {
    /// Pelvis position (m) and orientation (rad) in the world.
    pub anchor_pos: Kernel,
    pub anchor_rot: Kernel,
    /// Root-relative body positions (m) and orientations (rad), mean squared over the bodies.
    pub body_pos: Kernel,
    pub body_rot: Kernel,
    /// Body linear (m/s) and angular (rad/s) velocities, mean squared over the bodies.
    pub body_lin_vel: Kernel,
    pub body_ang_vel: Kernel,
    /// The pelvis's horizontal velocity (m/s): without it a humanoid that steps in place where
    /// the reference walks backward loses almost nothing (the body terms are root-relative, the
    /// anchor term saturates once the root is 0.6 m off). Its width: a 0.3 m/s error (stepping
    /// in place where the reference walks backward at 0.4 m/s) halves it, a gait's own 0.1 m/s
    /// ripple costs 6%.
    pub root_vel: Kernel,
    /// Penalty per rad^2 of change of the residual PD target between steps.
    pub action_rate: f64,
    /// Penalty per rad that hinges reach into the outer 5% of their ranges.
    pub joint_limit: f64,
}

impl Default for RewardConfig {
    fn default() -> Self {
        let kernel = |weight, sigma| Kernel { weight, sigma };
        Self {
            anchor_pos: kernel(0.5, 0.3),
            anchor_rot: kernel(0.5, 0.4),
            body_pos: kernel(1.0, 0.3),
            body_rot: kernel(1.0, 0.4),
            body_lin_vel: kernel(1.0, 1.0),
            body_ang_vel: kernel(1.0, std::f64::consts::PI),
            root_vel: kernel(1.0, 0.4),
            action_rate: 0.1,
            joint_limit: 10.0,
        }
    }
}

/// The terms of one step's reward: each kernel's value in [0, 1] before its weight, the
/// penalties weighted (0 or below); and the tracking metric.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct RewardTerms {
    pub anchor_pos: f32,
    pub anchor_rot: f32,
    pub body_pos: f32,
    pub body_rot: f32,
    pub body_lin_vel: f32,
    pub body_ang_vel: f32,
    pub root_vel: f32,
    pub action_rate: f32,
    pub joint_limit: f32,
    /// Mean body position error, m.
    pub body_pos_error: f32,
}

impl RewardTerms {
    /// The terms by name, as log.csv's columns name them (`reward_<term>`).
    pub fn named(&self) -> [(&'static str, f32); 9] {
        [
            ("anchor_pos", self.anchor_pos),
            ("anchor_rot", self.anchor_rot),
            ("body_pos", self.body_pos),
            ("body_rot", self.body_rot),
            ("body_lin_vel", self.body_lin_vel),
            ("body_ang_vel", self.body_ang_vel),
            ("root_vel", self.root_vel),
            ("action_rate", self.action_rate),
            ("joint_limit", self.joint_limit),
        ]
    }

    /// Adds `weight` times each of `other`'s terms into these (means over steps).
    pub fn add_weighted(&mut self, other: &Self, weight: f32) {
        let mine = [
            &mut self.anchor_pos,
            &mut self.anchor_rot,
            &mut self.body_pos,
            &mut self.body_rot,
            &mut self.body_lin_vel,
            &mut self.body_ang_vel,
            &mut self.root_vel,
            &mut self.action_rate,
            &mut self.joint_limit,
        ];
        for (m, (_, theirs)) in mine.into_iter().zip(other.named()) {
            *m += weight * theirs;
        }
        self.body_pos_error += weight * other.body_pos_error;
    }

    /// The reward: the kernels at their weights plus the penalties.
    pub fn total(&self, w: &RewardConfig) -> f32 {
        w.anchor_pos.weight as f32 * self.anchor_pos
            + w.anchor_rot.weight as f32 * self.anchor_rot
            + w.body_pos.weight as f32 * self.body_pos
            + w.body_rot.weight as f32 * self.body_rot
            + w.body_lin_vel.weight as f32 * self.body_lin_vel
            + w.body_ang_vel.weight as f32 * self.body_ang_vel
            + w.root_vel.weight as f32 * self.root_vel
            + self.action_rate
            + self.joint_limit
    }
}

/// `exp(-err2 / sigma^2)` of a squared error.
fn kernel(err2: f64, k: Kernel) -> f32 {
    (-err2 / (k.sigma * k.sigma)).exp() as f32
}

/// The mean over the bodies of `f(body)`.
fn body_mean(f: impl Fn(usize) -> f64) -> f64 {
    (0..NUM_BODIES).map(|b| f(b) / NUM_BODIES as f64).sum()
}

/// Squared pelvis position error in the world, m^2.
fn anchor_pos(k: &BodyKinematics, r: &BodyKinematics) -> f64 {
    (k.pos[body::PELVIS] - r.pos[body::PELVIS]).length_squared()
}

/// Squared pelvis orientation error, rad^2.
fn anchor_rot(k: &BodyKinematics, r: &BodyKinematics) -> f64 {
    angle(k.rot[body::PELVIS], r.rot[body::PELVIS]).powi(2)
}

/// Mean squared body position error in each pose's character frame, m^2.
fn body_pos(k: &BodyKinematics, r: &BodyKinematics, own: &CharFrame, theirs: &CharFrame) -> f64 {
    body_mean(|b| (own.point(k.pos[b]) - theirs.point(r.pos[b])).length_squared())
}

/// Mean body position error (not squared), m: the tracking metric.
fn body_pos_error(k: &BodyKinematics, r: &BodyKinematics, own: &CharFrame, theirs: &CharFrame) -> f64 {
    body_mean(|b| (own.point(k.pos[b]) - theirs.point(r.pos[b])).length())
}

/// Mean squared body orientation error in each pose's character frame, rad^2.
fn body_rot(k: &BodyKinematics, r: &BodyKinematics, own: &CharFrame, theirs: &CharFrame) -> f64 {
    body_mean(|b| angle(own.rotation(k.rot[b]), theirs.rotation(r.rot[b])).powi(2))
}

/// Mean squared body linear velocity error, (m/s)^2.
fn body_lin_vel(k: &BodyKinematics, r: &BodyKinematics) -> f64 {
    body_mean(|b| (k.lin_vel[b] - r.lin_vel[b]).length_squared())
}

/// Mean squared body angular velocity error, (rad/s)^2.
fn body_ang_vel(k: &BodyKinematics, r: &BodyKinematics) -> f64 {
    body_mean(|b| (k.ang_vel[b] - r.ang_vel[b]).length_squared())
}

/// Squared horizontal pelvis velocity error, (m/s)^2.
fn root_vel(k: &BodyKinematics, r: &BodyKinematics) -> f64 {
    (k.lin_vel[body::PELVIS] - r.lin_vel[body::PELVIS]).truncate().length_squared()
}

/// Squared change of the residual PD targets since the last step, rad^2.
fn action_rate(u: &[f32], prev: &[f32], action_scale: f64) -> f64 {
    u.iter().zip(prev).map(|(a, b)| (action_scale * f64::from(a - b)).powi(2)).sum()
}

/// How far the hinges reach into the outer 5% of their ranges, rad.
fn joint_limit(hinges: &[f64], lower: &[f64], upper: &[f64]) -> f64 {
    hinges
        .iter()
        .zip(lower.iter().zip(upper))
        .map(|(q, (&lo, &hi))| {
            let margin = 0.05 * (hi - lo);
            (lo + margin - q).max(0.0) + (q - hi + margin).max(0.0)
        })
        .sum()
}

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

/// The reference's next frame as the policy observes it, all in the world: a clip's frame, or
/// one a caller builds from elsewhere (a plan's next state; docs/guidance.md, "A tracking
/// policy that executes the plan").
pub struct NextFrame<'a> {
    pub hinges: &'a [f64],
    /// rad/s.
    pub hinge_velocities: &'a [f64],
    pub pelvis_pos: DVec3,
    pub pelvis_rot: DQuat,
    pub pelvis_vel: DVec3,
}

/// Writes the observation of `env`, whose body kinematics are `k`, tracking `next`
/// (unnormalised, [`OBS_DIM`] wide).
pub fn observe(env: &Env, k: &BodyKinematics, next: &NextFrame, out: &mut [f32]) {
    assert_eq!(out.len(), OBS_DIM, "observation width");
    let (q, v) = (env.qpos(), env.qvel());
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
    put(next.hinges, 1.0);
    put(next.hinge_velocities, 0.1);
    put(&frame.point(next.pelvis_pos).to_array(), 1.0);
    put(&rotvec(root.conjugate() * next.pelvis_rot).to_array(), 1.0);
    put(&frame.vector(next.pelvis_vel).to_array(), 1.0);
    debug_assert_eq!(at, OBS_DIM);
}

/// One humanoid tracking the shared reference.
pub struct Tracker {
    env: Env,
    /// Reference frame the humanoid is at.
    pub frame: usize,
    pub start: usize,
    prev_residual: Vec<f32>,
    next_push: f64,
    /// This episode's standard deviation of noise on the executed action, policy output units.
    action_noise: f32,
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
        Self {
            env: humanoid.env(),
            frame: 0,
            start: 0,
            prev_residual: vec![0.0; NUM_DOFS],
            next_push: 0.0,
            action_noise: 0.0,
        }
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
        // Drawn only when asked for, so that runs without it keep their random stream.
        self.action_noise = if cfg.action_noise > 0.0 { rng.random_range(0.0..=cfg.action_noise) as f32 } else { 0.0 };
        Ok(())
    }

    /// Writes the observation (unnormalised) into `out`, which is [`obs_dim`] wide: with the
    /// frames ahead when it has room for them.
    pub fn observe(&self, reference: &Reference, out: &mut [f32]) {
        let width = out.len();
        assert!(width == OBS_DIM || width == obs_dim(true), "observation width {width}");
        let k = self.env.bodies();
        let t = (self.frame + 1).min(reference.len() - 1);
        let r = &reference.clip.bodies[t];
        let next = NextFrame {
            hinges: reference.hinges(t),
            hinge_velocities: &reference.clip.qvel[t][6..],
            pelvis_pos: r.pos[body::PELVIS],
            pelvis_rot: r.rot[body::PELVIS],
            pelvis_vel: r.lin_vel[body::PELVIS],
        };
        observe(&self.env, &k, &next, &mut out[..OBS_DIM]);
        if width > OBS_DIM {
            let (frame, root) = (k.frame(), k.rot[body::PELVIS]);
            let mut at = OBS_DIM;
            let mut put = |xs: &[f64]| {
                for &x in xs {
                    out[at] = x as f32;
                    at += 1;
                }
            };
            for ahead in AHEAD_FRAMES {
                let t = (self.frame + ahead).min(reference.len() - 1);
                let r = &reference.clip.bodies[t];
                put(reference.hinges(t));
                put(&frame.point(r.pos[body::PELVIS]).to_array());
                put(&rotvec(root.conjugate() * r.rot[body::PELVIS]).to_array());
            }
            debug_assert_eq!(at, width);
        }
    }

    /// The environment action for policy output `u`.
    pub fn action(&self, reference: &Reference, u: &[f32], cfg: &TrackConfig) -> Vec<f32> {
        let t = (self.frame + 1).min(reference.len() - 1);
        let target: Vec<f64> =
            reference.hinges(t).iter().zip(u).map(|(q, u)| q + cfg.action_scale * f64::from(*u)).collect();
        self.env.humanoid().actions().action_for(&target)
    }

    /// One control step with policy output `u`, executed with this episode's action noise:
    /// returns the reward terms and how it ended.
    pub fn step(
        &mut self,
        reference: &Reference,
        u: &[f32],
        cfg: &TrackConfig,
        rng: &mut impl Rng,
    ) -> (RewardTerms, Ending) {
        let a = if self.action_noise > 0.0 {
            let noise = Normal::new(0.0, self.action_noise).expect("a positive finite deviation");
            let noisy: Vec<f32> = u.iter().map(|x| x + noise.sample(rng)).collect();
            self.action(reference, &noisy, cfg)
        } else {
            self.action(reference, u, cfg)
        };
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
        let (w, map) = (&cfg.reward, self.env.humanoid().actions());
        RewardTerms {
            anchor_pos: kernel(anchor_pos(k, r), w.anchor_pos),
            anchor_rot: kernel(anchor_rot(k, r), w.anchor_rot),
            body_pos: kernel(body_pos(k, r, &own, &theirs), w.body_pos),
            body_rot: kernel(body_rot(k, r, &own, &theirs), w.body_rot),
            body_lin_vel: kernel(body_lin_vel(k, r), w.body_lin_vel),
            body_ang_vel: kernel(body_ang_vel(k, r), w.body_ang_vel),
            root_vel: kernel(root_vel(k, r), w.root_vel),
            action_rate: (-w.action_rate * action_rate(u, &self.prev_residual, cfg.action_scale)) as f32,
            joint_limit: (-w.joint_limit * joint_limit(self.env.hinge_angles(), &map.lower, &map.upper)) as f32,
            body_pos_error: body_pos_error(k, r, &own, &theirs) as f32,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_reward_term_is_its_weight_at_no_error_and_falls_as_its_kernel_says() {
        let w = RewardConfig::default();
        let k = Kernel { weight: 1.0, sigma: 0.3 };
        assert_eq!(kernel(0.0, k), 1.0);
        assert!((kernel(0.09, k) - (-1.0f32).exp()).abs() < 1e-6, "an error of sigma leaves 1/e");
        // A perfect step scores the kernels' weights, no penalty.
        let perfect = RewardTerms {
            anchor_pos: 1.0,
            anchor_rot: 1.0,
            body_pos: 1.0,
            body_rot: 1.0,
            body_lin_vel: 1.0,
            body_ang_vel: 1.0,
            root_vel: 1.0,
            ..RewardTerms::default()
        };
        assert_eq!(perfect.total(&w), 6.0);
        // The penalties: a residual that moved 0.1 per hinge on 2 hinges at action_scale 0.15
        // (0.015 rad each), and a hinge 0.01 rad into its margin.
        let rate = action_rate(&[0.1, 0.1, 0.0], &[0.0, 0.0, 0.0], 0.15);
        assert!((rate - 2.0 * 0.015f64.powi(2)).abs() < 1e-9, "{rate}");
        let (lower, upper) = ([-1.0, -1.0], [1.0, 1.0]);
        assert_eq!(joint_limit(&[0.0, 0.5], &lower, &upper), 0.0, "inside the ranges' inner 90%");
        assert!((joint_limit(&[0.91, -0.5], &lower, &upper) - 0.01).abs() < 1e-12);
        // A pelvis 0.3 m off, turned 0.4 rad: each anchor term at 1/e.
        let mut a = BodyKinematics {
            pos: [DVec3::ZERO; NUM_BODIES],
            rot: [DQuat::IDENTITY; NUM_BODIES],
            lin_vel: [DVec3::ZERO; NUM_BODIES],
            ang_vel: [DVec3::ZERO; NUM_BODIES],
        };
        let reference = a.clone();
        a.pos[body::PELVIS].x = 0.3;
        a.rot[body::PELVIS] = DQuat::from_rotation_z(0.4);
        assert!((kernel(anchor_pos(&a, &reference), w.anchor_pos) - (-1.0f32).exp()).abs() < 1e-6);
        assert!((kernel(anchor_rot(&a, &reference), w.anchor_rot) - (-1.0f32).exp()).abs() < 1e-6);
        // The root's horizontal velocity only.
        a.lin_vel[body::PELVIS] = DVec3::new(0.4, 0.0, 0.3);
        assert!((kernel(root_vel(&a, &reference), w.root_vel) - (-1.0f32).exp()).abs() < 1e-6);
    }
}
