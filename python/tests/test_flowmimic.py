"""The Python package against the shipped model and experts: what it returns, that it steers,
that it keeps the binary's recommended settings, and that bad input is refused with a reason.
Run by `make test` (scripts/test-python.sh) after `pip install ./python`."""

import json
import os
import pathlib

import numpy as np
import pytest

import flowmimic

ROOT = pathlib.Path(__file__).resolve().parents[2]
MODEL = ROOT / "pretrained" / "models" / "fm"
EXPERT = ROOT / "pretrained" / "experts" / "walk_straight"
MOCAP = ROOT.parent / "shared" / "data" / "mocap" / "02_01.bvh"


@pytest.fixture(scope="module")
def model():
    return flowmimic.Model(str(MODEL))


def test_model_layout_and_sampling(model):
    assert (model.objective, model.horizon, model.history) == ("fm", 16, 4)
    mean, std = model.normalisation
    assert mean.shape == std.shape == (model.cond_len + model.future_len,)
    assert model.task_labels == []  # the shipped fm is not told its task
    clip = flowmimic.generate("walk", speed=1.0, duration=4.0)
    # A conditioning from the clip: four states, three actions between them (zeros will do for
    # shapes); the same seed gives the same futures, guidance changes them.
    cond = np.zeros((3, model.cond_len), dtype=np.float32)
    a = flowmimic.sample(model, cond, nfe=2, seed=1)
    b = flowmimic.sample(model, cond, nfe=2, seed=1)
    assert a.shape == (3, model.future_len) and np.isfinite(a).all()
    np.testing.assert_array_equal(a, b)
    back = flowmimic.sample(model, cond, nfe=2, seed=1, guidance=50.0, task=flowmimic.task(joystick=(-0.5, 0.0, 0.0)))
    assert np.abs(back - a).max() > 1e-3, "guidance did not change the futures"
    assert len(clip) == 121 and clip.states.shape == (121, flowmimic.STATE_DIM), "4 s at 30 Hz, both ends"


def test_controller_walks_where_the_joystick_says_with_the_models_settings(model):
    walkers = flowmimic.Controller(model, envs=4, task="joystick")
    # The model's recommended joystick settings, as `flowmimic run` prints them.
    recommended = {k: v for k, v in json.loads(model.recommended_json("joystick")).items() if v is not None}
    assert walkers.settings == recommended and recommended["nfe"] == 2
    start = walkers.body_positions()[:, 0, :2].copy()
    for _ in range(90):
        out = walkers.step(flowmimic.task(joystick=(1.0, 0.0, 0.0)))
    assert out.states.shape == (4, flowmimic.STATE_DIM) and out.actions.shape == (4, flowmimic.NUM_DOFS)
    assert out.alive.all() and not out.fell.any()
    walked = np.linalg.norm(walkers.body_positions()[:, 0, :2] - start, axis=1)
    assert (walked > 1.8).all(), f"walked {walked} m in 3 s at 1 m/s asked"
    # The plans ask to walk forward, not back or aside.
    planned = walkers.planned()
    assert planned.shape == (4, 3) and (planned[:, 0] > 0.5).all() and (np.abs(planned[:, 1]) < 0.3).all(), planned
    assert walkers.time == pytest.approx(3.0)
    walkers.reset()
    assert walkers.time == 0.0
    np.testing.assert_allclose(walkers.body_positions()[:, 0, :2], start, atol=1e-9)
    # A flag given wins over the model's.
    assert flowmimic.Controller(model, task="joystick", nfe=5).settings["nfe"] == 5


def test_obstacles_are_solid_and_walked_around(model):
    walkers = flowmimic.Controller(model, envs=2, task="waypoint")
    x, y, heading = walkers.start_pose(0)
    assert abs(heading) < 0.3
    # A post in the way of environment 0 (environment 1 starts 7 frames further on).
    post = flowmimic.cylinder(x + 2.5, y, 0.3)
    goal = (x + 5.0, y)
    touched = 0
    for _ in range(240):
        out = walkers.step([flowmimic.task(waypoint=goal, obstacles=[post]), flowmimic.task(waypoint=goal)])
        touched += int(out.touching[0])
    end = walkers.body_positions()[0, 0, :2]
    assert touched == 0 and out.alive.all()
    assert np.linalg.norm(end - np.array(goal)) < 1.0, f"ended at {end}, goal {goal}"


