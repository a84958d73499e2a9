//! A procedural walking generator: clips of any length from a handful of gait parameters,
//! deterministic, with planted feet. It is the default motion source of every stage.
//!
//! The root follows the commanded planar velocity (forward, sideways, in the heading frame)
//! and turn rate. Each foot alternates stance (planted: it does not move at all) and swing
//! (a smooth arc from one footprint to the next, lifted `step_height`). A footprint is placed
//! where the hip will be at the middle of that stance, so the body passes over it. The pelvis
//! bobs twice per gait cycle and sways toward the stance foot, the legs are solved with
//! two-bone IK (knees point along the foot), and the arms swing opposite to the legs. The
//! result is a set of landmarks, retargeted by the same code as captured motion.

use crate::MotionError;
use crate::clip::Clip;
use crate::landmarks::{LandmarkClip, NUM_LANDMARKS, Pose};
use crate::retarget::{RetargetReport, retarget};
use flowmimic_geom::{DQuat, DVec3, yaw_quat};
use flowmimic_sim::skeleton::{Shape, bodies, body};
use flowmimic_sim::{CONTROL_HZ, Humanoid};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};
use std::sync::Arc;

/// Gait parameters. Velocities are in the character's heading frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GaitParams {
    /// Forward speed, m/s (negative walks backward).
    pub speed: f64,
    /// Sideways speed, m/s (positive to the left).
    pub lateral: f64,
    /// Turn rate, rad/s (positive to the left).
    pub turn_rate: f64,
    /// Initial heading, rad.
    pub heading: f64,
    /// Steps per second (two steps per gait cycle).
    pub step_frequency: f64,
    /// Swing foot clearance, m.
    pub step_height: f64,
    /// Arm swing amplitude at the shoulder, rad.
    pub arm_swing: f64,
    /// Clip length, s.
    pub duration: f64,
}

impl Default for GaitParams {
    fn default() -> Self {
        Self {
            speed: 1.0,
            lateral: 0.0,
            turn_rate: 0.0,
            heading: 0.0,
            step_frequency: 1.8,
            step_height: 0.08,
            arm_swing: 0.35,
            duration: 6.0,
        }
    }
}

impl GaitParams {
    /// Rejects parameters outside what a walking human does.
    pub fn validate(&self) -> Result<(), MotionError> {
        let check = |ok: bool, what: &str| if ok { Ok(()) } else { Err(MotionError::Invalid(format!("gait: {what}"))) };
        let all = [
            self.speed,
            self.lateral,
            self.turn_rate,
            self.heading,
            self.step_frequency,
            self.step_height,
            self.arm_swing,
            self.duration,
        ];
        check(all.iter().all(|x| x.is_finite()), "parameters must be finite")?;
        check(self.speed.abs() <= 2.0, "speed must be within +-2 m/s (walking)")?;
        check(self.lateral.abs() <= 0.8, "lateral speed must be within +-0.8 m/s")?;
        check(self.turn_rate.abs() <= 1.5, "turn rate must be within +-1.5 rad/s")?;
        check((1.0..=3.0).contains(&self.step_frequency), "step frequency must be 1-3 steps/s")?;
        check((0.02..=0.2).contains(&self.step_height), "step height must be 0.02-0.2 m")?;
        check((0.0..=1.0).contains(&self.arm_swing), "arm swing must be 0-1 rad")?;
        check((0.5..=600.0).contains(&self.duration), "duration must be 0.5-600 s")?;
        // A step cannot be longer than the legs allow.
        let stride = (self.speed.hypot(self.lateral)) / self.step_frequency;
        check(stride <= 0.85, "speed / step frequency gives steps over 0.85 m: raise the step frequency")
    }

    /// A random walk from the ranges of everyday walking, for building diverse sets.
    pub fn sample(rng: &mut impl Rng, duration: f64) -> Self {
        let backward = rng.random_bool(0.15);
        let speed: f64 = if backward { -rng.random_range(0.3..0.8) } else { rng.random_range(0.4..1.5) };
        let lateral = if rng.random_bool(0.25) { rng.random_range(-0.3..0.3) } else { 0.0 };
        let turn_rate = if rng.random_bool(0.5) { rng.random_range(-0.6..0.6) } else { 0.0 };
        let step_frequency = (1.5 + 0.5 * speed.abs()).clamp(1.4, 2.4) + rng.random_range(-0.1..0.1);
        Self {
            speed,
            lateral,
            turn_rate,
            heading: rng.random_range(-PI..PI),
            step_frequency,
            step_height: rng.random_range(0.05..0.11),
            arm_swing: rng.random_range(0.15..0.5),
            duration,
        }
    }
}

