//! Tests of the simulated humanoid that can fail: model facts, frames, velocities, PD, falls,
//! kicks and bad input.

use flowmimic_geom::{DQuat, DVec3, from_rotvec, quat_from_wxyz, quat_to_wxyz, yaw_quat};
use flowmimic_sim::state::{ROTATION_BODIES, offset, state_feature_names};
use flowmimic_sim::*;
use std::sync::Arc;

fn humanoid() -> Arc<Humanoid> {
    Humanoid::new(SimConfig::default()).expect("model compiles")
}

/// Deterministic pseudo-random actions (no RNG dependency in the assertion path).
fn action(step: usize, scale: f32) -> Vec<f32> {
    (0..NUM_DOFS).map(|i| scale * (((step * 31 + i * 17) as f32) * 0.37).sin()).collect()
}

/// A humanoid mid-motion: stepped with varied actions, moving and tilted.
fn moving_env(h: &Arc<Humanoid>) -> Env {
    let mut env = h.env();
    let mut q = h.standing_qpos();
    q[0] = 0.4;
    q[1] = -1.2;
    q[2] += 0.3; // start in the air so it is moving when we look
    let yaw = yaw_quat(0.8) * DQuat::from_rotation_y(0.1);
    q[3..7].copy_from_slice(&quat_to_wxyz(yaw));
    let mut v = vec![0.0; h.nv()];
    v[0] = 0.7;
    v[1] = -0.3;
    v[5] = 0.6;
    env.reset(&q, &v).unwrap();
    for s in 0..4 {
        env.step(&action(s, 0.3)).unwrap();
    }
    env
}

#[test]
fn model_dimensions_body_order_and_size() {
    let h = humanoid();
    check_body_order(&h).unwrap();
    assert_eq!(h.mujoco_body_names()[1..], BODY_NAMES.map(String::from));
    assert_eq!((h.nq(), h.nv()), (76, 75));
    assert_eq!(NUM_DOFS, 69);
    assert_eq!(h.env().state().len(), STATE_DIM);
    let names = state_feature_names();
    assert_eq!(names.len(), 165);
    assert_eq!(names.iter().collect::<std::collections::HashSet<_>>().len(), 165, "feature names are unique");
    assert!((60.0..=75.0).contains(&h.mass()), "mass {}", h.mass());
    assert!((1.6..=1.8).contains(&h.height()), "height {}", h.height());
    // Depth-first order: every parent comes before its children.
    for (b, p) in skeleton::BODY_PARENTS.iter().enumerate() {
        if let Some(p) = p {
            assert!(*p < b);
        }
    }
}

