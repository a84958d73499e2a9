//! Obstacle avoidance: the plans' cost (gradient against finite differences, what it
//! measures) and the waypoint's detour around obstacles.

use flowmimic_control::obstacles::{Avoid, BODY, LOOKAHEAD, SIGHT, detour, in_frame, plan_way};
use flowmimic_control::*;
use flowmimic_geom::{CharFrame, DVec3};
use flowmimic_sim::{CONTROL_HZ, Footprint, Obstacle};

/// A plan whose pelvis walks along +x at 1.2 m/s.
fn walking(layout: Layout) -> Vec<f32> {
    let mut tau: Vec<f32> = (0..layout.len()).map(|i| 0.2 * ((i as f32) * 0.37).sin()).collect();
    for k in 1..=layout.horizon {
        let p = layout.root_pos(k);
        tau[p..p + 3].copy_from_slice(&[1.2 * k as f32 / CONTROL_HZ as f32, 0.02 * k as f32, 0.9]);
    }
    tau
}

#[test]
fn avoid_gradient_matches_finite_differences() {
    let layout = Layout { horizon: 8 };
    let tau = walking(layout);
    let wall =
        Obstacle { footprint: Footprint::Box { half: [0.1, 0.3], yaw: 0.4 }, ..Obstacle::cylinder([0.5, -0.5], 0.1) };
    let avoid = Avoid::new(layout, vec![Obstacle::cylinder([0.3, 0.35], 0.1).moving([0.0, -0.5]), wall]).unwrap();
    let mut grad = vec![0.0; tau.len()];
    avoid.add_grad(&tau, &mut grad);
    assert!(avoid.cost(&tau) > 0.0);
    let eps = 1e-3;
    // Hands beside the pelvis, so that their own terms (through offset and heading) act too.
    let mut tau = tau;
    for k in 1..=layout.horizon {
        let h = layout.body_pos(k, flowmimic_sim::skeleton::body::L_HAND);
        tau[h..h + 2].copy_from_slice(&[0.1, 0.3]);
    }
    let mut grad = vec![0.0; tau.len()];
    avoid.add_grad(&tau, &mut grad);
    for i in (0..tau.len()).filter(|&i| grad[i] != 0.0 || i % 7 == 0) {
        let (mut a, mut b) = (tau.clone(), tau.clone());
        (a[i], b[i]) = (a[i] + eps, b[i] - eps);
        let fd = (f64::from(avoid.cost(&a)) - f64::from(avoid.cost(&b))) / (2.0 * f64::from(eps));
        assert!((fd - f64::from(grad[i])).abs() < 2e-2 * (1.0 + fd.abs()), "d/dtau[{i}]: fd {fd} vs {}", grad[i]);
    }
    assert!(grad.iter().filter(|g| **g != 0.0).count() >= 4, "the gradient acts on several steps");
    let h = layout.body_pos(3, flowmimic_sim::skeleton::body::L_HAND);
    assert!(grad[h] != 0.0 && grad[layout.root_rot(3) + 2] != 0.0, "the hand's offset and the heading are pulled");
}

#[test]
fn avoid_sees_where_obstacles_will_be() {
    let layout = Layout { horizon: 16 };
    let tau = walking(layout);
    // 2 m to the side, nothing to avoid; the same obstacle crossing at 3 m/s reaches the path.
    let aside = Obstacle::cylinder([0.3, 2.0], 0.2);
    assert_eq!(Avoid::new(layout, vec![aside]).unwrap().cost(&tau), 0.0);
    let crossing = Avoid::new(layout, vec![aside.moving([0.0, -3.0])]).unwrap();
    assert!(crossing.cost(&tau) > 0.0 && crossing.error(&tau) > 0.0);
    // Pushing the plan along the gradient moves it away: the cost falls.
    let mut grad = vec![0.0; tau.len()];
    crossing.add_grad(&tau, &mut grad);
    let stepped: Vec<f32> = tau.iter().zip(&grad).map(|(x, g)| x - 0.05 * g).collect();
    assert!(crossing.cost(&stepped) < crossing.cost(&tau));
    assert!(Avoid::new(layout, vec![Obstacle::cylinder([1.0, 0.0], 0.0)]).is_err(), "a zero radius is refused");
}

