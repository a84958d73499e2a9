//! The paper's evaluation protocols, each run through the same controller as `flowmimic run`
//! with all trials batched into one set of environments.

use crate::{HAND_REACHED, composition_success, reach_errors, velocity_rmse};
use flowmimic_control::{
    Adaptive, ControlConfig, ControlError, Hand, JoystickSegment, Rollout, StartActions, Steer, StepReport, Task,
    controller,
};
use flowmimic_geom::{CharFrame, DVec3, wrap_angle};
use flowmimic_model::{Gradient, TrajectoryModel};
use flowmimic_motion::Clip;
use flowmimic_sim::skeleton::body;
use flowmimic_sim::state::offset;
use flowmimic_sim::{CONTROL_HZ, Humanoid, Obstacle};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

/// What every protocol needs: the model, the humanoid and the clip the trials start from.
pub struct Bench<'a> {
    pub model: &'a TrajectoryModel,
    pub humanoid: &'a Arc<Humanoid>,
    pub clip: &'a Clip,
    pub name: &'a str,
    /// Where each protocol run writes its rollout (`None`: nowhere).
    pub rollouts: Option<&'a Path>,
    /// The tracking policy's run that executes the plans (`None`: their own actions), and the
    /// share of its residual added to them.
    pub executor: Option<(&'a Path, f32)>,
}

/// Sampler settings of one evaluated point: the NFE and guidance scale a sweep varies, and how
/// guidance acts, which each model brings ([`crate::sweep::EvalModel::sampler`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub nfe: usize,
    pub scale: f32,
    /// Actions executed per sampled trajectory.
    pub execute: usize,
    pub seed: u64,
    #[serde(default)]
    pub gradient: Gradient,
    /// Guided solver steps `start..end`; `None`: the controller's default.
    #[serde(default)]
    pub guidance_steps: Option<(usize, usize)>,
    /// Adaptive guidance's reference error; `None`: the fixed scale.
    #[serde(default)]
    pub adaptive: Option<Adaptive>,
    /// Share of the executed action taken from inverse dynamics (0: the plan's own).
    #[serde(default)]
    pub inverse_dynamics: f32,
    /// The joystick velocity's most speed-up (m/s^2; 0: the command as given).
    #[serde(default)]
    pub acceleration: f32,
    /// A labelled model's label weight (0: told nothing; 1: as told).
    #[serde(default = "as_told")]
    pub label_scale: f32,
    /// The actions of the history each trial starts with.
    #[serde(default)]
    pub start_actions: StartActions,
    /// With a hand target, walk up to it ([`Task::approach`]) instead of walking on (reach) or
    /// to the waypoint (composition) with the hand's cost alone.
    #[serde(default)]
    pub approach: bool,
}

fn as_told() -> f32 {
    1.0
}

impl Point {
    /// The guidance scale as a table's `w` cell, with a label weight other than as told.
    pub fn w(&self) -> String {
        match self.label_scale {
            1.0 => self.scale.to_string(),
            0.0 => format!("{}, untold", self.scale),
            s => format!("{}, label {s}", self.scale),
        }
    }

    /// The controller's settings for an episode of `seconds` at this point, without kicks.
    pub fn control(&self, seconds: f64) -> ControlConfig {
        ControlConfig {
            gradient: self.gradient,
            adaptive: self.adaptive,
            guidance_steps: self.guidance_steps,
            execute: self.execute,
            inverse_dynamics: self.inverse_dynamics,
            acceleration: self.acceleration,
            label_scale: self.label_scale,
            start_actions: self.start_actions,
            seed: self.seed,
            ..ControlConfig::new(self.nfe, self.scale, seconds)
        }
    }

    /// How guidance acts, for a report: adaptive guidance, inverse dynamics and the start
    /// actions always, and the other settings where they differ from the controller's defaults.
    pub fn describe(&self) -> String {
        let adaptive = self.adaptive.map_or_else(|| "off".into(), |a| a.reference.to_string());
        let mut said = vec![
            format!("adaptive {adaptive}"),
            format!("inverse dynamics {}", self.inverse_dynamics),
            format!("start actions {}", setting_name(&self.start_actions)),
        ];
        if self.gradient != Gradient::default() {
            said.push(format!("gradient {}", setting_name(&self.gradient)));
        }
        if let Some((a, b)) = self.guidance_steps {
            said.push(format!("guidance on solver steps {a} to {}", b.saturating_sub(1)));
        }
        if self.acceleration > 0.0 {
            said.push(format!("acceleration {} m/s²", self.acceleration));
        }
        if self.approach {
            said.push("approach".into());
        }
        said.join(", ")
    }
}

