//! Which joint of a BVH skeleton gives each landmark, found from the skeleton's structure and
//! its motion, with names to confirm and break ties.
//!
//! Structure: the pelvis is the first joint below the root where three long chains meet (two
//! legs and the spine); the spine runs to the chest, the next joint where three meet (the neck
//! and two arms); the neck chain is the one that continues the spine's direction. Along a leg,
//! after dropping joints with no length and twist bones (joints that never bend over the clip),
//! the thigh and shin are the two consecutive segments that are longest together: hip, knee and
//! ankle are their ends, the toe the next joint (or the foot's End Site). Arms likewise give
//! shoulder, elbow and wrist; the head is the neck chain's last joint and the neck the one
//! before. Left is where the body's left is: up (pelvis to chest) crossed with forward (heel to
//! toe), averaged over the clip, so swapped or missing side names cannot mislead it.
//!
//! Names: side markers as prefix or suffix (`Left`, `L_`, `_L`, `.L`, `l`...) and synonyms
//! (`thigh`/`upleg`/`upperleg`, `shin`/`leg`/`lowerleg`/`calf`, ...). Where structure and names
//! agree the landmark is `structure+name`; where they differ, structure wins; a skeleton whose
//! structure cannot be read falls back on names alone. `--map FILE.toml` forces any landmark.

use crate::bvh::Bvh;
use crate::landmarks::{LANDMARK_NAMES, Landmark, LandmarkError, NUM_LANDMARKS};
use flowmimic_geom::DVec3;
use std::collections::BTreeMap;

/// Where a landmark is read from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Joint(usize),
    /// The End Site below a joint (a toe when the file has no toe joint).
    EndSite(usize),
}

/// How a landmark's joint was chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Evidence {
    /// The structure found it and the joint's name says so too.
    StructureAndName,
    /// The structure found it; the name says nothing (or something else, ignored).
    Structure,
    /// The structure could not be read; the name alone.
    Name,
    /// Given by the user's map.
    Forced,
}

impl std::fmt::Display for Evidence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Evidence::StructureAndName => "structure+name",
            Evidence::Structure => "structure",
            Evidence::Name => "name",
            Evidence::Forced => "forced",
        })
    }
}

/// The joint of each landmark, in [`LANDMARK_NAMES`] order, and how it was found.
#[derive(Clone, Debug, PartialEq)]
pub struct JointMap {
    pub sources: [Source; NUM_LANDMARKS],
    pub evidence: [Evidence; NUM_LANDMARKS],
    /// What the structural reading could not do, when it fell back on names.
    pub note: Option<String>,
}

impl JointMap {
    /// `landmark -> joint (evidence)` lines for printing.
    pub fn describe(&self, bvh: &Bvh) -> Vec<String> {
        (0..NUM_LANDMARKS)
            .map(|i| {
                let joint = match self.sources[i] {
                    Source::Joint(j) => bvh.joints[j].name.clone(),
                    Source::EndSite(j) => format!("{} (End Site)", bvh.joints[j].name),
                };
                format!("{:<11} {:<28} {}", LANDMARK_NAMES[i], joint, self.evidence[i])
            })
            .collect()
    }
}

/// A user's map: landmark name (`L_Hip`, ...) to joint name; a joint name ending in
/// `/end` means that joint's End Site.
pub type ForcedMap = BTreeMap<String, String>;

