//! The generative trajectory model's mathematics, kept apart from any network. Meta's
//! `flow_matching` splits its core into paths (with their schedulers), solvers and losses; here:
//!
//! - [`Network`]: anything that maps a noised batch, its noise level and a conditioning batch
//!   to a prediction (the Transformer over trajectory tokens, or a small MLP in tests);
//! - [`path`]: the straight path `x_s = (1 - s) x_0 + s x_1` from noise (s = 0) to data
//!   (s = 1) and what a flow network predicts on it, the velocity or the clean sample
//!   ([`path::CleanSample`]), for Flow Matching and MeanFlow alike;
//! - [`fm`]: Flow Matching's velocity regression and its Euler and Heun solvers at any NFE;
//! - [`meanflow`]: MeanFlow on the same path, regressing the average velocity over an interval,
//!   so that one network evaluation can jump from noise to data (NFE 1);
//! - [`ddpm`]: the DDPM baseline (epsilon or clean-sample prediction, cosine schedule),
//!   respaced to any NFE in closed form, ancestral sampling;
//! - [`guidance`]: the gradient of a task's cost of the predicted clean sample with respect to
//!   the noisy one (paper eq. 2), through the network or of the cost alone: flowmimic's own
//!   layer, which every sampler calls;
//! - [`trajectory`]: the Transformer over per-step tokens with the data's normalisation, and
//!   the sampling API the controller calls;
//! - [`train`]: training any objective on a dataset, checkpoints and the model directory;
//! - [`inverse`]: inverse dynamics, an MLP from a state and the next one to the action taken.
//!
//! Batches are flat row-major `f32` slices: `n` rows of the sample dimension.

pub mod ddpm;
pub mod fm;
pub mod guidance;
pub mod inverse;
pub mod meanflow;
pub mod path;
pub mod train;
pub mod trajectory;

pub use guidance::{Gradient, Guidance};
pub use inverse::{InverseConfig, InverseDynamics};
pub use train::{LrSchedule, ModelError, TrainConfig, Trainer, WindowSet};
pub use trajectory::{Label, ModelConfig, Objective, Pairing, TaskGuidance, TaskLabel, TokenLayout, TrajectoryModel};

/// A denoising network: predicts from `x` (n x dim), noise levels `t` (n, in [0, 1]; n x 2 for
/// MeanFlow's interval start and length) and conditioning `cond` (n x cond_dim).
pub trait Network {
    fn dim(&self) -> usize;
    fn predict(&self, x: &[f32], t: &[f32], cond: &[f32], n: usize) -> Vec<f32>;
    /// The prediction `y` and the vector-Jacobian product `(dy/dx)^T u` for the cotangent
    /// `u = cotangent(y)` (n x dim each).
    fn predict_pullback(
        &self,
        x: &[f32],
        t: &[f32],
        cond: &[f32],
        n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>);
}

/// A training batch: the network's input, noise levels and regression target.
pub struct TrainingBatch {
    pub x: Vec<f32>,
    pub t: Vec<f32>,
    pub target: Vec<f32>,
}
