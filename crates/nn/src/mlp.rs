//! A multi-layer perceptron with ELU activations, hand-written forward and backward passes on
//! `matrixmultiply`'s SGEMM, and Adam. Small and explicit, like CleanRL's networks: PPO needs
//! nothing more, and on a CPU this is faster than a general tensor library.

use crate::dense::{self, gemm};
use rand::Rng;
use rand_distr::{Distribution, Normal};

/// One dense layer, weights row-major `[out][in]`.
#[derive(Clone, Debug)]
pub struct Linear {
    pub inputs: usize,
    pub outputs: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

impl Linear {
    fn new(inputs: usize, outputs: usize, gain: f32, rng: &mut impl Rng) -> Self {
        // Scaled normal init (fan-in), the same spirit as orthogonal init with a gain.
        let normal = Normal::new(0.0, gain / (inputs as f32).sqrt()).expect("valid std");
        Self {
            inputs,
            outputs,
            weight: (0..inputs * outputs).map(|_| normal.sample(rng)).collect(),
            bias: vec![0.0; outputs],
        }
    }
}

/// An MLP: hidden layers with ELU, a linear output layer.
#[derive(Clone, Debug)]
pub struct Mlp {
    pub layers: Vec<Linear>,
}

/// Activations kept by a forward pass for the backward pass.
#[derive(Default)]
pub struct Tape {
    /// Input to each layer (the batch input first).
    inputs: Vec<Vec<f32>>,
    /// Output of the network.
    pub output: Vec<f32>,
    n: usize,
}

/// ELU over a slice. `exp_m1` from libm is a call per element, and it took a tenth of a PPO
/// iteration (perf, README "Benchmarks"); this branch-free form vectorises. For x <= 0,
/// x = n ln 2 + r with |r| <= ln 2 / 2 and exp(x) - 1 = 2^n (exp(r) - 1) + (2^n - 1), where
/// exp(r) - 1 is its Taylor series to r^7 (error below 1e-8; no cancellation near 0).
fn elu_in_place(v: &mut [f32]) {
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer without a branch.
    const ROUND: f32 = 12_582_912.0;
    for y in v {
        let x = y.clamp(-87.0, 0.0);
        let t = x * std::f32::consts::LOG2_E + ROUND;
        let n = t - ROUND;
        let r = (x - n * LN2_HI) - n * LN2_LO;
        let mut p = 1.0 / 5040.0;
        for c in [1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5] {
            p = p * r + c;
        }
        let em1 = r + r * r * p;
        // t's low bits hold n (two's complement): 2^n from the bits alone, where a float to
        // integer cast would be one saturating conversion per element.
        let scale = f32::from_bits(t.to_bits().wrapping_sub(ROUND.to_bits()).wrapping_add(127) << 23);
        let negative = scale * em1 + (scale - 1.0);
        *y = if *y > 0.0 { *y } else { negative };
    }
}

impl Mlp {
    /// `sizes` = [inputs, hidden..., outputs]; `output_gain` scales the last layer's init
    /// (small for a policy mean, so actions start near the reference).
    pub fn new(sizes: &[usize], output_gain: f32, rng: &mut impl Rng) -> Self {
        let last = sizes.len() - 2;
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(l, w)| Linear::new(w[0], w[1], if l == last { output_gain } else { 2f32.sqrt() }, rng))
            .collect();
        Self { layers }
    }

    pub fn inputs(&self) -> usize {
        self.layers[0].inputs
    }

    /// Appends `extra` inputs with zero weights: the outputs stay what they were, whatever the
    /// new inputs hold, until training moves their weights.
    pub fn widen_inputs(&mut self, extra: usize) {
        let first = &mut self.layers[0];
        let (i, o) = (first.inputs, first.outputs);
        let mut weight = vec![0.0; o * (i + extra)];
        for (row, old) in weight.chunks_exact_mut(i + extra).zip(first.weight.chunks_exact(i)) {
            row[..i].copy_from_slice(old);
        }
        first.weight = weight;
        first.inputs = i + extra;
    }

    /// Zeroes the last layer: the outputs are 0 whatever the inputs, until training moves it
    /// (the hidden layers keep what they learned).
    pub fn zero_outputs(&mut self) {
        let last = self.layers.last_mut().expect("layers");
        last.weight.fill(0.0);
        last.bias.fill(0.0);
    }

