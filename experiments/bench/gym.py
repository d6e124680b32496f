"""`python -m experiments bench-gym`: Gymnasium vector env throughput, the native one against SyncVectorEnv.

Both run the registered environment over the 9 training episodes with the table backend (cached DP tables),
random actions from a seeded generator, autoreset on. The native `GraspVectorEnv` steps all N environments as one
jitted, vmapped call; Gymnasium's `SyncVectorEnv` steps N `GymGraspEnv`s one after another (one Python step and one
dispatch of the shared compiled single-environment step each). Steps/s counts environment steps (N per vector
step), warm (one step first to compile), over about `--seconds` each; the table is printed last.
"""
from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

from experiments import common
from experiments.common import Run, table
from gsp_jax.planning import evaluation
from gsp_jax.model import scenario
from gsp_jax.learning.env import GraspEnv
from gsp_jax.planning.evaluation import dp_tables
from gsp_jax.learning.gym_env import GraspVectorEnv, GymGraspEnv
from gsp_jax.surrogate.step import Surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--envs", type=int, nargs="+", default=[1, 4, 16, 64, 256, 1024])
    p.add_argument("--sync-max", type=int, default=1024, help="largest N for SyncVectorEnv (it is slow)")
    p.add_argument("--seconds", type=float, default=3.0, help="time per measurement")


def rate(envs, n: int, seconds: float) -> float:
    """Environment steps per second over about `seconds` of random actions (after one warm-up step)."""
    rng = np.random.default_rng(0)
    envs.reset(seed=0)
    envs.step(rng.integers(0, envs.single_action_space.n, n))
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        envs.step(rng.integers(0, envs.single_action_space.n, n))
        steps += n
    return steps / (time.perf_counter() - t0)


def main(args, run: Run) -> None:
    sur = Surrogate(run.model, learned=run.learned)
    eps = scenario.training_set(sur.model)
    tables = dp_tables(sur, "train", eps, cache=common.RESULTS / evaluation.TABLES)
    env = GraspEnv(sur, scenario.stack(list(eps.values())), tables, auto_reset=False)
    rows = []
    for n in args.envs:
        native = rate(GraspVectorEnv(env, n), n, args.seconds)
        sync = None
        if n <= args.sync_max:
            sync = rate(gym.vector.SyncVectorEnv([lambda: GymGraspEnv(env) for _ in range(n)]), n, args.seconds)
        rows.append([n, f"{native:,.0f}", f"{sync:,.0f}" if sync else "-", f"{native / sync:.1f}x" if sync else "-"])
        print(f"  N = {n}: native {native:,.0f} steps/s" + (f", SyncVectorEnv {sync:,.0f}" if sync else ""), flush=True)
    run.record_figures("bench_gym", dict(rows=rows))
    print("\nGymnasium vector envs, table backend, 9 training episodes (env steps/s, warm)\n")
    print(table(["N envs", "GraspVectorEnv (vmapped)", "SyncVectorEnv", "speed-up"], rows))
