//! Going around obstacles, at two ranges: a cost on the predicted pelvis positions keeps each
//! plan clear of them (it sees as far as the plan reaches: H 16 steps at 30 Hz is half a second,
//! 0.4-0.5 m of walking), and a way planned around them on a grid (A*, metres ahead) leads the
//! waypoint's pursuit.

use crate::ControlError;
use crate::costs::Cost;
use crate::layout::Layout;
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::{CONTROL_HZ, Obstacle};

/// Seen from the character frame `frame` at `time`: each obstacle where it is then, its
/// velocity and footprint turned into the frame, so that `position(t)` is where it will be `t`
/// seconds later.
pub fn in_frame(obstacles: &[Obstacle], frame: &CharFrame, time: f64) -> Vec<Obstacle> {
    let here = CharFrame::new(DVec3::ZERO, 0.0);
    obstacles.iter().map(|o| Obstacle { at: o.position(time), ..*o }.carried(frame, &here)).collect()
}

/// Keep the predicted body clear of every obstacle: `1/2 sum_k sum_b sum_o max(0, m_b -
/// d_o(p_b,k))^2`, `d_o` the distance from body b's (x, y) at step k to obstacle o's edge where
/// o will be then (obstacles in the current character frame), `m_b` the body's margin
/// ([`Avoid::BODIES`]). A body other than the pelvis is where the state puts it: the root plus
/// its offset turned by the state's heading, as the reach cost builds the hand.
pub struct Avoid {
    layout: Layout,
    obstacles: Vec<Obstacle>,
}

/// One body of one predicted step inside an obstacle's margin.
struct Intrusion {
    k: usize,
    body: usize,
    /// How far inside (m), the distance's gradient, and the body's offset turned into the
    /// current frame (zero for the pelvis).
    depth: f64,
    normal: [f64; 2],
    turned: [f64; 2],
}

impl Avoid {
    /// The bodies kept clear, with their margins (m): the pelvis by half the body's width with
    /// its swinging arms (0.25 m) and more; the hands and toes, which touched first where only
    /// the pelvis was kept clear (docs/obstacles.md), by a little.
    pub const BODIES: [(usize, f64); 5] =
        [(body::PELVIS, 0.5), (body::L_HAND, 0.15), (body::R_HAND, 0.15), (body::L_TOE, 0.15), (body::R_TOE, 0.15)];
    /// Its weight beside the waypoint's pursuit (whose weight it is given times this).
    pub const WEIGHT: f32 = 30.0;

    /// `obstacles` in the current character frame ([`in_frame`]).
    pub fn new(layout: Layout, obstacles: Vec<Obstacle>) -> Result<Self, ControlError> {
        if let Some(e) = obstacles.iter().find_map(|o| o.validate().err()) {
            return Err(ControlError::Obstacle(e));
        }
        Ok(Self { layout, obstacles })
    }

    /// Every body's intrusion into an obstacle's margin, steps 1..=H.
    fn intrusions(&self, tau: &[f32]) -> Vec<Intrusion> {
        let mut found = Vec::new();
        for k in 1..=self.layout.horizon {
            let p = self.layout.root_pos(k);
            let (s, c) = f64::from(tau[self.layout.root_rot(k) + 2]).sin_cos();
            let t = k as f64 / CONTROL_HZ;
            for (body, margin) in Self::BODIES {
                let turned = match body {
                    body::PELVIS => [0.0, 0.0],
                    _ => {
                        let b = self.layout.body_pos(k, body);
                        let (x, y) = (f64::from(tau[b]), f64::from(tau[b + 1]));
                        [c * x - s * y, s * x + c * y]
                    }
                };
                let at = [f64::from(tau[p]) + turned[0], f64::from(tau[p + 1]) + turned[1]];
                for o in &self.obstacles {
                    let (d, normal) = o.distance(at, t);
                    if d < margin {
                        found.push(Intrusion { k, body, depth: margin - d, normal, turned });
                    }
                }
            }
        }
        found
    }
}

impl Cost for Avoid {
    fn cost(&self, tau: &[f32]) -> f32 {
        self.intrusions(tau).iter().map(|i| 0.5 * i.depth * i.depth).sum::<f64>() as f32
    }

