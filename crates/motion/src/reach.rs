//! Reaching in generated walks: a hand goes to a target and back while the walker stops;
//! the torso leans and the knees bend for targets low or far, so that the arm gets there.
//!
//! A [`Reach`] is drawn relative to the walker (which hand, how high, how far out from the
//! shoulder, toward which side) and placed in the world at the middle of its hold, where the
//! hand then stays while the walker stands, feet planted (apart for a squat, and kept apart
//! between reaches close in time: a [`WideStance`]). The pose of the upper body
//! is a [`Trunk`]: the walking generator's pelvis and chest, bent toward the target by a
//! [`Bend`]. The bend is the smallest (lean and crouch weighed together) from which the arm,
//! a two-bone chain from the shoulder to the hand, reaches the target with room to spare.

use crate::MotionError;
use crate::generator::{ankle_height, knee, rest_offset as offset};
use flowmimic_geom::{DQuat, DVec3, yaw_quat};
use flowmimic_sim::skeleton::body;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_PI_2;
use std::ops::Range;

/// Target heights above the ground, m, and horizontal distances from the shoulder, m. A third
/// of the heights are drawn below [`LOW`] and the rest above [`HIGH`] (of the 51 targets in the
/// reach test's clips, 31% below 0.9 m, 69% above 1.1 m, 25% above 1.4 m): a hand high up or
/// down near the knees is what walking data never holds (the first arms dataset had a hand
/// below 0.7 m in 1.3% of its steps); between the two, a walking hand swings.
pub const HEIGHTS: [f64; 2] = [0.4, 1.7];
pub const LOW: f64 = 0.9;
pub const HIGH: f64 = 1.1;
/// Share of the targets drawn below [`LOW`].
const LOW_SHARE: f64 = 1.0 / 3.0;
pub const DISTANCES: [f64; 2] = [0.2, 0.7];
/// Seconds to bring the hand out, to hold it, and to bring it back.
pub const APPROACH: [f64; 2] = [0.4, 1.0];
pub const HOLD: [f64; 2] = [0.3, 1.5];
/// Fastest mean speed of a hand on its way out or back, m/s: approaches drawn quicker than the
/// way allows are slowed to it (within [`APPROACH`]), so a hand going high peaks near 3 m/s
/// (smoothstep's peak is 1.5 times its mean), as a person's does, not at 6.
const HAND_SPEED: f64 = 2.0;
/// Most the torso leans, rad, and the pelvis drops (knees bent), m: a low target is reached
/// with a squat as well as a stoop, as a person does. An expert 6,000 iterations on squats held
/// 0.3 m down (pelvis at 0.61 m) fell there from fresh starts, and passed through squats to
/// 0.68-0.70 m (docs/data.md, "A shallower squat").
pub const MAX_LEAN: f64 = 1.2;
pub const MAX_DROP: f64 = 0.2;
/// How much wider each foot stands in a full squat ([`MAX_DROP`]), m: a person squats with the
/// feet apart. Squats held with the feet 0.22 m apart, as a walker stands, were where 38% of an
/// expert's falls under kicks came from (docs/tracking.md, "Where the kicks fell it").
pub const SQUAT_WIDEN: f64 = 0.1;
/// Seconds over which the walk slows before a reach and speeds up after it.
const SLOWING: f64 = 1.0;
/// Seconds the walker stands before a hand moves and after it is back: a step is placed under
/// the hips at the middle of its stance, so the last step lands up to 0.7 of a gait cycle
/// after the walk stops and the first lifts as long before it starts (0.93 s at the slowest
/// cadence), and a hand takes 0.4 s at the least between moving and holding.
const SETTLE: f64 = 0.6;
/// How far the hips go back per unit of lean's sine (away from the target), m, and per metre
/// of drop (behind the heels): a person leaning or crouching pushes the hips back to keep the
/// weight over the feet, and the shins stay within the ankles' range.
const HIPS_BACK: f64 = 0.12;
const SQUAT_BACK: f64 = 0.25;
/// Reach the arm is planned for, as a share of its length, less a margin (m): the elbow stays
/// bent, with room for a tracking policy's errors.
const ARM_SHARE: f64 = 0.97;
const ARM_MARGIN: f64 = 0.05;

