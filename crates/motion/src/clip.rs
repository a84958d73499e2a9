//! A clip: the humanoid's reference motion at 30 Hz, and its file format.
//!
//! # File format (`.clip.safetensors`)
//!
//! A [safetensors](https://github.com/huggingface/safetensors) file, readable in Python with
//! `safetensors.numpy.load_file(path)` (metadata via `safe_open(path, "np").metadata()`):
//!
//! | tensor         | dtype | shape        | what                                                     |
//! |----------------|-------|--------------|----------------------------------------------------------|
//! | `qpos`         | F64   | `[T, 76]`    | root position (3), root quaternion w x y z (4), 69 hinges |
//! | `qvel`         | F64   | `[T, 75]`    | root linear velocity (world), angular (root frame), hinges |
//! | `body_pos`     | F32   | `[T, 24, 3]` | body origins, world, MuJoCo depth-first body order        |
//! | `body_quat`    | F32   | `[T, 24, 4]` | body orientations, world, w x y z                         |
//! | `body_lin_vel` | F32   | `[T, 24, 3]` | body origin velocities, world                             |
//! | `body_ang_vel` | F32   | `[T, 24, 3]` | body angular velocities, world                            |
//!
//! Metadata: `format` (`flowmimic-clip/1`), `name`, `source`, `fps` (30), `cyclic`,
//! `body_names` and `hinge_names` (JSON lists). Body quantities are derived from `qpos`/`qvel`
//! through the simulator's own kinematics, so they are exactly what the tracker will see.
//!
//! A cyclic clip's last frame is its first frame one loop later; [`Clip::looped`] repeats
//! it with the root's displacement and heading accumulated (the loop's planar motion is fitted
//! on all body positions of the last frame against the first).

use crate::MotionError;
use crate::retarget::quat_of;
use flowmimic_geom::{DQuat, DVec3, rotvec, yaw_quat};
use flowmimic_io::le;
use flowmimic_sim::skeleton::{BODY_NAMES, NUM_BODIES, body, hinge_names};
use flowmimic_sim::{BodyKinematics, CONTROL_HZ, Humanoid, Mirror};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

pub const FORMAT: &str = "flowmimic-clip/1";

/// Reference motion at 30 Hz.
#[derive(Clone, Debug)]
pub struct Clip {
    pub name: String,
    /// Where it came from (file, generator parameters).
    pub source: String,
    pub cyclic: bool,
    pub qpos: Vec<Vec<f64>>,
    pub qvel: Vec<Vec<f64>>,
    pub bodies: Vec<BodyKinematics>,
    /// For a cyclic clip, the planar motion of one loop (first frame onto last).
    cycle: Option<Planar>,
}

/// A planar rigid motion: turn by `yaw` about `pivot`, then shift.
#[derive(Clone, Copy, Debug)]
struct Planar {
    yaw: f64,
    pivot: DVec3,
    shift: DVec3,
}

impl Planar {
    fn apply(&self, q: &mut [f64]) {
        let turn = yaw_quat(self.yaw);
        let p = turn * (DVec3::new(q[0], q[1], q[2]) - self.pivot) + self.pivot + self.shift;
        let r = turn * quat_of(q);
        q[..7].copy_from_slice(&[p.x, p.y, p.z, r.w, r.x, r.y, r.z]);
    }

    fn inverse(&self) -> Self {
        // x -> R(x - c) + c + s  inverts to  x -> R^T(x - c - s) + c.
        Self { yaw: -self.yaw, pivot: self.pivot + self.shift, shift: -self.shift }
    }
}

