//! The 165-d character-frame state (docs/conventions.md, section 2; paper section IV-A).
//!
//! | range     | what                                                                        |
//! |-----------|-----------------------------------------------------------------------------|
//! | 0..3      | root position in the frame `F`: x, y from `F`'s origin; z the height above the ground |
//! | 3..6      | root linear velocity in `F`                                                  |
//! | 6..9      | root orientation in `F`, rotation vector                                     |
//! | 9..81     | 24 body positions in the step's own character frame (pelvis first)          |
//! | 81..153   | 24 body linear velocities minus the root's, in the own frame                |
//! | 153..165  | rotation vectors of L_Hand, R_Hand, L_Ankle, R_Ankle in the own frame       |
//!
//! `F` is the character frame of the *current* control step: for the state of step t itself
//! it is its own frame (root x, y = 0, yaw = 0); for a future step it carries the planned
//! displacement and turn, which joystick and waypoint guidance read. The root height is kept
//! absolute because the paper's origin-at-the-root convention would make it always zero and
//! the model could not see the character sink.

use crate::skeleton::{BODY_NAMES, NUM_BODIES, body};
use flowmimic_geom::{CharFrame, DQuat, DVec3, rotvec};

/// Dimension of the state vector.
pub const STATE_DIM: usize = 165;
/// Offsets of the blocks of the state vector.
pub mod offset {
    pub const ROOT_POS: usize = 0;
    pub const ROOT_VEL: usize = 3;
    pub const ROOT_ROT: usize = 6;
    pub const BODY_POS: usize = 9;
    pub const BODY_VEL: usize = 81;
    pub const END_ROT: usize = 153;
}
/// Bodies whose orientation is part of the state, in order.
pub const ROTATION_BODIES: [usize; 4] = [body::L_HAND, body::R_HAND, body::L_ANKLE, body::R_ANKLE];

/// World-frame kinematics of all bodies at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct BodyKinematics {
    /// Body frame origins (joint centres), world.
    pub pos: [DVec3; NUM_BODIES],
    /// Body orientations, world.
    pub rot: [DQuat; NUM_BODIES],
    /// Linear velocities of the body frame origins, world.
    pub lin_vel: [DVec3; NUM_BODIES],
    /// Angular velocities, world.
    pub ang_vel: [DVec3; NUM_BODIES],
}

impl BodyKinematics {
    /// The character frame of this pose.
    pub fn frame(&self) -> CharFrame {
        CharFrame::from_root(self.pos[body::PELVIS], self.rot[body::PELVIS])
    }

    /// The state with its global part in `frame` (its own frame for the current step).
    pub fn state_in(&self, frame: &CharFrame) -> [f32; STATE_DIM] {
        let mut s = [0f32; STATE_DIM];
        let mut put = |at: usize, v: DVec3| {
            s[at] = v.x as f32;
            s[at + 1] = v.y as f32;
            s[at + 2] = v.z as f32;
        };
        let root = body::PELVIS;
        let p = frame.point(self.pos[root]);
        put(offset::ROOT_POS, DVec3::new(p.x, p.y, self.pos[root].z));
        put(offset::ROOT_VEL, frame.vector(self.lin_vel[root]));
        put(offset::ROOT_ROT, rotvec(frame.rotation(self.rot[root])));
        let own = self.frame();
        for b in 0..NUM_BODIES {
            put(offset::BODY_POS + 3 * b, own.point(self.pos[b]));
            put(offset::BODY_VEL + 3 * b, own.vector(self.lin_vel[b] - self.lin_vel[root]));
        }
        for (k, &b) in ROTATION_BODIES.iter().enumerate() {
            put(offset::END_ROT + 3 * k, rotvec(own.rotation(self.rot[b])));
        }
        s
    }

    /// The state in its own character frame.
    pub fn state(&self) -> [f32; STATE_DIM] {
        self.state_in(&self.frame())
    }
}

/// A name for each of the 165 state features, e.g. `root_pos.x`, `body_vel.L_Knee.z`.
pub fn state_feature_names() -> Vec<String> {
    let xyz = ["x", "y", "z"];
    let mut names: Vec<String> = Vec::with_capacity(STATE_DIM);
    for block in ["root_pos", "root_vel", "root_rotvec"] {
        names.extend(xyz.iter().map(|a| format!("{block}.{a}")));
    }
    for block in ["body_pos", "body_vel"] {
        for b in BODY_NAMES {
            names.extend(xyz.iter().map(|a| format!("{block}.{b}.{a}")));
        }
    }
    for &b in &ROTATION_BODIES {
        names.extend(xyz.iter().map(|a| format!("rotvec.{}.{a}", BODY_NAMES[b])));
    }
    names
}
