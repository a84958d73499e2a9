//! Protocol metrics on hand-made rollouts, where the answer is known.

use flowmimic_control::{Rollout, RolloutInfo, Task};
use flowmimic_eval::outcome::Outcome;
use flowmimic_eval::protocols::joystick_trial;
use flowmimic_sim::state::offset;
use flowmimic_sim::{NUM_BODIES, NUM_DOFS, STATE_DIM};

/// One environment, `steps` steps, commanded 1 m/s forward and turning at `yaw_rate`, achieving
/// 0.5 m/s forward and a heading that advances by `turn` radians per step, its plans asking 0.6
/// m/s forward; falls at `fall`.
fn rollout(steps: usize, yaw_rate: f64, turn: f64, fall: usize) -> Rollout {
    let nq = 76;
    let mut task = Task::joystick_eval();
    task.joystick = vec![flowmimic_control::JoystickSegment { seconds: 100.0, vx: 1.0, vy: 0.0, yaw_rate }];
    let mut r = Rollout {
        info: RolloutInfo {
            model: "hand-made".into(),
            objective: "fm".into(),
            nfe: 1,
            horizon: 1,
            guidance_scale: 0.0,
            guidance_steps: (0, 1),
            gradient: Default::default(),
            adaptive: None,
            inverse_dynamics: 0.0,
            tasks: vec![task.clone()],
            seed: 0,
            start: "test".into(),
            kick_every: 0.0,
            kick_max: 0.0,
        },
        envs: 1,
        steps,
        nq,
        qpos: vec![0.0; (steps + 1) * nq],
        state: vec![0.0; (steps + 1) * STATE_DIM],
        body_pos: vec![0.0; (steps + 1) * NUM_BODIES * 3],
        action: vec![0.0; steps * NUM_DOFS],
        command: Vec::new(),
        contact: vec![0.0; steps],
        plan: [0.6, 0.0, 0.0].repeat(steps),
        plan_hand: [0.2, -0.3, 1.1].repeat(steps),
        survived: vec![fall],
        model_ms: vec![1.0; steps],
        physics_ms: vec![1.0; steps],
    };
    for k in 0..=steps {
        let yaw = turn * k as f64;
        r.qpos[k * nq + 3] = (yaw / 2.0).cos() as f32;
        r.qpos[k * nq + 6] = (yaw / 2.0).sin() as f32;
        r.state[k * STATE_DIM + offset::ROOT_VEL] = 0.5;
    }
    r.command = (0..steps).flat_map(|k| task.command(k as f64 / 30.0)).collect();
    r
}

#[test]
fn a_known_trace_gives_known_errors() {
    let t = joystick_trial(&rollout(30, 0.0, 0.0, 30), 0);
    assert!((t.velocity_rmse - 0.5).abs() < 1e-9 && t.yaw_rate_rmse.abs() < 1e-9 && !t.fell, "{t:?}");
    // Turning at 0.01 rad per step is 0.3 rad/s against a commanded 0.6 rad/s.
    let t = joystick_trial(&rollout(30, 0.6, 0.01, 30), 0);
    assert!((t.yaw_rate_rmse - 0.3).abs() < 1e-4, "{t:?}");
    // A fall at step 10 counts only the steps before it and is reported.
    let t = joystick_trial(&rollout(30, 0.0, 0.0, 10), 0);
    assert!(t.fell && (t.velocity_rmse - 0.5).abs() < 1e-9, "{t:?}");
}

#[test]
fn each_joystick_segment_reports_what_it_achieved_after_settling() {
    // Two 2 s segments, 1 m/s forward then 0.5 m/s backward asked; 0.5 m/s forward then 0.3
    // m/s backward achieved, turning 0.01 rad per step.
    let seg = |vx| flowmimic_control::JoystickSegment { seconds: 2.0, vx, vy: 0.0, yaw_rate: 0.0 };
    let with = |fall| {
        let mut r = rollout(120, 0.0, 0.01, fall);
        r.info.tasks[0].joystick = vec![seg(1.0), seg(-0.5)];
        r.command = (0..120).flat_map(|k| r.info.tasks[0].command(k as f64 / 30.0)).collect();
        for k in 61..=120 {
            r.state[k * STATE_DIM + offset::ROOT_VEL] = -0.3;
        }
        r
    };
    let t = joystick_trial(&with(120), 0);
    assert_eq!(t.segments.len(), 2);
    for (got, want) in t.segments.iter().zip([[0.5, 0.0, 0.3], [-0.3, 0.0, 0.3]]) {
        assert!(got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-4), "{got:?} against {want:?}");
    }
    // What the plans asked, over the same steps: 0.6 m/s forward throughout.
    assert!(t.planned.iter().all(|p| p.iter().zip([0.6, 0.0, 0.0]).all(|(p, w)| (p - w).abs() < 1e-6)), "{t:?}");
    // Each segment's velocity error over all its steps: 0.5 and 0.2 m/s.
    assert!((t.segment_rmse[0] - 0.5).abs() < 1e-6 && (t.segment_rmse[1] - 0.2).abs() < 1e-6, "{t:?}");
    // A fall in the second segment's first second leaves nothing of it to report after
    // settling, and its error only over the steps before the fall.
    let t = joystick_trial(&with(80), 0);
    assert!((t.segments[0][0] - 0.5).abs() < 1e-9 && t.segments[1].iter().all(|v| v.is_nan()), "{t:?}");
    assert!((t.segment_rmse[1] - 0.2).abs() < 1e-6, "{t:?}");
    // A fall before the segment began: nothing of it at all.
    assert!(joystick_trial(&with(50), 0).segment_rmse[1].is_nan());
}

#[test]
fn a_fall_reports_what_the_body_did_against_its_plans_before_it() {
    // Falls at step 90 (3 s): from 1.5 to 0.5 s before, steps 45-74, the body walks 0.5 m/s
    // forward turning 0.3 rad/s while its plans ask 0.6; the last half second (0.9 m/s) is
    // the falling and is not read.
    let mut r = rollout(120, 0.0, 0.01, 90);
    for k in 76..=120 {
        r.state[k * STATE_DIM + offset::ROOT_VEL] = 0.9;
    }
    let o = Outcome::of(&r);
    assert_eq!(o.falls.len(), 1);
    let f = o.falls[0];
    assert!(f.env == 0 && (f.seconds - 3.0).abs() < 1e-9, "{f:?}");
    assert!(f.achieved.iter().zip([0.5, 0.0, 0.3]).all(|(g, w)| (g - w).abs() < 1e-4), "{f:?}");
    assert!(f.planned.iter().zip([0.6, 0.0, 0.0]).all(|(p, w)| (p - w).abs() < 1e-6), "{f:?}");
    // No fall, nothing reported.
    assert!(Outcome::of(&rollout(120, 0.0, 0.01, 120)).falls.is_empty());
}

#[test]
fn rollouts_round_trip_and_bad_files_are_named() {
    let dir = std::env::temp_dir().join(format!("flowmimic-rollout-{}", std::process::id()));
    let path = dir.join("r.rollout.safetensors");
    let r = rollout(5, 0.0, 0.01, 5);
    r.save(&path).unwrap();
    assert_eq!(Rollout::load(&path).unwrap(), r);
    std::fs::write(&path, b"not a rollout").unwrap();
    let err = Rollout::load(&path).unwrap_err().to_string();
    assert!(err.contains("r.rollout.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
