"""`python -m experiments bench-ppo`: PPO throughput and time to a target.

1. Environment steps per second inside a training iteration (rollout + update, one jitted call), for the table
   backend that training uses and for the surrogate backend (three IK and four wrench solves per step), beside a
   one-environment-at-a-time Gymnasium loop over the same MDP.
2. Wall-clock time for PPO, with and without DP pretraining, until the deterministic policy's mean return on
   the training set reaches the DP baseline's (the nominal optimal sequence replayed), validating every
   iteration. Compilation and pretraining are included and also shown apart.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import numpy as np

from experiments import common
from experiments.common import Run, best_time, table
from gsp_jax.planning import evaluation
from gsp_jax.learning.env import GraspEnv
from gsp_jax.learning.gym_env import GymGraspEnv
from gsp_jax.learning import pipeline
from gsp_jax.ppo import train as ppo
from gsp_jax.surrogate.step import Surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=sorted(pipeline.PRESETS), default=None, help="default: full on a GPU")
    p.add_argument("--surrogate-envs", type=int, default=None, help="envs for the surrogate-backend iteration")
    p.add_argument("--max-iterations", type=int, default=None, help="cap for the time-to-target runs")
    p.add_argument("--seed", type=int, default=0)


def iteration_rate(s, env, n_envs: int) -> tuple[float, float]:
    """(env steps/s warm, compile+first-call seconds) of one PPO iteration with n_envs environments."""
    cfg = dataclasses.replace(s.ppo_config, n_envs=n_envs, minibatches=min(s.ppo_config.minibatches, n_envs))
    trainer = ppo.Trainer(env, s.networks, cfg, {"val": s.eval_envs["val"]})
    ts = trainer.init(jax.random.PRNGKey(0))
    t0 = time.perf_counter()
    ts, _ = jax.block_until_ready(trainer.iteration(ts))
    compile_s = time.perf_counter() - t0
    dt = best_time(lambda x: trainer.iteration(x)[0], ts)
    return n_envs * cfg.unroll / dt, compile_s


def gym_rate(s, n_steps: int) -> float:
    g = GymGraspEnv(s.env)
    g.reset(seed=0)
    g.step(0)  # compile
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for _ in range(n_steps):
        _, _, term, _, _ = g.step(int(rng.integers(g.action_space.n)))
        if term:
            g.reset()
    return n_steps / (time.perf_counter() - t0)


def time_to_baseline(s, mode: str, seed: int, max_iterations: int | None) -> dict:
    target = s.reference["train"]["dp_baseline"]
    cfg = dataclasses.replace(pipeline.ppo_config(s, mode), eval_every=1, patience=0,
                              max_iterations=max_iterations or s.ppo_config.max_iterations)
    t0 = time.perf_counter()
    params = None
    bc_s = 0.0
    if mode == "dp":
        params, _ = pipeline.pretrained(s, seed, progress=False)
        bc_s = time.perf_counter() - t0
    trainer = ppo.Trainer(s.env, s.networks, cfg, s.eval_envs)
    result = ppo.train(trainer, seed, params=params, progress=False,
                       stop_when=lambda r: r.get("train_greedy_return", -np.inf) >= target)
    h = result.history
    hit = next((r for r in h if r.get("train_greedy_return", -np.inf) >= target), None)
    first = h[1]["wall_s"] if len(h) > 1 else float("nan")
    return {
        "mode": mode,
        "reached": hit is not None,
        "iteration": hit["iteration"] if hit else None,
        "wall_s": bc_s + (hit["wall_s"] if hit else h[-1]["wall_s"]),
        "pretrain_s": bc_s,
        "first_iteration_s": first,
        "final_train_greedy_return": h[-1].get("train_greedy_return"),
    }


def main(args: argparse.Namespace, run: Run) -> None:
    gpu = jax.default_backend() == "gpu"
    preset = args.preset or ("full" if gpu else "quick")
    s = pipeline.setup(preset, table_cache=common.RESULTS / evaluation.TABLES,
                       surrogate=Surrogate(run.model, learned=run.learned))
    n_envs = s.ppo_config.n_envs
    sur_envs = args.surrogate_envs or (1024 if gpu else 16)
    print(f"device: {jax.local_devices()[0].device_kind} ({jax.default_backend()}); preset {preset}")

    table_rate, table_compile = iteration_rate(s, s.env, n_envs)
    sur_env = GraspEnv(s.surrogate, s.env.episodes)  # no tables: IK + wrench solves every step
    sur_rate, sur_compile = iteration_rate(s, sur_env, sur_envs)
    loop_rate = gym_rate(s, 2000 if gpu else 500)
    rows = [
        ["PPO iteration, table backend", n_envs, table_rate, table_compile],
        ["PPO iteration, surrogate backend", sur_envs, sur_rate, sur_compile],
        ["Gymnasium loop, one env, table backend (env only)", 1, loop_rate, float("nan")],
    ]
    target = s.reference["train"]["dp_baseline"]
    runs = [time_to_baseline(s, m, args.seed, args.max_iterations) for m in ("none", "dp")]
    print(f"\nDP-baseline mean return on the training set: {target:.3f}")
    print(table(
        ["PPO", "reached", "iteration", "wall s (all)", "pretraining s", "first iteration s (compile)",
         "final greedy train return"],
        [[r["mode"], r["reached"], str(r["iteration"]), r["wall_s"], r["pretrain_s"], r["first_iteration_s"],
          r["final_train_greedy_return"]] for r in runs],
    ))
    steps_per_s = {r[0]: dict(envs=r[1], steps_per_s=r[2], compile_s=r[3]) for r in rows}
    run.record_figures("bench_ppo", dict(preset=preset, steps_per_s=steps_per_s, time_to_baseline=runs))
    print(f"\ntable backend: {table_rate / loop_rate:,.0f}x the one-env loop; "
          f"{table_rate / sur_rate:,.0f}x the surrogate backend\n")
    print(table(["env steps/s", "envs", "steps/s", "compile s"], rows, floatfmt=",.1f"))
