//! A pre-norm Transformer encoder over a fixed number of tokens with a noise-level embedding,
//! hand-written forward and backward passes (gradient-checked below) on SGEMM.
//!
//! ```text
//! h = X W_in + pos[l] + Time(t)                     Time(t) = sinusoids(1000 t) W_t
//! per block: h += Attn(LN(h));  h += W_2 gelu(W_1 LN(h))
//! Y = LN(h) W_out
//! ```
//!
//! Attention is bidirectional over all tokens. Parameters live in one flat vector (so Adam and
//! the checkpoint see a single buffer), addressed through [`Transformer::tensors`], which also
//! names them for safetensors.

use crate::dense;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Sizes of a Transformer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TransformerConfig {
    /// Width of each input and output token.
    pub token_dim: usize,
    /// Tokens per sample (fixed: each position has its own learned embedding).
    pub tokens: usize,
    /// Token width, attention heads and blocks.
    pub d_model: usize,
    pub heads: usize,
    pub layers: usize,
    /// Hidden width of each block's feed-forward network.
    pub d_ff: usize,
    /// Sinusoidal features of the noise level (even).
    pub time_features: usize,
    /// Features of each sample's own (a labelled model's label), embedded together with the
    /// noise level's and so added to every token.
    #[serde(default)]
    pub sample_features: usize,
}

/// A named parameter tensor: its place in the flat vector and its shape.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TensorSlot {
    pub name: String,
    pub at: usize,
    pub shape: Vec<usize>,
}

impl TensorSlot {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn range(&self) -> std::ops::Range<usize> {
        self.at..self.at + self.len()
    }
}

/// Offsets of one block's tensors.
#[derive(Clone, Debug)]
struct Block {
    ln1: (TensorSlot, TensorSlot),
    qkv: (TensorSlot, TensorSlot),
    proj: (TensorSlot, TensorSlot),
    ln2: (TensorSlot, TensorSlot),
    ff1: (TensorSlot, TensorSlot),
    ff2: (TensorSlot, TensorSlot),
}

#[derive(Clone, Debug)]
struct Slots {
    input: (TensorSlot, TensorSlot),
    pos: TensorSlot,
    time: (TensorSlot, TensorSlot),
    blocks: Vec<Block>,
    ln_out: (TensorSlot, TensorSlot),
    output: (TensorSlot, TensorSlot),
    all: Vec<TensorSlot>,
}

/// Lays tensors out one after another.
#[derive(Default)]
struct Layout {
    all: Vec<TensorSlot>,
    at: usize,
}

impl Layout {
    fn slot(&mut self, name: String, shape: Vec<usize>) -> TensorSlot {
        let s = TensorSlot { name, at: self.at, shape };
        self.at += s.len();
        self.all.push(s.clone());
        s
    }

    fn linear(&mut self, name: &str, outputs: usize, inputs: usize) -> (TensorSlot, TensorSlot) {
        (self.slot(format!("{name}.weight"), vec![outputs, inputs]), self.slot(format!("{name}.bias"), vec![outputs]))
    }

    fn norm(&mut self, name: &str, d: usize) -> (TensorSlot, TensorSlot) {
        (self.slot(format!("{name}.gamma"), vec![d]), self.slot(format!("{name}.beta"), vec![d]))
    }
}

impl Slots {
    fn new(c: &TransformerConfig) -> Self {
        let mut t = Layout::default();
        let d = c.d_model;
        let input = t.linear("input", d, c.token_dim);
        let time = t.linear("time", d, c.time_features + c.sample_features);
        let blocks = (0..c.layers)
            .map(|l| Block {
                ln1: t.norm(&format!("blocks.{l}.ln1"), d),
                qkv: t.linear(&format!("blocks.{l}.qkv"), 3 * d, d),
                proj: t.linear(&format!("blocks.{l}.proj"), d, d),
                ln2: t.norm(&format!("blocks.{l}.ln2"), d),
                ff1: t.linear(&format!("blocks.{l}.ff1"), c.d_ff, d),
                ff2: t.linear(&format!("blocks.{l}.ff2"), d, c.d_ff),
            })
            .collect();
        let ln_out = t.norm("ln_out", d);
        let output = t.linear("output", c.token_dim, d);
        let pos = t.slot("pos".into(), vec![c.tokens, d]);
        Self { input, pos, time, blocks, ln_out, output, all: t.all }
    }
}

