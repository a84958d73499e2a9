//! Reaching in generated walks, checked on many random clips: during each hold the reference
//! hand is on its target, the walker stops with the feet planted, the torso leans and the knees
//! bend for low targets with the feet stepped apart, the arm never passes through the torso (the
//! simulator's own collision detection on the reference poses), the weight stays over the feet
//! when standing, and the walking invariants still hold.

mod common;

use flowmimic_motion::clip::BODY_SPEED_JUMP;
use flowmimic_motion::generator::{self, Schedule};
use flowmimic_motion::reach::{self, Reaching, TargetHeights};
use flowmimic_motion::{Clip, GaitParams, RetargetReport, WanderParams, generate, wander};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::{CONTROL_HZ, Humanoid, SimConfig};
use rand::{Rng, SeedableRng};
use std::sync::Arc;

const ARMS: [usize; 8] = [
    body::L_SHOULDER,
    body::L_ELBOW,
    body::L_WRIST,
    body::L_HAND,
    body::R_SHOULDER,
    body::R_ELBOW,
    body::R_WRIST,
    body::R_HAND,
];
const TORSO: [usize; 4] = [body::PELVIS, body::TORSO, body::SPINE, body::CHEST];

/// Reaching clips of every kind: wandering walks, constant walks at any speed and direction,
/// and standing, each with its schedule and where the retargeting placed it.
fn reaching_clips(h: &Arc<Humanoid>) -> Vec<(Clip, Schedule, RetargetReport)> {
    let mut clips = Vec::new();
    for seed in 1..=3 {
        let p = WanderParams {
            seed,
            duration: 30.0,
            reach: Some(Reaching { share: 0.5, seed, heights: Default::default() }),
            ..Default::default()
        };
        let (clip, report) = wander(h, "reach", &p).unwrap();
        clips.push((clip, p.schedule(), report));
    }
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    for k in 0..8 {
        // Two standing clips, one with each way of drawing heights; uniform heights in every
        // other walk.
        let standing = k < 2;
        let heights = if k % 2 == 1 { TargetHeights::Uniform } else { TargetHeights::Split };
        let p = GaitParams {
            speed: if standing { 0.0 } else { rng.random_range(-0.6..1.5) },
            lateral: if standing { 0.0 } else { rng.random_range(-0.2..0.2) },
            turn_rate: if standing { 0.0 } else { rng.random_range(-0.5..0.5) },
            heading: rng.random_range(-3.0..3.0),
            duration: 15.0,
            reach: Some(Reaching { share: 0.7, seed: k, heights }),
            ..Default::default()
        };
        let (clip, report) = generate(h, "reach", &p).unwrap();
        clips.push((clip, p.schedule(), report));
    }
    clips
}

/// The frames whose times fall within `from..=to`, s.
fn frames_within(from: f64, to: f64) -> std::ops::RangeInclusive<usize> {
    (from * CONTROL_HZ).ceil() as usize..=(to * CONTROL_HZ).floor() as usize
}