#[test]
fn model_loads_without_compiler_warnings_and_runs_without_runtime_warnings() {
    let h = humanoid();
    let dir = std::env::temp_dir().join(format!("flowmimic-sim-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("humanoid.xml");
    std::fs::write(&path, h.xml()).unwrap();
    let c_path = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    let mut err = [0 as std::os::raw::c_char; 1000];
    // SAFETY: valid C strings and buffer; the model is freed right after.
    unsafe {
        let m = mujoco_rs::mujoco_c::mj_loadXML(c_path.as_ptr(), std::ptr::null(), err.as_mut_ptr(), 1000);
        assert!(!m.is_null());
        mujoco_rs::mujoco_c::mj_deleteModel(m);
    }
    let msg = unsafe { std::ffi::CStr::from_ptr(err.as_ptr()) }.to_string_lossy().into_owned();
    assert!(msg.is_empty(), "MuJoCo compiler said: {msg}");
    std::fs::remove_dir_all(&dir).ok();
    // Two seconds of motion and a fall raise no physics warning (Env::step would error).
    let mut env = h.env();
    env.kick([2.0, 0.0]).unwrap();
    for s in 0..60 {
        env.step(&action(s, 0.5)).unwrap();
    }
}

/// The state depends only on the pose relative to the character frame: moving and turning
/// the whole world state must leave all 165 features unchanged.
#[test]
fn state_is_invariant_to_world_translation_and_yaw() {
    let h = humanoid();
    let env = moving_env(&h);
    let (q, v) = (env.qpos().to_vec(), env.qvel().to_vec());
    let s0 = env.state();
    assert!(s0[offset::ROOT_VEL..offset::ROOT_VEL + 3].iter().any(|x| x.abs() > 0.1), "test needs motion");
    for (shift, yaw) in [(DVec3::new(3.0, -2.0, 0.0), 1.0), (DVec3::new(-10.0, 5.0, 0.0), -2.7)] {
        let turn = yaw_quat(yaw);
        let mut q2 = q.clone();
        let p = turn * DVec3::new(q[0], q[1], q[2]) + shift;
        q2[..3].copy_from_slice(&p.to_array());
        q2[3..7].copy_from_slice(&quat_to_wxyz(turn * quat_from_wxyz([q[3], q[4], q[5], q[6]])));
        let mut v2 = v.clone();
        // Free-joint linear velocity is in the world frame; angular velocity is local.
        let lin = turn * DVec3::new(v[0], v[1], v[2]);
        v2[..3].copy_from_slice(&lin.to_array());
        let mut other = h.env();
        other.reset(&q2, &v2).unwrap();
        let s1 = other.state();
        for i in 0..STATE_DIM {
            assert!(
                (s0[i] - s1[i]).abs() < 1e-5,
                "feature {} ({}) {} vs {}",
                i,
                state_feature_names()[i],
                s0[i],
                s1[i]
            );
        }
        // And the world-frame quantities really did change.
        let k = other.bodies();
        assert!((k.pos[0] - env.bodies().pos[0]).length() > 1.0);
    }
}

/// Body linear and angular velocities must be the time derivatives of positions and
/// orientations: integrate the state a tiny step along qvel and difference.
#[test]
fn body_velocities_match_finite_differences() {
    let h = humanoid();
    let env = moving_env(&h);
    let (q, v) = (env.qpos().to_vec(), env.qvel().to_vec());
    let eps = 1e-6;
    let mut q2 = q.clone();
    for i in 0..3 {
        q2[i] += eps * v[i];
    }
    let r = quat_from_wxyz([q[3], q[4], q[5], q[6]]);
    // The free joint's angular velocity is in the body frame: right-multiply.
    let r2 = r * from_rotvec(eps * DVec3::new(v[3], v[4], v[5]));
    q2[3..7].copy_from_slice(&quat_to_wxyz(r2));
    for i in 7..q.len() {
        q2[i] += eps * v[i - 1];
    }
    let mut other = h.env();
    other.reset(&q2, &v).unwrap();
    let (a, b) = (env.bodies(), other.bodies());
    let mut max_speed: f64 = 0.0;
    for k in 0..NUM_BODIES {
        let fd = (b.pos[k] - a.pos[k]) / eps;
        max_speed = max_speed.max(a.lin_vel[k].length());
        assert!((fd - a.lin_vel[k]).length() < 1e-4, "{}: fd {fd} vs {}", BODY_NAMES[k], a.lin_vel[k]);
        let dq = b.rot[k] * a.rot[k].conjugate();
        let w_fd = flowmimic_geom::rotvec(dq) / eps;
        assert!((w_fd - a.ang_vel[k]).length() < 1e-4, "{}: w fd {w_fd} vs {}", BODY_NAMES[k], a.ang_vel[k]);
    }
    assert!(max_speed > 0.5, "test needs motion, max speed {max_speed}");
    // The root-velocity feature is the root position's derivative, in the character frame.
    let s = env.state();
    let world_v = (b.pos[0] - a.pos[0]) / eps;
    let local = a.frame().vector(world_v);
    for i in 0..3 {
        assert!((f64::from(s[offset::ROOT_VEL + i]) - local[i]).abs() < 1e-3);
    }
}

#[test]
fn state_blocks_hold_what_the_layout_says() {
    let h = humanoid();
    let env = moving_env(&h);
    let (s, k) = (env.state(), env.bodies());
    let own = k.frame();
    // Own frame: root at the origin horizontally, height absolute, zero yaw.
    assert!(s[0].abs() < 1e-6 && s[1].abs() < 1e-6);
    assert!((f64::from(s[2]) - k.pos[0].z).abs() < 1e-6);
    let root_rot = from_rotvec(DVec3::new(s[6].into(), s[7].into(), s[8].into()));
    assert!(flowmimic_geom::heading(root_rot).abs() < 1e-6);
    let head = body_block(&s, offset::BODY_POS, skeleton::body::HEAD);
    assert!((head - own.point(k.pos[skeleton::body::HEAD])).length() < 1e-5);
    let hand_rot = from_rotvec(body_block(&s, offset::END_ROT, 0));
    assert!(hand_rot.dot(own.rotation(k.rot[ROTATION_BODIES[0]])).abs() > 1.0 - 1e-6);
    // In another step's frame, the root position carries the displacement.
    // A frame 1 m behind the root along its facing direction.
    let other = flowmimic_geom::CharFrame::new(k.pos[0] - own.vector_to_world(DVec3::X), own.yaw);
    let moved = k.state_in(&other);
    assert!((f64::from(moved[0]) - 1.0).abs() < 1e-5 && moved[1].abs() < 1e-5);
    assert_eq!(moved[offset::BODY_POS..], s[offset::BODY_POS..], "local part does not depend on the frame");
}

fn body_block(s: &[f32], at: usize, b: usize) -> DVec3 {
    DVec3::new(s[at + 3 * b].into(), s[at + 3 * b + 1].into(), s[at + 3 * b + 2].into())
}

#[test]
fn welded_root_humanoid_holds_a_target_pose() {
    let h = Humanoid::with_fixed_root(SimConfig::default(), 1.5).unwrap();
    assert_eq!((h.nq(), h.nv()), (69, 69));
    let map = h.actions();
    // A pose well inside the joint limits, away from the nominal one.
    let target: Vec<f64> = (0..NUM_DOFS)
        .map(|i| {
            let (lo, hi) = (map.lower[i], map.upper[i]);
            let mid = 0.5 * (lo + hi);
            mid + 0.4 * (hi - lo) * 0.5 * ((i as f64) * 0.9).sin()
        })
        .collect();
    let a = map.action_for(&target);
    let mut env = h.env();
    for _ in 0..60 {
        env.step(&a).unwrap();
    }
    let errors: Vec<f64> = env.hinge_angles().iter().zip(&target).map(|(q, t)| (q - t).abs()).collect();
    let max = errors.iter().cloned().fold(0.0, f64::max);
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    // Gravity sag against kp = I wn^2 stays under 0.1 rad everywhere, 0.02 rad on average.
    assert!(max < 0.1, "max hinge error {max} rad");
    assert!(mean < 0.02, "mean hinge error {mean} rad");
}

#[test]
fn free_humanoid_stands_like_a_statue_but_falls_when_pushed() {
    let h = humanoid();
    let zero = vec![0f32; NUM_DOFS];
    // The nominal pose is statically stable on flat feet: zero action alone does not fall.
    let mut env = h.env();
    for _ in 0..90 {
        env.step(&zero).unwrap();
    }
    assert!(!env.fallen() && env.head_height() > 1.4, "head at {}", env.head_height());
    // Zero action has no balance: a push topples it and the fall is detected.
    let mut env = h.env();
    env.kick([1.5, 0.0]).unwrap();
    let mut fell_at = None;
    for s in 0..150 {
        env.step(&zero).unwrap();
        if env.fallen() {
            fell_at = Some(s);
            break;
        }
    }
    assert!(fell_at.is_some(), "pushed statue did not fall; head at {}", env.head_height());
    assert!(env.head_height() < FALL_HEAD_HEIGHT);
}

#[test]
fn kick_changes_root_velocity_by_the_requested_amount() {
    let h = humanoid();
    let mut env = moving_env(&h);
    let before = env.bodies().lin_vel[0];
    env.kick([0.3, -0.4]).unwrap();
    let after = env.bodies().lin_vel[0];
    let dv = after - before;
    assert!((dv - DVec3::new(0.3, -0.4, 0.0)).length() < 1e-9, "dv {dv}");
    assert!(env.kick([f64::NAN, 0.0]).is_err());
    let welded = Humanoid::with_fixed_root(SimConfig::default(), 1.5).unwrap();
    assert!(welded.env().kick([0.1, 0.0]).is_err());
}

#[test]
fn bad_actions_and_states_are_errors_and_out_of_range_actions_are_clipped() {
    let h = humanoid();
    let mut env = h.env();
    let mut a = vec![0f32; NUM_DOFS];
    a[3] = f32::NAN;
    let err = env.step(&a).unwrap_err().to_string();
    assert!(err.contains("L_Knee_x") && err.contains("NaN"), "{err}");
    assert!(env.step(&[0.0; 10]).unwrap_err().to_string().contains("10 entries"));
    assert_eq!(env.steps(), 0, "a rejected action simulates nothing");
    let (q, v) = (h.standing_qpos(), vec![0.0; h.nv()]);
    assert!(env.reset(&q[..70], &v).unwrap_err().to_string().contains("qpos of length 70"));
    let mut bad = q.clone();
    bad[10] = f64::INFINITY;
    assert!(env.reset(&bad, &v).unwrap_err().to_string().contains("qpos at index 10"));
    // Clipping: 5.0 acts like 1.0, -7 like -1.
    let big: Vec<f32> = (0..NUM_DOFS).map(|i| if i % 2 == 0 { 5.0 } else { -7.0 }).collect();
    let unit: Vec<f32> = big.iter().map(|x| x.clamp(-1.0, 1.0)).collect();
    let (mut e1, mut e2) = (h.env(), h.env());
    e1.step(&big).unwrap();
    e2.step(&unit).unwrap();
    assert_eq!(e1.qpos(), e2.qpos());
}

#[test]
fn exploding_state_is_reported_not_silently_reset() {
    let h = humanoid();
    let mut env = h.env();
    let mut v = vec![0.0; h.nv()];
    v[10] = 1e12;
    env.reset(&h.standing_qpos(), &v).unwrap();
    let err = env.step(&vec![0.0; NUM_DOFS]).unwrap_err();
    assert!(matches!(err, SimError::Diverged { .. }), "{err}");
}

#[test]
fn parallel_envs_match_sequential_ones() {
    let h = humanoid();
    let n = 6;
    let mut batch = VecEnv::new(&h, n);
    let mut single: Vec<Env> = (0..n).map(|_| h.env()).collect();
    for s in 0..10 {
        let actions: Vec<f32> = (0..n).flat_map(|e| action(s + 100 * e, 0.4)).collect();
        batch.step(&actions).unwrap();
        for (e, env) in single.iter_mut().enumerate() {
            env.step(&actions[e * NUM_DOFS..(e + 1) * NUM_DOFS]).unwrap();
        }
    }
    for (a, b) in batch.envs().iter().zip(&single) {
        assert_eq!(a.qpos(), b.qpos());
    }
    assert_ne!(batch.envs()[0].qpos(), batch.envs()[1].qpos(), "envs are independent");
}

#[test]
fn pd_gains_follow_the_paper_formula() {
    use flowmimic_sim::mjcf::{DAMPING_RATIO, NATURAL_FREQUENCY, pd_gains};
    use flowmimic_sim::skeleton::JointGroup;
    let (kp, kd) = pd_gains(JointGroup::Leg);
    assert!((kp - 0.2 * NATURAL_FREQUENCY.powi(2)).abs() < 1e-9);
    assert!((kd - 2.0 * 0.2 * DAMPING_RATIO * NATURAL_FREQUENCY).abs() < 1e-9);
    assert!((700.0..900.0).contains(&kp), "leg kp {kp} near PHC's 800");
    // The XML carries the same numbers MuJoCo will use.
    assert!(humanoid().xml().contains(&format!("joint=\"L_Knee_y\" kp=\"{kp:.4}\" kv=\"{kd:.4}\"")));
}

#[test]
fn soles_touch_the_ground_when_standing_and_lift_with_the_body() {
    let h = humanoid();
    let mut env = h.env();
    let soles = env.sole_heights();
    // The nominal pose is built with the soles exactly at z = 0.
    assert!(soles.iter().all(|z| z.abs() < 1e-3), "{soles:?}");
    let mut q = h.standing_qpos();
    q[2] += 0.25;
    env.reset(&q, &vec![0.0; h.nv()]).unwrap();
    assert!(env.sole_heights().iter().all(|z| (z - 0.25).abs() < 1e-3));
    // Tip the body 90 degrees forward: the feet's lowest points are now their heels' backs.
    q[3..7].copy_from_slice(&quat_to_wxyz(DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2)));
    env.reset(&q, &vec![0.0; h.nv()]).unwrap();
    let [l, r] = env.sole_heights();
    assert!((l - r).abs() < 1e-9 && l > 0.9, "{l} {r}");
}

fn largest_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn the_mirror_image_of_a_motion_is_the_motion_of_the_mirrored_actions() {
    let h = humanoid();
    let (states, actions) = (Mirror::state(), Mirror::action());
    let mut env = moving_env(&h);
    let (q, v) = (Mirror::qpos(env.qpos()), Mirror::qvel(env.qvel()));
    let mut image = h.env();
    image.reset(&q, &v).unwrap();
    // The mirrored pose's state is the state's mirror image; mirroring twice is the identity.
    let state = env.state();
    assert!(largest_difference(&states.apply(&state), &image.state()) < 1e-5);
    assert_eq!(states.apply(&states.apply(&state)), state);
    assert_ne!(states.apply(&state), state, "a moving, tilted pose is not its own mirror image");
    // Two seconds driven by mirrored actions, falling and landing included, stay mirror images.
    for s in 0..60 {
        env.step(&action(s, 0.5)).unwrap();
        image.step(&actions.apply(&action(s, 0.5))).unwrap();
    }
    let difference = largest_difference(&states.apply(&env.state()), &image.state());
    assert!(difference < 1e-3, "mirror images {difference} apart after 2 s");
    assert!(largest_difference(&env.state(), &image.state()) > 0.1, "the two motions differ");
}

#[test]
fn obstacles_are_solid_move_and_leave_the_humanoid_as_it_was() {
    let h = humanoid();
    let zero = vec![0f32; NUM_DOFS];
    // Far away, a standing and a moving obstacle change nothing of the humanoid's own motion.
    let far = [Obstacle::cylinder([5.0, 5.0], 0.3), Obstacle::cylinder([-5.0, 5.0], 0.3).moving([0.0, -1.0])];
    let world = h.with_obstacles(&far).unwrap();
    check_body_order(&world).unwrap();
    assert!((world.mass() - h.mass()).abs() < 1e-9, "obstacles weigh nothing in the humanoid's mass");
    let (mut plain, mut with) = (moving_env(&h), h.env());
    with.enter(Arc::clone(&world)).unwrap();
    // Both from the same state, time and controls.
    let (q, v) = (plain.qpos().to_vec(), plain.qvel().to_vec());
    with.reset(&q, &v).unwrap();
    plain.reset(&q, &v).unwrap();
    for s in 0..30 {
        plain.step(&action(s, 0.3)).unwrap();
        with.step(&action(s, 0.3)).unwrap();
        assert!(!with.touching_obstacle());
    }
    assert_eq!(plain.qpos(), with.qpos(), "a far obstacle changed the humanoid's motion");
    assert!(plain.self_contacts() == with.self_contacts());

    // A cylinder rolling in from 2 m at 1 m/s reaches the standing humanoid, touches it (a
    // MuJoCo contact) and pushes it over.
    let wall =
        Obstacle { footprint: Footprint::Box { half: [0.2, 1.0], yaw: 0.0 }, ..Obstacle::cylinder([2.0, 0.0], 0.3) };
    let mut env = h.with_obstacles(&[wall.moving([-1.0, 0.0])]).unwrap().env();
    let mut first = None;
    for s in 0..90 {
        env.step(&zero).unwrap();
        if env.touching_obstacle() && first.is_none() {
            first = Some(s);
        }
    }
    let first = first.expect("the moving wall never touched the humanoid");
    // The wall's face starts 1.8 m out; the humanoid's front is 0.1-0.3 m from the pelvis.
    assert!((40..=55).contains(&first), "first contact at step {first}");
    assert!(env.obstacle_steps() > 5 && env.bodies().pos[0].x < -0.5, "not pushed: {}", env.bodies().pos[0].x);
    // Entering a world keeps state and time: the wall is still where its time puts it.
    let (q, t) = (env.qpos().to_vec(), env.time());
    env.enter(h.with_obstacles(&[wall.moving([-1.0, 0.0])]).unwrap()).unwrap();
    assert_eq!((env.qpos(), env.time()), (&q[..], t));
    assert!(h.with_obstacles(&[Obstacle::cylinder([0.0, 0.0], -1.0)]).is_err());
}
