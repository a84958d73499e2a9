//! Executing a plan with a tracking policy instead of the plan's own action: the policy
//! observes the plan's next state (its root) with the plan's action as the pose to reach, and
//! adds its residual, so that a body pushed off the plan is steered back to it.
//!
//! A plan's action is a PD target, not a pose: the policy must be trained on references whose
//! hinges are PD targets (`flowmimic track plan-clips`, [`flowmimic_track::plan`]), or it fails
//! them within 2 s. The plan's next state is relative to the current one, so the policy sees
//! one step of the plan at a time: a bias of its own is not corrected by the next plan, which
//! starts where the body is (docs/guidance.md, "A tracking policy that executes the plan").

use crate::ControlError;
use crate::layout::Layout;
use flowmimic_geom::{CharFrame, DVec3, from_rotvec};
use flowmimic_sim::{ActionMap, CONTROL_HZ, Env, NUM_DOFS};
use flowmimic_track::ppo::Policy;
use flowmimic_track::task::{NextFrame, OBS_DIM, observe};
use flowmimic_track::train::{Checkpoint, POLICY_FILE, policy_file};
use std::path::Path;

/// The share of an executor's residual added to the plan's action when none is given: with
/// `fm-walks`, half of the residual of either training seed's executor held kicks about as well
/// as all of it and steered about as the plan's own actions do, where all of it steered worse
/// (docs/guidance.md, "Half the executor's residual").
pub const DEFAULT_RESIDUAL: f32 = 0.5;

/// A tracking policy that executes plans.
pub struct Executor {
    policy: Policy,
    action_scale: f64,
    started_on_plans: bool,
}

impl Executor {
    /// The policy of a tracking run's `policy.safetensors` (a run directory or the file).
    pub fn load(path: &Path) -> Result<Self, ControlError> {
        let file = policy_file(path);
        if !path.exists() {
            return Err(ControlError::Start(format!(
                "executor {}: no such tracking run (an executor is a `flowmimic track train` run, such as \
                 pretrained/experts/executor-fm)",
                path.display()
            )));
        }
        if path.is_dir() && !file.exists() {
            return Err(ControlError::Start(format!(
                "executor {}: not a tracking run (no {POLICY_FILE}); an executor is a `flowmimic track train` run on \
                 `track plan-clips`' clips, such as pretrained/experts/executor-walks",
                path.display()
            )));
        }
        let bad = |e: flowmimic_track::TrackError| ControlError::Start(format!("executor: {e}"));
        let ck = Checkpoint::read(&file).map_err(bad)?;
        let (cfg, policy) = (ck.config().map_err(bad)?, ck.policy().map_err(bad)?);
        if policy.obs_dim() != OBS_DIM {
            return Err(ControlError::Start(format!(
                "executor {}: the policy observes the reference ahead, which a plan does not reach",
                file.display()
            )));
        }
        Ok(Self { policy, action_scale: cfg.action_scale, started_on_plans: cfg.fresh_output })
    }

    /// Whether the policy was started as an executor (`track.fresh_output`, as
    /// configs/executor.toml does). An expert of clips is a valid policy too, but it fails plans
    /// within 2 s; this is the one mark that tells them apart.
    pub fn started_on_plans(&self) -> bool {
        self.started_on_plans
    }

    /// The normalised actions that `envs` execute for their plans, each at its step `used`
    /// (the plan's action `used` and state `used + 1`, in the plan's `frame`): the plan's
    /// action plus `residual` times the policy's residual.
    pub fn actions(
        &self,
        map: &ActionMap,
        traj: Layout,
        envs: &[(&Env, &[f32], usize, CharFrame)],
        residual: f32,
    ) -> Vec<Vec<f32>> {
        let scale = f64::from(residual) * self.action_scale;
        let targets = |tau: &[f32], k: usize| -> Vec<f64> {
            let at = traj.action(k);
            (0..NUM_DOFS).map(|i| map.target(i, f64::from(tau[at + i].clamp(-1.0, 1.0)))).collect()
        };
        let mut raw = vec![0f32; envs.len() * OBS_DIM];
        let mut hinges = Vec::with_capacity(envs.len());
        for ((env, tau, used, frame), out) in envs.iter().zip(raw.chunks_exact_mut(OBS_DIM)) {
            let now = targets(tau, *used);
            let k = (*used + 1).min(traj.horizon);
            let velocities: Vec<f64> = if *used < traj.horizon {
                targets(tau, k).iter().zip(&now).map(|(b, a)| (b - a) * CONTROL_HZ).collect()
            } else {
                vec![0.0; NUM_DOFS]
            };
            let v3 = |at: usize| DVec3::new(f64::from(tau[at]), f64::from(tau[at + 1]), f64::from(tau[at + 2]));
            let p = v3(traj.root_pos(k));
            let mut pelvis_pos = frame.point_to_world(DVec3::new(p.x, p.y, 0.0));
            pelvis_pos.z = p.z;
            let next = NextFrame {
                hinges: &now,
                hinge_velocities: &velocities,
                pelvis_pos,
                pelvis_rot: flowmimic_geom::yaw_quat(frame.yaw) * from_rotvec(v3(traj.root_rot(k))),
                pelvis_vel: frame.vector_to_world(v3(traj.root_vel(k))),
            };
            observe(env, &env.bodies(), &next, out);
            hinges.push(now);
        }
        let u = self.policy.act(&raw, envs.len());
        hinges
            .iter()
            .zip(u.chunks_exact(NUM_DOFS))
            .map(|(q, u)| {
                let q: Vec<f64> = q.iter().zip(u).map(|(q, u)| q + scale * f64::from(*u)).collect();
                map.action_for(&q)
            })
            .collect()
    }
}
