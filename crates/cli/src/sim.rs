//! `flowmimic sim ...` and `flowmimic bench sim`: the simulated humanoid's numbers, its MJCF,
//! and a look at it standing.

use crate::config::Config;
use anyhow::Result;
use clap::Subcommand;
use flowmimic_sim::{Humanoid, NUM_DOFS, STATE_DIM, bench, mjcf, skeleton};
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum SimCommand {
    /// Dimensions, mass, height and PD gains of the humanoid.
    Info,
    /// Write the generated MJCF (open it in MuJoCo's `simulate` to look around).
    Xml {
        /// Output file; prints to stdout when omitted.
        #[arg(short, long)]
        output: Option<PathBuf>,
    },
    /// Simulate the free humanoid holding its nominal pose (zero action) and report.
    Hold {
        /// Simulated seconds.
        #[arg(long, default_value_t = 5.0, allow_negative_numbers = true, value_parser = crate::args::seconds)]
        seconds: f64,
        /// Planar push (m/s, world x) at the start, to watch it topple.
        #[arg(long, default_value_t = 0.0)]
        push: f64,
    },
}

pub fn run(cmd: SimCommand, config: &Config) -> Result<()> {
    let humanoid = Humanoid::new(config.sim)?;
    match cmd {
        SimCommand::Info => {
            println!("bodies {} (depth-first): {}", skeleton::NUM_BODIES, skeleton::BODY_NAMES.join(", "));
            println!("qpos {}  qvel {}  actions {}  state {}", humanoid.nq(), humanoid.nv(), NUM_DOFS, STATE_DIM);
            println!("mass {:.1} kg  height {:.2} m", humanoid.mass(), humanoid.height());
            println!(
                "physics {:.0} Hz ({} substeps per 30 Hz control step), integrator implicitfast",
                1.0 / config.sim.timestep(),
                config.sim.substeps
            );
            println!("{:<8} {:>10} {:>8} {:>8} {:>10}", "group", "armature", "kp", "kd", "torque");
            use skeleton::JointGroup::*;
            for group in [Leg, Toe, Trunk, Upper, Wrist] {
                let (kp, kd) = mjcf::pd_gains(group);
                let name = format!("{group:?}");
                println!("{name:<8} {:>10.3} {kp:>8.1} {kd:>8.1} {:>10.0}", group.armature(), group.torque_limit());
            }
        }
        SimCommand::Xml { output: None } => print!("{}", humanoid.xml()),
        SimCommand::Xml { output: Some(path) } => {
            flowmimic_io::write_atomic(&path, humanoid.xml().as_bytes())?;
            eprintln!("wrote {}", path.display());
        }
        SimCommand::Hold { seconds, push } => {
            let mut env = humanoid.env();
            env.kick([push, 0.0])?;
            let zero = vec![0f32; NUM_DOFS];
            let steps = (seconds * flowmimic_sim::CONTROL_HZ).round() as usize;
            println!("holding the nominal pose (zero action) for {seconds} s, push {push} m/s");
            println!("{:>6} {:>9} {:>9} {:>9} {:>9}", "t [s]", "pelvis z", "head z", "drift", "|torque|");
            for step in 1..=steps {
                env.step(&zero)?;
                let q = env.qpos();
                if step % 15 == 0 || step == steps || env.fallen() {
                    let torque = env.torques().iter().map(|t| t * t).sum::<f64>().sqrt();
                    println!(
                        "{:>6.2} {:>9.3} {:>9.3} {:>9.3} {:>9.1}",
                        env.time(),
                        q[2],
                        env.head_height(),
                        q[0].hypot(q[1]),
                        torque
                    );
                }
                if env.fallen() {
                    println!("fell after {:.2} s (head below {} m)", env.time(), flowmimic_sim::FALL_HEAD_HEIGHT);
                    return Ok(());
                }
            }
            println!("still standing after {seconds} s");
        }
    }
    Ok(())
}

/// `flowmimic bench sim`: physics and environment throughput, medians.
pub fn bench(config: &Config, envs: usize, repeats: usize) -> Result<()> {
    let humanoid = Humanoid::new(config.sim)?;
    println!(
        "humanoid: {} physics steps per 30 Hz control step ({:.0} Hz physics)",
        config.sim.substeps,
        1.0 / config.sim.timestep()
    );
    println!("{:<44} {:>14}  unit", "measurement", "median");
    for m in bench::run(&humanoid, envs.max(1), repeats.max(1)) {
        println!("{:<44} {:>14.0}  {}/s", m.name, m.per_second, m.unit);
    }
    Ok(())
}
