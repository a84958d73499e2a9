//! Checks on one reference frame that the generator's invariant tests share, made on the
//! humanoid posed as the clip's frame.
#![allow(dead_code)]

use flowmimic_geom::{heading, wrap_angle};
use flowmimic_motion::clip::CONTACT_HEIGHT;
use flowmimic_sim::skeleton::body;
use flowmimic_sim::{BodyKinematics, Env};

const LEFT_LEG: [usize; 4] = [body::L_HIP, body::L_KNEE, body::L_ANKLE, body::L_TOE];
const RIGHT_LEG: [usize; 4] = [body::R_HIP, body::R_KNEE, body::R_ANKLE, body::R_TOE];

/// How far, in degrees, the chest or the head faces from the pelvis, whichever is further.
pub fn upper_body_turn(k: &BodyKinematics) -> f64 {
    let pelvis = heading(k.rot[body::PELVIS]);
    [body::CHEST, body::HEAD]
        .map(|b| wrap_angle(heading(k.rot[b]) - pelvis).to_degrees().abs())
        .into_iter()
        .fold(0.0, f64::max)
}

/// Whether a touching pair of bodies (`Env::self_contacts`) is one leg against the other.
pub fn legs_touch((a, b): (usize, usize)) -> bool {
    (LEFT_LEG.contains(&a) && RIGHT_LEG.contains(&b)) || (RIGHT_LEG.contains(&a) && LEFT_LEG.contains(&b))
}

/// Horizontal speeds of the parts of the feet on the ground (the toe when it is lower, else
/// the foot), for an environment posed at the frame whose kinematics are `k`.
pub fn stance_speeds(env: &Env, k: &BodyKinematics) -> Vec<f64> {
    let mut speeds = Vec::new();
    for (side, [ankle, toe]) in [[body::L_ANKLE, body::L_TOE], [body::R_ANKLE, body::R_TOE]].iter().enumerate() {
        let [heel_z, toe_z] = env.foot_bottoms()[side];
        if heel_z.min(toe_z) < CONTACT_HEIGHT {
            let part = if toe_z < heel_z { *toe } else { *ankle };
            speeds.push(k.lin_vel[part].truncate().length());
        }
    }
    speeds
}
