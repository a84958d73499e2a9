//! MJCF generation for the humanoid: the model is code, so every number in it has one source
//! ([`crate::skeleton`]) and `flowmimic sim xml` writes the exact XML MuJoCo loads.

use crate::obstacle::{Footprint, Obstacle};
use crate::skeleton::{BODY_PARENTS, BodySpec, JointGroup, Shape, bodies};
use std::fmt::Write;

/// PD natural frequency `wn = 2 pi 10` rad/s (paper, BeyondMimic).
pub const NATURAL_FREQUENCY: f64 = 2.0 * std::f64::consts::PI * 10.0;
/// PD damping ratio (over-damped, as in the paper).
pub const DAMPING_RATIO: f64 = 2.0;
/// Geom density, kg/m^3 (human tissue is about 1050).
pub const DENSITY: f64 = 1050.0;

/// `kp = I wn^2`, `kd = 2 I zeta wn` for a reflected inertia `I`.
pub fn pd_gains(group: JointGroup) -> (f64, f64) {
    let i = group.armature();
    (i * NATURAL_FREQUENCY * NATURAL_FREQUENCY, 2.0 * i * DAMPING_RATIO * NATURAL_FREQUENCY)
}

/// How the pelvis is attached to the world.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Root {
    /// A free joint: the walking humanoid (nq = 76, nv = 75).
    Free,
    /// Welded in the air at this height: for testing the PD controller.
    Fixed { height: f64 },
}

/// Everything that selects a variant of the model.
#[derive(Clone, Debug, PartialEq)]
pub struct MjcfOptions {
    pub root: Root,
    /// Physics time step, seconds.
    pub timestep: f64,
    /// Body pairs whose geoms overlap in the rest or nominal pose and must not collide.
    pub exclude: Vec<(usize, usize)>,
    /// Solid obstacles, each a geom on a mocap body placed after the humanoid's (so the
    /// humanoid's body and geom numbers do not change), where it stands at time 0.
    pub obstacles: Vec<Obstacle>,
}

fn v3(v: [f64; 3]) -> String {
    format!("{} {} {}", v[0], v[1], v[2])
}

fn write_body(xml: &mut String, specs: &[BodySpec], index: usize, root: Root, depth: usize) {
    let spec = &specs[index];
    let pad = "  ".repeat(depth);
    let pos = match (index, root) {
        (0, Root::Fixed { height }) => [spec.offset[0], spec.offset[1], height],
        _ => spec.offset,
    };
    writeln!(xml, "{pad}<body name=\"{}\" pos=\"{}\">", spec.name, v3(pos)).unwrap();
    if index == 0 {
        if root == Root::Free {
            writeln!(xml, "{pad}  <freejoint name=\"root\"/>").unwrap();
        }
    } else {
        for (axis, name) in ["1 0 0", "0 1 0", "0 0 1"].iter().zip(["x", "y", "z"]) {
            let k = "xyz".find(name).unwrap();
            let [lo, hi] = spec.range[k];
            writeln!(
                xml,
                "{pad}  <joint name=\"{}_{name}\" axis=\"{axis}\" range=\"{lo:.6} {hi:.6}\" armature=\"{}\"/>",
                spec.name,
                spec.group.armature()
            )
            .unwrap();
        }
    }
    let geom = match spec.shape {
        Shape::Capsule { from, to, radius } => {
            format!("type=\"capsule\" fromto=\"{} {}\" size=\"{radius}\"", v3(from), v3(to))
        }
        Shape::Box { center, half } => format!("type=\"box\" pos=\"{}\" size=\"{}\"", v3(center), v3(half)),
        Shape::Sphere { center, radius } => format!("type=\"sphere\" pos=\"{}\" size=\"{radius}\"", v3(center)),
    };
    writeln!(xml, "{pad}  <geom name=\"{}\" {geom}/>", spec.name).unwrap();
    for child in (0..specs.len()).filter(|&c| BODY_PARENTS[c] == Some(index)) {
        write_body(xml, specs, child, root, depth + 1);
    }
    writeln!(xml, "{pad}</body>").unwrap();
}

