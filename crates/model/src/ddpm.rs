//! The DDPM baseline (Ho et al. 2020) with the cosine schedule (Nichol & Dhariwal 2021):
//! `x_k = sqrt(abar_k) x_0 + sqrt(1 - abar_k) eps`. The network predicts either `eps`
//! (Diffusion Policy's choice) or the clean sample `x_0` ([`Prediction`]); the trajectory model
//! uses `x_0`, because an epsilon model must reproduce its 1,941-dimensional input noise
//! exactly at high noise levels (any error is amplified by `1 / sqrt(abar)` in the `x_0`
//! estimate), which a Transformer whose width (128) is below its token width (234) cannot do:
//! measured, its epsilon error at k = T stayed at 0.46 instead of about 0, and sampling
//! diverged. Sampling at any NFE respaces the schedule in closed form: for chosen steps `k_1 < ... < k_M = T`,
//! `abar'_i = abar_{k_i}` and `beta'_i = 1 - abar_{k_i} / abar_{k_{i-1}}` (with `abar_{k_0} = 1`).

use crate::guidance::guided_prediction;
use crate::{Guidance, Network, TrainingBatch};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Cumulative `abar_k` for k = 0..=T (abar_0 = 1) of the cosine schedule, betas capped at 0.999.
#[derive(Clone, Debug, PartialEq)]
pub struct Schedule {
    pub alpha_bar: Vec<f64>,
}

impl Schedule {
    pub fn cosine(steps: usize) -> Self {
        let f = |k: f64| (((k / steps as f64) + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2);
        let mut alpha_bar = vec![1.0];
        for k in 1..=steps {
            let beta = (1.0 - f(k as f64) / f((k - 1) as f64)).min(0.999);
            alpha_bar.push(alpha_bar[k - 1] * (1.0 - beta));
        }
        Self { alpha_bar }
    }

    /// Training steps T.
    pub fn steps(&self) -> usize {
        self.alpha_bar.len() - 1
    }

    /// The `nfe` steps sampling visits, evenly spaced from T down, always including T.
    pub fn respaced_steps(&self, nfe: usize) -> Vec<usize> {
        let t = self.steps();
        let m = nfe.clamp(1, t);
        (1..=m).map(|i| ((i * t) as f64 / m as f64).round() as usize).collect()
    }

    /// `beta'` of the respaced schedule, aligned with `respaced_steps`.
    pub fn respaced_betas(&self, steps: &[usize]) -> Vec<f64> {
        let mut prev = 1.0;
        steps
            .iter()
            .map(|&k| {
                let beta = 1.0 - self.alpha_bar[k] / prev;
                prev = self.alpha_bar[k];
                beta
            })
            .collect()
    }
}

/// What the network predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Prediction {
    /// The noise `eps`.
    Epsilon,
    /// The clean sample `x_0`.
    Sample,
}

impl Prediction {
    /// The default of model files that do not say.
    pub fn epsilon() -> Self {
        Prediction::Epsilon
    }
}

/// A training batch: `k ~ U{1..T}`, noise level `t = k / T`, target `eps` or `x_0`.
pub fn training_batch(
    schedule: &Schedule,
    prediction: Prediction,
    x0: &[f32],
    dim: usize,
    rng: &mut impl Rng,
) -> TrainingBatch {
    let n = x0.len() / dim;
    let steps = schedule.steps();
    let ks: Vec<usize> = (0..n).map(|_| rng.random_range(1..=steps)).collect();
    let mut x = vec![0.0; x0.len()];
    let mut target = vec![0.0; x0.len()];
    for i in 0..x0.len() {
        let ab = schedule.alpha_bar[ks[i / dim]];
        let eps: f32 = StandardNormal.sample(rng);
        x[i] = (ab.sqrt() as f32) * x0[i] + ((1.0 - ab).sqrt() as f32) * eps;
        target[i] = match prediction {
            Prediction::Epsilon => eps,
            Prediction::Sample => x0[i],
        };
    }
    TrainingBatch { x, t: ks.iter().map(|&k| k as f32 / steps as f32).collect(), target }
}

/// Ancestral sampling with `nfe` network evaluations from noise `x_t` (n x dim). The clean
/// prediction `x_0 = (x_k - sqrt(1 - abar) eps) / sqrt(abar)` is clipped to `[-clip, clip]`
/// (as Diffusion Policy does) and, with guidance, moved by `-w grad_x G(x_0(x))` before the
/// posterior step.
#[allow(clippy::too_many_arguments)]
pub fn sample(
    net: &dyn Network,
    schedule: &Schedule,
    prediction: Prediction,
    cond: &[f32],
    x_t: Vec<f32>,
    n: usize,
    nfe: usize,
    clip: f32,
    guidance: Option<&Guidance>,
    rng: &mut impl Rng,
) -> Vec<f32> {
    let steps = schedule.respaced_steps(nfe);
    let betas = schedule.respaced_betas(&steps);
    let total = schedule.steps() as f32;
    let mut x = x_t;
    for (i, (&k, &beta)) in steps.iter().zip(&betas).enumerate().rev() {
        let step = steps.len() - 1 - i; // 0 for the first (noisiest) solver step
        let ab = schedule.alpha_bar[k];
        let ab_prev = if i == 0 { 1.0 } else { schedule.alpha_bar[steps[i - 1]] };
        let (sa, s1a) = (ab.sqrt() as f32, (1.0 - ab).sqrt() as f32);
        // The clean estimate is a x + b out.
        let ab_coef = match prediction {
            Prediction::Epsilon => (1.0 / sa, -s1a / sa),
            Prediction::Sample => (0.0, 1.0),
        };
        let t = vec![k as f32 / total; n];
        let (out, delta) = guided_prediction(net, &x, &t, cond, n, ab_coef, guidance, step);
        let mut x0: Vec<f32> =
            x.iter().zip(&out).map(|(x, o)| (ab_coef.0 * x + ab_coef.1 * o).clamp(-clip, clip)).collect();
        if let Some(delta) = delta {
            x0.iter_mut().zip(delta).for_each(|(x, d)| *x -= d);
        }
        if i == 0 {
            return x0;
        }
        // Posterior q(x_prev | x_k, x_0) of the respaced chain.
        let c0 = (ab_prev.sqrt() * beta / (1.0 - ab)) as f32;
        let ck = ((1.0 - beta).sqrt() * (1.0 - ab_prev) / (1.0 - ab)) as f32;
        let sd = (beta * (1.0 - ab_prev) / (1.0 - ab)).sqrt() as f32;
        for (x, x0) in x.iter_mut().zip(&x0) {
            let z: f32 = StandardNormal.sample(rng);
            *x = c0 * x0 + ck * *x + sd * z;
        }
    }
    x
}
