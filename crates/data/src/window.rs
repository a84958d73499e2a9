//! Training windows: history `O_t = [s_{t-N}, a_{t-N}, ..., s_t]` and future
//! `tau_t = [a_t, s_{t+1}, a_{t+1}, ..., s_{t+H}, a_{t+H}]` (docs/conventions.md, section 2), with every state's
//! global part (root position, velocity, rotation) re-expressed in the character frame of
//! step t, its local part as stored. Windows never cross an episode boundary.

use crate::DataError;
use crate::format::{Dataset, Shard};
use flowmimic_geom::{DVec3, from_rotvec, rotvec, wrap_angle, yaw_quat};
use flowmimic_io::tensors::{self, TensorFile};
use flowmimic_sim::state::offset;
use flowmimic_sim::{CONTROL_HZ, NUM_DOFS, STATE_DIM};
use serde::{Deserialize, Serialize};

/// History length N and horizon H.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct WindowSpec {
    pub history: usize,
    pub horizon: usize,
}

impl WindowSpec {
    /// States in a window: N + 1 in the history, H in the future.
    pub fn states(&self) -> usize {
        self.history + 1 + self.horizon
    }

    /// Actions in a window: N in the history, H + 1 in the future.
    pub fn actions(&self) -> usize {
        self.history + 1 + self.horizon
    }
}

/// One window: `states[k]` is s_{t-N+k}, `actions[k]` is a_{t-N+k}, both for k in
/// 0..N+1+H; the history is states 0..=N and actions 0..N, the future the rest.
#[derive(Clone, Debug, PartialEq)]
pub struct Window {
    pub states: Vec<f32>,
    pub actions: Vec<f32>,
}

/// The motion of a stretch of steps: the mean of their root velocities, each in its own
/// heading (forward, left; m/s), and the heading's rate of change (rad/s, the least-squares
/// slope through each step's heading relative to the step before the stretch, 0). Each item
/// is a step's own-heading velocity and relative heading. The joystick's three numbers: what a
/// plan asks of the body, and what a window's future does.
pub fn motion(steps: impl IntoIterator<Item = ([f32; 2], f32)>) -> [f32; 3] {
    let (mut forward, mut left, mut moment, mut squares, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (k, ([vx, vy], yaw)) in steps.into_iter().enumerate() {
        forward += vx;
        left += vy;
        let k = (k + 1) as f32;
        moment += k * yaw;
        squares += k * k;
        n += 1.0;
    }
    [forward / n, left / n, moment / squares * CONTROL_HZ as f32]
}

/// The [`motion`] of up to `steps` steps after step `t` of a shard, as many as its episode
/// holds (`None` where it holds none): what a model with command labels is told a window at
/// `t` does.
pub fn future_motion(shard: &Shard, t: usize, steps: usize) -> Option<[f32; 3]> {
    let heading = |k: usize| shard.root_pose[3 * k + 2];
    let ahead = (t + 1..shard.steps().min(t + 1 + steps))
        .take_while(|&k| shard.done[k - 1] == 0 && shard.rollout[k] == shard.rollout[t]);
    ahead.clone().next()?;
    // A stored state's root velocity is in its own heading.
    Some(motion(ahead.map(|k| {
        let v = &shard.state[k * STATE_DIM + offset::ROOT_VEL..];
        ([v[0], v[1]], wrap_angle(f64::from(heading(k) - heading(t))) as f32)
    })))
}

/// Re-expresses the 165-d state of step k (stored in its own frame) in the frame of step t,
/// given both steps' root poses (x, y, heading).
pub fn reexpress(state: &[f32], pose_k: [f32; 3], pose_t: [f32; 3], out: &mut [f32]) {
    out.copy_from_slice(state);
    let turn = yaw_quat(f64::from(pose_k[2] - pose_t[2]));
    let back = yaw_quat(-f64::from(pose_t[2]));
    let d = back * DVec3::new(f64::from(pose_k[0] - pose_t[0]), f64::from(pose_k[1] - pose_t[1]), 0.0);
    out[offset::ROOT_POS] = d.x as f32;
    out[offset::ROOT_POS + 1] = d.y as f32;
    let v = |i: usize| DVec3::new(state[i].into(), state[i + 1].into(), state[i + 2].into());
    let vel = turn * v(offset::ROOT_VEL);
    let rot = rotvec(turn * from_rotvec(v(offset::ROOT_ROT)));
    for (i, x) in [vel, rot]
        .iter()
        .zip([offset::ROOT_VEL, offset::ROOT_ROT])
        .flat_map(|(x, at)| (0..3).map(move |j| (at + j, x[j])))
    {
        out[i] = x as f32;
    }
}

/// Start indices `t` of all windows of a shard (rows where the whole window lies inside one
/// episode).
pub fn window_starts(shard: &Shard, spec: WindowSpec) -> Vec<usize> {
    let n = shard.steps();
    let (h, f) = (spec.history, spec.horizon);
    (h..n.saturating_sub(f))
        .filter(|&t| {
            // No episode ends inside [t - N, t + H - 1]; the rollout id is constant across it.
            shard.rollout[t - h] == shard.rollout[t + f] && shard.done[t - h..t + f].iter().all(|&d| d == 0)
        })
        .collect()
}

/// The window at `t`.
pub fn window(shard: &Shard, spec: WindowSpec, t: usize) -> Window {
    let pose = |k: usize| [shard.root_pose[3 * k], shard.root_pose[3 * k + 1], shard.root_pose[3 * k + 2]];
    let first = t - spec.history;
    let count = spec.states();
    let mut states = vec![0.0; count * STATE_DIM];
    for (j, out) in states.chunks_mut(STATE_DIM).enumerate() {
        let k = first + j;
        reexpress(&shard.state[k * STATE_DIM..(k + 1) * STATE_DIM], pose(k), pose(t), out);
    }
    let actions = shard.action[first * NUM_DOFS..(first + count) * NUM_DOFS].to_vec();
    Window { states, actions }
}

/// Per-slot feature statistics over windows: mean and standard deviation of each state slot
/// (N + 1 + H of 165) and action slot (N + 1 + H of 69), floored at 1e-3 so constant features
/// (the current step's root x, y) do not divide by zero.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub spec: WindowSpec,
    pub state_mean: Vec<f32>,
    pub state_std: Vec<f32>,
    pub action_mean: Vec<f32>,
    pub action_std: Vec<f32>,
    pub windows: usize,
}

