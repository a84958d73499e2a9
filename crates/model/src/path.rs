//! The straight probability path `x_s = (1 - s) x_0 + s x_1` from noise `x_0 ~ N(0, I)` (s = 0)
//! to data `x_1` (s = 1), which Flow Matching and MeanFlow share, and the two things a flow
//! network can predict on it: the velocity `x_1 - x_0`, or the clean sample, read as the
//! velocity `(x_hat - x_s) / (1 - s)` ([`CleanSample`]).

use crate::{Network, TrainingBatch};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

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
