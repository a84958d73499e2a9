//! Every cost's gradient against central finite differences, and the commands' checks.

use flowmimic_control::*;
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::state::offset;

/// A trajectory with plausible magnitudes: root moving forward, small tilts and turns.
fn trajectory(layout: Layout) -> Vec<f32> {
    let mut tau: Vec<f32> = (0..layout.len()).map(|i| 0.3 * ((i as f32) * 0.731).sin()).collect();
    for k in 1..=layout.horizon {
        let kf = k as f32;
        let p = layout.root_pos(k);
        tau[p..p + 3].copy_from_slice(&[0.04 * kf, 0.01 * kf, 0.9]);
        let r = layout.root_rot(k);
        tau[r..r + 3].copy_from_slice(&[0.02, -0.03, 0.05 * kf]);
        let h = layout.body_pos(k, body::R_HAND);
        tau[h..h + 3].copy_from_slice(&[0.1, -0.25, 0.05 + 0.01 * kf]);
    }
    tau
}

fn check_gradient(cost: &dyn Cost, tau: &[f32], what: &str) {
    let mut grad = vec![0.0; tau.len()];
    cost.add_grad(tau, &mut grad);
    let eps = 1e-3;
    let mut checked = 0;
    for i in 0..tau.len() {
        let (mut a, mut b) = (tau.to_vec(), tau.to_vec());
        a[i] += eps;
        b[i] -= eps;
        let fd = (f64::from(cost.cost(&a)) - f64::from(cost.cost(&b))) / (2.0 * f64::from(eps));
        let tol = 2e-2 * (1.0 + fd.abs());
        assert!((fd - f64::from(grad[i])).abs() < tol, "{what}: d/dtau[{i}] fd {fd} vs {}", grad[i]);
        checked += usize::from(grad[i] != 0.0);
    }
    assert!(checked > 0, "{what}: the gradient is not all zero");
}

#[test]
fn gradients_match_finite_differences() {
    let layout = Layout { horizon: 4 };
    let tau = trajectory(layout);
    check_gradient(&Joystick::new(layout, 1.0, -0.2).unwrap(), &tau, "joystick");
    check_gradient(&Joystick::turning(layout, 1.0, -0.2, 0.7).unwrap(), &tau, "joystick while turning");
    check_gradient(&Heading::new(layout, 0.5).unwrap(), &tau, "heading");
    check_gradient(&Reach::new(layout, body::R_HAND, [0.3, -0.5, 1.4]).unwrap(), &tau, "reach");
    let both = Sum::default()
        .with(1.0, Heading::new(layout, -0.4).unwrap())
        .with(3.0, Reach::new(layout, body::R_HAND, [0.3, -0.5, 1.4]).unwrap());
    check_gradient(&both, &tau, "heading + reach");
}

#[test]
fn costs_measure_what_they_say() {
    let layout = Layout { horizon: 3 };
    let mut tau = vec![0.0f32; layout.len()];
    for k in 1..=3 {
        let v = layout.root_vel(k);
        tau[v] = 1.0;
    }
    // Walking at exactly the command costs nothing; the wrong way costs 1/2 * 4 per state.
    assert_eq!(Joystick::new(layout, 1.0, 0.0).unwrap().cost(&tau), 0.0);
    assert!((Joystick::new(layout, -1.0, 0.0).unwrap().cost(&tau) - 6.0).abs() < 1e-6);
    // The hand is the root plus the yaw-rotated local offset: a 90 degree turn maps +x to +y.
    let k = 1;
    tau[layout.root_pos(k)..layout.root_pos(k) + 3].copy_from_slice(&[1.0, 0.0, 0.9]);
    tau[layout.root_rot(k) + 2] = std::f32::consts::FRAC_PI_2;
    let h = layout.body_pos(k, body::L_HAND);
    tau[h..h + 3].copy_from_slice(&[0.5, 0.0, 0.1]);
    let single = Layout { horizon: 1 };
    let at = Reach::new(single, body::L_HAND, [1.0, 0.5, 1.0]).unwrap();
    assert!(at.cost(&tau[..single.len()]) < 1e-10, "hand at (1, 0.5, 1.0)");
    assert_eq!(layout.state(1), 69);
    assert_eq!(layout.root_vel(2) - layout.root_pos(2), offset::ROOT_VEL);
}

