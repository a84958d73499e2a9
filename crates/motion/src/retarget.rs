//! Landmarks to humanoid poses.
//!
//! 1. Resample to 30 Hz (linear interpolation of positions).
//! 2. Scale the source so its hip-to-ankle length is the humanoid's (0.76 m).
//! 3. Orient each driven body from two directions measured on the landmarks, mapped onto the
//!    same directions of the humanoid's T-pose: `R = B(d, s) B(d0, s0)^T`, where `B` builds an
//!    orthonormal basis from a primary direction `d` and a secondary `s`:
//!
//!    | body        | primary `d` (T-pose `d0`)   | secondary `s` (T-pose `s0`)                |
//!    |-------------|-----------------------------|--------------------------------------------|
//!    | Pelvis      | L_Hip - R_Hip (+y)          | Chest - hip centre (+z)                    |
//!    | Chest       | L_Shoulder - R_Shoulder (+y)| Neck - Chest (+z)                          |
//!    | Head        | Head - Neck (+z)            | shoulder line (+y)                         |
//!    | thigh, shin | Knee - Hip, Ankle - Knee (-z)| knee axis: thigh x shin, + foot lateral (+y) |
//!    | foot        | Toe - Ankle (stance slope)  | knee axis (+y)                             |
//!    | upper arm   | Elbow - Shoulder (+-y)      | forearm, else chest forward (+x)           |
//!    | forearm     | the upper arm swung onto Wrist - Elbow                                   |
//!
//!    The foot's T-pose direction is tilted by the source's own ankle-to-toe slope measured
//!    in stance (the slowest 30% of frames), when the sole is flat: skeletons place those
//!    joints differently, and the humanoid's foot must be flat when the source's is.
//!    Torso and Spine share the pelvis-to-chest rotation in thirds, Neck and Head the
//!    chest-to-head rotation in halves; toes stay level when the heel rises; clavicles,
//!    wrists and hands keep their nominal (zero) angles: the sources do not measure them.
//! 4. Local rotations become the three hinge angles (intrinsic x-y-z Euler, as MuJoCo chains
//!    the hinges). A rotation the ranges do not hold (counted and reported) becomes the
//!    in-range angles whose rotation is nearest it, near the previous frame's: clamping each
//!    angle alone sent an arm raised past the shoulder's range from one end of a range to the
//!    other where the Euler angle wrapped (the hand 0.8 m in a frame).
//! 5. The pelvis sits above the hip centre as in the humanoid; the clip is moved to start at
//!    the origin facing +x, and each frame is lowered or raised by the lowest sole point's
//!    height averaged over 0.2 s, so the stance foot stays on the ground although the
//!    source's legs and feet differ from the humanoid's.

use crate::MotionError;
use crate::clip::Clip;
use crate::landmarks::{Landmark as L, LandmarkClip, Pose};
use flowmimic_geom::{DMat3, DQuat, DVec3, euler_xyz, from_euler_xyz, heading, yaw_quat};
use flowmimic_sim::skeleton::{BODY_PARENTS, BodySpec, NUM_BODIES, bodies, body as b};
use flowmimic_sim::{CONTROL_HZ, Humanoid, NUM_DOFS};
use std::f64::consts::{PI, TAU};

/// Bodies whose joints keep their nominal angles: the sources do not measure them reliably.
const UNMEASURED: [usize; 6] = [b::L_THORAX, b::R_THORAX, b::L_WRIST, b::R_WRIST, b::L_HAND, b::R_HAND];

