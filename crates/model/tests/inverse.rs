//! Inverse dynamics: fitted to transitions whose action is a known function of both states, it
//! finds that function; it saves, loads, and refuses a file for other sizes.

use flowmimic_data::{Dataset, Manifest, Shard, ShardInfo};
use flowmimic_model::{InverseConfig, InverseDynamics};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// A dataset of 200 rollouts of 30 random states whose executed action `j` is
/// `0.5 s_{t+1}[9 + j] - 0.3 s_t[9 + j]` (body positions, which no frame change touches).
fn dataset(dir: &std::path::Path) -> Dataset {
    let (sd, ad) = (Manifest::default().state_dim, Manifest::default().action_dim);
    let mut rng = StdRng::seed_from_u64(1);
    let mut shard = Shard::default();
    for rollout in 0..200u32 {
        let states: Vec<f32> = (0..30 * sd).map(|_| rng.random_range(-1.0..1.0)).collect();
        for t in 0..30 {
            shard.state.extend_from_slice(&states[t * sd..(t + 1) * sd]);
            let next = &states[(t + 1).min(29) * sd..];
            let action: Vec<f32> = (0..ad).map(|j| 0.5 * next[9 + j] - 0.3 * states[t * sd + 9 + j]).collect();
            shard.action.extend(vec![0.0; ad]);
            shard.noisy_action.extend(action);
            shard.root_pose.extend([0.0, 0.0, 0.0]);
            shard.done.push(u8::from(t == 29));
            shard.sigma.push(0.1);
            shard.rollout.push(rollout);
            shard.frame.push(t as u32);
        }
    }
    let mut data = Dataset::open_or_create(dir).unwrap();
    let info = ShardInfo {
        file: "toy.rollouts.safetensors".into(),
        clip: "toy".into(),
        expert: "none".into(),
        seed: 0,
        steps: 0,
        rollouts: 200,
        sigmas: vec![(0.1, 1)],
        falls: vec![],
        sha256: String::new(),
        mirror_of: None,
    };
    data.add(info, &shard).unwrap();
    data
}

#[test]
fn fits_the_action_from_both_states_and_round_trips() {
    let dir = std::env::temp_dir().join(format!("flowmimic-inverse-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let data = dataset(&dir);
    let (sd, ad) = (data.manifest.state_dim, data.manifest.action_dim);
    let config =
        InverseConfig { hidden: vec![64], steps: 1000, batch: 128, lr: 3e-3, validation_fraction: 0.25, seed: 0 };
    let mut last = None;
    let model = InverseDynamics::fit(std::slice::from_ref(&data), sd, ad, &config, |p| last = Some(*p)).unwrap();
    let last = last.unwrap();
    assert_eq!(last.step, 1000);
    // 0.09 here; reading the action from s_t alone leaves 0.8 (checked by feeding s_t twice).
    let held_out = last.validation_mse.unwrap();
    assert!(held_out < 0.2, "held-out error {held_out} in standardised units");

    let path = dir.join("inverse.safetensors");
    model.save(&path).unwrap();
    let back = InverseDynamics::load(&path, sd, ad).unwrap();
    let x: Vec<f32> = (0..3 * 2 * sd).map(|i| (i as f32 * 0.37).sin()).collect();
    assert_eq!(model.actions(&x, 3), back.actions(&x, 3));

    let err = InverseDynamics::load(&path, sd, ad + 1).unwrap_err().to_string();
    assert!(err.contains("inverse.safetensors") && err.contains("actions of 69"), "{err}");
    let err = InverseDynamics::fit(&[data], sd, ad, &InverseConfig { steps: 0, ..config }, |_| {}).unwrap_err();
    assert!(err.to_string().contains("inverse.steps (0)"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
