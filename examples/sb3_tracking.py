"""Training a tracker with a standard Python RL library: Stable-Baselines3's PPO (PyTorch) on
`flowmimic.gym.TrackingVectorEnv` (64 humanoids stepped in Rust threads), its first iterations,
then `flowmimic track train` on the same clip for as many environment steps, side by side:

    pip install './python[gym]' stable-baselines3
    python examples/sb3_tracking.py [STEPS]        # 65,536 environment steps by default

Both learn the same task (the same observations, reward, terminations and clip, the 10 s
straight walk), with the cpu preset's sizes (64 environments, 32 steps per update, 5 epochs of
4 minibatches, a 256-128-64 policy); SB3's PPO is its own (its normalisation, its log-std).
"""

import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

import flowmimic
from flowmimic.gym import TrackingVectorEnv

ROOT = pathlib.Path(__file__).resolve().parents[1]
STEPS = int(sys.argv[1]) if len(sys.argv) > 1 else 65_536
ENVS, HORIZON = 64, 32


class SB3Adapter(VecEnv):
    """A Gymnasium vector environment as SB3's VecEnv (whose step returns one `done` and puts the
    last observation of an ended episode in `info["terminal_observation"]`)."""

    def __init__(self, envs: TrackingVectorEnv):
        self.envs = envs
        super().__init__(envs.num_envs, envs.single_observation_space, envs.single_action_space)

    def reset(self):
        return self.envs.reset(seed=0)[0]

    def step_async(self, actions):
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.envs.step(self._actions)
        infos = [{} for _ in range(self.num_envs)]
        for e in np.flatnonzero(terminated | truncated):
            infos[e] = {"terminal_observation": info["final_obs"][e], "TimeLimit.truncated": bool(truncated[e])}
        return obs, reward.astype(np.float32), terminated | truncated, infos

    def close(self):
        pass

    def get_attr(self, name, indices=None):
        return [getattr(self, name)] * self.num_envs

    def set_attr(self, name, value, indices=None):
        setattr(self, name, value)

    def env_method(self, name, *args, indices=None, **kwargs):
        raise NotImplementedError(name)

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * self.num_envs


class Progress(BaseCallback):
    """Prints each update's mean step reward and episode length, as `flowmimic track train` does."""

    def __init__(self):
        super().__init__()
        self.rewards, self.ended, self.started = [], 0, time.perf_counter()

    def _on_step(self):
        self.rewards.append(float(np.mean(self.locals["rewards"])))
        self.ended += int(np.sum(self.locals["dones"]))
        return True

    def _on_rollout_end(self):
        steps = self.num_timesteps
        rate = steps / (time.perf_counter() - self.started)
        print(f"sb3 [{steps:>8} steps]  reward {np.mean(self.rewards):.3f}  episodes ended {self.ended:>4}  {rate:,.0f} steps/s")
        self.rewards, self.ended = [], 0


clip = flowmimic.generate("walk", speed=1.0, duration=10.0)
envs = VecNormalize(SB3Adapter(TrackingVectorEnv(clip, num_envs=ENVS, seed=0)), norm_reward=False)
learner = PPO(
    "MlpPolicy",
    envs,
    n_steps=HORIZON,
    batch_size=ENVS * HORIZON // 4,
    n_epochs=5,
    learning_rate=1e-3,
    target_kl=0.02,
    policy_kwargs={"net_arch": [256, 128, 64], "log_std_init": -0.5},
    device="cpu",
    seed=0,
    verbose=0,
)
start = time.perf_counter()
learner.learn(total_timesteps=STEPS, callback=Progress())
sb3 = time.perf_counter() - start
print(f"sb3: {STEPS:,} steps in {sb3:.1f} s: {STEPS / sb3:,.0f} steps/s (simulation, policy and updates)")

binary = ROOT / "target" / "release" / "flowmimic"
if binary.exists():
    with tempfile.TemporaryDirectory() as out:
        clip.save(f"{out}/walk.clip.safetensors")
        iterations = str(max(1, STEPS // (ENVS * HORIZON)))
        command = [str(binary), "track", "train", "--clip", f"{out}/walk.clip.safetensors", "-o", f"{out}/run", "--iterations", iterations]
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        seconds = time.perf_counter() - start
        lines = [l for l in done.stderr.splitlines() + done.stdout.splitlines() if l.startswith("[")]
        print("\n".join(lines[-3:]))
        print(f"flowmimic track train: {STEPS:,} steps in {seconds:.1f} s: {STEPS / seconds:,.0f} steps/s (same machine, just after)")