/// The humanoid's hip-to-ankle length, metres.
fn humanoid_leg(specs: &[BodySpec]) -> f64 {
    specs[2].offset.iter().map(|x| x * x).sum::<f64>().sqrt()
        + specs[3].offset.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// Resamples positions to `CONTROL_HZ` by linear interpolation.
pub fn resample(clip: &LandmarkClip) -> Vec<Pose> {
    let n = clip.frames.len();
    let duration = (n - 1) as f64 / clip.fps;
    // Files round their frame time (".0083333", "0.033332"): a last frame within 1% of a
    // period of the end still counts.
    let count = (duration * CONTROL_HZ + 0.01).floor() as usize + 1;
    (0..count)
        .map(|k| {
            let f = (k as f64 / CONTROL_HZ * clip.fps).min((n - 1) as f64);
            let (i, w) = (f.floor() as usize, f.fract());
            let j = (i + 1).min(n - 1);
            std::array::from_fn(|l| clip.frames[i][l].lerp(clip.frames[j][l], w))
        })
        .collect()
}

fn basis(primary: DVec3, secondary: DVec3) -> Option<DMat3> {
    let x = primary.normalize_or_zero();
    let s = secondary - x * secondary.dot(x);
    if x == DVec3::ZERO || s.length() < 1e-6 {
        return None;
    }
    let y = s.normalize();
    Some(DMat3::from_cols(x, y, x.cross(y)))
}

/// The rotation taking `(d0, s0)` onto `(d, s)`; `fallback` when `s` is parallel to `d`.
fn orient(d: DVec3, s: DVec3, d0: DVec3, s0: DVec3, fallback: DVec3) -> DQuat {
    let b = basis(d, s).or_else(|| basis(d, fallback)).unwrap_or(DMat3::IDENTITY);
    let b0 = basis(d0, s0).expect("reference directions are not parallel");
    DQuat::from_mat3(&(b * b0.transpose())).normalize()
}

/// Median of a list (the lower middle for even lengths).
pub(crate) fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[(xs.len() - 1) / 2]
}

/// Slope of ankle-to-toe below horizontal, radians, in the slowest 30% of frames.
fn stance_foot_slope(frames: &[Pose], ankle: L, toe: L) -> f64 {
    if frames.len() < 3 {
        return 0.0;
    }
    let mut by_speed: Vec<(f64, f64)> = (1..frames.len())
        .map(|t| {
            let speed = (frames[t][ankle] - frames[t - 1][ankle]).length();
            let d = frames[t][toe] - frames[t][ankle];
            (speed, (-d.z).atan2(d.truncate().length()))
        })
        .collect();
    by_speed.sort_by(|a, b| a.0.total_cmp(&b.0));
    let keep = (by_speed.len() * 3 / 10).max(1);
    median(by_speed[..keep].iter().map(|x| x.1).collect())
}

/// The hinge ranges of one joint, radians, and the direction of its bone (toward its first
/// child) in the body's frame.
struct Joint {
    lower: [f64; 3],
    upper: [f64; 3],
    bone: DVec3,
}

/// Weights of the terms of [`Joint::nearest`]'s search: where the bone points (a child's
/// position) counts before how the body turns about it, and nearness to the previous frame's
/// angles keeps a run of frames on one side of a range.
const BONE_WEIGHT: f64 = 3.0;
const CONTINUITY: f64 = 0.1;
/// How much lower (squared radians) another solution's cost must be to leave the previous
/// frame's: without it the angles hop between two about as near (an arm raised past the
/// shoulder's range, 20 m/s hands).
const SWITCH_MARGIN: f64 = 0.5;
/// Gauss-Newton steps of the search for in-range angles.
const NEAREST_STEPS: usize = 20;