#[test]
fn world_targets_are_converted_through_the_root_pose() {
    let layout = Layout { horizon: 1 };
    // Standing at (2, 3) facing +y: a world point 1 m further along +y is 1 m straight ahead,
    // so the walker goes straight at full speed without turning.
    let frame = CharFrame::new(DVec3::new(2.0, 3.0, 0.9), std::f64::consts::FRAC_PI_2);
    let ahead = Pursuit::world([2.0, 4.0], &frame).unwrap();
    assert!((ahead.speed - 1.0).abs() < 1e-9 && ahead.yaw_rate.abs() < 1e-9, "{ahead:?}");
    // A point at -x in the world lies on its left: it turns left, at the capped rate, slowly,
    // stepping left at the capped sideways speed.
    let left = Pursuit::world([0.0, 3.0], &frame).unwrap();
    assert!((left.yaw_rate - 1.2).abs() < 1e-9 && (left.speed - 0.2).abs() < 1e-9, "{left:?}");
    assert!((left.lateral - 0.3).abs() < 1e-9, "{left:?}");
    // 0.1 m to the right, 2 m ahead: a small right turn and a sidestep of 0.1 m/s.
    let right = Pursuit::world([2.1, 5.0], &frame).unwrap();
    assert!(right.yaw_rate < 0.0 && (right.lateral + 0.1).abs() < 1e-9, "{right:?}");
    let reach = Reach::world(layout, body::R_HAND, [2.0, 4.0, 1.0], &frame).unwrap();
    let mut tau = vec![0.0f32; layout.len()];
    tau[layout.root_pos(1)..layout.root_pos(1) + 3].copy_from_slice(&[1.0, 0.0, 1.0]);
    assert!(reach.cost(&tau) < 1e-6, "the hand at the root, 1 m ahead and 1 m up");
}

#[test]
fn bad_commands_are_refused_with_the_value() {
    let layout = Layout { horizon: 2 };
    let err = Joystick::new(layout, f64::NAN, 0.0).err().unwrap().to_string();
    assert!(err.contains("joystick") && err.contains("NaN"), "{err}");
    assert!(Joystick::new(layout, 10.0, 0.0).err().unwrap().to_string().contains("10"));
    assert!(Reach::new(layout, body::R_HAND, [9.0, 0.0, 1.0]).is_err());
    assert!(Reach::new(layout, body::R_HAND, [0.5, 0.0, -1.0]).is_err());
    assert!(Pursuit::new([f64::INFINITY, 0.0]).is_err());
    assert!(Pursuit::new([300.0, 0.0]).err().unwrap().to_string().contains("300"));
    assert!(Heading::new(layout, 7.0).is_err());
}

#[test]
fn turning_is_asked_step_by_step_and_far_targets_still_pull() {
    let layout = Layout { horizon: 16 };
    let mut tau = vec![0.0f32; layout.len()];
    let dt = 1.0 / 30.0;
    // A walker turning at exactly 0.6 rad/s with its forward velocity turning along.
    for k in 1..=16 {
        let yaw = 0.6 * k as f32 * dt;
        tau[layout.root_rot(k) + 2] = yaw;
        tau[layout.root_vel(k)..layout.root_vel(k) + 2].copy_from_slice(&[0.8 * yaw.cos(), 0.8 * yaw.sin()]);
    }
    let heading = Heading::new(layout, 0.6).unwrap();
    assert!(heading.cost(&tau) < 1e-10 && heading.error(&tau) < 1e-5);
    assert!(Joystick::turning(layout, 0.8, 0.0, 0.6).unwrap().cost(&tau) < 1e-10);
    // The heading gradient is spread over the steps: none holds more than a third of it (a
    // rate on successive differences put it all on the last state).
    let still = vec![0.0f32; layout.len()];
    // Its error is in the command's unit: a walker that does not turn misses by 0.6 rad/s.
    assert!((heading.error(&still) - 0.6).abs() < 1e-5, "{}", heading.error(&still));
    let mut grad = vec![0.0; layout.len()];
    heading.add_grad(&still, &mut grad);
    let per_step: Vec<f32> = (1..=16).map(|k| grad[layout.root_rot(k) + 2].abs()).collect();
    let total: f32 = per_step.iter().sum();
    assert!(per_step.iter().all(|g| *g < total / 3.0), "{per_step:?}");
    // A hand target 6 m away (the walker wandered off) is a cost like any other, not an error.
    let frame = CharFrame::new(DVec3::new(0.0, 0.0, 0.9), 0.0);
    let far = Reach::world(layout, body::R_HAND, [6.0, 0.0, 1.2], &frame).unwrap();
    assert!(far.error(&still) > 5.0);
    assert!(Reach::world(layout, body::R_HAND, [6.0, 0.0, 3.5], &frame).is_err(), "heights are still checked");
}

