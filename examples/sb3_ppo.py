"""Stable-Baselines3 PPO on the registered Gymnasium environment, in a few lines.

    pip install -e ".[sb3]"              # SB3 (and PyTorch): an optional extra, not needed by gsp_jax itself
    python examples/sb3_ppo.py --steps 30000

Trains on the 9 training episodes (table backend: exact DP-table lookups), then prints the deterministic
policy's return on each of them, their mean, and the training steps/s. For reference: the DP optimum of the
training set is about -0.92 per episode, the DP baseline's about -1.80; -200 is a dropped tool.
"""
from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import PPO

import gsp_jax

gsp_jax.register_gymnasium()  # gsp_jax/GraspSequence-v0

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("--steps", type=int, default=30_000)
parser.add_argument("--seed", type=int, default=0)
args = parser.parse_args()

torch.set_num_threads(1)  # a 64x64 MLP: on a busy 2-core CPU, two threads made PPO's update 17x slower
env = gym.make("gsp_jax/GraspSequence-v0", episodes="train", backend="table")  # builds 9 DP tables (~2 min on CPU)
model = PPO("MlpPolicy", env, seed=args.seed, device="cpu", verbose=0)
t0 = time.perf_counter()
model.learn(total_timesteps=args.steps)
seconds = time.perf_counter() - t0

returns = []
for i in range(env.unwrapped.env.n_episodes):  # each training episode once, deterministic actions
    obs, _ = env.reset(options={"episode": i})
    total, done = 0.0, False
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(int(action))
        total, done = total + reward, terminated or truncated
    returns.append(total)
print("returns per training episode:", np.round(returns, 3).tolist())
print(f"SB3 PPO, {args.steps} steps in {seconds:.1f} s ({args.steps / seconds:.0f} steps/s): "
      f"mean deterministic return {np.mean(returns):.3f}")