impl Joint {
    fn clamp(&self, e: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|k| e[k].clamp(self.lower[k], self.upper[k]))
    }

    /// What the angles `h` miss of the rotation `q`, weighted: the bone's direction, the
    /// rotation (a rotation vector), and the distance to `previous`.
    fn residual(&self, q: DQuat, h: [f64; 3], previous: Option<[f64; 3]>) -> [f64; 9] {
        let r = from_euler_xyz(h);
        let bone = BONE_WEIGHT * (r * self.bone - q * self.bone);
        let mut miss = q.conjugate() * r;
        if miss.w < 0.0 {
            miss = -miss;
        }
        let miss = miss.to_scaled_axis();
        let p = previous.unwrap_or(h);
        let c = CONTINUITY.sqrt();
        [bone.x, bone.y, bone.z, miss.x, miss.y, miss.z, c * (h[0] - p[0]), c * (h[1] - p[1]), c * (h[2] - p[2])]
    }

    fn cost(&self, q: DQuat, h: [f64; 3], previous: Option<[f64; 3]>) -> f64 {
        self.residual(q, h, previous).iter().map(|r| r * r).sum()
    }

    /// In-range hinge angles for the local rotation `q`, and how many of its Euler angles lie
    /// outside the range (0: they are returned as they are). Otherwise a search from the
    /// previous frame's angles, and from the clamped Euler angles of either solution, which win
    /// only by [`SWITCH_MARGIN`].
    fn nearest(&self, q: DQuat, previous: Option<[f64; 3]>) -> ([f64; 3], usize) {
        let e = euler_xyz(q);
        let outside = (0..3).filter(|&k| !(self.lower[k]..=self.upper[k]).contains(&e[k])).count();
        if outside == 0 {
            return (e, 0);
        }
        let wrap = |a: f64| (a + PI).rem_euclid(TAU) - PI;
        // The other Euler solution of the same rotation.
        let other = [wrap(e[0] + PI), wrap(PI - e[1]), wrap(e[2] + PI)];
        let fresh = [e, other]
            .map(|h| self.descend(q, self.clamp(h), previous))
            .into_iter()
            .min_by(|a, b| self.cost(q, *a, previous).total_cmp(&self.cost(q, *b, previous)))
            .expect("two starts");
        let best = match previous.map(|p| self.descend(q, p, previous)) {
            Some(kept) if self.cost(q, kept, previous) <= self.cost(q, fresh, previous) + SWITCH_MARGIN => kept,
            _ => fresh,
        };
        (best, outside)
    }

    /// Projected Gauss-Newton from `h` on [`Joint::residual`], finite-difference Jacobian.
    fn descend(&self, q: DQuat, mut h: [f64; 3], previous: Option<[f64; 3]>) -> [f64; 3] {
        for _ in 0..NEAREST_STEPS {
            let r = self.residual(q, h, previous);
            let jacobian: [[f64; 9]; 3] = std::array::from_fn(|k| {
                let mut shifted = h;
                shifted[k] += 1e-6;
                let rs = self.residual(q, shifted, previous);
                std::array::from_fn(|m| (rs[m] - r[m]) / 1e-6)
            });
            let dot = |a: &[f64; 9], b: &[f64; 9]| (0..9).map(|m| a[m] * b[m]).sum::<f64>();
            let jtj = DMat3::from_cols_array_2d(&std::array::from_fn(|a| {
                std::array::from_fn(|b| dot(&jacobian[a], &jacobian[b]))
            }));
            let jtr = DVec3::from_array(std::array::from_fn(|a| dot(&jacobian[a], &r)));
            let step = (jtj + DMat3::IDENTITY * 1e-6).inverse() * jtr;
            h = self.clamp([h[0] - step.x, h[1] - step.y, h[2] - step.z]);
            if step.length() < 1e-9 {
                break;
            }
        }
        h
    }
}

