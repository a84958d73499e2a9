//! `flowmimic demo`: the shipped guidance model walks on a joystick schedule (forward, turn
//! left, turn right, backward), then reaches with its right hand while walking; rollouts, plots
//! and metrics in one command.

use crate::run::{DriveArgs, load_model, start_clip};
use anyhow::Result;
use flowmimic_control::recommended::{Recommended, Settings};
use flowmimic_control::{Hand, HeadingHold, JoystickSegment, Rollout, Task};
use flowmimic_eval::protocols::{SEGMENT_SETTLE, joystick_trial, yaw_rates};
use flowmimic_plot::{Chart, Series};
use flowmimic_sim::skeleton::body;
use flowmimic_sim::state::offset;
use flowmimic_sim::{CONTROL_HZ, Humanoid};
use std::path::Path;
use std::sync::Arc;

/// The joystick part's settings where no flag is given: a fixed scale with inverse dynamics,
/// under which `fm` walks backward at the asked -0.5 m/s once the command is held (5 s here).
/// The model's recommended joystick settings (adaptive guidance at w 50) fall less over the
/// protocol's 3 s segments but barely reverse: -0.18 m/s after 5 s in this demo.
const DEMO_JOYSTICK: Settings = Settings {
    nfe: Some(2),
    guidance_scale: Some(40.0),
    adaptive: Some(0.0),
    inverse_dynamics: Some(0.2),
    acceleration: None,
    label_scale: None,
    guidance_interval: None,
    approach: None,
    start_actions: None,
    executor: None,
    executor_residual: None,
};

/// Forward, turn left, turn right, then backward, the walk the joystick protocol asks in
/// another order, with longer turns and backward walk: walking forward again after walking
/// backward toppled 3 of 8 walkers at w 30 with inverse dynamics 0.2 (6 of 8 with 2 s of forward
/// walking between), and in this order 8 of 8 stand at w 40 (README, "Holding the joystick's
/// heading").
fn schedule() -> Task {
    let seg = |seconds, vx, yaw_rate| JoystickSegment { seconds, vx, vy: 0.0, yaw_rate };
    Task {
        joystick: vec![seg(3.0, 1.0, 0.0), seg(4.0, 0.8, 0.6), seg(4.0, 0.8, -0.6), seg(5.0, -0.5, 0.0)],
        ..Task::walk()
    }
}

