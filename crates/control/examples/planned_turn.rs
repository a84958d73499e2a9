//! What the guided plan does against what the humanoid executes, per environment: a joystick
//! command held for 10 s from the generated straight walk, 8 environments, NFE 2.
//!
//! `cargo run --release -p flowmimic-control --example planned_turn -- MODEL W [VX YAW_RATE BETA]`
//! (defaults: 1 m/s forward, no turn, the plan's own actions; BETA is the share of inverse
//! dynamics in the executed action). Prints, after the first second, the mean yaw rate and
//! forward speed the plans predict (over their horizon, and on their first step) and the ones
//! executed.

mod probe;

use flowmimic_control::{JoystickSegment, Layout, Task};
use flowmimic_geom::{DVec3, heading, wrap_angle};
use flowmimic_sim::CONTROL_HZ;

const ENVS: usize = 8;
const STEPS: usize = 300;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let probe = probe::Probe::from_args("W [VX YAW_RATE BETA]")?;
    let number = |i, default| probe.number(i, default);
    let (w, vx, yaw_rate, beta) = (number(1, 30.0)?, number(2, 1.0)?, number(3, 0.0)?, number(4, 0.0)?);
    let segment = JoystickSegment { seconds: 10.0, vx, vy: 0.0, yaw_rate };
    let tasks = vec![Task { joystick: vec![segment], ..Task::walk() }; ENVS];
    let mut controller = probe.controller(ENVS, w, beta, 10.0)?;
    let traj = Layout { horizon: probe.model.layout().spec.horizon };
    let (h, horizon_s) = (traj.horizon, traj.horizon as f64 / CONTROL_HZ);
    // Per environment: the yaw rate over the plan's horizon, on its first step and executed;
    // then the same for the forward speed.
    let mut sums = [[0.0f64; 6]; ENVS];
    for step in 0..STEPS {
        let before: Vec<_> = (0..ENVS).map(|e| controller.env(e).bodies().frame()).collect();
        controller.step(&tasks, step as f64 / CONTROL_HZ)?;
        for (e, sum) in sums.iter_mut().enumerate().filter(|_| step >= CONTROL_HZ as usize) {
            let plan = controller.plan(e).ok_or("an environment fell")?;
            let at = |i: usize| f64::from(plan[i]);
            let now = controller.env(e).bodies();
            let turned = wrap_angle(heading(now.rot[0]) - before[e].yaw);
            let moved = before[e].point(DVec3::new(now.pos[0].x, now.pos[0].y, before[e].origin.z)).x;
            let rates = [
                at(traj.root_rot(h) + 2) / horizon_s,
                at(traj.root_rot(1) + 2) * CONTROL_HZ,
                turned * CONTROL_HZ,
                at(traj.root_pos(h)) / horizon_s,
                at(traj.root_pos(1)) * CONTROL_HZ,
                moved * CONTROL_HZ,
            ];
            for (s, x) in sum.iter_mut().zip(rates) {
                *s += x / (STEPS - CONTROL_HZ as usize) as f64;
            }
        }
    }
    println!("w {w}, command {vx} m/s at {yaw_rate} rad/s; planned over the horizon / first step / executed:");
    println!("         yaw rate (rad/s)        forward speed (m/s)");
    let row = |s: &[f64; 6]| {
        format!("{:+.2} / {:+.2} / {:+.2}    {:+.2} / {:+.2} / {:+.2}", s[0], s[1], s[2], s[3], s[4], s[5])
    };
    for (e, sum) in sums.iter().enumerate() {
        println!("  env {e}: {}", row(sum));
    }
    let mut mean = [0.0; 6];
    for (i, m) in mean.iter_mut().enumerate() {
        *m = sums.iter().map(|s| s[i]).sum::<f64>() / ENVS as f64;
    }
    println!("  mean:  {}", row(&mean));
    Ok(())
}