/// A unit enum's name as settings files and flags spell it (`inverse-dynamics`).
pub fn setting_name(value: &impl Serialize) -> String {
    serde_json::to_string(value).expect("json").trim_matches('"').to_string()
}

impl Bench<'_> {
    fn run(
        &self,
        protocol: &str,
        tasks: Vec<Task>,
        point: Point,
        seconds: f64,
        kicks: bool,
        on_step: impl FnMut(&StepReport),
    ) -> Result<Rollout, ControlError> {
        let config = ControlConfig {
            kick_every: if kicks { 1.0 } else { 0.0 },
            kick_max: if kicks { 0.5 } else { 0.0 },
            executor: self.executor.map(|(run, _)| run.to_path_buf()),
            executor_residual: self.executor.map_or(flowmimic_control::executor::DEFAULT_RESIDUAL, |(_, share)| share),
            ..point.control(seconds)
        };
        let r = controller::run(self.model, self.humanoid, self.clip, tasks, &config, self.name, on_step)?;
        if let Some(dir) = self.rollouts {
            let file = format!(
                "{}-{protocol}-nfe{}-w{}-seed{}.rollout.safetensors",
                self.name,
                point.nfe,
                point.w(),
                point.seed
            );
            let saved = std::fs::create_dir_all(dir).map_err(|e| e.to_string());
            if let Err(e) = saved.and_then(|()| r.save(&dir.join(&file)).map_err(|e| e.to_string())) {
                return Err(ControlError::Start(format!("cannot write the rollout {file} in {}: {e}", dir.display())));
            }
            eprintln!("wrote {}", dir.join(&file).display());
        }
        Ok(r)
    }

    /// The world pose (x, y, heading) environment `e` starts from.
    fn start_pose(&self, e: usize) -> CharFrame {
        controller::start_pose(self.clip, self.model.layout().spec.history, e)
    }

    /// A point given in environment `e`'s starting character frame, in the world.
    fn start_to_world(&self, e: usize, local: DVec3) -> DVec3 {
        self.start_pose(e).point_to_world(local)
    }
}

/// Survival (paper Fig. 2): unguided walking with a random planar kick of 0-0.5 m/s every
/// second; control steps until the head falls below 0.2 m, capped at `cap_seconds`.
pub fn survival(
    bench: &Bench,
    point: Point,
    trials: usize,
    cap_seconds: f64,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<usize>, ControlError> {
    let rollout = bench.run("survival", vec![Task::walk(); trials], point, cap_seconds, true, on_step)?;
    Ok(rollout.survived)
}

/// One joystick trial: RMSE of planar velocity (m/s) and yaw rate (rad/s) over the steps
/// before any fall, and what each segment of the schedule achieved.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JoystickTrial {
    pub velocity_rmse: f64,
    pub yaw_rate_rmse: f64,
    /// Per joystick segment: the mean achieved forward and left velocity (m/s, character
    /// frame) and yaw rate (rad/s) from [`SEGMENT_SETTLE`] after the segment's start to its
    /// end, before any fall (NaN when the humanoid fell before).
    pub segments: Vec<[f64; 3]>,
    /// Per joystick segment, over the same steps: what the plans in force asked, the same three
    /// numbers ([`flowmimic_control::Layout::intent`]; NaN where the rollout holds no plans).
    pub planned: Vec<[f64; 3]>,
    /// Per joystick segment: the planar velocity RMSE (m/s) over all its steps before any fall,
    /// the change of gait included (NaN when the humanoid fell before it began).
    pub segment_rmse: Vec<f64>,
    pub fell: bool,
}

/// Seconds of each joystick segment left out of its achieved velocity: the change of gait.
pub const SEGMENT_SETTLE: f64 = 1.0;