    fn add_grad(&self, tau: &[f32], grad: &mut [f32]) {
        for i in self.intrusions(tau) {
            // dG/dposition = -depth * normal, carried to the root, the offset and the heading.
            let g = [-i.depth * i.normal[0], -i.depth * i.normal[1]];
            let p = self.layout.root_pos(i.k);
            grad[p] += g[0] as f32;
            grad[p + 1] += g[1] as f32;
            if i.body != body::PELVIS {
                let r = self.layout.root_rot(i.k) + 2;
                let (s, c) = f64::from(tau[r]).sin_cos();
                let b = self.layout.body_pos(i.k, i.body);
                grad[b] += (g[0] * c + g[1] * s) as f32;
                grad[b + 1] += (-g[0] * s + g[1] * c) as f32;
                grad[r] += (-g[0] * i.turned[1] + g[1] * i.turned[0]) as f32;
            }
        }
    }

    /// Root mean square intrusion over the predicted steps (m).
    fn error(&self, tau: &[f32]) -> f32 {
        (2.0 * self.cost(tau) / self.layout.horizon as f32).sqrt()
    }
}

/// How far (m) from an obstacle's edge a planned way keeps the pelvis where it can: the
/// humanoid is 0.5 m wide with its swinging arms, and its executed path strays 0.1-0.3 m from
/// the one planned.
pub const CLEARANCE: f64 = 0.8;
/// Nearer than this (m), the pelvis would put an arm into the obstacle: no way passes there
/// (except out of it, near the walker).
pub const BODY: f64 = 0.4;
/// A way's cost per metre grows to `1 + CROWDING` at [`BODY`] from an edge: a wide gap is
/// worth a detour of several metres.
const CROWDING: f64 = 4.0;
/// Grid cell (m) of the planner, and the most cells along a side (a larger area takes larger cells).
const CELL: f64 = 0.15;
const MAX_SIDE: usize = 240;
/// The planner's area reaches this far (m) beyond the walker and the goal.
const PAD: f64 = 3.0;
/// Speed (m/s) at which the walker is assumed to go, to place moving obstacles.
const WALKING_SPEED: f64 = 0.8;
/// How far (m) along its way the pursuit looks for the point it walks to.
pub const LOOKAHEAD: f64 = 3.0;
/// A straight walk to that point must keep this far (m) from every edge (or, already nearer,
/// not come nearer).
pub const SIGHT: f64 = 0.6;
/// An edge already nearer than [`SIGHT`] may come this much nearer (m): walking past it along
/// a curve dips toward it.
const SIGHT_SLACK: f64 = 0.05;

/// Distance (m) from `p` to the nearest obstacle's edge, each obstacle where it is `t` s on.
fn nearest_edge(p: [f64; 2], obstacles: &[Obstacle], t: f64) -> f64 {
    obstacles.iter().map(|o| o.distance(p, t).0).fold(f64::INFINITY, f64::min)
}

/// The cheapest way from `from` to `to` (character frame, m) among `obstacles` (character
/// frame, time 0 now) on a grid, A* with 8 neighbours; a cell's cost per metre grows as it
/// nears an edge ([`CLEARANCE`], [`BODY`]). Moving obstacles are placed where they will be when a
/// walker at [`WALKING_SPEED`] gets there by the straight line. `None` when no way exists.
pub fn plan_way(from: [f64; 2], to: [f64; 2], obstacles: &[Obstacle]) -> Option<Vec<[f64; 2]>> {
    let lo = [from[0].min(to[0]) - PAD, from[1].min(to[1]) - PAD];
    let extent = [(from[0] - to[0]).abs() + 2.0 * PAD, (from[1] - to[1]).abs() + 2.0 * PAD];
    let cell = CELL.max(extent[0].max(extent[1]) / MAX_SIDE as f64);
    let (nx, ny) = ((extent[0] / cell).ceil() as usize + 1, (extent[1] / cell).ceil() as usize + 1);
    let centre = |i: usize| [lo[0] + (i % nx) as f64 * cell, lo[1] + (i / nx) as f64 * cell];
    let index = |p: [f64; 2]| {
        let (x, y) = (((p[0] - lo[0]) / cell).round() as usize, ((p[1] - lo[1]) / cell).round() as usize);
        x.min(nx - 1) + y.min(ny - 1) * nx
    };
    // Cost per metre of each cell; infinite where the body would touch, except near the walker.
    let weight: Vec<f64> = (0..nx * ny)
        .map(|i| {
            let c = centre(i);
            let t = (c[0] - from[0]).hypot(c[1] - from[1]) / WALKING_SPEED;
            let d = nearest_edge(c, obstacles, t);
            let near_walker = (c[0] - from[0]).hypot(c[1] - from[1]) < 0.5;
            if d < BODY && !near_walker {
                f64::INFINITY
            } else {
                1.0 + CROWDING * ((CLEARANCE - d) / (CLEARANCE - BODY)).clamp(0.0, 1.0)
            }
        })
        .collect();
    let (start, goal) = (index(from), index(to));
    let h = |i: usize| {
        let (a, b) = (centre(i), centre(goal));
        (a[0] - b[0]).hypot(a[1] - b[1])
    };
    let mut cost = vec![f64::INFINITY; nx * ny];
    let mut came = vec![usize::MAX; nx * ny];
    let mut open = std::collections::BinaryHeap::new();
    cost[start] = 0.0;
    open.push(Visit(-h(start), start));
    while let Some(Visit(_, i)) = open.pop() {
        if i == goal {
            let mut way = vec![to];
            let mut j = came[goal];
            while j != usize::MAX && j != start {
                way.push(centre(j));
                j = came[j];
            }
            way.push(from);
            way.reverse();
            return Some(way);
        }
        let (x, y) = ((i % nx) as i64, (i / nx) as i64);
        for (dx, dy) in [(-1i64, -1i64), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)] {
            let (u, v) = (x + dx, y + dy);
            if u < 0 || v < 0 || u >= nx as i64 || v >= ny as i64 {
                continue;
            }
            let j = u as usize + v as usize * nx;
            let step = cell * ((dx * dx + dy * dy) as f64).sqrt() * 0.5 * (weight[i] + weight[j]);
            if cost[i] + step < cost[j] {
                cost[j] = cost[i] + step;
                came[j] = i;
                open.push(Visit(-(cost[j] + h(j)), j));
            }
        }
    }
    None
}

