//! Task costs `G(tau)` and their gradients, for test-time guidance (`v' = v - w grad G`).
//!
//! Each cost reads a trajectory laid out by [`Layout`] in physical units (the model maps the
//! gradient onto its normalised coordinates). Gradients are analytic; the tests check each
//! against finite differences.

use crate::ControlError;
use crate::layout::Layout;
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_sim::CONTROL_HZ;

/// A differentiable cost of one trajectory.
pub trait Cost: Sync {
    fn cost(&self, tau: &[f32]) -> f32;
    /// Adds `dG/dtau` into `grad`.
    fn add_grad(&self, tau: &[f32], grad: &mut [f32]);
}

fn finite(what: &'static str, values: &[f64]) -> Result<(), ControlError> {
    match values.iter().find(|v| !v.is_finite()) {
        Some(v) => Err(ControlError::BadCommand { what, value: *v }),
        None => Ok(()),
    }
}

/// Joystick (paper eq. 7): `1/2 sum_k ||v_xy(s_k) - g_v||^2` over the predicted states, the
/// command in the character frame of the current step (x forward, y left), m/s.
pub struct Joystick {
    layout: Layout,
    command: [f32; 2],
}

impl Joystick {
    /// Commands beyond 3 m/s are refused: walking data never goes there.
    pub fn new(layout: Layout, vx: f64, vy: f64) -> Result<Self, ControlError> {
        finite("joystick velocity", &[vx, vy])?;
        if vx.hypot(vy) > 3.0 {
            return Err(ControlError::BadCommand { what: "joystick speed (max 3 m/s)", value: vx.hypot(vy) });
        }
        Ok(Self { layout, command: [vx as f32, vy as f32] })
    }
}

impl Cost for Joystick {
    fn cost(&self, tau: &[f32]) -> f32 {
        (1..=self.layout.horizon)
            .map(|k| {
                let v = self.layout.root_vel(k);
                0.5 * ((tau[v] - self.command[0]).powi(2) + (tau[v + 1] - self.command[1]).powi(2))
            })
            .sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for k in 1..=self.layout.horizon {
            let v = self.layout.root_vel(k);
            grad[v] += tau[v] - self.command[0];
            grad[v + 1] += tau[v + 1] - self.command[1];
        }
    }
}

/// Heading change of state k relative to the current step, from its root rotation vector's z
/// component: exact for a pure yaw, and within 1% for tilts under 0.2 rad.
fn yaw(tau: &[f32], layout: &Layout, k: usize) -> f32 {
    tau[layout.root_rot(k) + 2]
}

/// Turn-rate variant of the joystick: `1/2 sum_k (yaw rate_k - g_w)^2`, the rate from
/// successive predicted headings (the current step's heading is 0 in its own frame).
pub struct TurnRate {
    layout: Layout,
    rate: f32,
}

impl TurnRate {
    pub fn new(layout: Layout, rate: f64) -> Result<Self, ControlError> {
        finite("turn rate", &[rate])?;
        if rate.abs() > 3.0 {
            return Err(ControlError::BadCommand { what: "turn rate (max 3 rad/s)", value: rate });
        }
        Ok(Self { layout, rate: rate as f32 })
    }
}

