//! What the humanoid is asked to do, in the world and over time, and the cost that asks it at
//! each control step (re-expressed in that step's character frame).

use crate::adapt::Recent;
use crate::costs::{Heading, Joystick, Pursuit, Reach, Sum};
use crate::obstacles::{Avoid, in_frame, world_detour};
use crate::{ControlError, Layout};
use flowmimic_geom::{CharFrame, DVec3, wrap_angle};
use flowmimic_model::{Label, ModelConfig, TaskLabel};
use flowmimic_sim::Obstacle;
use flowmimic_sim::skeleton::body;
use serde::{Deserialize, Serialize};

/// One piece of a joystick schedule: hold (vx forward, vy left in the character frame, m/s;
/// yaw rate rad/s) for `seconds`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct JoystickSegment {
    pub seconds: f64,
    pub vx: f64,
    pub vy: f64,
    pub yaw_rate: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Hand {
    Left,
    Right,
}

impl Hand {
    pub fn body(self) -> usize {
        match self {
            Hand::Left => body::L_HAND,
            Hand::Right => body::R_HAND,
        }
    }

    /// Where walking up to a target aims the pelvis, relative to the hand's target (x forward,
    /// y left in the current character frame, m). In walking the right hand swings 0.11 m ahead
    /// of the pelvis and 0.22 m to its right (medians of the shipped `fm` model's unguided
    /// walking, 8 environments for 8 s; 0.74-0.85 m high), but the walker closes a gap to the
    /// side only partly before it passes the target: aiming for 0.08 m instead of 0.22 m brought
    /// the hand within 15 cm in 55-70% of reach trials instead of 25-50% (README, Results,
    /// "Walking up to the hand target").
    pub fn aim_offset(self) -> [f64; 2] {
        match self {
            Hand::Left => [0.11, 0.08],
            Hand::Right => [0.11, -0.08],
        }
    }
}

/// A task: any of a joystick schedule, a hand target and a waypoint, each weighted; empty is
/// unguided walking.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Task {
    /// Played in order; the last segment holds after the schedule ends.
    pub joystick: Vec<JoystickSegment>,
    /// A hand and its world-frame target (x, y, height).
    pub reach: Option<(Hand, [f64; 3])>,
    /// A world-frame goal for the pelvis (x, y).
    pub waypoint: Option<[f64; 2]>,
    /// Walk up to the hand target: a pursuit command toward the point [`Hand::aim_offset`] from
    /// it, where the pelvis passes when the hand meets the target, weighted as a waypoint; with
    /// a waypoint too, toward the nearest such point within [`Task::WAYPOINT_RADIUS`] of it.
    #[serde(default)]
    pub approach: bool,
    /// Relative weights of the joystick, heading, reach and waypoint costs.
    pub weights: [f32; 4],
    /// Solid obstacles (world frame): placed in the simulator, kept clear of by the plans
    /// ([`Avoid`], weighted as the waypoint) and walked around by the waypoint's pursuit.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub obstacles: Vec<Obstacle>,
    /// The obstacles are solid but guidance ignores them (the baseline of `eval forest`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub blind: bool,
}

/// Width of the per-step command record: joystick (vx, vy, yaw rate), hand target (x, y, z),
/// waypoint (x, y); zeros for what the task does not ask.
pub const COMMAND_DIM: usize = 8;

impl Task {
    /// What `model` is told the task does at `time`: with task labels, [`Task::task_label`];
    /// with command labels, what it asks of the pelvis ([`Task::pelvis_command`] from `frame`,
    /// shaped by `steer`; nothing asked: not said); without labels, nothing.
    pub fn label(
        &self,
        model: &ModelConfig,
        time: f64,
        frame: &CharFrame,
        steer: Steer,
    ) -> Result<Option<Label>, ControlError> {
        if model.command_labels {
            return Ok(self.pelvis_command(time, frame, steer)?.map(|c| Label::Command(c.map(|v| v as f32))));
        }
        Ok(model.task_labels.then(|| Label::Task(self.task_label())))
    }

    /// What a model with task labels is told: reach with a hand target, walk without.
    pub fn task_label(&self) -> TaskLabel {
        if self.reach.is_some() { TaskLabel::Reach } else { TaskLabel::Walk }
    }

    /// How far from its waypoint the pelvis may stand to bring the hand to its target, when the
    /// task asks both (m; the composition's success radius is 0.5 m).
    pub const WAYPOINT_RADIUS: f64 = 0.4;
    /// Among obstacles, how near (m, from the pelvis) a hand target is before the hand is asked
    /// for it (with `run --task reach --approach` through a post in the way, asked from the
    /// start, 6 of 8 walkers touched it: docs/obstacles.md).
    pub const HAND_NEAR: f64 = 1.5;

    pub fn walk() -> Self {
        Self { weights: [1.0; 4], ..Default::default() }
    }

