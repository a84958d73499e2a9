//! What the guided plan turns against what the humanoid executes, per environment: a joystick
//! command held for 10 s from the generated straight walk, 8 environments, NFE 2.
//!
//! `cargo run --release -p flowmimic-control --example planned_turn -- MODEL W [VX YAW_RATE]`
//! (defaults: 1 m/s forward, no turn). Prints, after the first second, the mean yaw rate the
//! plans predict (over their horizon, and on their first step) and the one executed.

use flowmimic_control::{ControlConfig, Controller, JoystickSegment, Layout, Task};
use flowmimic_geom::{heading, wrap_angle};
use flowmimic_model::TrajectoryModel;
use flowmimic_motion::{GaitParams, generate};
use flowmimic_sim::{CONTROL_HZ, Humanoid, SimConfig};
use std::path::Path;

const ENVS: usize = 8;
const STEPS: usize = 300;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let number = |i: usize, default: f64| args.get(i).map_or(Ok(default), |a| a.parse::<f64>());
    let model = TrajectoryModel::load(Path::new(args.first().ok_or("usage: MODEL W [VX YAW_RATE]")?))?;
    let (w, vx, yaw_rate) = (number(1, 30.0)?, number(2, 1.0)?, number(3, 0.0)?);
    let humanoid = Humanoid::new(SimConfig::default())?;
    let clip = generate(&humanoid, "walk_straight", &GaitParams { duration: 10.0, ..Default::default() })?.0;
    let segment = JoystickSegment { seconds: 10.0, vx, vy: 0.0, yaw_rate };
    let tasks = vec![Task { joystick: vec![segment], ..Task::walk() }; ENVS];
    let mut controller = Controller::new(&model, &humanoid, &clip, ENVS, &ControlConfig::new(2, w as f32, 10.0))?;
    let traj = Layout { horizon: model.layout().spec.horizon };
    let horizon_s = traj.horizon as f64 / CONTROL_HZ;
    // Per environment: planned yaw rate over the horizon, on the first step, executed.
    let mut sums = [[0.0f64; 3]; ENVS];
    for step in 0..STEPS {
        let before: Vec<f64> = (0..ENVS).map(|e| heading(controller.env(e).bodies().rot[0])).collect();
        controller.step(&tasks, step as f64 / CONTROL_HZ)?;
        for (e, sum) in sums.iter_mut().enumerate().filter(|_| step >= CONTROL_HZ as usize) {
            let plan = controller.plan(e).ok_or("an environment fell")?;
            let yaw = |k: usize| f64::from(plan[traj.root_rot(k) + 2]);
            let turned = wrap_angle(heading(controller.env(e).bodies().rot[0]) - before[e]);
            for (s, x) in sum.iter_mut().zip([yaw(traj.horizon) / horizon_s, yaw(1) * CONTROL_HZ, turned * CONTROL_HZ])
            {
                *s += x / (STEPS - CONTROL_HZ as usize) as f64;
            }
        }
    }
    println!(
        "w {w}, command {vx} m/s at {yaw_rate} rad/s; yaw rates (rad/s): planned over the horizon / first step / executed"
    );
    for (e, [h, first, done]) in sums.iter().enumerate() {
        println!("  env {e}: {h:+.2} / {first:+.2} / {done:+.2}");
    }
    let mean = |i: usize| sums.iter().map(|s| s[i]).sum::<f64>() / ENVS as f64;
    println!("  mean:  {:+.2} / {:+.2} / {:+.2}", mean(0), mean(1), mean(2));
    Ok(())
}