/// The gradients of a (weight, bias) pair, stored next to each other.
fn pair_mut<'a>(grads: &'a mut [f32], (w, b): &(TensorSlot, TensorSlot)) -> (&'a mut [f32], &'a mut [f32]) {
    debug_assert_eq!(b.at, w.at + w.len());
    grads[w.at..b.at + b.len()].split_at_mut(w.len())
}

/// A Transformer and its parameters.
#[derive(Clone, Debug)]
pub struct Transformer {
    pub config: TransformerConfig,
    pub params: Vec<f32>,
    slots: Slots,
}

/// What a forward pass keeps for the backward pass.
pub struct Tape {
    n: usize,
    x: Vec<f32>,
    time_features: Vec<f32>,
    blocks: Vec<BlockTape>,
    final_norm: Norm,
    final_out: Vec<f32>,
    /// The network's output, `n x tokens x token_dim`.
    pub output: Vec<f32>,
}

struct BlockTape {
    norm1: Norm,
    a: Vec<f32>,
    qkv: Vec<f32>,
    probs: Vec<f32>,
    attended: Vec<f32>,
    norm2: Norm,
    b: Vec<f32>,
    pre_gelu: Vec<f32>,
    hidden: Vec<f32>,
}

/// A layer norm's normalised input and inverse standard deviations.
struct Norm {
    xhat: Vec<f32>,
    rstd: Vec<f32>,
}

const GELU_C: f32 = 0.797_884_6; // sqrt(2 / pi)

/// `tanh` as a rational function (Eigen's `ptanh_float` coefficients, within a few ulp of
/// libm): libm's `tanhf` cost a third of the forward pass, and this one vectorises.
#[allow(clippy::excessive_precision)] // the published coefficients, digit for digit
fn tanh(x: f32) -> f32 {
    let x = x.clamp(-7.905_311, 7.905_311);
    let x2 = x * x;
    let mut p = x2 * -2.760_768_5e-16 + 2.000_187_9e-13;
    p = x2 * p - 8.604_671_5e-11;
    p = x2 * p + 5.122_297e-8;
    p = x2 * p + 1.485_722_4e-5;
    p = x2 * p + 6.372_619_3e-4;
    p = x2 * p + 4.893_524_6e-3;
    let mut q = x2 * 1.198_258_4e-6 + 1.185_347_1e-4;
    q = x2 * q + 2.268_434_6e-3;
    q = x2 * q + 4.893_525e-3;
    x * p / q
}

fn gelu(x: f32) -> f32 {
    0.5 * x * (1.0 + tanh(GELU_C * (x + 0.044715 * x * x * x)))
}

fn gelu_grad(x: f32) -> f32 {
    let th = tanh(GELU_C * (x + 0.044715 * x * x * x));
    0.5 * (1.0 + th) + 0.5 * x * (1.0 - th * th) * GELU_C * (1.0 + 3.0 * 0.044715 * x * x)
}

