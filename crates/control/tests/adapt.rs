//! Adaptive guidance: the executed motion is measured as it happened, the factor follows it
//! within its bounds, and the controller applies it to joystick tasks only.

use flowmimic_control::adapt::{Recent, WINDOW};
use flowmimic_control::{Adaptive, ControlConfig, Hand, JoystickSegment, Task, run};
use flowmimic_model::TrajectoryModel;
use flowmimic_sim::{Humanoid, SimConfig};
use std::path::Path;

/// Poses of a walker at `speed` m/s forward turning at `rate` rad/s, from heading `start`.
fn walked(speed: f64, rate: f64, start: f64, steps: usize) -> Recent {
    let mut recent = Recent::default();
    let (mut x, mut y, mut h) = (1.0, -2.0, start);
    for _ in 0..steps {
        recent.push([x, y, h]);
        x += speed * h.cos() / 30.0;
        y += speed * h.sin() / 30.0;
        h += rate / 30.0;
    }
    recent
}

#[test]
fn the_executed_velocity_is_measured_in_the_walkers_own_frame() {
    assert_eq!(walked(1.0, 0.0, 0.3, WINDOW).velocity(), None, "not before half a second");
    // Straight, in any heading (3.1 wraps past pi on the way).
    for start in [0.0, 2.0, 3.1, -1.0] {
        let ([vx, vy], rate) = walked(-0.5, 0.0, start, 40).velocity().unwrap();
        assert!((vx + 0.5).abs() < 1e-9 && vy.abs() < 1e-9 && rate.abs() < 1e-9, "{vx} {vy} {rate}");
    }
    // Turning: the chord of the arc, seen from the middle heading, points forward (within
    // the half step by which this walker moves before it turns).
    let ([vx, vy], rate) = walked(0.8, 0.6, 3.0, 40).velocity().unwrap();
    assert!((rate - 0.6).abs() < 1e-9 && (vx - 0.8).abs() < 0.01 && vy.abs() < 0.01, "{vx} {vy} {rate}");

    let back =
        Task { joystick: vec![JoystickSegment { seconds: 3.0, vx: -0.5, vy: 0.0, yaw_rate: 0.0 }], ..Task::walk() };
    let error = back.executed_error(1.0, &walked(1.0, 0.0, 0.0, 40)).unwrap();
    assert!((error - 1.5).abs() < 1e-9, "forward at 1 m/s asked -0.5: {error}");
    let reach = Task { reach: Some((Hand::Right, [2.0, 0.0, 1.2])), ..Task::walk() };
    assert_eq!(reach.executed_error(1.0, &walked(1.0, 0.0, 0.0, 40)), None, "a hand target keeps w");
}

#[test]
fn the_factor_follows_the_error_within_its_bounds() {
    let a = Adaptive::new(0.5).unwrap();
    assert_eq!(a.factor(None), 1.0);
    assert_eq!(a.factor(Some(0.25)), 0.5);
    assert_eq!(a.factor(Some(0.5)), 1.0);
    assert_eq!(a.factor(Some(0.0)), Adaptive::MIN_FACTOR as f32);
    assert_eq!(a.factor(Some(9.0)), Adaptive::MAX_FACTOR as f32);
    for bad in [0.0, -1.0, f32::NAN, f32::INFINITY] {
        let err = Adaptive::new(bad).unwrap_err().to_string();
        assert!(err.contains("adaptive guidance reference"), "{err}");
    }
}

/// The shipped guidance model: adaptive guidance changes the executed actions of a joystick
/// task once half a second has been measured, and leaves a reach task exactly as the fixed
/// scale runs it.
#[test]
fn the_controller_adapts_joystick_tasks_only() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../pretrained/models/guide"));
    let model = TrajectoryModel::load(dir).unwrap();
    let clip = flowmimic_motion::straight_walk(&h).unwrap();
    let fixed = ControlConfig::new(2, 20.0, 1.0);
    let adaptive = ControlConfig { adaptive: Some(Adaptive::new(1.0).unwrap()), ..fixed.clone() };
    let actions = |tasks: &[Task], config: &ControlConfig| {
        run(&model, &h, &clip, tasks.to_vec(), config, "guide", |_| {}).unwrap().action
    };
    let joystick = [Task::joystick_eval()];
    let (a, b) = (actions(&joystick, &fixed), actions(&joystick, &adaptive));
    let step = a.len() / 30;
    assert_eq!(a[..step * 15], b[..step * 15], "the same until half a second is measured");
    assert_ne!(a[step * 16..], b[step * 16..], "then the scale follows the error");
    let reach = [Task { reach: Some((Hand::Right, [2.0, -0.4, 1.3])), ..Task::walk() }];
    assert_eq!(actions(&reach, &fixed), actions(&reach, &adaptive));
}
