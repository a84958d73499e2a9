//! Whether a model samples or regresses: how far its predicted futures spread across noise
//! draws for the same conditioning. A one-step clean-sample FM returns its conditional mean, so
//! its draws barely differ; a model that samples in one call spreads as its many-step samplers do.
//!
//! On 64 random windows of a dataset, 16 noise draws each, prints per model and NFE the standard
//! deviation across draws (physical units, averaged over entries) of the executed action `a_t`
//! and of the whole future, and the mean absolute error of the draws' mean `a_t` against the
//! data's.
//!
//! `cargo run --release -p flowmimic-model --example diversity -- DATASET_DIR MODEL_DIR:NFE...`

use flowmimic_data::{Dataset, window, window_starts};
use flowmimic_model::TrajectoryModel;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::path::Path;

const WINDOWS: usize = 64;
const DRAWS: usize = 16;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [dataset, models @ ..] = args.as_slice() else {
        return Err("usage: diversity DATASET_DIR MODEL_DIR:NFE...".into());
    };
    let shards = Dataset::open(Path::new(dataset))?.load_all()?;
    for spec in models {
        let (dir, nfe) = spec.split_once(':').ok_or(format!("{spec}: expected MODEL_DIR:NFE"))?;
        let nfe: usize = nfe.parse()?;
        let model = TrajectoryModel::load(Path::new(dir))?;
        let layout = model.layout();
        let (c, f, actions) = (layout.cond_len(), layout.future_len(), layout.action_dim);
        // The same windows and noise for every model.
        let mut rng = StdRng::seed_from_u64(1);
        let (mut spread_action, mut spread_future, mut error_action) = (0.0, 0.0, 0.0);
        for _ in 0..WINDOWS {
            let w = loop {
                let (_, shard) = &shards[rng.random_range(0..shards.len())];
                let starts = window_starts(shard, layout.spec);
                // A rollout shorter than a window has none.
                if !starts.is_empty() {
                    break window(shard, layout.spec, starts[rng.random_range(0..starts.len())]);
                }
            };
            let row = layout.interleave(&w.states, &w.actions);
            let cond: Vec<f32> = (0..DRAWS).flat_map(|_| row[..c].iter().copied()).collect();
            let out = model.sample(&cond, DRAWS, nfe, None, &mut rng);
            // Mean and standard deviation of each future entry across the draws.
            let moments: Vec<(f64, f64)> = (0..f)
                .map(|j| {
                    let xs: Vec<f64> = (0..DRAWS).map(|d| f64::from(out[d * f + j])).collect();
                    let mean = xs.iter().sum::<f64>() / DRAWS as f64;
                    (mean, (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / DRAWS as f64).sqrt())
                })
                .collect();
            spread_action += moments[..actions].iter().map(|m| m.1).sum::<f64>() / actions as f64;
            spread_future += moments.iter().map(|m| m.1).sum::<f64>() / f as f64;
            let errors = moments[..actions].iter().zip(&row[c..]).map(|(m, &x)| (m.0 - f64::from(x)).abs());
            error_action += errors.sum::<f64>() / actions as f64;
        }
        let n = WINDOWS as f64;
        println!(
            "{dir} NFE {nfe}: spread across draws: executed action {:.4}, whole future {:.4}; \
             |mean executed action - data| {:.4}",
            spread_action / n,
            spread_future / n,
            error_action / n
        );
    }
    Ok(())
}