/// Maps a skeleton's joints to the landmarks (see the module docs).
pub fn map_joints(bvh: &Bvh, forced: Option<&ForcedMap>) -> Result<JointMap, LandmarkError> {
    let by_name = name_map(bvh);
    let (mut sources, mut evidence, note) = match structure_map(bvh) {
        Ok(sources) => {
            let evidence = std::array::from_fn(|i| {
                if by_name[i] == Some(sources[i]) { Evidence::StructureAndName } else { Evidence::Structure }
            });
            (sources.map(Some), evidence, None)
        }
        Err(why) => (by_name, [Evidence::Name; NUM_LANDMARKS], Some(why)),
    };
    for (landmark, joint) in forced.into_iter().flatten() {
        let i = LANDMARK_NAMES.iter().position(|n| n.eq_ignore_ascii_case(landmark)).ok_or_else(|| {
            LandmarkError::Format(format!("map: '{landmark}' is not a landmark ({})", LANDMARK_NAMES.join(", ")))
        })?;
        let (name, end) = match joint.strip_suffix("/end") {
            Some(n) => (n, true),
            None => (joint.as_str(), false),
        };
        let j = bvh.joint(name).ok_or_else(|| {
            LandmarkError::Format(format!("map: {landmark} = '{name}', but the file has no such joint"))
        })?;
        if end && bvh.joints[j].end_site.is_none() {
            return Err(LandmarkError::Format(format!("map: {landmark} = '{joint}', but {name} has no End Site")));
        }
        sources[i] = Some(if end { Source::EndSite(j) } else { Source::Joint(j) });
        evidence[i] = Evidence::Forced;
    }
    let joints = || bvh.joints.iter().map(|j| j.name.as_str()).collect::<Vec<_>>().join(", ");
    let mut out = [Source::Joint(0); NUM_LANDMARKS];
    for i in 0..NUM_LANDMARKS {
        out[i] = sources[i].ok_or_else(|| LandmarkError::MissingJoint {
            landmark: LANDMARK_NAMES[i],
            tried: format!(
                "the skeleton's structure, which has {}, and joint names",
                note.as_deref().unwrap_or("no such joint")
            ),
            joints: joints(),
        })?;
    }
    Ok(JointMap { sources: out, evidence, note })
}

// ----- names -----

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    Left,
    Right,
}

/// Lower case without `_ - . space` and without a `namespace:` prefix.
pub(crate) fn normalise(name: &str) -> String {
    let name = name.rsplit(':').next().unwrap_or(name);
    name.chars().filter(|c| !matches!(c, '_' | '-' | ' ' | '.')).flat_map(char::to_lowercase).collect()
}

/// Every way to read a joint name as a side marker (prefix or suffix) and the rest: "legl" is
/// both a left "leg" and an unsided "legl"; the synonyms decide which reading names a landmark.
fn readings(name: &str) -> Vec<(Option<Side>, String)> {
    let n = normalise(name);
    let mut out = vec![(None, n.clone())];
    for (marks, side) in [(["left", "lft", "l"], Side::Left), (["right", "rgt", "r"], Side::Right)] {
        for m in marks {
            for rest in [n.strip_prefix(m), n.strip_suffix(m)].into_iter().flatten() {
                if rest.len() >= 2 {
                    out.push((Some(side), rest.to_string()));
                }
            }
        }
    }
    out
}

/// Names a landmark's joint goes by, most specific first (without the side).
fn synonyms(l: Landmark) -> &'static [&'static str] {
    use Landmark::*;
    match l {
        LHip | RHip => &["upleg", "upperleg", "thigh", "hip", "femur"],
        LKnee | RKnee => &["leg", "lowerleg", "shin", "calf", "knee", "tibia"],
        LAnkle | RAnkle => &["foot", "ankle"],
        LToe | RToe => &["toebase", "toe", "toes", "ball"],
        LShoulder | RShoulder => &["arm", "upperarm", "humerus", "shoulder"],
        LElbow | RElbow => &["forearm", "lowerarm", "elbow"],
        LWrist | RWrist => &["hand", "wrist"],
        Chest => &["chest", "spine3", "spine2", "spine1", "upperchest", "spine"],
        Neck => &["neck1", "neck"],
        Head => &["head"],
    }
}

fn side_of_landmark(l: Landmark) -> Option<Side> {
    let name = LANDMARK_NAMES[l as usize];
    if name.starts_with("L_") {
        Some(Side::Left)
    } else if name.starts_with("R_") {
        Some(Side::Right)
    } else {
        None
    }
}

/// The joint each landmark's name points to, where one does. A foot with no toe joint gives
/// its End Site.
fn name_map(bvh: &Bvh) -> [Option<Source>; NUM_LANDMARKS] {
    let read: Vec<Vec<(Option<Side>, String)>> = bvh.joints.iter().map(|j| readings(&j.name)).collect();
    let find = |l: Landmark| -> Option<usize> {
        let side = side_of_landmark(l);
        synonyms(l).iter().find_map(|syn| read.iter().position(|r| r.iter().any(|(s, base)| *s == side && base == syn)))
    };
    let mut out = [None; NUM_LANDMARKS];
    for (i, &l) in ALL_LANDMARKS.iter().enumerate() {
        out[i] = find(l).map(Source::Joint);
    }
    for (toe, ankle) in [(Landmark::LToe, Landmark::LAnkle), (Landmark::RToe, Landmark::RAnkle)] {
        if out[toe as usize].is_none() {
            out[toe as usize] = find(ankle).filter(|&a| bvh.joints[a].end_site.is_some()).map(Source::EndSite);
        }
    }
    out
}

