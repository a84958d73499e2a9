//! Tracking tests on the `tiny` scale: the task's rewards and terminations, and that training
//! runs, checkpoints, resumes and refuses bad checkpoints.

use flowmimic_motion::{Clip, GaitParams, generate};
use flowmimic_sim::{Humanoid, NUM_DOFS, SimConfig};
use flowmimic_track::task::{AHEAD_DIM, AHEAD_FRAMES, Ending, OBS_DIM, Reference, Tracker, obs_dim};
use flowmimic_track::train::Checkpoint;
use flowmimic_track::{TrackConfig, Trainer};
use rand::SeedableRng;
use std::sync::Arc;

fn setup() -> (Arc<Humanoid>, Clip) {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let clip = generate(&h, "walk", &GaitParams { duration: 2.0, ..Default::default() }).unwrap().0;
    (h, clip)
}

fn tiny() -> TrackConfig {
    TrackConfig { envs: 4, horizon: 8, iterations: 2, hidden: vec![32, 32], checkpoint_every: 1, ..Default::default() }
}

/// With `action_noise`, each episode executes the policy's action plus noise of its own
/// deviation, so the same output takes the humanoid elsewhere; without it, nothing changes.
#[test]
fn action_noise_perturbs_what_is_executed_and_only_when_asked() {
    let (h, clip) = setup();
    let reference = Reference::new(clip);
    let qpos_after = |action_noise: f64, seed: u64| {
        let cfg = TrackConfig { init_noise: 0.0, push_max: 0.0, action_noise, ..tiny() };
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut tracker = Tracker::new(&h);
        tracker.reset(&reference, 10, &cfg, &mut rng).unwrap();
        for _ in 0..5 {
            tracker.step(&reference, &[0.0; NUM_DOFS], &cfg, &mut rng);
        }
        tracker.env().qpos().to_vec()
    };
    let gap = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
    // No draws without noise: the seed does not matter.
    assert_eq!(qpos_after(0.0, 1), qpos_after(0.0, 2));
    let (clean, noisy) = (qpos_after(0.0, 1), qpos_after(0.6, 1));
    assert!(gap(&clean, &noisy) > 1e-3, "noise of up to 0.6 units moved no joint");
    assert!(gap(&noisy, &qpos_after(0.6, 2)) > 1e-3, "episodes with other seeds executed the same noise");
}

#[test]
fn reference_state_scores_near_the_maximum_and_falling_terminates() {
    let (h, clip) = setup();
    let reference = Reference::new(clip);
    let cfg = TrackConfig { init_noise: 0.0, push_max: 0.0, ..tiny() };
    let mut rng = rand::rngs::StdRng::seed_from_u64(0);
    let mut tracker = Tracker::new(&h);
    tracker.reset(&reference, 10, &cfg, &mut rng).unwrap();
    let mut obs = vec![f32::NAN; OBS_DIM];
    tracker.observe(&reference, &mut obs);
    assert!(obs.iter().all(|x| x.is_finite()), "observation fully written and finite");
    // Following the reference's own next pose for one step tracks it closely.
    let (terms, ending) = tracker.step(&reference, &[0.0; NUM_DOFS], &cfg, &mut rng);
    assert_eq!(ending, Ending::None);
    let best: f64 = [0.5, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0].iter().sum();
    let total = terms.total(&cfg.reward);
    assert!(f64::from(total) > best - 1.0, "reward {total} of {best} on the reference: {terms:?}");
    assert!(terms.body_pos_error < 0.03, "{terms:?}");
    assert!(terms.root_vel > 0.8, "the root moves as the reference's: {terms:?}");
    // Walking forward where the reference walks backward costs the root velocity term.
    let back = generate(&h, "back", &GaitParams { duration: 2.0, speed: -0.6, ..Default::default() }).unwrap().0;
    let back = Reference::new(back);
    tracker.reset(&reference, 10, &cfg, &mut rng).unwrap();
    let (terms, _) = tracker.step(&back, &[0.0; NUM_DOFS], &cfg, &mut rng);
    assert!(terms.root_vel < 0.01, "1.6 m/s off the reference's root velocity: {terms:?}");
    // Without balance the open-loop reference falls within a few seconds, and that ends it.
    let mut ended = None;
    for step in 0..50 {
        let (_, e) = tracker.step(&reference, &[0.0; NUM_DOFS], &cfg, &mut rng);
        if e != Ending::None {
            ended = Some((step, e));
            break;
        }
    }
    assert!(matches!(ended, Some((_, Ending::Failed | Ending::ClipEnd))), "{ended:?}");
    // A reset far from the reference fails at once.
    tracker.reset(&reference, 10, &cfg, &mut rng).unwrap();
    let lying: Vec<f32> = (0..NUM_DOFS).map(|i| if i % 3 == 1 { 6.0 } else { 0.0 }).collect();
    let mut failed = false;
    for _ in 0..30 {
        if tracker.step(&reference, &lying, &cfg, &mut rng).1 == Ending::Failed {
            failed = true;
            break;
        }
    }
    assert!(failed, "bending every pitch hinge 0.9 rad away from the reference must fail tracking within 1 s");
}