/// Running per-column sums of rows, for their mean and standard deviation.
#[derive(Clone, Debug)]
pub struct Moments {
    sum: Vec<f64>,
    squares: Vec<f64>,
    rows: usize,
}

impl Moments {
    pub fn new(width: usize) -> Self {
        Self { sum: vec![0.0; width], squares: vec![0.0; width], rows: 0 }
    }

    /// Adds every row of `rows` (rows of this width, one after another).
    pub fn add(&mut self, rows: &[f32]) {
        for row in rows.chunks_exact(self.sum.len()) {
            for ((s, q), &x) in self.sum.iter_mut().zip(&mut self.squares).zip(row) {
                *s += f64::from(x);
                *q += f64::from(x) * f64::from(x);
            }
            self.rows += 1;
        }
    }

    /// Mean and standard deviation of each column, the deviation floored at 1e-3 so that a
    /// constant column does not divide by zero.
    pub fn finish(&self) -> (Vec<f32>, Vec<f32>) {
        let n = self.rows.max(1) as f64;
        self.sum
            .iter()
            .zip(&self.squares)
            .map(|(s, q)| {
                let m = s / n;
                (m as f32, ((q / n - m * m).max(0.0).sqrt().max(1e-3)) as f32)
            })
            .unzip()
    }
}

impl Stats {
    pub fn compute<'a>(spec: WindowSpec, shards: impl Iterator<Item = &'a Shard>) -> Self {
        let mut states = Moments::new(spec.states() * STATE_DIM);
        let mut actions = Moments::new(spec.actions() * NUM_DOFS);
        for shard in shards {
            for t in window_starts(shard, spec) {
                let w = window(shard, spec, t);
                states.add(&w.states);
                actions.add(&w.actions);
            }
        }
        let (state_mean, state_std) = states.finish();
        let (action_mean, action_std) = actions.finish();
        Self { spec, state_mean, state_std, action_mean, action_std, windows: states.rows }
    }
}

impl Stats {
    /// `stats-N<history>-H<horizon>.safetensors` in the dataset directory.
    pub fn file_name(spec: WindowSpec) -> String {
        format!("stats-N{}-H{}.safetensors", spec.history, spec.horizon)
    }

    /// The dataset's statistics for `spec`: read from disk when stored for the same shards,
    /// otherwise computed once over all shards and stored.
    pub fn of_dataset(dataset: &Dataset, spec: WindowSpec) -> Result<Self, DataError> {
        let path = dataset.dir.join(Self::file_name(spec));
        let shards_key = dataset.shards_key();
        if path.exists() {
            let (stats, key) = Self::load(&path)?;
            if key == shards_key && stats.spec == spec {
                return Ok(stats);
            }
        }
        let shards = dataset.load_all()?;
        let stats = Self::compute(spec, shards.iter().map(|(_, s)| s));
        stats.save(&path, &shards_key)?;
        Ok(stats)
    }

    /// Writes the statistics with the checksums of the shards they were computed over.
    pub fn save(&self, path: &std::path::Path, shards_key: &str) -> Result<(), DataError> {
        let slots = self.spec.states();
        let meta = [
            ("history", self.spec.history.to_string()),
            ("horizon", self.spec.horizon.to_string()),
            ("windows", self.windows.to_string()),
            ("shards_sha256", shards_key.to_string()),
        ]
        .map(|(k, v)| (k.to_string(), v));
        tensors::save(
            path,
            &[
                ("state_mean", vec![slots, STATE_DIM], &self.state_mean),
                ("state_std", vec![slots, STATE_DIM], &self.state_std),
                ("action_mean", vec![slots, NUM_DOFS], &self.action_mean),
                ("action_std", vec![slots, NUM_DOFS], &self.action_std),
            ],
            meta.into_iter().collect(),
        )?;
        Ok(())
    }

    /// Reads a stats file, returning it and the shard checksums it was computed over.
    pub fn load(path: &std::path::Path) -> Result<(Self, String), DataError> {
        let file = TensorFile::open(path)?;
        let num =
            |k: &str| file.meta(k)?.parse::<usize>().map_err(|_| file.error(format!("metadata '{k}' is not a count")));
        let spec = WindowSpec { history: num("history")?, horizon: num("horizon")? };
        let slots = spec.states();
        let stats = Self {
            spec,
            state_mean: file.f32("state_mean", &[slots, STATE_DIM])?,
            state_std: file.f32("state_std", &[slots, STATE_DIM])?,
            action_mean: file.f32("action_mean", &[slots, NUM_DOFS])?,
            action_std: file.f32("action_std", &[slots, NUM_DOFS])?,
            windows: num("windows")?,
        };
        Ok((stats, file.meta("shards_sha256").unwrap_or_default().to_string()))
    }
}
