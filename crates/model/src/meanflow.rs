//! MeanFlow (Geng et al. 2025): on Flow Matching's straight path `x_s = (1 - s) x_0 + s x_1`
//! (noise at s = 0, data at s = 1), regress the *average* velocity over an interval,
//! `u(x_s, s, r) = (z_r - z_s) / (r - s)` along the sampling ODE's solution `z`, so that one step
//! `x_r = x_s + (r - s) u` crosses the whole interval: at NFE 1 a single network evaluation goes
//! from noise to data. The network takes two times per sample, the start `s` and the interval's
//! length `r - s`; a length of 0 asks for the instantaneous velocity, Flow Matching's target.
//!
//! The target for an interval comes from the network itself, one of two ways ([`Consistency`]):
//!
//! - the MeanFlow identity `u = v + (r - s) du/ds`, where `v = x_1 - x_0` and
//!   `du/ds = v . d_x u + d_s u` is the total derivative along the path with `r` held (so the
//!   length input shrinks as `s` grows). That derivative is a Jacobian-vector product; here it
//!   is a central difference of two network evaluations, and like the paper's JVP it is not
//!   differentiated (stop-gradient), so training needs no forward-mode autodiff;
//! - interval splitting (SplitMeanFlow, Guo et al. 2025; shortcut models' self-consistency,
//!   Frans et al. 2024, at a random split instead of the midpoint): crossing `[s, m]` and then
//!   `[m, r]` from where the first jump lands is crossing `[s, r]`, so
//!   `(r - s) u(x, s, r) = (m - s) u(x, s, m) + (r - m) u(x + (m - s) u(x, s, m), m, r)`. It uses
//!   the network's values, not its derivatives, and on the toy mixture its one step lands where
//!   the identity's does not at the same budget (`tests/toy.rs`).

use crate::guidance::guided_velocity;
use crate::{Guidance, Network, TrainingBatch, path};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// How the target of a sample with an interval is made from the network (module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Consistency {
    /// The MeanFlow identity `u = v + (r - s) du/ds`.
    #[default]
    Derivative,
    /// Two jumps at a random split `m` of `[s, r]` make one.
    Split,
}

/// Step of the central difference along the path: small against the fastest time feature
/// (1000 rad per unit of time), large against f32 rounding of outputs of order 1.
const DIFFERENCE_STEP: f32 = 1e-4;

/// A training batch from clean samples `x1` (n x dim): a share `share` of the samples get an
/// interval `r > s`, the rest `r = s` (the plain Flow Matching target). Times `t` are
/// `[s, r - s]` per sample.
pub fn training_batch(
    net: &dyn Network,
    cond: &[f32],
    x1: &[f32],
    dim: usize,
    (share, consistency): (f32, Consistency),
    rng: &mut impl Rng,
) -> TrainingBatch {
    let n = x1.len() / dim;
    let mut t = Vec::with_capacity(2 * n);
    let mut splits = Vec::with_capacity(n);
    for _ in 0..n {
        let (a, b) = (rng.random::<f32>(), rng.random::<f32>());
        let (s, r) = if rng.random::<f32>() < share { (a.min(b), a.max(b)) } else { (a, a) };
        t.extend([s, r - s]);
        // Drawn only where used, so that the identity's batches stay as they were.
        splits.push(if consistency == Consistency::Split { rng.random::<f32>() } else { 0.0 });
    }
    let (x, v) = path::on_path(x1, dim, |row| t[2 * row], rng);
    let mut target = v.clone();
    let wide: Vec<usize> = (0..n).filter(|&i| t[2 * i + 1] > 0.0).collect();
    if wide.is_empty() {
        return TrainingBatch { x, t, target };
    }
    let c = cond.len() / n.max(1);
    let rows = |i: &usize| i * dim..(i + 1) * dim;
    let cond_w: Vec<f32> = wide.iter().flat_map(|&i| cond[i * c..(i + 1) * c].to_vec()).collect();
    let predict = |xs: &[f32], ts: &[f32]| net.predict(xs, ts, &cond_w, wide.len());
    let u = match consistency {
        Consistency::Derivative => {
            // du/ds by a central difference along (v, 1, -1).
            let shifted = |h: f32| -> Vec<f32> {
                let xs: Vec<f32> = wide.iter().flat_map(|i| rows(i).map(|j| x[j] + h * v[j])).collect();
                let ts: Vec<f32> = wide.iter().flat_map(|&i| [t[2 * i] + h, t[2 * i + 1] - h]).collect();
                predict(&xs, &ts)
            };
            let (plus, minus) = (shifted(DIFFERENCE_STEP), shifted(-DIFFERENCE_STEP));
            let v_w: Vec<f32> = wide.iter().flat_map(|i| v[rows(i)].to_vec()).collect();
            (0..v_w.len())
                .map(|j| {
                    let length = t[2 * wide[j / dim] + 1];
                    v_w[j] + length * ((plus[j] - minus[j]) / (2.0 * DIFFERENCE_STEP))
                })
                .collect::<Vec<f32>>()
        }
        Consistency::Split => {
            // The first part `[s, m]` from x, the second `[m, r]` from where the first lands.
            let x_w: Vec<f32> = wide.iter().flat_map(|i| x[rows(i)].to_vec()).collect();
            let first: Vec<f32> = wide.iter().flat_map(|&i| [t[2 * i], splits[i] * t[2 * i + 1]]).collect();
            let u1 = predict(&x_w, &first);
            let landed: Vec<f32> =
                x_w.iter().zip(&u1).enumerate().map(|(j, (x, u))| x + first[2 * (j / dim) + 1] * u).collect();
            let second: Vec<f32> = wide
                .iter()
                .flat_map(|&i| [t[2 * i] + splits[i] * t[2 * i + 1], (1.0 - splits[i]) * t[2 * i + 1]])
                .collect();
            let u2 = predict(&landed, &second);
            (0..u1.len())
                .map(|j| {
                    let m = splits[wide[j / dim]];
                    m * u1[j] + (1.0 - m) * u2[j]
                })
                .collect()
        }
    };
    for (k, i) in wide.iter().enumerate() {
        target[rows(i)].copy_from_slice(&u[k * dim..(k + 1) * dim]);
    }
    TrainingBatch { x, t, target }
}

/// Samples `n` trajectories from noise `x0` (n x dim) in `nfe` equal jumps. With guidance, each
/// active step uses `u' = u - w grad_x G(x_hat)` with the clean estimate `x_hat = x + (1 - s) u`:
/// exact on the last jump (and so at NFE 1), where the step's interval reaches the data.
pub fn sample(
    net: &dyn Network,
    cond: &[f32],
    x0: Vec<f32>,
    n: usize,
    nfe: usize,
    guidance: Option<&Guidance>,
) -> Vec<f32> {
    let steps = nfe.max(1);
    let h = 1.0 / steps as f32;
    let mut x = x0;
    for step in 0..steps {
        let s = step as f32 * h;
        let times: Vec<f32> = (0..n).flat_map(|_| [s, h]).collect();
        let u = guided_velocity(net, &x, (s, &times), cond, n, guidance, step);
        x.iter_mut().zip(&u).for_each(|(x, u)| *x += h * u);
    }
    x
}
