//! The SMPL-topology skeleton: body names and order, rest offsets, joint groups, ranges and
//! collision geometry, written once for the left side and mirrored for the right.
//!
//! Proportions are those of a 1.70 m adult (pelvis 0.93 m, hips 0.84 m, knees 0.465 m,
//! ankles 0.08 m above the ground; shoulders 1.43 m); the rest pose is SMPL's T-pose
//! (arms along +-y, x forward, z up). Masses come from the geoms at a density of 1050 kg/m^3.

use std::f64::consts::PI;

/// Number of bodies (the pelvis is the free-floating root).
pub const NUM_BODIES: usize = 24;
/// Number of ball joints, each modelled as three hinges x, y, z.
pub const NUM_JOINTS: usize = 23;
/// Number of actuated hinges, the action dimension.
pub const NUM_DOFS: usize = 3 * NUM_JOINTS;

/// Body names in MuJoCo's depth-first order: the order of every body-indexed array.
pub const BODY_NAMES: [&str; NUM_BODIES] = [
    "Pelvis",
    "L_Hip",
    "L_Knee",
    "L_Ankle",
    "L_Toe",
    "R_Hip",
    "R_Knee",
    "R_Ankle",
    "R_Toe",
    "Torso",
    "Spine",
    "Chest",
    "Neck",
    "Head",
    "L_Thorax",
    "L_Shoulder",
    "L_Elbow",
    "L_Wrist",
    "L_Hand",
    "R_Thorax",
    "R_Shoulder",
    "R_Elbow",
    "R_Wrist",
    "R_Hand",
];

/// Parent of each body in [`BODY_NAMES`] (`None` for the root).
pub const BODY_PARENTS: [Option<usize>; NUM_BODIES] = [
    None,
    Some(0),
    Some(1),
    Some(2),
    Some(3),
    Some(0),
    Some(5),
    Some(6),
    Some(7),
    Some(0),
    Some(9),
    Some(10),
    Some(11),
    Some(12),
    Some(11),
    Some(14),
    Some(15),
    Some(16),
    Some(17),
    Some(11),
    Some(19),
    Some(20),
    Some(21),
    Some(22),
];

/// Index of a body by name.
pub fn body_index(name: &str) -> Option<usize> {
    BODY_NAMES.iter().position(|n| *n == name)
}

/// Well-known bodies.
pub mod body {
    pub const PELVIS: usize = 0;
    pub const L_HIP: usize = 1;
    pub const L_KNEE: usize = 2;
    pub const L_ANKLE: usize = 3;
    pub const L_TOE: usize = 4;
    pub const R_HIP: usize = 5;
    pub const R_KNEE: usize = 6;
    pub const R_ANKLE: usize = 7;
    pub const R_TOE: usize = 8;
    pub const TORSO: usize = 9;
    pub const SPINE: usize = 10;
    pub const CHEST: usize = 11;
    pub const NECK: usize = 12;
    pub const HEAD: usize = 13;
    pub const L_THORAX: usize = 14;
    pub const L_SHOULDER: usize = 15;
    pub const L_ELBOW: usize = 16;
    pub const L_WRIST: usize = 17;
    pub const L_HAND: usize = 18;
    pub const R_THORAX: usize = 19;
    pub const R_SHOULDER: usize = 20;
    pub const R_ELBOW: usize = 21;
    pub const R_WRIST: usize = 22;
    pub const R_HAND: usize = 23;
}

/// Joint groups share a reflected inertia (hence PD gains) and a torque limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointGroup {
    Leg,
    Toe,
    Trunk,
    Upper,
    Wrist,
}

impl JointGroup {
    /// Reflected inertia `I_j` (kg m^2), also the joint armature. Chosen so that
    /// `kp = I wn^2` lands near the gains known to work for SMPL humanoids (docs/conventions.md, section 3).
    pub fn armature(self) -> f64 {
        match self {
            JointGroup::Leg => 0.2,
            JointGroup::Toe => 0.125,
            JointGroup::Trunk => 0.25,
            JointGroup::Upper => 0.125,
            JointGroup::Wrist => 0.075,
        }
    }

