//! Invariants of the walking generator, checked on many random walks: the upper body faces
//! where the pelvis faces, the legs never touch each other (the simulator's own collision
//! detection on the reference poses), planted feet do not slide, and the root follows the
//! command.

mod common;

use flowmimic_motion::generator::{self, Schedule};
use flowmimic_motion::{Clip, Coverage, GaitParams, Segment, WanderParams, generate, scheduled, wander};
use flowmimic_sim::{CONTROL_HZ, Humanoid, SimConfig};
use rand::{Rng, SeedableRng};
use std::sync::Arc;

/// Walks from the whole range: any speed forward and back, sideways, turn rate, heading and
/// step frequency the generator accepts, plus wandering walks, walks of transitions and a scheduled walk that
/// reverses from forward to backward and back, turning and sidestepping.
fn random_walks(h: &Arc<Humanoid>) -> Vec<(Clip, Schedule)> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let mut walks = Vec::new();
    while walks.len() < 24 {
        let p = GaitParams {
            speed: rng.random_range(-0.8..1.6),
            lateral: rng.random_range(-0.3..0.3),
            turn_rate: rng.random_range(-0.8..0.8),
            heading: rng.random_range(-3.1..3.1),
            step_frequency: rng.random_range(1.5..2.4),
            duration: 4.0,
            ..Default::default()
        };
        if p.validate().is_ok() {
            walks.push((generate(h, "random", &p).unwrap().0, p.schedule()));
        }
    }
    for seed in 1..=2 {
        let p = WanderParams { seed, duration: 30.0, ..Default::default() };
        walks.push((wander(h, "wander", &p).unwrap().0, p.schedule()));
        let p = WanderParams { seed, duration: 30.0, transitions: true, ..Default::default() };
        walks.push((wander(h, "transitions", &p).unwrap().0, p.schedule()));
    }
    let seg = |seconds, speed, lateral, turn_rate| Segment { seconds, speed, lateral, turn_rate };
    let segments =
        [seg(2.0, 1.0, 0.0, 0.0), seg(3.0, -0.6, 0.0, 0.3), seg(3.0, 1.2, 0.0, -0.5), seg(2.0, 0.1, 0.25, 0.0)];
    walks.push((scheduled(h, "reversals", &segments).unwrap().0, generator::scheduled_walk(&segments).unwrap()));
    walks
}

#[test]
fn generated_walks_keep_their_invariants() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let mut env = h.env();
    for (n, (clip, schedule)) in random_walks(&h).iter().enumerate() {
        let what = format!("walk {n} ({:?})", schedule.keys.first().unwrap().1);
        let velocities = clip.walking_velocities();
        let mut stance_speeds = Vec::new();
        for (t, k) in clip.bodies.iter().enumerate() {
            // The chest and head face within 25 degrees of the pelvis.
            let turn = common::upper_body_turn(k);
            assert!(turn < 25.0, "{what}: frame {t}: the upper body faces {turn:.0} deg from the pelvis");
            // The legs never touch each other.
            env.reset(&clip.qpos[t], &clip.qvel[t]).unwrap();
            if let Some((a, b)) = env.self_contacts().into_iter().find(|&pair| common::legs_touch(pair)) {
                let near: Vec<_> = schedule.keys.iter().filter(|k| (k.0 - t as f64 / 30.0).abs() < 3.0).collect();
                panic!(
                    "{what}: frame {t}: bodies {a} and {b} touch; command {:?} {near:?}",
                    schedule.at(t as f64 / 30.0)
                );
            }
            // Planted feet do not slide: the touching part of a foot on the ground is still.
            stance_speeds.extend(common::stance_speeds(&env, k));
        }
        let mean = stance_speeds.iter().sum::<f64>() / stance_speeds.len() as f64;
        assert!(mean < 0.05, "{what}: feet on the ground move at {mean:.3} m/s on average");
        // The root follows the command (both averaged over the same second).
        let half = (CONTROL_HZ / 2.0) as usize;
        for t in half..clip.len() - half {
            let mut command = [0.0; 3];
            for s in t - half..=t + half {
                let c = schedule.at(s as f64 / CONTROL_HZ);
                for (m, x) in command.iter_mut().zip([c.speed, c.lateral, c.turn_rate]) {
                    *m += x / (2 * half + 1) as f64;
                }
            }
            let v = velocities[t];
            let err = [(v[0] - command[0]).abs(), (v[1] - command[1]).abs(), (v[2] - command[2]).abs()];
            assert!(
                err[0] < 0.12 && err[1] < 0.12 && err[2] < 0.1,
                "{what}: frame {t}: walks {v:?} for the command {command:?}"
            );
        }
    }
}