/// Joystick: every trial follows `schedule` (the paper's, Fig. 3: forward, backward, turn left,
/// turn right, 3 s each, is [`Task::joystick_eval`]'s).
pub fn joystick(
    bench: &Bench,
    point: Point,
    schedule: &[JoystickSegment],
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<JoystickTrial>, ControlError> {
    let task = Task { joystick: schedule.to_vec(), ..Task::walk() };
    let seconds = task.schedule_seconds();
    let r = bench.run("joystick", vec![task; trials], point, seconds, false, on_step)?;
    Ok((0..trials).map(|e| joystick_trial(&r, e)).collect())
}

/// The achieved yaw rate (rad/s) of each step of environment `e` before any fall.
pub fn yaw_rates(r: &Rollout, e: usize) -> Vec<f64> {
    (0..r.survived[e]).map(|k| wrap_angle(r.heading(e, k + 1) - r.heading(e, k)) * CONTROL_HZ).collect()
}

/// Environment `e`'s mean motion over `steps` (NaN where empty): achieved forward and sideways
/// speed (m/s) and yaw rate (rad/s, from its [`yaw_rates`] `rates`), and what its plans asked.
pub(crate) fn mean_motion(r: &Rollout, e: usize, rates: &[f64], steps: Range<usize>) -> ([f64; 3], [f64; 3]) {
    let n = steps.len() as f64;
    let mean = |v: &dyn Fn(usize) -> f64| steps.clone().map(v).sum::<f64>() / n;
    let velocity = |k: usize, i: usize| f64::from(r.state(e, k + 1)[offset::ROOT_VEL + i]);
    let achieved = [mean(&|k| velocity(k, 0)), mean(&|k| velocity(k, 1)), mean(&|k| rates[k])];
    (achieved, [0, 1, 2].map(|i| mean(&|k| f64::from(r.plan(e, k)[i]))))
}

/// Commanded against achieved velocities of one environment of a rollout.
pub fn joystick_trial(r: &Rollout, e: usize) -> JoystickTrial {
    let steps = r.survived[e];
    let (mut cmd, mut got, mut yaw_err) = (Vec::new(), Vec::new(), 0.0);
    let rates = yaw_rates(r, e);
    for (k, &rate) in rates.iter().enumerate() {
        let c = r.command(e, k);
        let s = r.state(e, k + 1);
        cmd.push([f64::from(c[0]), f64::from(c[1])]);
        got.push([f64::from(s[offset::ROOT_VEL]), f64::from(s[offset::ROOT_VEL + 1])]);
        yaw_err += (rate - f64::from(c[2])).powi(2);
    }
    let (mut start, mut segments, mut planned, mut segment_rmse) = (0.0, Vec::new(), Vec::new(), Vec::new());
    for seg in &r.info.tasks[e].joystick {
        let begin = ((start * CONTROL_HZ).round() as usize).min(steps);
        let from = ((start + SEGMENT_SETTLE) * CONTROL_HZ).round() as usize;
        start += seg.seconds;
        let to = ((start * CONTROL_HZ).round() as usize).min(steps);
        let (achieved, asked) = mean_motion(r, e, &rates, from..to);
        segments.push(achieved);
        planned.push(asked);
        segment_rmse.push(velocity_rmse(&cmd[begin..to.max(begin)], &got[begin..to.max(begin)]));
    }
    JoystickTrial {
        velocity_rmse: velocity_rmse(&cmd, &got),
        yaw_rate_rmse: (yaw_err / steps.max(1) as f64).sqrt(),
        segments,
        planned,
        segment_rmse,
        fell: r.fell(e),
    }
}

/// One reach trial: hand-to-target distances over the trial (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReachTrial {
    pub mean: f64,
    pub rms: f64,
    pub min: f64,
    /// The closest the plans put the hand, at their horizons' end (NaN where the rollout holds
    /// no planned hands): a plan that reaches beside a hand that does not is the execution's
    /// miss, a plan that misses is the model's (or guidance's).
    pub planned_min: f64,
    pub fell: bool,
}

impl ReachTrial {
    /// The distances of `hands` (one position a step) and `planned` (where each step's plan
    /// put the hand) from `target`.
    fn of(hands: &[[f64; 3]], planned: &[[f64; 3]], target: [f64; 3], fell: bool) -> Self {
        let (mean, rms) = reach_errors(hands, &vec![target; hands.len()]);
        let closest = |points: &[[f64; 3]]| points.iter().map(|h| distance(h, &target)).fold(f64::INFINITY, f64::min);
        let planned_min = if planned.iter().any(|p| p[0].is_finite()) { closest(planned) } else { f64::NAN };
        Self { mean, rms, min: closest(hands), planned_min, fell }
    }