    /// The paper's joystick evaluation: forward, backward, turn left, turn right, 3 s each.
    pub fn joystick_eval() -> Self {
        let seg = |vx, yaw_rate| JoystickSegment { seconds: 3.0, vx, vy: 0.0, yaw_rate };
        Self { joystick: vec![seg(1.0, 0.0), seg(-0.5, 0.0), seg(0.8, 0.6), seg(0.8, -0.6)], ..Self::walk() }
    }

    /// Checks every number of the task, naming the first bad one.
    pub fn validate(&self) -> Result<(), ControlError> {
        let layout = Layout { horizon: 1 };
        for s in &self.joystick {
            if !(s.seconds.is_finite() && s.seconds > 0.0) {
                return Err(ControlError::BadCommand { what: "joystick segment duration (s)", value: s.seconds });
            }
            Joystick::new(layout, s.vx, s.vy)?;
            Heading::new(layout, s.yaw_rate)?;
        }
        if let Some((_, target)) = self.reach {
            check_world(&target)?;
            if !(0.0..=2.5).contains(&target[2]) {
                return Err(ControlError::BadCommand { what: "hand target height (m, 0-2.5)", value: target[2] });
            }
        }
        if let Some(goal) = self.waypoint {
            check_world(&goal)?;
        }
        if let Some(e) = self.obstacles.iter().find_map(|o| o.validate().err()) {
            return Err(ControlError::Obstacle(e));
        }
        match self.weights.iter().find(|w| !w.is_finite() || **w < 0.0) {
            Some(w) => Err(ControlError::BadCommand { what: "task weight", value: f64::from(*w) }),
            None => Ok(()),
        }
    }

    /// The task carried rigidly from the frame `from` to the frame `to`: its hand target,
    /// waypoint and obstacles (their velocities and turns too) stay where they are relative to
    /// the frame; heights and the joystick, which is in the walker's own frame, do not change.
    pub fn moved(&self, from: &CharFrame, to: &CharFrame) -> Task {
        let carry = |p: [f64; 2]| {
            let w = to.point_to_world(from.point(DVec3::new(p[0], p[1], from.origin.z)));
            [w.x, w.y]
        };
        Task {
            reach: self.reach.map(|(hand, t)| {
                let [x, y] = carry([t[0], t[1]]);
                (hand, [x, y, t[2]])
            }),
            waypoint: self.waypoint.map(carry),
            obstacles: self.obstacles.iter().map(|o| o.carried(from, to)).collect(),
            ..self.clone()
        }
    }

    /// Seconds the joystick schedule lasts (its last segment holds after it).
    pub fn schedule_seconds(&self) -> f64 {
        self.joystick.iter().map(|s| s.seconds).sum()
    }

    /// The joystick segment in force at `time`.
    pub fn joystick_at(&self, time: f64) -> Option<&JoystickSegment> {
        let mut end = 0.0;
        for s in &self.joystick {
            end += s.seconds;
            if time < end {
                return Some(s);
            }
        }
        self.joystick.last()
    }

    /// The command record at `time` (see [`COMMAND_DIM`]).
    pub fn command(&self, time: f64) -> [f32; COMMAND_DIM] {
        let mut c = [0.0; COMMAND_DIM];
        if let Some(s) = self.joystick_at(time) {
            c[..3].copy_from_slice(&[s.vx as f32, s.vy as f32, s.yaw_rate as f32]);
        }
        if let Some((_, t)) = self.reach {
            c[3..6].copy_from_slice(&t.map(|x| x as f32));
        }
        if let Some(g) = self.waypoint {
            c[6..8].copy_from_slice(&g.map(|x| x as f32));
        }
        c
    }

    /// The cost at `time` for a trajectory predicted from the character frame `frame`, its
    /// joystick command shaped by `steer` (the turn asked is the command's rate plus what
    /// catches the heading lag up in [`HeadingHold::CATCH_UP`]); `None` when the task asks
    /// nothing.
    pub fn cost(
        &self,
        layout: Layout,
        time: f64,
        frame: &CharFrame,
        steer: Steer,
    ) -> Result<Option<Sum>, ControlError> {
        let mut sum = Sum::default();
        let [wj, wt, wr, ww] = self.weights;
        if let Some([vx, vy, rate]) = self.joystick_command(time, steer) {
            sum = sum.with(wj, Joystick::turning(layout, vx, vy, rate)?);
            sum = sum.with(wt, Heading::new(layout, rate)?);
        }
        if let Some((hand, target)) = self.reach {
            // Among obstacles the hand's cost would pull the walker straight at its target,
            // through whatever stands between: it waits until the target is near.
            let near = (target[0] - frame.origin.x).hypot(target[1] - frame.origin.y) <= Self::HAND_NEAR;
            if !self.avoids() || near {
                sum = sum.with(wr, Reach::world(layout, hand.body(), target, frame)?);
            }
        }
        if let Some(to) = self.pursuit(frame, time)? {
            sum = sum.with(ww, Joystick::turning(layout, to.speed, to.lateral, to.yaw_rate)?);
            sum = sum.with(ww, Heading::new(layout, to.yaw_rate)?);
        }
        if self.avoids() {
            sum = sum.with(ww * Avoid::WEIGHT, Avoid::new(layout, in_frame(&self.obstacles, frame, time))?);
        }
        Ok((!sum.terms.is_empty()).then_some(sum))
    }

