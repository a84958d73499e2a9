//! `flowmimic train` and `flowmimic bench model`: the trajectory model.

use crate::progress::{CsvLog, Progress};
use anyhow::{Context, Result, anyhow, bail};
use flowmimic_control::humanoid_layout;
use flowmimic_data::{Dataset, Stats};
use flowmimic_model::train::{CHECKPOINT_FILE, MODEL_FILE};
use flowmimic_model::{
    InverseConfig, InverseDynamics, ModelConfig, Pairing, TokenLayout, TrainConfig, Trainer, TrajectoryModel, WindowSet,
};
use flowmimic_plot::{Chart, Series};
use flowmimic_sim::{NUM_DOFS, STATE_DIM};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};
use std::path::{Path, PathBuf};
use std::time::Instant;

const LOG_HEADER: &str = "step,train_loss,validation_loss,lr,seconds,windows_per_second";

/// Trains a model on `dataset` into `out`.
pub fn train(
    dataset: &Path,
    objective: &str,
    out: &Path,
    steps: Option<usize>,
    resume: bool,
    model: ModelConfig,
    mut cfg: TrainConfig,
) -> Result<()> {
    if let Some(s) = steps {
        cfg.steps = s;
        cfg.validate().map_err(|e| anyhow!("--steps {s}: {e}"))?;
    }
    let objective = cfg.objective(objective)?;
    if !model.time_features.is_multiple_of(2 * objective.times()) {
        bail!(
            "model.time_features ({}) must be a multiple of {} for {} (its network takes {} times)",
            model.time_features,
            2 * objective.times(),
            objective.name(),
            objective.times()
        );
    }
    if !resume && out.join(CHECKPOINT_FILE).exists() {
        bail!("{} exists: pass --resume to continue it, or choose another --out", out.join(CHECKPOINT_FILE).display());
    }
    let dataset = Dataset::open(dataset)?;
    let layout = humanoid_layout(&model);
    let stats = Stats::of_dataset(&dataset, layout.spec)?;
    let started = Instant::now();
    let data = WindowSet::from_dataset(
        &dataset,
        layout,
        &stats,
        cfg.validation_fraction,
        &cfg.reach_clips,
        model.label_steps(),
    )?;
    eprintln!(
        "{}: {} training and {} validation windows (history {}, horizon {}) in {:.1} s",
        dataset.dir.display(),
        data.train_len(),
        data.validation_len(),
        layout.spec.history,
        layout.spec.horizon,
        started.elapsed().as_secs_f64()
    );
    let dropped = 100.0 * cfg.label_dropout;
    if model.task_labels {
        let ((clips, share), all) = (data.reach(), dataset.manifest.shards.len());
        let share = 100.0 * share;
        eprintln!(
            "task labels: reach on {clips} of {all} clips ({share:.0}% of training windows), walk on the rest; left out in {dropped:.0}%"
        );
    }
    if model.command_labels {
        let steps = model.label_steps();
        eprintln!(
            "command labels: each window's motion (forward, left, yaw rate) over the {steps} steps after it; left out in {dropped:.0}%"
        );
    }
    let fresh = Trainer::new(
        TrajectoryModel::new(layout, model, objective, stats, cfg.seed),
        cfg.clone(),
        data,
        dataset.shards_key(),
    );
    let mut trainer = if resume {
        let t = Trainer::resume(out, fresh)?;
        eprintln!("resumed {} at step {}", out.join(CHECKPOINT_FILE).display(), t.step);
        t
    } else {
        fresh
    };
    let net = &trainer.model.net.net;
    eprintln!(
        "{} Transformer: {} layers, {} heads, d {}, ff {}, {} tokens of {}: {} parameters ({:.1} MFLOP per sample)",
        objective.label(),
        model.layers,
        model.heads,
        model.d_model,
        model.d_ff,
        net.config.tokens,
        net.config.token_dim,
        net.num_params(),
        net.flops_per_sample() / 1e6
    );
    let config = serde_json::json!({
        "objective": objective, "model": model, "train": cfg, "dataset": dataset.dir, "dataset_sha256": dataset.shards_key(),
    });
    flowmimic_io::write_atomic(&out.join("config.json"), serde_json::to_string_pretty(&config)?.as_bytes())?;
    let mut log = CsvLog::open(out.join("log.csv"), LOG_HEADER, resume.then_some(trainer.step));
    let progress = Progress::new(cfg.steps, trainer.step);
    let (mut sum, mut count, mut since) = (0.0, 0, Instant::now());
    let clock = Instant::now();
    while trainer.step < cfg.steps {
        sum += trainer.train_step().context("training stopped; the last checkpoint is intact")?;
        count += 1;
        let step = trainer.step;
        let last = step == cfg.steps;
        if step % cfg.log_every.max(1) == 0 || last {
            let rate = (count * cfg.batch) as f64 / since.elapsed().as_secs_f64();
            let train_loss = sum / count as f32;
            let validation = trainer.validation_loss();
            let val = validation.map_or(String::new(), |v| format!("{v:.5}"));
            log.rows.push(format!(
                "{step},{train_loss:.5},{val},{:.3e},{:.1},{rate:.0}",
                trainer.lr(),
                clock.elapsed().as_secs_f64()
            ));
            progress.update(
                step,
                &format!("loss {train_loss:.4}  validation {val:>7}  lr {:.1e}  {rate:.0} windows/s", trainer.lr()),
            );
            (sum, count, since) = (0.0, 0, Instant::now());
        }
        if step % cfg.checkpoint_every.max(1) == 0 || last {
            // Log first: a kill between the writes must not leave a checkpoint past the log.
            log.save()?;
            trainer.save(out)?;
            plot_loss(out, &log)?;
        }
    }
    progress.finish();
    // Nothing to train (`--steps` already reached, or 0): the model directory is still complete.
    if !out.join(MODEL_FILE).exists() {
        trainer.save(out)?;
    }
    eprintln!("wrote {} (weights, stats, checkpoint, log.csv, loss.png)", out.display());
    Ok(())
}

