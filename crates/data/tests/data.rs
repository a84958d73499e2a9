//! Dataset tests: windows against the simulator's own frames, collection, the format.

use flowmimic_data::*;
use flowmimic_geom::heading;
use flowmimic_motion::{GaitParams, generate};
use flowmimic_sim::{BodyKinematics, Humanoid, Mirror, NUM_DOFS, STATE_DIM, SimConfig};
use flowmimic_track::TrackConfig;
use flowmimic_track::ppo::Policy;
use flowmimic_track::task::OBS_DIM;
use rand::SeedableRng;
use std::path::PathBuf;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("flowmimic-data-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A free-falling, flailing humanoid: a rollout with motion, turning and no expert.
fn raw_rollout(steps: usize) -> (Shard, Vec<BodyKinematics>) {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let mut env = h.env();
    let mut q = h.standing_qpos();
    q[2] += 0.5;
    let mut v = vec![0.0; h.nv()];
    v[0] = 1.0;
    v[1] = -0.5;
    v[5] = 2.0; // spinning about z
    env.reset(&q, &v).unwrap();
    let mut shard = Shard::default();
    let mut kin = Vec::new();
    for s in 0..steps {
        let k = env.bodies();
        shard.state.extend_from_slice(&k.state());
        let a: Vec<f32> = (0..NUM_DOFS).map(|i| 0.3 * ((s * 7 + i) as f32 * 0.3).sin()).collect();
        shard.action.extend_from_slice(&a);
        shard.noisy_action.extend_from_slice(&a);
        shard.root_pose.extend_from_slice(&[k.pos[0].x as f32, k.pos[0].y as f32, heading(k.rot[0]) as f32]);
        shard.done.push(u8::from(s == steps / 2 || s + 1 == steps));
        shard.sigma.push(0.1);
        shard.rollout.push(u32::from(s > steps / 2));
        shard.frame.push(s as u32);
        kin.push(k);
        env.step(&a).unwrap();
    }
    (shard, kin)
}

#[test]
fn windows_reexpress_states_in_the_current_frame_exactly() {
    let (shard, kin) = raw_rollout(30);
    let spec = WindowSpec { history: 4, horizon: 6 };
    let starts = window_starts(&shard, spec);
    assert!(!starts.is_empty());
    for &t in &starts {
        let w = window(&shard, spec, t);
        let frame = kin[t].frame();
        for j in 0..spec.states() {
            let k = t - spec.history + j;
            let expected = kin[k].state_in(&frame);
            let got = &w.states[j * STATE_DIM..(j + 1) * STATE_DIM];
            for i in 0..STATE_DIM {
                assert!(
                    (got[i] - expected[i]).abs() < 1e-4,
                    "t {t} slot {j} feature {i}: {} vs {}",
                    got[i],
                    expected[i]
                );
            }
        }
        assert_eq!(&w.actions[..NUM_DOFS], &shard.action[(t - 4) * NUM_DOFS..(t - 3) * NUM_DOFS]);
        // The current step sits at its own origin facing +x.
        let now = &w.states[spec.history * STATE_DIM..];
        assert!(now[0].abs() < 1e-5 && now[1].abs() < 1e-5);
    }
    // No window crosses the episode end at step 15.
    for &t in &starts {
        assert!(t + spec.horizon <= 15 || t - spec.history > 15, "window at {t} crosses the episode end");
    }
    // Far-future states carry the displacement: the root moved about 1 m/s * 0.2 s ahead.
    let t = starts[0];
    let w = window(&shard, spec, t);
    let last = &w.states[(spec.states() - 1) * STATE_DIM..];
    assert!(last[0].hypot(last[1]) > 0.1);
}

#[test]
fn stats_match_direct_computation() {
    let (shard, _) = raw_rollout(30);
    let spec = WindowSpec { history: 2, horizon: 3 };
    let stats = Stats::compute(spec, [&shard].into_iter());
    let starts = window_starts(&shard, spec);
    assert_eq!(stats.windows, starts.len());
    let feature = 5 * STATE_DIM + 40; // a body position in the last future slot
    let xs: Vec<f64> = starts.iter().map(|&t| f64::from(window(&shard, spec, t).states[feature])).collect();
    let mean = xs.iter().sum::<f64>() / xs.len() as f64;
    let std = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64).sqrt();
    assert!((f64::from(stats.state_mean[feature]) - mean).abs() < 1e-5);
    assert!((f64::from(stats.state_std[feature]) - std.max(1e-3)).abs() < 1e-4);
    assert_eq!(stats.state_std[spec.history * STATE_DIM], 1e-3, "the current root x is always 0: floored std");
}