#[test]
fn obstacles_seen_from_the_character_frame() {
    // A walker at (1, 1) facing +y: a box at (2, 1) turned 0.3 rad lies on its right, turned -1.27.
    let frame = CharFrame::new(DVec3::new(1.0, 1.0, 0.9), std::f64::consts::FRAC_PI_2);
    let b =
        Obstacle { footprint: Footprint::Box { half: [0.2, 0.4], yaw: 0.3 }, ..Obstacle::cylinder([2.0, 1.0], 0.1) };
    let seen = in_frame(&[b.moving([1.0, 0.0])], &frame, 0.0)[0];
    assert!((seen.at[0]).abs() < 1e-12 && (seen.at[1] + 1.0).abs() < 1e-12, "{:?}", seen.at);
    assert!((seen.velocity[0]).abs() < 1e-12 && (seen.velocity[1] + 1.0).abs() < 1e-12);
    let Footprint::Box { yaw, .. } = seen.footprint else { panic!("a box stays a box") };
    assert!((yaw - (0.3 - std::f64::consts::FRAC_PI_2)).abs() < 1e-12);
    // Later, the moving box has moved on: at t = 2 s it is 2 m further along world +x.
    assert!((in_frame(&[b.moving([1.0, 0.0])], &frame, 2.0)[0].at[1] + 3.0).abs() < 1e-12);
}

