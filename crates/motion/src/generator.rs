//! A procedural walking generator: clips of any length from a walking command that may change
//! over time, deterministic, with planted feet. It is the default motion source of every stage.
//!
//! A [`Schedule`] says what the walker is told at each instant (forward and sideways speed in
//! the heading frame, turn rate, step frequency), held from key times and blended smoothly into
//! the next. [`GaitParams`] is one constant command; [`WanderParams`] draws a long walk whose
//! command changes every 1.5-4 s: faster, slower, backward, sideways, turning, stopping.
//!
//! The root path and the gait phase are integrated from the schedule. Each foot alternates
//! stance (planted: it does not move at all) and swing (an arc from one footprint to the next,
//! lifted `step_height` and bowed outward, carried along in the turning root frame so it never
//! cuts across the other leg). A footprint is placed where its hip will be at the middle of that
//! stance, widened by a quarter of the sideways travel of a gait cycle so that a sidestep's
//! closing foot stays clear of the other, and around reaches that squat by
//! [`reach::SQUAT_WIDEN`] per full squat (the feet step out before it and back after it). The
//! pelvis bobs twice per gait cycle and sways toward the stance foot, the legs are solved with
//! two-bone IK (knees point along the foot), the trunk and arms are built in the heading frame
//! (the arms swing opposite to the legs). The result is a set of landmarks, retargeted by the
//! same code as captured motion.
//!
//! With [`Reaching`], hands also reach for targets and back while the walker stops
//! ([`crate::reach`]).

use crate::MotionError;
use crate::clip::Clip;
use crate::landmarks::{LandmarkClip, NUM_LANDMARKS, Pose};
use crate::reach::{self, Bend, PELVIS_HEIGHT, Reach, Reaching, Trunk};
use crate::retarget::{RetargetReport, retarget};
use flowmimic_geom::{DVec3, yaw_quat};
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
    /// Hands reaching for targets while walking (none by default).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reach: Option<Reaching>,
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
            reach: None,
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
        self.reach.as_ref().map_or(Ok(()), Reaching::validate)?;
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
            reach: None,
        }
    }

    /// The constant schedule of these parameters.
    pub fn schedule(&self) -> Schedule {
        let command = Command {
            speed: self.speed,
            lateral: self.lateral,
            turn_rate: self.turn_rate,
            step_frequency: self.step_frequency,
        };
        Schedule {
            keys: vec![(0.0, command)],
            heading: self.heading,
            step_height: self.step_height,
            arm_swing: self.arm_swing,
            duration: self.duration,
            reaches: self.reach.map(|r| r.reaches(self.duration)).unwrap_or_default(),
        }
    }
}

/// A wandering walk: one long clip whose command changes smoothly every 1.5-4 s across the
/// range a person walks (forward 0.3-1.6 m/s, backward to -0.7 m/s, sidesteps up to 0.3 m/s,
/// turns up to 0.8 rad/s while walking, short stops). The seed picks the walk.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WanderParams {
    pub seed: u64,
    /// Clip length, s.
    pub duration: f64,
    /// Hands reaching for targets along the way (none by default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reach: Option<Reaching>,
    /// A walk of transitions instead ([`Command::transition`]): every 1-2.5 s a reversal, a
    /// stop or start, a sidestep or a turn on the spot.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub transitions: bool,
}

/// Seconds a command of a walk of transitions is held, drawn uniformly.
pub const TRANSITION_HOLD: [f64; 2] = [1.0, 2.5];

/// Seconds a wandering command is held, drawn uniformly.
pub const WANDER_HOLD: [f64; 2] = [1.5, 4.0];

impl WanderParams {
    pub fn validate(&self) -> Result<(), MotionError> {
        if !(self.duration.is_finite() && (WANDER_HOLD[0]..=600.0).contains(&self.duration)) {
            return Err(MotionError::Invalid(format!(
                "wander: duration must be {}-600 s, not {}",
                WANDER_HOLD[0], self.duration
            )));
        }
        self.reach.as_ref().map_or(Ok(()), Reaching::validate)
    }

