//! Task costs `G(tau)` and their gradients, for test-time guidance (`v' = v - w grad G`).
//!
//! Each cost reads a trajectory laid out by [`Layout`] in physical units (the model maps the
//! gradient onto its normalised coordinates). Gradients are analytic; the tests check each
//! against finite differences.
//!
//! Each cost also reports its error in its own unit (m/s, rad/s, m, over the predicted steps),
//! so that [`Sum::guidance_grad`] can make the guidance scale mean the same
//! for every task and model: each term's gradient is scaled to a length, in the model's
//! normalised coordinates, equal to its error.

use crate::ControlError;
use crate::layout::Layout;
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_sim::CONTROL_HZ;

/// A differentiable cost of one trajectory.
pub trait Cost: Sync {
    fn cost(&self, tau: &[f32]) -> f32;
    /// Adds `dG/dtau` into `grad`.
    fn add_grad(&self, tau: &[f32], grad: &mut [f32]);
    /// How far the trajectory is from what the cost asks, in the task's unit (root mean square
    /// over the predicted steps).
    fn error(&self, tau: &[f32]) -> f32;
}

fn finite(what: &'static str, values: &[f64]) -> Result<(), ControlError> {
    match values.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(ControlError::BadCommand { what, value: *v }),
        None => Ok(()),
    }
}

/// Joystick (paper eq. 7): `1/2 sum_k ||v_xy(s_k) - g_v,k||^2` over the predicted states, the
/// command (x forward, y left, m/s) in the character frame of the current step. With a turn
/// rate `w` the walker is asked to turn, so the command at step k is turned by `w k dt`: a
/// forward command stays forward for the body that turns.
pub struct Joystick {
    layout: Layout,
    command: [f32; 2],
    yaw_rate: f32,
}

impl Joystick {
    /// Commands beyond 3 m/s are refused: walking data never goes there.
    pub fn new(layout: Layout, vx: f64, vy: f64) -> Result<Self, ControlError> {
        Self::turning(layout, vx, vy, 0.0)
    }

    /// The command while turning at `yaw_rate` rad/s.
    pub fn turning(layout: Layout, vx: f64, vy: f64, yaw_rate: f64) -> Result<Self, ControlError> {
        finite("joystick velocity", &[vx, vy, yaw_rate])?;
        if vx.hypot(vy) > 3.0 {
            return Err(ControlError::BadCommand { what: "joystick speed (max 3 m/s)", value: vx.hypot(vy) });
        }
        Ok(Self { layout, command: [vx as f32, vy as f32], yaw_rate: yaw_rate as f32 })
    }

    /// The commanded velocity at predicted step k, in the current frame.
    fn target(&self, k: usize) -> [f32; 2] {
        let (s, c) = (self.yaw_rate * k as f32 / CONTROL_HZ as f32).sin_cos();
        let [x, y] = self.command;
        [c * x - s * y, s * x + c * y]
    }
}

impl Cost for Joystick {
    fn cost(&self, tau: &[f32]) -> f32 {
        (1..=self.layout.horizon)
            .map(|k| {
                let (v, g) = (self.layout.root_vel(k), self.target(k));
                0.5 * ((tau[v] - g[0]).powi(2) + (tau[v + 1] - g[1]).powi(2))
            })
            .sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for k in 1..=self.layout.horizon {
            let (v, g) = (self.layout.root_vel(k), self.target(k));
            grad[v] += tau[v] - g[0];
            grad[v + 1] += tau[v + 1] - g[1];
        }
    }

    fn error(&self, tau: &[f32]) -> f32 {
        (2.0 * self.cost(tau) / self.layout.horizon as f32).sqrt()
    }
}

/// Heading change of state k relative to the current step, from its root rotation vector's z
/// component: exact for a pure yaw, and within 1% for tilts under 0.2 rad.
fn yaw(tau: &[f32], layout: &Layout, k: usize) -> f32 {
    tau[layout.root_rot(k) + 2]
}

/// Turning: `1/2 sum_k (yaw_k - w k dt)^2`, a heading target for every predicted step (the
/// current step's heading is 0 in its own frame). Each step has its own target, so the gradient
/// is spread over the horizon instead of landing on the last state, as a cost on differences of
/// successive headings (a rate) would make it.
pub struct Heading {
    layout: Layout,
    rate: f32,
}

impl Heading {
    /// The fastest turn asked (rad/s).
    pub const MAX_RATE: f64 = 3.0;

    pub fn new(layout: Layout, rate: f64) -> Result<Self, ControlError> {
        finite("turn rate", &[rate])?;
        if rate.abs() > Self::MAX_RATE {
            return Err(ControlError::BadCommand { what: "turn rate (max 3 rad/s)", value: rate });
        }
        Ok(Self { layout, rate: rate as f32 })
    }

    fn target(&self, k: usize) -> f32 {
        self.rate * k as f32 / CONTROL_HZ as f32
    }
}

