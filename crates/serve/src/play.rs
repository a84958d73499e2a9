//! `flowmimic play`: the guided controller paced at 30 Hz, steered live from a browser.
//!
//! One simulation thread owns the model and the humanoid. At each control step it reads the
//! latest inputs (behind a mutex), steps the [`Controller`], and publishes the frame on a
//! watch channel, which holds only the newest: a slow page skips frames, it never queues them
//! or slows the loop. Each WebSocket client is its own task that forwards frames and applies
//! commands; a client that leaves, or sends nonsense, never stops the session.
//!
//! The protocol, JSON text messages over `/ws` (at most [`MAX_MESSAGE`] bytes each):
//!
//! | from the page | meaning |
//! |---|---|
//! | `{"type":"drive","vx":1,"vy":0,"yaw_rate":0,"seq":7}` | joystick: m/s in the character frame (x forward, y left), rad/s, all zero for none; `seq` is echoed as `applied` |
//! | `{"type":"waypoint","at":[x,y]}` / `"at":null` | walk to a world point / stop |
//! | `{"type":"hand","hand":"right","target":[x,y,z]}` / `"target":null` | reach / stop |
//! | `{"type":"sampler","scale":10,"nfe":5}` | guidance scale and solver steps; `"inverse_dynamics":0.2` also sets the share of inverse dynamics in the executed action (a model with one) |
//! | `{"type":"push"}`, `{"type":"reset"}`, `{"type":"record"}` | a random kick of the kick protocol's size; restart; start or stop recording |
//!
//! | from the server | meaning |
//! |---|---|
//! | `hello` | model, body names and parents, control rate, horizon, sampler (`inverse_dynamics` null for a model without it) |
//! | `frame` | every control step: body positions (world), predicted pelvis path, command in force and the `seq` it came with, achieved velocity, milliseconds of model and physics, achieved rate, fall, recording |
//! | `notice` | a recording was written, or the controller stopped (and why) |
//! | `error` | the last message was refused, and why (the session goes on) |

use crate::ServeError;
use axum::Router;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::response::{Html, Response};
use axum::routing::get;
use flowmimic_control::controller::start_frame;
use flowmimic_control::{ControlConfig, Controller, Hand, JoystickSegment, Layout, Rollout, RolloutInfo, Row, Task};
use flowmimic_geom::{CharFrame, DVec3, heading, wrap_angle};
use flowmimic_model::TrajectoryModel;
use flowmimic_motion::Clip;
use flowmimic_sim::skeleton::BODY_PARENTS;
use flowmimic_sim::state::offset;
use flowmimic_sim::{BODY_NAMES, CONTROL_HZ, Humanoid, Obstacle};
use futures_util::{SinkExt, StreamExt};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio::sync::{broadcast, watch};

const PAGE: &str = include_str!("play.html");

/// Largest message the protocol reads, bytes: a longer one is answered with an error.
pub const MAX_MESSAGE: usize = 4096;
/// Largest message the socket accepts at all: past it the connection (only) is closed.
const MAX_TRANSPORT: usize = 64 * 1024;
/// Time a client may take to accept one frame before it is dropped.
const SEND_TIMEOUT: Duration = Duration::from_secs(5);
/// Control steps the reported yaw rate is averaged over (half a second).
const YAW_RATE_STEPS: usize = 15;
/// The push button's kick: a uniform planar speed up to this (the kick protocol's size).
const PUSH_MAX: f64 = 0.5;
/// Radius of a dropped obstacle (m), and the most the page may drop (each one compiles the
/// world anew: milliseconds).
pub const OBSTACLE_RADIUS: f64 = 0.3;
const MAX_OBSTACLES: usize = 32;

/// What `flowmimic play` runs.
pub struct PlayConfig {
    /// Sampler settings (NFE, guidance scale and gradient); the page may change NFE and scale.
    pub control: ControlConfig,
    /// Where the record button writes its rollouts.
    pub record_dir: PathBuf,
    /// The model's name in the page and in recordings.
    pub model_name: String,
}

/// A message from the page.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Command {
    Drive {
        vx: f64,
        vy: f64,
        yaw_rate: f64,
        #[serde(default)]
        seq: u64,
    },
    Waypoint {
        at: Option<[f64; 2]>,
    },
    Hand {
        hand: Hand,
        target: Option<[f64; 3]>,
    },
    /// Drops a cylinder ([`OBSTACLE_RADIUS`]) on the ground at `at`; `None` clears them all.
    Obstacle {
        at: Option<[f64; 2]>,
    },
    Sampler {
        scale: f32,
        nfe: usize,
        /// `None`: unchanged.
        #[serde(default)]
        inverse_dynamics: Option<f32>,
    },
    Push,
    Reset,
    Record,
}