/// Fraction of a gait cycle a foot is in the air.
const SWING_FRACTION: f64 = 0.4;
/// Highest pelvis height while walking (legs slightly bent), m.
const PELVIS_HEIGHT: f64 = 0.905;
/// Vertical pelvis bob amplitude, m.
const BOB: f64 = 0.012;
/// Fraction of the full leg length the hip-to-ankle distance may reach.
const REACH: f64 = 0.98;

/// The planar root path: position and heading at time `t`, integrated in closed form.
fn root_path(p: &GaitParams, t: f64) -> (DVec3, f64) {
    let yaw = p.heading + p.turn_rate * t;
    let v = DVec3::new(p.speed, p.lateral, 0.0);
    let pos = if p.turn_rate.abs() < 1e-9 {
        yaw_quat(p.heading) * v * t
    } else {
        // Integral of R(h0 + w s) v ds from 0 to t.
        let (w, h0) = (p.turn_rate, p.heading);
        let (s0, c0, s1, c1) = (h0.sin(), h0.cos(), yaw.sin(), yaw.cos());
        let ix = DVec3::new(s1 - s0, -(c1 - c0), 0.0) / w; // integral of (cos, sin)
        let iy = DVec3::new(c1 - c0, s1 - s0, 0.0) / w; // integral of (-sin, cos)
        ix * v.x + iy * v.y
    };
    (pos, yaw)
}

/// A footprint: where the ankle sits (above the ground) and the foot's heading.
#[derive(Clone, Copy)]
struct Footprint {
    ankle: DVec3,
    yaw: f64,
}

struct Gait<'a> {
    p: &'a GaitParams,
    cycle: f64,
    hip_width: f64,
    ankle_height: f64,
}

impl Gait<'_> {
    /// Phase offset of each foot: the right foot is half a cycle after the left.
    fn offset(side: usize) -> f64 {
        0.5 * side as f64
    }

    /// Footprint `k` of a foot: the stance that starts at cycle `k` after its swing.
    fn footprint(&self, side: usize, k: i64) -> Footprint {
        let stance_start = (k as f64 + Self::offset(side) + SWING_FRACTION) * self.cycle;
        let mid = stance_start + 0.5 * (1.0 - SWING_FRACTION) * self.cycle;
        let (pos, yaw) = root_path(self.p, mid);
        let side_sign = if side == 0 { 1.0 } else { -1.0 };
        let ankle =
            pos + yaw_quat(yaw) * DVec3::new(0.0, side_sign * self.hip_width, 0.0) + DVec3::Z * self.ankle_height;
        Footprint { ankle, yaw }
    }

    /// Ankle position and foot heading of a foot at time `t`.
    fn foot(&self, side: usize, t: f64) -> (DVec3, f64) {
        let phase = t / self.cycle - Self::offset(side);
        let k = phase.floor();
        let u = phase - k;
        let (k, u) = (k as i64, u);
        if u >= SWING_FRACTION {
            let f = self.footprint(side, k);
            return (f.ankle, f.yaw);
        }
        // Swing from footprint k-1 to k: smooth horizontally, a sine bump vertically.
        let s = u / SWING_FRACTION;
        let ease = s * s * (3.0 - 2.0 * s);
        let (a, b) = (self.footprint(side, k - 1), self.footprint(side, k));
        let mut ankle = a.ankle.lerp(b.ankle, ease);
        ankle.z += self.p.step_height * (PI * s).sin();
        let yaw = a.yaw + flowmimic_geom::wrap_angle(b.yaw - a.yaw) * ease;
        (ankle, yaw)
    }
}

/// Knee position of a two-bone leg from hip to ankle, bending toward `forward`.
fn knee(hip: DVec3, ankle: DVec3, thigh: f64, shin: f64, forward: DVec3) -> DVec3 {
    let d = (ankle - hip).length().clamp(1e-6, (thigh + shin) * 0.9999);
    let u = (ankle - hip).normalize();
    let along = (thigh * thigh - shin * shin + d * d) / (2.0 * d);
    let out = (thigh * thigh - along * along).max(0.0).sqrt();
    let f = (forward - u * forward.dot(u)).normalize_or_zero();
    hip + u * along + f * out
}