#[test]
fn wandering_walks_cover_what_people_do_and_differ_by_seed() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let walk = |seed| wander(&h, "w", &WanderParams { seed, duration: 40.0, ..Default::default() }).unwrap().0;
    let (a, b) = (walk(1), walk(2));
    assert_eq!(a.len(), 1201);
    assert_ne!(a.qpos, b.qpos, "different seeds, different walks");
    assert_eq!(a.qpos, walk(1).qpos, "the same seed, the same walk");
    // Commands change every 1.5-4 s.
    let keys = WanderParams { seed: 1, duration: 40.0, ..Default::default() }.schedule().keys;
    for pair in keys.windows(2) {
        let hold = pair[1].0 - pair[0].0;
        assert!((1.5..=4.0).contains(&hold), "a command held {hold} s");
    }
    // Four walks together walk backward, turn and sidestep.
    let clips: Vec<Clip> = (1..=4).map(walk).collect();
    let cov = Coverage::of(clips.iter().flat_map(|c| c.walking_velocities()).collect());
    assert!(cov.backward > 0.1 && cov.turning > 0.15 && cov.sidestep > 0.1, "{cov:?}");
    assert!(cov.ranges[0].1 > 1.3 && cov.ranges[0].0 < -0.5, "forward speeds {:?}", cov.ranges[0]);
    for q in clips.iter().map(|c| c.quality(&h)) {
        assert!(q.penetration_max < 0.01 && q.airborne == 0.0, "{q:?}");
        assert!(q.body_speed_max < flowmimic_motion::clip::BODY_SPEED_JUMP, "a wandering walk jumps: {q:?}");
    }
    // A hand moved 0.3 m in one frame (a retargeting glitch) is a jump of 9 m/s.
    let mut glitch = clips[0].clone();
    glitch.bodies[40].pos[flowmimic_sim::skeleton::body::R_HAND].z += 0.3;
    assert!((glitch.body_speed_max() - 0.3 * 30.0).abs() < 1.0, "{}", glitch.body_speed_max());
}

#[test]
fn sidesteps_are_counted_to_each_side_apart_from_diagonal_walks() {
    // A generated sidestep to the right.
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let p = GaitParams { speed: 0.0, lateral: -0.3, duration: 4.0, ..Default::default() };
    let right = Coverage::of(generate(&h, "w", &p).unwrap().0.walking_velocities());
    assert!(right.aside[1] > 0.8 && right.aside[0] == 0.0, "a sidestep right: {:?}", right.aside);
    // A walk at 1 m/s facing 0.3 rad left of its path (as a turning pelvis does) moves 0.3 m/s
    // to its right: a sidestep by speed alone, but it walks more forward than sideways.
    let path: Vec<[f64; 3]> = (0..120).map(|t| [t as f64 / CONTROL_HZ, 0.0, 0.3]).collect();
    let diagonal = Coverage::of(flowmimic_motion::coverage::walking_velocities(&path));
    assert!(diagonal.sidestep > 0.9 && diagonal.aside == [0.0, 0.0], "{diagonal:?}");
}

#[test]
fn impossible_walks_are_refused_quickly() {
    // A duration no walk can have is refused before any walk is drawn (it used to loop forever).
    assert!(generator::sample_set(4, 0, 0.1).is_err());
    assert!(generator::sample_set(4, 0, 1e6).is_err());
    let h = Humanoid::new(SimConfig::default()).unwrap();
    for duration in [0.5, f64::NAN, 1e9] {
        assert!(
            wander(&h, "w", &WanderParams { seed: 1, duration, ..Default::default() }).is_err(),
            "duration {duration}"
        );
    }
    // A schedule is checked segment by segment, and the error names the segment.
    let seg = |speed| Segment { seconds: 2.0, speed, lateral: 0.0, turn_rate: 0.0 };
    let err = scheduled(&h, "s", &[seg(1.0), seg(f64::NAN)]).unwrap_err().to_string();
    assert!(err.contains("segment 2") && err.contains("finite"), "{err}");
    assert!(scheduled(&h, "s", &[seg(1.0), seg(-3.0)]).unwrap_err().to_string().contains("speed"));
    assert!(scheduled(&h, "s", &[]).is_err(), "no segment");
}