    /// The hand came within [`HAND_REACHED`] of the target at some step.
    pub fn reached(&self) -> bool {
        self.min <= HAND_REACHED
    }
}

/// The heights the reach and composition protocols draw their hand targets from (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetHeights {
    pub low: f64,
    pub high: f64,
}

impl TargetHeights {
    /// A target height: uniform in `low..high` (no draw when the range is one height).
    fn draw(&self, rng: &mut StdRng) -> f64 {
        if self.high > self.low { rng.random_range(self.low..self.high) } else { self.low }
    }

    /// The heights for a report: `0.85 m` or `0.7-1 m`.
    pub fn label(&self) -> String {
        if self.high > self.low { format!("{}-{} m", self.low, self.high) } else { format!("{} m", self.low) }
    }
}

/// Reach (paper Fig. 4): right-hand targets drawn 1.5-3 m ahead, up to 0.5 m to either side,
/// at `heights`, of each trial's start; guided reaching while the model walks (up to the
/// target when the point says approach), 4 s.
pub fn reach(
    bench: &Bench,
    point: Point,
    heights: TargetHeights,
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<ReachTrial>, ControlError> {
    let mut rng = StdRng::seed_from_u64(point.seed ^ 0x5EAC);
    let tasks: Vec<Task> = (0..trials)
        .map(|e| {
            let local = DVec3::new(rng.random_range(1.5..3.0), rng.random_range(-0.5..0.5), heights.draw(&mut rng));
            let t = bench.start_to_world(e, local);
            Task { reach: Some((Hand::Right, [t.x, t.y, local.z])), approach: point.approach, ..Task::walk() }
        })
        .collect();
    let r = bench.run("reach", tasks, point, 4.0, false, on_step)?;
    Ok((0..trials).map(|e| reach_trial(&r, e).expect("reach task")).collect())
}

/// How near the hand comes for a standing reach to count (m): closer than walking's
/// [`HAND_REACHED`], since the walker has time to settle on it.
pub const STANDING_REACHED: f64 = 0.10;

/// Targets of a standing reach: heights (m) and how far out from the right shoulder, m
/// (horizontally, from straight ahead to straight out to the side).
pub const STANDING_HEIGHTS: (f64, f64) = (0.5, 1.6);
pub const STANDING_DISTANCES: (f64, f64) = (0.2, 0.65);

/// Below this height (m) a standing reach's target asks the walker to bend: a standing hand
/// hangs at 0.7-0.9 m, and `eval reach --standing` reports these targets apart.
pub const STANDING_LOW: f64 = 0.9;

/// One standing reach: the target's height, the hand's distances, and when it first came within
/// [`STANDING_REACHED`] (s after the start; infinite when it never did).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StandingReachTrial {
    pub height: f64,
    pub reach: ReachTrial,
    pub seconds_to_reach: f64,
}