#[test]
fn reaching_hands_hold_their_targets_and_the_walk_keeps_its_invariants() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let mut env = h.env();
    let (mut reaches, mut low, mut lowest, mut highest, mut worst_balance) = (0, 0, f64::MAX, 0.0_f64, 0.0_f64);
    let (mut lowest_pelvis, mut middle) = (f64::MAX, 0);
    let (mut planted_worst, mut shared_stances) = (0.0_f64, 0);
    for (n, (clip, schedule, report)) in reaching_clips(&h).iter().enumerate() {
        let targets = generator::reach_targets(schedule);
        assert!(!targets.is_empty(), "clip {n} has no reach");
        for (r, target) in schedule.reaches.iter().zip(&targets) {
            reaches += 1;
            let what = format!("clip {n}, reach at {:.1} s ({r:?})", r.start);
            assert!((reach::HEIGHTS[0]..=reach::HEIGHTS[1]).contains(&r.height), "{what}");
            assert!((reach::DISTANCES[0]..=reach::DISTANCES[1]).contains(&r.distance), "{what}");
            assert!((0.4..=1.0).contains(&r.approach) && (0.3..=1.5).contains(&r.hold), "{what}");
            let hand = [body::L_HAND, body::R_HAND][r.side];
            let hold = frames_within(r.hold_start(), r.hold_end());
            let mut worst = 0.0_f64;
            for t in hold.clone() {
                let goal = report.placement.apply(t, *target);
                worst = worst.max(clip.bodies[t].pos[hand].distance(goal));
                // The walker stands while the hand is out (the pelvis moves only as the bend
                // pushes the hips back).
                let v = clip.bodies[t].lin_vel[body::PELVIS].truncate().length();
                assert!(v < 0.15, "{what}: frame {t}: the pelvis moves at {v:.2} m/s");
            }
            assert!(worst < 0.02, "{what}: the hand is {:.1} cm from its target during the hold", 100.0 * worst);
            low += usize::from(r.height < reach::LOW);
            middle += usize::from((reach::LOW..reach::HIGH).contains(&r.height));
            lowest = lowest.min(r.height);
            highest = highest.max(r.height);
            // Low targets are reached by bending: the pelvis lower or the chest tilted.
            let mid = &clip.bodies[(*hold.start() + *hold.end()) / 2];
            let tilt = (mid.rot[body::CHEST] * flowmimic_geom::DVec3::Z).z.acos().to_degrees();
            lowest_pelvis = lowest_pelvis.min(mid.pos[body::PELVIS].z);
            // A deep squat stands wide: the feet step out before the pelvis drops (walking, they
            // are 0.22 m apart).
            if mid.pos[body::PELVIS].z < reach::PELVIS_HEIGHT - 0.5 * reach::MAX_DROP {
                let lateral = (mid.rot[body::PELVIS] * flowmimic_geom::DVec3::Y).truncate();
                let apart = (mid.pos[body::L_ANKLE] - mid.pos[body::R_ANKLE]).truncate().dot(lateral);
                assert!(apart > 0.3, "{what}: squatting with the feet {apart:.2} m apart");
            }
            if r.height < 0.6 {
                assert!(
                    tilt > 20.0 && mid.pos[body::PELVIS].z < 0.85,
                    "{what}: reaching low with the chest tilted {tilt:.0} deg, the pelvis {:.2} m high",
                    mid.pos[body::PELVIS].z
                );
            }
        }
        // The feet stay planted while a hand holds; standing, from a wide stance's first hold to
        // its last too (they do not step in and out between squats close in time).
        let standing = schedule.keys.iter().all(|(_, c)| c.speed == 0.0 && c.lateral == 0.0 && c.turn_rate == 0.0);
        for stance in reach::wide_stances(&schedule.reaches) {
            let reaches = &schedule.reaches[stance.reaches.clone()];
            let holds: Vec<_> = if standing {
                vec![(reaches[0].hold_start(), reaches[reaches.len() - 1].hold_end())]
            } else {
                reaches.iter().map(|r| (r.hold_start(), r.hold_end())).collect()
            };
            for (from, to) in holds {
                let frames = frames_within(from, to);
                for ankle in [body::L_ANKLE, body::R_ANKLE] {
                    let planted = clip.bodies[*frames.start()].pos[ankle];
                    let moved = frames.clone().map(|t| clip.bodies[t].pos[ankle].distance(planted)).fold(0.0, f64::max);
                    planted_worst = planted_worst.max(moved);
                    assert!(
                        moved < 0.01,
                        "clip {n}: the ankle {ankle} moves {:.1} cm in {from:.1}-{to:.1} s",
                        100.0 * moved
                    );
                }
            }
            shared_stances += usize::from(standing && reaches.len() > 1);
        }
        let mut stance_speeds = Vec::new();
        for (t, k) in clip.bodies.iter().enumerate() {
            let what = format!("clip {n}, frame {t}");
            // The chest and head face within 30 degrees of the pelvis (25 when walking: leaning
            // toward a target out to the side turns a body's forward axis a little).
            let turn = common::upper_body_turn(k);
            assert!(turn < 30.0, "{what}: the upper body faces {turn:.0} deg from the pelvis");
            env.reset(&clip.qpos[t], &clip.qvel[t]).unwrap();
            // Reaching while standing or creeping, the weight stays over the feet (within 0.1 m
            // of the line between their middles; a foot reaches 0.11 m to either side of its
            // middle): a bend that reaches far pushes the hips back, and no further.
            let reaching = schedule.reaches.iter().any(|r| (r.start..=r.end()).contains(&(t as f64 / CONTROL_HZ)));
            if reaching && k.lin_vel[body::PELVIS].truncate().length() < 0.15 {
                let foot = |ankle: usize, toe: usize| 0.5 * (k.pos[ankle] + k.pos[toe]).truncate();
                let (l, r) = (foot(body::L_ANKLE, body::L_TOE), foot(body::R_ANKLE, body::R_TOE));
                let com = env.centre_of_mass().truncate();
                // Distance to the line between the feet's middles (the support, less the feet).
                let along = ((com - l).dot(r - l) / (r - l).length_squared()).clamp(0.0, 1.0);
                let off = com - (l + along * (r - l));
                worst_balance = worst_balance.max(off.length());
                let forward = (k.rot[body::PELVIS] * flowmimic_geom::DVec3::X).truncate();
                let way = if off.dot(forward) > 0.0 { "ahead of" } else { "behind" };
                assert!(
                    off.length() < 0.1,
                    "{what}: the centre of mass is {:.2} m {way} the feet, the pelvis {:.2} m high",
                    off.length(),
                    k.pos[body::PELVIS].z
                );
            }
            for (a, b) in env.self_contacts() {
                assert!(!common::legs_touch((a, b)), "{what}: legs {a} and {b} touch");
                let arm_in_torso =
                    (ARMS.contains(&a) && TORSO.contains(&b)) || (TORSO.contains(&a) && ARMS.contains(&b));
                assert!(!arm_in_torso, "{what}: arm and torso bodies {a} and {b} touch");
            }
            stance_speeds.extend(common::stance_speeds(&env, k));
        }
        let mean = stance_speeds.iter().sum::<f64>() / stance_speeds.len() as f64;
        assert!(mean < 0.05, "clip {n}: feet on the ground move at {mean:.3} m/s on average");
        let q = clip.quality(&h);
        assert!(q.penetration_max < 0.01 && q.airborne == 0.0, "clip {n}: {q:?}");
        // No body jumps between frames: a hand out and back moves as fast as a person's.
        assert!(q.body_speed_max < BODY_SPEED_JUMP, "clip {n}: a body moves at {:.1} m/s", q.body_speed_max);
    }
    assert!(reaches >= 40, "only {reaches} reaches");
    assert!(shared_stances > 0, "no standing wide stance holds two reaches: the stance between them is untested");
    eprintln!(
        "{shared_stances} standing wide stances hold two or more reaches; an ankle moved at most {planted_worst:.4} m while planted"
    );
    eprintln!("reaching slowly, the centre of mass was at most {worst_balance:.3} m from between the feet");
    // Targets span the range, from near the floor to above the head, and a quarter or more come
    // low, reached with a squat (a third are drawn there; some low and far are out of reach).
    assert!(lowest < 0.6 && highest > 1.6, "targets {lowest:.2}-{highest:.2} m high");
    assert!(4 * low >= reaches, "{low} of {reaches} targets below {} m", reach::LOW);
    // Uniform heights hold targets in front of the waist and chest, which split ones never do.
    assert!(middle > 0, "no target {}-{} m high", reach::LOW, reach::HIGH);
    eprintln!(
        "{low} of {reaches} targets below {} m; the lowest pelvis while holding {lowest_pelvis:.2} m",
        reach::LOW
    );
    // Some low target is reached with most of the squat.
    let squat = reach::PELVIS_HEIGHT - 0.75 * reach::MAX_DROP;
    assert!(lowest_pelvis < squat, "the pelvis holds no lower than {lowest_pelvis:.2} m (bar {squat:.2})");
}