    /// The walk's commands: the first held from t = 0, a new one every 1.5-4 s (1-2.5 s for a
    /// walk of transitions).
    pub fn schedule(&self) -> Schedule {
        let mut rng = rand::rngs::StdRng::seed_from_u64(self.seed);
        let hold = if self.transitions { TRANSITION_HOLD } else { WANDER_HOLD };
        let mut keys = vec![(0.0, Command::walk(rng.random_range(0.6..1.2), 0.0, 0.0))];
        let mut t = rng.random_range(hold[0]..hold[1]);
        while t < self.duration {
            let command = if self.transitions {
                Command::transition(&mut rng, &keys.last().expect("a first command").1)
            } else {
                Command::sample(&mut rng)
            };
            keys.push((t, command));
            t += rng.random_range(hold[0]..hold[1]);
        }
        Schedule {
            keys,
            heading: 0.0,
            step_height: rng.random_range(0.06..0.1),
            arm_swing: rng.random_range(0.2..0.45),
            duration: self.duration,
            reaches: self.reach.map(|r| r.reaches(self.duration)).unwrap_or_default(),
        }
    }
}

/// One command of a scheduled walk, held for `seconds` (velocities in the heading frame: m/s
/// forward and to the left, rad/s to the left).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Segment {
    pub seconds: f64,
    pub speed: f64,
    pub lateral: f64,
    pub turn_rate: f64,
}

/// The schedule of a walk that follows `segments` in order, each blended into the next over
/// 1 s, at the step frequency people choose for each speed; every segment is checked as a
/// constant walk would be.
pub fn scheduled_walk(segments: &[Segment]) -> Result<Schedule, MotionError> {
    let mut keys = Vec::with_capacity(segments.len());
    let mut t = 0.0;
    for s in segments {
        let command = Command::walk(s.speed, s.lateral, s.turn_rate);
        let p = GaitParams {
            speed: s.speed,
            lateral: s.lateral,
            turn_rate: s.turn_rate,
            step_frequency: command.step_frequency,
            duration: s.seconds,
            ..Default::default()
        };
        p.validate().map_err(|e| MotionError::Invalid(format!("schedule segment {}: {e}", keys.len() + 1)))?;
        keys.push((t, command));
        t += s.seconds;
    }
    if keys.is_empty() {
        return Err(MotionError::Invalid("schedule: no segment".into()));
    }
    let defaults = GaitParams::default();
    Ok(Schedule {
        keys,
        heading: 0.0,
        step_height: defaults.step_height,
        arm_swing: defaults.arm_swing,
        duration: t,
        reaches: Vec::new(),
    })
}

/// What the walker is told at one instant. Velocities are in the heading frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Forward speed, m/s (negative walks backward).
    pub speed: f64,
    /// Sideways speed, m/s (positive to the left).
    pub lateral: f64,
    /// Turn rate, rad/s (positive to the left).
    pub turn_rate: f64,
    /// Steps per second.
    pub step_frequency: f64,
}

impl Command {
    /// A command with the step frequency people choose for its speed (longer and quicker steps
    /// as they walk faster).
    pub fn walk(speed: f64, lateral: f64, turn_rate: f64) -> Self {
        let step_frequency = (1.5 + 0.5 * speed.hypot(lateral)).clamp(1.5, 2.4);
        Self { speed, lateral, turn_rate, step_frequency }
    }

    /// One command of a wandering walk: forward (often turning), backward, sidestepping, or
    /// a stop.
    fn sample(rng: &mut impl Rng) -> Self {
        let r: f64 = rng.random();
        let sign = |rng: &mut dyn rand::RngCore| if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        if r < 0.35 {
            let turn = if rng.random_bool(0.4) { rng.random_range(-0.8..0.8) } else { 0.0 };
            Self::walk(rng.random_range(0.3..1.6), 0.0, turn)
        } else if r < 0.55 {
            Self::walk(rng.random_range(0.3..1.0), 0.0, sign(rng) * rng.random_range(0.4..0.8))
        } else if r < 0.75 {
            let turn = if rng.random_bool(0.3) { rng.random_range(-0.3..0.3) } else { 0.0 };
            Self::walk(-rng.random_range(0.25..0.7), 0.0, turn)
        } else if r < 0.92 {
            Self::walk(rng.random_range(-0.1..0.2), sign(rng) * rng.random_range(0.15..0.3), 0.0)
        } else {
            Self::walk(0.0, 0.0, 0.0)
        }
    }