    /// Torque limit of each hinge, N m.
    pub fn torque_limit(self) -> f64 {
        match self {
            JointGroup::Leg => 500.0,
            JointGroup::Toe => 150.0,
            JointGroup::Trunk => 500.0,
            JointGroup::Upper => 250.0,
            JointGroup::Wrist => 150.0,
        }
    }
}

/// Collision (and inertia) geometry of one body, in the body frame.
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    Capsule { from: [f64; 3], to: [f64; 3], radius: f64 },
    Box { center: [f64; 3], half: [f64; 3] },
    Sphere { center: [f64; 3], radius: f64 },
}

/// One body of the skeleton.
#[derive(Clone, Copy, Debug)]
pub struct BodySpec {
    pub name: &'static str,
    /// Offset from the parent's joint centre in the T-pose, metres.
    pub offset: [f64; 3],
    pub group: JointGroup,
    /// Hinge ranges (x, y, z) in radians.
    pub range: [[f64; 2]; 3],
    /// Nominal hinge angles (x, y, z): the standing pose `q_bar`, radians.
    pub nominal: [f64; 3],
    pub shape: Shape,
}

const fn deg(d: f64) -> f64 {
    d * PI / 180.0
}

const fn r(lo: f64, hi: f64) -> [f64; 2] {
    [deg(lo), deg(hi)]
}

/// Left-side and central bodies; `mirror` derives the right side.
fn left_and_centre() -> Vec<BodySpec> {
    use JointGroup::*;
    use Shape::*;
    let b = |name, offset, group, range, nominal, shape| BodySpec { name, offset, group, range, nominal, shape };
    let z3 = [0.0; 3];
    vec![
        b(
            "Pelvis",
            [0.0, 0.0, 0.93],
            Trunk,
            [[0.0; 2]; 3],
            z3,
            Capsule { from: [-0.01, -0.07, -0.02], to: [-0.01, 0.07, -0.02], radius: 0.1 },
        ),
        b(
            "L_Hip",
            [0.0, 0.085, -0.09],
            Leg,
            [r(-40.0, 60.0), r(-130.0, 40.0), r(-50.0, 50.0)],
            z3,
            Capsule { from: [0.0, 0.0, -0.06], to: [0.0, 0.0, -0.32], radius: 0.075 },
        ),
        b(
            "L_Knee",
            [0.0, 0.0, -0.375],
            Leg,
            [r(-15.0, 15.0), r(-5.0, 150.0), r(-30.0, 30.0)],
            z3,
            Capsule { from: [0.0, 0.0, -0.05], to: [0.0, 0.0, -0.33], radius: 0.055 },
        ),
        b(
            "L_Ankle",
            [0.0, 0.0, -0.385],
            Leg,
            [r(-35.0, 35.0), r(-50.0, 60.0), r(-35.0, 35.0)],
            z3,
            Box { center: [0.03, 0.0, -0.045], half: [0.09, 0.045, 0.035] },
        ),
        b(
            "L_Toe",
            [0.125, 0.0, -0.05],
            Toe,
            [r(-20.0, 20.0), r(-70.0, 30.0), r(-20.0, 20.0)],
            z3,
            Box { center: [0.03, 0.0, -0.01], half: [0.03, 0.045, 0.02] },
        ),
        b(
            "Torso",
            [-0.01, 0.0, 0.10],
            Trunk,
            [r(-40.0, 40.0), r(-40.0, 60.0), r(-45.0, 45.0)],
            z3,
            Capsule { from: [0.0, -0.03, 0.06], to: [0.0, 0.03, 0.06], radius: 0.085 },
        ),
        b(
            "Spine",
            [0.0, 0.0, 0.13],
            Trunk,
            [r(-40.0, 40.0), r(-40.0, 60.0), r(-45.0, 45.0)],
            z3,
            Capsule { from: [0.0, -0.04, 0.03], to: [0.0, 0.04, 0.03], radius: 0.09 },
        ),
        b(
            "Chest",
            [0.01, 0.0, 0.055],
            Trunk,
            [r(-40.0, 40.0), r(-40.0, 60.0), r(-45.0, 45.0)],
            z3,
            Capsule { from: [-0.01, -0.06, 0.11], to: [-0.01, 0.06, 0.11], radius: 0.115 },
        ),
        b(
            "Neck",
            [-0.02, 0.0, 0.215],
            Upper,
            [r(-45.0, 45.0), r(-50.0, 60.0), r(-70.0, 70.0)],
            z3,
            Capsule { from: [0.005, 0.0, 0.015], to: [0.02, 0.0, 0.05], radius: 0.045 },
        ),
        b(
            "Head",
            [0.03, 0.0, 0.07],
            Upper,
            [r(-45.0, 45.0), r(-50.0, 60.0), r(-70.0, 70.0)],
            z3,
            Sphere { center: [0.01, 0.0, 0.09], radius: 0.1 },
        ),
        b(
            "L_Thorax",
            [-0.03, 0.075, 0.125],
            Upper,
            [r(-30.0, 30.0), r(-30.0, 30.0), r(-30.0, 30.0)],
            z3,
            Capsule { from: [0.0, 0.02, 0.0], to: [0.0, 0.08, 0.02], radius: 0.05 },
        ),
        // The arm points along +y in the T-pose; the nominal pose lowers it by 75 degrees.
        b(
            "L_Shoulder",
            [0.0, 0.10, 0.03],
            Upper,
            [r(-120.0, 120.0), r(-90.0, 90.0), r(-120.0, 90.0)],
            [deg(-75.0), 0.0, 0.0],
            Capsule { from: [0.0, 0.05, 0.0], to: [0.0, 0.21, 0.0], radius: 0.05 },
        ),
        b(
            "L_Elbow",
            [0.0, 0.26, 0.0],
            Upper,
            [r(-30.0, 30.0), r(-90.0, 90.0), r(-150.0, 5.0)],
            [0.0, 0.0, deg(-15.0)],
            Capsule { from: [0.0, 0.05, 0.0], to: [0.0, 0.20, 0.0], radius: 0.04 },
        ),
        b(
            "L_Wrist",
            [0.0, 0.25, 0.0],
            Wrist,
            [r(-60.0, 60.0), r(-80.0, 80.0), r(-60.0, 60.0)],
            z3,
            Capsule { from: [0.0, 0.02, 0.0], to: [0.0, 0.06, 0.0], radius: 0.03 },
        ),
        b(
            "L_Hand",
            [0.0, 0.085, 0.0],
            Wrist,
            [r(-30.0, 30.0), r(-30.0, 30.0), r(-30.0, 30.0)],
            z3,
            Box { center: [0.0, 0.05, 0.0], half: [0.045, 0.05, 0.015] },
        ),
    ]
}