/// The joystick velocity asked speeds up at most the acceleration given, on each axis, and
/// slows toward standing at once; a ramped command reaches the joystick's cost.
#[test]
fn a_joystick_speeds_up_gently_and_slows_at_once() {
    let seg = |vx, vy| JoystickSegment { seconds: 3.0, vx, vy, yaw_rate: 0.0 };
    let mut ramp = SpeedRamp::default();
    assert_eq!(ramp.velocity(Some(&seg(0.0, 0.0)), 0.0, 1.0), Some([0.0, 0.0]), "the first command as given");
    let close = |v: Option<[f64; 2]>, want: [f64; 2]| {
        let v = v.unwrap();
        assert!((v[0] - want[0]).abs() < 1e-12 && (v[1] - want[1]).abs() < 1e-12, "{v:?} vs {want:?}");
    };
    // From standing to 1.4 m/s forward and 0.3 m/s right: 0.5 s later, 0.5 m/s on each axis at most.
    close(ramp.velocity(Some(&seg(1.4, -0.3)), 0.5, 1.0), [0.5, -0.3]);
    close(ramp.velocity(Some(&seg(1.4, -0.3)), 1.0, 1.0), [1.0, -0.3]);
    close(ramp.velocity(Some(&seg(1.4, -0.3)), 2.0, 1.0), [1.4, -0.3]);
    // Reversing: down to 0 at once, then backward at the acceleration.
    close(ramp.velocity(Some(&seg(-0.6, 0.0)), 2.1, 1.0), [-0.1, 0.0]);
    close(ramp.velocity(Some(&seg(-0.6, 0.0)), 2.5, 1.0), [-0.5, 0.0]);
    close(ramp.velocity(Some(&seg(0.4, 0.0)), 2.6, 1.0), [0.1, 0.0]);
    assert_eq!(ramp.velocity(None, 3.0, 1.0), None, "no joystick, nothing asked");
    close(ramp.velocity(Some(&seg(1.0, 0.0)), 3.1, 1.0), [1.0, 0.0]);
    // The joystick cost asks the ramped velocity in place of the command's.
    let layout = Layout { horizon: 4 };
    let tau = trajectory(layout);
    let frame = CharFrame::new(DVec3::new(0.0, 0.0, 0.9), 0.0);
    let task = Task { joystick: vec![seg(1.4, 0.0)], ..Task::walk() };
    let asked =
        task.cost(layout, 0.0, &frame, Steer { heading_lag: 0.0, velocity: Some([0.5, 0.0]) }).unwrap().unwrap();
    let slower = Task { joystick: vec![seg(0.5, 0.0)], ..Task::walk() };
    let slower = slower.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap();
    assert!((asked.cost(&tau) - slower.cost(&tau)).abs() < 1e-6, "{} vs {}", asked.cost(&tau), slower.cost(&tau));
}

/// The joystick's heading is held from when its turn rate was set: a walker that turned less
/// than asked (or drifted while asked to go straight) is behind it by what it missed, so the
/// next plan is asked to undo it.
#[test]
fn a_joystick_heading_is_held_from_when_its_command_began() {
    let seg = |vx, yaw_rate| JoystickSegment { seconds: 3.0, vx, vy: 0.0, yaw_rate };
    let (straight, left) = (seg(1.0, 0.0), seg(0.8, 0.6));
    let mut hold = HeadingHold::default();
    assert_eq!(hold.lag(Some(&straight), 0.0, 3.0), 0.0, "a new command starts where the walker faces");
    // Drifted 0.2 rad left walking straight: 0.2 rad to the right is asked back.
    assert!((hold.lag(Some(&straight), 1.0, 3.2) + 0.2).abs() < 1e-12);
    // Headings wrap: from 3.0 on past pi to -3.0 is 0.28 rad left, not 6 rad right.
    let lag = hold.lag(Some(&straight), 1.5, -3.0);
    assert!((lag + (2.0 * std::f64::consts::PI - 6.0)).abs() < 1e-12, "{lag}");
    // A new command starts again; after 1 s of a 0.6 rad/s turn that only reached 0.2 rad the
    // walker is 0.4 rad behind, and never more than MAX_LAG however far behind it falls.
    assert_eq!(hold.lag(Some(&left), 2.0, 1.0), 0.0);
    assert!((hold.lag(Some(&left), 3.0, 1.2) - 0.4).abs() < 1e-12);
    assert_eq!(hold.lag(Some(&left), 5.0, 1.0), HeadingHold::MAX_LAG);
    // ... and the heading asked is kept within MAX_LAG of the walker's (1.5 rad here, not 2.8),
    // integrated on through a new speed and a turn rate that only jitters (0.62 for 0.6).
    let lag = hold.lag(Some(&seg(0.5, 0.62)), 5.5, 1.6);
    assert!((lag - (1.5 + 0.31 - 1.6)).abs() < 1e-12, "{lag}");
    assert_eq!(hold.lag(None, 5.5, 1.0), 0.0, "no joystick, no heading");
    // A lag is asked back as a faster turn: 0.25 rad in HeadingHold::CATCH_UP (0.5 s) adds 0.5
    // rad/s to a 0.6 rad/s command, for the heading and for the turning velocity alike.
    let layout = Layout { horizon: 4 };
    let tau = trajectory(layout);
    let frame = CharFrame::new(DVec3::new(0.0, 0.0, 0.9), 0.0);
    let task = Task { joystick: vec![left], ..Task::walk() };
    let asked = task.cost(layout, 0.0, &frame, Steer { heading_lag: 0.25, velocity: None }).unwrap().unwrap();
    let faster = Sum::default()
        .with(1.0, Joystick::turning(layout, 0.8, 0.0, 1.1).unwrap())
        .with(1.0, Heading::new(layout, 1.1).unwrap());
    assert!((asked.cost(&tau) - faster.cost(&tau)).abs() < 1e-6, "{} vs {}", asked.cost(&tau), faster.cost(&tau));
    // Walking straight, the heading is asked too (rate 0).
    let straight =
        Task { joystick: vec![straight], ..Task::walk() }.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap();
    assert_eq!(straight.terms.len(), 2);
}