/// Fits inverse dynamics to `datasets` and adds it to the model directory `model_dir`.
pub fn fit_inverse(datasets: &[PathBuf], model_dir: &Path, config: &InverseConfig) -> Result<()> {
    // The model must load (and be this humanoid's) before minutes of fitting.
    crate::run::load_model(model_dir)?;
    let datasets: Vec<Dataset> = datasets.iter().map(|d| Dataset::open(d)).collect::<Result<_, _>>()?;
    let progress = Progress::new(config.steps, 0);
    let mut log = CsvLog::open(model_dir.join("inverse-log.csv"), "step,train_mse,validation_mse", None);
    let inverse = InverseDynamics::fit(&datasets, STATE_DIM, NUM_DOFS, config, |p| {
        let validation = p.validation_mse.map_or(String::new(), |v| format!("{v:.5}"));
        log.rows.push(format!("{},{:.5},{validation}", p.step, p.train_mse));
        progress.update(p.step, &format!("mse {:.5}  validation {validation:>7} (standardised actions)", p.train_mse));
    })?;
    progress.finish();
    let path = model_dir.join(flowmimic_model::inverse::INVERSE_FILE);
    inverse.save(&path)?;
    log.save()?;
    let last = log.rows.last().map_or("", String::as_str);
    eprintln!("wrote {} (step,train_mse,validation_mse: {last})", path.display());
    Ok(())
}

fn plot_loss(out: &Path, log: &CsvLog) -> Result<()> {
    let chart = Chart::new("trajectory model loss", "optimiser steps", "mean squared error (normalised units)")
        .series(Series::line("train", log.column(0, 1)))
        .series(Series::line("validation", log.column(0, 2)));
    chart.save(&out.join("loss"))?;
    Ok(())
}

/// Default model directory of an objective.
pub fn default_out(objective: &str) -> PathBuf {
    PathBuf::from("runs/model").join(objective)
}

