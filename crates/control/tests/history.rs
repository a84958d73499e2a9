//! The live history equals the training window's history part on the same steps.

use flowmimic_control::History;
use flowmimic_data::Shard;
use flowmimic_data::window::{WindowSpec, window, window_starts};
use flowmimic_sim::{Humanoid, NUM_DOFS, STATE_DIM, SimConfig};

#[test]
fn live_history_matches_training_windows() {
    let h = Humanoid::new(SimConfig::default()).unwrap();
    let mut env = h.env();
    let mut v = vec![0.0; h.nv()];
    v[0] = 0.8;
    v[5] = 1.0;
    env.reset(&h.standing_qpos(), &v).unwrap();
    let spec = WindowSpec { history: 3, horizon: 2 };
    let mut history = History::new(spec);
    let mut shard = Shard::default();
    let mut live = Vec::new();
    for s in 0..12 {
        let k = env.bodies();
        history.observe(&k);
        live.push(history.conditioning());
        let a: Vec<f32> = (0..NUM_DOFS).map(|i| 0.2 * ((s * 5 + i) as f32 * 0.4).sin()).collect();
        history.act(&a);
        let root = k.pos[0];
        shard.state.extend_from_slice(&k.state());
        shard.action.extend_from_slice(&a);
        shard.noisy_action.extend_from_slice(&a);
        shard.root_pose.extend_from_slice(&[root.x as f32, root.y as f32, flowmimic_geom::heading(k.rot[0]) as f32]);
        shard.done.push(u8::from(s == 11));
        shard.sigma.push(0.0);
        shard.rollout.push(0);
        shard.frame.push(s as u32);
        env.step(&a).unwrap();
    }
    let starts = window_starts(&shard, spec);
    assert!(!starts.is_empty());
    for t in starts {
        let w = window(&shard, spec, t);
        let (states, actions) = &live[t];
        assert_eq!(&w.states[..(spec.history + 1) * STATE_DIM], &states[..], "states at step {t}");
        assert_eq!(&w.actions[..spec.history * NUM_DOFS], &actions[..], "actions at step {t}");
    }
    // Before N + 1 steps the oldest state stands in for the missing ones.
    assert!(!History::new(spec).is_full());
    let (early, _) = &live[0];
    assert_eq!(early[..STATE_DIM], early[spec.history * STATE_DIM..]);
}