/// One reach of a hand, in the walker's heading frame at the middle of its hold.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reach {
    /// When the hand starts to move, s.
    pub start: f64,
    /// Seconds to the target, on it, and back.
    pub approach: f64,
    pub hold: f64,
    pub back: f64,
    /// 0 the left hand, 1 the right.
    pub side: usize,
    /// Target height above the ground, m.
    pub height: f64,
    /// Horizontal distance of the target from the standing shoulder, m.
    pub distance: f64,
    /// Direction of the target from the shoulder: 0 straight ahead, pi/2 out to the hand's side.
    pub azimuth: f64,
}

fn smoothstep(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

impl Reach {
    pub fn hold_start(&self) -> f64 {
        self.start + self.approach
    }

    pub fn hold_end(&self) -> f64 {
        self.hold_start() + self.hold
    }

    pub fn end(&self) -> f64 {
        self.hold_end() + self.back
    }

    /// How much the walk is slowed at `t` (1: standing): over a second up to [`SETTLE`] before
    /// the hand moves, and over a second from [`SETTLE`] after it is back.
    pub fn slowing(&self, t: f64) -> f64 {
        let (stopped, starting) = (self.start - SETTLE, self.end() + SETTLE);
        smoothstep((t - stopped + SLOWING) / SLOWING).min(smoothstep((starting + SLOWING - t) / SLOWING))
    }

    /// How far the hand is out at `t`: 0 before and after, 1 while holding, eased between.
    pub fn weight(&self, t: f64) -> f64 {
        smoothstep((t - self.start) / self.approach).min(smoothstep((self.end() - t) / self.back))
    }

    /// The target relative to the standing shoulder, in the heading frame (height absolute).
    fn offset(&self) -> DVec3 {
        let sign = if self.side == 0 { 1.0 } else { -1.0 };
        DVec3::new(self.distance * self.azimuth.cos(), sign * self.distance * self.azimuth.sin(), 0.0)
    }

    /// Roughly how far the hand goes from hanging at the side to the target, m.
    fn way(&self) -> f64 {
        let (upper, lower) = arm_bones();
        let shoulder = Trunk::standing(DVec3::ZERO, 0.0, Bend::NONE).shoulder(self.side);
        let hanging = shoulder - DVec3::Z * (upper + lower);
        (self.target(DVec3::ZERO, 0.0) - hanging).length()
    }

    /// The target in the world for a walker at `root` facing `yaw` at the middle of the hold.
    pub fn target(&self, root: DVec3, yaw: f64) -> DVec3 {
        let shoulder = Trunk::standing(root, yaw, Bend::NONE).shoulder(self.side);
        let mut t = shoulder + yaw_quat(yaw) * self.offset();
        t.z = self.height;
        t
    }
}

/// A stretch over which the feet stand apart for the squats of one or more reaches in a row:
/// from the first one's start to the last one's end, s. Reaches whose slowing overlaps share
/// one: the walk does not get back to speed between them, and the feet would step in from one
/// squat and out again for the next (four steps in 3.5 s where an expert fell, docs/data.md,
/// "Feet planted while a hand is out").
#[derive(Clone, Debug, PartialEq)]
pub struct WideStance {
    pub start: f64,
    pub end: f64,
    /// The reaches it holds, indices into the schedule's.
    pub reaches: Range<usize>,
}

/// The wide stances of reaches given in time order.
pub fn wide_stances(reaches: &[Reach]) -> Vec<WideStance> {
    let mut out: Vec<WideStance> = Vec::new();
    for (i, r) in reaches.iter().enumerate() {
        match out.last_mut() {
            Some(stance) if r.start - stance.end < 2.0 * (SLOWING + SETTLE) => {
                stance.end = r.end();
                stance.reaches.end = i + 1;
            }
            _ => out.push(WideStance { start: r.start, end: r.end(), reaches: i..i + 1 }),
        }
    }
    out
}

/// How often hands reach in a generated clip, the seed of their targets, and how their heights
/// are drawn.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Reaching {
    /// Share of the time a hand is out (approach, hold and return), 0-0.9.
    pub share: f64,
    pub seed: u64,
    /// Clips from before the choice drew [`TargetHeights::Split`].
    #[serde(default)]
    pub heights: TargetHeights,
}