pub(crate) const ALL_LANDMARKS: [Landmark; NUM_LANDMARKS] = {
    use Landmark::*;
    [
        LHip, RHip, LKnee, RKnee, LAnkle, RAnkle, LToe, RToe, Chest, Neck, Head, LShoulder, RShoulder, LElbow, RElbow,
        LWrist, RWrist,
    ]
};

// ----- structure -----

/// Joint positions of a few frames spread over the clip (file units and axes), with the End
/// Sites after the joints: point `joints + j` is joint j's End Site (its own position if none).
struct Posed {
    frames: Vec<Vec<DVec3>>,
    joints: usize,
}

impl Posed {
    fn new(bvh: &Bvh) -> Self {
        let n = bvh.frames();
        let picks: Vec<usize> = (0..n.min(24)).map(|k| k * n / n.min(24)).collect();
        let frames = picks
            .iter()
            .map(|&f| {
                let (pos, rot) = bvh.global_pose(f);
                let ends: Vec<DVec3> =
                    (0..pos.len()).map(|j| pos[j] + rot[j] * bvh.joints[j].end_site.unwrap_or_default()).collect();
                pos.into_iter().chain(ends).collect()
            })
            .collect();
        Self { frames, joints: bvh.joints.len() }
    }

    fn at(&self, point: usize) -> DVec3 {
        self.frames[0][point]
    }

    fn mean(&self, f: impl Fn(&[DVec3]) -> DVec3) -> DVec3 {
        self.frames.iter().map(|p| f(p)).sum::<DVec3>() / self.frames.len() as f64
    }
}

struct Tree<'a> {
    bvh: &'a Bvh,
    children: Vec<Vec<usize>>,
    posed: Posed,
    /// Size of the skeleton (largest distance between two joints), for "long" and "short".
    size: f64,
}

impl<'a> Tree<'a> {
    fn new(bvh: &'a Bvh) -> Self {
        let mut children = vec![Vec::new(); bvh.joints.len()];
        for (j, joint) in bvh.joints.iter().enumerate() {
            if let Some(p) = joint.parent {
                children[p].push(j);
            }
        }
        let posed = Posed::new(bvh);
        let p = &posed.frames[0];
        let size = p.iter().flat_map(|a| p.iter().map(move |b| a.distance(*b))).fold(0.0, f64::max);
        Self { bvh, children, posed, size }
    }

    /// The farthest any point below `j` (End Sites included) lies from `j`.
    fn reach(&self, j: usize) -> f64 {
        let here = self.posed.at(j);
        let mut best = self.posed.at(self.posed.joints + j).distance(here);
        let mut stack = self.children[j].clone();
        while let Some(k) = stack.pop() {
            best = best.max(self.posed.at(k).distance(here)).max(self.posed.at(self.posed.joints + k).distance(here));
            stack.extend(&self.children[k]);
        }
        best
    }

    /// Children that start a long chain (longer than a tenth of the skeleton: not fingers,
    /// toes or helper bones), farthest-reaching first.
    fn long_children(&self, j: usize) -> Vec<usize> {
        let mut c: Vec<(f64, usize)> = self.children[j]
            .iter()
            .map(|&k| (self.reach(k) + self.posed.at(k).distance(self.posed.at(j)), k))
            .filter(|(r, _)| *r > 0.1 * self.size)
            .collect();
        c.sort_by(|a, b| b.0.total_cmp(&a.0));
        c.into_iter().map(|(_, k)| k).collect()
    }

    fn subtree_len(&self, j: usize) -> usize {
        1 + self.children[j].iter().map(|&k| self.subtree_len(k)).sum::<usize>()
    }

    /// The first joint at or below `from` (through single long children) where three or more
    /// long chains start.
    fn branch_below(&self, from: usize) -> Option<usize> {
        let mut j = from;
        loop {
            match self.long_children(j)[..] {
                [only] => j = only,
                [_, _, _, ..] => return Some(j),
                _ => return None,
            }
        }
    }