    /// The next command of a walk of transitions: from walking, a reversal (forward to
    /// backward or back, blended over 1 s), a stop, a sidestep (0.2-0.4 m/s to either side) or
    /// a turn on the spot (0.3-0.7 rad/s); from standing, a start forward or backward.
    pub fn transition(rng: &mut impl Rng, previous: &Self) -> Self {
        let sign = |rng: &mut dyn rand::RngCore| if rng.random_bool(0.5) { 1.0 } else { -1.0 };
        let forward = |rng: &mut dyn rand::RngCore| Self::walk(rng.random_range(0.5..1.3), 0.0, 0.0);
        let backward = |rng: &mut dyn rand::RngCore| Self::walk(-rng.random_range(0.3..0.7), 0.0, 0.0);
        let r: f64 = rng.random();
        if previous.activity() < 0.5 || r < 0.4 {
            // A start from standing, or a reversal of the forward walk.
            if previous.speed > 0.1 || (previous.speed.abs() <= 0.1 && rng.random_bool(0.3)) {
                backward(rng)
            } else {
                forward(rng)
            }
        } else if r < 0.55 {
            Self::walk(0.0, 0.0, 0.0)
        } else if r < 0.8 {
            Self::walk(0.0, sign(rng) * rng.random_range(0.2..0.4), 0.0)
        } else {
            Self::walk(0.0, 0.0, sign(rng) * rng.random_range(0.3..0.7))
        }
    }

    fn lerp(self, other: Self, s: f64) -> Self {
        let mix = |a: f64, b: f64| a + (b - a) * s;
        Self {
            speed: mix(self.speed, other.speed),
            lateral: mix(self.lateral, other.lateral),
            turn_rate: mix(self.turn_rate, other.turn_rate),
            step_frequency: mix(self.step_frequency, other.step_frequency),
        }
    }

    /// How much the walker moves: 0 standing (the feet stay planted), 1 walking or turning.
    fn activity(&self) -> f64 {
        (self.speed.hypot(self.lateral) / 0.2 + self.turn_rate.abs() / 0.3).min(1.0)
    }
}

/// A walking command over time, and the style of the walk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    /// Commands and the times they take over (the first at 0), in order.
    pub keys: Vec<(f64, Command)>,
    /// Initial heading, rad.
    pub heading: f64,
    /// Swing foot clearance, m.
    pub step_height: f64,
    /// Arm swing amplitude at the shoulder, rad.
    pub arm_swing: f64,
    /// Clip length, s.
    pub duration: f64,
    /// Hands reaching for targets, one at a time, in time order.
    #[serde(default)]
    pub reaches: Vec<Reach>,
}

/// Seconds over which one command blends into the next (a smoothstep).
const BLEND: f64 = 1.0;

impl Schedule {
    /// The command at time `t`: the last key's, blended in from the one before over [`BLEND`],
    /// slowed to a standstill around each reach.
    pub fn at(&self, t: f64) -> Command {
        let k = self.keys.partition_point(|&(time, _)| time <= t).max(1) - 1;
        let (time, current) = self.keys[k];
        let command = if k == 0 {
            current
        } else {
            let s = ((t - time) / BLEND).clamp(0.0, 1.0);
            self.keys[k - 1].1.lerp(current, s * s * (3.0 - 2.0 * s))
        };
        let slowing = self.reaches.iter().map(|r| r.slowing(t)).fold(0.0, f64::max);
        if slowing == 0.0 {
            return command;
        }
        command.lerp(Command::walk(0.0, 0.0, 0.0), slowing)
    }

    /// The reach under way at `t`, with how far out its hand is.
    fn reach_at(&self, t: f64) -> Option<(usize, f64)> {
        self.reaches.iter().enumerate().map(|(i, r)| (i, r.weight(t))).find(|&(_, w)| w > 0.0)
    }
}

