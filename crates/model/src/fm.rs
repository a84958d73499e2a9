//! Flow Matching (paper eq. 1): regress `v(x_s, s)` on `x_1 - x_0` along the straight path
//! `x_s = (1 - s) x_0 + s x_1`, `x_0 ~ N(0, I)`; sample by integrating `dx/ds = v` from s = 0.

use crate::guidance::guided_velocity;
use crate::path::on_path;
use crate::{Guidance, Network, TrainingBatch};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// How training draws `s`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum TimeDistribution {
    Uniform,
    /// `s = sigmoid(m + sd * z)`: more weight in the middle of the path (Esser et al. 2024).
    LogitNormal {
        mean: f32,
        std: f32,
    },
}

/// ODE solver for sampling.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Solver {
    /// One network evaluation per step.
    Euler,
    /// Heun's second-order method: two evaluations per step (NFE = 2 x steps, the last step Euler).
    Heun,
}

/// A training batch from clean samples `x1` (n x dim).
pub fn training_batch(x1: &[f32], dim: usize, times: TimeDistribution, rng: &mut impl Rng) -> TrainingBatch {
    let n = x1.len() / dim;
    let t: Vec<f32> = (0..n)
        .map(|_| match times {
            TimeDistribution::Uniform => rng.random::<f32>(),
            TimeDistribution::LogitNormal { mean, std } => {
                let z: f32 = StandardNormal.sample(rng);
                1.0 / (1.0 + (-(mean + std * z)).exp())
            }
        })
        .collect();
    let (x, target) = on_path(x1, dim, |row| t[row], rng);
    TrainingBatch { x, t, target }
}

/// Samples `n` trajectories with `nfe` network evaluations from noise `x0` (n x dim).
/// With guidance, each active step uses `v' = v - w grad_x G(x_hat)`, `x_hat = x + (1 - s) v`.
pub fn sample(
    net: &dyn Network,
    cond: &[f32],
    x0: Vec<f32>,
    n: usize,
    nfe: usize,
    solver: Solver,
    guidance: Option<&Guidance>,
) -> Vec<f32> {
    let steps = match solver {
        Solver::Euler => nfe.max(1),
        Solver::Heun => (nfe / 2).max(1),
    };
    let h = 1.0 / steps as f32;
    let mut x = x0;
    let velocity = |x: &[f32], s: f32, step: usize| -> Vec<f32> {
        guided_velocity(net, x, (s, &vec![s; n]), cond, n, guidance, step)
    };
    for step in 0..steps {
        let s = step as f32 * h;
        let v = velocity(&x, s, step);
        if solver == Solver::Heun && step + 1 < steps {
            let predicted: Vec<f32> = x.iter().zip(&v).map(|(x, v)| x + h * v).collect();
            let v2 = velocity(&predicted, s + h, step);
            x.iter_mut().zip(v.iter().zip(&v2)).for_each(|(x, (a, b))| *x += 0.5 * h * (a + b));
        } else {
            x.iter_mut().zip(&v).for_each(|(x, v)| *x += h * v);
        }
    }
    x
}