/// Reaching while standing (the reach issue's protocol): the walker is asked to stand (a zero
/// joystick command) and to bring its right hand to a target [`STANDING_DISTANCES`] out from
/// where its right shoulder starts, ahead to the right side, at `heights`; 4 s. Start from a
/// standing clip: from a walk, the first steps carry the shoulder past the target.
pub fn reach_standing(
    bench: &Bench,
    point: Point,
    heights: (f64, f64),
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<StandingReachTrial>, ControlError> {
    let mut rng = StdRng::seed_from_u64(point.seed ^ 0x57A4D);
    let history = bench.model.layout().spec.history;
    let stand = JoystickSegment { seconds: 4.0, vx: 0.0, vy: 0.0, yaw_rate: 0.0 };
    let tasks: Vec<Task> = (0..trials)
        .map(|e| {
            let start = bench.start_pose(e);
            let frame = controller::start_frame(bench.clip.len(), history, e);
            let shoulder = start.point(bench.clip.bodies[frame].pos[body::R_SHOULDER]);
            let (distance, azimuth) = (
                rng.random_range(STANDING_DISTANCES.0..STANDING_DISTANCES.1),
                rng.random_range(0.0..std::f64::consts::FRAC_PI_2),
            );
            let height = rng.random_range(heights.0..=heights.1);
            let local =
                DVec3::new(shoulder.x + distance * azimuth.cos(), shoulder.y - distance * azimuth.sin(), height);
            let t = start.point_to_world(local);
            Task { joystick: vec![stand], reach: Some((Hand::Right, [t.x, t.y, height])), ..Task::walk() }
        })
        .collect();
    let r = bench.run("reach-standing", tasks, point, 4.0, false, on_step)?;
    Ok((0..trials)
        .map(|e| {
            let path = HandPath::of(&r, e).expect("reach task");
            // Step k + 1 is the first within reach (the hands start at step 1).
            let first = path.hands.iter().position(|h| distance(h, &path.target) <= STANDING_REACHED);
            let seconds_to_reach = first.map_or(f64::INFINITY, |k| (k + 1) as f64 / CONTROL_HZ);
            StandingReachTrial { height: path.target[2], reach: path.trial(r.fell(e)), seconds_to_reach }
        })
        .collect())
}

/// The hand-to-target distances of one environment of a rollout whose task reaches (`None`
/// for a task without a hand target).
pub fn reach_trial(r: &Rollout, e: usize) -> Option<ReachTrial> {
    HandPath::of(r, e).map(|path| path.trial(r.fell(e)))
}

/// The asked hand of one environment: where it is at each step 1..=survived, where the plans in
/// force over steps 0..survived put it, and its target.
struct HandPath {
    hands: Vec<[f64; 3]>,
    planned: Vec<[f64; 3]>,
    target: [f64; 3],
}

impl HandPath {
    /// Environment `e`'s (`None` for a task without a hand target).
    fn of(r: &Rollout, e: usize) -> Option<Self> {
        let (hand, target) = r.info.tasks[e].reach?;
        let hands = (1..=r.survived[e]).map(|k| r.body(e, k, hand.body())).collect();
        let planned = (0..r.survived[e]).map(|k| r.planned_hand(e, k)).collect();
        Some(Self { hands, planned, target })
    }

    fn trial(&self, fell: bool) -> ReachTrial {
        ReachTrial::of(&self.hands, &self.planned, self.target, fell)
    }
}

fn distance(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()
}

/// One waypoint trial: the pelvis's closest approach to the goal, when it first came within
/// 0.5 m (`None`: never), and its distance at the end (whether it stays).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WaypointTrial {
    pub closest: f64,
    pub arrival: Option<f64>,
    pub last: f64,
    pub fell: bool,
}

/// Waypoint navigation (BeyondMimic's task): a goal 3-4 m from each trial's start at a bearing
/// within 90 degrees of its heading, 10 s to walk there; arrival when the pelvis is within
/// 0.5 m of it (the composition's rule).
pub fn waypoint(
    bench: &Bench,
    point: Point,
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<WaypointTrial>, ControlError> {
    let mut rng = StdRng::seed_from_u64(point.seed ^ 0x3A7);
    let tasks: Vec<Task> = (0..trials)
        .map(|e| {
            let (d, bearing) = (rng.random_range(3.0..4.0), rng.random_range(-1.0..1.0) * std::f64::consts::FRAC_PI_2);
            let goal = bench.start_to_world(e, DVec3::new(d * bearing.cos(), d * bearing.sin(), 0.0));
            Task { waypoint: Some([goal.x, goal.y]), ..Task::walk() }
        })
        .collect();
    let r = bench.run("waypoint", tasks, point, 10.0, false, on_step)?;
    Ok((0..trials).map(|e| waypoint_trial(&r, e).expect("waypoint task")).collect())
}

/// The pelvis's way to the goal in one environment of a rollout whose task has a waypoint
/// (`None` for a task without one).
pub fn waypoint_trial(r: &Rollout, e: usize) -> Option<WaypointTrial> {
    let distances = r.pelvis_distances(e, r.info.tasks[e].waypoint?);
    let closest = distances.iter().copied().fold(f64::INFINITY, f64::min);
    let arrival = distances.iter().position(|&d| d <= 0.5).map(|k| (k + 1) as f64 / CONTROL_HZ);
    let last = distances.last().copied().unwrap_or(f64::NAN);
    Some(WaypointTrial { closest, arrival, last, fell: r.fell(e) })
}

/// The forest protocol's two worlds: standing cylinders between the start and the goal, or a
/// few crossing the way.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ForestSetup {
    /// 2-3 cylinders crossing the way at 0.5-1.0 m/s instead of 10-20 standing ones.
    pub moving: bool,
    /// Guidance ignores the obstacles (they stay solid): the baseline.
    pub blind: bool,
}

