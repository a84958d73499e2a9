//! Landmarks: the world positions of 17 joints every skeleton has, z up, metres.
//!
//! Every motion source (BVH of any family, DeepMimic clips, the walking generator) becomes a
//! [`LandmarkClip`]; [`crate::retarget`] turns landmarks into humanoid poses. Working from
//! positions rather than source-local rotations means no rest-pose alignment of the source's
//! joint frames is needed (LAFAN1's rest pose, for one, is not a standing pose).
//!
//! Which BVH joint gives which landmark is read from the skeleton's structure, names
//! confirming ([`crate::joint_map`]). What the structure finds on the two common families:
//!
//! | landmark  | LAFAN1       | CMU (cgspeed) |
//! |-----------|--------------|---------------|
//! | L_Hip     | LeftUpLeg    | LeftUpLeg     |
//! | L_Knee    | LeftLeg      | LeftLeg       |
//! | L_Ankle   | LeftFoot     | LeftFoot      |
//! | L_Toe     | LeftToe      | LeftToeBase   |
//! | Chest     | Spine2       | Spine1        |
//! | Neck      | Neck         | Neck1         |
//! | Head      | Head         | Head          |
//! | L_Shoulder| LeftArm      | LeftArm       |
//! | L_Elbow   | LeftForeArm  | LeftForeArm   |
//! | L_Wrist   | LeftHand     | LeftHand      |
//!
//! and the same on the right. DeepMimic clips have their own loader ([`deepmimic`]).

use crate::bvh::Bvh;
use crate::joint_map::{ForcedMap, JointMap, Source, map_joints, normalise};
use flowmimic_geom::{DQuat, DVec3};

/// The landmarks, in the order of [`LandmarkClip::frames`] entries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Landmark {
    LHip,
    RHip,
    LKnee,
    RKnee,
    LAnkle,
    RAnkle,
    LToe,
    RToe,
    Chest,
    Neck,
    Head,
    LShoulder,
    RShoulder,
    LElbow,
    RElbow,
    LWrist,
    RWrist,
}

pub const NUM_LANDMARKS: usize = 17;
pub const LANDMARK_NAMES: [&str; NUM_LANDMARKS] = [
    "L_Hip",
    "R_Hip",
    "L_Knee",
    "R_Knee",
    "L_Ankle",
    "R_Ankle",
    "L_Toe",
    "R_Toe",
    "Chest",
    "Neck",
    "Head",
    "L_Shoulder",
    "R_Shoulder",
    "L_Elbow",
    "R_Elbow",
    "L_Wrist",
    "R_Wrist",
];

pub type Pose = [DVec3; NUM_LANDMARKS];

/// Landmark positions over time.
#[derive(Clone, Debug)]
pub struct LandmarkClip {
    pub fps: f64,
    pub frames: Vec<Pose>,
}

impl std::ops::Index<Landmark> for Pose {
    type Output = DVec3;
    fn index(&self, l: Landmark) -> &DVec3 {
        &self[l as usize]
    }
}

/// What went wrong turning a file into landmarks.
#[derive(Debug, thiserror::Error)]
pub enum LandmarkError {
    #[error("no joint for landmark {landmark} (tried {tried}); joints are: {joints}")]
    MissingJoint { landmark: &'static str, tried: String, joints: String },
    #[error("cannot tell the length unit: the leg is {0} file units long")]
    Units(f64),
    #[error("{0}")]
    Format(String),
}

/// Length units of a BVH file: metres per file unit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Units {
    Metres,
    Centimetres,
    Millimetres,
    Inches,
    /// CMU's ASF unit, (1/0.45) * 2.54 cm.
    CmuAsf,
}

impl Units {
    pub const ALL: [Units; 5] = [Units::Metres, Units::Centimetres, Units::Millimetres, Units::Inches, Units::CmuAsf];

    pub fn metres(self) -> f64 {
        match self {
            Units::Metres => 1.0,
            Units::Centimetres => 0.01,
            Units::Millimetres => 0.001,
            Units::Inches => 0.0254,
            Units::CmuAsf => 0.0254 / 0.45,
        }
    }

    pub fn parse(s: &str) -> Option<Self> {
        Some(match s.to_ascii_lowercase().as_str() {
            "m" | "metres" | "meters" => Units::Metres,
            "cm" => Units::Centimetres,
            "mm" => Units::Millimetres,
            "in" | "inch" | "inches" => Units::Inches,
            "cmu" | "asf" => Units::CmuAsf,
            _ => return None,
        })
    }

    /// The unit that makes a hip-to-ankle length of `leg` file units closest to an adult's
    /// 0.8 m (on a log scale; neighbouring units differ by at least 2.2x).
    pub fn detect(leg: f64) -> Option<Self> {
        if !(leg.is_finite() && leg > 0.0) {
            return None;
        }
        let best = Units::ALL
            .into_iter()
            .min_by(|a, b| {
                let da = (leg * a.metres() / 0.8).ln().abs();
                let db = (leg * b.metres() / 0.8).ln().abs();
                da.total_cmp(&db)
            })
            .expect("non-empty");
        // Reject legs outside 0.4-1.6 m in every unit: not a human skeleton.
        ((leg * best.metres() / 0.8).ln().abs() < 2f64.ln()).then_some(best)
    }
}