/// Sampling latency table: batch 1 and 64, NFE 1-20, both objectives, the given sizes.
pub fn bench(sizes: &[(&str, ModelConfig)], repeats: usize) -> Result<()> {
    let peak = flowmimic_nn::sgemm_gflops(512, 20);
    println!("SGEMM peak (best of 20 products of 512^3, all threads): {peak:.1} GFLOP/s");
    println!(
        "{:<6} {:>9} {:<5} {:>5} {:>4} {:>11} {:>11} {:>9} {:>7}",
        "size", "params", "obj", "batch", "nfe", "median ms", "ms/sample", "GFLOP", "peak"
    );
    for (name, config) in sizes {
        let layout = humanoid_layout(config);
        for objective in ["fm", "ddpm"] {
            let model = untrained(config, &layout, TrainConfig::default().objective(objective)?);
            for batch in [1, 64] {
                for nfe in [1, 2, 5, 10, 20] {
                    let cond = vec![0.0; batch * layout.cond_len()];
                    let mut rng = StdRng::seed_from_u64(0);
                    let mut times: Vec<f64> = (0..repeats.max(1) + 1)
                        .map(|_| {
                            let t = Instant::now();
                            std::hint::black_box(model.sample(&cond, batch, nfe, None, &mut rng));
                            t.elapsed().as_secs_f64()
                        })
                        .skip(1)
                        .collect();
                    times.sort_by(f64::total_cmp);
                    let median = times[times.len() / 2];
                    let flops = model.sample_flops(batch, nfe);
                    println!(
                        "{name:<6} {:>9} {objective:<5} {batch:>5} {nfe:>4} {:>11.2} {:>11.3} {:>9.3} {:>6.1}%",
                        model.net.net.num_params(),
                        median * 1e3,
                        median * 1e3 / batch as f64,
                        flops / 1e9,
                        100.0 * flops / median / 1e9 / peak
                    );
                }
            }
        }
    }
    // A training step: forward, backward and Adam at the training batch, in the preset's shape
    // and the shipped guidance models' (H 16, state-action-state tokens).
    println!("\ntraining step (forward, backward, Adam; FLOPs counted as 3 forward passes)");
    println!("{:<12} {:>5} {:>6} {:>11} {:>9} {:>7}", "size", "H", "batch", "median ms", "GFLOP", "peak");
    let guidance = |c: &ModelConfig| ModelConfig { horizon: 16, pairing: Pairing::StateActionState, ..*c };
    let shapes = sizes.iter().flat_map(|(n, c)| {
        // A preset already in the guidance models' shape is measured once.
        let guide = (guidance(c) != *c).then(|| (format!("{n}-guide"), guidance(c)));
        std::iter::once((n.to_string(), *c)).chain(guide)
    });
    for (name, config) in shapes {
        let layout = humanoid_layout(&config);
        let mut model = untrained(&config, &layout, TrainConfig::default().objective("fm")?);
        let batch = 256; // the cpu and paper presets' batch
        let (c, f) = (layout.cond_len(), layout.future_len());
        let mut rng = StdRng::seed_from_u64(0);
        let mut normal = |n: usize| -> Vec<f32> { (0..n).map(|_| StandardNormal.sample(&mut rng)).collect() };
        let (x, cond, target) = (normal(batch * f), normal(batch * c), normal(batch * f));
        let t: Vec<f32> = (0..batch).map(|i| (i as f32 + 0.5) / batch as f32).collect();
        let mut adam = flowmimic_nn::Adam::new(model.net.net.num_params());
        let mut times: Vec<f64> = (0..repeats.max(1) + 1)
            .map(|_| {
                let start = Instant::now();
                let tape = model.net.forward(&x, &t, &cond, batch);
                let pred = model.net.future(&tape.output);
                let d: Vec<f32> = pred.iter().zip(&target).map(|(p, y)| 2.0 * (p - y) / pred.len() as f32).collect();
                let mut grads = vec![0.0; model.net.net.num_params()];
                model.net.net.backward(&tape, &model.net.output_cotangent(&d, batch), &mut grads);
                adam.step(&mut model.net.net.params, &grads, 1e-4);
                start.elapsed().as_secs_f64()
            })
            .skip(1)
            .collect();
        times.sort_by(f64::total_cmp);
        let median = times[times.len() / 2];
        let flops = 3.0 * model.sample_flops(batch, 1);
        println!(
            "{name:<12} {:>5} {batch:>6} {:>11.1} {:>9.2} {:>6.1}%",
            config.horizon,
            median * 1e3,
            flops / 1e9,
            100.0 * flops / median / 1e9 / peak
        );
    }
    Ok(())
}

/// A randomly initialised model with unit statistics (timing only).
fn untrained(config: &ModelConfig, layout: &TokenLayout, objective: flowmimic_model::Objective) -> TrajectoryModel {
    let spec = layout.spec;
    let stats = Stats {
        spec,
        state_mean: vec![0.0; spec.states() * STATE_DIM],
        state_std: vec![1.0; spec.states() * STATE_DIM],
        action_mean: vec![0.0; spec.actions() * NUM_DOFS],
        action_std: vec![1.0; spec.actions() * NUM_DOFS],
        windows: 0,
    };
    TrajectoryModel::new(*layout, *config, objective, stats, 0)
}