/// How a reach's target height is drawn within [`HEIGHTS`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TargetHeights {
    /// A third below [`LOW`], the rest above [`HIGH`]: the heights a walking hand never holds.
    #[default]
    Split,
    /// Uniform over [`HEIGHTS`], [`LOW`]-[`HIGH`] too: a hand held in front of the waist or
    /// chest, near the body, is as far from a walking hand's swing as a high one (the standing
    /// reach protocol missed such targets with `Split`'s data, the plans as much as the hand).
    Uniform,
}

impl Reaching {
    pub fn validate(&self) -> Result<(), MotionError> {
        if !(self.share > 0.0 && self.share <= 0.9) {
            return Err(MotionError::Invalid(format!("reach: share must be in (0, 0.9], not {}", self.share)));
        }
        Ok(())
    }

    /// Reaches over a clip of `duration` s, one at a time, each with a target the arm can get
    /// to from a bend within [`MAX_LEAN`] and [`MAX_DROP`].
    pub fn reaches(&self, duration: f64) -> Vec<Reach> {
        // A stream of its own: walks with and without reaches share their walking commands.
        let mut rng = rand::rngs::StdRng::seed_from_u64(self.seed ^ 0x7265_6163_6865_7321);
        let mean_reach = APPROACH[0] + APPROACH[1] + 0.5 * (HOLD[0] + HOLD[1]);
        let mean_gap = mean_reach * (1.0 - self.share) / self.share;
        let mut out = Vec::new();
        let mut t = rng.random_range(0.3..1.0_f64.max(mean_gap));
        loop {
            let r = loop {
                let (lowest, highest) = match self.heights {
                    TargetHeights::Split if rng.random_bool(LOW_SHARE) => (HEIGHTS[0], LOW),
                    TargetHeights::Split => (HIGH, HEIGHTS[1]),
                    TargetHeights::Uniform => (HEIGHTS[0], HEIGHTS[1]),
                };
                let r = Reach {
                    start: t,
                    approach: rng.random_range(APPROACH[0]..APPROACH[1]),
                    hold: rng.random_range(HOLD[0]..HOLD[1]),
                    back: rng.random_range(APPROACH[0]..APPROACH[1]),
                    side: rng.random_range(0..2),
                    height: rng.random_range(lowest..highest),
                    distance: rng.random_range(DISTANCES[0]..DISTANCES[1]),
                    azimuth: rng.random_range(0.0..FRAC_PI_2),
                };
                if reachable(&r) {
                    let least = (r.way() / HAND_SPEED).min(APPROACH[1]);
                    break Reach { approach: r.approach.max(least), back: r.back.max(least), ..r };
                }
            };
            if r.end() > duration - 0.1 {
                return out;
            }
            t = r.end() + rng.random_range(0.5 * mean_gap..1.5 * mean_gap).max(0.3);
            out.push(r);
        }
    }
}

/// How much wider than a walker's each foot stands for a bend that drops the pelvis by `drop`, m.
pub fn stance_widening(drop: f64) -> f64 {
    SQUAT_WIDEN * drop / MAX_DROP
}

/// Whether a standing walker reaches the target of `r` from some bend.
pub fn reachable(r: &Reach) -> bool {
    let target = r.target(DVec3::ZERO, 0.0);
    let (bend, miss) = bend_for(target, r.side, |bend| Trunk::standing(DVec3::ZERO, 0.0, bend));
    miss == 0.0 && bend.lean <= MAX_LEAN
}