/// Fraction of a gait cycle a foot is in the air.
const SWING_FRACTION: f64 = 0.4;
/// Vertical pelvis bob amplitude, m.
const BOB: f64 = 0.012;
/// Fraction of the full leg length the hip-to-ankle distance may reach.
const REACH: f64 = 0.98;
/// How much wider than the hips the feet are planted, m: the pelvis sways over the stance foot,
/// and with feet right under the hips the thighs, 2 cm apart at rest, would brush.
const STANCE_WIDEN: f64 = 0.025;
/// How far the swing foot bows outward at mid-swing, m.
const SWING_OUT: f64 = 0.03;

/// The root path and gait phase integrated from a schedule on a fine grid (midpoint rule),
/// with margins before 0 and after the end so footprints of steps that straddle them exist.
struct Plan<'a> {
    schedule: &'a Schedule,
    start: f64,
    pos: Vec<DVec3>,
    yaw: Vec<f64>,
    /// Gait cycles since t = 0.
    phase: Vec<f64>,
}

/// Integration step of the plan, s (8 per control step).
const PLAN_DT: f64 = 1.0 / 240.0;
/// Margin of the plan on either side of the clip, s.
const PLAN_MARGIN: f64 = 4.0;

impl<'a> Plan<'a> {
    fn new(schedule: &'a Schedule) -> Self {
        let before = (PLAN_MARGIN / PLAN_DT).round() as usize;
        let n = before + ((schedule.duration + PLAN_MARGIN) / PLAN_DT).ceil() as usize + 1;
        let mut plan = Plan {
            schedule,
            start: -(before as f64) * PLAN_DT,
            pos: vec![DVec3::ZERO; n],
            yaw: vec![schedule.heading; n],
            phase: vec![0.0; n],
        };
        let advance = |plan: &mut Plan, from: usize, to: usize| {
            let dt = if to > from { PLAN_DT } else { -PLAN_DT };
            let c = schedule.at(plan.time(from) + 0.5 * dt);
            let yaw_mid = plan.yaw[from] + 0.5 * dt * c.turn_rate;
            plan.pos[to] = plan.pos[from] + yaw_quat(yaw_mid) * DVec3::new(c.speed, c.lateral, 0.0) * dt;
            plan.yaw[to] = plan.yaw[from] + dt * c.turn_rate;
            plan.phase[to] = plan.phase[from] + 0.5 * dt * c.step_frequency;
        };
        for i in before..n - 1 {
            advance(&mut plan, i, i + 1);
        }
        for i in (1..=before).rev() {
            advance(&mut plan, i, i - 1);
        }
        plan
    }

    fn time(&self, i: usize) -> f64 {
        self.start + i as f64 * PLAN_DT
    }

    /// Index and weight of the grid interval holding `t`.
    fn locate(&self, t: f64) -> (usize, f64) {
        let x = ((t - self.start) / PLAN_DT).clamp(0.0, (self.pos.len() - 1) as f64);
        let i = (x.floor() as usize).min(self.pos.len() - 2);
        (i, x - i as f64)
    }

    /// Root position and heading at `t`.
    fn root(&self, t: f64) -> (DVec3, f64) {
        let (i, w) = self.locate(t);
        (self.pos[i].lerp(self.pos[i + 1], w), self.yaw[i] + (self.yaw[i + 1] - self.yaw[i]) * w)
    }

    fn phase(&self, t: f64) -> f64 {
        let (i, w) = self.locate(t);
        self.phase[i] + (self.phase[i + 1] - self.phase[i]) * w
    }

    /// The time at which the gait reaches `phase` (the phase only grows).
    fn time_of_phase(&self, phase: f64) -> f64 {
        let i = self.phase.partition_point(|&p| p <= phase).clamp(1, self.phase.len() - 1) - 1;
        let (a, b) = (self.phase[i], self.phase[i + 1]);
        self.time(i) + PLAN_DT * ((phase - a) / (b - a)).clamp(0.0, 1.0)
    }
}

/// A footprint: where the ankle sits (above the ground), the foot's heading, and how much
/// wider than walking it stands for a squat.
#[derive(Clone, Copy)]
struct Footprint {
    ankle: DVec3,
    yaw: f64,
    widen: f64,
}