/// One forest trial: arrival (pelvis within 0.5 m of the goal), control steps touching an
/// obstacle, fall; success is arrival with neither.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ForestTrial {
    pub arrival: Option<f64>,
    pub closest: f64,
    pub contact_steps: usize,
    pub fell: bool,
    pub obstacles: usize,
}

impl ForestTrial {
    pub fn success(&self) -> bool {
        self.arrival.is_some() && self.contact_steps == 0 && !self.fell
    }
}

/// How far (m) from the start and the goal no obstacle stands (centres): the walker starts
/// at walking speed, and turns slowly (at 1.5 m, 30% of the trials touched the first obstacles
/// within 4 s: docs/obstacles.md).
pub const FOREST_CLEAR: f64 = 2.0;

/// How far (m) to either side of the line from the start to the goal the forest reaches.
pub const FOREST_WIDTH: f64 = 4.0;

/// Seconds a forest trial lasts.
pub const FOREST_SECONDS: f64 = 20.0;

/// A forest in the start frame: the goal `distance` m straight ahead and 10-20 cylinders of
/// radius 0.2-0.5 m, centred [`FOREST_CLEAR`] m or more from the start and the goal and within
/// [`FOREST_WIDTH`] of the line between them, every two at least 1 m apart edge to edge (a way through: the
/// walker is 0.5 m wide); or, `moving`, 2-3 cylinders of radius 0.3-0.4 m that cross the line at 0.5-1.0
/// m/s, each where a walker at 0.8 m/s would meet it.
pub fn forest_layout(rng: &mut StdRng, distance: f64, moving: bool) -> Vec<Obstacle> {
    if moving {
        let n = rng.random_range(2..=3);
        return (0..n)
            .map(|i| {
                // Spread along the way, each crossing from a side drawn at random.
                let x = 2.5 + (distance - 5.0) * (f64::from(i) + rng.random_range(0.2..0.8)) / f64::from(n);
                let (speed, side) = (rng.random_range(0.5..1.0), if rng.random_bool(0.5) { 1.0 } else { -1.0 });
                let meet = x / 0.8;
                Obstacle::cylinder([x, side * speed * meet], rng.random_range(0.3..0.4)).moving([0.0, -side * speed])
            })
            .collect();
    }
    let n = rng.random_range(10..=20);
    let mut placed: Vec<Obstacle> = Vec::with_capacity(n);
    for _ in 0..10_000 {
        if placed.len() == n {
            break;
        }
        let c = Obstacle::cylinder(
            [rng.random_range(FOREST_CLEAR..distance - FOREST_CLEAR), rng.random_range(-FOREST_WIDTH..FOREST_WIDTH)],
            rng.random_range(0.2..0.5),
        );
        let apart = placed.iter().all(|o| {
            let gap = (o.at[0] - c.at[0]).hypot(o.at[1] - c.at[1]) - o.bounding_radius() - c.bounding_radius();
            gap >= 1.0
        });
        if apart {
            placed.push(c);
        }
    }
    placed
}

/// The forest (Diffuse-CLoC's test): walk to a goal 8-10 m ahead through [`forest_layout`]'s
/// obstacles in [`FOREST_SECONDS`]; the obstacles are solid MuJoCo geoms.
pub fn forest(
    bench: &Bench,
    point: Point,
    setup: ForestSetup,
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<ForestTrial>, ControlError> {
    let mut rng = StdRng::seed_from_u64(point.seed ^ 0xF0E5);
    let tasks: Vec<Task> = (0..trials)
        .map(|e| {
            let distance = rng.random_range(8.0..10.0);
            let obstacles = forest_layout(&mut rng, distance, setup.moving);
            let local = Task { waypoint: Some([distance, 0.0]), obstacles, blind: setup.blind, ..Task::walk() };
            local.moved(&CharFrame::new(DVec3::ZERO, 0.0), &bench.start_pose(e))
        })
        .collect();
    let name =
        format!("forest{}{}", if setup.moving { "-moving" } else { "" }, if setup.blind { "-blind" } else { "" });
    let r = bench.run(&name, tasks, point, FOREST_SECONDS, false, on_step)?;
    Ok((0..trials)
        .map(|e| {
            let w = waypoint_trial(&r, e).expect("waypoint task");
            let obstacles = r.info.tasks[e].obstacles.len();
            ForestTrial {
                arrival: w.arrival,
                closest: w.closest,
                contact_steps: r.contact_steps(e),
                fell: w.fell,
                obstacles,
            }
        })
        .collect())
}

/// One composition trial: closest approach to the waypoint and the hand target, and success.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ComposeTrial {
    pub pelvis_min: f64,
    pub hand_min: f64,
    pub success: bool,
    pub fell: bool,
}