/// Global body rotations of one pose.
fn body_rotations(p: &Pose, foot_slope: [f64; 2]) -> [DQuat; NUM_BODIES] {
    let (x, y, z) = (DVec3::X, DVec3::Y, DVec3::Z);
    let hip_centre = 0.5 * (p[L::LHip] + p[L::RHip]);
    let pelvis = orient(p[L::LHip] - p[L::RHip], p[L::Chest] - hip_centre, y, z, z);
    let lateral = p[L::LShoulder] - p[L::RShoulder];
    let chest = orient(lateral, p[L::Neck] - p[L::Chest], y, z, pelvis * z);
    let head = orient(p[L::Head] - p[L::Neck], lateral, z, y, chest * y);
    let chest_forward = chest * x;
    let mut r = [DQuat::IDENTITY; NUM_BODIES];
    r[b::PELVIS] = pelvis;
    let spine = pelvis.conjugate() * chest;
    r[b::TORSO] = pelvis * DQuat::IDENTITY.slerp(spine, 1.0 / 3.0);
    r[b::SPINE] = pelvis * DQuat::IDENTITY.slerp(spine, 2.0 / 3.0);
    r[b::CHEST] = chest;
    r[b::NECK] = chest * DQuat::IDENTITY.slerp(chest.conjugate() * head, 0.5);
    r[b::HEAD] = head;
    let legs = [
        ([b::L_HIP, b::L_KNEE, b::L_ANKLE, b::L_TOE], [L::LHip, L::LKnee, L::LAnkle, L::LToe], foot_slope[0]),
        ([b::R_HIP, b::R_KNEE, b::R_ANKLE, b::R_TOE], [L::RHip, L::RKnee, L::RAnkle, L::RToe], foot_slope[1]),
    ];
    for ([thigh, shin, foot, toes], [hip, knee, ankle, toe], slope) in legs {
        let (thigh_dir, shin_dir, foot_dir) = (p[knee] - p[hip], p[ankle] - p[knee], p[toe] - p[ankle]);
        // The knee's hinge axis orients thigh, shin and foot about their long axes. It is the
        // normal of the thigh-shin plane when the knee bends; for a straight leg the foot's
        // lateral axis takes over (the blend is continuous).
        let foot_lateral = z.cross(foot_dir).normalize_or_zero();
        let axis = thigh_dir.normalize_or_zero().cross(shin_dir.normalize_or_zero()) + 0.15 * foot_lateral;
        r[thigh] = orient(thigh_dir, axis, -z, y, pelvis * y);
        r[shin] = orient(shin_dir, axis, -z, y, r[thigh] * y);
        let flat = DVec3::new(slope.cos(), 0.0, -slope.sin());
        r[foot] = orient(foot_dir, axis, flat, y, r[shin] * y);
        // Toes stay level when the heel rises (sources do not measure the toe joint, and a
        // rigid foot would drive its toes into the ground at push-off).
        let forward = r[foot] * x;
        let level = DVec3::new(forward.x, forward.y, forward.z.max(0.0)).normalize_or_zero();
        r[toes] = if level == DVec3::ZERO { r[foot] } else { DQuat::from_rotation_arc(forward, level) * r[foot] };
    }
    let arms = [
        ([b::L_THORAX, b::L_SHOULDER, b::L_ELBOW, b::L_WRIST, b::L_HAND], [L::LShoulder, L::LElbow, L::LWrist], y),
        ([b::R_THORAX, b::R_SHOULDER, b::R_ELBOW, b::R_WRIST, b::R_HAND], [L::RShoulder, L::RElbow, L::RWrist], -y),
    ];
    for ([thorax, upper_arm, forearm, wrist_b, hand], [shoulder, elbow, wrist], outward) in arms {
        r[thorax] = chest;
        let upper = p[elbow] - p[shoulder];
        let fore = p[wrist] - p[elbow];
        r[upper_arm] = orient(upper, fore, outward, x, chest_forward);
        // The forearm is the upper arm bent onto its own direction: a hinge-like elbow.
        let bend = DQuat::from_rotation_arc(upper.normalize_or_zero(), fore.normalize_or_zero());
        r[forearm] = if upper.length() > 1e-9 && fore.length() > 1e-9 { bend * r[upper_arm] } else { r[upper_arm] };
        r[wrist_b] = r[forearm];
        r[hand] = r[forearm];
    }
    r
}

/// How retargeting went.
#[derive(Clone, Debug, Default)]
pub struct RetargetReport {
    /// Source hip-to-ankle length (metres, after unit conversion) divided into the humanoid's.
    pub scale: f64,
    /// Hinge values that had to be clamped to the joint range, as a fraction of all.
    pub clamped: f64,
    /// Median over frames of the height correction applied to the root, metres.
    pub ground_offset: f64,
    /// Where the source's frame went: the clip starts at the origin facing +x.
    pub placement: Placement,
}

/// How retargeting moved the source: scaled by `scale`, shifted by `-start`, turned by `-yaw`
/// about the vertical, and each frame lowered by its height correction.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Placement {
    pub scale: f64,
    pub start: DVec3,
    pub yaw: f64,
    pub lowered: Vec<f64>,
}