    /// The motion the task asks of the pelvis at `time` (forward, left, m/s; yaw rate, rad/s):
    /// the joystick's, shaped by `steer`, else the pursuit of its waypoint (or of the point
    /// that brings the hand to its target); `None` when it asks neither.
    pub fn pelvis_command(&self, time: f64, frame: &CharFrame, steer: Steer) -> Result<Option<[f64; 3]>, ControlError> {
        if let Some(c) = self.joystick_command(time, steer) {
            return Ok(Some(c));
        }
        Ok(self.pursuit(frame, time)?.map(|to| [to.speed, to.lateral, to.yaw_rate]))
    }

    /// The joystick's command at `time` as guidance asks it: the velocity `steer` ramps, the
    /// turn rate with the heading's lag asked back.
    fn joystick_command(&self, time: f64, steer: Steer) -> Option<[f64; 3]> {
        self.joystick_at(time).map(|s| {
            let rate =
                (s.yaw_rate + steer.heading_lag / HeadingHold::CATCH_UP).clamp(-Heading::MAX_RATE, Heading::MAX_RATE);
            let [vx, vy] = steer.velocity.unwrap_or([s.vx, s.vy]);
            [vx, vy, rate]
        })
    }

    /// The pursuit command toward [`Task::pelvis_goal`], when there is one.
    fn pursuit(&self, frame: &CharFrame, time: f64) -> Result<Option<Pursuit>, ControlError> {
        self.pelvis_goal(frame, time).map(|goal| Pursuit::world(goal, frame)).transpose()
    }

    /// Whether guidance keeps clear of obstacles (there are some, and the task is not blind).
    pub fn avoids(&self) -> bool {
        !self.obstacles.is_empty() && !self.blind
    }

    /// Where the task's pursuit command leads the pelvis (world x, y), seen from the current root
    /// pose `frame` at `time`: the waypoint, or with [`Task::approach`] the point that brings the
    /// hand to its target (within [`Task::WAYPOINT_RADIUS`] of a waypoint), by way of a detour
    /// around the obstacles ([`world_detour`]); `None` when it asks neither.
    pub fn pelvis_goal(&self, frame: &CharFrame, time: f64) -> Option<[f64; 2]> {
        let goal = match (self.reach, self.waypoint) {
            (Some((hand, target)), waypoint) if self.approach => {
                Some(aim_point(hand, [target[0], target[1]], waypoint, frame))
            }
            (_, waypoint) => waypoint,
        }?;
        Some(if self.avoids() { world_detour(goal, &self.obstacles, frame, time) } else { goal })
    }

    /// How far the humanoid's executed motion is from the joystick command at `time`, in the
    /// costs' units (m/s and rad/s, which [`Sum::guidance_grad`] weighs alike): the
    /// root-sum-square of the velocity and yaw-rate errors over the last half second
    /// (`recent`). `None` without a joystick command or before half a second has passed. A hand
    /// target is left out: its distance starts at metres and would double `w` from the first
    /// step (measured: 20% falls at w 20 where the fixed scale has none), and a waypoint is a
    /// command recomputed from the pose at every step already.
    pub fn executed_error(&self, time: f64, recent: &Recent) -> Option<f64> {
        let s = self.joystick_at(time)?;
        let ([vx, vy], yaw_rate) = recent.velocity()?;
        Some(((vx - s.vx).powi(2) + (vy - s.vy).powi(2) + (yaw_rate - s.yaw_rate).powi(2)).sqrt())
    }
}

/// How the controller shapes a joystick command before guidance asks it (the default: as
/// given, the walker on its heading).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Steer {
    /// Radians the walker is behind the joystick's heading ([`HeadingHold::lag`]).
    pub heading_lag: f64,
    /// The velocity asked (forward, left; m/s) in place of the command's ([`SpeedRamp`]).
    pub velocity: Option<[f64; 2]>,
}

/// The joystick velocity asked of guidance, brought up to the command at a bounded
/// acceleration. Asked at once to go from standing to 1.4 m/s, `fm-walks` spun and fell in 19
/// of 40 trials of issue 46's schedule; brought up at 1 m/s^2, in 4 (docs/guidance.md, "A
/// joystick that speeds up gently"). Slowing down is not limited: it is what a walker asked to
/// stop or reverse must do first, and limiting it as well measured no better (5 falls in 40).
#[derive(Clone, Debug, Default)]
pub struct SpeedRamp {
    /// The velocity last asked (forward, left; m/s) and when (s).
    asked: Option<([f64; 2], f64)>,
}