/// Seconds before a wide stance starts and after it ends during which the feet stand wide for
/// its squats: they step out before the pelvis drops and back once it is up.
const WIDEN_MARGIN: f64 = 0.3;
/// How far a step goes at which it is lifted as high as a walking step, m, where the walk's own
/// lift does not hold: a step out or back for a squat, and around a reach, the last steps as
/// the walker comes to a standstill (the walk's lift falls to nothing before they land, and the
/// feet would slide).
const STEP_LIFT: f64 = 0.05;

struct Gait<'a> {
    plan: Plan<'a>,
    hip_width: f64,
    ankle_height: f64,
    /// Each wide stance's time span, margins included, and how much wider each foot stands for
    /// its deepest squat (0 for reaches without one).
    stances: Vec<(f64, f64, f64)>,
}

/// +1 for the left side (0), -1 for the right (1).
fn side_sign(side: usize) -> f64 {
    if side == 0 { 1.0 } else { -1.0 }
}

impl Gait<'_> {
    /// Phase offset of each foot: the right foot is half a cycle after the left.
    fn offset(side: usize) -> f64 {
        0.5 * side as f64
    }

    /// Footprint `k` of a foot: the stance that starts at cycle `k` after its swing.
    fn footprint(&self, side: usize, k: i64) -> Footprint {
        let mid = k as f64 + Self::offset(side) + SWING_FRACTION + 0.5 * (1.0 - SWING_FRACTION);
        let t = self.plan.time_of_phase(mid);
        let (pos, yaw) = self.plan.root(t);
        let c = self.plan.schedule.at(t);
        let stance = |phase: f64| self.plan.time_of_phase(phase + Self::offset(side));
        let widen = self.widening(stance(k as f64 + SWING_FRACTION), stance(k as f64 + 1.0));
        let width = self.hip_width + STANCE_WIDEN + 0.25 * c.lateral.abs() * 2.0 / c.step_frequency + widen;
        let ankle = pos + yaw_quat(yaw) * DVec3::new(0.0, side_sign(side) * width, 0.0) + DVec3::Z * self.ankle_height;
        Footprint { ankle, yaw, widen }
    }

    /// How much wider each foot stands for the squats of reaches within `from..to`, m.
    fn widening(&self, from: f64, to: f64) -> f64 {
        self.stances.iter().filter(|&&(start, end, _)| start < to && from < end).map(|s| s.2).fold(0.0, f64::max)
    }

    /// Ankle position and foot heading of a foot at time `t`.
    fn foot(&self, side: usize, t: f64) -> (DVec3, f64) {
        let phase = self.plan.phase(t) - Self::offset(side);
        let k = phase.floor();
        let u = phase - k;
        let k = k as i64;
        if u >= SWING_FRACTION {
            let f = self.footprint(side, k);
            return (f.ankle, f.yaw);
        }
        // Swing from footprint k-1 to k, interpolated in the moving root frame (so on a turn the
        // foot follows the path's curve instead of cutting toward the stance leg), bowed outward
        // and lifted by sine bumps.
        let s = u / SWING_FRACTION;
        let ease = s * s * (3.0 - 2.0 * s);
        let (a, b) = (self.footprint(side, k - 1), self.footprint(side, k));
        let (root, yaw) = self.plan.root(t);
        let to_local = |p: DVec3| yaw_quat(-yaw) * (p - root);
        let bump = (PI * s).sin();
        let around_reach = self.stances.iter().any(|&(from, to, _)| (from..=to).contains(&t));
        let way = if around_reach { a.ankle.distance(b.ankle) } else { (b.widen - a.widen).abs() };
        let lift = self.plan.schedule.at(t).activity().max((way / STEP_LIFT).min(1.0));
        let local = to_local(a.ankle).lerp(to_local(b.ankle), ease)
            + DVec3::new(0.0, side_sign(side) * SWING_OUT * lift * bump, 0.0);
        let mut ankle = root + yaw_quat(yaw) * local;
        ankle.z += self.plan.schedule.step_height * lift * bump;
        let foot_yaw = a.yaw + flowmimic_geom::wrap_angle(b.yaw - a.yaw) * ease;
        (ankle, foot_yaw)
    }
}

