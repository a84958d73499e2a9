//! The joint map from a skeleton's structure: every capture in ../shared/data/mocap maps with
//! structure and names agreeing, and synthetic variants of a capture (joints renamed to random
//! strings, left and right names swapped, side suffixes, an extra root above the hips, position
//! channels on every joint, Z up, centimetres, twist bones) give the same clip.

use flowmimic_geom::{DQuat, DVec3};
use flowmimic_motion::bvh::{Bvh, Channel, Joint};
use flowmimic_motion::{Clip, ImportOptions, import};
use flowmimic_sim::{Humanoid, SimConfig};
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn mocap(file: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/mocap").join(file)
}

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("flowmimic-joint-map-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A skeleton with per-frame, per-joint channel values, easy to edit and written back in the
/// depth-first order a BVH file has.
struct Editable {
    joints: Vec<Joint>,
    /// [frame][joint] channel values.
    values: Vec<Vec<Vec<f64>>>,
    frame_time: f64,
}

impl Editable {
    fn new(bvh: &Bvh) -> Self {
        let values = bvh
            .values
            .chunks(bvh.values_per_frame)
            .map(|row| {
                bvh.joints.iter().map(|j| row[j.first_value..j.first_value + j.channels.len()].to_vec()).collect()
            })
            .collect();
        Self { joints: bvh.joints.clone(), values, frame_time: bvh.frame_time }
    }

    /// Inserts a joint between `child` and its parent with `offset`, channels and a value per
    /// frame; `child`'s offset becomes `child_offset`.
    fn insert_above(
        &mut self,
        child: usize,
        name: &str,
        offset: DVec3,
        channels: Vec<Channel>,
        value: Vec<f64>,
        child_offset: DVec3,
    ) {
        let parent = self.joints[child].parent;
        self.joints.push(Joint { name: name.into(), parent, offset, channels, first_value: 0, end_site: None });
        let new = self.joints.len() - 1;
        self.joints[child].parent = Some(new);
        self.joints[child].offset = child_offset;
        self.values.iter_mut().for_each(|f| f.push(value.clone()));
    }

    fn to_bvh(&self) -> Bvh {
        let mut order = Vec::new();
        fn visit(e: &Editable, j: usize, order: &mut Vec<usize>) {
            order.push(j);
            for c in (0..e.joints.len()).filter(|&c| e.joints[c].parent == Some(j)) {
                visit(e, c, order);
            }
        }
        let root = self.joints.iter().position(|j| j.parent.is_none()).unwrap();
        visit(self, root, &mut order);
        let new_index = |old: usize| order.iter().position(|&o| o == old).unwrap();
        let mut first = 0;
        let joints: Vec<Joint> = order
            .iter()
            .map(|&old| {
                let j = &self.joints[old];
                let out = Joint { parent: j.parent.map(new_index), first_value: first, ..j.clone() };
                first += j.channels.len();
                out
            })
            .collect();
        let values = self.values.iter().flat_map(|f| order.iter().flat_map(move |&old| f[old].clone())).collect();
        Bvh { joints, frame_time: self.frame_time, values_per_frame: first, values }
    }
}

fn humanoid() -> Arc<Humanoid> {
    Humanoid::new(SimConfig::default()).unwrap()
}

fn import_text(h: &Arc<Humanoid>, text: &str, name: &str) -> flowmimic_motion::Imported {
    let path = tmp(&format!("{name}.bvh"));
    std::fs::write(&path, text).unwrap();
    import(h, &path, &ImportOptions { name: Some("walk".into()), ..Default::default() }).unwrap()
}

fn assert_same_clip(a: &Clip, b: &Clip, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: frames");
    let worst =
        a.qpos.iter().zip(&b.qpos).flat_map(|(x, y)| x.iter().zip(y).map(|(p, q)| (p - q).abs())).fold(0.0, f64::max);
    assert!(worst < 1e-3, "{what}: qpos differs by up to {worst}");
}

#[test]
fn every_shared_capture_maps_by_structure_and_names_alike() {
    let h = humanoid();
    for file in ["02_01.bvh", "05_01.bvh", "07_01.bvh", "08_01.bvh", "09_12.bvh", "16_11.bvh"] {
        let im = import(&h, &mocap(file), &ImportOptions::default()).unwrap();
        assert_eq!(im.joint_map.len(), 17, "{file}: {:?}", im.joint_map);
        for line in &im.joint_map {
            assert!(line.ends_with("structure+name"), "{file}: {line}");
        }
    }
}

#[test]
fn variants_of_a_capture_give_the_same_clip() {
    let h = humanoid();
    let text = std::fs::read_to_string(mocap("07_01.bvh")).unwrap();
    let bvh = Bvh::parse(&text).unwrap();
    let original = import_text(&h, &bvh.to_text(), "original").clip;
    let edited = |what: &str, edit: &dyn Fn(&mut Editable)| {
        let mut e = Editable::new(&bvh);
        edit(&mut e);
        let im = import_text(&h, &e.to_bvh().to_text(), what);
        assert_same_clip(&original, &im.clip, what);
        im
    };
    // Every joint renamed to a meaningless string: structure alone.
    let im = edited("renamed", &|e| {
        for (k, j) in e.joints.iter_mut().enumerate() {
            j.name = format!("bone{:x}", (k as u64 + 7).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40);
        }
    });
    assert!(im.joint_map.iter().all(|l| l.ends_with(" structure")), "{:?}", im.joint_map);
    // Left and right names swapped: geometry wins.
    edited("swapped", &|e| {
        for j in &mut e.joints {
            j.name = j.name.replace("Left", "TMP").replace("Right", "Left").replace("TMP", "Right");
        }
    });
    // Side suffixes (UpperLeg_L ...).
    edited("suffixes", &|e| {
        for j in &mut e.joints {
            for (prefix, suffix) in [("Left", "_L"), ("Right", "_R")] {
                if let Some(rest) = j.name.strip_prefix(prefix) {
                    j.name = format!("{rest}{suffix}");
                }
            }
        }
    });
    // An extra root joint above the hips, rotated so that the file is Z up.
    let im = edited("extra root, Z up", &|e| {
        let hips = 0;
        let hips_offset = e.joints[hips].offset;
        let quarter = vec![90.0];
        e.insert_above(hips, "joint_Root", DVec3::ZERO, vec![Channel::XRotation], quarter, hips_offset);
    });
    assert_eq!(im.up, flowmimic_motion::UpAxis::Z);
    // Position channels on every joint (their value is the joint's offset), as LAFAN1 has.
    edited("positions everywhere", &|e| {
        for j in 1..e.joints.len() {
            let o = e.joints[j].offset;
            e.joints[j].channels.splice(0..0, [Channel::XPosition, Channel::YPosition, Channel::ZPosition]);
            for f in &mut e.values {
                f[j].splice(0..0, [o.x, o.y, o.z]);
            }
        }
    });
    // Centimetres instead of CMU's unit.
    let im = edited("centimetres", &|e| {
        let k = 0.0254 / 0.45 / 0.01;
        for j in &mut e.joints {
            j.offset *= k;
            j.end_site = j.end_site.map(|s| s * k);
        }
        for f in &mut e.values {
            for (j, joint) in e.joints.iter().enumerate() {
                for (v, c) in f[j].iter_mut().zip(&joint.channels) {
                    if matches!(c, Channel::XPosition | Channel::YPosition | Channel::ZPosition) {
                        *v *= k;
                    }
                }
            }
        }
    });
    assert_eq!(im.units, Some(flowmimic_motion::Units::Centimetres));
    // Twist bones half way down each thigh and forearm (they never bend).
    edited("twist bones", &|e| {
        for name in ["LeftLeg", "RightLeg", "LeftHand", "RightHand"] {
            let j = e.joints.iter().position(|x| x.name == name).unwrap();
            let half = e.joints[j].offset * 0.5;
            let zeros = vec![0.0; 3];
            let rot = vec![Channel::ZRotation, Channel::YRotation, Channel::XRotation];
            e.insert_above(j, &format!("{name}Twist"), half, rot, zeros, half);
        }
    });
    let _ = DQuat::IDENTITY;
}

#[test]
fn skeletons_that_cannot_walk_are_refused_with_the_reason() {
    let h = humanoid();
    let bvh = Bvh::parse(&std::fs::read_to_string(mocap("07_01.bvh")).unwrap()).unwrap();
    // No legs: cut both leg chains off the hips and rename everything.
    let mut e = Editable::new(&bvh);
    for j in 0..e.joints.len() {
        e.joints[j].name = format!("b{j}");
    }
    let legs: Vec<usize> = (0..e.joints.len())
        .filter(|&j| {
            e.joints[j].parent == Some(0) && e.joints[j].offset.y.abs() < 1.0 && bvh.joints[j].name.contains("Hip")
        })
        .collect();
    assert_eq!(legs.len(), 2, "CMU's hip joints");
    // Re-parent the legs' subtrees onto nothing: drop them by giving them a detached root is not
    // valid BVH, so instead shorten them to nothing (zero offsets, no end sites).
    let mut stack = legs.clone();
    while let Some(j) = stack.pop() {
        e.joints[j].offset = DVec3::ZERO;
        e.joints[j].end_site = e.joints[j].end_site.map(|_| DVec3::ZERO);
        for f in &mut e.values {
            f[j].iter_mut().for_each(|v| *v = 0.0);
        }
        stack.extend((0..e.joints.len()).filter(|&c| e.joints[c].parent == Some(j)));
    }
    let path = tmp("legless.bvh");
    std::fs::write(&path, e.to_bvh().to_text()).unwrap();
    let err = import(&h, &path, &ImportOptions::default()).unwrap_err().to_string();
    assert!(err.contains("legless.bvh") && err.contains("legs"), "{err}");
}

#[test]
fn a_map_file_forces_joints_and_a_bad_one_is_refused() {
    let h = humanoid();
    let force = |pairs: &[(&str, &str)]| ImportOptions {
        map: Some(pairs.iter().map(|(a, b)| (a.to_string(), b.to_string())).collect()),
        ..Default::default()
    };
    let im = import(&h, &mocap("07_01.bvh"), &force(&[("L_Wrist", "LeftFingerBase")])).unwrap();
    let wrist = im.joint_map.iter().find(|l| l.starts_with("L_Wrist")).unwrap();
    assert!(wrist.contains("LeftFingerBase") && wrist.ends_with("forced"), "{wrist}");
    for (bad, needle) in
        [(("L_Wrist", "NoSuchJoint"), "NoSuchJoint"), (("Tail", "Hips"), "Tail"), (("L_Toe", "Hips/end"), "End Site")]
    {
        let err = import(&h, &mocap("07_01.bvh"), &force(&[bad])).unwrap_err().to_string();
        assert!(err.contains("07_01.bvh") && err.contains(needle), "{err}");
    }
}
