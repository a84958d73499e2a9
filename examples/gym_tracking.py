"""The tracking task from Gymnasium: the shipped straight-walk expert tracks its clip in
`flowmimic.gym.TrackingVectorEnv`, and the environment's throughput beside `flowmimic bench
track`'s (the PPO trainer's own rollouts), measured in one run:

    pip install './python[gym]'
    python examples/gym_tracking.py [ENVS]

A learner plugs in where the expert acts: any library that takes a Gymnasium vector
environment (observations [E, 295] float32, actions [E, 69], SAME_STEP autoreset).
"""

import pathlib
import subprocess
import sys
import time

import numpy as np

import flowmimic
from flowmimic.gym import TrackingVectorEnv

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXPERT = ROOT / "pretrained" / "experts" / "walk_straight"
envs_n = int(sys.argv[1]) if len(sys.argv) > 1 else 88

clip = flowmimic.Clip.load(str(EXPERT / "clip.safetensors"))
expert = flowmimic.Expert(str(EXPERT))
envs = TrackingVectorEnv(clip, num_envs=envs_n, seed=0)
obs, _ = envs.reset(seed=0)
steps, rewards, ended = 0, [], 0
start = time.perf_counter()
while time.perf_counter() - start < 10.0:
    obs, reward, terminated, truncated, info = envs.step(expert.act(obs))
    steps += envs_n
    rewards.append(reward.mean())
    ended += int(terminated.sum())
seconds = time.perf_counter() - start
print(f"gymnasium: {envs_n} environments, expert acting: {steps / seconds:,.0f} steps/s "
      f"(policy included), mean reward {np.mean(rewards):.2f}, {ended} failures in {steps} steps")
binary = ROOT / "target" / "release" / "flowmimic"
if binary.exists():
    out = subprocess.run([str(binary), "bench", "track", "--iterations", "3"], capture_output=True, text=True)
    print("flowmimic bench track (the trainer's rollouts, same machine, just after):")
    print(out.stdout.strip())
