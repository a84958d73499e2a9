//! The trajectory model's plumbing: token layout, normalisation, guidance in physical units and
//! the learning-rate schedule.

use flowmimic_data::{Stats, WindowSpec};
use flowmimic_model::{Gradient, LrSchedule, ModelConfig, TaskGuidance, TokenLayout, TrainConfig, TrajectoryModel};
use rand::SeedableRng;
use rand::rngs::StdRng;

fn layout() -> TokenLayout {
    TokenLayout { state_dim: 3, action_dim: 2, spec: WindowSpec { history: 1, horizon: 2 }, labels: 0 }
}

#[test]
fn conditioning_and_future_split_an_interleaved_window() {
    let l = layout();
    // Window of 4 steps: states s0..s3 (3 each), actions a0..a3 (2 each).
    let states: Vec<f32> = (0..12).map(|i| i as f32).collect();
    let actions: Vec<f32> = (100..108).map(|i| i as f32).collect();
    let w = l.interleave(&states, &actions);
    assert_eq!(w.len(), l.window_len());
    // O_t = [s0, a0, s1]; tau_t = [a1, s2, a2, s3, a3].
    assert_eq!(&w[..l.cond_len()], &[0.0, 1.0, 2.0, 100.0, 101.0, 3.0, 4.0, 5.0]);
    assert_eq!(&w[l.cond_len()..l.cond_len() + 5], &[102.0, 103.0, 6.0, 7.0, 8.0]);
    // The history's N + 1 states and N actions interleave into exactly O_t.
    assert_eq!(l.interleave(&states[..6], &actions[..2]), w[..l.cond_len()].to_vec());
}

#[test]
fn guidance_acts_in_physical_units() {
    let l = layout();
    let spec = l.spec;
    let stats = Stats {
        spec,
        state_mean: vec![10.0; spec.states() * 3],
        state_std: vec![5.0; spec.states() * 3],
        action_mean: vec![0.0; spec.actions() * 2],
        action_std: vec![0.5; spec.actions() * 2],
        windows: 1,
    };
    let config = ModelConfig {
        history: 1,
        horizon: 2,
        d_model: 8,
        heads: 2,
        layers: 1,
        d_ff: 16,
        time_features: 4,
        ..Default::default()
    };
    let objective = TrainConfig::default().objective("fm").unwrap();
    let model = TrajectoryModel::new(l, config, objective, stats, 0);
    let cond = vec![10.0f32; 4 * l.cond_len()];
    let unguided = model.sample(&cond, 4, 10, None, &mut StdRng::seed_from_u64(1));
    // An untrained model predicts about zero velocity: samples stay near the mean (10 for
    // states) in physical units.
    let f = l.future_len();
    let state0 = |x: &[f32]| x.chunks(f).map(|r| r[2]).sum::<f32>() / 4.0;
    assert!((state0(&unguided) - 10.0).abs() < 10.0, "{}", state0(&unguided));
    // A cost (x - 40)^2 / 2 on the first future state's first feature pulls it there.
    let grad = |x: &[f32], n: usize| -> Vec<f32> {
        let mut g = vec![0.0; n * f];
        for i in 0..n {
            g[i * f + 2] = x[i * f + 2] - 40.0;
        }
        g
    };
    let guidance = TaskGuidance { weight: 0.2, grad: &grad, steps: 0..10, gradient: Gradient::CostOnly };
    let guided = model.sample(&cond, 4, 10, Some(&guidance), &mut StdRng::seed_from_u64(1));
    assert!(state0(&guided) > state0(&unguided) + 10.0, "guided {} vs {}", state0(&guided), state0(&unguided));
    // The other entries move far less than the guided one.
    let change = state0(&guided) - state0(&unguided);
    let others: f32 =
        guided.iter().zip(&unguided).enumerate().filter(|(j, _)| j % f != 2).map(|(_, (a, b))| (a - b).abs()).sum();
    let others = others / (4 * (f - 1)) as f32;
    assert!(others < 0.2 * change, "other entries moved {others} on average, the guided one {change}");
}

#[test]
fn the_learning_rate_warms_up_then_holds_or_follows_a_cosine_to_zero() {
    let constant = TrainConfig { steps: 1000, warmup: 100, lr: 1e-3, ..Default::default() };
    assert!((constant.lr_at(49) - 5e-4).abs() < 1e-9, "half-way through warm-up");
    assert_eq!(constant.lr_at(99), 1e-3);
    assert_eq!(constant.lr_at(999), 1e-3);
    let cosine = TrainConfig { lr_schedule: LrSchedule::Cosine, ..constant.clone() };
    assert_eq!(cosine.lr_at(49), constant.lr_at(49), "the same warm-up");
    assert!((cosine.lr_at(100) - 1e-3).abs() < 1e-9, "full at the end of warm-up");
    assert!((cosine.lr_at(550) - 5e-4).abs() < 1e-7, "half between warm-up and the last step");
    assert!(cosine.lr_at(1000) < 1e-12 && cosine.lr_at(5000) < 1e-12, "zero from the last step on");
    let lrs: Vec<f32> = (100..=1000).map(|s| cosine.lr_at(s)).collect();
    assert!(lrs.windows(2).all(|w| w[1] <= w[0]), "it only falls after warm-up");
    // Held until `decay_from`, then the whole run's cosine: a constant run resumed there with
    // `cosine` (configs/decay.toml's recipe).
    let held = TrainConfig { decay_from: 600, ..cosine.clone() };
    assert!(held.validate().is_ok());
    for s in [0, 99, 100, 599] {
        assert_eq!(held.lr_at(s), constant.lr_at(s), "held at step {s}");
    }
    for s in [600, 601, 999, 1000] {
        assert_eq!(held.lr_at(s), cosine.lr_at(s), "the cosine at step {s}");
    }
    let error = TrainConfig { decay_from: 600, ..constant }.validate().unwrap_err();
    assert!(error.contains("decay_from") && error.contains("cosine"), "{error}");
    let error = TrainConfig { decay_from: 1000, ..cosine }.validate().unwrap_err();
    assert!(error.contains("decay_from") && error.contains("steps"), "{error}");
}