/// How the upper body bends toward a target: the torso leans by `lean` toward the heading-frame
/// direction `toward`, the pelvis drops by `drop` (the knees bend) and goes back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bend {
    pub lean: f64,
    pub toward: f64,
    pub drop: f64,
}

impl Bend {
    pub const NONE: Bend = Bend { lean: 0.0, toward: 0.0, drop: 0.0 };

    /// This bend `w` of the way (0 upright, 1 all of it).
    pub fn scaled(self, w: f64) -> Bend {
        Bend { lean: w * self.lean, toward: self.toward, drop: w * self.drop }
    }
}

/// The generator's pelvis and chest: where they are and how they are turned.
pub struct Trunk {
    pub pelvis: DVec3,
    pub pelvis_rot: DQuat,
    pub chest: DVec3,
    pub chest_rot: DQuat,
}

/// Highest pelvis height while walking (legs slightly bent), m.
pub const PELVIS_HEIGHT: f64 = 0.905;

impl Trunk {
    /// The trunk of a walker standing at the ground point `root`, facing `yaw`, bent by `bend`.
    pub fn standing(root: DVec3, yaw: f64, bend: Bend) -> Self {
        Self::new(root + DVec3::Z * PELVIS_HEIGHT, yaw, 0.0, bend)
    }

    /// The trunk over the upright pelvis position `pelvis`, facing `yaw`, leaning `walk_lean`
    /// forward into the walk, bent by `bend`.
    pub fn new(pelvis: DVec3, yaw: f64, walk_lean: f64, bend: Bend) -> Self {
        let heading = yaw_quat(yaw);
        let toward = heading * DVec3::new(bend.toward.cos(), bend.toward.sin(), 0.0);
        // The chest leans toward the target; the pelvis and the hips only for its forward part
        // (tilted sideways, the pelvis would cross the thighs).
        let ahead = bend.toward.cos().max(0.0);
        let pelvis = pelvis - DVec3::Z * bend.drop
            + heading * DVec3::new(-HIPS_BACK * ahead * bend.lean.sin() - SQUAT_BACK * bend.drop, 0.0, 0.0);
        let pitch = DQuat::from_axis_angle(heading * DVec3::Y, 0.5 * ahead * bend.lean);
        let pelvis_rot = pitch * heading * DQuat::from_rotation_y(0.5 * walk_lean);
        let chest_rot =
            DQuat::from_axis_angle(DVec3::Z.cross(toward), bend.lean) * heading * DQuat::from_rotation_y(walk_lean);
        let chest = pelvis + pelvis_rot * (offset(body::TORSO) + offset(body::SPINE) + offset(body::CHEST));
        Trunk { pelvis, pelvis_rot, chest, chest_rot }
    }

    /// The shoulder joint of a side (0 left, 1 right).
    pub fn shoulder(&self, side: usize) -> DVec3 {
        let mirror = DVec3::new(1.0, if side == 0 { 1.0 } else { -1.0 }, 1.0);
        self.chest + self.chest_rot * ((offset(body::L_THORAX) + offset(body::L_SHOULDER)) * mirror)
    }
}

/// Steepest forward tilt of a shin in a bend, rad: the ankle bends no further (it would lift
/// the heel or the toe off the ground).
const MAX_SHIN_TILT: f64 = 0.7;