impl Placement {
    /// A point of the source at frame `frame` (of the 30 Hz resampling), in the clip's frame.
    pub fn apply(&self, frame: usize, p: DVec3) -> DVec3 {
        yaw_quat(-self.yaw) * (p * self.scale - self.start) - DVec3::Z * self.lowered[frame]
    }
}

/// Retargets landmarks to the humanoid. `cyclic` marks a clip whose last frame repeats its
/// first one step of the loop on.
pub fn retarget(
    humanoid: &std::sync::Arc<Humanoid>,
    source: &LandmarkClip,
    name: &str,
    origin: &str,
    cyclic: bool,
) -> Result<(Clip, RetargetReport), MotionError> {
    if source.frames.len() < 2 || !(source.fps.is_finite() && source.fps > 0.0) {
        return Err(MotionError::Invalid(format!("{name}: a clip needs at least 2 frames and a positive rate")));
    }
    if source.frames.iter().flatten().any(|v| !v.is_finite()) {
        return Err(MotionError::Invalid(format!("{name}: non-finite landmark position")));
    }
    let specs = bodies();
    let mut frames = resample(source);
    let src_leg = median(
        frames
            .iter()
            .map(|p| {
                0.5 * (p[L::LHip].distance(p[L::LKnee])
                    + p[L::LKnee].distance(p[L::LAnkle])
                    + p[L::RHip].distance(p[L::RKnee])
                    + p[L::RKnee].distance(p[L::RAnkle]))
            })
            .collect(),
    );
    let scale = humanoid_leg(&specs) / src_leg;
    if !(0.2..5.0).contains(&scale) {
        return Err(MotionError::Invalid(format!("{name}: leg length {src_leg:.3} m is not a human's (wrong units?)")));
    }
    for p in &mut frames {
        for v in p.iter_mut() {
            *v *= scale;
        }
    }
    let slopes = [stance_foot_slope(&frames, L::LAnkle, L::LToe), stance_foot_slope(&frames, L::RAnkle, L::RToe)];
    let map = humanoid.actions();
    let hip_height = -specs[1].offset[2];
    let (mut clamped, mut qpos) = (0usize, Vec::<Vec<f64>>::with_capacity(frames.len()));
    let joints: Vec<Joint> = (1..NUM_BODIES)
        .map(|body| {
            let i = 3 * (body - 1);
            let child = (0..NUM_BODIES).find(|&c| BODY_PARENTS[c] == Some(body));
            let bone = child.map_or(DVec3::Z, |c| DVec3::from_array(specs[c].offset).normalize_or(DVec3::Z));
            Joint {
                lower: std::array::from_fn(|k| map.lower[i + k]),
                upper: std::array::from_fn(|k| map.upper[i + k]),
                bone,
            }
        })
        .collect();
    for p in &frames {
        let rot = body_rotations(p, slopes);
        let mut hinges = map.q_bar;
        // Each body turns from where its parent's angles put it (a parent out of range moves
        // its children too), the rotations chained down the tree.
        let mut placed = [DQuat::IDENTITY; NUM_BODIES];
        placed[0] = rot[0];
        for body in 1..NUM_BODIES {
            let parent = BODY_PARENTS[body].expect("non-root body");
            let i = 3 * (body - 1);
            if !UNMEASURED.contains(&body) {
                let previous = qpos.last().map(|q| std::array::from_fn(|k| q[7 + i + k]));
                let (angles, outside) = joints[body - 1].nearest(placed[parent].conjugate() * rot[body], previous);
                hinges[i..i + 3].copy_from_slice(&angles);
                clamped += outside;
            }
            placed[body] = placed[parent] * from_euler_xyz([hinges[i], hinges[i + 1], hinges[i + 2]]);
        }
        let root = 0.5 * (p[L::LHip] + p[L::RHip]) + rot[0] * DVec3::new(0.0, 0.0, hip_height);
        let q = rot[0];
        qpos.push(humanoid.qpos(root.to_array(), [q.w, q.x, q.y, q.z], &hinges));
    }
    // Start at the origin facing +x.
    let (start, yaw0) = (DVec3::new(qpos[0][0], qpos[0][1], 0.0), heading(quat_of(&qpos[0])));
    let turn = yaw_quat(-yaw0);
    for q in &mut qpos {
        let p = turn * (DVec3::new(q[0], q[1], q[2]) - start);
        let r = turn * quat_of(q);
        q[..7].copy_from_slice(&[p.x, p.y, p.z, r.w, r.x, r.y, r.z]);
    }
    let lowest = lowest_soles(humanoid, &qpos);
    let ground_offset = median(lowest.clone());
    let lowered = smooth(&lowest, GROUNDING_WINDOW);
    for (q, z) in qpos.iter_mut().zip(&lowered) {
        q[2] -= z;
    }
    let clip = Clip::from_qpos(humanoid, name, origin, cyclic, qpos)?;
    let placement = Placement { scale, start, yaw: yaw0, lowered };
    let report =
        RetargetReport { scale, clamped: clamped as f64 / (frames.len() * NUM_DOFS) as f64, ground_offset, placement };
    Ok((clip, report))
}

