//! Retargeting on random placements (proptest): the same motion turned about z, shifted and
//! scaled in the world gives the same clip, since retargeting scales to the humanoid's legs and
//! starts every clip at the origin facing +x.

use flowmimic_geom::{DVec3, yaw_quat};
use flowmimic_motion::GaitParams;
use flowmimic_motion::generator::landmarks;
use flowmimic_motion::retarget::retarget;
use flowmimic_sim::{Humanoid, SimConfig};
use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: 8, failure_persistence: None, ..ProptestConfig::default() })]
    #[test]
    fn placement_and_size_do_not_change_the_clip(yaw in -3.1f64..3.1, dx in -30.0f64..30.0, dy in -30.0f64..30.0, size in 0.6f64..1.6) {
        let h = Humanoid::new(SimConfig::default()).unwrap();
        let walk = GaitParams { duration: 1.0, turn_rate: 0.3, lateral: 0.1, ..Default::default() };
        let marks = landmarks(&walk.schedule()).unwrap();
        let mut moved = marks.clone();
        for pose in &mut moved.frames {
            for p in pose.iter_mut() {
                *p = yaw_quat(yaw) * (*p * size) + DVec3::new(dx, dy, 0.0);
            }
        }
        let (a, _) = retarget(&h, &marks, "a", "test", false).unwrap();
        let (b, _) = retarget(&h, &moved, "b", "test", false).unwrap();
        for (x, y) in a.qpos.iter().zip(&b.qpos) {
            // The root quaternion up to sign (q and -q are one rotation), the rest as numbers.
            let dot: f64 = (3..7).map(|i| x[i] * y[i]).sum();
            prop_assert!(dot.abs() > 1.0 - 1e-9, "root rotation differs: {dot}");
            let worst = x.iter().zip(y).enumerate().filter(|(i, _)| !(3..7).contains(i)).map(|(_, (p, q))| (p - q).abs()).fold(0.0, f64::max);
            prop_assert!(worst < 1e-6, "qpos differs by {worst}");
        }
    }
}