/// The mirror image through the sagittal (x-z) plane: y flips, rotations about x and z flip.
fn mirror(left: &BodySpec, name: &'static str) -> BodySpec {
    let flip_y = |p: [f64; 3]| [p[0], -p[1], p[2]];
    let flip_range = |r: [f64; 2]| [-r[1], -r[0]];
    let shape = match left.shape {
        Shape::Capsule { from, to, radius } => Shape::Capsule { from: flip_y(from), to: flip_y(to), radius },
        Shape::Box { center, half } => Shape::Box { center: flip_y(center), half },
        Shape::Sphere { center, radius } => Shape::Sphere { center: flip_y(center), radius },
    };
    BodySpec {
        name,
        offset: flip_y(left.offset),
        group: left.group,
        range: [flip_range(left.range[0]), left.range[1], flip_range(left.range[2])],
        nominal: [-left.nominal[0], left.nominal[1], -left.nominal[2]],
        shape,
    }
}

/// All 24 bodies in [`BODY_NAMES`] order.
pub fn bodies() -> Vec<BodySpec> {
    let base = left_and_centre();
    BODY_NAMES
        .iter()
        .map(|&name| match name.strip_prefix("R_") {
            Some(rest) => {
                let left = base.iter().find(|b| b.name.strip_prefix("L_") == Some(rest)).expect("left twin");
                mirror(left, name)
            }
            None => *base.iter().find(|b| b.name == name).expect("body in table"),
        })
        .collect()
}

/// Hinge names in action order: `<Body>_x, <Body>_y, <Body>_z` for each non-root body.
pub fn hinge_names() -> Vec<String> {
    BODY_NAMES[1..].iter().flat_map(|b| ["x", "y", "z"].map(|a| format!("{b}_{a}"))).collect()
}
