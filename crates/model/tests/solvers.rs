//! The Flow Matching solvers on an ODE whose solution is known (as Meta's `flow_matching` tests
//! its solvers): with the velocity field `v(x, s) = x`, `x(1) = e x(0)`. Euler's error falls in
//! proportion to the step, Heun's (whose last step is Euler's) to its square.

use flowmimic_model::Network;
use flowmimic_model::fm::{Solver, sample};

/// `v(x, s) = x` for every sample and noise level.
struct Exponential;

impl Network for Exponential {
    fn dim(&self) -> usize {
        1
    }

    fn predict(&self, x: &[f32], _t: &[f32], _cond: &[f32], _n: usize) -> Vec<f32> {
        x.to_vec()
    }

    fn predict_pullback(
        &self,
        x: &[f32],
        _t: &[f32],
        _cond: &[f32],
        _n: usize,
        cotangent: &mut dyn FnMut(&[f32]) -> Vec<f32>,
    ) -> (Vec<f32>, Vec<f32>) {
        (x.to_vec(), cotangent(x))
    }
}

fn error(solver: Solver, nfe: usize) -> f64 {
    let x = sample(&Exponential, &[], vec![1.0], 1, nfe, solver, None);
    (f64::from(x[0]) - std::f64::consts::E).abs()
}

#[test]
fn euler_and_heun_converge_at_their_orders_on_a_known_solution() {
    for nfe in [4, 8, 16, 32] {
        // Euler: x(1) = (1 + 1/N)^N, error about e / (2 N).
        let (coarse, fine) = (error(Solver::Euler, nfe), error(Solver::Euler, 2 * nfe));
        assert!((1.8..2.2).contains(&(coarse / fine)), "Euler NFE {nfe}: error {coarse:.2e} -> {fine:.2e}");
        assert!(
            (coarse - std::f64::consts::E / (2 * nfe) as f64).abs() < 0.3 * coarse,
            "Euler NFE {nfe}: {coarse:.3e}"
        );
        // Heun: two evaluations a step, the error a quarter as the step halves.
        let (coarse, fine) = (error(Solver::Heun, 2 * nfe), error(Solver::Heun, 4 * nfe));
        assert!((3.2..4.8).contains(&(coarse / fine)), "Heun NFE {}: error {coarse:.2e} -> {fine:.2e}", 2 * nfe);
        assert!(coarse < error(Solver::Euler, 2 * nfe), "Heun beats Euler at the same NFE {}", 2 * nfe);
    }
}
