//! What walking a set of motions covers: forward speed, sideways speed and yaw rate, each
//! averaged over a second (about a gait cycle, so the pelvis's sway averages out), and the
//! fractions that walk backward, turn and sidestep. Clips and rollout datasets are measured
//! alike, from the root's planar path.

use flowmimic_geom::{DVec3, wrap_angle, yaw_quat};
use flowmimic_sim::CONTROL_HZ;

/// Forward speed below which a step walks backward, m/s.
pub const BACKWARD: f64 = -0.2;
/// Yaw rate above which a step turns, rad/s.
pub const TURNING: f64 = 0.3;
/// Sideways speed above which a step sidesteps, m/s.
pub const SIDESTEP: f64 = 0.15;
/// Forward speed, either way, that a reversing window starts and ends beyond, m/s.
pub const REVERSING: f64 = 0.1;

/// Forward and sideways speed (m/s, in the step's heading frame) and yaw rate (rad/s) of a
/// planar root path sampled at the control rate, `[x, y, heading]` per step, each averaged
/// over the second around the step (shorter at the ends).
pub fn walking_velocities(path: &[[f64; 3]]) -> Vec<[f64; 3]> {
    let n = path.len();
    let half = (CONTROL_HZ / 2.0).round() as usize;
    (0..n)
        .map(|t| {
            let (a, b) = (t.saturating_sub(half), (t + half).min(n - 1));
            if a == b {
                return [0.0; 3];
            }
            let dt = (b - a) as f64 / CONTROL_HZ;
            let d = DVec3::new(path[b][0] - path[a][0], path[b][1] - path[a][1], 0.0);
            let local = yaw_quat(-path[t][2]) * d / dt;
            [local.x, local.y, wrap_angle(path[b][2] - path[a][2]) / dt]
        })
        .collect()
}

/// Coverage of a set of walking velocities.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Coverage {
    pub steps: usize,
    /// Fractions of steps with forward speed < [`BACKWARD`], |yaw rate| > [`TURNING`],
    /// |sideways speed| > [`SIDESTEP`].
    pub backward: f64,
    pub turning: f64,
    pub sidestep: f64,
    /// Fractions of steps that sidestep more than they walk forward or back (|sideways speed| >
    /// [`SIDESTEP`] and > |forward speed|): to the left, to the right. A turning walk's pelvis
    /// also moves sideways, so [`Coverage::sidestep`] alone overstates sidestepping.
    pub aside: [f64; 2],
    /// Fraction of 1 s windows that reverse: forward speed beyond [`REVERSING`] one way at the
    /// start and the other way at the end (forward to backward, or back).
    pub reversing: f64,
    /// Ranges seen: forward speed, sideways speed, yaw rate (min, max).
    pub ranges: [(f64, f64); 3],
    /// The velocities themselves (forward, sideways, yaw rate), for histograms.
    #[serde(skip)]
    pub velocities: Vec<[f64; 3]>,
}

impl Coverage {
    /// The coverage of one walk's velocities.
    pub fn of(velocities: Vec<[f64; 3]>) -> Self {
        Self::of_walks(vec![velocities])
    }

    /// The coverage of several walks (or episodes), each reversal window within one walk.
    pub fn of_walks(walks: Vec<Vec<[f64; 3]>>) -> Self {
        let window = CONTROL_HZ.round() as usize;
        let (mut windows, mut reversals) = (0, 0);
        for w in walks.iter().filter(|w| w.len() > window) {
            windows += w.len() - window;
            let reverses = |a: f64, b: f64| (a > REVERSING && b < -REVERSING) || (a < -REVERSING && b > REVERSING);
            reversals += w.windows(window + 1).filter(|p| reverses(p[0][0], p[window][0])).count();
        }
        let velocities: Vec<[f64; 3]> = walks.into_iter().flatten().collect();
        let n = velocities.len().max(1) as f64;
        let share = |f: &dyn Fn(&[f64; 3]) -> bool| velocities.iter().filter(|v| f(v)).count() as f64 / n;
        let mut ranges = [(f64::MAX, f64::MIN); 3];
        for v in &velocities {
            for (r, x) in ranges.iter_mut().zip(v) {
                *r = (r.0.min(*x), r.1.max(*x));
            }
        }
        Self {
            steps: velocities.len(),
            backward: share(&|v| v[0] < BACKWARD),
            turning: share(&|v| v[2].abs() > TURNING),
            sidestep: share(&|v| v[1].abs() > SIDESTEP),
            aside: [1.0, -1.0].map(|side| share(&|v| side * v[1] > SIDESTEP.max(v[0].abs()))),
            reversing: reversals as f64 / windows.max(1) as f64,
            ranges,
            velocities,
        }
    }
}