/// A body's rest offset from its parent, m (the skeleton's, built once: the reach planner asks
/// for them thousands of times per reach).
pub(crate) fn rest_offset(b: usize) -> DVec3 {
    static OFFSETS: std::sync::OnceLock<Vec<DVec3>> = std::sync::OnceLock::new();
    OFFSETS.get_or_init(|| bodies().iter().map(|s| DVec3::from_array(s.offset)).collect())[b]
}

/// How high the ankle stands above the ground: as far as the foot geom reaches below it, m.
pub(crate) fn ankle_height() -> f64 {
    match bodies()[body::L_ANKLE].shape {
        Shape::Box { center, half } => half[2] - center[2],
        _ => unreachable!("the foot is a box"),
    }
}

/// Knee position of a two-bone leg from hip to ankle, bending toward `forward`.
pub(crate) fn knee(hip: DVec3, ankle: DVec3, thigh: f64, shin: f64, forward: DVec3) -> DVec3 {
    let d = (ankle - hip).length().clamp(1e-6, (thigh + shin) * 0.9999);
    let u = (ankle - hip).normalize();
    let along = (thigh * thigh - shin * shin + d * d) / (2.0 * d);
    let out = (thigh * thigh - along * along).max(0.0).sqrt();
    let f = (forward - u * forward.dot(u)).normalize_or_zero();
    hip + u * along + f * out
}

/// Landmarks of a generated walk at 30 Hz.
pub fn landmarks(schedule: &Schedule) -> Result<LandmarkClip, MotionError> {
    landmarks_aimed(schedule, &[])
}

