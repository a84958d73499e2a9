//! Simulator throughput, measured the same way every time: medians over repeats.
//! `flowmimic bench sim` prints these rows.

use crate::{Humanoid, NUM_DOFS, VecEnv};
use std::sync::Arc;
use std::time::Instant;

/// One measured quantity.
#[derive(Clone, Debug)]
pub struct Measurement {
    pub name: String,
    /// Median rate over the repeats, per second.
    pub per_second: f64,
    /// What is counted.
    pub unit: &'static str,
}

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

/// Median of `repeats` timings of `work`, which performs `count` units each call.
fn rate(repeats: usize, count: usize, mut work: impl FnMut()) -> f64 {
    work(); // warm-up
    median(
        (0..repeats)
            .map(|_| {
                let t = Instant::now();
                work();
                count as f64 / t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

/// A small deterministic action sequence around the nominal pose (keeps the humanoid busy
/// without a controller; it falls and lies on the ground, which exercises contacts).
fn wiggle(step: usize, env: usize) -> Vec<f32> {
    (0..NUM_DOFS).map(|i| 0.05 * ((step * 7 + i * 13 + env * 3) as f32 * 0.1).sin()).collect()
}

fn stand(humanoid: &Humanoid, env: &mut crate::Env) {
    env.reset(&humanoid.standing_qpos(), &vec![0.0; humanoid.nv()]).expect("standing pose");
}

/// `VecEnv::step` of a fixed batch of environments, set up once and timed as often as asked, so
/// that `flowmimic bench track` can time it between PPO iterations on the same threads.
pub struct VecEnvTimer {
    humanoid: Arc<Humanoid>,
    batch: VecEnv,
    actions: Vec<Vec<f32>>,
}

impl VecEnvTimer {
    pub fn new(humanoid: &Arc<Humanoid>, envs: usize) -> Self {
        let control_steps = 60;
        let actions = (0..control_steps).map(|s| (0..envs).flat_map(|e| wiggle(s, e)).collect()).collect();
        Self { humanoid: Arc::clone(humanoid), batch: VecEnv::new(humanoid, envs), actions }
    }

    /// One burst from the standing pose, on the current rayon pool.
    fn burst(&mut self) {
        self.batch.envs_mut().iter_mut().for_each(|env| stand(&self.humanoid, env));
        for a in &self.actions {
            self.batch.step(a).expect("bench step");
        }
    }

    /// Control steps in one burst.
    fn steps(&self) -> usize {
        self.actions.len() * self.batch.len()
    }

    /// Control steps per second of one burst.
    pub fn per_second(&mut self) -> f64 {
        let t = Instant::now();
        self.burst();
        self.steps() as f64 / t.elapsed().as_secs_f64()
    }
}

/// `VecEnv::step` for `envs` environments on the current rayon pool's threads, in control steps
/// per second: the median of `repeats` bursts after one warm-up.
pub fn vec_env(humanoid: &Arc<Humanoid>, envs: usize, repeats: usize) -> Measurement {
    let mut timer = VecEnvTimer::new(humanoid, envs);
    let steps = timer.steps();
    Measurement {
        name: format!("VecEnv::step, {envs} envs on {} threads", rayon::current_num_threads()),
        per_second: rate(repeats, steps, || timer.burst()),
        unit: "control steps",
    }
}

/// Raw MuJoCo steps, control steps for 1 and `envs` environments, and state reads.
pub fn run(humanoid: &Arc<Humanoid>, envs: usize, repeats: usize) -> Vec<Measurement> {
    let control_steps = 60;
    let mut out = Vec::new();

    let mut env = humanoid.env();
    let physics_steps = control_steps * humanoid.config().substeps;
    out.push(Measurement {
        name: "MuJoCo mj_step, 1 env".into(),
        per_second: rate(repeats, physics_steps, || {
            stand(humanoid, &mut env);
            for _ in 0..physics_steps {
                env.physics_step();
            }
        }),
        unit: "physics steps",
    });
    let actions: Vec<Vec<f32>> = (0..control_steps).map(|s| wiggle(s, 0)).collect();
    out.push(Measurement {
        name: "Env::step (30 Hz), 1 env".into(),
        per_second: rate(repeats, control_steps, || {
            stand(humanoid, &mut env);
            for a in &actions {
                env.step(a).expect("bench step");
            }
        }),
        unit: "control steps",
    });
    out.push(vec_env(humanoid, envs, repeats));
    let reads = 2000;
    out.push(Measurement {
        name: "Env::state (165-d features)".into(),
        per_second: rate(repeats, reads, || {
            for _ in 0..reads {
                std::hint::black_box(env.state());
            }
        }),
        unit: "reads",
    });
    out
}
