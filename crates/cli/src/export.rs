//! `flowmimic export`: a trajectory model or an expert as an ONNX graph, and optionally the data
//! to check another runtime against flowmimic (`examples/onnx_check.py`).

use anyhow::{Context, Result, bail};
use flowmimic_control::{History, Rollout};
use flowmimic_geom::{heading, quat_from_wxyz};
use flowmimic_model::{Objective, TrajectoryModel};
use flowmimic_sim::Humanoid;
use flowmimic_sim::{NUM_DOFS, STATE_DIM};
use flowmimic_track::task::{Reference, Tracker};
use flowmimic_track::train::{Checkpoint, POLICY_FILE};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

/// Samples in a check file.
const CHECK_SAMPLES: usize = 16;
/// Network evaluations of the sampler in a check file.
const CHECK_NFE: usize = 5;

/// Exports `path` to `out`; with `check`, writes check data there (for a trajectory model with
/// `rollout`, also the conditioning the controller builds from that rollout's step `step`).
pub fn run(
    humanoid: &Arc<Humanoid>,
    path: &Path,
    out: &Path,
    check: Option<&Path>,
    rollout: Option<&Path>,
    step: usize,
) -> Result<()> {
    let mut rng = StdRng::seed_from_u64(7);
    let normal = |n: usize, rng: &mut StdRng| -> Vec<f32> { (0..n).map(|_| StandardNormal.sample(rng)).collect() };
    let n = CHECK_SAMPLES;
    let path = &crate::paths::resolve(path);
    if !path.exists() {
        bail!("{}: no such directory (a model directory from `flowmimic train`, or an expert run)", path.display());
    }
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
            // Normalised inputs, the network's outputs, and samples of the objective's sampler
            // from stored noise (with DDPM's ancestral noise, drawn after it).
            let layout = model.layout();
            let (c, f) = (layout.cond_len(), layout.future_len());
            let times = model.objective.times();
            let (x, cond, noise) = (normal(n * f, &mut rng), normal(n * c, &mut rng), normal(n * f, &mut rng));
            let t: Vec<f32> = (0..n * times).map(|i| (i as f32 + 0.5) / (n * times) as f32).collect();
            let y = flowmimic_model::Network::predict(&model.net, &x, &t, &cond, n);
            let (samples, z) = sampled(&model, &cond, &noise, n, &mut rng);
            let mut tensors = vec![
                ("x", vec![n, f], &x[..]),
                ("t", if times == 1 { vec![n] } else { vec![n, times] }, &t[..]),
                ("cond", vec![n, c], &cond[..]),
                ("y", vec![n, f], &y[..]),
                ("noise", vec![n, f], &noise[..]),
                ("samples", vec![n, f], &samples[..]),
            ];
            if !z.is_empty() {
                tensors.push(("ancestral_noise", vec![CHECK_NFE - 1, n, f], &z[..]));
            }
            let (physical, rollout_samples, rollout_z);
            if let Some(file) = rollout {
                // The controller's conditioning at a rollout's step, and samples from it.
                let r = Rollout::load(file)?;
                physical = rollout_conditioning(&model, &r, step).with_context(|| format!("{}", file.display()))?;
                let mut normalised = physical.clone();
                model.norm.normalise(&mut normalised, 0, c);
                let noise = &x[..f];
                (rollout_samples, rollout_z) = sampled(&model, &normalised, noise, 1, &mut rng);
                tensors.extend([
                    ("rollout_cond", vec![1, c], &physical[..]),
                    ("rollout_noise", vec![1, f], noise),
                    ("rollout_samples", vec![1, f], &rollout_samples[..]),
                ]);
                if !rollout_z.is_empty() {
                    tensors.push(("rollout_ancestral_noise", vec![CHECK_NFE - 1, 1, f], &rollout_z[..]));
                }
            }
            let meta = HashMap::from([
                ("rollout_step".to_string(), step.to_string()),
                ("nfe".to_string(), CHECK_NFE.to_string()),
            ]);
            flowmimic_io::tensors::save(check, &tensors, meta)?;
            eprintln!("wrote {}: {n} inputs and flowmimic's outputs and samples", check.display());
        }
    } else if path.join(POLICY_FILE).exists() {
        let checkpoint = Checkpoint::read(&path.join(POLICY_FILE))?;
        let policy = checkpoint.policy()?;
        let clip = checkpoint.meta("clip")?;
        let bytes =
            flowmimic_export::policy(&policy, &clip).with_context(|| format!("exporting {}", path.display()))?;
        flowmimic_io::write_atomic(out, &bytes)?;
        eprintln!("wrote {} ({} bytes): the actor of the expert for '{clip}'", out.display(), bytes.len());
        if let Some(check) = check {
            // Observations along the run's clip (reference-state starts spread over it, with the
            // reset noise), and the deterministic actions.
            let reference = Reference::new(crate::track::run_clips(humanoid, path)?.remove(0));
            let cfg = checkpoint.config()?;
            let mut tracker = Tracker::new(humanoid);
            let mut obs = vec![0.0; n * policy.obs_dim()];
            for (i, row) in obs.chunks_exact_mut(policy.obs_dim()).enumerate() {
                tracker.reset(&reference, i * (reference.len() - 1) / n, &cfg, &mut rng)?;
                tracker.observe(&reference, row);
            }
            let actions = policy.act(&obs, n);
            let tensors =
                [("obs", vec![n, policy.obs_dim()], &obs[..]), ("action", vec![n, actions.len() / n], &actions[..])];
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

/// Samples of the model's own sampler at [`CHECK_NFE`] from `noise` (normalised units), and the
/// ancestral noise DDPM drew for them (empty for the deterministic samplers): the sampler draws
/// it from `rng` in order, so a copy of `rng` taken before gives the same values.
fn sampled(model: &TrajectoryModel, cond: &[f32], noise: &[f32], n: usize, rng: &mut StdRng) -> (Vec<f32>, Vec<f32>) {
    let before = rng.clone();
    let samples = model.sample_from(cond, noise.to_vec(), n, CHECK_NFE, None, rng);
    let z = match model.objective {
        Objective::Ddpm { .. } => {
            let mut replay = before;
            (0..(CHECK_NFE - 1) * noise.len()).map(|_| StandardNormal.sample(&mut replay)).collect()
        }
        _ => Vec::new(),
    };
    (samples, z)
}

/// The conditioning (physical units) that the controller builds at `step` of environment 0 of
/// `rollout`: the states before it re-expressed in that step's character frame, and the actions
/// executed between them.
fn rollout_conditioning(model: &TrajectoryModel, rollout: &Rollout, step: usize) -> Result<Vec<f32>> {
    let layout = model.layout();
    if step > rollout.steps {
        bail!("step {step} is past the rollout's {} steps", rollout.steps);
    }
    let nq = rollout.nq;
    let mut history = History::new(layout.spec);
    for k in 0..=step {
        let state: [f32; STATE_DIM] = rollout.state[k * STATE_DIM..(k + 1) * STATE_DIM].try_into()?;
        let q = &rollout.qpos[k * nq..(k + 1) * nq];
        let rot = quat_from_wxyz([q[3], q[4], q[5], q[6]].map(f64::from));
        history.push(state, [q[0], q[1], heading(rot) as f32]);
        if k < step {
            history.act(&rollout.action[k * NUM_DOFS..(k + 1) * NUM_DOFS]);
        }
    }
    let (states, actions) = history.conditioning();
    Ok(layout.conditioning(&states, &actions, None))
}