/// Landmarks of a generated walk whose reaching hands aim at their targets moved by `aim[frame]`
/// (none where `aim` is short).
fn landmarks_aimed(schedule: &Schedule, aim: &[DVec3]) -> Result<LandmarkClip, MotionError> {
    let off = rest_offset;
    let (thigh, shin) = (off(body::L_KNEE).length(), off(body::L_ANKLE).length());
    let ankle_height = ankle_height();
    let plan = Plan::new(schedule);
    let planned: Vec<(DVec3, Bend)> = schedule.reaches.iter().map(|r| planned_reach(&plan, r)).collect();
    let stances = reach::wide_stances(&schedule.reaches)
        .iter()
        .map(|stance| {
            let deepest = planned[stance.reaches.clone()].iter().map(|(_, bend)| bend.drop).fold(0.0, f64::max);
            (stance.start - WIDEN_MARGIN, stance.end + WIDEN_MARGIN, reach::stance_widening(deepest))
        })
        .collect();
    let gait = Gait { plan, hip_width: off(body::L_HIP).y, ankle_height, stances };
    let frames = (schedule.duration * CONTROL_HZ).round() as usize + 1;
    let poses = (0..frames)
        .map(|i| {
            let t = i as f64 / CONTROL_HZ;
            let c = schedule.at(t);
            let activity = c.activity();
            let (root, yaw) = gait.plan.root(t);
            // With flat feet, both must reach the ground in double support, when each ankle is
            // half a step from the hip: lower the pelvis for long steps (a more bent-knee gait).
            let half_step = 0.5 * c.speed.hypot(c.lateral) / c.step_frequency;
            let leg_reach = (REACH * (thigh + shin)).powi(2) - half_step * half_step;
            let pelvis_height = PELVIS_HEIGHT.min(leg_reach.max(0.0).sqrt() + ankle_height - off(body::L_HIP).z + BOB);
            let cycle_phase = TAU * gait.plan.phase(t);
            // Bob: highest at mid-stance of either foot; sway toward the stance foot.
            let mid_stance = TAU * (SWING_FRACTION + 0.5 * (1.0 - SWING_FRACTION));
            let bob = activity * BOB * (2.0 * cycle_phase - mid_stance).cos();
            let sway = activity * 0.02 * (cycle_phase - mid_stance).cos();
            let lean = 0.06 * c.speed; // lean into the walk
            let upright = root + DVec3::new(0.0, 0.0, pelvis_height + bob) + yaw_quat(yaw) * DVec3::new(0.0, sway, 0.0);
            // A reach under way: its side, target and how far out the hand is, and the bend.
            let under_way = schedule.reach_at(t);
            let reaching = under_way.map(|(k, w)| (schedule.reaches[k].side, planned[k].0, w));
            let bend = under_way.map_or(Bend::NONE, |(k, w)| planned[k].1.scaled(w));
            let trunk = Trunk::new(upright, yaw, lean, bend);
            let Trunk { pelvis, pelvis_rot, chest, chest_rot } = trunk;
            let neck = chest + chest_rot * off(body::NECK);
            let head = neck + chest_rot * DVec3::new(0.0, 0.0, 0.12);
            let mut pose: Pose = [DVec3::ZERO; NUM_LANDMARKS];
            for side in 0..2 {
                let sign = side_sign(side);
                let hip = pelvis + pelvis_rot * DVec3::new(0.0, sign * gait.hip_width, off(body::L_HIP).z);
                let (ankle, foot_yaw) = gait.foot(side, t);
                let forward = yaw_quat(foot_yaw) * DVec3::X;
                let knee_p = knee(hip, ankle, thigh, shin, forward);
                let toe = ankle + yaw_quat(foot_yaw) * off(body::L_TOE);
                // Arms swing with the opposite leg: forward when that leg is behind.
                let swing = activity
                    * schedule.arm_swing
                    * (cycle_phase - TAU * Gait::offset(1 - side) - PI * SWING_FRACTION).sin();
                let shoulder = trunk.shoulder(side);
                let down = chest_rot * DVec3::new(swing.sin(), sign * 0.12, -swing.cos()).normalize();
                let mut elbow = shoulder + down * off(body::L_ELBOW).length();
                let bend = chest_rot * DVec3::new((swing + 0.5).sin(), sign * 0.1, -(swing + 0.5).cos()).normalize();
                let mut wrist = elbow + bend * off(body::L_WRIST).length();
                if let Some((_, target, w)) = reaching.filter(|r| r.0 == side) {
                    // The hand goes from where it swings to the target, the
                    // elbow pointing back, out and down as when a person reaches; the swinging
                    // arm's elbow gives way to that one early on, while both are close.
                    let hand = wrist + (wrist - elbow).normalize() * off(body::L_HAND).length();
                    let aimed = target + aim.get(i).copied().unwrap_or_default();
                    let pole = chest_rot * DVec3::new(-0.5, sign * 0.5, -0.7);
                    // On the way, the hand bows out to the side, clear of the hips.
                    let out = chest_rot * DVec3::new(0.0, sign * 0.3 * w * (1.0 - w), 0.0);
                    let (e, h) = reach::arm(shoulder, reach::hand_path(shoulder, hand, aimed, w) + out, pole);
                    let early = (w / 0.3).min(1.0);
                    (elbow, wrist) = (elbow.lerp(e, early), wrist.lerp(h, early));
                }
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

/// A reach's target in the world (placed at the middle of its hold, where the walker is then)
/// and the bend that gets the hand there.
fn planned_reach(plan: &Plan, r: &Reach) -> (DVec3, Bend) {
    let (root, yaw) = plan.root(0.5 * (r.hold_start() + r.hold_end()));
    let target = r.target(root, yaw);
    (target, reach::bend_for(target, r.side, |bend| Trunk::standing(root, yaw, bend)).0)
}

/// The world targets of a schedule's reaches, in the frame of its landmarks.
pub fn reach_targets(schedule: &Schedule) -> Vec<DVec3> {
    let plan = Plan::new(schedule);
    schedule.reaches.iter().map(|r| planned_reach(&plan, r).0).collect()
}

/// Passes of aiming a reaching hand again at where the retargeted hand missed: the humanoid's
/// shoulder sits up to 2 cm from the generator's, and two passes bring the hand within 2 mm.
const AIM_PASSES: usize = 2;

/// The clip of a schedule. With reaches, the retargeted hands are measured against their
/// targets and aimed again ([`AIM_PASSES`]).
fn clip_of(
    humanoid: &Arc<Humanoid>,
    schedule: &Schedule,
    name: &str,
    origin: &str,
) -> Result<(Clip, RetargetReport), MotionError> {
    let mut aim = Vec::new();
    let mut out = retarget(humanoid, &landmarks(schedule)?, name, origin, false)?;
    if schedule.reaches.is_empty() {
        return Ok(out);
    }
    let targets = reach_targets(schedule);
    for _ in 0..AIM_PASSES {
        let (clip, report) = &out;
        aim.resize(clip.len(), DVec3::ZERO);
        // The miss is measured while the hand holds; on the way out and back the hand aims
        // where it will hold (a miss measured there would count the way as a miss).
        for (r, target) in schedule.reaches.iter().zip(&targets) {
            let frames = |t: f64| ((t * CONTROL_HZ).round() as usize).min(clip.len() - 1);
            let (hold_start, hold_end) = (frames(r.hold_start()).max(1), frames(r.hold_end()));
            let hand = [body::L_HAND, body::R_HAND][r.side];
            for i in hold_start..=hold_end {
                let miss = clip.bodies[i].pos[hand] - report.placement.apply(i, *target);
                aim[i] -= yaw_quat(report.placement.yaw) * miss / report.placement.scale;
            }
            let (held_start, held_end) = (aim[hold_start], aim[hold_end]);
            aim[frames(r.start)..hold_start].fill(held_start);
            aim[hold_end + 1..=frames(r.end())].fill(held_end);
        }
        out = retarget(humanoid, &landmarks_aimed(schedule, &aim)?, name, origin, false)?;
    }
    Ok(out)
}

/// A generated walking clip for the humanoid, one constant command.
pub fn generate(humanoid: &Arc<Humanoid>, name: &str, p: &GaitParams) -> Result<(Clip, RetargetReport), MotionError> {
    p.validate()?;
    let source = serde_json::to_string(p).expect("json");
    clip_of(humanoid, &p.schedule(), name, &format!("generator {source}"))
}

/// A generated wandering walk (see [`WanderParams`]).
pub fn wander(humanoid: &Arc<Humanoid>, name: &str, p: &WanderParams) -> Result<(Clip, RetargetReport), MotionError> {
    p.validate()?;
    let source = serde_json::to_string(p).expect("json");
    clip_of(humanoid, &p.schedule(), name, &format!("generator wander {source}"))
}

/// A generated walk that follows a command schedule (see [`scheduled_walk`]).
pub fn scheduled(
    humanoid: &Arc<Humanoid>,
    name: &str,
    segments: &[Segment],
) -> Result<(Clip, RetargetReport), MotionError> {
    let schedule = scheduled_walk(segments)?;
    let source = serde_json::to_string(segments).expect("json");
    clip_of(humanoid, &schedule, name, &format!("generator schedule {source}"))
}

/// The generated 10 s straight walk at 1 m/s, `walk_straight`: every stage's default clip
/// (the shipped expert tracks it).
pub fn straight_walk(humanoid: &Arc<Humanoid>) -> Result<Clip, MotionError> {
    let walk = GaitParams { duration: 10.0, ..Default::default() };
    Ok(generate(humanoid, "walk_straight", &walk)?.0)
}

/// The generated 10 s of standing still, `stand`: where standing protocols start.
pub fn standing(humanoid: &Arc<Humanoid>) -> Result<Clip, MotionError> {
    let stand = GaitParams { speed: 0.0, duration: 10.0, ..Default::default() };
    Ok(generate(humanoid, "stand", &stand)?.0)
}

/// `count` diverse walks from `seed` (the same seed gives the same set).
pub fn sample_set(count: usize, seed: u64, duration: f64) -> Result<Vec<GaitParams>, MotionError> {
    // Every sampled walk would fail on a bad duration: refuse it before drawing any.
    GaitParams { duration, ..Default::default() }.validate()?;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(count);
    while out.len() < count {
        let p = GaitParams::sample(&mut rng, duration);
        if p.validate().is_ok() {
            out.push(p);
        }
    }
    Ok(out)
}