impl Cost for TurnRate {
    fn cost(&self, tau: &[f32]) -> f32 {
        let hz = CONTROL_HZ as f32;
        let mut prev = 0.0;
        let mut total = 0.0;
        for k in 1..=self.layout.horizon {
            let y = yaw(tau, &self.layout, k);
            total += 0.5 * ((y - prev) * hz - self.rate).powi(2);
            prev = y;
        }
        total
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        let hz = CONTROL_HZ as f32;
        let mut prev = 0.0;
        for k in 1..=self.layout.horizon {
            let y = yaw(tau, &self.layout, k);
            let e = (y - prev) * hz - self.rate;
            grad[self.layout.root_rot(k) + 2] += e * hz;
            if k > 1 {
                grad[self.layout.root_rot(k - 1) + 2] -= e * hz;
            }
            prev = y;
        }
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

    /// A world-frame target, converted through the current root pose (`frame`).
    pub fn world(layout: Layout, body: usize, target: [f64; 3], frame: &CharFrame) -> Result<Self, ControlError> {
        finite("reach target", &target)?;
        let local = frame.point(DVec3::from_array(target));
        Self::new(layout, body, [local.x, local.y, target[2]])
    }

    /// Hand position in the current frame, and its own-frame offset rotated into it.
    fn hand(&self, tau: &[f32], k: usize) -> ([f32; 3], [f32; 2]) {
        let (p, b) = (self.layout.root_pos(k), self.layout.body_pos(k, self.body));
        let (c, s) = (yaw(tau, &self.layout, k).cos(), yaw(tau, &self.layout, k).sin());
        let (hx, hy) = (tau[b], tau[b + 1]);
        let rotated = [c * hx - s * hy, s * hx + c * hy];
        ([tau[p] + rotated[0], tau[p + 1] + rotated[1], tau[p + 2] + tau[b + 2]], rotated)
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
            let (c, s) = (yaw(tau, &self.layout, k).cos(), yaw(tau, &self.layout, k).sin());
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
}

/// Waypoint navigation (BeyondMimic): `sum_k (1 - e^{-2d}) ||P_k - g||^2 + e^{-2d} ||V_k||^2`,
/// `P` the root's planar position and `V` its planar velocity, `d = ||P_k - g||`: far away it
/// pulls toward the goal, near it asks to stop.
pub struct Waypoint {
    layout: Layout,
    goal: [f32; 2],
}

impl Waypoint {
    pub fn new(layout: Layout, goal: [f64; 2]) -> Result<Self, ControlError> {
        finite("waypoint", &goal)?;
        if goal[0].hypot(goal[1]) > 100.0 {
            return Err(ControlError::BadCommand {
                what: "waypoint distance (max 100 m)",
                value: goal[0].hypot(goal[1]),
            });
        }
        Ok(Self { layout, goal: goal.map(|x| x as f32) })
    }

    pub fn world(layout: Layout, goal: [f64; 2], frame: &CharFrame) -> Result<Self, ControlError> {
        finite("waypoint", &goal)?;
        let local = frame.point(DVec3::new(goal[0], goal[1], frame.origin.z));
        Self::new(layout, [local.x, local.y])
    }
}

impl Cost for Waypoint {
    fn cost(&self, tau: &[f32]) -> f32 {
        (1..=self.layout.horizon)
            .map(|k| {
                let (p, v) = (self.layout.root_pos(k), self.layout.root_vel(k));
                let (dx, dy) = (tau[p] - self.goal[0], tau[p + 1] - self.goal[1]);
                let d2 = dx * dx + dy * dy;
                let near = (-2.0 * d2.sqrt()).exp();
                (1.0 - near) * d2 + near * (tau[v].powi(2) + tau[v + 1].powi(2))
            })
            .sum()
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for k in 1..=self.layout.horizon {
            let (p, v) = (self.layout.root_pos(k), self.layout.root_vel(k));
            let (dx, dy) = (tau[p] - self.goal[0], tau[p + 1] - self.goal[1]);
            let d2 = dx * dx + dy * dy;
            let d = d2.sqrt().max(1e-6);
            let near = (-2.0 * d).exp();
            let speed2 = tau[v].powi(2) + tau[v + 1].powi(2);
            // d/dP: 2 near d2 (P-g)/d + (1 - near) 2 (P-g) - 2 near speed2 (P-g)/d.
            let scale = 2.0 * near * d2 / d + 2.0 * (1.0 - near) - 2.0 * near * speed2 / d;
            grad[p] += scale * dx;
            grad[p + 1] += scale * dy;
            grad[v] += 2.0 * near * tau[v];
            grad[v + 1] += 2.0 * near * tau[v + 1];
        }
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
}
