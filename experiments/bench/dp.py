"""`python -m experiments bench-dp`: time to solve DP (table + Bellman backup) for one unseen episode and for
the 27 evaluation episodes in one batch, beside the paper's way of building the table (one `env.step()` per
(grasp, action, time): a sample of such calls, extrapolated to all 288 x 17 x 16), in one run."""
from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from experiments.common import Run, best_time, table, timed
from gsp_jax.planning import dp
from gsp_jax.core import files
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate

PAPER_DP_SECONDS = 151.79  # DP optimal per unseen episode, 32-core Xeon (paper Table 1)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", type=int, default=27, help="evaluation episodes in the batch (27 = A + B)")
    p.add_argument("--loop-steps", type=int, default=64, help="env.step() calls sampled for the step-at-a-time table")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=None)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.out else [()]  # results/ itself


def main(args: argparse.Namespace, run: Run) -> None:
    env = surrogate.Surrogate(run.model, learned=run.learned)
    evals = list(scenario.episode_set("eval", env.model).values())[: args.episodes]
    device = jax.local_devices()[0]
    print(f"device: {device.platform} ({device.device_kind}); jax {jax.__version__}", flush=True)

    one = jax.jit(lambda e: dp.solve(env, e))
    _, compile_one = timed(one, evals[0])
    t_one = best_time(one, evals[0], repeats=args.repeats)
    print(f"one episode: compile+first {compile_one:.1f} s, warm {t_one:.3f} s", flush=True)

    batch = scenario.stack(evals)
    many = jax.jit(jax.vmap(lambda e: dp.solve(env, e)))
    _, compile_many = timed(many, batch)
    t_many = best_time(many, batch, repeats=args.repeats - 1)
    print(f"{len(evals)} episodes batched: compile+first {compile_many:.1f} s, warm {t_many:.3f} s", flush=True)

    # the paper's way: one env.step() per (grasp, action, t), called from Python
    ep = evals[0]
    n_g, n_a, n_t = env.space.n_grasps, env.space.n_actions, ep.n_steps
    state_at = jax.jit(env.discrete_state)
    step = jax.jit(env.step)
    rng = np.random.default_rng(0)
    samples = [(int(rng.integers(n_g)), int(rng.integers(n_a)), int(rng.integers(n_t))) for _ in range(args.loop_steps)]
    states = [state_at(ep, g, t) for g, _, t in samples]
    jax.block_until_ready(step(states[0], samples[0][1]))  # compile
    t0 = time.perf_counter()
    for s, (_, a, _) in zip(states, samples):
        jax.block_until_ready(step(s, a))
    per_step = (time.perf_counter() - t0) / len(samples)
    t_loop = per_step * n_g * n_a * n_t
    print(f"step-at-a-time: {per_step * 1e3:.2f} ms per env.step() -> {t_loop:.0f} s for the table (extrapolated "
          f"from {len(samples)} calls)", flush=True)

    result = dict(
        device=f"{device.platform}:{device.device_kind}", one_episode_s=t_one, one_episode_compile_s=compile_one,
        batch_episodes=len(evals), batch_s=t_many, batch_compile_s=compile_many,
        per_episode_in_batch_s=t_many / len(evals),
        loop_step_s=per_step, loop_table_s_extrapolated=t_loop, speedup_one=t_loop / t_one,
        speedup_batched=t_loop / (t_many / len(evals)), paper_s=PAPER_DP_SECONDS,
    )
    out = args.out or str(run.results_dir() / "bench_dp.json")
    files.write_json(out, result)
    print(f"wrote {out}\n")
    run.record_figures("bench_dp", result)
    print(table(
        ["DP solve (table + backup)", "wall [s]", "per episode [s]", "vs step-at-a-time"],
        [
            ["step-at-a-time table (extrapolated)", f"{t_loop:.1f}", f"{t_loop:.1f}", "1x"],
            ["one episode, vmapped", t_one, t_one, f"{t_loop / t_one:,.0f}x"],
            [f"{len(evals)} episodes, one batch", t_many, t_many / len(evals), f"{t_loop * len(evals) / t_many:,.0f}x"],
            ["paper (32-core Xeon)", PAPER_DP_SECONDS, PAPER_DP_SECONDS, ""],
        ],
    ))