impl SpeedRamp {
    /// The velocity to ask at `time` for the joystick `segment`: each axis moves toward the
    /// command freely between 0 and what was last asked, and at most `acceleration` (m/s^2)
    /// beyond. The first command is asked as given. `None` without a joystick command.
    pub fn velocity(&mut self, segment: Option<&JoystickSegment>, time: f64, acceleration: f64) -> Option<[f64; 2]> {
        let Some(s) = segment else {
            self.asked = None;
            return None;
        };
        let command = [s.vx, s.vy];
        let velocity = match self.asked {
            Some((last, at)) => {
                let most = acceleration * (time - at).max(0.0);
                [0, 1].map(|i| command[i].clamp(last[i].min(0.0) - most, last[i].max(0.0) + most))
            }
            None => command,
        };
        self.asked = Some((velocity, time));
        Some(velocity)
    }
}

/// The heading a joystick command asks for: integrated from the commanded turn rate since the
/// rate last changed, from the walker's heading then. A turn asked of each plan from wherever
/// the walker faces now never undoes what the executed motion drifted: guided walking forward
/// circled left at up to 0.5 rad/s, and a right turn ran at a sixth of its rate (README,
/// "Holding the joystick's heading"). The lag is asked back as a faster turn, not as a heading
/// offset at every predicted step: an offset pulled as hard as a 1.5 rad/s rate error and
/// toppled 2 walkers in 20.
#[derive(Clone, Debug, Default)]
pub struct HeadingHold {
    /// The turn rate held (rad/s), the heading it asks (rad, world) and when it was asked (s).
    held: Option<(f64, f64, f64)>,
}

impl HeadingHold {
    /// The most lag asked back (rad): the heading asked is kept within it of the walker's, so a
    /// walker far behind is asked at most `MAX_LAG / CATCH_UP` rad/s beyond its command.
    pub const MAX_LAG: f64 = 0.5;
    /// Seconds in which a lag is asked back (README, "Holding the joystick's heading": 0.33 s
    /// turned right at -0.55 of -0.6 rad/s and 1 s at -0.29, the velocity RMSE 0.43 and 0.41).
    pub const CATCH_UP: f64 = 0.5;
    /// A change of the commanded rate beyond this (rad/s) starts again from the walker's
    /// heading (a key pressed or let go); within it (a gamepad stick's jitter) the heading is
    /// integrated on.
    pub const NEW_RATE: f64 = 0.05;

    /// How far (rad, positive to the left) a walker facing `heading` (world) at `time` is behind
    /// the heading of its joystick `segment`, within [`HeadingHold::MAX_LAG`]. 0 without a
    /// joystick command.
    pub fn lag(&mut self, segment: Option<&JoystickSegment>, time: f64, heading: f64) -> f64 {
        let rate = match segment {
            Some(s) => s.yaw_rate,
            None => {
                self.held = None;
                return 0.0;
            }
        };
        let lag = match self.held {
            Some((held, asked, at)) if (held - rate).abs() <= Self::NEW_RATE => {
                wrap_angle(asked + rate * (time - at) - heading).clamp(-Self::MAX_LAG, Self::MAX_LAG)
            }
            _ => 0.0,
        };
        self.held = Some((rate, heading + lag, time));
        lag
    }
}

/// Where walking up to `target` aims the pelvis (world x, y): [`Hand::aim_offset`] from it,
/// the walker facing as it does now; with a waypoint, the nearest such point within
/// [`Task::WAYPOINT_RADIUS`] of it.
fn aim_point(hand: Hand, target: [f64; 2], waypoint: Option<[f64; 2]>, frame: &CharFrame) -> [f64; 2] {
    let [x, y] = hand.aim_offset();
    let offset = frame.vector_to_world(DVec3::new(x, y, 0.0));
    let stand = [target[0] - offset.x, target[1] - offset.y];
    let Some(goal) = waypoint else { return stand };
    let (dx, dy) = (stand[0] - goal[0], stand[1] - goal[1]);
    let shrink = (Task::WAYPOINT_RADIUS / dx.hypot(dy)).min(1.0);
    [goal[0] + dx * shrink, goal[1] + dy * shrink]
}

/// World coordinates must be finite and within 10 km.
fn check_world(values: &[f64]) -> Result<(), ControlError> {
    match values.iter().find(|v| !v.is_finite() || v.abs() > 1e4) {
        Some(v) => Err(ControlError::BadCommand { what: "world coordinate (m)", value: *v }),
        None => Ok(()),
    }
}