/// The nearest any point of the straight walk from `a` to `b` comes to an edge.
fn clearance(a: [f64; 2], b: [f64; 2], obstacles: &[Obstacle]) -> f64 {
    (0..=100)
        .map(|i| {
            let s = f64::from(i) / 100.0;
            let p = [a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s];
            obstacles.iter().map(|o| o.distance(p, 0.0).0).fold(f64::INFINITY, f64::min)
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn detours_go_around_what_blocks_the_way_and_only_that() {
    let goal = [8.0, 0.0];
    assert_eq!(detour(goal, &[]), goal, "nothing in the way");
    assert_eq!(detour(goal, &[Obstacle::cylinder([4.0, 2.0], 0.4)]), goal, "an obstacle well aside");
    assert_eq!(detour([3.0, 0.0], &[Obstacle::cylinder([4.5, 0.0], 0.4)]), [3.0, 0.0], "one beyond the goal");
    // Straight ahead but a little to the left: around it on the right, in sight.
    let post = [Obstacle::cylinder([1.5, 0.1], 0.4)];
    let p = detour(goal, &post);
    assert!(p[1] < 0.0 && p[0].hypot(p[1]) <= LOOKAHEAD + 0.2, "detour to {p:?}");
    assert!(clearance([0.0, 0.0], p, &post) >= SIGHT - 1e-6);
    // A crossing post meets a walker going straight: the detour avoids where it will be.
    let crossing = [Obstacle::cylinder([2.0, -2.5], 0.3).moving([0.0, 1.0])];
    assert_ne!(detour(goal, &crossing), goal);
    assert_eq!(detour(goal, &[Obstacle::cylinder([2.0, -2.5], 0.3)]), goal, "standing there it blocks nothing");
}

#[test]
fn planned_ways_keep_the_body_clear_and_prefer_wide_gaps() {
    // A wall across the way with a narrow gap (0.4 m, under the body's width) and a wide one
    // (1.6 m): the way goes through the wide one, and nowhere nearer an edge than the body.
    let wall = [
        Obstacle { footprint: Footprint::Box { half: [0.2, 1.5], yaw: 0.0 }, ..Obstacle::cylinder([3.0, -1.7], 0.1) },
        Obstacle { footprint: Footprint::Box { half: [0.2, 0.5], yaw: 0.0 }, ..Obstacle::cylinder([3.0, 0.7], 0.1) },
        Obstacle { footprint: Footprint::Box { half: [0.2, 3.0], yaw: 0.0 }, ..Obstacle::cylinder([3.0, 5.8], 0.1) },
    ];
    let way = plan_way([0.0, 0.0], [6.0, 0.0], &wall).expect("a way through the wide gap");
    assert_eq!((way[0], *way.last().unwrap()), ([0.0, 0.0], [6.0, 0.0]));
    for pair in way.windows(2) {
        assert!(clearance(pair[0], pair[1], &wall) >= BODY - 0.1, "{pair:?} passes too near");
    }
    let crossing = way.iter().find(|p| (p[0] - 3.0).abs() < 0.1).expect("crosses the wall");
    assert!((1.2..=2.8).contains(&crossing[1]), "through the wide gap at y 1.2-2.8, not the narrow one: {crossing:?}");
    // Walled in: no way.
    let ring: Vec<Obstacle> = (0..24)
        .map(|i| {
            let a = f64::from(i) * std::f64::consts::TAU / 24.0;
            Obstacle::cylinder([6.0 + 1.5 * a.cos(), 1.5 * a.sin()], 0.3)
        })
        .collect();
    assert!(plan_way([0.0, 0.0], [6.0, 0.0], &ring).is_none());
}

#[test]
fn a_task_with_obstacles_avoids_them_unless_blind() {
    let layout = Layout { horizon: 16 };
    let frame = CharFrame::new(DVec3::new(0.0, 0.0, 0.9), 0.0);
    let post = Obstacle::cylinder([1.5, 0.1], 0.4);
    let task = Task { waypoint: Some([8.0, 0.0]), obstacles: vec![post], ..Task::walk() };
    assert_eq!(
        task.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap().terms.len(),
        3,
        "pursuit, heading, avoid"
    );
    assert!(task.pelvis_goal(&frame, 0.0).unwrap()[1] < 0.0, "the pursuit detours");
    let blind = Task { blind: true, ..task.clone() };
    assert_eq!(blind.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap().terms.len(), 2);
    assert_eq!(blind.pelvis_goal(&frame, 0.0), Some([8.0, 0.0]));
    let bad = Task { obstacles: vec![Obstacle::cylinder([1.0, f64::NAN], 0.3)], ..task };
    assert!(matches!(bad.validate(), Err(ControlError::Obstacle(_))));
}

#[test]
fn among_obstacles_the_hand_waits_until_its_target_is_near() {
    let layout = Layout { horizon: 16 };
    let frame = CharFrame::new(DVec3::new(0.0, 0.0, 0.9), 0.0);
    let reach = Some((Hand::Right, [4.0, -0.4, 0.85]));
    let task = Task { reach, approach: true, obstacles: vec![Obstacle::cylinder([2.8, 0.0], 0.3)], ..Task::walk() };
    let far = task.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap();
    let near =
        task.cost(layout, 0.0, &CharFrame::new(DVec3::new(3.0, 0.0, 0.9), 0.0), Steer::default()).unwrap().unwrap();
    let open =
        Task { obstacles: Vec::new(), ..task.clone() }.cost(layout, 0.0, &frame, Steer::default()).unwrap().unwrap();
    // Pursuit and heading, and the plan's obstacle cost; the hand's cost once near, or always
    // without obstacles.
    assert_eq!((far.terms.len(), near.terms.len(), open.terms.len()), (3, 4, 3));
}

#[test]
fn a_task_moves_rigidly_with_the_frame_it_is_given_in() {
    let from = CharFrame::new(DVec3::new(1.0, 0.0, 0.0), 0.0);
    let to = CharFrame::new(DVec3::new(0.0, 2.0, 0.0), std::f64::consts::FRAC_PI_2);
    let wall =
        Obstacle { footprint: Footprint::Box { half: [0.2, 1.0], yaw: 0.1 }, ..Obstacle::cylinder([3.0, 0.0], 0.1) };
    let task = Task {
        reach: Some((Hand::Left, [2.0, 1.0, 1.2])),
        waypoint: Some([5.0, 0.0]),
        obstacles: vec![wall.moving([0.0, 1.0])],
        ..Task::joystick_eval()
    };
    let moved = task.moved(&from, &to);
    let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12;
    // 4 m ahead of `from` is 4 m ahead of `to`, which faces +y.
    assert!(close(moved.waypoint.unwrap(), [0.0, 6.0]), "{:?}", moved.waypoint);
    let (hand, t) = moved.reach.unwrap();
    assert!(hand == Hand::Left && close([t[0], t[1]], [-1.0, 3.0]) && t[2] == 1.2, "{t:?}");
    let o = moved.obstacles[0];
    assert!(close(o.at, [0.0, 4.0]) && close(o.velocity, [-1.0, 0.0]), "{o:?}");
    assert!(
        matches!(o.footprint, Footprint::Box { yaw, .. } if (yaw - (0.1 + std::f64::consts::FRAC_PI_2)).abs() < 1e-12)
    );
    assert_eq!(moved.joystick, task.joystick, "the joystick is the walker's own");
    assert_eq!(task.moved(&from, &from), task);
}
