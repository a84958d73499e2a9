//! Flow Matching (paper eq. 1): regress `v(x_s, s)` on `x_1 - x_0` along the straight path
//! `x_s = (1 - s) x_0 + s x_1`, `x_0 ~ N(0, I)`; sample by integrating `dx/ds = v` from s = 0.

use crate::{Guidance, Network, TrainingBatch, guided_velocity};
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

/// What a flow network (Flow Matching's or MeanFlow's) predicts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Prediction {
    /// The velocity `x_1 - x_0` (or MeanFlow's average velocity) itself: the paper's choice.
    #[default]
    Velocity,
    /// The clean sample `x_hat`, read as the velocity `(x_hat - x_s) / (1 - s)` (Li and He 2025,
    /// "Back to Basics"): a velocity network must cancel its input noise exactly, which at s = 0
    /// is all of it; a clean-sample network never has to reproduce the noise.
    Sample,
}

/// Smallest `1 - s` a clean-sample network divides by (near the data end of the path).
const MIN_REMAINING: f32 = 0.05;

/// `1 - s` of each row, from its first time, kept off zero.
fn remaining(t: &[f32], n: usize) -> Vec<f32> {
    let times = t.len() / n.max(1);
    (0..n).map(|i| (1.0 - t[i * times]).max(MIN_REMAINING)).collect()
}

/// A network that predicts the clean sample, seen by the samplers and by MeanFlow's target as
/// one that predicts the velocity `(x_hat - x_s) / (1 - s)`.
pub struct CleanSample<'a>(pub &'a dyn Network);

/// The velocity `(x_hat - x) / c` of each row (`c`: each row's `1 - s`).
fn velocity(x_hat: &[f32], x: &[f32], c: &[f32], dim: usize) -> Vec<f32> {
    x_hat.iter().zip(x).enumerate().map(|(j, (d, x))| (d - x) / c[j / dim]).collect()
}

impl Network for CleanSample<'_> {
    fn dim(&self) -> usize {
        self.0.dim()
    }

    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32> {
        velocity(&self.0.predict(x, t, cond, n), x, &remaining(t, n), self.dim())
    }

    /// `v = (x_hat - x) / c`, so `(dv/dx)^T u = (dx_hat/dx)^T (u / c) - u / c`.
    fn predict_pullback(
        &self,
        x: &[f32],
        t: &[f32],
        cond: &[f32],
        n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>) {
        let dim = self.dim();
        let c = remaining(t, n);
        let (mut v, mut u_over_c) = (Vec::new(), Vec::new());
        let (_, pulled) = self.0.predict_pullback(x, t, cond, n, &mut |x_hat| {
            v = velocity(x_hat, x, &c, dim);
            u_over_c = cotangent(&v).iter().enumerate().map(|(j, u)| u / c[j / dim]).collect();
            u_over_c.clone()
        });
        let grad = pulled.iter().zip(&u_over_c).map(|(p, u)| p - u).collect();
        (v, grad)
    }
}

/// Turns a batch whose target is a velocity into one whose target is the clean sample that
/// velocity implies, `x_s + (1 - s) v`: the regression target of a [`CleanSample`] network
/// (for Flow Matching, `x_1` itself wherever `1 - s` is above its floor).
pub fn clean_sample_target(mut batch: TrainingBatch, dim: usize) -> TrainingBatch {
    let c = remaining(&batch.t, batch.x.len() / dim);
    for (j, (target, x)) in batch.target.iter_mut().zip(&batch.x).enumerate() {
        *target = x + c[j / dim] * *target;
    }
    batch
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

/// Points `x_s = (1 - s) x_0 + s x_1` with fresh noise `x_0`, at the time `s_of(row)` of each
/// row of `x1` (n x dim), and the path's velocity `x_1 - x_0` there.
pub(crate) fn on_path(x1: &[f32], dim: usize, s_of: impl Fn(usize) -> f32, rng: &mut impl Rng) -> (Vec<f32>, Vec<f32>) {
    let mut x = vec![0.0; x1.len()];
    let mut v = vec![0.0; x1.len()];
    for i in 0..x1.len() {
        let x0: f32 = StandardNormal.sample(rng);
        let s = s_of(i / dim);
        x[i] = (1.0 - s) * x0 + s * x1[i];
        v[i] = x1[i] - x0;
    }
    (x, v)
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