pub(crate) fn quat_of(q: &[f64]) -> DQuat {
    flowmimic_geom::quat_from_wxyz([q[3], q[4], q[5], q[6]])
}

/// Frames (at 30 Hz) over which the height correction is averaged: 0.2 s keeps steps, bounces
/// and flight phases and removes the slow drift between the source's feet and the humanoid's.
const GROUNDING_WINDOW: usize = 7;

/// The lowest sole point of each frame.
fn lowest_soles(humanoid: &std::sync::Arc<Humanoid>, qpos: &[Vec<f64>]) -> Vec<f64> {
    let mut env = humanoid.env();
    let zero = vec![0.0; humanoid.nv()];
    qpos.iter()
        .map(|q| {
            env.reset(q, &zero).expect("retargeted pose is finite");
            let [l, r] = env.sole_heights();
            l.min(r)
        })
        .collect()
}

/// Centred moving average over `window` frames (shrinking at the ends).
fn smooth(xs: &[f64], window: usize) -> Vec<f64> {
    let half = window / 2;
    (0..xs.len())
        .map(|i| {
            let span = &xs[i.saturating_sub(half)..(i + half + 1).min(xs.len())];
            span.iter().sum::<f64>() / span.len() as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The right shoulder's ranges (radians) and bone.
    fn shoulder() -> Joint {
        Joint { lower: [-2.094, -1.571, -1.571], upper: [2.094, 1.571, 2.094], bone: DVec3::NEG_Y }
    }

    #[test]
    fn angles_in_range_are_kept_and_a_turn_past_the_range_moves_them_smoothly() {
        let joint = shoulder();
        let q = from_euler_xyz([0.5, -0.3, 1.0]);
        let (h, outside) = joint.nearest(q, None);
        assert_eq!(outside, 0);
        assert!((h[0] - 0.5).abs() < 1e-12 && (h[1] + 0.3).abs() < 1e-12 && (h[2] - 1.0).abs() < 1e-12);
        // An arm raised past the range, shaking: the x angle goes from 100 degrees to 185 and
        // back, 3 degrees of jitter on top, with some swing and twist. The Euler angle wraps at
        // 180, past the range's 120, where the other end of the range is about as near.
        let mut previous: Option<[f64; 3]> = None;
        for k in 0..=120 {
            let a = (100.0 + 85.0 * (PI * k as f64 / 120.0).sin() + 3.0 * (k as f64).sin()).to_radians();
            let q = from_euler_xyz([a, -0.9, 2.3]);
            let (h, _) = joint.nearest(q, previous);
            assert!((0..3).all(|i| (joint.lower[i]..=joint.upper[i]).contains(&h[i])), "frame {k}: {h:?}");
            if let Some(p) = previous {
                let step = (0..3).map(|i| (h[i] - p[i]).abs()).fold(0.0, f64::max);
                assert!(step < 0.3, "frame {k}: the angles jump {step:.2} rad, {p:?} -> {h:?}");
            }
            previous = Some(h);
        }
    }
}