    pub fn outputs(&self) -> usize {
        self.layers.last().expect("layers").outputs
    }

    pub fn num_params(&self) -> usize {
        self.layers.iter().map(|l| l.weight.len() + l.bias.len()).sum()
    }

    /// Forward pass over `n` rows, keeping what backward needs.
    pub fn forward(&self, x: &[f32], n: usize) -> Tape {
        assert_eq!(x.len(), n * self.inputs(), "input has the wrong width");
        let mut tape = Tape { inputs: Vec::with_capacity(self.layers.len()), output: Vec::new(), n };
        let mut current = x.to_vec();
        for (l, layer) in self.layers.iter().enumerate() {
            let mut y = dense::forward(&current, n, &layer.weight, &layer.bias, layer.inputs);
            if l + 1 < self.layers.len() {
                elu_in_place(&mut y);
            }
            tape.inputs.push(std::mem::replace(&mut current, y));
        }
        tape.output = current;
        tape
    }

    /// Forward pass without keeping activations.
    pub fn predict(&self, x: &[f32], n: usize) -> Vec<f32> {
        self.forward(x, n).output
    }

    /// Accumulates parameter gradients (same layout as [`Mlp::params`]) for `d loss / d output`.
    pub fn backward(&self, tape: &Tape, grad_output: &[f32], grads: &mut [f32]) {
        let n = tape.n;
        let mut grad = grad_output.to_vec();
        let mut offset = self.num_params();
        for l in (0..self.layers.len()).rev() {
            let layer = &self.layers[l];
            let (i, o) = (layer.inputs, layer.outputs);
            offset -= layer.weight.len() + layer.bias.len();
            let (gw, gb) = grads[offset..offset + i * o + o].split_at_mut(i * o);
            let x = &tape.inputs[l];
            let Some(mut gx) = dense::backward(x, &grad, n, &layer.weight, i, (gw, gb), l > 0) else {
                break;
            };
            // Through the ELU that produced X (x > 0: 1, else elu(x) + 1).
            for (g, &y) in gx.iter_mut().zip(x) {
                *g *= if y > 0.0 { 1.0 } else { y + 1.0 };
            }
            grad = gx;
        }
    }

    /// All parameters, layer by layer: weights then bias.
    pub fn params(&self) -> Vec<f32> {
        let mut p = Vec::with_capacity(self.num_params());
        for l in &self.layers {
            p.extend_from_slice(&l.weight);
            p.extend_from_slice(&l.bias);
        }
        p
    }

    pub fn set_params(&mut self, p: &[f32]) {
        assert_eq!(p.len(), self.num_params());
        let mut at = 0;
        for l in &mut self.layers {
            let (w, b) = (l.weight.len(), l.bias.len());
            l.weight.copy_from_slice(&p[at..at + w]);
            l.bias.copy_from_slice(&p[at + w..at + w + b]);
            at += w + b;
        }
    }
}

/// Adam over a flat parameter vector.
#[derive(Clone, Debug)]
pub struct Adam {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub t: u64,
}

impl Adam {
    pub fn new(n: usize) -> Self {
        Self { m: vec![0.0; n], v: vec![0.0; n], t: 0 }
    }

    pub fn step(&mut self, params: &mut [f32], grads: &[f32], lr: f32) {
        let (b1, b2, eps) = (0.9f32, 0.999f32, 1e-8f32);
        self.t += 1;
        let c1 = 1.0 - b1.powi(self.t as i32);
        let c2 = 1.0 - b2.powi(self.t as i32);
        // Indexed over slices of one length, so the compiler drops the bounds checks and
        // vectorises the square roots and divisions (the zipped form ran element by element).
        let n = params.len();
        let (grads, m, v) = (&grads[..n], &mut self.m[..n], &mut self.v[..n]);
        for i in 0..n {
            let g = grads[i];
            m[i] = b1 * m[i] + (1.0 - b1) * g;
            v[i] = b2 * v[i] + (1.0 - b2) * g * g;
            params[i] -= lr * (m[i] / c1) / ((v[i] / c2).sqrt() + eps);
        }
    }
}

