//! `flowmimic export`: a trajectory model or an expert as an ONNX graph, and optionally the data
//! to check another runtime against flowmimic (`examples/onnx_check.py`).

use crate::track::RUN_POLICY;
use anyhow::{Context, Result, bail};
use flowmimic_model::fm::{self, Solver};
use flowmimic_track::train::Checkpoint;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};
use std::collections::HashMap;
use std::path::Path;

/// Samples in a check file.
const CHECK_SAMPLES: usize = 16;
/// Network evaluations of the sampler in a check file.
const CHECK_NFE: usize = 5;

pub fn run(path: &Path, out: &Path, check: Option<&Path>) -> Result<()> {
    let mut rng = StdRng::seed_from_u64(7);
    let mut normal = |n: usize| -> Vec<f32> { (0..n).map(|_| StandardNormal.sample(&mut rng)).collect() };
    let n = CHECK_SAMPLES;
    if path.join(flowmimic_model::train::MODEL_FILE).exists() {
        let model = crate::run::load_model(path)?;
        let bytes =
            flowmimic_export::trajectory_model(&model).with_context(|| format!("exporting {}", path.display()))?;
        flowmimic_io::write_atomic(out, &bytes)?;
        eprintln!(
            "wrote {} ({} bytes): the {} denoiser, opset {}",
            out.display(),
            bytes.len(),
            model.objective.name(),
            flowmimic_export::OPSET
        );
        if let Some(check) = check {
            // Normalised inputs, the network's outputs and, for Flow Matching, Euler samples.
            let layout = model.layout();
            let (c, f) = (layout.cond_len(), layout.future_len());
            let (x, cond, noise) = (normal(n * f), normal(n * c), normal(n * f));
            let t: Vec<f32> = (0..n).map(|i| (i as f32 + 0.5) / n as f32).collect();
            let y = flowmimic_model::Network::predict(&model.net, &x, &t, &cond, n);
            let mut tensors = vec![("x", vec![n, f], &x[..]), ("t", vec![n], &t[..]), ("cond", vec![n, c], &cond[..])];
            tensors.push(("y", vec![n, f], &y[..]));
            let samples;
            if model.objective.name() == "fm" {
                samples = fm::sample(&model.net, &cond, noise.clone(), n, CHECK_NFE, Solver::Euler, None);
                tensors.extend([("noise", vec![n, f], &noise[..]), ("euler_nfe5", vec![n, f], &samples[..])]);
            }
            flowmimic_io::tensors::save(check, &tensors, HashMap::new())?;
            eprintln!("wrote {}: {n} inputs and flowmimic's outputs", check.display());
        }
    } else if path.join(RUN_POLICY).exists() {
        let checkpoint = Checkpoint::read(&path.join(RUN_POLICY))?;
        let policy = checkpoint.policy()?;
        let clip = checkpoint.meta("clip")?;
        let bytes =
            flowmimic_export::policy(&policy, &clip).with_context(|| format!("exporting {}", path.display()))?;
        flowmimic_io::write_atomic(out, &bytes)?;
        eprintln!("wrote {} ({} bytes): the actor of the expert for '{clip}'", out.display(), bytes.len());
        if let Some(check) = check {
            // Raw observations around the running statistics, and the deterministic actions.
            let norm = &policy.normalizer;
            let dim = norm.mean.len();
            let obs: Vec<f32> = normal(n * dim)
                .iter()
                .enumerate()
                .map(|(k, z)| (norm.mean[k % dim] + norm.var[k % dim].sqrt() * 2.0 * f64::from(*z)) as f32)
                .collect();
            let actions = policy.act(&obs, n);
            let tensors = [("obs", vec![n, dim], &obs[..]), ("action", vec![n, actions.len() / n], &actions[..])];
            flowmimic_io::tensors::save(check, &tensors, HashMap::new())?;
            eprintln!("wrote {}: {n} observations and flowmimic's actions", check.display());
        }
    } else {
        bail!(
            "{}: neither a model directory (model.safetensors) nor an expert run (policy.safetensors)",
            path.display()
        );
    }
    Ok(())
}
