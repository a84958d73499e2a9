//! Rotations and character frames: the one place where flowmimic does 3-D math.
//!
//! Conventions (docs/conventions.md, section 1): z up, right-handed, metres and radians, quaternions
//! stored as `(w, x, y, z)` like MuJoCo. Internally we use `glam`'s `DQuat`/`DVec3`; the
//! `*_wxyz` helpers convert at the boundary to MuJoCo arrays.
//!
//! The character frame `C` of a pose has its origin at the root (pelvis), its x axis along
//! the root's facing direction projected on the ground (yaw only) and z up:
//! `C_p = R_yaw^T (W_p - W_p_root)` and `C_v = R_yaw^T (W_v - W_v_root)` (paper eqs. 4-5).

pub use glam::{DMat3, DQuat, DVec2, DVec3};

/// A quaternion from MuJoCo's `(w, x, y, z)` layout.
pub fn quat_from_wxyz(q: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(q[1], q[2], q[3], q[0])
}

/// A quaternion in MuJoCo's `(w, x, y, z)` layout.
pub fn quat_to_wxyz(q: DQuat) -> [f64; 4] {
    [q.w, q.x, q.y, q.z]
}

/// Heading angle of a rotation: the yaw of its x axis projected on the ground plane.
///
/// Well defined unless the x axis points straight up or down (then it returns 0).
pub fn heading(q: DQuat) -> f64 {
    let x = q * DVec3::X;
    if x.x.abs() < 1e-12 && x.y.abs() < 1e-12 { 0.0 } else { x.y.atan2(x.x) }
}

/// The rotation about z by `yaw` radians.
pub fn yaw_quat(yaw: f64) -> DQuat {
    DQuat::from_rotation_z(yaw)
}

/// Wraps an angle to `(-pi, pi]`.
pub fn wrap_angle(a: f64) -> f64 {
    let r = a.rem_euclid(std::f64::consts::TAU);
    if r > std::f64::consts::PI { r - std::f64::consts::TAU } else { r }
}

/// Rotation vector (axis times angle, angle in `[0, pi]`) of a unit quaternion.
pub fn rotvec(q: DQuat) -> DVec3 {
    // Pick the hemisphere with w >= 0 so the angle is the short way round.
    let q = if q.w < 0.0 { -q } else { q };
    let s = q.xyz().length();
    if s < 1e-12 {
        // Small-angle limit: angle * axis ~= 2 * vector part.
        return 2.0 * q.xyz();
    }
    let angle = 2.0 * s.atan2(q.w);
    q.xyz() * (angle / s)
}

/// The unit quaternion of a rotation vector.
pub fn from_rotvec(v: DVec3) -> DQuat {
    let angle = v.length();
    if angle < 1e-12 {
        return DQuat::from_xyzw(0.5 * v.x, 0.5 * v.y, 0.5 * v.z, 1.0).normalize();
    }
    DQuat::from_axis_angle(v / angle, angle)
}

/// Intrinsic x-y-z Euler angles `[a, b, c]` with `q = Rx(a) * Ry(b) * Rz(c)`.
///
/// This is how MuJoCo composes three hinges x, y, z listed in that order in one body, so it
/// turns a joint's local rotation into the humanoid's three hinge angles. `b` lies in
/// `[-pi/2, pi/2]`; at `|b| = pi/2` (gimbal lock) `c` is set to 0.
pub fn euler_xyz(q: DQuat) -> [f64; 3] {
    let m = glam::DMat3::from_quat(q.normalize());
    // R = Rx Ry Rz: R[0][2] = sin b, R[1][2] = -sin a cos b, R[2][2] = cos a cos b,
    // R[0][1] = -cos b sin c, R[0][0] = cos b cos c (row-major indices).
    let (r00, r01, r02) = (m.x_axis.x, m.y_axis.x, m.z_axis.x);
    let (r12, r22) = (m.z_axis.y, m.z_axis.z);
    let b = r02.clamp(-1.0, 1.0).asin();
    if r02.abs() < 1.0 - 1e-9 {
        let a = (-r12).atan2(r22);
        let c = (-r01).atan2(r00);
        [a, b, c]
    } else {
        // Gimbal lock: only a +/- c is determined; put it all in a.
        let (r10, r11) = (m.x_axis.y, m.y_axis.y);
        [r10.atan2(r11), b, 0.0]
    }
}

/// The rotation `Rx(a) * Ry(b) * Rz(c)` of intrinsic x-y-z Euler angles.
pub fn from_euler_xyz(e: [f64; 3]) -> DQuat {
    DQuat::from_rotation_x(e[0]) * DQuat::from_rotation_y(e[1]) * DQuat::from_rotation_z(e[2])
}

/// The character frame of a pose: origin at the root, yaw-only rotation, z up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CharFrame {
    /// World position of the origin (the root).
    pub origin: DVec3,
    /// Heading of the root in the world, radians.
    pub yaw: f64,
    inverse: DQuat,
}

impl CharFrame {
    /// The character frame of a root at `root_pos` with orientation `root_rot`.
    pub fn from_root(root_pos: DVec3, root_rot: DQuat) -> Self {
        Self::new(root_pos, heading(root_rot))
    }