/// What the page asks, as the simulation thread reads it at each step.
#[derive(Clone, Debug)]
struct Inputs {
    drive: [f64; 3],
    seq: u64,
    waypoint: Option<[f64; 2]>,
    reach: Option<(Hand, [f64; 3])>,
    obstacles: Vec<Obstacle>,
    scale: f32,
    nfe: usize,
    /// Share of inverse dynamics in the executed action; `None`: the model has none.
    inverse_dynamics: Option<f32>,
    push: bool,
    reset: bool,
    record: bool,
}

impl Inputs {
    /// The task in force; a zero joystick asks nothing (the model walks as it likes, or walks
    /// up to a hand target when there is one).
    fn task(&self) -> Task {
        let [vx, vy, yaw_rate] = self.drive;
        let held = JoystickSegment { seconds: 1.0, vx, vy, yaw_rate };
        let idle = self.drive == [0.0; 3];
        Task {
            joystick: if idle { Vec::new() } else { vec![held] },
            reach: self.reach,
            waypoint: self.waypoint,
            approach: idle,
            obstacles: self.obstacles.clone(),
            ..Task::walk()
        }
    }

    /// Applies `command` if the result is a task the controller accepts; otherwise says why.
    fn apply(&mut self, command: Command) -> Result<(), String> {
        let mut next = self.clone();
        match command {
            Command::Drive { vx, vy, yaw_rate, seq } => (next.drive, next.seq) = ([vx, vy, yaw_rate], seq),
            Command::Waypoint { at } => next.waypoint = at,
            Command::Hand { hand, target } => next.reach = target.map(|t| (hand, t)),
            Command::Obstacle { at: Some(at) } if next.obstacles.len() >= MAX_OBSTACLES => {
                return Err(format!("at most {MAX_OBSTACLES} obstacles (at {at:?}): clear them first"));
            }
            Command::Obstacle { at: Some(at) } => next.obstacles.push(Obstacle::cylinder(at, OBSTACLE_RADIUS)),
            Command::Obstacle { at: None } => next.obstacles.clear(),
            Command::Sampler { scale, nfe, inverse_dynamics } => {
                if !(scale.is_finite() && (0.0..=1000.0).contains(&scale)) {
                    return Err(format!("guidance scale must be 0-1000, not {scale}"));
                }
                if !(1..=50).contains(&nfe) {
                    return Err(format!("NFE must be 1-50, not {nfe}"));
                }
                (next.scale, next.nfe) = (scale, nfe);
                if let Some(beta) = inverse_dynamics {
                    if next.inverse_dynamics.is_none() {
                        return Err("this model has no inverse dynamics (`flowmimic inverse`)".into());
                    }
                    if !(0.0..=1.0).contains(&beta) {
                        return Err(format!("inverse-dynamics share must be 0-1, not {beta}"));
                    }
                    next.inverse_dynamics = Some(beta);
                }
            }
            Command::Push => next.push = true,
            Command::Reset => next.reset = true,
            Command::Record => next.record = true,
        }
        next.task().validate().map_err(|e| e.to_string())?;
        *self = next;
        Ok(())
    }
}

/// What the server sends.
#[derive(Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
enum Outgoing {
    Hello {
        model: String,
        names: Vec<&'static str>,
        parents: Vec<i64>,
        hz: f64,
        horizon: usize,
        scale: f32,
        nfe: usize,
        inverse_dynamics: Option<f32>,
    },
    Frame(Frame),
    Notice {
        message: String,
    },
    Error {
        message: String,
    },
}

/// One control step, as the page draws it.
#[derive(Serialize)]
struct Frame {
    step: usize,
    /// Seconds since the last reset.
    time: f64,
    /// World positions of the 24 bodies.
    bodies: Vec<[f32; 3]>,
    /// The predicted pelvis path (world), H steps ahead.
    plan: Vec<[f32; 3]>,
    /// The joystick command in force (vx, vy, yaw rate) and the `seq` it came with.
    command: [f32; 3],
    applied: u64,
    waypoint: Option<[f64; 2]>,
    reach: Option<(Hand, [f64; 3])>,
    obstacles: Vec<Obstacle>,
    /// Whether the humanoid touched an obstacle in this step.
    touching: bool,
    /// Achieved root velocity in the character frame (forward, left; m/s) and yaw rate over the
    /// last half second (rad/s).
    velocity: [f32; 3],
    scale: f32,
    nfe: usize,
    inverse_dynamics: Option<f32>,
    model_ms: f32,
    physics_ms: f32,
    /// Control steps per second of wall time, over the last second.
    rate: f32,
    fell: bool,
    recording: bool,
}