/// Composition: walk to a waypoint 3-4 m ahead (up to 1.5 m to either side) and touch a
/// target 0.4 m to its right at `heights` with the right hand, within 10 s. Success
/// when, at some step, the pelvis is within 0.5 m of the waypoint and the hand within 0.15 m
/// of the target.
pub fn compose(
    bench: &Bench,
    point: Point,
    heights: TargetHeights,
    trials: usize,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<ComposeTrial>, ControlError> {
    let mut rng = StdRng::seed_from_u64(point.seed ^ 0xC0);
    let tasks: Vec<Task> = (0..trials)
        .map(|e| {
            let (x, y) = (rng.random_range(3.0..4.0), rng.random_range(-1.5..1.5));
            let height = heights.draw(&mut rng);
            let goal = bench.start_to_world(e, DVec3::new(x, y, 0.0));
            let hand = bench.start_to_world(e, DVec3::new(x, y - 0.4, height));
            let reach = Some((Hand::Right, [hand.x, hand.y, height]));
            Task { waypoint: Some([goal.x, goal.y]), reach, approach: point.approach, ..Task::walk() }
        })
        .collect();
    let r = bench.run("compose", tasks, point, 10.0, false, on_step)?;
    Ok((0..trials)
        .map(|e| {
            let task = &r.info.tasks[e];
            let (goal, target) = (task.waypoint.expect("waypoint"), task.reach.expect("reach").1);
            let (mut pelvis_min, mut hand_min, mut success) = (f64::INFINITY, f64::INFINITY, false);
            for (k, d_pelvis) in (1..).zip(r.pelvis_distances(e, goal)) {
                let d_hand = distance(&r.body(e, k, body::R_HAND), &target);
                pelvis_min = pelvis_min.min(d_pelvis);
                hand_min = hand_min.min(d_hand);
                success |= composition_success(d_pelvis, d_hand);
            }
            ComposeTrial { pelvis_min, hand_min, success, fell: r.fell(e) }
        })
        .collect())
}

/// Motion-quality features of one state (documented in the README): root height, root
/// velocity (3, character frame), and the positions relative to the root of the head, both
/// hands and both feet (15): 19 numbers that describe posture and gait.
pub fn quality_features(state: &[f32]) -> Vec<f64> {
    let mut f = vec![f64::from(state[offset::ROOT_POS + 2])];
    f.extend((0..3).map(|i| f64::from(state[offset::ROOT_VEL + i])));
    for b in [body::HEAD, body::L_HAND, body::R_HAND, body::L_ANKLE, body::R_ANKLE] {
        f.extend((0..3).map(|i| f64::from(state[offset::BODY_POS + 3 * b + i])));
    }
    f
}

/// Features of every state of unguided walking before any fall (`trials` x `seconds`).
pub fn generated_features(
    bench: &Bench,
    point: Point,
    trials: usize,
    seconds: f64,
    on_step: impl FnMut(&StepReport),
) -> Result<Vec<Vec<f64>>, ControlError> {
    let r = bench.run("quality", vec![Task::walk(); trials], point, seconds, false, on_step)?;
    Ok((0..trials)
        .flat_map(|e| (1..=r.survived[e]).map(move |k| (e, k)))
        .map(|(e, k)| quality_features(r.state(e, k)))
        .collect())
}

/// Median model and physics milliseconds per control step, one environment walking: unguided,
/// or with a guidance scale, on the joystick protocol's schedule (the cost gradient, through the
/// network when the point says so, included in the model's time).
pub fn latency(bench: &Bench, point: Point, seconds: f64) -> Result<(f64, f64), ControlError> {
    let task = if point.scale > 0.0 { Task::joystick_eval() } else { Task::walk() };
    let r = bench.run("latency", vec![task], point, seconds, false, |_| {})?;
    let (model_ms, physics_ms) = r.median_ms();
    Ok((f64::from(model_ms), f64::from(physics_ms)))
}

/// How far guidance moves what is executed, measured on the model's output alone (no
/// physics): for `samples` conditionings from the start clip, the same noise sampled unguided
/// and guided; `first_action` is the mean absolute change of the executed action `a_t`,
/// `later_actions` that of `a_{t+1} .. a_{t+H}` (normalised action units), and the task's
/// error (m/s, rad or m) before and after. The task's hand target and waypoint are given in
/// each start's character frame (x ahead, y left, z height).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GuidanceEffect {
    pub first_action: f64,
    pub later_actions: f64,
    pub error_unguided: f64,
    pub error_guided: f64,
}