/// Landmarks of a generated walk at 30 Hz.
pub fn landmarks(p: &GaitParams) -> Result<LandmarkClip, MotionError> {
    p.validate()?;
    let specs = bodies();
    let off = |b: usize| DVec3::from_array(specs[b].offset);
    let (thigh, shin) = (off(body::L_KNEE).length(), off(body::L_ANKLE).length());
    // The ankle stands as high above the ground as the foot geom reaches below it.
    let ankle_height = match specs[body::L_ANKLE].shape {
        Shape::Box { center, half } => half[2] - center[2],
        _ => unreachable!("the foot is a box"),
    };
    let gait = Gait { p, cycle: 2.0 / p.step_frequency, hip_width: off(body::L_HIP).y, ankle_height };
    // With flat feet, both must reach the ground in double support, when each ankle is half a
    // step from the hip: lower the pelvis for long steps (a more bent-knee gait).
    let half_step = 0.5 * p.speed.hypot(p.lateral) / p.step_frequency;
    let reach = (REACH * (thigh + shin)).powi(2) - half_step * half_step;
    let pelvis_height = PELVIS_HEIGHT.min(reach.max(0.0).sqrt() + ankle_height - off(body::L_HIP).z + BOB);
    let frames = (p.duration * CONTROL_HZ).round() as usize + 1;
    let poses = (0..frames)
        .map(|i| {
            let t = i as f64 / CONTROL_HZ;
            let (root, yaw) = root_path(p, t);
            let cycle_phase = TAU * t / gait.cycle;
            // Bob: highest at mid-stance of either foot; sway toward the stance foot.
            let bob = BOB * (2.0 * cycle_phase - TAU * (SWING_FRACTION + 0.5 * (1.0 - SWING_FRACTION))).cos();
            let sway = 0.02 * (cycle_phase - TAU * (SWING_FRACTION + 0.5 * (1.0 - SWING_FRACTION))).cos();
            let lean = 0.06 * p.speed; // lean into the walk
            let pelvis_rot = yaw_quat(yaw) * DQuat::from_rotation_y(lean * 0.5);
            let pelvis = root + DVec3::new(0.0, 0.0, pelvis_height + bob) + yaw_quat(yaw) * DVec3::new(0.0, sway, 0.0);
            let chest_rot = yaw_quat(yaw) * DQuat::from_rotation_y(lean);
            let chest = pelvis + pelvis_rot * (off(body::TORSO) + off(body::SPINE) + off(body::CHEST));
            let neck = chest + chest_rot * off(body::NECK);
            let head = neck + chest_rot * DVec3::new(0.0, 0.0, 0.12);
            let mut pose: Pose = [DVec3::ZERO; NUM_LANDMARKS];
            for side in 0..2 {
                let sign = if side == 0 { 1.0 } else { -1.0 };
                let hip = pelvis + pelvis_rot * DVec3::new(0.0, sign * gait.hip_width, off(body::L_HIP).z);
                let (ankle, foot_yaw) = gait.foot(side, t);
                let forward = yaw_quat(foot_yaw) * DVec3::X;
                let knee_p = knee(hip, ankle, thigh, shin, forward);
                let toe = ankle + yaw_quat(foot_yaw) * off(body::L_TOE);
                // Arms swing with the opposite leg: forward when that leg is behind.
                let swing = p.arm_swing * (cycle_phase - TAU * Gait::offset(1 - side) - PI * SWING_FRACTION).sin();
                let shoulder =
                    chest + chest_rot * (off(body::L_THORAX) + off(body::L_SHOULDER)) * DVec3::new(1.0, sign, 1.0);
                let down = chest_rot * DVec3::new(swing.sin(), sign * 0.12, -swing.cos()).normalize();
                let elbow = shoulder + down * off(body::L_ELBOW).length();
                let bend = chest_rot * DVec3::new((swing + 0.5).sin(), sign * 0.1, -(swing + 0.5).cos()).normalize();
                let wrist = elbow + bend * off(body::L_WRIST).length();
                let set = |pose: &mut Pose, l: usize, v: DVec3| pose[l + side] = v;
                set(&mut pose, 0, hip);
                set(&mut pose, 2, knee_p);
                set(&mut pose, 4, ankle);
                set(&mut pose, 6, toe);
                set(&mut pose, 11, shoulder);
                set(&mut pose, 13, elbow);
                set(&mut pose, 15, wrist);
            }
            pose[8] = chest;
            pose[9] = neck;
            pose[10] = head;
            pose
        })
        .collect();
    Ok(LandmarkClip { fps: CONTROL_HZ, frames: poses })
}

/// A generated walking clip for the humanoid.
pub fn generate(humanoid: &Arc<Humanoid>, name: &str, p: &GaitParams) -> Result<(Clip, RetargetReport), MotionError> {
    let source = serde_json::to_string(p).expect("json");
    retarget(humanoid, &landmarks(p)?, name, &format!("generator {source}"), false)
}

/// The generated 10 s straight walk at 1 m/s, `walk_straight`: every stage's default clip
/// (the shipped expert tracks it).
pub fn straight_walk(humanoid: &Arc<Humanoid>) -> Result<Clip, MotionError> {
    let walk = GaitParams { duration: 10.0, ..Default::default() };
    Ok(generate(humanoid, "walk_straight", &walk)?.0)
}

/// `count` diverse walks from `seed` (the same seed gives the same set).
pub fn sample_set(count: usize, seed: u64, duration: f64) -> Vec<GaitParams> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(count);
    while out.len() < count {
        let p = GaitParams::sample(&mut rng, duration);
        if p.validate().is_ok() {
            out.push(p);
        }
    }
    out
}