#[test]
fn guidance_gradients_have_the_length_of_their_error_in_normalised_units() {
    let layout = Layout { horizon: 4 };
    let tau = trajectory(layout);
    let std: Vec<f32> = (0..layout.len()).map(|i| 0.1 + 0.05 * (i % 7) as f32).collect();
    let joystick = Joystick::new(layout, 1.5, 0.0).unwrap();
    let reach = Reach::new(layout, body::R_HAND, [0.3, -0.5, 1.4]).unwrap();
    let length = |g: &[f32]| g.iter().zip(&std).map(|(g, s)| (g * s).powi(2)).sum::<f32>().sqrt();
    for (cost, error) in [
        (Sum::default().with(1.0, Joystick::new(layout, 1.5, 0.0).unwrap()), joystick.error(&tau)),
        (
            Sum::default().with(2.0, Reach::new(layout, body::R_HAND, [0.3, -0.5, 1.4]).unwrap()),
            2.0 * reach.error(&tau),
        ),
    ] {
        let mut g = vec![0.0; layout.len()];
        cost.guidance_grad(&tau, &std, &mut g);
        assert!((length(&g) - error).abs() < 1e-4 * (1.0 + error), "{} vs {error}", length(&g));
        // It points where the cost's own gradient points.
        let mut plain = vec![0.0; layout.len()];
        cost.add_grad(&tau, &mut plain);
        assert!(g.iter().zip(&plain).map(|(a, b)| a * b).sum::<f32>() > 0.0);
    }
}

#[test]
fn walking_up_to_a_hand_target_leads_the_pelvis_beside_it() {
    // Standing at (2, 3) facing +y: the pelvis is aimed 0.08 m left of a right-hand target
    // (-x in the world) and 0.11 m short of it.
    let frame = CharFrame::new(DVec3::new(2.0, 3.0, 0.9), std::f64::consts::FRAC_PI_2);
    let reach = Some((Hand::Right, [4.0, 6.0, 0.8]));
    let task = Task { reach, approach: true, ..Task::walk() };
    let [x, y] = task.pelvis_goal(&frame, 0.0).unwrap();
    assert!((x - 3.92).abs() < 1e-9 && (y - 5.89).abs() < 1e-9, "{x} {y}");
    // Without the approach the hand's cost alone pulls: no pursuit.
    assert_eq!(Task { approach: false, ..task.clone() }.pelvis_goal(&frame, 0.0), None);
    // With a waypoint 1 m from that point, the pelvis is led to within 0.4 m of the waypoint,
    // on the line toward it.
    let task = Task { waypoint: Some([3.92, 4.89]), ..task };
    let [x, y] = task.pelvis_goal(&frame, 0.0).unwrap();
    assert!((x - 3.92).abs() < 1e-9 && (y - 5.29).abs() < 1e-9, "{x} {y}");
    // Without the approach the waypoint itself.
    assert_eq!(Task { approach: false, ..task }.pelvis_goal(&frame, 0.0), Some([3.92, 4.89]));
}