    /// A frame with the given origin and heading.
    pub fn new(origin: DVec3, yaw: f64) -> Self {
        Self { origin, yaw, inverse: yaw_quat(-yaw) }
    }

    /// `C_p = R_yaw^T (W_p - origin)`.
    pub fn point(&self, world: DVec3) -> DVec3 {
        self.inverse * (world - self.origin)
    }

    /// `R_yaw^T v`: a direction or velocity, no translation.
    pub fn vector(&self, world: DVec3) -> DVec3 {
        self.inverse * world
    }

    /// `R_yaw^T R`: an orientation expressed in this frame.
    pub fn rotation(&self, world: DQuat) -> DQuat {
        self.inverse * world
    }

    /// Inverse of [`CharFrame::point`].
    pub fn point_to_world(&self, local: DVec3) -> DVec3 {
        self.inverse.conjugate() * local + self.origin
    }

    /// Inverse of [`CharFrame::vector`].
    pub fn vector_to_world(&self, local: DVec3) -> DVec3 {
        self.inverse.conjugate() * local
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn close(a: DVec3, b: DVec3, tol: f64) -> bool {
        (a - b).length() < tol
    }

    fn sample_quats() -> Vec<DQuat> {
        let mut out = vec![DQuat::IDENTITY];
        // A deterministic spread of rotations, including near-gimbal and near-pi cases.
        for i in 0..40 {
            let t = i as f64;
            let axis = DVec3::new((1.3 * t).sin(), (0.7 * t + 1.0).cos(), (0.31 * t).sin() + 0.2);
            out.push(DQuat::from_axis_angle(axis.normalize(), (0.37 * t) % (2.0 * PI) - PI));
        }
        out.push(from_euler_xyz([0.3, PI / 2.0 - 1e-7, 0.2]));
        out.push(DQuat::from_axis_angle(DVec3::Z, PI - 1e-9));
        out
    }

    #[test]
    fn wxyz_round_trip_matches_mujoco_layout() {
        let q = DQuat::from_axis_angle(DVec3::Z, 0.5);
        let w = quat_to_wxyz(q);
        assert!((w[0] - (0.25f64).cos()).abs() < 1e-12);
        assert!((w[3] - (0.25f64).sin()).abs() < 1e-12);
        assert_eq!(quat_from_wxyz(w), q);
    }

    #[test]
    fn rotvec_round_trip() {
        for q in sample_quats() {
            let v = rotvec(q);
            assert!(v.length() <= PI + 1e-9);
            let back = from_rotvec(v);
            assert!(back.dot(q).abs() > 1.0 - 1e-9, "{q:?} -> {v:?} -> {back:?}");
        }
        assert!(close(rotvec(DQuat::from_rotation_y(0.4)), DVec3::new(0.0, 0.4, 0.0), 1e-12));
    }

    #[test]
    fn euler_xyz_round_trip_and_composition_order() {
        for q in sample_quats() {
            let e = euler_xyz(q);
            let back = from_euler_xyz(e);
            assert!(back.dot(q).abs() > 1.0 - 1e-7, "{q:?} -> {e:?}");
        }
        // Intrinsic order: rotating about x first turns the later y axis.
        let q = from_euler_xyz([PI / 2.0, 0.3, 0.0]);
        let expected = DQuat::from_rotation_x(PI / 2.0) * DQuat::from_rotation_y(0.3);
        assert!(q.dot(expected).abs() > 1.0 - 1e-12);
        let e = euler_xyz(from_euler_xyz([0.1, -0.4, 1.2]));
        assert!((e[0] - 0.1).abs() < 1e-12 && (e[1] + 0.4).abs() < 1e-12 && (e[2] - 1.2).abs() < 1e-12);
    }

    #[test]
    fn heading_ignores_tilt() {
        let yaw = 2.5;
        let tilted = yaw_quat(yaw) * DQuat::from_rotation_y(0.3) * DQuat::from_rotation_x(-0.2);
        assert!((heading(tilted) - yaw).abs() < 1e-12);
        assert!((wrap_angle(3.0 * PI + 0.1) - (-PI + 0.1)).abs() < 1e-12);
    }

    #[test]
    fn char_frame_matches_paper_equations() {
        let frame = CharFrame::from_root(DVec3::new(1.0, 2.0, 0.9), yaw_quat(PI / 2.0));
        // A point 1 m north of the root (+y world) is 1 m ahead (+x) when facing north.
        assert!(close(frame.point(DVec3::new(1.0, 3.0, 0.9)), DVec3::X, 1e-12));
        assert!(close(frame.vector(DVec3::new(0.0, -2.0, 0.5)), DVec3::new(-2.0, 0.0, 0.5), 1e-12));
        let p = DVec3::new(-0.3, 4.0, 1.1);
        assert!(close(frame.point_to_world(frame.point(p)), p, 1e-12));
        let v = DVec3::new(0.3, -1.0, 0.2);
        assert!(close(frame.vector_to_world(frame.vector(v)), v, 1e-12));
        let r = frame.rotation(yaw_quat(PI / 2.0));
        assert!(r.dot(DQuat::IDENTITY).abs() > 1.0 - 1e-12);
    }
}