/// Measured single-precision matrix-multiply throughput of this machine (all of rayon's
/// threads, as the dense layers split large products): the best of `repeats` square
/// `size x size` products, GFLOP/s.
pub fn sgemm_gflops(size: usize, repeats: usize) -> f64 {
    let a: Vec<f32> = (0..size * size).map(|i| (i % 7) as f32 * 0.1).collect();
    let mut c = vec![0.0f32; size * size];
    let s = size as isize;
    let rates: Vec<f64> = (0..repeats.max(1) + 1)
        .map(|_| {
            let t = std::time::Instant::now();
            gemm(size, size, size, (&a, s, 1), (&a, s, 1), &mut c, 0.0);
            std::hint::black_box(&c);
            2.0 * (size as f64).powi(3) / t.elapsed().as_secs_f64() / 1e9
        })
        .skip(1)
        .collect();
    // The best run: a peak, which the machine's other work and clock changes only lower.
    rates.into_iter().fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn elu_matches_libm() {
        let mut xs: Vec<f32> = (-2000..=200).map(|i| i as f32 * 0.01).collect();
        xs.extend([-1e-7, -1e-4, -3e-3, -86.9, -87.5, -200.0, -f32::MAX, f32::MIN_POSITIVE, 1e30]);
        let mut ys = xs.clone();
        elu_in_place(&mut ys);
        for (x, y) in xs.iter().zip(&ys) {
            let want = if *x > 0.0 { *x } else { x.exp_m1() };
            // Relative to the value near 0 (where exp_m1 is tiny), absolute elsewhere.
            let tol = 2e-7 * want.abs().max(1e-3);
            assert!((y - want).abs() <= tol.max(f32::EPSILON * want.abs()), "elu({x}) = {y}, libm {want}");
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let net = Mlp::new(&[5, 7, 6, 3], 1.0, &mut rng);
        let n = 4;
        let x: Vec<f32> = (0..n * 5).map(|i| ((i as f32) * 0.37).sin()).collect();
        let target: Vec<f32> = (0..n * 3).map(|i| ((i as f32) * 0.11).cos()).collect();
        let loss = |net: &Mlp| -> f64 {
            net.predict(&x, n).iter().zip(&target).map(|(y, t)| 0.5 * ((y - t) as f64).powi(2)).sum()
        };
        let tape = net.forward(&x, n);
        let grad_out: Vec<f32> = tape.output.iter().zip(&target).map(|(y, t)| y - t).collect();
        let mut grads = vec![0.0; net.num_params()];
        net.backward(&tape, &grad_out, &mut grads);
        let base = net.params();
        let eps = 1e-3;
        for k in (0..base.len()).step_by(7) {
            let mut p = base.clone();
            p[k] += eps;
            let mut plus = net.clone();
            plus.set_params(&p);
            p[k] -= 2.0 * eps;
            let mut minus = net.clone();
            minus.set_params(&p);
            let fd = (loss(&plus) - loss(&minus)) / (2.0 * eps as f64);
            assert!((fd - grads[k] as f64).abs() < 2e-3 * (1.0 + fd.abs()), "param {k}: fd {fd} vs {}", grads[k]);
        }
    }

    #[test]
    fn adam_fits_a_linear_map() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(2);
        let mut net = Mlp::new(&[3, 16, 2], 1.0, &mut rng);
        let mut opt = Adam::new(net.num_params());
        let n = 64;
        let x: Vec<f32> = (0..n * 3).map(|i| ((i as f32) * 0.7).sin()).collect();
        let y: Vec<f32> = x.chunks(3).flat_map(|r| [r[0] - 2.0 * r[1], 0.5 * r[2] + 1.0]).collect();
        let mse = |net: &Mlp| net.predict(&x, n).iter().zip(&y).map(|(a, b)| (a - b).powi(2)).sum::<f32>() / n as f32;
        let first = mse(&net);
        for _ in 0..500 {
            let tape = net.forward(&x, n);
            let g: Vec<f32> = tape.output.iter().zip(&y).map(|(a, b)| 2.0 * (a - b) / n as f32).collect();
            let mut grads = vec![0.0; net.num_params()];
            net.backward(&tape, &g, &mut grads);
            let mut p = net.params();
            opt.step(&mut p, &grads, 3e-3);
            net.set_params(&p);
        }
        assert!(mse(&net) < 0.01 * first, "mse {} from {first}", mse(&net));
    }
}