/// A grid cell in A*'s queue, ordered by its negated estimate (the heap pops the largest).
#[derive(PartialEq)]
struct Visit(f64, usize);

impl Eq for Visit {}

impl PartialOrd for Visit {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Visit {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0).then(self.1.cmp(&other.1))
    }
}

/// Whether the straight walk from the origin to `p` keeps [`SIGHT`] from every edge (an edge
/// already nearer may not come nearer).
fn in_sight(p: [f64; 2], obstacles: &[Obstacle]) -> bool {
    let length = p[0].hypot(p[1]);
    let samples = (length / 0.05).ceil().max(1.0) as usize;
    obstacles.iter().all(|o| {
        let need = SIGHT.min(o.distance([0.0, 0.0], 0.0).0 - SIGHT_SLACK);
        (1..=samples).all(|i| {
            let s = i as f64 / samples as f64;
            o.distance([p[0] * s, p[1] * s], s * length / WALKING_SPEED).0 >= need
        })
    })
}

/// The point (character frame) the pursuit walks to on its way to `goal` among `obstacles`
/// (character frame, time 0 now): the goal itself when the straight walk there is clear,
/// otherwise toward the farthest point of [`plan_way`]'s way, within [`LOOKAHEAD`] along it,
/// that the walker sees ([`SIGHT`]), as far away as the goal or [`LOOKAHEAD`] (the pursuit
/// slows near the point it walks to: a near corner would stall it); the goal when there is no
/// way.
pub fn detour(goal: [f64; 2], obstacles: &[Obstacle]) -> [f64; 2] {
    if obstacles.is_empty() || in_sight(goal, obstacles) {
        return goal;
    }
    let Some(way) = plan_way([0.0, 0.0], goal, obstacles) else { return goal };
    let mut along = 0.0;
    let mut chosen = way[1.min(way.len() - 1)];
    for pair in way.windows(2) {
        along += (pair[1][0] - pair[0][0]).hypot(pair[1][1] - pair[0][1]);
        if along > LOOKAHEAD {
            break;
        }
        if in_sight(pair[1], obstacles) {
            chosen = pair[1];
        }
    }
    let (length, reach) = (chosen[0].hypot(chosen[1]), goal[0].hypot(goal[1]).min(LOOKAHEAD));
    if length < 1e-9 {
        return goal;
    }
    [chosen[0] * reach / length, chosen[1] * reach / length]
}
/// The world point the pursuit walks to on the way to `goal` (world x, y) through `obstacles`
/// (world, at `time`), seen from the root pose `frame`.
pub fn world_detour(goal: [f64; 2], obstacles: &[Obstacle], frame: &CharFrame, time: f64) -> [f64; 2] {
    let local = frame.point(DVec3::new(goal[0], goal[1], frame.origin.z));
    let [x, y] = detour([local.x, local.y], &in_frame(obstacles, frame, time));
    let world = frame.point_to_world(DVec3::new(x, y, 0.0));
    [world.x, world.y]
}