impl Clip {
    /// A clip from root-and-hinge poses: velocities by central differences (wrapping around
    /// the loop for cyclic clips), body kinematics through the simulator.
    pub fn from_qpos(
        humanoid: &Arc<Humanoid>,
        name: &str,
        source: &str,
        cyclic: bool,
        qpos: Vec<Vec<f64>>,
    ) -> Result<Self, MotionError> {
        check_name(name)?;
        if qpos.len() < 2 {
            return Err(MotionError::Invalid(format!("{name}: a clip needs at least 2 frames")));
        }
        if let Some(q) = qpos.iter().find(|q| q.len() != humanoid.nq()) {
            return Err(MotionError::Invalid(format!(
                "{name}: qpos has {} entries, expected {}",
                q.len(),
                humanoid.nq()
            )));
        }
        let cycle = cyclic.then(|| loop_motion(humanoid, &qpos[0], &qpos[qpos.len() - 1]));
        let mut clip = Self {
            name: name.into(),
            source: source.into(),
            cyclic,
            qpos,
            qvel: Vec::new(),
            bodies: Vec::new(),
            cycle,
        };
        clip.qvel = clip.central_velocities();
        clip.derive_bodies(humanoid)?;
        Ok(clip)
    }

    /// Velocities by central differences, wrapping around the loop for cyclic clips and
    /// one-sided at the ends otherwise.
    fn central_velocities(&self) -> Vec<Vec<f64>> {
        let n = self.qpos.len() as isize;
        let dt = 1.0 / CONTROL_HZ;
        (0..n)
            .map(|t| {
                let (a, b) = if self.cyclic { (t - 1, t + 1) } else { ((t - 1).max(0), (t + 1).min(n - 1)) };
                velocity(&self.frame(a), &self.frame(b), (b - a) as f64 * dt)
            })
            .collect()
    }

