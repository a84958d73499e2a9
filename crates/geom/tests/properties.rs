//! Properties of the rotation and frame helpers on random inputs (proptest): round trips,
//! ranges, and the invariance of character-frame coordinates to where and which way the
//! character stands in the world.

use flowmimic_geom::*;
use proptest::prelude::*;
use std::f64::consts::PI;

fn vec3(r: f64) -> impl Strategy<Value = DVec3> {
    (-r..r, -r..r, -r..r).prop_map(|(x, y, z)| DVec3::new(x, y, z))
}

/// A unit quaternion from a rotation vector of angle below pi.
fn rotation() -> impl Strategy<Value = DQuat> {
    vec3(1.7).prop_filter("angle below pi", |v| v.length() < 3.1).prop_map(from_rotvec)
}

proptest! {
    #[test]
    fn rotation_vectors_round_trip(v in vec3(1.8).prop_filter("angle below pi", |v| v.length() < 3.1)) {
        prop_assert!((rotvec(from_rotvec(v)) - v).length() < 1e-9);
    }

    #[test]
    fn euler_angles_round_trip_away_from_gimbal_lock(q in rotation()) {
        let e = euler_xyz(q);
        prop_assume!(e[1].abs() < 1.5);
        let back = from_euler_xyz(e);
        // q and -q are the same rotation.
        prop_assert!(back.dot(q).abs() > 1.0 - 1e-9, "{q:?} -> {e:?} -> {back:?}");
    }

    #[test]
    fn wrapped_angles_are_the_same_angle_in_range(a in -100.0f64..100.0) {
        let w = wrap_angle(a);
        prop_assert!(w > -PI - 1e-12 && w <= PI + 1e-12);
        prop_assert!((w.sin() - a.sin()).abs() < 1e-9 && (w.cos() - a.cos()).abs() < 1e-9);
    }

    #[test]
    fn turning_the_world_adds_to_the_heading(q in rotation(), yaw in -PI..PI) {
        // Well defined unless the body's x axis is near vertical.
        prop_assume!((q * DVec3::X).z.abs() < 0.9);
        let turned = heading(yaw_quat(yaw) * q);
        prop_assert!(wrap_angle(turned - heading(q) - yaw).abs() < 1e-9);
    }

    #[test]
    fn character_frame_coordinates_ignore_where_the_character_stands(
        root in vec3(5.0), tilt in rotation(), point in vec3(2.0), shift in vec3(10.0), yaw in -PI..PI
    ) {
        prop_assume!((tilt * DVec3::X).z.abs() < 0.9);
        let frame = CharFrame::from_root(root, tilt);
        // Move and turn the whole world about z: the root, its orientation and the point.
        let (turn, shift) = (yaw_quat(yaw), DVec3::new(shift.x, shift.y, 0.0));
        let moved = CharFrame::from_root(turn * root + shift, turn * tilt);
        let (a, b) = (frame.point(point), moved.point(turn * point + shift));
        prop_assert!((a - b).length() < 1e-9, "{a} vs {b}");
        prop_assert!((frame.point_to_world(frame.point(point)) - point).length() < 1e-9);
        prop_assert!((frame.vector(point) - moved.vector(turn * point)).length() < 1e-9);
    }
}