#[test]
fn training_checkpoints_resumes_and_refuses_bad_checkpoints() {
    let (h, clip) = setup();
    let dir = std::env::temp_dir().join(format!("flowmimic-track-{}", std::process::id()));
    let path = dir.join("policy.safetensors");
    let mut trainer = Trainer::new(&h, vec![clip.clone()], tiny()).unwrap();
    for _ in 0..2 {
        let log = trainer.iterate().unwrap();
        assert!(log.mean_reward.is_finite() && log.update.value_loss.is_finite() && log.update.kl.is_finite());
    }
    trainer.save(&path).unwrap();
    let resumed = Trainer::resume(&h, vec![clip.clone()], tiny(), &path).unwrap();
    assert_eq!((resumed.iteration, resumed.env_steps), (2, 64));
    assert_eq!(resumed.policy.params(), trainer.policy.params());
    assert_eq!(resumed.policy.normaliser.mean, trainer.policy.normaliser.mean);
    // The stored policy acts like the trained one.
    let policy = Checkpoint::read(&path).unwrap().policy().unwrap();
    let obs = vec![0.3f32; OBS_DIM];
    assert_eq!(policy.act(&obs, 1), trainer.policy.act(&obs, 1));
    // A checkpoint for another clip, another network, or a damaged file is refused by name.
    let other = generate(&h, "other", &GaitParams { duration: 3.0, ..Default::default() }).unwrap().0;
    let err = Trainer::resume(&h, vec![other], tiny(), &path).err().unwrap().to_string();
    assert!(err.contains("policy.safetensors") && err.contains("clip"), "{err}");
    let wider = TrackConfig { hidden: vec![64, 64], ..tiny() };
    assert!(Trainer::resume(&h, vec![clip.clone()], wider, &path).err().unwrap().to_string().contains("hidden"));
    let bytes = std::fs::read(&path).unwrap();
    let broken = dir.join("broken.safetensors");
    std::fs::write(&broken, &bytes[..bytes.len() - 100]).unwrap();
    let err = Trainer::resume(&h, vec![clip], tiny(), &broken).err().unwrap().to_string();
    assert!(err.contains("broken.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_config_is_refused() {
    let (h, clip) = setup();
    for cfg in [TrackConfig { envs: 0, ..tiny() }, TrackConfig { hidden: vec![], ..tiny() }] {
        assert!(Trainer::new(&h, vec![clip.clone()], cfg).is_err());
    }
    assert!(Trainer::new(&h, vec![], tiny()).is_err(), "no clip");
    // More clips than environments is fine: each episode draws its clip.
    let mut trainer = Trainer::new(&h, vec![clip; 5], tiny()).unwrap();
    assert!(trainer.iterate().is_ok());
}

#[test]
fn one_policy_trains_on_several_clips() {
    let (h, a) = setup();
    let b = generate(&h, "back", &GaitParams { speed: -0.5, duration: 1.5, ..Default::default() }).unwrap().0;
    let mut trainer = Trainer::new(&h, vec![a.clone(), b.clone()], tiny()).unwrap();
    assert_eq!(trainer.references.len(), 2);
    let log = trainer.iterate().unwrap();
    assert!(log.mean_reward.is_finite());
    let dir = std::env::temp_dir().join(format!("flowmimic-track-multi-{}", std::process::id()));
    let path = dir.join("policy.safetensors");
    trainer.save(&path).unwrap();
    let resumed = Trainer::resume(&h, vec![a.clone(), b.clone()], tiny(), &path).unwrap();
    assert_eq!(resumed.policy.params(), trainer.policy.params());
    let err = Trainer::resume(&h, vec![b.clone(), a], tiny(), &path).err().unwrap().to_string();
    assert!(err.contains("walk,back"), "clips in another order are another run: {err}");
    // A warm start takes the policy onto other clips and other environments, counters at zero.
    let more_envs = TrackConfig { envs: tiny().envs + 2, ..tiny() };
    let mut warm = Trainer::warm_start(&h, vec![b.clone()], more_envs, &path).unwrap();
    assert_eq!((warm.iteration, warm.env_steps), (0, 0));
    assert_eq!(warm.policy.params(), trainer.policy.params());
    assert_eq!(warm.policy.normaliser.mean, trainer.policy.normaliser.mean);
    assert!(warm.iterate().unwrap().mean_reward.is_finite());
    let wider = TrackConfig { hidden: vec![64, 64], ..tiny() };
    let err = Trainer::warm_start(&h, vec![b], wider, &path).err().unwrap().to_string();
    assert!(err.contains("hidden") && err.contains("policy.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// A policy with `observe_ahead` observes the reference's hinges 10 and 30 frames ahead after
/// what every policy observes; warm-started from one without, it acts as that one did whatever
/// the new entries hold, and a checkpoint of it loads only where the config asks for it.
#[test]
fn a_policy_observing_ahead_sees_the_reference_ahead_and_starts_where_its_start_was() {
    let (h, clip) = setup();
    let reference = Reference::new(clip);
    let cfg = TrackConfig { init_noise: 0.0, ..tiny() };
    let mut tracker = Tracker::new(&h);
    tracker.reset(&reference, 5, &cfg, &mut rand::rngs::StdRng::seed_from_u64(0)).unwrap();
    let (mut narrow, mut wide) = (vec![0.0; OBS_DIM], vec![f32::NAN; obs_dim(true)]);
    tracker.observe(&reference, &mut narrow);
    tracker.observe(&reference, &mut wide);
    assert_eq!(wide.len(), OBS_DIM + AHEAD_FRAMES.len() * AHEAD_DIM);
    assert_eq!(wide[..OBS_DIM], narrow[..]);
    for (k, ahead) in AHEAD_FRAMES.into_iter().enumerate() {
        let block = &wide[OBS_DIM + k * AHEAD_DIM..][..NUM_DOFS];
        let hinges: Vec<f32> = reference.clip.qpos[5 + ahead][7..].iter().map(|&q| q as f32).collect();
        assert_eq!(block, &hinges[..], "{ahead} frames ahead");
    }
    assert!(wide.iter().all(|x| x.is_finite()));

    let dir = std::env::temp_dir().join(format!("flowmimic-track-ahead-{}", std::process::id()));
    let path = dir.join("policy.safetensors");
    let mut start = Trainer::new(&h, vec![reference.clip.clone()], tiny()).unwrap();
    start.iterate().unwrap();
    start.save(&path).unwrap();
    let ahead = TrackConfig { observe_ahead: true, ..tiny() };
    let mut warm = Trainer::warm_start(&h, vec![reference.clip.clone()], ahead.clone(), &path).unwrap();
    assert_eq!(warm.policy.obs_dim(), obs_dim(true));
    let mut noisy = wide.clone();
    noisy[OBS_DIM..].iter_mut().enumerate().for_each(|(i, x)| *x += (i % 7) as f32 - 3.0);
    assert_eq!(warm.policy.act(&noisy, 1), start.policy.act(&narrow, 1), "the new inputs start unused");
    warm.iterate().unwrap();
    warm.save(&path).unwrap();
    assert_eq!(Checkpoint::read(&path).unwrap().policy().unwrap().obs_dim(), obs_dim(true));
    let err = Trainer::warm_start(&h, vec![reference.clip.clone()], tiny(), &path).err().unwrap().to_string();
    assert!(err.contains("observe_ahead"), "{err}");
    let err = Trainer::resume(&h, vec![reference.clip], tiny(), &path).err().unwrap().to_string();
    assert!(err.contains("observe_ahead"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

/// Evaluation sets the episodes' backward and sidestep shares beside the reference's, each
/// measured on its own path: an untrained policy falls, swaying where the reference walks
/// straight back.
#[test]
fn evaluation_measures_the_path_beside_the_reference() {
    let (h, forward) = setup();
    let back = generate(&h, "back", &GaitParams { speed: -0.6, duration: 2.0, ..Default::default() }).unwrap().0;
    let trainer = Trainer::new(&h, vec![back.clone()], tiny()).unwrap();
    let setup = flowmimic_track::EvalSetup { episodes: 2, start_frame: 0, kicks: false, seed: 0 };
    let eval = |clip: &Clip| flowmimic_track::evaluate(&h, &trainer.policy, clip, &tiny(), setup).unwrap();
    let report = eval(&back);
    assert!(report.reference_backward > 0.8 && report.reference_sidestep < 0.05, "{report:?}");
    assert!((report.sidestep - report.reference_sidestep).abs() > 0.1, "{report:?}");
    let report = eval(&forward);
    assert!(report.reference_backward == 0.0 && report.reference_sidestep < 0.05, "{report:?}");
}

#[test]
fn bench_reports_ppo_beside_the_physics_of_the_same_iterations() {
    let (h, clip) = setup();
    let report = flowmimic_track::train::bench(&h, vec![clip], tiny(), 3, 2).unwrap();
    let log = &report.log;
    for (name, value) in [
        ("env steps/s", f64::from(log.steps_per_second)),
        ("physics s", f64::from(log.physics_seconds)),
        ("update s", f64::from(log.update_seconds)),
        ("VecEnv /s", report.vec_env_per_second),
        ("PPO / VecEnv", report.ppo_over_vec_env),
    ] {
        assert!(value.is_finite() && value > 0.0, "{name}: {value}");
    }
    // Physics is part of each iteration, never more than all of it.
    assert!(report.physics_share > 0.0 && report.physics_share <= 1.0, "{}", report.physics_share);
}

/// A warm start with `fresh_output` acts with a zero residual (the reference's hinges as they
/// are) whatever it observes, explores at `init_log_std` at least, and lets its observation
/// statistics move.
#[test]
fn a_fresh_output_starts_at_a_zero_residual() {
    let (h, clip) = setup();
    let dir = std::env::temp_dir().join(format!("flowmimic-track-fresh-{}", std::process::id()));
    let path = dir.join("policy.safetensors");
    let mut start = Trainer::new(&h, vec![clip.clone()], TrackConfig { init_log_std: -3.0, ..tiny() }).unwrap();
    start.iterate().unwrap();
    start.save(&path).unwrap();
    let fresh = TrackConfig { fresh_output: true, init_log_std: -1.0, learning_rate: 3e-4, ..tiny() };
    let warm = Trainer::warm_start(&h, vec![clip], fresh, &path).unwrap();
    let obs: Vec<f32> = (0..2 * OBS_DIM).map(|i| (i % 11) as f32 - 5.0).collect();
    assert!(start.policy.act(&obs, 2).iter().any(|&u| u != 0.0));
    assert!(warm.policy.act(&obs, 2).iter().all(|&u| u == 0.0));
    assert!(warm.policy.log_std.iter().all(|&s| s >= -1.0));
    assert!(warm.policy.normaliser.count <= flowmimic_track::train::FRESH_OBSERVATIONS);
    assert_eq!(warm.policy.normaliser.mean, start.policy.normaliser.mean);
    std::fs::remove_dir_all(&dir).ok();
}

/// Plan clips: each rollout of the expert from a random frame, 3 s to the length asked, its
/// first frame a state of the simulator (velocities included); the same seed the same clips.
#[test]
fn plan_clips_hold_the_experts_targets_after_its_own_first_state() {
    use flowmimic_track::plan::{PlanClipSetup, plan_clips};
    let h = Humanoid::new(SimConfig::default()).unwrap();
    // The shipped expert of the generated straight walk.
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../pretrained/experts/walk_straight/policy.safetensors");
    let ck = Checkpoint::read(&file).unwrap();
    let (cfg, policy) = (ck.config().unwrap(), ck.policy().unwrap());
    let clip = flowmimic_motion::straight_walk(&h).unwrap();
    let setup = PlanClipSetup { per_clip: 3, seconds: 4.0, seed: 7 };
    let clips = plan_clips(&h, &policy, &cfg, std::slice::from_ref(&clip), setup).unwrap();
    assert!(!clips.is_empty());
    for c in &clips {
        assert!(c.name.starts_with(&format!("{}_plan700", clip.name)), "{}", c.name);
        assert!((90..=121).contains(&c.len()), "{} frames", c.len());
        // Frame 0 is a state of the simulator: its body kinematics are its qpos and qvel's.
        let mut env = h.env();
        env.reset(&c.qpos[0], &c.qvel[0]).unwrap();
        assert_eq!(env.bodies().pos, c.bodies[0].pos);
        assert!(c.qpos.iter().flatten().all(|x| x.is_finite()));
    }
    let again = plan_clips(&h, &policy, &cfg, std::slice::from_ref(&clip), setup).unwrap();
    assert_eq!(again.iter().map(|c| &c.qpos).collect::<Vec<_>>(), clips.iter().map(|c| &c.qpos).collect::<Vec<_>>());
}