    fn derive_bodies(&mut self, humanoid: &Arc<Humanoid>) -> Result<(), MotionError> {
        let mut env = humanoid.env();
        self.bodies = Vec::with_capacity(self.qpos.len());
        for (t, (q, v)) in self.qpos.iter().zip(&self.qvel).enumerate() {
            env.reset(q, v).map_err(|e| MotionError::Invalid(format!("{}: frame {t}: {e}", self.name)))?;
            self.bodies.push(env.bodies());
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.qpos.len()
    }

    pub fn is_empty(&self) -> bool {
        self.qpos.is_empty()
    }

    /// Duration in seconds (frames - 1 intervals).
    pub fn duration(&self) -> f64 {
        (self.len() - 1) as f64 / CONTROL_HZ
    }

    /// `qpos` of frame `i`; any integer for a cyclic clip (loops accumulate), clamped to the
    /// ends otherwise.
    pub fn frame(&self, i: isize) -> Vec<f64> {
        let n = self.len() as isize;
        if !self.cyclic {
            return self.qpos[i.clamp(0, n - 1) as usize].clone();
        }
        let period = n - 1;
        let (loops, j) = (i.div_euclid(period), i.rem_euclid(period));
        let mut q = self.qpos[j as usize].clone();
        let cycle = self.cycle.expect("cyclic clips have a loop motion");
        let step = if loops >= 0 { cycle } else { cycle.inverse() };
        for _ in 0..loops.unsigned_abs() {
            step.apply(&mut q);
        }
        q
    }

    /// A cyclic clip repeated to at least `frames` frames; non-cyclic clips are returned as is.
    pub fn looped(&self, humanoid: &Arc<Humanoid>, frames: usize) -> Result<Self, MotionError> {
        if !self.cyclic || frames <= self.len() {
            return Ok(self.clone());
        }
        let qpos = (0..frames as isize).map(|i| self.frame(i)).collect();
        let (name, source) = (self.name.clone(), self.source.clone());
        let mut clip = Self { name, source, cyclic: false, qpos, qvel: Vec::new(), bodies: Vec::new(), cycle: None };
        clip.qvel = clip.central_velocities();
        // Keep the loop's exact velocity at the start rather than a one-sided one.
        clip.qvel[0] = self.qvel[0].clone();
        clip.derive_bodies(humanoid)?;
        Ok(clip)
    }

    /// The clip's left-right mirror image ([`Mirror`]), named `<name>-mirrored`: a walk that
    /// turns left becomes one that turns right at the same rate.
    pub fn mirror_image(&self, humanoid: &Arc<Humanoid>) -> Result<Self, MotionError> {
        let qpos = self.qpos.iter().map(|q| Mirror::qpos(q)).collect();
        let source = format!("mirror image of {}", self.source);
        Self::from_qpos(humanoid, &format!("{}-mirrored", self.name), &source, self.cyclic, qpos)
    }

    /// The walking each frame carries out (see [`crate::coverage::walking_velocities`]).
    pub fn walking_velocities(&self) -> Vec<[f64; 3]> {
        let path: Vec<[f64; 3]> = self.qpos.iter().map(|q| [q[0], q[1], flowmimic_geom::heading(quat_of(q))]).collect();
        crate::coverage::walking_velocities(&path)
    }

    /// Walking-quality metrics, computed through the simulator's kinematics.
    pub fn quality(&self, humanoid: &Arc<Humanoid>) -> Quality {
        let n = self.len();
        let mut env = humanoid.env();
        let bottoms: Vec<[[f64; 2]; 2]> = self
            .qpos
            .iter()
            .zip(&self.qvel)
            .map(|(q, v)| {
                env.reset(q, v).expect("clip frames are valid states");
                env.foot_bottoms()
            })
            .collect();
        let soles: Vec<[f64; 2]> = bottoms.iter().map(|f| f.map(|[heel, toe]| heel.min(toe))).collect();
        let root_xy = |t: usize| DVec3::new(self.qpos[t][0], self.qpos[t][1], 0.0);
        let path: f64 = (1..n).map(|t| root_xy(t).distance(root_xy(t - 1))).sum();
        let heights: Vec<f64> = self.qpos.iter().map(|q| q[2]).collect();
        let penetration: Vec<f64> = soles.iter().map(|s| (-s[0].min(s[1])).max(0.0)).collect();
        // Skating: horizontal speed of the touching part of a foot (the toe body, which pivots
        // at the ball of the foot, or the foot body) while it is within 1 cm of the ground.
        let (mut skate_sum, mut skate_n, mut single, mut double) = (0.0, 0usize, 0usize, 0usize);
        for t in 0..n {
            match soles[t].iter().filter(|z| **z < CONTACT_HEIGHT).count() {
                1 => single += 1,
                2 => double += 1,
                _ => {}
            }
            for (side, parts) in [[body::L_ANKLE, body::L_TOE], [body::R_ANKLE, body::R_TOE]].iter().enumerate() {
                let [heel, toe] = bottoms[t][side];
                if heel.min(toe) < CONTACT_HEIGHT {
                    let part = if toe < heel { parts[1] } else { parts[0] };
                    skate_sum += self.bodies[t].lin_vel[part].truncate().length();
                    skate_n += 1;
                }
            }
        }
        Quality {
            frames: n,
            duration: self.duration(),
            speed: path / self.duration(),
            root_height_mean: heights.iter().sum::<f64>() / n as f64,
            root_height_min: heights.iter().cloned().fold(f64::MAX, f64::min),
            penetration_mean: penetration.iter().sum::<f64>() / n as f64,
            penetration_max: penetration.iter().cloned().fold(0.0, f64::max),
            skating: if skate_n > 0 { skate_sum / skate_n as f64 } else { 0.0 },
            single_support: single as f64 / n as f64,
            double_support: double as f64 / n as f64,
            airborne: (n - single - double) as f64 / n as f64,
            hand_high: self.share_with_hand_above(HAND_HIGH),
            hand_overhead: self.share_with_hand_above(HAND_OVERHEAD),
            hand_low: self.share_with_hand_below(HAND_LOW),
            body_speed_max: self.body_speed_max(),
        }
    }

    /// The fastest any body moves between two frames, m/s.
    pub fn body_speed_max(&self) -> f64 {
        let fps = CONTROL_HZ;
        self.bodies
            .windows(2)
            .flat_map(|w| (0..NUM_BODIES).map(move |b| w[1].pos[b].distance(w[0].pos[b])))
            .fold(0.0, f64::max)
            * fps
    }

    /// Fraction of frames in which either hand is higher than `height`, m.
    pub fn share_with_hand_above(&self, height: f64) -> f64 {
        self.share_of_hand_heights(|l, r| l.max(r) > height)
    }

    /// Fraction of frames with a hand (either) below `height`, m.
    pub fn share_with_hand_below(&self, height: f64) -> f64 {
        self.share_of_hand_heights(|l, r| l.min(r) < height)
    }

    /// Fraction of frames whose left and right hand heights, m, satisfy `keep`.
    fn share_of_hand_heights(&self, keep: impl Fn(f64, f64) -> bool) -> f64 {
        let kept = self.bodies.iter().filter(|b| keep(b.pos[body::L_HAND].z, b.pos[body::R_HAND].z)).count();
        kept as f64 / self.len().max(1) as f64
    }

    /// Writes the clip atomically (see the module docs for the format).
    pub fn save(&self, path: &Path) -> Result<(), MotionError> {
        let n = self.len();
        let f64_bytes = |rows: &[Vec<f64>]| le::bytes(rows.iter().flatten().copied());
        let f32_bytes = |vals: Vec<f64>| le::bytes(vals.into_iter().map(|v| v as f32));
        let by_body = |f: &dyn Fn(&BodyKinematics, usize) -> Vec<f64>| {
            f32_bytes(self.bodies.iter().flat_map(|k| (0..NUM_BODIES).flat_map(|b| f(k, b))).collect())
        };
        let tensors: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
            ("qpos", Dtype::F64, vec![n, self.qpos[0].len()], f64_bytes(&self.qpos)),
            ("qvel", Dtype::F64, vec![n, self.qvel[0].len()], f64_bytes(&self.qvel)),
            ("body_pos", Dtype::F32, vec![n, NUM_BODIES, 3], by_body(&|k, b| k.pos[b].to_array().to_vec())),
            (
                "body_quat",
                Dtype::F32,
                vec![n, NUM_BODIES, 4],
                by_body(&|k, b| {
                    let q = k.rot[b];
                    vec![q.w, q.x, q.y, q.z]
                }),
            ),
            ("body_lin_vel", Dtype::F32, vec![n, NUM_BODIES, 3], by_body(&|k, b| k.lin_vel[b].to_array().to_vec())),
            ("body_ang_vel", Dtype::F32, vec![n, NUM_BODIES, 3], by_body(&|k, b| k.ang_vel[b].to_array().to_vec())),
        ];
        let views: Vec<(&str, TensorView)> = tensors
            .iter()
            .map(|(name, dtype, shape, bytes)| {
                (*name, TensorView::new(*dtype, shape.clone(), bytes).expect("consistent shape"))
            })
            .collect();
        let metadata: HashMap<String, String> = [
            ("format", FORMAT.to_string()),
            ("name", self.name.clone()),
            ("source", self.source.clone()),
            ("fps", CONTROL_HZ.to_string()),
            ("cyclic", self.cyclic.to_string()),
            ("body_names", serde_json::to_string(&BODY_NAMES).expect("json")),
            ("hinge_names", serde_json::to_string(&hinge_names()).expect("json")),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let bytes =
            safetensors::serialize(views, Some(metadata)).map_err(|e| MotionError::file(path, e.to_string()))?;
        flowmimic_io::write_atomic(path, &bytes)?;
        Ok(())
    }

    /// Reads a clip written by [`Clip::save`]; body kinematics are recomputed and checked
    /// against the stored ones, so a file from another humanoid is refused.
    pub fn load(humanoid: &Arc<Humanoid>, path: &Path) -> Result<Self, MotionError> {
        let bytes = flowmimic_io::read(path)?;
        let bad = |m: String| MotionError::file(path, m);
        let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| {
            bad(format!(
                "not a clip (.clip.safetensors, written by `flowmimic motion import|generate|corpus`; {e}): it is {}",
                flowmimic_io::describe(path)
            ))
        })?;
        let meta = meta.metadata().clone().unwrap_or_default();
        let get = |k: &str| meta.get(k).cloned().ok_or_else(|| bad(format!("metadata has no '{k}'")));
        if get("format")? != FORMAT {
            return Err(bad(format!("format is '{}', expected '{FORMAT}'", get("format")?)));
        }
        let tensors = SafeTensors::deserialize(&bytes).map_err(|e| bad(e.to_string()))?;
        let matrix = |name: &str, width: usize| -> Result<Vec<Vec<f64>>, MotionError> {
            let t = tensors.tensor(name).map_err(|e| bad(format!("tensor '{name}': {e}")))?;
            if t.dtype() != Dtype::F64 || t.shape().len() != 2 || t.shape()[1] != width {
                return Err(bad(format!(
                    "tensor '{name}' is {:?} {:?}, expected F64 [T, {width}]",
                    t.dtype(),
                    t.shape()
                )));
            }
            let vals: Vec<f64> = le::values(t.data());
            if let Some(i) = vals.iter().position(|v| !v.is_finite()) {
                return Err(bad(format!("tensor '{name}' has a non-finite value at flat index {i}")));
            }
            Ok(vals.chunks(width).map(<[f64]>::to_vec).collect())
        };
        let qpos = matrix("qpos", humanoid.nq())?;
        let qvel = matrix("qvel", humanoid.nv())?;
        if qpos.len() != qvel.len() || qpos.len() < 2 {
            return Err(bad(format!("qpos has {} frames and qvel {}", qpos.len(), qvel.len())));
        }
        let fps: f64 = get("fps")?.parse().map_err(|_| bad("fps is not a number".into()))?;
        if fps != CONTROL_HZ {
            return Err(bad(format!("clip is at {fps} Hz; flowmimic clips are at {CONTROL_HZ} Hz")));
        }
        let cyclic = get("cyclic")? == "true";
        let name = get("name")?;
        check_name(&name).map_err(|e| bad(e.to_string()))?;
        let cycle = cyclic.then(|| loop_motion(humanoid, &qpos[0], &qpos[qpos.len() - 1]));
        let mut clip = Self { name, source: get("source")?, cyclic, qpos, qvel, bodies: Vec::new(), cycle };
        clip.derive_bodies(humanoid).map_err(|e| bad(e.to_string()))?;
        let stored = tensors.tensor("body_pos").map_err(|e| bad(format!("tensor 'body_pos': {e}")))?;
        let expected = clip.len() * NUM_BODIES * 3 * 4;
        if stored.data().len() != expected {
            return Err(bad("tensor 'body_pos' does not match qpos in length".into()));
        }
        let worst = stored
            .data()
            .chunks_exact(4)
            .map(|c| f64::from(<f32 as le::Scalar>::read(c)))
            .zip(clip.bodies.iter().flat_map(|k| k.pos.iter().flat_map(|p| p.to_array())))
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        if worst > 1e-3 {
            return Err(bad(format!(
                "stored body positions differ from this humanoid's by {worst:.3} m: a clip for another model?"
            )));
        }
        Ok(clip)
    }
}