/// An obstacle's mocap body and geom, its base 1 mm above the floor so that the two never touch.
fn write_obstacle(xml: &mut String, index: usize, o: &Obstacle) {
    let half_height = o.height / 2.0;
    let (size, yaw) = match o.footprint {
        Footprint::Cylinder { radius } => (format!("type=\"cylinder\" size=\"{radius} {half_height}\""), 0.0),
        Footprint::Box { half, yaw } => (format!("type=\"box\" size=\"{} {} {half_height}\"", half[0], half[1]), yaw),
    };
    let pos = v3([o.at[0], o.at[1], half_height + 1e-3]);
    writeln!(xml, "    <body name=\"obstacle_{index}\" mocap=\"true\" pos=\"{pos}\" euler=\"0 0 {yaw}\">").unwrap();
    writeln!(xml, "      <geom name=\"obstacle_{index}\" {size} rgba=\"0.45 0.5 0.6 1\"/>").unwrap();
    writeln!(xml, "    </body>").unwrap();
}

/// The humanoid's MJCF.
pub fn humanoid_xml(options: &MjcfOptions) -> String {
    let specs = bodies();
    let mut xml = String::new();
    writeln!(xml, "<mujoco model=\"flowmimic_smpl\">").unwrap();
    writeln!(xml, "  <compiler angle=\"radian\" autolimits=\"true\"/>").unwrap();
    writeln!(xml, "  <option timestep=\"{}\" integrator=\"implicitfast\"/>", options.timestep).unwrap();
    writeln!(xml, "  <size memory=\"4M\"/>").unwrap();
    writeln!(xml, "  <visual><global offwidth=\"1280\" offheight=\"720\"/></visual>").unwrap();
    xml.push_str(concat!(
        "  <default>\n",
        // Body geoms (contype 1) collide with the floor (conaffinity 1) and with each other.
        "    <geom contype=\"1\" conaffinity=\"1\" condim=\"3\" friction=\"1.0 0.005 0.0001\" ",
        "density=\"1050\" rgba=\"0.8 0.6 0.4 1\"/>\n",
        "    <joint type=\"hinge\" damping=\"0\"/>\n",
        "  </default>\n",
        "  <asset>\n",
        "    <texture name=\"grid\" type=\"2d\" builtin=\"checker\" rgb1=\".2 .3 .4\" rgb2=\".1 .15 .2\" ",
        "width=\"512\" height=\"512\"/>\n",
        "    <material name=\"grid\" texture=\"grid\" texrepeat=\"1 1\" texuniform=\"true\" reflectance=\".1\"/>\n",
        "  </asset>\n",
        "  <worldbody>\n",
        "    <light name=\"sun\" directional=\"true\" pos=\"0 0 5\" dir=\"0.2 0.3 -1\"/>\n",
        "    <geom name=\"floor\" type=\"plane\" size=\"0 0 0.05\" material=\"grid\"/>\n",
        "    <camera name=\"side\" mode=\"trackcom\" pos=\"0 -3.5 1.2\" xyaxes=\"1 0 0 0 0.25 1\"/>\n",
    ));
    write_body(&mut xml, &specs, 0, options.root, 2);
    for (i, o) in options.obstacles.iter().enumerate() {
        write_obstacle(&mut xml, i, o);
    }
    writeln!(xml, "  </worldbody>").unwrap();
    if !options.exclude.is_empty() {
        writeln!(xml, "  <contact>").unwrap();
        for &(a, b) in &options.exclude {
            writeln!(xml, "    <exclude body1=\"{}\" body2=\"{}\"/>", specs[a].name, specs[b].name).unwrap();
        }
        writeln!(xml, "  </contact>").unwrap();
    }
    // Position actuators with kv: MuJoCo applies kp and kd, and implicitfast integrates the
    // damping implicitly, which keeps light bodies (hands, toes) stable (docs/conventions.md, section 3).
    writeln!(xml, "  <actuator>").unwrap();
    for spec in &specs[1..] {
        let (kp, kd) = pd_gains(spec.group);
        let limit = spec.group.torque_limit();
        for axis in ["x", "y", "z"] {
            writeln!(
                xml,
                "    <position name=\"{0}_{axis}\" joint=\"{0}_{axis}\" kp=\"{kp:.4}\" kv=\"{kd:.4}\" forcerange=\"-{limit} {limit}\"/>",
                spec.name
            )
            .unwrap();
        }
    }
    writeln!(xml, "  </actuator>").unwrap();
    writeln!(xml, "</mujoco>").unwrap();
    xml
}