fn text(message: &Outgoing) -> Arc<str> {
    serde_json::to_string(message).expect("serialisable").into()
}

/// The live session: the simulation thread's inputs and outputs.
#[derive(Clone)]
pub struct Session {
    inputs: Arc<Mutex<Inputs>>,
    frames: watch::Receiver<Arc<str>>,
    notices: broadcast::Sender<Arc<str>>,
    hello: Arc<str>,
}

impl Session {
    /// Starts the simulation thread: the humanoid at a frame of `clip`, walking unguided until
    /// the page asks otherwise.
    pub fn start(
        model: TrajectoryModel,
        humanoid: Arc<Humanoid>,
        clip: Clip,
        config: PlayConfig,
    ) -> Result<Self, ServeError> {
        // Fail here, not in the thread, on a model or clip that cannot start.
        Controller::new(&model, &humanoid, &clip, 1, &config.control)?;
        let inputs = Inputs {
            drive: [0.0; 3],
            seq: 0,
            waypoint: None,
            reach: None,
            obstacles: Vec::new(),
            scale: config.control.guidance_scale,
            nfe: config.control.nfe,
            inverse_dynamics: model.inverse.is_some().then_some(config.control.inverse_dynamics),
            push: false,
            reset: false,
            record: false,
        };
        let hello = text(&Outgoing::Hello {
            model: config.model_name.clone(),
            names: BODY_NAMES.to_vec(),
            parents: BODY_PARENTS.iter().map(|p| p.map_or(-1, |p| p as i64)).collect(),
            hz: CONTROL_HZ,
            horizon: model.layout().spec.horizon,
            scale: inputs.scale,
            nfe: inputs.nfe,
            inverse_dynamics: inputs.inverse_dynamics,
        });
        let inputs = Arc::new(Mutex::new(inputs));
        let (frame_tx, frames) = watch::channel(Arc::from(""));
        let (notices, _) = broadcast::channel(16);
        let session = Self { inputs: Arc::clone(&inputs), frames, notices: notices.clone(), hello };
        std::thread::Builder::new().name("play".into()).spawn(move || {
            let mut sim = Simulation { model: &model, humanoid, clip, config, inputs, frames: frame_tx, notices };
            sim.run();
        })?;
        Ok(session)
    }

    /// The routes: the page at `/`, the WebSocket at `/ws`.
    pub fn router(self) -> Router {
        Router::new().route("/", get(|| async { Html(PAGE) })).route("/ws", get(upgrade)).with_state(self)
    }

    /// Parses and applies one message from a page; the error is what to tell it.
    pub fn handle(&self, message: &str) -> Result<(), String> {
        if message.len() > MAX_MESSAGE {
            return Err(format!("message of {} bytes: the limit is {MAX_MESSAGE}", message.len()));
        }
        let command: Command = serde_json::from_str(message).map_err(|e| format!("bad message: {e}"))?;
        self.inputs.lock().expect("inputs").apply(command)
    }
}

async fn upgrade(ws: WebSocketUpgrade, State(session): State<Session>) -> Response {
    ws.max_message_size(MAX_TRANSPORT).max_frame_size(MAX_TRANSPORT).on_upgrade(move |socket| client(socket, session))
}

/// One page's connection: frames out (the newest only), commands in, until it leaves.
async fn client(socket: WebSocket, session: Session) {
    let (mut out, mut incoming) = socket.split();
    let (mut frames, mut notices) = (session.frames.clone(), session.notices.subscribe());
    let send = |text: Arc<str>| Message::Text(text.to_string().into());
    if out.send(send(Arc::clone(&session.hello))).await.is_err() {
        return;
    }
    loop {
        let reply = tokio::select! {
            changed = frames.changed() => match changed {
                Ok(()) => Some(frames.borrow_and_update().clone()),
                Err(_) => break,
            },
            notice = notices.recv() => match notice {
                Ok(text) => Some(text),
                Err(broadcast::error::RecvError::Lagged(_)) => None,
                Err(broadcast::error::RecvError::Closed) => break,
            },
            message = incoming.next() => match message {
                Some(Ok(Message::Text(t))) => {
                    session.handle(t.as_str()).err().map(|message| text(&Outgoing::Error { message }))
                }
                Some(Ok(Message::Binary(_))) => {
                    Some(text(&Outgoing::Error { message: "binary messages are not part of the protocol".into() }))
                }
                Some(Ok(Message::Close(_))) | Some(Err(_)) | None => break,
                Some(Ok(_)) => None,
            },
        };
        if let Some(reply) = reply {
            match tokio::time::timeout(SEND_TIMEOUT, out.send(send(reply))).await {
                Ok(Ok(())) => {}
                _ => break,
            }
        }
    }
}

