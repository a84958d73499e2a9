//! How much a trajectory model's executed action depends on the future it predicts: the
//! question behind guidance, which steers the predicted states and needs the action to follow.
//!
//! On 256 random windows of a dataset (Flow Matching models, NFE 5), samples the future four
//! ways from the same noise and compares the executed action `a_t` and the later actions with the
//! data's (mean absolute error, normalised units):
//! - free: the model's own sample;
//! - free, other noise: the same with different noise (how much the noise alone moves `a_t`);
//! - true states inpainted: the window's real future states held along the path (replacement),
//!   the actions generated;
//! - other states inpainted: another window's future states held instead.
//!
//! If inpainting the true states leaves `a_t` where it was, the model infers the executed
//! action from the past alone, and no guidance on the states will move it.
//!
//! `cargo run --release -p flowmimic-model --example coupling -- MODEL_DIR DATASET_DIR`

use flowmimic_data::{Dataset, window, window_starts};
use flowmimic_model::fm::{self, Solver};
use flowmimic_model::{Network, Objective, TrajectoryModel};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use std::path::Path;

const WINDOWS: usize = 256;
const NFE: usize = 5;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [model_dir, dataset_dir] = &args[..] else {
        return Err("usage: coupling MODEL_DIR DATASET_DIR".into());
    };
    let model = TrajectoryModel::load(Path::new(model_dir))?;
    if !matches!(model.objective, Objective::Fm { .. }) {
        return Err(
            format!("{model_dir} is {}; this probe samples Flow Matching models", model.objective.name()).into()
        );
    }
    let dataset = Dataset::open(Path::new(dataset_dir))?;
    let shards: Vec<_> = dataset.load_all()?.into_iter().map(|(_, shard)| shard).collect();
    let layout = *model.layout();
    let (c, f, w) = (layout.cond_len(), layout.future_len(), layout.window_len());
    let (sd, ad) = (layout.state_dim, layout.action_dim);
    let mut rng = StdRng::seed_from_u64(1);
    let mut rows = Vec::new();
    while rows.len() < WINDOWS {
        let shard = &shards[rng.random_range(0..shards.len())];
        let starts = window_starts(shard, layout.spec);
        if starts.is_empty() {
            continue;
        }
        let win = window(shard, layout.spec, starts[rng.random_range(0..starts.len())]);
        let mut row = layout.interleave(&win.states, &win.actions);
        model.norm.normalise(&mut row, 0, w);
        rows.push(row);
    }
    let n = WINDOWS;
    let cond: Vec<f32> = rows.iter().flat_map(|r| r[..c].to_vec()).collect();
    let truth: Vec<f32> = rows.iter().flat_map(|r| r[c..].to_vec()).collect();
    let other: Vec<f32> = (0..n).flat_map(|i| rows[(i + 1) % n][c..].to_vec()).collect();
    // The future is [a_t, s_{t+1}, a_{t+1}, ...]: true at the state entries.
    let is_state: Vec<bool> = (0..f).map(|j| j >= ad && (j - ad) % (sd + ad) < sd).collect();
    let noise = |rng: &mut StdRng| -> Vec<f32> { (0..n * f).map(|_| StandardNormal.sample(rng)).collect() };
    let z = noise(&mut rng);
    let free = fm::sample(&model.net, &cond, z.clone(), n, NFE, Solver::Euler, None);
    let free_other = fm::sample(&model.net, &cond, noise(&mut rng), n, NFE, Solver::Euler, None);
    let inpaint = |known: &[f32]| inpainted(&model.net, &cond, z.clone(), n, known, &is_state);
    let (true_states, other_states) = (inpaint(&truth), inpaint(&other));
    let mean_abs = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(a, b)| (a - b).abs()).sum::<f32>() / a.len() as f32;
    let first = |x: &[f32], i: usize| x[i * f..i * f + ad].to_vec();
    let later = |x: &[f32], i: usize| -> Vec<f32> { (ad..f).filter(|&j| !is_state[j]).map(|j| x[i * f + j]).collect() };
    println!("{:<26} {:>12} {:>18} {:>16}", "future", "|a_t - data|", "|a_t+k - data|", "|a_t - free a_t|");
    for (name, x) in [
        ("free", &free),
        ("free, other noise", &free_other),
        ("true states inpainted", &true_states),
        ("other states inpainted", &other_states),
    ] {
        let avg = |g: &dyn Fn(usize) -> f32| (0..n).map(g).sum::<f32>() / n as f32;
        println!(
            "{name:<26} {:>12.4} {:>18.4} {:>16.4}",
            avg(&|i| mean_abs(&first(x, i), &first(&truth, i))),
            avg(&|i| mean_abs(&later(x, i), &later(&truth, i))),
            avg(&|i| mean_abs(&first(x, i), &first(&free, i)))
        );
    }
    Ok(())
}

/// Euler sampling with the entries marked `known` held on the straight path to `known`'s values
/// (`(1 - s) x0 + s known`), the others generated.
fn inpainted(net: &dyn Network, cond: &[f32], mut x: Vec<f32>, n: usize, known: &[f32], mask: &[bool]) -> Vec<f32> {
    let x0 = x.clone();
    let hold = |x: &mut [f32], s: f32| {
        for (i, v) in x.iter_mut().enumerate().filter(|(i, _)| mask[i % mask.len()]) {
            *v = (1.0 - s) * x0[i] + s * known[i];
        }
    };
    let h = 1.0 / NFE as f32;
    for step in 0..NFE {
        let s = step as f32 * h;
        hold(&mut x, s);
        let v = net.predict(&x, &vec![s; n], cond, n);
        x.iter_mut().zip(&v).for_each(|(x, v)| *x += h * v);
    }
    hold(&mut x, 1.0);
    x
}
