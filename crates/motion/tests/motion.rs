//! Motion tests on the real captures in ../shared/data/mocap (never copied into the project).

use flowmimic_geom::{DQuat, DVec3, heading, quat_from_wxyz, yaw_quat};
use flowmimic_motion::bvh::{Bvh, Channel, Joint};
use flowmimic_motion::landmarks::{self, Landmark as L};
use flowmimic_motion::*;
use flowmimic_sim::skeleton::body;
use flowmimic_sim::{Humanoid, SimConfig};
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn humanoid() -> Arc<Humanoid> {
    Humanoid::new(SimConfig::default()).unwrap()
}

fn mocap(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mocap").join(file)
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flowmimic-motion-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// (file, frames in the file, walking speed from SOURCES.md in m/s, starts with a T-pose frame)
const CMU: [(&str, usize, f64, bool); 6] = [
    ("02_01.bvh", 344, 1.18, true),
    ("05_01.bvh", 599, 0.89, true),
    ("07_01.bvh", 317, 1.36, true),
    ("08_01.bvh", 278, 1.60, true),
    ("09_12.bvh", 1919, 0.97, true),
    ("16_11.bvh", 534, 0.97, false),
];

#[test]
fn all_cmu_walks_import_with_detected_units_axes_and_t_pose() {
    let h = humanoid();
    for (file, frames, speed, t_pose) in CMU {
        let im = import(&h, &mocap(file), &ImportOptions::default()).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!(im.family, "CMU", "{file}");
        assert_eq!(im.units, Some(Units::CmuAsf), "{file}");
        assert_eq!(im.up, UpAxis::Y, "{file}");
        assert_eq!(im.dropped_frames, usize::from(t_pose), "{file}: T-pose frame");
        assert!((im.source_fps - 120.0).abs() < 0.01, "{file}");
        let kept = frames - usize::from(t_pose);
        let expected = (kept - 1) / 4 + 1;
        assert_eq!(im.clip.len(), expected, "{file}: resampled to 30 Hz");
        let q = im.clip.quality(&h);
        // Straight walks: the path speed is the source's, scaled to the humanoid's legs.
        if file != "09_12.bvh" {
            let want = speed * im.report.scale;
            assert!((q.speed - want).abs() < 0.1 * want, "{file}: speed {} vs {want}", q.speed);
        }
        assert!((0.83..0.95).contains(&q.root_height_mean), "{file}: root height {}", q.root_height_mean);
        assert!(q.penetration_max < 0.03, "{file}: feet {} m into the ground", q.penetration_max);
        assert!(q.airborne < 0.02, "{file}: both feet off the ground in {} of frames", q.airborne);
        assert!(q.single_support > 0.4, "{file}: single support {}", q.single_support);
        // Mean speed of the touching part of a foot, heel strikes and toe-offs included.
        assert!(q.skating < 0.5, "{file}: skating {} m/s", q.skating);
        assert!(im.report.clamped < 0.02, "{file}: {} of hinge values clamped", im.report.clamped);
    }
}

#[test]
fn deepmimic_clips_import_and_the_walk_loops_seamlessly() {
    let h = humanoid();
    let run = import(&h, &mocap("humanoid3d_run.txt"), &ImportOptions::default()).unwrap();
    assert!(run.clip.cyclic && run.clip.len() == 25);
    let walk = import(&h, &mocap("humanoid3d_walk.txt"), &ImportOptions::default()).unwrap();
    let clip = &walk.clip;
    assert!(clip.cyclic);
    assert_eq!(clip.len(), 39);
    let q = clip.quality(&h);
    assert!((q.speed - 0.98 * walk.report.scale).abs() < 0.1, "speed {}", q.speed);
    assert!(q.penetration_max < 0.02 && q.airborne < 0.02);
    let looped = clip.looped(&h, 3 * 38 + 1).unwrap();
    assert_eq!(looped.len(), 115);
    // Three loops travel three times one loop (within 5%: the capture's loop does not close
    // exactly, and its fitted turn of about 2 degrees per loop bends the path a little).
    let one = DVec3::new(clip.qpos[38][0], clip.qpos[38][1], 0.0);
    let three = DVec3::new(looped.qpos[114][0], looped.qpos[114][1], 0.0);
    assert!((three - 3.0 * one).length() < 0.05 * 3.0 * one.length(), "{three} vs 3 x {one}");
    // No jump at the seams: every root step is within 2x the largest step inside one loop.
    let step = |c: &Clip, t: usize| DVec3::from_slice(&c.qpos[t][..3]).distance(DVec3::from_slice(&c.qpos[t - 1][..3]));
    let inside = (1..clip.len()).map(|t| step(clip, t)).fold(0.0, f64::max);
    for t in 1..looped.len() {
        assert!(step(&looped, t) < 2.0 * inside, "jump at frame {t}");
    }
    assert!(looped.qvel.iter().flatten().all(|v| v.is_finite()));
    // A value near 1e308 is finite, yet no pose has it: refused with the file and frame.
    let text = std::fs::read_to_string(mocap("humanoid3d_walk.txt")).unwrap();
    // The second number of frame 0 (the root's x).
    let first = text.find("\"Frames\"").unwrap();
    let at = first + text[first..].find(',').unwrap() + 1;
    let end = at + text[at..].find(',').unwrap();
    let hostile = tmp("huge.txt");
    std::fs::write(&hostile, format!("{}1e308{}", &text[..at], &text[end..])).unwrap();
    let err = import(&h, &hostile, &ImportOptions::default()).unwrap_err().to_string();
    assert!(err.contains("huge.txt") && err.contains("frame 0"), "{err}");
}

/// A LAFAN1-style file: 22 joints with LAFAN1's names, cm, Y up, 30 fps, position channels on
/// every joint. The knees flex and the root walks along +z at 1.2 m/s.
fn lafan_style() -> Bvh {
    let names = [
        ("Hips", None, [0.0, 0.0, 0.0]),
        ("LeftUpLeg", Some(0), [10.0, -8.0, 0.0]),
        ("LeftLeg", Some(1), [0.0, -42.0, 0.0]),
        ("LeftFoot", Some(2), [0.0, -42.0, 0.0]),
        ("LeftToe", Some(3), [0.0, -7.0, 13.0]),
        ("RightUpLeg", Some(0), [-10.0, -8.0, 0.0]),
        ("RightLeg", Some(5), [0.0, -42.0, 0.0]),
        ("RightFoot", Some(6), [0.0, -42.0, 0.0]),
        ("RightToe", Some(7), [0.0, -7.0, 13.0]),
        ("Spine", Some(0), [0.0, 10.0, 0.0]),
        ("Spine1", Some(9), [0.0, 13.0, 0.0]),
        ("Spine2", Some(10), [0.0, 13.0, 0.0]),
        ("Neck", Some(11), [0.0, 20.0, 0.0]),
        ("Head", Some(12), [0.0, 10.0, 0.0]),
        ("LeftShoulder", Some(11), [5.0, 15.0, 0.0]),
        ("LeftArm", Some(14), [12.0, 0.0, 0.0]),
        ("LeftForeArm", Some(15), [28.0, 0.0, 0.0]),
        ("LeftHand", Some(16), [25.0, 0.0, 0.0]),
        ("RightShoulder", Some(11), [-5.0, 15.0, 0.0]),
        ("RightArm", Some(18), [-12.0, 0.0, 0.0]),
        ("RightForeArm", Some(19), [-28.0, 0.0, 0.0]),
        ("RightHand", Some(20), [-25.0, 0.0, 0.0]),
    ];
    use Channel::*;
    let joints: Vec<Joint> = names
        .iter()
        .enumerate()
        .map(|(i, (name, parent, offset))| Joint {
            name: name.to_string(),
            parent: *parent,
            offset: DVec3::from_array(*offset),
            channels: vec![XPosition, YPosition, ZPosition, ZRotation, YRotation, XRotation],
            first_value: 6 * i,
            end_site: None,
        })
        .collect();
    let frames = 61;
    let mut values = Vec::new();
    for f in 0..frames {
        let t = f as f64 / 30.0;
        for (j, joint) in joints.iter().enumerate() {
            let mut row = joint.offset.to_array().to_vec();
            let mut rot = [0.0, 0.0, 0.0]; // Z, Y, X degrees
            match j {
                0 => row = vec![0.0, 92.0, 120.0 * t],
                2 => rot[2] = 30.0 + 25.0 * (6.0 * t).sin(), // left knee flexes about +x
                6 => rot[2] = 30.0 - 25.0 * (6.0 * t).sin(),
                // Arms hang down from the T-pose.
                15 => rot[0] = -75.0,
                19 => rot[0] = 75.0,
                _ => {}
            }
            row.extend(rot);
            values.extend(row);
        }
    }
    Bvh { joints, frame_time: 1.0 / 30.0, values_per_frame: 22 * 6, values }
}

#[test]
fn lafan1_style_file_writes_rereads_and_retargets() {
    let h = humanoid();
    let path = tmp("walk1_subject1.bvh");
    std::fs::write(&path, lafan_style().to_text()).unwrap();
    let back = Bvh::parse(&std::fs::read_to_string(&path).unwrap()).unwrap();
    assert_eq!(back.joints.len(), 22);
    assert_eq!(back.frames(), 61);
    assert_eq!(landmarks::bvh_family(&back), "LAFAN1");
    let im = import(&h, &path, &ImportOptions::default()).unwrap();
    assert_eq!((im.units, im.up, im.dropped_frames), (Some(Units::Centimetres), UpAxis::Y, 0));
    assert_eq!(im.clip.len(), 61);
    // The root moves at 1.2 m/s scaled to the humanoid's legs, along +x after canonicalisation.
    let q = &im.clip.qpos;
    let travel = q[60][0] - q[0][0];
    assert!((travel - 2.4 * im.report.scale).abs() < 0.05, "travel {travel}");
    assert!(q[60][1].abs() < 0.02);
    // Knee flexion shows up in the knee's y hinge with the file's phase.
    let knee_y = |t: usize| q[t][7 + 3 * (body::L_KNEE - 1) + 1];
    let flex_max = (0..61).max_by(|&a, &b| knee_y(a).total_cmp(&knee_y(b))).unwrap();
    let expected = (55.0f64).to_radians();
    assert!((knee_y(flex_max) - expected).abs() < 0.05, "max knee {} rad", knee_y(flex_max));
    let _ = std::fs::remove_file(&path);
}

fn check_error(text: &str, line: usize, needle: &str) {
    let err = Bvh::parse(text).expect_err("malformed file accepted");
    assert_eq!(err.line, line, "{err}");
    assert!(err.to_string().contains(needle), "'{err}' lacks '{needle}'");
}

const SMALL: &str = "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n JOINT Leg\n {\n  OFFSET 0 -40 0\n  CHANNELS 3 Zrotation Yrotation Xrotation\n  End Site\n  {\n   OFFSET 0 -40 0\n  }\n }\n}\nMOTION\nFrames: 2\nFrame Time: 0.0333333\n0 90 0 0 0 0 10 0 0\n0 90 1 0 0 0 20 0 0\n";

#[test]
fn malformed_bvh_gives_line_numbered_errors_never_panics() {
    assert_eq!(Bvh::parse(SMALL).unwrap().frames(), 2);
    check_error(&SMALL.replace("0 90 1 0 0 0 20 0 0\n", ""), 19, "truncated: 2 frames declared, 1 present");
    check_error(
        &SMALL.replace("CHANNELS 3 Zrotation Yrotation Xrotation", "CHANNELS 3 Zrotation Yrotation"),
        10,
        "not a channel",
    );
    check_error(
        &SMALL.replace("0 90 1 0 0 0 20 0 0", "0 90 1 0 0 0 20 0"),
        20,
        "frame 1 has 8 values; the channels need 9",
    );
    check_error(&SMALL.replace("0 90 1 0 0 0 20", "0 90 1 0 zero 0 20"), 20, "'zero' is not a number");
    check_error(&SMALL.replace("Frames: 2", "Frames: 900000000000"), 17, "absurdly large");
    check_error(
        &SMALL.replace("OFFSET 0 -40 0\n  CHANNELS", "OFFSET 0 -4e40 0\n  CHANNELS"),
        8,
        "outside the plausible range",
    );
    check_error(&SMALL.replace("Frame Time: 0.0333333", "Frame Time: 0"), 18, "not a plausible frame period");
    check_error(&SMALL.replace("CHANNELS 3 Z", "CHANNELS 9 Z"), 9, "must be 1 to 6");
    check_error("", 1, "no MOTION");
    // Every truncation of a valid file is an error or a (shorter) valid parse, never a panic.
    for cut in 0..SMALL.len() {
        let _ = Bvh::parse(&SMALL[..cut]);
    }
    // Errors name the file when importing.
    let path = tmp("broken.bvh");
    std::fs::write(&path, &SMALL[..SMALL.len() - 12]).unwrap();
    let err = import(&humanoid(), &path, &ImportOptions::default()).unwrap_err().to_string();
    assert!(err.contains("broken.bvh") && err.contains("line 20"), "{err}");
}

#[test]
fn generated_walk_reproduces_its_landmarks_and_commands() {
    let h = humanoid();
    let p = GaitParams { heading: 0.7, ..Default::default() };
    let marks = generator::landmarks(&p.schedule()).unwrap();
    let (clip, report) = generate(&h, "walk", &p).unwrap();
    assert!((report.scale - 1.0).abs() < 1e-9, "generator uses the humanoid's own proportions");
    assert_eq!(clip.len(), marks.frames.len());
    // Retargeting turned the clip to face +x: undo the 0.7 rad heading on the landmarks.
    let turn = yaw_quat(-0.7);
    let angle = |a: DVec3, b: DVec3| a.normalize().angle_between(b.normalize()).to_degrees();
    let mut worst: f64 = 0.0;
    for (k, m) in clip.bodies.iter().zip(&marks.frames) {
        for (bodies, marks) in [
            ((body::L_HIP, body::L_KNEE), (L::LHip, L::LKnee)),
            ((body::R_KNEE, body::R_ANKLE), (L::RKnee, L::RAnkle)),
            ((body::L_SHOULDER, body::L_ELBOW), (L::LShoulder, L::LElbow)),
            ((body::R_ELBOW, body::R_WRIST), (L::RElbow, L::RWrist)),
        ] {
            let ours = k.pos[bodies.1] - k.pos[bodies.0];
            let theirs = turn * (m[marks.1] - m[marks.0]);
            worst = worst.max(angle(ours, theirs));
        }
    }
    assert!(worst < 2.0, "limb directions differ by up to {worst} degrees");
    let q = clip.quality(&h);
    assert!((q.speed - 1.0).abs() < 0.03, "speed {}", q.speed);
    assert!(q.skating < 0.05 && q.penetration_max < 0.01 && q.airborne == 0.0, "{q:?}");
    // Contacts alternate: each foot is on the ground part of the time and off it part.
    let mut env = h.env();
    let contact: Vec<[bool; 2]> = clip
        .qpos
        .iter()
        .map(|q| {
            env.reset(q, &vec![0.0; h.nv()]).unwrap();
            env.sole_heights().map(|z| z < clip::CONTACT_HEIGHT)
        })
        .collect();
    for side in 0..2 {
        let on = contact.iter().filter(|c| c[side]).count() as f64 / contact.len() as f64;
        assert!((0.5..0.75).contains(&on), "foot {side} on the ground {on} of the time");
        let switches = contact.windows(2).filter(|w| w[0][side] != w[1][side]).count();
        // 6 s at 1.8 steps/s is 5.4 gait cycles: two switches each.
        assert!(switches >= 9, "foot {side} switched contact {switches} times in 6 s");
    }
}

fn yaw_of(q: &[f64]) -> f64 {
    heading(quat_from_wxyz([q[3], q[4], q[5], q[6]]))
}

#[test]
fn generator_walks_backward_sideways_and_turns_as_told() {
    let h = humanoid();
    let run = |p: GaitParams| generate(&h, "g", &p).unwrap().0;
    let back = run(GaitParams { speed: -0.6, ..Default::default() });
    let end = back.qpos.last().unwrap();
    assert!((end[0] + 3.6).abs() < 0.15, "backward walk ends at x = {}", end[0]);
    let side = run(GaitParams { speed: 0.0, lateral: 0.3, ..Default::default() });
    let end = side.qpos.last().unwrap();
    assert!((end[1] - 1.8).abs() < 0.15 && end[0].abs() < 0.15, "sideways walk ends at {end:?}");
    let turn = run(GaitParams { turn_rate: 0.4, ..Default::default() });
    let total = flowmimic_geom::wrap_angle(yaw_of(turn.qpos.last().unwrap()) - yaw_of(&turn.qpos[0]));
    assert!((total - 2.4).abs() < 0.15, "turned {total} rad in 6 s at 0.4 rad/s");
    for c in [&back, &side, &turn] {
        let q = c.quality(&h);
        assert!(q.skating < 0.08 && q.penetration_max < 0.01, "{q:?}");
    }
}

#[test]
fn generator_is_deterministic_and_rejects_bad_parameters() {
    let h = humanoid();
    let p = GaitParams::default();
    assert_eq!(generate(&h, "a", &p).unwrap().0.qpos, generate(&h, "a", &p).unwrap().0.qpos);
    assert_eq!(generator::sample_set(5, 3, 4.0).unwrap(), generator::sample_set(5, 3, 4.0).unwrap());
    assert_ne!(generator::sample_set(5, 3, 4.0).unwrap(), generator::sample_set(5, 4, 4.0).unwrap());
    for bad in [
        GaitParams { speed: f64::NAN, ..Default::default() },
        GaitParams { speed: 5.0, ..Default::default() },
        GaitParams { speed: 2.0, step_frequency: 1.2, ..Default::default() },
        GaitParams { duration: 0.0, ..Default::default() },
    ] {
        assert!(generate(&h, "bad", &bad).is_err(), "{bad:?} accepted");
    }
}

#[test]
fn clip_files_round_trip_and_bad_files_are_refused_by_name() {
    let h = humanoid();
    let (clip, _) = generate(&h, "walk", &GaitParams { duration: 2.0, ..Default::default() }).unwrap();
    let path = tmp("walk.clip.safetensors");
    clip.save(&path).unwrap();
    let back = Clip::load(&h, &path).unwrap();
    assert_eq!(back.qpos, clip.qpos);
    assert_eq!(back.qvel, clip.qvel);
    assert_eq!((back.name.as_str(), back.cyclic), ("walk", false));
    assert!(back.source.starts_with("generator"));
    let bytes = std::fs::read(&path).unwrap();
    let broken = tmp("broken.clip.safetensors");
    std::fs::write(&broken, &bytes[..bytes.len() / 2]).unwrap();
    let err = Clip::load(&h, &broken).unwrap_err().to_string();
    assert!(err.contains("broken.clip.safetensors"), "{err}");
    let err = Clip::load(&h, &tmp("missing.clip.safetensors")).unwrap_err().to_string();
    assert!(err.contains("missing.clip.safetensors"), "{err}");
    // Names become output paths: one that would leave the folder is refused, made or read.
    for name in ["../../escaped", "/abs", "", "a\\b"] {
        assert!(generate(&h, name, &GaitParams { duration: 1.0, ..Default::default() }).is_err(), "{name:?}");
        let mut hostile = clip.clone();
        hostile.name = name.into();
        let path = tmp("hostile.clip.safetensors");
        hostile.save(&path).unwrap();
        let err = Clip::load(&h, &path).unwrap_err().to_string();
        assert!(err.contains("hostile.clip.safetensors") && err.contains("plain file name"), "{err}");
    }
}

#[test]
fn velocities_are_central_differences_of_the_poses() {
    let h = humanoid();
    let (clip, _) = generate(&h, "walk", &GaitParams { turn_rate: 0.3, ..Default::default() }).unwrap();
    for t in 1..clip.len() - 1 {
        let (a, b, v) = (&clip.qpos[t - 1], &clip.qpos[t + 1], &clip.qvel[t]);
        for i in 0..3 {
            assert!(((b[i] - a[i]) * 15.0 - v[i]).abs() < 1e-9, "root velocity, frame {t}");
        }
        for i in 7..a.len() {
            assert!(((b[i] - a[i]) * 15.0 - v[i - 1]).abs() < 1e-9, "hinge {} velocity, frame {t}", i - 7);
        }
        // The root's turn rate about z matches the heading change.
        let yaw_rate = flowmimic_geom::wrap_angle(yaw_of(b) - yaw_of(a)) * 15.0;
        let w_world = quat_from_wxyz([clip.qpos[t][3], clip.qpos[t][4], clip.qpos[t][5], clip.qpos[t][6]])
            * DVec3::from_slice(&v[3..6]);
        assert!((w_world.z - yaw_rate).abs() < 0.1, "frame {t}: yaw rate {} vs {yaw_rate}", w_world.z);
    }
    // Body velocities come from the simulator's kinematics of (qpos, qvel).
    let mut env = h.env();
    env.reset(&clip.qpos[10], &clip.qvel[10]).unwrap();
    assert_eq!(env.bodies().lin_vel, clip.bodies[10].lin_vel);
    let _ = DQuat::IDENTITY;
}

#[test]
fn the_corpus_holds_the_wandering_walks_the_backward_walk_and_the_walking_captures() {
    let h = humanoid();
    let dir = mocap("");
    let built = corpus(
        &h,
        &CorpusParams {
            walks: 2,
            duration: 6.0,
            reaching: 0,
            transitions: 0,
            mocap: Some(dir.clone()),
            walking_only: true,
        },
    )
    .unwrap();
    let names: Vec<&str> = built.clips.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(
        names,
        ["wander_1", "wander_2", "walk_back", "02_01", "05_01", "07_01", "08_01", "09_12", "16_11", "humanoid3d_walk"]
    );
    // DeepMimic's run is the one capture that is not a walk.
    assert_eq!(built.left_out.len(), 1, "{:?}", built.left_out);
    assert_eq!(built.left_out[0].0, dir.join("humanoid3d_run.txt"));
    assert!(built.left_out[0].1.contains("not a walk"), "{}", built.left_out[0].1);
    // The backward walk walks backward (1 s windows of its root path), steadily.
    let back = Coverage::of(built.clips[2].walking_velocities());
    assert!(back.backward > 0.9, "backward in {:.0}% of its steps", 100.0 * back.backward);
    assert!(back.turning < 0.05 && back.sidestep < 0.05, "turning {} sidestepping {}", back.turning, back.sidestep);
    // Without a folder, the generated walks alone.
    let generated = corpus(
        &h,
        &CorpusParams { walks: 1, duration: 6.0, reaching: 0, transitions: 0, mocap: None, walking_only: false },
    )
    .unwrap();
    assert_eq!(generated.clips.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(), ["wander_1", "walk_back"]);
}

#[test]
fn the_corpus_with_arms_holds_reaches_transitions_and_the_captures_of_the_subfolders() {
    let h = humanoid();
    let params = CorpusParams {
        walks: 1,
        duration: 30.0,
        reaching: 4,
        transitions: 2,
        mocap: Some(mocap("")),
        walking_only: false,
    };
    let built = corpus(&h, &params).unwrap();
    let names: Vec<&str> = built.clips.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(
        names[..9],
        [
            "wander_1",
            "walk_back",
            "reach_1",
            "reach_2",
            "reach_3",
            "reach_4",
            "reach_stand",
            "transitions_1",
            "transitions_2"
        ]
    );
    let from = |folder: &str| {
        let files = std::fs::read_dir(mocap(folder)).unwrap().filter_map(|e| e.ok()).collect::<Vec<_>>();
        let stems: Vec<String> = files.iter().map(|f| f.path().file_stem().unwrap().to_string_lossy().into()).collect();
        names.iter().filter(|n| stems.iter().any(|s| s == *n)).count()
    };
    assert!(from("arms") >= 6 && from("walks") >= 10, "arms {} walks {}", from("arms"), from("walks"));
    // The reaching clips raise a hand above the walking swing and lower one below it (each
    // clip out of the swing's range in a tenth of its frames, all of them both ways), the arms
    // captures too.
    let reaching: Vec<_> = built.clips.iter().filter(|c| c.name.starts_with("reach")).collect();
    for clip in &reaching {
        assert!(clip.duration() >= 30.0, "{}: {:.1} s", clip.name, clip.duration());
        let (high, low) = (clip.share_with_hand_above(clip::HAND_HIGH), clip.share_with_hand_below(clip::HAND_LOW));
        assert!(high + low > 0.1, "{}: a hand high in {high:.2} of frames, low in {low:.2}", clip.name);
    }
    let frames = |share: &dyn Fn(&Clip) -> f64| reaching.iter().map(|c| share(c) * c.len() as f64).sum::<f64>();
    let all = frames(&|_| 1.0);
    let high = frames(&|c| c.share_with_hand_above(clip::HAND_HIGH)) / all;
    let low = frames(&|c| c.share_with_hand_below(clip::HAND_LOW)) / all;
    // A third of the targets are low; the hands are out 45% of the time and hold for about 40%
    // of that, so about 6% of the frames hold a low hand.
    assert!(high > 0.1 && low > 0.06, "the reaching clips: a hand high in {high:.2} of frames, low in {low:.2}");
    let arms = built.clips.iter().find(|c| c.name == "02_06").unwrap();
    assert!(arms.share_with_hand_above(clip::HAND_OVERHEAD) > 0.3);
    // No clip jumps between frames: the captures that do are left out, named.
    for clip in &built.clips {
        assert!(clip.body_speed_max() < clip::BODY_SPEED_JUMP, "{}: {:.1} m/s", clip.name, clip.body_speed_max());
    }
    let jumping: Vec<_> = built.left_out.iter().filter(|(_, why)| why.starts_with("jumps")).collect();
    assert!(jumping.iter().any(|(file, _)| file.ends_with("arms/05_10.bvh")), "{:?}", built.left_out);
    // The walks of transitions reverse from forward to backward and back within a second.
    let transitions: Vec<_> = built.clips.iter().filter(|c| c.name.starts_with("transitions")).collect();
    let cov = Coverage::of_walks(transitions.iter().map(|c| c.walking_velocities()).collect());
    assert!(cov.reversing > 0.05 && cov.sidestep > 0.1 && cov.backward > 0.1, "{cov:?}");
    // The wandering walk alone hardly reverses, and a steady walk never does.
    let steady = Coverage::of(built.clips[1].walking_velocities());
    assert_eq!(steady.reversing, 0.0);
}

#[test]
fn a_mirrored_walk_turns_and_steps_the_other_way_with_the_other_foot() {
    let h = humanoid();
    let p = GaitParams { turn_rate: 0.4, lateral: 0.2, duration: 3.0, ..Default::default() };
    let walk = generate(&h, "g", &p).unwrap().0;
    let image = walk.mirror_image(&h).unwrap();
    assert_eq!(image.name, "g-mirrored");
    // Per frame, the walking velocities mirror: forward the same, sideways and turning negated.
    for (a, b) in walk.walking_velocities().iter().zip(image.walking_velocities()) {
        assert!((a[0] - b[0]).abs() < 1e-6 && (a[1] + b[1]).abs() < 1e-6 && (a[2] + b[2]).abs() < 1e-6, "{a:?} {b:?}");
    }
    // The left foot of the image is where the right foot was, across the sagittal plane.
    for (k, m) in walk.bodies.iter().zip(&image.bodies) {
        let (l, r) = (m.pos[body::L_ANKLE], k.pos[body::R_ANKLE]);
        assert!((l - DVec3::new(r.x, -r.y, r.z)).length() < 1e-9);
    }
    let q = image.quality(&h);
    assert!(q.skating < 0.08 && q.penetration_max < 0.01, "{q:?}");
    let twice = image.mirror_image(&h).unwrap();
    assert!(twice.qpos.iter().flatten().zip(walk.qpos.iter().flatten()).all(|(a, b)| a == b));
}
