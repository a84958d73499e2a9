"""Gymnasium environments for the tracking task `flowmimic track train` learns: the humanoid
tracks a clip in MuJoCo, observing itself and the reference ahead, acting with residuals on the
reference's next pose. The work is `flowmimic._flowmimic.Tracking` (the track crate).

    from flowmimic.gym import TrackingEnv, TrackingVectorEnv
    env = TrackingEnv(flowmimic.generate("walk", duration=4.0))
    envs = TrackingVectorEnv(clip, num_envs=64)      # stepped in Rust threads

Reward: BeyondMimic's tracking terms (`flowmimic config` lists their weights). Termination: the
tracking failed (pelvis or an end effector more than 0.25 m off in height, or the pelvis tilted
0.8 off the reference's) or physics diverged. Truncation: the clip's end.
"""

from typing import Any, Dict, Optional, Tuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from ._flowmimic import NUM_DOFS, Clip, Tracking

# Residuals beyond this many action scales (0.15 rad each) are clipped by the joint targets'
# range anyway; the bound only tells learners the scale.
ACTION_BOUND = 10.0


def _spaces(obs_dim: int) -> Tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32)
    act = spaces.Box(-ACTION_BOUND, ACTION_BOUND, (NUM_DOFS,), np.float32)
    return obs, act


class TrackingEnv(gym.Env):
    """One humanoid tracking `clip`. `kicks`: a random push of up to 0.5 m/s every second;
    `random_start`: episodes start at a random frame (reference state initialisation);
    `observe_ahead`: observations hold the reference 1/3 s and 1 s ahead too."""

    metadata: Dict[str, Any] = {"render_modes": []}

    def __init__(
        self, clip: Clip, kicks: bool = False, random_start: bool = False, seed: int = 0, observe_ahead: bool = False
    ):
        self._task = Tracking(clip, 1, kicks, random_start, seed, observe_ahead)
        self.observation_space, self.action_space = _spaces(self._task.obs_dim)

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None):
        super().reset(seed=seed)
        obs = self._task.reset_env(0, seed)
        return obs, {"frame": int(self._task.frames[0])}

    def step(self, action):
        u = np.ascontiguousarray(np.asarray(action, dtype=np.float32).reshape(1, NUM_DOFS))
        obs, reward, terminated, truncated = self._task.step(u)
        info = {"frame": int(self._task.frames[0])}
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info


class TrackingVectorEnv(VectorEnv):
    """`num_envs` humanoids tracking `clip`, stepped together in Rust threads. An environment
    that ends is reset in the same step (`autoreset_mode` SAME_STEP): its last observation is in
    `info["final_obs"]` where `info["_final_obs"]` is set."""

    metadata: Dict[str, Any] = {"render_modes": [], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        clip: Clip,
        num_envs: int,
        kicks: bool = False,
        random_start: bool = True,
        seed: int = 0,
        observe_ahead: bool = False,
    ):
        self._task = Tracking(clip, num_envs, kicks, random_start, seed, observe_ahead)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self._task.obs_dim)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None):
        obs = np.stack([self._task.reset_env(e, None if seed is None else seed + e) for e in range(self.num_envs)])
        return obs, {}

    def step(self, actions):
        u = np.ascontiguousarray(np.asarray(actions, dtype=np.float32).reshape(self.num_envs, NUM_DOFS))
        obs, reward, terminated, truncated = self._task.step(u)
        ended = terminated | truncated
        info: Dict[str, Any] = {}
        if ended.any():
            info["final_obs"] = np.where(ended[:, None], obs, np.nan).astype(np.float32)
            info["_final_obs"] = ended
            for e in np.flatnonzero(ended):
                obs[e] = self._task.reset_env(int(e))
        return obs, reward.astype(np.float64), terminated, truncated, info