#[test]
fn a_plans_intent_is_its_own_frame_velocity_and_its_turn_rate() {
    // A plan turning at 0.9 rad/s while it walks 0.5 m/s forward and 0.2 m/s to the right in
    // its own heading: in the frame it was sampled in, each state's velocity is turned by its
    // heading, and the intent turns it back.
    let layout = Layout { horizon: 8 };
    let mut tau = vec![0.0f32; layout.len()];
    for k in 1..=layout.horizon {
        let yaw = 0.9 * k as f32 / 30.0;
        let (s, c) = yaw.sin_cos();
        let v = layout.root_vel(k);
        tau[v] = c * 0.5 + s * 0.2;
        tau[v + 1] = s * 0.5 - c * 0.2;
        tau[layout.root_rot(k) + 2] = yaw;
    }
    let [forward, left, rate] = layout.intent(&tau);
    assert!(
        (forward - 0.5).abs() < 1e-5 && (left + 0.2).abs() < 1e-5 && (rate - 0.9).abs() < 1e-4,
        "{forward} {left} {rate}"
    );
}

#[test]
fn a_planned_body_is_read_into_the_current_frame() {
    // State 3 stands 1 m ahead and 0.5 m to the left of the current step, turned a quarter to
    // the left, its pelvis 0.8 m high and its hand 0.2 m ahead of it and 0.3 m up in its own
    // frame: in the current frame the hand is 0.2 m further left, 1.1 m high.
    let layout = Layout { horizon: 4 };
    let mut tau = vec![0.0f32; layout.len()];
    let (p, b) = (layout.root_pos(3), layout.body_pos(3, body::R_HAND));
    tau[p..p + 3].copy_from_slice(&[1.0, 0.5, 0.8]);
    tau[layout.root_rot(3) + 2] = std::f32::consts::FRAC_PI_2;
    tau[b..b + 3].copy_from_slice(&[0.2, 0.0, 0.3]);
    let (hand, rotated) = layout.body_in_frame(&tau, 3, body::R_HAND);
    let near = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
    assert!(near(&hand, &[1.0, 0.7, 1.1]) && near(&rotated, &[0.0, 0.2]), "{hand:?} {rotated:?}");
}

/// A model with command labels is told what guidance asks of the pelvis: the joystick's
/// command as ramped and held, or a waypoint's pursuit; a model with task labels whether the
/// task reaches; a model without labels nothing.
#[test]
fn a_labelled_model_is_told_what_guidance_asks_of_the_pelvis() {
    use flowmimic_model::{Label, ModelConfig, TaskLabel};
    let frame = CharFrame::new(DVec3::new(1.0, 2.0, 0.9), 0.5);
    let seg = JoystickSegment { seconds: 3.0, vx: 1.4, vy: -0.3, yaw_rate: 0.6 };
    let joystick = Task { joystick: vec![seg], ..Task::walk() };
    let steer = Steer { heading_lag: 0.1, velocity: Some([0.5, -0.3]) };
    let asked = joystick.pelvis_command(0.0, &frame, steer).unwrap().unwrap();
    assert_eq!(asked, [0.5, -0.3, 0.6 + 0.1 / HeadingHold::CATCH_UP]);
    let waypoint = Task { waypoint: Some([4.0, 5.0]), ..Task::walk() };
    let to = Pursuit::world([4.0, 5.0], &frame).unwrap();
    let pursued = waypoint.pelvis_command(0.0, &frame, Steer::default()).unwrap();
    assert_eq!(pursued, Some([to.speed, to.lateral, to.yaw_rate]));
    assert_eq!(Task::walk().pelvis_command(0.0, &frame, Steer::default()).unwrap(), None);

    let commands = ModelConfig { command_labels: true, ..ModelConfig::default() };
    let told = |task: &Task, model: &ModelConfig, steer| task.label(model, 0.0, &frame, steer).unwrap();
    assert_eq!(told(&joystick, &commands, steer), Some(Label::Command(asked.map(|v| v as f32))));
    assert_eq!(told(&Task::walk(), &commands, Steer::default()), None, "nothing asked, nothing said");
    let tasks = ModelConfig { task_labels: true, ..ModelConfig::default() };
    let reach = Task { reach: Some((Hand::Right, [1.0, 0.0, 1.2])), ..Task::walk() };
    assert_eq!(told(&reach, &tasks, Steer::default()), Some(Label::Task(TaskLabel::Reach)));
    assert_eq!(told(&joystick, &tasks, steer), Some(Label::Task(TaskLabel::Walk)));
    assert_eq!(told(&joystick, &ModelConfig::default(), steer), None);
}