/// Which axis of the source points up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum UpAxis {
    Y,
    Z,
}

impl UpAxis {
    /// The rotation taking this axis to +z (a right-handed rotation, so nothing is mirrored).
    pub fn to_z_up(self) -> DQuat {
        match self {
            UpAxis::Y => DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
            UpAxis::Z => DQuat::IDENTITY,
        }
    }
}

/// The skeleton family, for reporting.
pub fn bvh_family(bvh: &Bvh) -> &'static str {
    let names: Vec<String> = bvh.joints.iter().map(|j| normalise(&j.name)).collect();
    let has = |n: &str| names.iter().any(|x| x == n);
    if has("lhipjoint") && has("lefttoebase") {
        "CMU"
    } else if bvh.joints.len() == 22 && has("lefttoe") && has("spine2") {
        "LAFAN1"
    } else {
        "generic"
    }
}

/// How a BVH file was read.
#[derive(Clone, Debug)]
pub struct BvhReading {
    pub family: &'static str,
    pub units: Units,
    pub up: UpAxis,
    pub clip: LandmarkClip,
    /// Which joint became which landmark, and how sure that is.
    pub map: JointMap,
}

/// Landmarks of a BVH file. `units` and `up` are detected when `None`; `map` forces joints.
pub fn from_bvh(
    bvh: &Bvh,
    units: Option<Units>,
    up: Option<UpAxis>,
    map: Option<&ForcedMap>,
) -> Result<BvhReading, LandmarkError> {
    let joint_map = map_joints(bvh, map)?;
    let raw: Vec<Pose> = (0..bvh.frames())
        .map(|f| {
            let (pos, rot) = bvh.global_pose(f);
            joint_map.sources.map(|s| match s {
                Source::Joint(j) => pos[j],
                Source::EndSite(j) => pos[j] + rot[j] * bvh.joints[j].end_site.unwrap_or_default(),
            })
        })
        .collect();
    let first = &raw[0];
    let leg = 0.5
        * (first[Landmark::LHip].distance(first[Landmark::LKnee])
            + first[Landmark::LKnee].distance(first[Landmark::LAnkle])
            + first[Landmark::RHip].distance(first[Landmark::RKnee])
            + first[Landmark::RKnee].distance(first[Landmark::RAnkle]));
    let units = match units {
        Some(u) => u,
        None => Units::detect(leg).ok_or(LandmarkError::Units(leg))?,
    };
    let up = up.unwrap_or_else(|| detect_up(&raw));
    let (scale, turn) = (units.metres(), up.to_z_up());
    let frames = raw.iter().map(|p| p.map(|v| turn * (v * scale))).collect();
    let clip = LandmarkClip { fps: 1.0 / bvh.frame_time, frames };
    Ok(BvhReading { family: bvh_family(bvh), units, up, clip, map: joint_map })
}

/// Up is the axis along which the head sits above the ankles, on average over the clip.
fn detect_up(frames: &[Pose]) -> UpAxis {
    let mut v = DVec3::ZERO;
    for p in frames {
        v += p[Landmark::Head] - 0.5 * (p[Landmark::LAnkle] + p[Landmark::RAnkle]);
    }
    if v.z.abs() > v.y.abs() { UpAxis::Z } else { UpAxis::Y }
}

pub mod deepmimic {
    //! DeepMimic reference motions (`{"Loop": ..., "Frames": [[dt, root pos, root quat, ...]]}`),
    //! for its `humanoid3d` character (Y up, facing +x, right side +z). Layout per frame: frame
    //! duration; root position (3) and quaternion w x y z (4); chest, neck, right hip quaternions;
    //! right knee angle; right ankle, right shoulder quaternions; right elbow angle; then the same
    //! for the left side. Knees and elbows rotate about their local z axis.

    use super::*;

    /// Attachment offsets of `humanoid3d`, metres, relative to the parent joint.
    const CHEST: [f64; 3] = [0.0, 0.236151, 0.0];
    const NECK: [f64; 3] = [0.0, 0.223894, 0.0];
    const HIP: [f64; 3] = [0.0, 0.0, 0.084887];
    const KNEE: [f64; 3] = [0.0, -0.421546, 0.0];
    const ANKLE: [f64; 3] = [0.0, -0.40987, 0.0];
    const SHOULDER: [f64; 3] = [-0.02405, 0.2435, 0.18311];
    const ELBOW: [f64; 3] = [0.0, -0.274788, 0.0];
    const WRIST: [f64; 3] = [0.0, -0.258947, 0.0];
    /// Toe tip and head top in their joints' frames (the character's foot box and head sphere).
    const TOE: [f64; 3] = [0.13, -0.045, 0.0];
    const HEAD: [f64; 3] = [0.0, 0.2, 0.0];

