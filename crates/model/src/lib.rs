//! The generative trajectory model's mathematics, kept apart from any network (as Meta's
//! `flow_matching` library separates paths, solvers and guidance):
//!
//! - [`Network`]: anything that maps a noised batch, its noise level and a conditioning batch
//!   to a prediction (the Transformer over trajectory tokens, or a small MLP in tests);
//! - [`fm`]: Flow Matching on the linear path `x_s = (1 - s) x_0 + s x_1` from noise (s = 0)
//!   to data (s = 1), velocity regression, Euler and Heun solvers at any NFE;
//! - [`ddpm`]: the DDPM baseline (epsilon prediction, cosine schedule), respaced to any NFE in
//!   closed form, ancestral sampling;
//! - [`Guidance`]: a cost gradient applied to the predicted clean sample on an interval of
//!   solver steps (`v' = v - w grad G(x_hat)` for FM; the same on DDPM's `x_0` prediction).
//!
//! - [`trajectory`]: the Transformer over per-step tokens with the data's normalisation, and
//!   the sampling API the controller calls;
//! - [`train`]: training either objective on a dataset, checkpoints and the model directory.
//!
//! Batches are flat row-major `f32` slices: `n` rows of the sample dimension.

pub mod ddpm;
pub mod fm;
pub mod train;
pub mod trajectory;

pub use train::{ModelError, TrainConfig, Trainer, WindowSet};
pub use trajectory::{ModelConfig, Objective, TaskGuidance, TokenLayout, TrajectoryModel};

use std::ops::Range;

/// A denoising network: predicts from `x` (n x dim), noise levels `t` (n, in [0, 1]) and
/// conditioning `cond` (n x cond_dim).
pub trait Network {
    fn dim(&self) -> usize;
    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32>;
}

/// Test-time guidance: `grad` returns the gradient of the task cost at the predicted clean
/// samples (n x dim), differentiating the cost only, never the network.
pub struct Guidance<'a> {
    pub weight: f32,
    pub grad: &'a (dyn Fn(&[f32], usize) -> Vec<f32> + Sync),
    /// Solver steps (0-based) on which guidance acts; the paper skips the last 5 of 20.
    pub steps: Range<usize>,
}

impl Guidance<'_> {
    /// `x_hat - scale * weight * grad G(x_hat)` on active steps.
    fn nudge(&self, step: usize, x_hat: &[f32], n: usize, scale: f32) -> Option<Vec<f32>> {
        if !self.steps.contains(&step) || self.weight == 0.0 {
            return None;
        }
        let g = (self.grad)(x_hat, n);
        Some(g.iter().map(|g| scale * self.weight * g).collect())
    }
}

/// A training batch: the network's input, noise levels and regression target.
pub struct TrainingBatch {
    pub x: Vec<f32>,
    pub t: Vec<f32>,
    pub target: Vec<f32>,
}