/// The planar motion taking the first pose onto the last: a least-squares fit of all body
/// positions on the ground plane. Captured loops rarely close exactly (the DeepMimic walk's
/// pelvis ends 7 degrees turned on a straight path), so one body's heading would be noise.
fn loop_motion(humanoid: &Arc<Humanoid>, first: &[f64], last: &[f64]) -> Planar {
    let mut env = humanoid.env();
    let zero = vec![0.0; humanoid.nv()];
    let mut flat = |q: &[f64]| -> Vec<DVec3> {
        env.reset(q, &zero).expect("clip frames are valid states");
        env.bodies().pos.iter().map(|p| DVec3::new(p.x, p.y, 0.0)).collect()
    };
    let (a, b) = (flat(first), flat(last));
    let centre = |ps: &[DVec3]| ps.iter().sum::<DVec3>() / ps.len() as f64;
    let (ca, cb) = (centre(&a), centre(&b));
    let (mut dot, mut cross) = (0.0, 0.0);
    for (p, q) in a.iter().zip(&b) {
        let (u, v) = (*p - ca, *q - cb);
        dot += u.x * v.x + u.y * v.y;
        cross += u.x * v.y - u.y * v.x;
    }
    Planar { yaw: cross.atan2(dot), pivot: ca, shift: cb - ca }
}