    /// The chain of points from `parent` down through `first`, always into the child that
    /// reaches farthest, ending with the last joint's End Site if it has one.
    fn chain(&self, parent: usize, first: usize) -> Vec<usize> {
        let mut points = vec![parent, first];
        let mut j = first;
        while let Some(&next) = self.children[j].iter().max_by(|&&a, &&b| self.reach(a).total_cmp(&self.reach(b))) {
            points.push(next);
            j = next;
        }
        if self.bvh.joints[j].end_site.is_some() {
            points.push(self.posed.joints + j);
        }
        points
    }

    /// The chain's points that matter: without those at the same place as the previous one,
    /// and without twist bones (points that never bend over the clip).
    fn major(&self, chain: &[usize]) -> Vec<usize> {
        let mut kept: Vec<usize> = vec![chain[0]];
        for &p in &chain[1..] {
            if self.posed.at(p).distance(self.posed.at(*kept.last().expect("non-empty"))) > 0.01 * self.size {
                kept.push(p);
            }
        }
        let bends = |a: usize, b: usize, c: usize| -> f64 {
            self.posed.frames.iter().map(|f| (f[b] - f[a]).angle_between(f[c] - f[b]).to_degrees()).fold(0.0, f64::max)
        };
        let mut k = 1;
        while k + 1 < kept.len() {
            if bends(kept[k - 1], kept[k], kept[k + 1]) < 3.0 {
                kept.remove(k);
            } else {
                k += 1;
            }
        }
        kept
    }

    /// The limb's root, middle and end joint (hip, knee, ankle; shoulder, elbow, wrist): the end
    /// is the first major point below which everything lies within `extremity` (a share of the
    /// skeleton's size: a hand is about 0.06 of it and a forearm with its hand 0.15; a foot 0.13
    /// and a shin with its foot 0.35), the middle and root the two major points before it. Also
    /// the index of the end in `points`.
    fn limb(&self, points: &[usize], extremity: f64) -> Option<([usize; 3], usize)> {
        let reach = |q: usize| if q < self.posed.joints { self.reach(q) } else { 0.0 };
        let end = (2..points.len()).find(|&k| reach(points[k]) < extremity * self.size)?;
        Some(([points[end - 2], points[end - 1], points[end]], end))
    }

    fn source(&self, point: usize) -> Source {
        if point >= self.posed.joints { Source::EndSite(point - self.posed.joints) } else { Source::Joint(point) }
    }
}

/// Largest reach below the wrist and the ankle, as shares of the skeleton's size (see
/// [`Tree::limb`]).
const HAND: f64 = 0.1;
const FOOT: f64 = 0.22;

