//! Properties of the window re-expression on random states and root poses (proptest): a state
//! re-expressed in its own frame is itself, and where the walker is in the world (a common turn
//! and shift of both root poses) changes nothing.

use flowmimic_data::window::reexpress;
use flowmimic_sim::STATE_DIM;
use flowmimic_sim::state::offset;
use proptest::prelude::*;
use std::f32::consts::PI;

/// A state in its own character frame: root at the origin (height free), anything else random,
/// the root's rotation vector below pi.
fn state() -> impl Strategy<Value = Vec<f32>> {
    (proptest::collection::vec(-2.0f32..2.0, STATE_DIM), -1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0).prop_map(
        |(mut s, a, b, c)| {
            s[offset::ROOT_POS] = 0.0;
            s[offset::ROOT_POS + 1] = 0.0;
            s[offset::ROOT_ROT..offset::ROOT_ROT + 3].copy_from_slice(&[a, b, c]);
            s
        },
    )
}

fn pose() -> impl Strategy<Value = [f32; 3]> {
    (-20.0f32..20.0, -20.0f32..20.0, -PI..PI).prop_map(|(x, y, h)| [x, y, h])
}

proptest! {
    #[test]
    fn a_state_in_its_own_frame_is_itself(s in state(), p in pose()) {
        let mut out = vec![0.0; STATE_DIM];
        reexpress(&s, p, p, &mut out);
        for (i, (a, b)) in s.iter().zip(&out).enumerate() {
            prop_assert!((a - b).abs() < 1e-4, "entry {i}: {a} vs {b}");
        }
    }

    #[test]
    fn where_the_walker_stands_changes_nothing(s in state(), k in pose(), t in pose(), turn in -PI..PI, dx in -50.0f32..50.0, dy in -50.0f32..50.0) {
        let moved = |p: [f32; 3]| {
            let (sin, cos) = turn.sin_cos();
            [cos * p[0] - sin * p[1] + dx, sin * p[0] + cos * p[1] + dy, p[2] + turn]
        };
        let (mut a, mut b) = (vec![0.0; STATE_DIM], vec![0.0; STATE_DIM]);
        reexpress(&s, k, t, &mut a);
        reexpress(&s, moved(k), moved(t), &mut b);
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            prop_assert!((x - y).abs() < 2e-3, "entry {i}: {x} vs {y}");
        }
        // Local features (bodies in the state's own frame) are never touched.
        prop_assert_eq!(&a[offset::BODY_POS..], &s[offset::BODY_POS..]);
    }
}