#[test]
fn collection_writes_checked_shards_and_appends_without_rewriting() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let cfg = TrackConfig { hidden: vec![16], ..Default::default() };
    let expert = Policy::new(OBS_DIM, NUM_DOFS, &cfg, &mut rand::rngs::StdRng::seed_from_u64(0));
    let collect_cfg =
        CollectConfig { noise: vec![(0.12, 2), (0.36, 1)], rollout_steps: 20, seed: 3, ..Default::default() };
    let dir = tmp("collect");
    let mut dataset = Dataset::open_or_create(&dir).unwrap();
    let mut first_bytes = Vec::new();
    for (k, name) in ["a", "b"].iter().enumerate() {
        let clip = generate(&h, name, &GaitParams { duration: 1.0 + k as f64, ..Default::default() }).unwrap().0;
        let (shard, stats) = collect(&h, &clip, &expert, &cfg, &collect_cfg).unwrap();
        assert_eq!(shard.steps(), 3 * 20);
        assert_eq!(stats.steps, 60);
        assert_eq!(shard.done.iter().filter(|&&d| d == 1).count() as u32, shard.rollout.last().unwrap() + 1);
        // Clean and executed actions differ by the noise; larger sigma, larger difference.
        let diff = |lo: usize, hi: usize| -> f32 {
            (lo * NUM_DOFS..hi * NUM_DOFS).map(|i| (shard.action[i] - shard.noisy_action[i]).abs()).sum::<f32>()
                / ((hi - lo) * NUM_DOFS) as f32
        };
        assert!(diff(40, 60) > 1.5 * diff(0, 40), "sigma 0.36 rows vs 0.12 rows");
        assert!(shard.sigma[..40].iter().all(|&s| s == 0.12) && shard.sigma[40..].iter().all(|&s| s == 0.36));
        let info = ShardInfo {
            file: format!("{name}.rollouts.safetensors"),
            clip: name.to_string(),
            expert: "untrained".into(),
            seed: 3,
            steps: 0,
            rollouts: 3,
            sigmas: collect_cfg.noise.clone(),
            falls: stats.falls.clone(),
            sha256: String::new(),
            mirror_of: None,
        };
        dataset.add(info, &shard).unwrap();
        if k == 0 {
            first_bytes = std::fs::read(dir.join("a.rollouts.safetensors")).unwrap();
        }
    }
    assert_eq!(
        std::fs::read(dir.join("a.rollouts.safetensors")).unwrap(),
        first_bytes,
        "adding b left a's shard alone"
    );
    // An untrained expert fails; dropping the steps before each failure keeps fewer, and every
    // episode still ends with a done flag.
    let clip = generate(&h, "c", &GaitParams { duration: 3.0, ..Default::default() }).unwrap().0;
    let long = CollectConfig { rollout_steps: 60, ..collect_cfg.clone() };
    let (all_steps, stats) = collect(&h, &clip, &expert, &cfg, &long).unwrap();
    assert!(stats.falls.iter().map(|f| f.2).sum::<usize>() > 0, "the untrained expert fails");
    let (dropped, _) = collect(&h, &clip, &expert, &cfg, &CollectConfig { drop_before_failure: 5, ..long }).unwrap();
    assert!(dropped.steps() < all_steps.steps(), "{} vs {}", dropped.steps(), all_steps.steps());
    assert_eq!(*dropped.done.last().unwrap(), 1);
    assert_eq!(dropped.done.iter().filter(|&&d| d == 1).count() as u32, dropped.rollout.last().unwrap() + 1);
    let reopened = Dataset::open(&dir).unwrap();
    assert_eq!(reopened.manifest.shards.len(), 2);
    let all = reopened.load_all().unwrap();
    assert_eq!(all[0].1.steps(), 60);
    // Statistics are computed once, stored, and read back for the same shards.
    let spec = WindowSpec { history: 2, horizon: 3 };
    let stats = Stats::of_dataset(&reopened, spec).unwrap();
    let stored = dir.join(Stats::file_name(spec));
    assert!(stored.exists() && stats.windows > 0);
    let (back, _) = Stats::load(&stored).unwrap();
    assert_eq!(back, stats);
    assert_eq!(Stats::of_dataset(&reopened, spec).unwrap(), stats);
    // A damaged shard is named.
    let mut bytes = first_bytes.clone();
    let n = bytes.len();
    bytes[n - 10] ^= 0xff;
    std::fs::write(dir.join("a.rollouts.safetensors"), &bytes).unwrap();
    let err = reopened.load_all().unwrap_err().to_string();
    assert!(err.contains("a.rollouts.safetensors") && err.contains("checksum"), "{err}");
    // A manifest of other dimensions is refused.
    let text = std::fs::read_to_string(dir.join("manifest.json")).unwrap();
    std::fs::write(dir.join("manifest.json"), text.replace("\"state_dim\": 165", "\"state_dim\": 160")).unwrap();
    let err = Dataset::open(&dir).err().unwrap().to_string();
    assert!(err.contains("manifest.json") && err.contains("160"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A shard's manifest entry for tests.
fn entry(clip: &str) -> ShardInfo {
    ShardInfo {
        file: format!("{clip}.rollouts.safetensors"),
        clip: clip.into(),
        expert: "none".into(),
        seed: 0,
        steps: 0,
        rollouts: 2,
        sigmas: vec![(0.1, 1)],
        falls: vec![],
        sha256: String::new(),
        mirror_of: None,
    }
}

#[test]
fn a_mirrored_shard_holds_the_mirror_images_of_the_windows_and_is_added_once() {
    let (shard, _) = raw_rollout(30);
    let image = shard.mirror_image();
    let spec = WindowSpec { history: 4, horizon: 6 };
    let (states, actions) = (Mirror::state(), Mirror::action());
    for &t in &window_starts(&shard, spec) {
        let (w, m) = (window(&shard, spec, t), window(&image, spec, t));
        let mut expected = w.states.clone();
        states.apply_rows(&mut expected);
        assert!(expected.iter().zip(&m.states).all(|(a, b)| (a - b).abs() < 1e-4), "window at {t}");
        let mut expected = w.actions.clone();
        actions.apply_rows(&mut expected);
        assert_eq!(expected, m.actions);
    }
    // The spinning humanoid turns left; its image turns right as fast.
    let turn = |s: &Shard| s.root_pose[3 * 10 + 2] - s.root_pose[2];
    assert!(turn(&shard) > 0.5 && (turn(&image) + turn(&shard)).abs() < 1e-5, "{} {}", turn(&shard), turn(&image));

    let dir = tmp("mirror");
    let mut dataset = Dataset::open_or_create(&dir).unwrap();
    dataset.add(entry("a"), &shard).unwrap();
    let collected = std::fs::read(dir.join("a.rollouts.safetensors")).unwrap();
    assert_eq!(dataset.add_mirror_images().unwrap(), ["a-mirrored"]);
    assert!(dataset.add_mirror_images().unwrap().is_empty(), "a second call adds nothing");
    let reopened = Dataset::open(&dir).unwrap();
    let all = reopened.load_all().unwrap();
    assert_eq!(all.len(), 2);
    assert_eq!(all[1].0.mirror_of.as_deref(), Some(all[0].0.sha256.as_str()));
    assert_eq!(all[1].1, image);
    assert_eq!(std::fs::read(dir.join("a.rollouts.safetensors")).unwrap(), collected, "the collected shard is kept");
    // A clip collected again is mirrored again.
    let mut shorter = shard.clone();
    shorter.truncate(20);
    dataset.add(entry("a"), &shorter).unwrap();
    assert_eq!(dataset.add_mirror_images().unwrap(), ["a-mirrored"]);
    assert_eq!(Dataset::open(&dir).unwrap().load_all().unwrap()[1].1, shorter.mirror_image());
    std::fs::remove_dir_all(&dir).ok();
}

/// A window's command label reads the steps after it within its episode: their own-heading
/// velocity and their turn rate, with headings that wrap past pi.
#[test]
fn a_future_motion_is_read_within_the_episode() {
    let steps = 12;
    let mut shard = Shard::default();
    for k in 0..steps {
        let mut state = vec![0.0f32; STATE_DIM];
        state[flowmimic_sim::state::offset::ROOT_VEL] = 0.8;
        state[flowmimic_sim::state::offset::ROOT_VEL + 1] = -0.1;
        shard.state.extend_from_slice(&state);
        // Turning left at 0.6 rad/s (0.02 rad a step at 30 Hz) through pi.
        let heading = 3.08 + 0.02 * k as f32;
        let heading = if heading > std::f32::consts::PI { heading - std::f32::consts::TAU } else { heading };
        shard.root_pose.extend_from_slice(&[0.0, 0.0, heading]);
        shard.done.push(u8::from(k == 7 || k + 1 == steps));
        shard.rollout.push(0);
    }
    let [forward, left, rate] = future_motion(&shard, 1, 4).unwrap();
    assert!((forward - 0.8).abs() < 1e-6 && (left + 0.1).abs() < 1e-6 && (rate - 0.6).abs() < 1e-3, "{rate}");
    // From step 5 the episode holds steps 6 and 7 only: the same motion over two steps.
    let [_, _, rate] = future_motion(&shard, 5, 10).unwrap();
    assert!((rate - 0.6).abs() < 1e-3, "{rate}");
    // A new episode's steps are not read: step 7 ends one, so from 7 nothing lies ahead.
    assert_eq!(future_motion(&shard, 7, 4), None);
}