    /// Largest magnitude of any number in a DeepMimic frame: positions in metres, quaternion
    /// entries and angles in radians are all far below it (1e308 passed a finiteness check
    /// and overflowed in retargeting).
    const MAX_VALUE: f64 = 1e4;

    /// A parsed DeepMimic clip: landmarks, and whether it loops.
    pub struct DeepMimicClip {
        pub clip: LandmarkClip,
        pub cyclic: bool,
    }

    pub fn parse(text: &str) -> Result<DeepMimicClip, LandmarkError> {
        let fail = |m: String| LandmarkError::Format(m);
        let json: serde_json::Value = serde_json::from_str(text).map_err(|e| fail(format!("not JSON: {e}")))?;
        let frames = json["Frames"].as_array().ok_or_else(|| fail("no \"Frames\" array".into()))?;
        if frames.len() < 2 {
            return Err(fail(format!("{} frames; a clip needs at least 2", frames.len())));
        }
        let cyclic = json["Loop"].as_str() == Some("wrap");
        let mut poses = Vec::with_capacity(frames.len());
        let mut dt = 0.0;
        for (i, f) in frames.iter().enumerate() {
            let v: Vec<f64> = f
                .as_array()
                .filter(|a| a.len() == 44)
                .and_then(|a| a.iter().map(|x| x.as_f64().filter(|x| x.abs() <= MAX_VALUE)).collect())
                .ok_or_else(|| fail(format!("frame {i} is not 44 numbers within +-{MAX_VALUE}")))?;
            if i == 0 {
                dt = v[0];
            }
            poses.push(pose(&v));
        }
        if !(1e-4..=1.0).contains(&dt) {
            return Err(fail(format!("frame duration {dt} s is not plausible")));
        }
        let turn = UpAxis::Y.to_z_up();
        let frames = poses.into_iter().map(|p| p.map(|x| turn * x)).collect();
        Ok(DeepMimicClip { clip: LandmarkClip { fps: 1.0 / dt, frames }, cyclic })
    }

    fn quat(v: &[f64]) -> DQuat {
        DQuat::from_xyzw(v[1], v[2], v[3], v[0]).normalize()
    }

    fn pose(v: &[f64]) -> Pose {
        let o = DVec3::from_array;
        let root_p = DVec3::new(v[1], v[2], v[3]);
        let root_r = quat(&v[4..8]);
        let chest_r = root_r * quat(&v[8..12]);
        let chest_p = root_p + root_r * o(CHEST);
        let neck_p = chest_p + chest_r * o(NECK);
        let neck_r = chest_r * quat(&v[12..16]);
        // side: +1 right (+z), -1 left; indices of hip quat, knee, ankle quat, shoulder quat, elbow.
        let limb = |mirror: f64, at: usize| {
            let m = |a: [f64; 3]| DVec3::new(a[0], a[1], mirror * a[2]);
            let hip_p = root_p + root_r * m(HIP);
            let hip_r = root_r * quat(&v[at..at + 4]);
            let knee_p = hip_p + hip_r * m(KNEE);
            let knee_r = hip_r * DQuat::from_rotation_z(v[at + 4]);
            let ankle_p = knee_p + knee_r * m(ANKLE);
            let ankle_r = knee_r * quat(&v[at + 5..at + 9]);
            let toe_p = ankle_p + ankle_r * m(TOE);
            let sh_p = chest_p + chest_r * m(SHOULDER);
            let sh_r = chest_r * quat(&v[at + 9..at + 13]);
            let el_p = sh_p + sh_r * m(ELBOW);
            let el_r = sh_r * DQuat::from_rotation_z(v[at + 13]);
            let wr_p = el_p + el_r * m(WRIST);
            [hip_p, knee_p, ankle_p, toe_p, sh_p, el_p, wr_p]
        };
        let [rh, rk, ra, rt, rs, re, rw] = limb(1.0, 16);
        let [lh, lk, la, lt, ls, le, lw] = limb(-1.0, 30);
        let head = neck_p + neck_r * o(HEAD);
        [lh, rh, lk, rk, la, ra, lt, rt, chest_p, neck_p, head, ls, rs, le, re, lw, rw]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units_are_detected_from_leg_length() {
        assert_eq!(Units::detect(80.0), Some(Units::Centimetres));
        assert_eq!(Units::detect(0.85), Some(Units::Metres));
        assert_eq!(Units::detect(32.0), Some(Units::Inches));
        assert_eq!(Units::detect(13.5), Some(Units::CmuAsf));
        assert_eq!(Units::detect(790.0), Some(Units::Millimetres));
        assert_eq!(Units::detect(0.0), None);
        assert_eq!(Units::detect(f64::NAN), None);
    }

    #[test]
    fn names_normalise() {
        assert_eq!(normalise("mixamorig:Left_Up-Leg"), "leftupleg");
    }
}