/// The structural reading (see the module docs), or why it failed.
fn structure_map(bvh: &Bvh) -> Result<[Source; NUM_LANDMARKS], String> {
    let tree = Tree::new(bvh);
    let root = bvh.joints.iter().position(|j| j.parent.is_none()).ok_or("the skeleton has no root")?;
    let pelvis = tree.branch_below(root).ok_or("no joint where two legs and a spine meet")?;
    let mut from_pelvis = tree.long_children(pelvis);
    // The spine carries the arms and head: the largest subtree.
    from_pelvis.sort_by_key(|&k| std::cmp::Reverse(tree.subtree_len(k)));
    let (spine, legs) = (from_pelvis[0], [from_pelvis[1], from_pelvis[2]]);
    // Legs hang away from the spine (else this is the chest of a skeleton without legs).
    let centre = |k: usize| {
        let mut sum = (DVec3::ZERO, 0.0);
        let mut stack = vec![k];
        while let Some(j) = stack.pop() {
            sum = (sum.0 + tree.posed.at(j), sum.1 + 1.0);
            stack.extend(&tree.children[j]);
        }
        sum.0 / sum.1 - tree.posed.at(pelvis)
    };
    let cos = |a: DVec3, b: DVec3| a.normalize_or_zero().dot(b.normalize_or_zero());
    if legs.iter().any(|&l| cos(centre(l), centre(spine)) > -0.5) {
        return Err(format!(
            "no legs: the first joint where three long chains meet ({}) has no two pointing away from the third",
            bvh.joints[pelvis].name
        ));
    }
    let chest = tree.branch_below(spine).ok_or("no joint where the neck and two arms meet")?;
    let p = tree.posed.joints;
    let up = tree.posed.mean(|f| (f[chest] - f[pelvis]).normalize_or_zero()).normalize_or_zero();
    // The neck continues the spine; the arms are the two longest of the others.
    let mut from_chest = tree.long_children(chest);
    let neck_at = from_chest
        .iter()
        .enumerate()
        .max_by(|a, b| {
            let d =
                |k: usize| (tree.posed.at(k) + tree.posed.at(p + k) - 2.0 * tree.posed.at(chest)).normalize_or_zero();
            d(*a.1).dot(up).total_cmp(&d(*b.1).dot(up))
        })
        .map(|(i, _)| i)
        .ok_or("the chest has no children")?;
    let neck_chain = from_chest.remove(neck_at);
    if from_chest.len() < 2 {
        return Err("the chest has fewer than two arms".into());
    }
    let arms = [from_chest[0], from_chest[1]];
    let read_limb = |parent: usize, first: usize, with_toe: bool| -> Result<[usize; 4], String> {
        let points = tree.major(&tree.chain(parent, first));
        let extremity = if with_toe { FOOT } else { HAND };
        let ([a, b, c], end) =
            tree.limb(&points, extremity).ok_or("a limb without two segments above a hand or foot")?;
        if a == parent {
            return Err("a limb whose first segment starts at the pelvis or chest".into());
        }
        let toe = if with_toe { *points.get(end + 1).ok_or("a leg without a foot")? } else { c };
        Ok([a, b, c, toe])
    };
    let leg = |k: usize| read_limb(pelvis, legs[k], true);
    let arm = |k: usize| read_limb(chest, arms[k], false);
    let (leg0, leg1, arm0, arm1) = (leg(0)?, leg(1)?, arm(0)?, arm(1)?);
    // Forward: from the ankles to the toes; left = up x forward.
    let forward = tree.posed.mean(|f| {
        let d = f[leg0[3]] - f[leg0[2]] + f[leg1[3]] - f[leg1[2]];
        (d - up * d.dot(up)).normalize_or_zero()
    });
    let left = up.cross(forward).normalize_or_zero();
    if left == DVec3::ZERO {
        return Err("cannot tell forward from the feet".into());
    }
    let side = |point: usize| (tree.posed.mean(|f| f[point] - f[pelvis])).dot(left);
    let (left_leg, right_leg) = if side(leg0[0]) > side(leg1[0]) { (leg0, leg1) } else { (leg1, leg0) };
    let (left_arm, right_arm) = if side(arm0[0]) > side(arm1[0]) { (arm0, arm1) } else { (arm1, arm0) };
    // Head: the neck chain's joint named so, else its last joint; neck: the joint before it
    // (skipping joints at the same place).
    let joints: Vec<usize> = tree.chain(chest, neck_chain).into_iter().filter(|&q| q < p && q != chest).collect();
    let head_at = joints
        .iter()
        .position(|&j| normalise(&bvh.joints[j].name) == "head")
        .or(joints.len().checked_sub(1))
        .ok_or("the neck chain is empty")?;
    let head = joints[head_at];
    let neck = *joints[..head_at]
        .iter()
        .rev()
        .find(|&&j| tree.posed.at(j).distance(tree.posed.at(head)) > 0.01 * tree.size)
        .ok_or("the head sits directly on the chest")?;
    let s = |q: usize| tree.source(q);
    Ok([
        s(left_leg[0]),
        s(right_leg[0]),
        s(left_leg[1]),
        s(right_leg[1]),
        s(left_leg[2]),
        s(right_leg[2]),
        s(left_leg[3]),
        s(right_leg[3]),
        s(chest),
        s(neck),
        s(head),
        s(left_arm[0]),
        s(right_arm[0]),
        s(left_arm[1]),
        s(right_arm[1]),
        s(left_arm[2]),
        s(right_arm[2]),
    ])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_markers_and_synonyms_are_read() {
        let has = |name: &str, side: Option<Side>, base: &str| readings(name).contains(&(side, base.to_string()));
        assert!(has("UpperLeg_L", Some(Side::Left), "upperleg"));
        assert!(has("LowerLeg_L", Some(Side::Left), "lowerleg"));
        assert!(has("mixamorig:RightForeArm", Some(Side::Right), "forearm"));
        assert!(has("thigh.r", Some(Side::Right), "thigh"));
        assert!(has("L_Knee", Some(Side::Left), "knee"));
        assert!(has("Spine1", None, "spine1"));
        assert_eq!(side_of_landmark(Landmark::LHip), Some(Side::Left));
        assert_eq!(side_of_landmark(Landmark::RWrist), Some(Side::Right));
        assert_eq!(side_of_landmark(Landmark::Head), None);
    }
}
