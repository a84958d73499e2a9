//! Test-time guidance (paper eq. 2): the gradient of a cost of the predicted clean sample
//! `x_hat(x)` with respect to the noisy sample `x`, applied on an interval of solver steps
//! (`v' = v - w grad_x G(x_hat(x))` for Flow Matching and MeanFlow; the same on DDPM's `x_0`
//! prediction). It is taken through the network by a vector-Jacobian product
//! ([`Gradient::ThroughNetwork`], DPS-style: the network's learned coupling carries a cost on
//! states into the actions), or of the cost alone, treating `d x_hat / d x` as the identity
//! ([`Gradient::CostOnly`]). Meta's `flow_matching` keeps guidance out of its core; here it is
//! this crate's own layer, which every sampler calls.

use crate::Network;
use std::ops::Range;

/// How the guidance gradient with respect to the noisy sample is taken.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Gradient {
    /// `(d x_hat / d x)^T grad G(x_hat)` by a vector-Jacobian product through the network.
    #[default]
    ThroughNetwork,
    /// `grad G(x_hat)`: the cost's gradient alone, as if `x_hat` were `x`.
    CostOnly,
}

/// Test-time guidance: `grad` returns the gradient of the task cost at the predicted clean
/// samples (n x dim); `gradient` says how it is carried back to the noisy sample.
pub struct Guidance<'a> {
    pub weight: f32,
    pub grad: &'a (dyn Fn(&[f32], usize) -> Vec<f32> + Sync),
    /// Solver steps (0-based) on which guidance acts; the paper skips the last 5 of 20.
    pub steps: Range<usize>,
    pub gradient: Gradient,
}

/// A network's prediction at `x` and, on guided steps, `weight * grad_x G(x_hat(x))`, where
/// `x_hat = a x + b y` is the clean sample the objective infers from the prediction `y`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn guided_prediction(
    net: &dyn Network,
    x: &[f32],
    t: &[f32],
    cond: &[f32],
    n: usize,
    (a, b): (f32, f32),
    guidance: Option<&Guidance>,
    step: usize,
) -> (Vec<f32>, Option<Vec<f32>>) {
    let Some(g) = guidance.filter(|g| g.steps.contains(&step) && g.weight != 0.0) else {
        return (net.predict(x, t, cond, n), None);
    };
    let x_hat = |y: &[f32]| -> Vec<f32> { x.iter().zip(y).map(|(x, y)| a * x + b * y).collect() };
    let (y, grad_x) = match g.gradient {
        Gradient::CostOnly => {
            let y = net.predict(x, t, cond, n);
            let grad = (g.grad)(&x_hat(&y), n);
            (y, grad)
        }
        Gradient::ThroughNetwork => {
            // grad_x G = a grad G + (dy/dx)^T (b grad G), with grad G at x_hat(y).
            let mut at_x_hat = Vec::new();
            let (y, pulled) = net.predict_pullback(x, t, cond, n, &mut |y| {
                at_x_hat = (g.grad)(&x_hat(y), n);
                at_x_hat.iter().map(|g| b * g).collect()
            });
            let grad = at_x_hat.iter().zip(&pulled).map(|(g, p)| a * g + p).collect();
            (y, grad)
        }
    };
    (y, Some(grad_x.into_iter().map(|v: f32| g.weight * v).collect()))
}

/// The velocity along the straight path at `x` (time `s`, network times `t`), less
/// `w grad_x G(x_hat)` on guided steps, with the clean estimate `x_hat = x + (1 - s) v`: the
/// step Flow Matching's and MeanFlow's samplers both take.
#[allow(clippy::too_many_arguments)]
pub(crate) fn guided_velocity(
    net: &dyn Network,
    x: &[f32],
    (s, t): (f32, &[f32]),
    cond: &[f32],
    n: usize,
    guidance: Option<&Guidance>,
    step: usize,
) -> Vec<f32> {
    let (mut v, delta) = guided_prediction(net, x, t, cond, n, (1.0, 1.0 - s), guidance, step);
    if let Some(delta) = delta {
        v.iter_mut().zip(delta).for_each(|(v, d)| *v -= d);
    }
    v
}