/// Refuses a clip name that is not a plain file name: names become output files
/// (`<name>.rollouts.safetensors`, `runs/track/<name>`), so `../x`, `/x` or control characters
/// would write outside the folder asked for.
pub fn check_name(name: &str) -> Result<(), MotionError> {
    let plain = !name.is_empty()
        && name.len() <= 100
        && name != "."
        && name != ".."
        && !name.chars().any(|c| c == '/' || c == '\\' || c.is_control());
    if plain {
        Ok(())
    } else {
        Err(MotionError::Invalid(format!("clip name {name:?} is not a plain file name (1-100 characters, no / or \\)")))
    }
}

/// Sole height below which a foot counts as in contact, metres.
pub const CONTACT_HEIGHT: f64 = 0.01;

/// Quality metrics of a clip.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Quality {
    pub frames: usize,
    pub duration: f64,
    /// Mean horizontal root speed along the path, m/s.
    pub speed: f64,
    pub root_height_mean: f64,
    pub root_height_min: f64,
    /// Depth of the lowest sole point below the ground, mean and max over frames, m.
    pub penetration_mean: f64,
    pub penetration_max: f64,
    /// Mean horizontal speed of the touching part of a foot in contact, m/s.
    pub skating: f64,
    /// Fractions of frames with one, two and no feet in contact.
    pub single_support: f64,
    pub double_support: f64,
    pub airborne: f64,
    /// Fractions of frames with a hand (either) above [`HAND_HIGH`] and [`HAND_OVERHEAD`].
    pub hand_high: f64,
    pub hand_overhead: f64,
    /// Fraction of frames with a hand (either) below [`HAND_LOW`].
    pub hand_low: f64,
    /// The fastest any body moves from one frame to the next, m/s: a person's hand peaks near
    /// 3 m/s; far beyond, the clip jumps (a retargeting glitch no expert can follow).
    pub body_speed_max: f64,
}