pub fn guidance_effect(
    bench: &Bench,
    task: &Task,
    point: Point,
    samples: usize,
) -> Result<GuidanceEffect, ControlError> {
    use flowmimic_control::{Cost, History, Layout};
    use flowmimic_geom::CharFrame;
    use flowmimic_model::TaskGuidance;
    let steps = point.guidance_steps.unwrap_or(controller::default_guidance_steps(point.nfe));
    controller::check_guidance_steps(steps, point.nfe)?;
    let layout = bench.model.layout();
    let traj = Layout { horizon: layout.spec.horizon };
    let (mut cond, mut costs) = (Vec::new(), Vec::new());
    for e in 0..samples {
        let mut env = bench.humanoid.env();
        let mut history = History::new(layout.spec);
        let frame = controller::start_frame(bench.clip.len(), layout.spec.history, e);
        controller::start_from_clip(&mut env, &mut history, bench.clip, frame, bench.model, point.start_actions)?;
        let mut task = task.clone();
        if let Some((_, target)) = task.reach.as_mut() {
            let t = bench.start_to_world(e, DVec3::from_array(*target));
            *target = [t.x, t.y, target[2]];
        }
        if let Some(goal) = task.waypoint.as_mut() {
            let g = bench.start_to_world(e, DVec3::new(goal[0], goal[1], 0.0));
            *goal = [g.x, g.y];
        }
        let b = env.bodies();
        let frame = CharFrame::from_root(b.pos[0], b.rot[0]);
        // The command has just begun: the walker is on its heading.
        let label = task.label(&bench.model.config, 0.0, &frame, Steer::default())?;
        let (states, actions) = history.conditioning();
        cond.extend(layout.conditioning(&states, &actions, label));
        let cost = task.cost(traj, 0.0, &frame, Steer::default())?;
        costs.push(Some(cost.ok_or(ControlError::Start("the task asks nothing to guide".into()))?));
    }
    let (len, std) = (traj.len(), &bench.model.norm.std[layout.cond_len()..]);
    let grad = |x: &[f32], n: usize| flowmimic_control::costs::batch_guidance_grad(&costs, std, x, n);
    let nfe = point.nfe;
    let guidance = TaskGuidance { weight: point.scale, grad: &grad, steps: steps.0..steps.1, gradient: point.gradient };
    let unguided = bench.model.sample(&cond, samples, nfe, None, &mut StdRng::seed_from_u64(point.seed));
    let guided = bench.model.sample(&cond, samples, nfe, Some(&guidance), &mut StdRng::seed_from_u64(point.seed));
    let change = |k: usize| -> f64 {
        let at = traj.action(k);
        let sum: f32 = (0..samples)
            .flat_map(|i| (0..flowmimic_sim::NUM_DOFS).map(move |j| i * len + at + j))
            .map(|j| (guided[j].clamp(-1.0, 1.0) - unguided[j].clamp(-1.0, 1.0)).abs())
            .sum();
        f64::from(sum) / (samples * flowmimic_sim::NUM_DOFS) as f64
    };
    let error = |x: &[f32]| -> f64 {
        costs.iter().flatten().enumerate().map(|(i, c)| f64::from(c.error(&x[i * len..(i + 1) * len]))).sum::<f64>()
            / samples as f64
    };
    let h = traj.horizon;
    Ok(GuidanceEffect {
        first_action: change(0),
        later_actions: (1..=h).map(change).sum::<f64>() / h as f64,
        error_unguided: error(&unguided),
        error_guided: error(&guided),
    })
}