/// A dot product kept in eight running sums, which the compiler holds in vector registers
/// (one running sum would force it to add the products one by one, in order).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let (ac, bc) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ac.remainder().iter().zip(bc.remainder()).map(|(x, y)| x * y).sum();
    let mut acc = [0f32; 8];
    for (x, y) in ac.zip(bc) {
        for j in 0..8 {
            acc[j] += x[j] * y[j];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// Elements in one block of a row-wise pass (layer norm, GELU): a training batch splits into
/// many, which rayon's threads share; a batch-1 control step fits in one and stays on the
/// calling thread, which a hand-off to the pool would only delay. The blocks do not depend on
/// the number of threads, so neither do the sums over them.
const BLOCK_ELEMENTS: usize = 1 << 15;

/// Rows per block of a pass over `rows` rows of `d` elements.
fn block_rows(rows: usize, d: usize) -> usize {
    (BLOCK_ELEMENTS / d).clamp(1, rows.max(1))
}

/// Runs `f` on every block (disjoint chunks of the pass's buffers), on rayon's threads when
/// there is more than one. The results come back in block order, so that a sum over them is the
/// same whatever the threads did.
fn for_blocks<I, T>(blocks: I, f: impl Fn(I::Item) -> T + Sync + Send) -> Vec<T>
where
    I: ExactSizeIterator + Send,
    I::Item: Send,
    T: Send,
{
    if blocks.len() <= 1 {
        return blocks.map(f).collect();
    }
    let mut results: Vec<(usize, T)> = blocks.enumerate().par_bridge().map(|(i, b)| (i, f(b))).collect();
    results.sort_by_key(|(i, _)| *i);
    results.into_iter().map(|(_, t)| t).collect()
}

/// `f(y, x)` for every element of `y` and `x`, in blocks of [`BLOCK_ELEMENTS`].
fn apply(y: &mut [f32], x: &[f32], f: impl Fn(&mut f32, f32) + Sync + Send) {
    let chunk = BLOCK_ELEMENTS.min(x.len()).max(1);
    for_blocks(y.chunks_mut(chunk).zip(x.chunks(chunk)), |(y, x)| y.iter_mut().zip(x).for_each(|(y, &x)| f(y, x)));
}

fn layer_norm(x: &[f32], d: usize, gamma: &[f32], beta: &[f32]) -> (Vec<f32>, Norm) {
    let rows = x.len() / d;
    let mut xhat = vec![0.0; x.len()];
    let mut rstd = vec![0.0; rows];
    let mut y = vec![0.0; x.len()];
    let block = block_rows(rows, d);
    let blocks = x.chunks(block * d).zip(xhat.chunks_mut(block * d)).zip(y.chunks_mut(block * d));
    for_blocks(blocks.zip(rstd.chunks_mut(block)), |(((x, xhat), y), rstd)| {
        for (r, rstd) in rstd.iter_mut().enumerate() {
            let row = &x[r * d..(r + 1) * d];
            let mean = row.iter().sum::<f32>() / d as f32;
            let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d as f32;
            *rstd = 1.0 / (var + 1e-5).sqrt();
            for j in 0..d {
                let h = (row[j] - mean) * *rstd;
                xhat[r * d + j] = h;
                y[r * d + j] = gamma[j] * h + beta[j];
            }
        }
    });
    (y, Norm { xhat, rstd })
}

/// Accumulates the norm's parameter gradients (gamma, beta) when given and returns `dx`.
fn layer_norm_backward(dy: &[f32], norm: &Norm, gamma: &[f32], params: Option<(&mut [f32], &mut [f32])>) -> Vec<f32> {
    let d = gamma.len();
    let mut dx = vec![0.0; dy.len()];
    let block = block_rows(norm.rstd.len(), d);
    let blocks = dy.chunks(block * d).zip(norm.xhat.chunks(block * d)).zip(norm.rstd.chunks(block));
    let param_len = if params.is_some() { d } else { 0 };
    // Each block returns its rows' share of the parameter gradients, added below in block order.
    let shares = for_blocks(blocks.zip(dx.chunks_mut(block * d)), |(((dy, xhat), rstd), dx)| {
        let (mut gg, mut gb) = (vec![0.0; param_len], vec![0.0; param_len]);
        for (r, &rstd) in rstd.iter().enumerate() {
            let (dyr, xh) = (&dy[r * d..(r + 1) * d], &xhat[r * d..(r + 1) * d]);
            let (mut mean_g, mut mean_gx) = (0.0, 0.0);
            for j in 0..d {
                let g = dyr[j] * gamma[j];
                mean_g += g;
                mean_gx += g * xh[j];
            }
            for j in 0..param_len {
                gg[j] += dyr[j] * xh[j];
                gb[j] += dyr[j];
            }
            mean_g /= d as f32;
            mean_gx /= d as f32;
            for j in 0..d {
                dx[r * d + j] = rstd * (dyr[j] * gamma[j] - mean_g - xh[j] * mean_gx);
            }
        }
        (gg, gb)
    });
    if let Some((pg, pb)) = params {
        for (gg, gb) in shares {
            pg.iter_mut().zip(gg).for_each(|(p, g)| *p += g);
            pb.iter_mut().zip(gb).for_each(|(p, g)| *p += g);
        }
    }
    dx
}

/// Sinusoidal features of noise levels `t` in [0, 1] (scaled by 1000, as diffusion models do).
/// With `times` times per sample, each gets `features / times` of them.
fn time_features(t: &[f32], times: usize, features: usize) -> Vec<f32> {
    let half = features / times / 2;
    t.iter()
        .flat_map(|&t| {
            (0..half)
                .map(move |j| 1000.0 * t * (-(10000f32).ln() * j as f32 / half as f32).exp())
                .flat_map(|a| [a.sin(), a.cos()])
        })
        .collect()
}

impl Transformer {
    pub fn new(config: TransformerConfig, rng: &mut impl Rng) -> Self {
        assert!(config.d_model.is_multiple_of(config.heads), "d_model must be a multiple of heads");
        assert!(config.time_features.is_multiple_of(2), "time_features must be even");
        let slots = Slots::new(&config);
        let total = slots.all.iter().map(TensorSlot::len).sum();
        let mut params = vec![0.0; total];
        let mut fill = |s: &TensorSlot, std: f32| {
            let normal = Normal::new(0.0, std).expect("valid std");
            params[s.range()].iter_mut().for_each(|p| *p = normal.sample(rng));
        };
        let fan_in = |s: &TensorSlot| 1.0 / (s.shape[1] as f32).sqrt();
        // Residual branches scaled down with depth (GPT-2); the output starts small so the
        // first predictions are near zero.
        let residual = 1.0 / (2.0 * config.layers as f32).sqrt();
        fill(&slots.input.0, fan_in(&slots.input.0));
        fill(&slots.time.0, fan_in(&slots.time.0));
        fill(&slots.pos, 0.02);
        for b in &slots.blocks {
            fill(&b.qkv.0, fan_in(&b.qkv.0));
            fill(&b.proj.0, fan_in(&b.proj.0) * residual);
            fill(&b.ff1.0, fan_in(&b.ff1.0));
            fill(&b.ff2.0, fan_in(&b.ff2.0) * residual);
        }
        fill(&slots.output.0, 0.1 * fan_in(&slots.output.0));
        let gammas = slots.blocks.iter().flat_map(|b| [&b.ln1.0, &b.ln2.0]).chain([&slots.ln_out.0]);
        for gamma in gammas {
            params[gamma.range()].fill(1.0);
        }
        Self { config, params, slots }
    }

    pub fn num_params(&self) -> usize {
        self.params.len()
    }

    /// The named tensors of the flat parameter vector, in storage order.
    pub fn tensors(&self) -> &[TensorSlot] {
        &self.slots.all
    }

    fn p(&self, s: &TensorSlot) -> &[f32] {
        &self.params[s.range()]
    }

    /// Multiply-adds of one forward pass over one sample, x 2 (FLOPs).
    pub fn flops_per_sample(&self) -> f64 {
        let c = &self.config;
        let (l, d) = (c.tokens as f64, c.d_model as f64);
        let block = l * (4.0 * d * d + 2.0 * d * c.d_ff as f64) + 2.0 * l * l * d;
        2.0 * (l * 2.0 * d * c.token_dim as f64 + c.layers as f64 * block)
    }

    /// Forward pass: `x` is `n x tokens x token_dim`, `t` the noise levels (`n`, or `n x k`
    /// for a model of k times, such as an interval's start and length).
    pub fn forward(&self, x: &[f32], t: &[f32], n: usize) -> Tape {
        self.forward_with(x, t, &[], n)
    }

    /// [`Transformer::forward`] with each sample's own `features` (`n x sample_features`),
    /// embedded with its noise level's.
    pub fn forward_with(&self, x: &[f32], t: &[f32], features: &[f32], n: usize) -> Tape {
        let c = &self.config;
        assert_eq!(features.len(), n * c.sample_features, "features are not n x sample_features");
        let (d, l, rows) = (c.d_model, c.tokens, n * c.tokens);
        assert_eq!(x.len(), rows * c.token_dim, "input is not n x tokens x token_dim");
        let times = t.len().checked_div(n).unwrap_or(1);
        assert!(times >= 1 && t.len() == n * times, "the same number of noise levels for every sample");
        assert!(c.time_features.is_multiple_of(2 * times), "time_features must split evenly between the times");
        let s = &self.slots;
        let mut tf = time_features(t, times, c.time_features);
        if c.sample_features > 0 {
            let (own, sines) = (features.chunks_exact(c.sample_features), tf.chunks_exact(c.time_features));
            tf = sines.zip(own).flat_map(|(a, b)| a.iter().chain(b).copied()).collect();
        }
        let temb = dense::forward(&tf, n, self.p(&s.time.0), self.p(&s.time.1), c.time_features + c.sample_features);
        let mut h = dense::forward(x, rows, self.p(&s.input.0), self.p(&s.input.1), c.token_dim);
        let pos = self.p(&s.pos);
        for (r, row) in h.chunks_exact_mut(d).enumerate() {
            let (p, e) = (&pos[(r % l) * d..(r % l + 1) * d], &temb[(r / l) * d..(r / l + 1) * d]);
            row.iter_mut().zip(p.iter().zip(e)).for_each(|(h, (p, e))| *h += p + e);
        }
        let mut blocks = Vec::with_capacity(c.layers);
        for b in &s.blocks {
            let (a, norm1) = layer_norm(&h, d, self.p(&b.ln1.0), self.p(&b.ln1.1));
            let qkv = dense::forward(&a, rows, self.p(&b.qkv.0), self.p(&b.qkv.1), d);
            let (attended, probs) = self.attention(&qkv, n);
            let out = dense::forward(&attended, rows, self.p(&b.proj.0), self.p(&b.proj.1), d);
            h.iter_mut().zip(&out).for_each(|(h, o)| *h += o);
            let (bn, norm2) = layer_norm(&h, d, self.p(&b.ln2.0), self.p(&b.ln2.1));
            let pre_gelu = dense::forward(&bn, rows, self.p(&b.ff1.0), self.p(&b.ff1.1), d);
            let mut hidden = vec![0.0; pre_gelu.len()];
            apply(&mut hidden, &pre_gelu, |h, u| *h = gelu(u));
            let out = dense::forward(&hidden, rows, self.p(&b.ff2.0), self.p(&b.ff2.1), c.d_ff);
            h.iter_mut().zip(&out).for_each(|(h, o)| *h += o);
            blocks.push(BlockTape { norm1, a, qkv, probs, attended, norm2, b: bn, pre_gelu, hidden });
        }
        let (final_out, final_norm) = layer_norm(&h, d, self.p(&s.ln_out.0), self.p(&s.ln_out.1));
        let output = dense::forward(&final_out, rows, self.p(&s.output.0), self.p(&s.output.1), d);
        Tape { n, x: x.to_vec(), time_features: tf, blocks, final_norm, final_out, output }
    }

    /// Forward pass keeping nothing but the output.
    pub fn predict(&self, x: &[f32], t: &[f32], n: usize) -> Vec<f32> {
        self.forward(x, t, n).output
    }

    /// Multi-head attention of every sample: returns the heads' outputs (`rows x d`) and the
    /// attention probabilities (`n x heads x tokens x tokens`).
    fn attention(&self, qkv: &[f32], n: usize) -> (Vec<f32>, Vec<f32>) {
        let c = &self.config;
        let (d, l, heads) = (c.d_model, c.tokens, c.heads);
        let dh = d / heads;
        let scale = 1.0 / (dh as f32).sqrt();
        let mut out = vec![0.0; n * l * d];
        let mut probs = vec![0.0; n * heads * l * l];
        out.par_chunks_mut(l * d).zip(probs.par_chunks_mut(heads * l * l)).enumerate().for_each(|(i, (out, probs))| {
            let qkv = &qkv[i * l * 3 * d..(i + 1) * l * 3 * d];
            for head in 0..heads {
                let (q, k, v) = (head * dh, d + head * dh, 2 * d + head * dh);
                let p = &mut probs[head * l * l..(head + 1) * l * l];
                for a in 0..l {
                    let row = &mut p[a * l..(a + 1) * l];
                    let qa = &qkv[a * 3 * d + q..a * 3 * d + q + dh];
                    for b in 0..l {
                        row[b] = scale * dot(qa, &qkv[b * 3 * d + k..b * 3 * d + k + dh]);
                    }
                    let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                    row.iter_mut().for_each(|x| *x = (*x - max).exp());
                    let sum: f32 = row.iter().sum();
                    row.iter_mut().for_each(|x| *x /= sum);
                    let o = &mut out[a * d + head * dh..a * d + (head + 1) * dh];
                    for b in 0..l {
                        let vb = &qkv[b * 3 * d + v..b * 3 * d + v + dh];
                        o.iter_mut().zip(vb).for_each(|(o, v)| *o += row[b] * v);
                    }
                }
            }
        });
        (out, probs)
    }

    /// Gradient of the attention output `d_out` (`rows x d`) with respect to `qkv`.
    fn attention_backward(&self, qkv: &[f32], probs: &[f32], d_out: &[f32], n: usize) -> Vec<f32> {
        let c = &self.config;
        let (d, l, heads) = (c.d_model, c.tokens, c.heads);
        let dh = d / heads;
        let scale = 1.0 / (dh as f32).sqrt();
        let mut dqkv = vec![0.0; n * l * 3 * d];
        dqkv.par_chunks_mut(l * 3 * d).enumerate().for_each(|(i, dqkv)| {
            let qkv = &qkv[i * l * 3 * d..(i + 1) * l * 3 * d];
            let d_out = &d_out[i * l * d..(i + 1) * l * d];
            let (mut ds, mut dq) = (vec![0.0; l], vec![0.0; dh]);
            for head in 0..heads {
                let (q, k, v) = (head * dh, d + head * dh, 2 * d + head * dh);
                let p = &probs[(i * heads + head) * l * l..(i * heads + head + 1) * l * l];
                for a in 0..l {
                    let row = &p[a * l..(a + 1) * l];
                    let go = &d_out[a * d + head * dh..a * d + (head + 1) * dh];
                    // dP[a][b] = dO[a] . V[b]; dV[b] += P[a][b] dO[a].
                    for b in 0..l {
                        ds[b] = dot(go, &qkv[b * 3 * d + v..b * 3 * d + v + dh]);
                        let dv = &mut dqkv[b * 3 * d + v..b * 3 * d + v + dh];
                        dv.iter_mut().zip(go).for_each(|(dv, g)| *dv += row[b] * g);
                    }
                    // Softmax backward, then the scaled dot product.
                    let mean = dot(row, &ds);
                    let qa = &qkv[a * 3 * d + q..a * 3 * d + q + dh];
                    dq.fill(0.0);
                    for b in 0..l {
                        let g = scale * row[b] * (ds[b] - mean);
                        let kb = &qkv[b * 3 * d + k..b * 3 * d + k + dh];
                        dq.iter_mut().zip(kb).for_each(|(dq, k)| *dq += g * k);
                        let dk = &mut dqkv[b * 3 * d + k..b * 3 * d + k + dh];
                        dk.iter_mut().zip(qa).for_each(|(dk, q)| *dk += g * q);
                    }
                    let dqa = &mut dqkv[a * 3 * d + q..a * 3 * d + q + dh];
                    dqa.iter_mut().zip(&dq).for_each(|(a, g)| *a += g);
                }
            }
        });
        dqkv
    }

    /// Accumulates parameter gradients (layout of `params`) for `d loss / d output`.
    pub fn backward(&self, tape: &Tape, grad_output: &[f32], grads: &mut [f32]) {
        assert_eq!(grads.len(), self.params.len());
        self.backward_pass(tape, grad_output, Some(grads));
    }

    /// The vector-Jacobian product `(d output / d x)^T grad_output` for the input `x` of the
    /// taped forward pass (`n x tokens x token_dim`). No parameter gradient is formed, so this
    /// costs about one forward pass (test-time guidance through the network).
    pub fn input_grad(&self, tape: &Tape, grad_output: &[f32]) -> Vec<f32> {
        self.backward_pass(tape, grad_output, None).expect("asked for the input gradient")
    }

    /// The backward pass: parameter gradients into `grads` when given; otherwise only the
    /// gradient with respect to the input, which it then returns.
    fn backward_pass(&self, tape: &Tape, grad_output: &[f32], mut grads: Option<&mut [f32]>) -> Option<Vec<f32>> {
        let c = &self.config;
        let (d, l, n) = (c.d_model, c.tokens, tape.n);
        let rows = n * l;
        let s = &self.slots;
        let mut dh = {
            let df = self.dense_backward(&s.output, &tape.final_out, grad_output, rows, grads.as_deref_mut(), true);
            self.norm_backward(&s.ln_out, &df.expect("dx"), &tape.final_norm, grads.as_deref_mut())
        };
        for (b, t) in s.blocks.iter().zip(&tape.blocks).rev() {
            // Feed-forward branch.
            let mut du = self.dense_backward(&b.ff2, &t.hidden, &dh, rows, grads.as_deref_mut(), true).expect("dx");
            apply(&mut du, &t.pre_gelu, |g, u| *g *= gelu_grad(u));
            let dbn = self.dense_backward(&b.ff1, &t.b, &du, rows, grads.as_deref_mut(), true).expect("dx");
            let dx = self.norm_backward(&b.ln2, &dbn, &t.norm2, grads.as_deref_mut());
            dh.iter_mut().zip(&dx).for_each(|(a, b)| *a += b);
            // Attention branch.
            let dattn = self.dense_backward(&b.proj, &t.attended, &dh, rows, grads.as_deref_mut(), true).expect("dx");
            let dqkv = self.attention_backward(&t.qkv, &t.probs, &dattn, n);
            let da = self.dense_backward(&b.qkv, &t.a, &dqkv, rows, grads.as_deref_mut(), true).expect("dx");
            let dx = self.norm_backward(&b.ln1, &da, &t.norm1, grads.as_deref_mut());
            dh.iter_mut().zip(&dx).for_each(|(a, b)| *a += b);
        }
        let Some(grads) = grads else {
            // The input projection is the only way back to x.
            return self.dense_backward(&s.input, &tape.x, &dh, rows, None, true);
        };
        // Embeddings: input projection, positions, noise level.
        self.dense_backward(&s.input, &tape.x, &dh, rows, Some(&mut *grads), false);
        let mut dtemb = vec![0.0; n * d];
        let dpos = &mut grads[s.pos.range()];
        for (r, row) in dh.chunks_exact(d).enumerate() {
            dpos[(r % l) * d..(r % l + 1) * d].iter_mut().zip(row).for_each(|(p, g)| *p += g);
            dtemb[(r / l) * d..(r / l + 1) * d].iter_mut().zip(row).for_each(|(p, g)| *p += g);
        }
        self.dense_backward(&s.time, &tape.time_features, &dtemb, n, Some(grads), false);
        None
    }

    /// Backward of a dense layer whose (weight, bias) are `pair`: accumulates its parameter
    /// gradients into `grads` when given, returns `dx` when asked.
    fn dense_backward(
        &self,
        pair: &(TensorSlot, TensorSlot),
        x: &[f32],
        dy: &[f32],
        rows: usize,
        grads: Option<&mut [f32]>,
        want_dx: bool,
    ) -> Option<Vec<f32>> {
        let w = self.p(&pair.0);
        match grads {
            Some(grads) => dense::backward(x, dy, rows, w, pair.0.shape[1], pair_mut(grads, pair), want_dx),
            None => want_dx.then(|| dense::input_grad(dy, rows, w, pair.0.shape[1])),
        }
    }

    fn norm_backward(
        &self,
        pair: &(TensorSlot, TensorSlot),
        dy: &[f32],
        norm: &Norm,
        grads: Option<&mut [f32]>,
    ) -> Vec<f32> {
        let gamma = self.p(&pair.0);
        match grads {
            Some(grads) => {
                let (gg, gb) = pair_mut(grads, pair);
                layer_norm_backward(dy, norm, gamma, Some((gg, gb)))
            }
            None => layer_norm_backward(dy, norm, gamma, None),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn small() -> Transformer {
        let config = TransformerConfig {
            token_dim: 5,
            tokens: 3,
            d_model: 8,
            heads: 2,
            layers: 2,
            d_ff: 12,
            time_features: 4,
            sample_features: 0,
        };
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut net = Transformer::new(config, &mut rng);
        // Random parameters everywhere (not the init's ones and zeros) so every path is tested.
        let normal = Normal::new(0.0, 0.5).unwrap();
        net.params.iter_mut().for_each(|p| *p += normal.sample(&mut rng));
        net
    }

    #[test]
    fn a_training_batch_gives_the_same_pass_on_any_number_of_threads() {
        // Large enough for the row-wise passes to split into blocks.
        let net = small();
        let n = 3000;
        assert!(n * 3 * 8 > 2 * BLOCK_ELEMENTS);
        let x: Vec<f32> = (0..n * 3 * 5).map(|i| ((i as f32) * 0.37).sin()).collect();
        let t: Vec<f32> = (0..n).map(|i| (i as f32 * 0.13).fract()).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let tape = net.forward(&x, &t, n);
                let mut grads = vec![0.0; net.num_params()];
                net.backward(&tape, &tape.output, &mut grads);
                (tape.output.clone(), grads)
            })
        };
        assert_eq!(run(1), run(3));
    }

    #[test]
    fn rational_tanh_matches_libm() {
        for i in -2000..=2000 {
            let x = i as f32 * 0.01;
            assert!((tanh(x) - x.tanh()).abs() < 5e-7, "tanh({x}) = {} vs {}", tanh(x), x.tanh());
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let net = small();
        let n = 2;
        let x: Vec<f32> = (0..n * 3 * 5).map(|i| ((i as f32) * 0.37).sin()).collect();
        let t = [0.2, 0.7];
        let target: Vec<f32> = (0..n * 3 * 5).map(|i| ((i as f32) * 0.11).cos()).collect();
        let loss = |net: &Transformer| -> f64 {
            net.predict(&x, &t, n).iter().zip(&target).map(|(y, t)| 0.5 * f64::from(y - t).powi(2)).sum()
        };
        let tape = net.forward(&x, &t, n);
        let grad_out: Vec<f32> = tape.output.iter().zip(&target).map(|(y, t)| y - t).collect();
        let mut grads = vec![0.0; net.num_params()];
        net.backward(&tape, &grad_out, &mut grads);
        let eps = 1e-2;
        let mut checked = 0;
        for slot in net.tensors() {
            for k in slot.range().step_by(3) {
                let mut plus = net.clone();
                plus.params[k] += eps;
                let mut minus = net.clone();
                minus.params[k] -= eps;
                let fd = (loss(&plus) - loss(&minus)) / (2.0 * f64::from(eps));
                let g = f64::from(grads[k]);
                assert!((fd - g).abs() < 2e-2 * (1.0 + fd.abs()), "{} [{}]: fd {fd} vs {g}", slot.name, k - slot.at);
                checked += 1;
            }
        }
        assert!(checked > 100);
    }

    #[test]
    fn input_gradient_matches_finite_differences() {
        let net = small();
        let n = 2;
        let x: Vec<f32> = (0..n * 3 * 5).map(|i| ((i as f32) * 0.37).sin()).collect();
        let t = [0.2, 0.7];
        let u: Vec<f32> = (0..n * 3 * 5).map(|i| ((i as f32) * 0.11).cos()).collect();
        // The vector-Jacobian product is the gradient of u . f(x).
        let dot = |x: &[f32]| -> f64 { net.predict(x, &t, n).iter().zip(&u).map(|(y, u)| f64::from(y * u)).sum() };
        let grad = net.input_grad(&net.forward(&x, &t, n), &u);
        let eps = 1e-2;
        for k in 0..x.len() {
            let (mut plus, mut minus) = (x.clone(), x.clone());
            plus[k] += eps;
            minus[k] -= eps;
            let fd = (dot(&plus) - dot(&minus)) / (2.0 * f64::from(eps));
            let g = f64::from(grad[k]);
            assert!((fd - g).abs() < 2e-2 * (1.0 + fd.abs()), "x[{k}]: fd {fd} vs {g}");
        }
        // The same with the parameter-gradient pass taken as well: it does not change dx.
        let mut grads = vec![0.0; net.num_params()];
        net.backward(&net.forward(&x, &t, n), &u, &mut grads);
        assert_eq!(grad, net.input_grad(&net.forward(&x, &t, n), &u));
    }

    #[test]
    fn tokens_see_each_other_and_the_noise_level() {
        let net = small();
        let x: Vec<f32> = (0..15).map(|i| (i as f32 * 0.3).cos()).collect();
        let base = net.predict(&x, &[0.5], 1);
        let mut moved = x.clone();
        moved[0] += 1.0; // token 0 only
        let other = net.predict(&moved, &[0.5], 1);
        assert!((5..15).any(|i| (other[i] - base[i]).abs() > 1e-4), "attention mixes tokens");
        let later = net.predict(&x, &[0.9], 1);
        assert!(base.iter().zip(&later).any(|(a, b)| (a - b).abs() > 1e-4), "the noise level matters");
        // Batched and single calls agree.
        let both = net.predict(&[x.clone(), moved].concat(), &[0.5, 0.5], 2);
        assert!(both[..15].iter().zip(&base).all(|(a, b)| (a - b).abs() < 1e-5));
    }
}