/// Whether the legs hold a bent trunk with the feet planted where an upright walker stands,
/// each `widen` further out: the hips within the legs' reach of the ankles, the shins within
/// [`MAX_SHIN_TILT`].
fn legs_hold(upright: &Trunk, bent: &Trunk, widen: f64) -> bool {
    let (thigh, shin) = (offset(body::L_KNEE).length(), offset(body::L_ANKLE).length());
    let hip = offset(body::L_HIP);
    let ankle_height = ankle_height();
    let forward = upright.pelvis_rot * DVec3::X;
    [1.0, -1.0].into_iter().all(|sign| {
        let side = DVec3::new(0.0, sign * hip.y, 0.0);
        let mut ankle = upright.pelvis + upright.pelvis_rot * DVec3::new(0.0, sign * (hip.y + widen), 0.0);
        ankle.z = ankle_height;
        let hip = bent.pelvis + bent.pelvis_rot * (side + DVec3::Z * hip.z);
        if hip.distance(ankle) > 0.98 * (thigh + shin) {
            return false;
        }
        let knee = knee(hip, ankle, thigh, shin, forward);
        (knee - ankle).normalize().dot(forward).asin() <= MAX_SHIN_TILT
    })
}

/// Upper arm and forearm-with-hand lengths, m (the hand in line with the forearm, as the
/// retargeting leaves the wrist).
fn arm_bones() -> (f64, f64) {
    (offset(body::L_ELBOW).length(), offset(body::L_WRIST).length() + offset(body::L_HAND).length())
}

/// The smallest bend from which the hand of `side` gets to `target`, and by how much it still
/// misses (0 when it does not), searched on a grid of leans and drops that the legs hold.
/// `trunk` builds the trunk for a bend.
pub fn bend_for(target: DVec3, side: usize, trunk: impl Fn(Bend) -> Trunk) -> (Bend, f64) {
    let (upper, lower) = arm_bones();
    let reach = ARM_SHARE * (upper + lower) - ARM_MARGIN;
    let upright = trunk(Bend::NONE);
    let heading_frame = upright.pelvis_rot.conjugate() * (target - upright.pelvis);
    let toward = heading_frame.y.atan2(heading_frame.x);
    let (leans, drops) = (36, 20);
    let mut best = (f64::MAX, f64::MAX, Bend::NONE);
    for i in 0..=leans {
        for j in 0..=drops {
            let bend =
                Bend { lean: MAX_LEAN * i as f64 / leans as f64, toward, drop: MAX_DROP * j as f64 / drops as f64 };
            let bent = trunk(bend);
            if !legs_hold(&upright, &bent, stance_widening(bend.drop)) {
                continue;
            }
            let miss = (bent.shoulder(side).distance(target) - reach).max(0.0);
            let effort = (bend.lean / MAX_LEAN).powi(2) + (bend.drop / MAX_DROP).powi(2);
            if (miss, effort) < (best.0, best.1) {
                best = (miss, effort, bend);
            }
        }
    }
    (best.2, best.0)
}

/// Elbow and wrist of an arm from `shoulder` whose hand is at `hand` (or as near as the arm
/// reaches), the elbow pointing toward `pole`.
pub fn arm(shoulder: DVec3, hand: DVec3, pole: DVec3) -> (DVec3, DVec3) {
    let (upper, lower) = arm_bones();
    let elbow = knee(shoulder, hand, upper, lower, pole);
    let wrist = elbow + (hand - elbow).normalize() * offset(body::L_WRIST).length();
    (elbow, wrist)
}

/// Nearest a moving hand comes to its shoulder, m, unless it starts or ends nearer: a straight
/// line from a swinging hand to a high target passes the shoulder, where the elbow folds and
/// the arm whips round within a frame (9 m/s hands in the first reaching corpus).
const SHOULDER_CLEARANCE: f64 = 0.4;

/// Where a hand is `w` of the way (0-1) from `from` to `to`: along the straight line, pushed
/// out to [`SHOULDER_CLEARANCE`] from the shoulder where the line passes closer.
pub fn hand_path(shoulder: DVec3, from: DVec3, to: DVec3, w: f64) -> DVec3 {
    let r = from.lerp(to, w) - shoulder;
    let least = SHOULDER_CLEARANCE.min(from.distance(shoulder) + w * (to.distance(shoulder) - from.distance(shoulder)));
    if r.length() < least { shoulder + r.normalize_or(DVec3::X) * least } else { shoulder + r }
}
