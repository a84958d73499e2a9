//! The humanoid's mirror image through its sagittal (x-z) plane: left and right swap, positions
//! and velocities flip y, and rotations (rotation vectors, and hinge angles, which turn about the
//! body's x, y and z axes) flip about x and z. The skeleton is built left-right symmetric
//! ([`crate::skeleton`] derives the right side by the same reflection), so the mirror image of a
//! physical motion is one too: mirroring a walking dataset doubles it and balances its left and
//! right turns.

use crate::skeleton::hinge_names;
use crate::state::state_feature_names;
use std::ops::Neg;
use std::sync::OnceLock;

/// A mirror of one vector layout: entry `i` of the image is entry `source[i]`, negated where
/// `flip[i]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Mirror {
    source: Vec<usize>,
    flip: Vec<bool>,
}

impl Mirror {
    /// The 165-d state ([`crate::state`]): `root_pos.y`, `body_vel.L_Knee.x`, `rotvec.R_Hand.z`...
    pub fn state() -> Self {
        Self::from_names(&state_feature_names(), '.', |name| if name.contains("rotvec") { "xz" } else { "y" })
    }

    /// The 69 normalised actions (and hinge angles), `<Body>_<axis>`: the action map is as
    /// symmetric as the skeleton, so the mirrored PD target is the mirrored action's.
    pub fn action() -> Self {
        Self::from_names(&hinge_names(), '_', |_| "xz")
    }

    /// From feature names ending in `<separator><axis>`: each takes the value of its left-right
    /// twin (the name with `L_` and `R_` swapped, or itself), negated along the `flipped` axes.
    fn from_names(names: &[String], separator: char, flipped: impl Fn(&str) -> &'static str) -> Self {
        let twin = |name: &str| {
            let swapped: String = name.replace("L_", "\0").replace("R_", "L_").replace('\0', "R_");
            names.iter().position(|n| *n == swapped).expect("every feature has a left-right twin")
        };
        Self {
            source: names.iter().map(|n| twin(n)).collect(),
            flip: names
                .iter()
                .map(|n| n.rsplit(separator).next().is_some_and(|axis| flipped(n).contains(axis)))
                .collect(),
        }
    }

    /// The image of `x`, one row of this layout.
    pub fn apply<T: Copy + Neg<Output = T>>(&self, x: &[T]) -> Vec<T> {
        self.source.iter().zip(&self.flip).map(|(&s, &f)| if f { -x[s] } else { x[s] }).collect()
    }

    /// The mirror image of a pose: `qpos` (root position, root quaternion `w, x, y, z`, 69
    /// hinge angles).
    pub fn qpos(qpos: &[f64]) -> Vec<f64> {
        Self::root_and_hinges(qpos, [1, 4, 6], 7)
    }

    /// The mirror image of a pose's velocity: `qvel` (root linear and angular velocity, 69
    /// hinge rates).
    pub fn qvel(qvel: &[f64]) -> Vec<f64> {
        Self::root_and_hinges(qvel, [1, 3, 5], 6)
    }

    /// The root's `flipped` entries negated, the hinges from `hinges` on as the actions are.
    fn root_and_hinges(x: &[f64], flipped: [usize; 3], hinges: usize) -> Vec<f64> {
        // Built from the names once, not for every frame of a clip.
        static ACTION: OnceLock<Mirror> = OnceLock::new();
        let mut image = x.to_vec();
        flipped.iter().for_each(|&i| image[i] = -x[i]);
        image[hinges..].copy_from_slice(&ACTION.get_or_init(Self::action).apply(&x[hinges..]));
        image
    }

    /// The image of every row of `rows` (rows of this layout, one after another), in place.
    pub fn apply_rows<T: Copy + Neg<Output = T>>(&self, rows: &mut [T]) {
        for row in rows.chunks_mut(self.source.len()) {
            let image = self.apply(row);
            row.copy_from_slice(&image);
        }
    }
}