pub fn run(model_dir: &Path, out: &Path, drive: &DriveArgs, humanoid: &Arc<Humanoid>) -> Result<()> {
    let model = load_model(model_dir)?;
    let clip = start_clip(humanoid, None)?;
    let name = model_dir.display().to_string();
    eprintln!("{} model from {name} (H {})", model.objective.label(), model.layout().spec.horizon);
    // The demo's own guidance, with the model's executor for the joystick where it has one.
    let settings = Recommended::load(model_dir)?;
    let demo_joystick = Settings {
        executor: settings.joystick.executor,
        executor_residual: settings.joystick.executor_residual,
        ..DEMO_JOYSTICK
    };
    let joystick = drive.choose_over(&demo_joystick, "demo", "joystick")?;
    let reach = drive.choose(&settings.reach, "reach")?;

    // 1. Joystick: forward, turn left, turn right, backward.
    let task = schedule();
    let control = joystick.control(drive.guidance.gradient, task.schedule_seconds());
    let r = flowmimic_control::run(&model, humanoid, &clip, vec![task], &control, &name, |_| {})?;
    r.save(&out.join("joystick.rollout.safetensors"))?;
    let t = joystick_trial(&r, 0);
    let time = |k: usize| k as f64 / CONTROL_HZ;
    let series = |f: &dyn Fn(usize) -> f64| (0..r.survived[0]).map(|k| (time(k), f(k))).collect::<Vec<_>>();
    Chart::new("joystick: forward speed", "seconds", "m/s")
        .series(Series::line("commanded", series(&|k| f64::from(r.command(0, k)[0]))))
        .series(Series::line("achieved", series(&|k| f64::from(r.state(0, k + 1)[offset::ROOT_VEL]))))
        .save(&out.join("joystick_velocity"))?;
    // Headings (the yaw rates summed), which the gait's sway of about 1 rad/s per step hides in
    // the rates themselves.
    let rates = yaw_rates(&r, 0);
    let heading = |rate: &dyn Fn(usize) -> f64| {
        let mut sum = 0.0;
        (0..r.survived[0])
            .map(|k| {
                sum += rate(k) / CONTROL_HZ;
                (time(k), sum)
            })
            .collect::<Vec<_>>()
    };
    let achieved = heading(&|k| rates[k]);
    // What each turn rate asks: its rate from the heading the walker had when it was set (as
    // `HeadingHold` starts again), so each segment's line shows how well that turn is followed.
    let mut since: Option<(f64, f64, f64)> = None;
    let asked: Vec<(f64, f64)> = achieved
        .iter()
        .enumerate()
        .map(|(k, &(t, now))| {
            let rate = f64::from(r.command(0, k)[2]);
            let (_, from, at) = match since {
                Some(held) if (held.0 - rate).abs() <= HeadingHold::NEW_RATE => held,
                _ => *since.insert((rate, now, t)),
            };
            (t, from + rate * (t - at))
        })
        .collect();
    Chart::new("joystick: heading (each turn rate from the heading it found)", "seconds", "rad")
        .series(Series::line("commanded", asked))
        .series(Series::line("achieved", achieved))
        .save(&out.join("joystick_heading"))?;
    println!(
        "joystick (forward, turn left, turn right, backward; w {}): velocity RMSE {:.2} m/s, yaw-rate RMSE {:.2} rad/s, {}",
        joystick.guidance_scale,
        t.velocity_rmse,
        t.yaw_rate_rmse,
        fell(&r)
    );
    for ((seg, got), rmse) in r.info.tasks[0].joystick.iter().zip(&t.segments).zip(&t.segment_rmse) {
        println!(
            "  commanded {:+.1} m/s forward at {:+.1} rad/s: achieved {:+.2} m/s forward, {:+.2} m/s left, {:+.2} rad/s (from {SEGMENT_SETTLE} s in); velocity RMSE {rmse:.2} m/s",
            seg.vx, seg.yaw_rate, got[0], got[1], got[2]
        );
    }

    // 2. Walk up to a target 2 m ahead, 0.3 m right, at a walking hand's height (0.85 m) and
    // touch it with the right hand (a target above the walking hand is out of reach: README).
    let start = &clip.qpos[flowmimic_control::controller::start_frame(clip.len(), model.layout().spec.history, 0)];
    let target = [start[0] + 2.0, start[1] - 0.3, 0.85];
    let task = Task { reach: Some((Hand::Right, target)), approach: true, ..Task::walk() };
    let control = reach.control(drive.guidance.gradient, 5.0);
    let r = flowmimic_control::run(&model, humanoid, &clip, vec![task], &control, &name, |_| {})?;
    r.save(&out.join("reach.rollout.safetensors"))?;
    let distance = |k: usize| {
        let h = r.body(0, k, body::R_HAND);
        ((h[0] - target[0]).powi(2) + (h[1] - target[1]).powi(2) + (h[2] - target[2]).powi(2)).sqrt()
    };
    let d: Vec<(f64, f64)> = (0..=r.survived[0]).map(|k| (time(k), distance(k))).collect();
    let closest = d.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    Chart::new("walking up to a target: right hand to target", "seconds", "metres")
        .series(Series::line("distance", d))
        .save(&out.join("reach_distance"))?;
    println!(
        "walking up to a hand target (w {}): closest hand-target distance {closest:.2} m, {}",
        reach.guidance_scale,
        fell(&r)
    );
    let (model_ms, physics_ms) = r.median_ms();
    println!("per control step (median): model {model_ms:.1} ms, physics {physics_ms:.1} ms");
    eprintln!("wrote rollouts and joystick_velocity/joystick_heading/reach_distance .png/.svg in {}", out.display());
    Ok(())
}

fn fell(r: &Rollout) -> String {
    if r.fell(0) { format!("fell after {:.1} s", r.survived[0] as f64 / CONTROL_HZ) } else { "no fall".into() }
}