def test_clips_round_trip_and_import(tmp_path):
    clip = flowmimic.generate("arc", speed=0.8, turn_rate=0.3, duration=3.0)
    path = tmp_path / "arc.clip.safetensors"
    clip.save(str(path))
    again = flowmimic.Clip.load(str(path))
    assert again.name == "arc" and len(again) == len(clip)
    np.testing.assert_array_equal(again.qpos, clip.qpos)
    assert clip.body_positions.shape == (len(clip), 24, 3)
    if MOCAP.exists():
        captured = flowmimic.import_bvh(MOCAP)
        assert captured.name == "02_01" and len(captured) > 30


def test_experts_act_deterministically():
    expert = flowmimic.Expert(str(EXPERT))
    obs = np.random.default_rng(0).normal(size=(5, expert.obs_dim)).astype(np.float32)
    a, b = expert.act(obs), expert.act(obs)
    assert a.shape == (5, flowmimic.NUM_DOFS) and np.isfinite(a).all()
    np.testing.assert_array_equal(a, b)
    assert np.abs(a[0] - a[1]).max() > 0, "actions do not depend on the observation"


def test_bad_input_is_refused_with_a_reason(model, tmp_path):
    with pytest.raises(ValueError, match="no such|model.safetensors|not"):
        flowmimic.Model(str(tmp_path))
    with pytest.raises(ValueError, match="columns"):
        flowmimic.sample(model, np.zeros((2, 3), dtype=np.float32))
    walkers = flowmimic.Controller(model, envs=2)
    with pytest.raises(ValueError, match="1 tasks for 2 environments"):
        walkers.step([flowmimic.task()])
    with pytest.raises(ValueError, match="joystick speed"):
        walkers.step(flowmimic.task(joystick=(9.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match="obstacle"):
        walkers.step(flowmimic.task(obstacles=[flowmimic.cylinder(1.0, 0.0, -0.2)]))
    with pytest.raises(TypeError, match="unknown settings"):
        flowmimic.Controller(model, guidance=3)
    with pytest.raises(ValueError, match="0 environments"):
        flowmimic.Controller(model, envs=0)
    with pytest.raises(ValueError, match="gait"):
        flowmimic.generate("x", speeed=1.0)
    with pytest.raises(ValueError, match="obs"):
        flowmimic.Expert(str(EXPERT)).act(np.zeros((1, 3), dtype=np.float32))
    assert os.path.basename(str(MODEL)) == "fm"


def test_gymnasium_tracking_env_passes_the_checker_and_the_shipped_expert_tracks_in_it():
    gym = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    from flowmimic.gym import TrackingEnv, TrackingVectorEnv

    clip = flowmimic.Clip.load(str(EXPERT / "clip.safetensors"))
    check_env(TrackingEnv(clip, random_start=True), skip_render_check=True)
    # The expert trained by `flowmimic track train` on this clip tracks it to its end here: the
    # environment observes, acts and ends as the trainer's task does.
    env, expert = TrackingEnv(clip), flowmimic.Expert(str(EXPERT))
    obs, info = env.reset(seed=3)
    assert info["frame"] == 0
    rewards, steps = [], 0
    while True:
        obs, reward, terminated, truncated, info = env.step(expert.act(obs[None])[0])
        rewards.append(reward)
        steps += 1
        if terminated or truncated:
            break
    assert truncated and not terminated and steps == len(clip) - 1, f"ended after {steps} of {len(clip) - 1} steps"
    assert np.mean(rewards) > 0.5 * np.max(rewards)
    # Vectorised: 8 at once in Rust threads, ended ones reset in the same step.
    envs = TrackingVectorEnv(clip, num_envs=8, seed=1)
    obs, _ = envs.reset(seed=1)
    assert obs.shape == (8, env.observation_space.shape[0])
    ended = 0
    for _ in range(90):
        # No residuals: PD on the reference alone, which topples within seconds.
        obs, reward, terminated, truncated, info = envs.step(np.zeros((8, flowmimic.NUM_DOFS), np.float32))
        assert reward.shape == (8,) and np.isfinite(obs).all()
        done = terminated | truncated
        if done.any():
            np.testing.assert_array_equal(info["_final_obs"], done)
            assert np.isfinite(info["final_obs"][done]).all()
        ended += int(done.sum())
    assert ended > 0, "no episode ended in 3 s without residuals"