/// The simulation thread's state.
struct Simulation<'m> {
    model: &'m TrajectoryModel,
    humanoid: Arc<Humanoid>,
    clip: Clip,
    config: PlayConfig,
    inputs: Arc<Mutex<Inputs>>,
    frames: watch::Sender<Arc<str>>,
    notices: broadcast::Sender<Arc<str>>,
}

/// One recorded step's action, the command in force, what the plan asked and whether the
/// humanoid touched an obstacle.
struct Acted {
    action: Vec<f32>,
    command: [f32; flowmimic_control::task::COMMAND_DIM],
    plan: [f32; 3],
    /// Where the plan put the task's hand (with a hand target).
    plan_hand: Option<[f64; 3]>,
    touched: bool,
}

/// Steps recorded since the record button, written as a one-environment rollout.
struct Recording {
    started: SystemTime,
    task: Task,
    /// The sampler in force when recording started (the page may change it later).
    sampler: ControlConfig,
    rows: Vec<Row>,
    /// Per step, what was executed.
    actions: Vec<Acted>,
    model_ms: Vec<f32>,
    physics_ms: Vec<f32>,
}

impl Simulation<'_> {
    fn notice(&self, message: String) {
        let _ = self.notices.send(text(&Outgoing::Notice { message }));
    }

    fn run(&mut self) {
        let model = self.model;
        let mut controller =
            Controller::new(model, &self.humanoid, &self.clip, 1, &self.config.control).expect("checked at start");
        let start = start_frame(self.clip.len(), model.layout().spec.history, 0);
        let traj = Layout { horizon: model.layout().spec.horizon };
        let period = Duration::from_secs_f64(1.0 / CONTROL_HZ);
        let mut rng = rand::rngs::StdRng::seed_from_u64(self.config.control.seed);
        let (mut time, mut stopped, mut recording) = (0.0, None::<String>, None::<Recording>);
        let mut placed: Vec<Obstacle> = Vec::new();
        let mut step_starts = std::collections::VecDeque::new();
        // Headings of the last half second: the yaw rate over it (a step's own swings with the gait).
        let mut headings = std::collections::VecDeque::new();
        let mut next_tick = Instant::now();
        loop {
            let inputs = {
                let mut shared = self.inputs.lock().expect("inputs");
                let now = shared.clone();
                (shared.push, shared.reset, shared.record) = (false, false, false);
                now
            };
            let mut sampler = controller.config().clone();
            (sampler.guidance_scale, sampler.nfe) = (inputs.scale, inputs.nfe);
            sampler.inverse_dynamics = inputs.inverse_dynamics.unwrap_or(0.0);
            if sampler != *controller.config() {
                controller.set_config(sampler).expect("validated when received");
            }
            if inputs.reset {
                match controller.restart(0, &self.clip, start) {
                    Ok(()) => (time, stopped) = (0.0, None),
                    Err(e) => self.notice(format!("reset failed: {e}")),
                }
                headings.clear();
            }
            if inputs.push {
                let (speed, angle) = (rng.random_range(0.0..=PUSH_MAX), rng.random_range(0.0..std::f64::consts::TAU));
                if let Err(e) = controller.kick(0, [speed * angle.cos(), speed * angle.sin()]) {
                    self.notice(format!("push failed: {e}"));
                }
            }
            if inputs.record {
                match recording.take() {
                    Some(r) => self.save(r),
                    None => {
                        recording = Some(Recording {
                            started: SystemTime::now(),
                            task: inputs.task(),
                            sampler: controller.config().clone(),
                            rows: vec![Row::of(controller.env(0))],
                            actions: Vec::new(),
                            model_ms: Vec::new(),
                            physics_ms: Vec::new(),
                        })
                    }
                }
            }
            if inputs.obstacles != placed {
                match controller.place_obstacles(0, &inputs.obstacles) {
                    Ok(()) => placed = inputs.obstacles.clone(),
                    Err(e) => self.notice(format!("obstacles not placed: {e}")),
                }
            }
            let bodies = controller.env(0).bodies();
            let planned_from = CharFrame::from_root(bodies.pos[0], bodies.rot[0]);
            let task = inputs.task();
            let (mut model_ms, mut physics_ms) = (0.0, 0.0);
            if controller.is_alive(0) && stopped.is_none() {
                match controller.step(std::slice::from_ref(&task), time) {
                    Ok(outcome) => {
                        (model_ms, physics_ms) = (outcome.model_ms, outcome.physics_ms);
                        if let (Some(r), Some(a)) = (recording.as_mut(), &outcome.actions[0]) {
                            r.actions.push(Acted {
                                action: a.clone(),
                                command: task.command(time),
                                plan: controller.intent(0).expect("acted on a plan"),
                                plan_hand: task
                                    .reach
                                    .and_then(|(hand, _)| controller.planned_body(0, hand.body()))
                                    .map(|p| p.to_array()),
                                touched: controller.env(0).touching_obstacle(),
                            });
                            r.rows.push(Row::of(controller.env(0)));
                            r.model_ms.push(model_ms);
                            r.physics_ms.push(physics_ms);
                        }
                    }
                    Err(e) => {
                        self.notice(format!("the controller stopped: {e}; reset to go on"));
                        stopped = Some(e.to_string());
                    }
                }
                time += 1.0 / CONTROL_HZ;
            }
            let now = Instant::now();
            step_starts.push_back(now);
            while step_starts.front().is_some_and(|t| now.duration_since(*t) > Duration::from_secs(1)) {
                step_starts.pop_front();
            }
            let env = controller.env(0);
            let b = env.bodies();
            headings.push_back(heading(b.rot[0]));
            if headings.len() > YAW_RATE_STEPS + 1 {
                headings.pop_front();
            }
            let turned = wrap_angle(headings.back().expect("pushed") - headings.front().expect("pushed"));
            let yaw_rate = turned * CONTROL_HZ / (headings.len() - 1).max(1) as f64;
            let state = env.state();
            let plan = controller
                .plan(0)
                .map(|tau| {
                    (1..=traj.horizon)
                        .map(|k| {
                            let p = traj.root_pos(k);
                            let w =
                                planned_from.point_to_world(DVec3::new(f64::from(tau[p]), f64::from(tau[p + 1]), 0.0));
                            [w.x as f32, w.y as f32, tau[p + 2]]
                        })
                        .collect()
                })
                .unwrap_or_default();
            let frame = Frame {
                step: controller.steps(),
                time,
                bodies: b.pos.iter().map(|p| [p.x as f32, p.y as f32, p.z as f32]).collect(),
                plan,
                command: inputs.drive.map(|x| x as f32),
                applied: inputs.seq,
                waypoint: inputs.waypoint,
                reach: inputs.reach,
                obstacles: inputs.obstacles.clone(),
                touching: env.touching_obstacle(),
                velocity: [state[offset::ROOT_VEL], state[offset::ROOT_VEL + 1], yaw_rate as f32],
                scale: inputs.scale,
                nfe: inputs.nfe,
                inverse_dynamics: inputs.inverse_dynamics,
                model_ms,
                physics_ms,
                rate: step_starts.len() as f32,
                fell: !controller.is_alive(0) || stopped.is_some(),
                recording: recording.is_some(),
            };
            self.frames.send_replace(text(&Outgoing::Frame(frame)));
            // Paced at 30 Hz; a step that overran starts the clock afresh rather than racing.
            next_tick += period;
            let now = Instant::now();
            match next_tick.checked_duration_since(now) {
                Some(wait) => std::thread::sleep(wait),
                None => next_tick = now,
            }
        }
    }

    /// Writes a recording as `play-<unix seconds>.rollout.safetensors` in the record directory.
    fn save(&self, r: Recording) {
        let steps = r.actions.len();
        if steps == 0 {
            return self.notice("nothing recorded: no control step ran".into());
        }
        let start = format!("clip '{}', live play", self.clip.name);
        let info = RolloutInfo::new(&self.config.model_name, self.model, &r.sampler, vec![r.task], start);
        let mut rollout = Rollout::new(info, 1, steps, self.humanoid.nq());
        for (k, row) in r.rows.iter().enumerate() {
            rollout.put_row(0, k, row);
        }
        for (k, a) in r.actions.iter().enumerate() {
            rollout.record_action(0, k, &a.action, &a.command, a.plan, a.touched);
            if let Some(hand) = a.plan_hand {
                rollout.record_planned_hand(0, k, hand);
            }
        }
        (rollout.model_ms, rollout.physics_ms) = (r.model_ms, r.physics_ms);
        let seconds = r.started.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let path = self.config.record_dir.join(format!("play-{seconds}.rollout.safetensors"));
        let saved = std::fs::create_dir_all(&self.config.record_dir)
            .map_err(|e| e.to_string())
            .and_then(|()| rollout.save(&path).map_err(|e| e.to_string()));
        self.notice(match saved {
            Ok(()) => format!("recorded {steps} steps to {}", path.display()),
            Err(e) => format!("recording not written: {}: {e}", path.display()),
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs() -> Inputs {
        Inputs {
            drive: [0.0; 3],
            seq: 0,
            waypoint: None,
            reach: None,
            obstacles: Vec::new(),
            scale: 10.0,
            nfe: 5,
            inverse_dynamics: Some(0.0),
            push: false,
            reset: false,
            record: false,
        }
    }

    fn apply(i: &mut Inputs, message: &str) -> Result<(), String> {
        i.apply(serde_json::from_str(message).map_err(|e| e.to_string())?)
    }

    #[test]
    fn commands_apply_and_bad_ones_are_refused_whole() {
        let mut i = inputs();
        apply(&mut i, r#"{"type":"drive","vx":1.2,"vy":-0.2,"yaw_rate":0.5,"seq":3}"#).unwrap();
        assert_eq!((i.drive, i.seq), ([1.2, -0.2, 0.5], 3));
        apply(&mut i, r#"{"type":"hand","hand":"left","target":[1,2,1.4]}"#).unwrap();
        assert_eq!(i.reach, Some((Hand::Left, [1.0, 2.0, 1.4])));
        apply(&mut i, r#"{"type":"waypoint","at":[3,-1]}"#).unwrap();
        apply(&mut i, r#"{"type":"push"}"#).unwrap();
        assert!(i.push && i.task().waypoint == Some([3.0, -1.0]));
        apply(&mut i, r#"{"type":"sampler","scale":50,"nfe":2,"inverse_dynamics":0.2}"#).unwrap();
        apply(&mut i, r#"{"type":"sampler","scale":40,"nfe":2}"#).unwrap();
        assert_eq!((i.scale, i.inverse_dynamics), (40.0, Some(0.2)), "a sampler message without the share keeps it");
        apply(&mut i, r#"{"type":"obstacle","at":[2,0.5]}"#).unwrap();
        apply(&mut i, r#"{"type":"obstacle","at":[3,0]}"#).unwrap();
        assert_eq!(i.task().obstacles, vec![Obstacle::cylinder([2.0, 0.5], 0.3), Obstacle::cylinder([3.0, 0.0], 0.3)]);
        apply(&mut i, r#"{"type":"obstacle","at":null}"#).unwrap();
        assert!(i.task().obstacles.is_empty());
        let before = i.clone();
        for (bad, why) in [
            (r#"{"type":"drive","vx":9,"vy":0,"yaw_rate":0}"#, "joystick speed"),
            (r#"{"type":"hand","hand":"right","target":[1,0,7]}"#, "height"),
            (r#"{"type":"sampler","scale":-1,"nfe":5}"#, "guidance scale"),
            (r#"{"type":"sampler","scale":1,"nfe":0}"#, "NFE"),
            (r#"{"type":"sampler","scale":1,"nfe":2,"inverse_dynamics":1.5}"#, "inverse-dynamics share"),
            (r#"{"type":"obstacle","at":[1e9,0]}"#, "obstacle position"),
            (r#"{"type":"fly"}"#, "unknown variant"),
            (r#"{"type":"drive","vx":"fast"}"#, "invalid type"),
        ] {
            let e = apply(&mut i, bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
        assert_eq!(format!("{i:?}"), format!("{before:?}"), "a refused message changed nothing");
        let mut without = Inputs { inverse_dynamics: None, ..inputs() };
        let e = apply(&mut without, r#"{"type":"sampler","scale":1,"nfe":2,"inverse_dynamics":0.2}"#).unwrap_err();
        assert!(e.contains("no inverse dynamics"), "{e}");
    }
}
