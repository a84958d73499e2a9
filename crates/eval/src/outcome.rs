//! What a rollout achieved for its task, environment by environment: each joystick segment's
//! achieved speeds against the asked ones (and in how many environments it was followed), the
//! hand's closest approach to its target, the pelvis's way to its goal, obstacles touched, and
//! for each environment that fell, what it was doing against what its plans asked. `flowmimic run` prints
//! it after a run and `flowmimic eval outcome` for a saved rollout, so that one failing segment
//! or environment cannot hide behind an average.

use crate::protocols::{
    JoystickTrial, ReachTrial, SEGMENT_SETTLE, WaypointTrial, joystick_trial, mean_motion, reach_trial, waypoint_trial,
    yaw_rates,
};
use flowmimic_control::Rollout;
use flowmimic_sim::CONTROL_HZ;

/// How close a followed segment comes to its command over its settled part: forward and
/// sideways speed within 0.25 m/s, yaw rate within 0.25 rad/s.
pub const FOLLOWED_SPEED: f64 = 0.25;
pub const FOLLOWED_YAW_RATE: f64 = 0.25;

/// One joystick segment over the environments that were asked it.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    /// Asked forward and sideways speed (m/s) and yaw rate (rad/s).
    pub asked: [f64; 3],
    /// Achieved, per environment, over the segment after [`crate::protocols::SEGMENT_SETTLE`].
    pub achieved: Vec<[f64; 3]>,
    /// What the plans asked, per environment, over the same steps (NaN: no plans recorded).
    pub planned: Vec<[f64; 3]>,
    /// Environments within [`FOLLOWED_SPEED`] and [`FOLLOWED_YAW_RATE`] of the command that did
    /// not fall.
    pub followed: usize,
}

/// How long before a fall the body's motion is read, and where the reading stops: the last
/// half second is the falling itself.
pub const BEFORE_FALL: (f64, f64) = (1.5, 0.5);

/// An environment that fell: when, and over [`BEFORE_FALL`] what the body did against what its
/// plans asked (forward and sideways m/s, yaw rate rad/s, as a segment's). A plan asking less
/// than the body does is a stop (or turn) the executed actions did not carry out.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fall {
    pub env: usize,
    pub seconds: f64,
    pub achieved: [f64; 3],
    /// NaN where the rollout recorded no plans.
    pub planned: [f64; 3],
}

/// A rollout's outcome.
#[derive(Clone, Debug, PartialEq)]
pub struct Outcome {
    pub envs: usize,
    pub falls: Vec<Fall>,
    /// The first environment's joystick schedule, segment by segment, over every environment
    /// given the same schedule (empty when there is none), up to the last one the rollout
    /// reaches past its settling time.
    pub segments: Vec<Segment>,
    /// Segments of the schedule the rollout ended before reaching.
    pub unreached_segments: usize,
    /// Per environment with a hand target, and with a waypoint.
    pub reach: Vec<ReachTrial>,
    pub waypoint: Vec<WaypointTrial>,
    /// Control steps each environment touched an obstacle (`None`: no task has obstacles).
    pub touched: Option<Vec<usize>>,
}

/// Whether an achieved segment follows its command.
pub fn followed(asked: [f64; 3], achieved: [f64; 3]) -> bool {
    (achieved[0] - asked[0]).abs() <= FOLLOWED_SPEED
        && (achieved[1] - asked[1]).abs() <= FOLLOWED_SPEED
        && (achieved[2] - asked[2]).abs() <= FOLLOWED_YAW_RATE
}

impl Outcome {
    pub fn of(r: &Rollout) -> Self {
        let schedule = &r.info.tasks[0].joystick;
        let same: Vec<usize> = (0..r.envs).filter(|&e| &r.info.tasks[e].joystick == schedule).collect();
        let trials: Vec<JoystickTrial> = same.iter().map(|&e| joystick_trial(r, e)).collect();
        let mut start = 0.0;
        let reached = schedule
            .iter()
            .take_while(|s| {
                let from = ((start + SEGMENT_SETTLE) * CONTROL_HZ).round() as usize;
                start += s.seconds;
                from < r.steps
            })
            .count();
        let segments: Vec<Segment> = schedule[..reached]
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let asked = [s.vx, s.vy, s.yaw_rate];
                let achieved: Vec<[f64; 3]> = trials.iter().map(|t| t.segments[i]).collect();
                let planned: Vec<[f64; 3]> = trials.iter().map(|t| t.planned[i]).collect();
                let followed = trials.iter().filter(|t| !t.fell && followed(asked, t.segments[i])).count();
                Segment { asked, achieved, planned, followed }
            })
            .collect();
        Self {
            envs: r.envs,
            falls: (0..r.envs).filter(|&e| r.fell(e)).map(|e| fall(r, e)).collect(),
            unreached_segments: schedule.len() - reached,
            segments,
            reach: (0..r.envs).filter_map(|e| reach_trial(r, e)).collect(),
            waypoint: (0..r.envs).filter_map(|e| waypoint_trial(r, e)).collect(),
            touched: r
                .info
                .tasks
                .iter()
                .any(|t| !t.obstacles.is_empty())
                .then(|| (0..r.envs).map(|e| r.contact_steps(e)).collect()),
        }
    }
}

/// Environment `e`'s fall (it fell).
fn fall(r: &Rollout, e: usize) -> Fall {
    let steps = r.survived[e];
    let step = |seconds: f64| steps.saturating_sub((seconds * CONTROL_HZ).round() as usize);
    let from = step(BEFORE_FALL.0);
    let to = step(BEFORE_FALL.1).max(from + 1).min(steps);
    let (achieved, planned) = mean_motion(r, e, &yaw_rates(r, e), from..to);
    Fall { env: e, seconds: steps as f64 / CONTROL_HZ, achieved, planned }
}