impl Cost for Heading {
    fn cost(&self, tau: &[f32]) -> f32 {
        (1..=self.layout.horizon).map(|k| 0.5 * (yaw(tau, &self.layout, k) - self.target(k)).powi(2)).sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for k in 1..=self.layout.horizon {
            grad[self.layout.root_rot(k) + 2] += yaw(tau, &self.layout, k) - self.target(k);
        }
    }

    /// In rad/s, the joystick's unit: the yaw-rate error whose heading errors `e k dt` have this
    /// cost. (The heading error itself is small by construction: a 0.6 rad/s turn is 0.3 rad
    /// over 16 steps, so in rad the turn pulled a third as hard as a 0.6 m/s speed error.)
    fn error(&self, tau: &[f32]) -> f32 {
        let dt = 1.0 / CONTROL_HZ as f32;
        let times: f32 = (1..=self.layout.horizon).map(|k| (k as f32 * dt).powi(2)).sum();
        (2.0 * self.cost(tau) / times).sqrt()
    }
}

/// End-effector reach (paper eq. 8): `sum_k ||p_hand(s_k) - p_target||^2`, the hand built
/// from the state's root and body features: in the current frame, the hand is at
/// `(root_x, root_y, root_z) + R_z(yaw_k) * hand_k`, `hand_k` the body position in state k's
/// own frame.
pub struct Reach {
    layout: Layout,
    body: usize,
    target: [f32; 3],
}

impl Reach {
    /// `target` in the current step's character frame (x, y) and height above ground (z).
    pub fn new(layout: Layout, body: usize, target: [f64; 3]) -> Result<Self, ControlError> {
        finite("reach target", &target)?;
        let reach = target[0].hypot(target[1]);
        if reach > 5.0 || !(0.0..=2.5).contains(&target[2]) {
            return Err(ControlError::BadCommand {
                what: "reach target distance (m; within 5 m and 0-2.5 m high)",
                value: reach.max(target[2]),
            });
        }
        Ok(Self { layout, body, target: target.map(|x| x as f32) })
    }

    /// A world-frame target, converted through the current root pose (`frame`). The target
    /// may be any distance away (a walker that has wandered 6 m from it is pulled back, not
    /// refused); only its height is checked, by [`Reach::new`]'s rule.
    pub fn world(layout: Layout, body: usize, target: [f64; 3], frame: &CharFrame) -> Result<Self, ControlError> {
        Self::new(layout, body, [0.0, 0.0, target[2]])?;
        let local = frame.point(DVec3::from_array(target));
        Ok(Self { layout, body, target: [local.x as f32, local.y as f32, target[2] as f32] })
    }

    /// Hand position in the current frame, and its own-frame offset rotated into it.
    fn hand(&self, tau: &[f32], k: usize) -> ([f32; 3], [f32; 2]) {
        self.layout.body_in_frame(tau, k, self.body)
    }
}

impl Cost for Reach {
    fn cost(&self, tau: &[f32]) -> f32 {
        (1..=self.layout.horizon)
            .map(|k| {
                let (h, _) = self.hand(tau, k);
                (0..3).map(|i| (h[i] - self.target[i]).powi(2)).sum::<f32>()
            })
            .sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for k in 1..=self.layout.horizon {
            let (h, rotated) = self.hand(tau, k);
            let e: Vec<f32> = (0..3).map(|i| 2.0 * (h[i] - self.target[i])).collect();
            let (p, b, r) = (self.layout.root_pos(k), self.layout.body_pos(k, self.body), self.layout.root_rot(k) + 2);
            let (s, c) = yaw(tau, &self.layout, k).sin_cos();
            for i in 0..3 {
                grad[p + i] += e[i];
            }
            // d(R h)/dh = R; d(R h)/dyaw = (-ry, rx).
            grad[b] += e[0] * c + e[1] * s;
            grad[b + 1] += -e[0] * s + e[1] * c;
            grad[b + 2] += e[2];
            grad[r] += -e[0] * rotated[1] + e[1] * rotated[0];
        }
    }

    fn error(&self, tau: &[f32]) -> f32 {
        (self.cost(tau) / self.layout.horizon as f32).sqrt()
    }
}

/// Waypoint navigation as a joystick command (pure pursuit): walk forward toward the goal,
/// turning toward it at [`Pursuit::TURN_GAIN`] times its bearing (at most 1.2 rad/s; 09_12
/// turns at up to 2.3), stepping sideways toward it at 1/s times its offset to the side (at
/// most 0.3 m/s), slower within 1 m of it (walk and turn alike) and while it lies to the side.
/// BeyondMimic's cost on the predicted root positions, `sum_k ||P_k - g||^2`, was measured
/// against it and replaced: over a 16-step horizon it pulls the path sideways instead of
/// turning the walker, which then passes the goal (README, "Guidance that steers").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pursuit {
    /// Forward speed (m/s).
    pub speed: f64,
    /// Yaw rate (rad/s, left positive).
    pub yaw_rate: f64,
    /// Sideways speed (m/s, left positive).
    pub lateral: f64,
}

