//! How high the guided plan puts the hand against how high the humanoid executes it, per
//! environment: a hand target held for 4 s from the generated straight walk, 8 environments,
//! NFE 2.
//!
//! `cargo run --release -p flowmimic-control --example planned_reach -- MODEL W [HEIGHT BETA]`
//! (defaults: the reach protocol's default target, 2.0 m ahead, 0.4 m right, 1.3 m high; the
//! plan's own actions). Prints, from the first second until a fall, the hand's mean and highest
//! height over the plans' horizons, on their first step, and executed.

mod probe;

use flowmimic_control::{Hand, Layout, Task};
use flowmimic_sim::CONTROL_HZ;

const ENVS: usize = 8;
const STEPS: usize = 120;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let probe = probe::Probe::from_args("W [HEIGHT BETA]")?;
    let (w, height, beta) = (probe.number(1, 30.0)?, probe.number(2, 1.3)?, probe.number(3, 0.0)?);
    let hand = Hand::Right;
    let tasks = vec![Task { reach: Some((hand, [2.0, -0.4, height])), approach: true, ..Task::walk() }; ENVS];
    let mut controller = probe.controller(ENVS, w, beta, 4.0)?;
    let traj = Layout { horizon: probe.model.layout().spec.horizon };
    let b = hand.body();
    // Per environment: mean and highest hand height over the plans' horizons, on their first
    // step, and executed.
    let mut sum = [[0.0f64; 3]; ENVS];
    let mut high = [[0.0f64; 3]; ENVS];
    let mut counted = [0usize; ENVS];
    for step in 0..STEPS {
        controller.step(&tasks, step as f64 / CONTROL_HZ)?;
        for e in (0..ENVS).filter(|&e| step >= CONTROL_HZ as usize && controller.is_alive(e)) {
            let plan = controller.plan(e).ok_or("a standing environment has a plan")?;
            let z = |k: usize| f64::from(plan[traj.root_pos(k) + 2] + plan[traj.body_pos(k, b) + 2]);
            let horizon: Vec<f64> = (1..=traj.horizon).map(z).collect();
            let heights =
                [horizon.iter().sum::<f64>() / horizon.len() as f64, z(1), controller.env(e).bodies().pos[b].z];
            let peak = [horizon.iter().copied().fold(f64::MIN, f64::max), z(1), heights[2]];
            for i in 0..3 {
                sum[e][i] += heights[i];
                high[e][i] = high[e][i].max(peak[i]);
            }
            counted[e] += 1;
        }
    }
    println!(
        "w {w}, target {height} m high, BETA {beta}; hand height planned over the horizon / first step / executed (m):"
    );
    for e in 0..ENVS {
        let (m, h) = (sum[e].map(|s| s / counted[e].max(1) as f64), high[e]);
        let fell = if controller.is_alive(e) {
            String::new()
        } else {
            format!("   fell after {:.1} s", counted[e] as f64 / CONTROL_HZ + 1.0)
        };
        println!(
            "  env {e}: mean {:.2} / {:.2} / {:.2}   highest {:.2} / {:.2} / {:.2}{fell}",
            m[0], m[1], m[2], h[0], h[1], h[2]
        );
    }
    Ok(())
}