/// Frame-to-frame body speed (m/s) beyond which a clip is taken to jump.
pub const BODY_SPEED_JUMP: f64 = 6.0;

/// Heights that tell reaching apart from walking, m: a walking hand swings 0.7-1.1 m high, a
/// hand above 1.1 m reaches for a table or shelf, above 1.4 m for a high shelf.
pub const HAND_HIGH: f64 = 1.1;
pub const HAND_OVERHEAD: f64 = 1.4;
/// Below this height, m, a hand reaches low: a standing hand hangs at 0.7-0.9 m, so one under
/// 0.7 m comes with a bend or a crouch.
pub const HAND_LOW: f64 = 0.7;

/// Generalised velocity from pose `a` to pose `b` over `dt` seconds (free root layout).
fn velocity(a: &[f64], b: &[f64], dt: f64) -> Vec<f64> {
    let mut v = vec![0.0; a.len() - 1];
    for i in 0..3 {
        v[i] = (b[i] - a[i]) / dt;
    }
    let (ra, rb): (DQuat, DQuat) = (quat_of(a), quat_of(b));
    // Angular velocity in the root frame, at the midpoint's orientation.
    let mid = ra.slerp(rb, 0.5);
    let w_world = rotvec(rb * ra.conjugate()) / dt;
    let w_local = mid.conjugate() * w_world;
    v[3..6].copy_from_slice(&w_local.to_array());
    for i in 7..a.len() {
        v[i - 1] = (b[i] - a[i]) / dt;
    }
    v
}