impl Pursuit {
    /// Yaw rate per radian of bearing (1/s).
    pub const TURN_GAIN: f64 = 4.0;
    const MAX_YAW_RATE: f64 = 1.2;
    /// Sideways speed per metre of the goal's offset to the side (1/s), and its limit (m/s):
    /// the last few decimetres, which a turn alone corrects only by walking on.
    const LATERAL_GAIN: f64 = 1.0;
    const MAX_LATERAL: f64 = 0.3;
    const MAX_SPEED: f64 = 1.0;
    /// Within this distance (m) the walker slows in proportion.
    const SLOWING: f64 = 1.0;
    /// Slowest forward speed, as a share of the full one, while turning toward a goal aside.
    const TURNING_SPEED: f64 = 0.2;

    /// The command toward `goal`, given in the current character frame (x forward, y left).
    pub fn new(goal: [f64; 2]) -> Result<Self, ControlError> {
        finite("waypoint", &goal)?;
        let distance = goal[0].hypot(goal[1]);
        if distance > 100.0 {
            return Err(ControlError::BadCommand { what: "waypoint distance (max 100 m)", value: distance });
        }
        let bearing = goal[1].atan2(goal[0]);
        // Near the goal its bearing swings with every step: slow the turn down with the walk,
        // so that the walker stops there instead of spinning on the spot.
        let near = (distance / Self::SLOWING).min(1.0);
        Ok(Self {
            speed: Self::MAX_SPEED * near * bearing.cos().max(Self::TURNING_SPEED),
            yaw_rate: near * (Self::TURN_GAIN * bearing).clamp(-Self::MAX_YAW_RATE, Self::MAX_YAW_RATE),
            lateral: (Self::LATERAL_GAIN * goal[1]).clamp(-Self::MAX_LATERAL, Self::MAX_LATERAL),
        })
    }

    /// The command toward a world-frame goal, seen from the current root pose (`frame`).
    pub fn world(goal: [f64; 2], frame: &CharFrame) -> Result<Self, ControlError> {
        finite("waypoint", &goal)?;
        let local = frame.point(DVec3::new(goal[0], goal[1], frame.origin.z));
        Self::new([local.x, local.y])
    }
}

/// A weighted sum of costs (walk to a point while reaching).
#[derive(Default)]
pub struct Sum {
    pub terms: Vec<(f32, Box<dyn Cost>)>,
}

impl Sum {
    pub fn with(mut self, weight: f32, cost: impl Cost + 'static) -> Self {
        self.terms.push((weight, Box::new(cost)));
        self
    }

    /// Every term's weight times `factor` (adaptive guidance, [`crate::adapt`]).
    pub fn scaled(mut self, factor: f32) -> Self {
        self.terms.iter_mut().for_each(|(w, _)| *w *= factor);
        self
    }
}

impl Sum {
    /// The gradient guidance applies (physical units, added into `grad`): each term's gradient
    /// scaled so that its length in the model's normalised coordinates (`std`, the standard
    /// deviation of each trajectory entry: a normalised entry is `x / std`, so its gradient is
    /// `std * dG/dx`) equals the term's error, times the term's weight. The guidance scale `w`
    /// then means the same for every task and model: a 1 m/s joystick error, a 1 rad/s turn
    /// error and a hand 1 m from its target pull equally hard.
    pub fn guidance_grad(&self, tau: &[f32], std: &[f32], grad: &mut [f32]) {
        let mut part = vec![0.0; grad.len()];
        for (w, c) in &self.terms {
            part.fill(0.0);
            c.add_grad(tau, &mut part);
            let length = part.iter().zip(std).map(|(g, s)| (g * s).powi(2)).sum::<f32>().sqrt();
            if length > 1e-12 {
                let scale = w * c.error(tau) / length;
                grad.iter_mut().zip(&part).for_each(|(g, p)| *g += scale * p);
            }
        }
    }
}

/// The guidance gradient of a batch of trajectories (`x`: `n` rows, one per cost), each row
/// under its own cost (`None`: not guided), as [`Sum::guidance_grad`] gives it.
pub fn batch_guidance_grad(costs: &[Option<Sum>], std: &[f32], x: &[f32], n: usize) -> Vec<f32> {
    let len = x.len() / n.max(1);
    let mut g = vec![0.0; x.len()];
    for (i, cost) in costs.iter().enumerate().take(n) {
        if let Some(c) = cost {
            c.guidance_grad(&x[i * len..(i + 1) * len], std, &mut g[i * len..(i + 1) * len]);
        }
    }
    g
}

impl Cost for Sum {
    fn cost(&self, tau: &[f32]) -> f32 {
        self.terms.iter().map(|(w, c)| w * c.cost(tau)).sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        let mut part = vec![0.0; grad.len()];
        for (w, c) in &self.terms {
            part.fill(0.0);
            c.add_grad(tau, &mut part);
            grad.iter_mut().zip(&part).for_each(|(g, p)| *g += w * p);
        }
    }

    /// The weighted root-sum-square of the terms' errors.
    fn error(&self, tau: &[f32]) -> f32 {
        self.terms.iter().map(|(w, c)| (w * c.error(tau)).powi(2)).sum::<f32>().sqrt()
    }
}
