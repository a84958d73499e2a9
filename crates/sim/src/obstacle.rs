//! Solid obstacles on the ground: vertical cylinders and boxes, standing or moving along a
//! straight line at a constant velocity. The simulator makes them MuJoCo geoms on mocap bodies
//! (so a collision is a real contact); guidance reads the same description as a footprint.

use flowmimic_geom::{CharFrame, DVec3, wrap_angle};
use serde::{Deserialize, Serialize};

/// An obstacle's footprint on the ground.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Footprint {
    /// A vertical cylinder of this radius (m).
    Cylinder { radius: f64 },
    /// A box of these half-widths (m, along its own x and y), turned `yaw` rad from the world's x.
    Box {
        half: [f64; 2],
        #[serde(default)]
        yaw: f64,
    },
}

/// One obstacle: where its centre stands at time 0 (world x, y, m), how it moves (m/s), its
/// footprint and its height (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Obstacle {
    #[serde(flatten)]
    pub footprint: Footprint,
    pub at: [f64; 2],
    #[serde(default)]
    pub velocity: [f64; 2],
    #[serde(default = "default_height")]
    pub height: f64,
}

fn default_height() -> f64 {
    Obstacle::HEIGHT
}

impl Obstacle {
    /// Height of an obstacle when none is given (m): taller than the humanoid.
    pub const HEIGHT: f64 = 2.0;
    /// The keys an obstacle of footprint type `kind` (`cylinder`, `box`) is written with in JSON
    /// or TOML; any type's keys for another `kind`.
    pub fn keys(kind: &str) -> &'static [&'static str] {
        match kind {
            "cylinder" => &["type", "radius", "at", "velocity", "height"],
            "box" => &["type", "half", "yaw", "at", "velocity", "height"],
            _ => &["type", "radius", "half", "yaw", "at", "velocity", "height"],
        }
    }

    /// A standing cylinder.
    pub fn cylinder(at: [f64; 2], radius: f64) -> Self {
        Self { footprint: Footprint::Cylinder { radius }, at, velocity: [0.0; 2], height: Self::HEIGHT }
    }

    /// The same obstacle moving at `velocity` (m/s) from where it stands at time 0.
    pub fn moving(self, velocity: [f64; 2]) -> Self {
        Self { velocity, ..self }
    }

    /// Checks every number, naming the first bad one.
    pub fn validate(&self) -> Result<(), String> {
        let sizes = match self.footprint {
            Footprint::Cylinder { radius } => vec![radius],
            Footprint::Box { half, yaw } => {
                if !yaw.is_finite() {
                    return Err(format!("box yaw {yaw} is not finite"));
                }
                half.to_vec()
            }
        };
        if let Some(s) = sizes.iter().find(|s| !(s.is_finite() && (0.01..=10.0).contains(*s))) {
            return Err(format!("obstacle size {s} m (radius or half-width, 0.01-10 m)"));
        }
        if !(self.height.is_finite() && (0.05..=10.0).contains(&self.height)) {
            return Err(format!("obstacle height {} m (0.05-10 m)", self.height));
        }
        if let Some(v) = self.at.iter().find(|v| !v.is_finite() || v.abs() > 1e4) {
            return Err(format!("obstacle position {v} m (finite, within 10 km)"));
        }
        match self.velocity.iter().find(|v| !v.is_finite() || v.abs() > 10.0) {
            Some(v) => Err(format!("obstacle velocity {v} m/s (finite, within 10 m/s)")),
            None => Ok(()),
        }
    }

    /// The obstacle carried rigidly from the frame `from` to the frame `to`: where it stands,
    /// how it moves and how its footprint is turned stay the same relative to the frame.
    pub fn carried(&self, from: &CharFrame, to: &CharFrame) -> Obstacle {
        let at = to.point_to_world(from.point(DVec3::new(self.at[0], self.at[1], from.origin.z)));
        let v = to.vector_to_world(from.vector(DVec3::new(self.velocity[0], self.velocity[1], 0.0)));
        let footprint = match self.footprint {
            Footprint::Box { half, yaw } => Footprint::Box { half, yaw: wrap_angle(yaw + to.yaw - from.yaw) },
            cylinder => cylinder,
        };
        Obstacle { footprint, at: [at.x, at.y], velocity: [v.x, v.y], height: self.height }
    }

    /// Where its centre is at `time` (s).
    pub fn position(&self, time: f64) -> [f64; 2] {
        [self.at[0] + self.velocity[0] * time, self.at[1] + self.velocity[1] * time]
    }

    /// The radius of the smallest circle about its centre that holds its footprint (m).
    pub fn bounding_radius(&self) -> f64 {
        match self.footprint {
            Footprint::Cylinder { radius } => radius,
            Footprint::Box { half, .. } => half[0].hypot(half[1]),
        }
    }

    /// Signed distance (m) from the point `p` (world x, y) to the footprint's edge at `time`
    /// (negative inside), and its gradient with respect to `p` (unit length outside).
    pub fn distance(&self, p: [f64; 2], time: f64) -> (f64, [f64; 2]) {
        let c = self.position(time);
        let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
        match self.footprint {
            Footprint::Cylinder { radius } => {
                let r = dx.hypot(dy);
                let dir = if r > 1e-9 { [dx / r, dy / r] } else { [1.0, 0.0] };
                (r - radius, dir)
            }
            Footprint::Box { half, yaw } => {
                // Into the box's frame, the rectangle's signed distance, and back.
                let (s, co) = yaw.sin_cos();
                let local = [co * dx + s * dy, -s * dx + co * dy];
                let q = [local[0].abs() - half[0], local[1].abs() - half[1]];
                let (d, g) = if q[0] > 0.0 || q[1] > 0.0 {
                    let out = [q[0].max(0.0), q[1].max(0.0)];
                    let n = out[0].hypot(out[1]);
                    (n, [out[0] / n, out[1] / n])
                } else if q[0] > q[1] {
                    (q[0], [1.0, 0.0])
                } else {
                    (q[1], [0.0, 1.0])
                };
                let g = [g[0] * local[0].signum(), g[1] * local[1].signum()];
                (d, [co * g[0] - s * g[1], s * g[0] + co * g[1]])
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_and_their_gradients() {
        let c = Obstacle::cylinder([1.0, 2.0], 0.5).moving([1.0, 0.0]);
        let (d, g) = c.distance([2.0, 4.0], 1.0);
        assert!((d - 1.5).abs() < 1e-12 && (g[0]).abs() < 1e-12 && (g[1] - 1.0).abs() < 1e-12);
        let b = Obstacle { footprint: Footprint::Box { half: [1.0, 0.5], yaw: 0.7 }, ..c.moving([0.0; 2]) };
        for p in [[3.0, 2.5], [1.2, 2.1], [0.0, 0.0], [1.0, 3.1]] {
            let (d, g) = b.distance(p, 0.0);
            let h = 1e-6;
            let fd = [
                (b.distance([p[0] + h, p[1]], 0.0).0 - b.distance([p[0] - h, p[1]], 0.0).0) / (2.0 * h),
                (b.distance([p[0], p[1] + h], 0.0).0 - b.distance([p[0], p[1] - h], 0.0).0) / (2.0 * h),
            ];
            assert!((fd[0] - g[0]).abs() < 1e-5 && (fd[1] - g[1]).abs() < 1e-5, "at {p:?}: {g:?} vs {fd:?}");
            assert!(d.abs() < 3.0);
        }
        // A corner: 0.3 beyond both half-widths of an unturned box.
        let square = Obstacle { footprint: Footprint::Box { half: [1.0, 1.0], yaw: 0.0 }, ..b };
        assert!((square.distance([2.3, 3.3], 0.0).0 - 0.3 * 2f64.sqrt()).abs() < 1e-12);
        assert!(square.distance([1.0, 2.0], 0.0).0 < 0.0, "the centre is inside");
    }

    #[test]
    fn bad_numbers_are_named() {
        assert!(Obstacle::cylinder([0.0, 0.0], 0.3).validate().is_ok());
        assert!(Obstacle::cylinder([0.0, 0.0], -0.3).validate().unwrap_err().contains("size"));
        assert!(Obstacle::cylinder([f64::NAN, 0.0], 0.3).validate().unwrap_err().contains("position"));
        assert!(Obstacle::cylinder([0.0, 0.0], 0.3).moving([20.0, 0.0]).validate().unwrap_err().contains("velocity"));
    }

    #[test]
    fn reads_json_with_defaults() {
        let o: Obstacle = serde_json::from_str(r#"{"type": "cylinder", "radius": 0.3, "at": [4, 0]}"#).unwrap();
        assert_eq!(o, Obstacle::cylinder([4.0, 0.0], 0.3));
        let b: Obstacle =
            serde_json::from_str(r#"{"type": "box", "half": [0.5, 1], "at": [4, 0], "velocity": [0, 0.5]}"#).unwrap();
        assert_eq!(b.footprint, Footprint::Box { half: [0.5, 1.0], yaw: 0.0 });
        assert_eq!(b.velocity, [0.0, 0.5]);
    }
}
