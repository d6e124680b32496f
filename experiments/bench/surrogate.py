"""`python -m experiments bench-surrogate`: surrogate steps per second, all (grasp, action) pairs of one
waypoint as one vmapped call, against the same jitted step called one pair at a time from Python (a Gym
loop, the paper's execution model), measured side by side in one run."""
from __future__ import annotations

import argparse
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import Run, best_time, table, timed
from gsp_jax.core import files
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--waypoint", type=int, default=7, help="waypoint whose 288 x 17 pairs are stepped")
    p.add_argument("--loop-steps", type=int, default=64,
                   help="pairs stepped one at a time (a sample; rate extrapolated)")
    p.add_argument("--repeats", type=int, default=3, help="timed repeats of the batched call (best is reported)")
    p.add_argument("--out", default=None, help="JSON file for the results (default results/bench_surrogate.json)")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.out else [()]  # results/ itself


def main(args: argparse.Namespace, run: Run) -> None:
    ep = scenario.make_episode(model=run.model)
    env = surrogate.Surrogate(run.model, learned=run.learned)
    n_g, n_a = env.space.n_grasps, env.space.n_actions
    if not 0 <= args.waypoint < ep.n_steps:
        raise SystemExit(f"--waypoint: {args.waypoint} is out of range 0..{ep.n_steps - 1}")
    device = jax.local_devices()[0]
    print(f"device: {device.platform} ({device.device_kind}); host {platform.node()}; jax {jax.__version__}",
          flush=True)

    states = jax.jit(jax.vmap(env.discrete_state, (None, 0, None)))(ep, jnp.arange(n_g), args.waypoint)
    pairs_s = jax.tree.map(lambda x: jnp.repeat(x, n_a, axis=0), states)  # (G*A, ...)
    pairs_a = jnp.tile(jnp.arange(n_a, dtype=jnp.int32), n_g)
    n_pairs = n_g * n_a

    batched = jax.jit(jax.vmap(env.step))
    (_, rew_b, _), compile_b = timed(batched, pairs_s, pairs_a)
    t_b = best_time(batched, pairs_s, pairs_a, repeats=args.repeats)
    print(f"batched: compile+first {compile_b:.2f} s, warm {t_b:.4f} s for {n_pairs} steps", flush=True)

    single = jax.jit(env.step)
    pick = lambda i: jax.tree.map(lambda x: x[i], pairs_s)  # noqa: E731
    _, compile_s = timed(single, pick(0), pairs_a[0])
    rng = np.random.default_rng(0)
    idx = rng.choice(n_pairs, size=min(args.loop_steps, n_pairs), replace=False)
    inputs = [(pick(int(i)), pairs_a[int(i)]) for i in idx]  # slicing done before timing
    t0 = time.perf_counter()
    loop_rewards = []
    for s, a in inputs:  # one env.step() per Python call, as a Gym loop does
        _, r, _ = single(s, a)
        loop_rewards.append(float(r))
    t_loop = time.perf_counter() - t0
    agree = float(np.max(np.abs(np.asarray(loop_rewards) - np.asarray(rew_b)[idx])))
    print(f"one-at-a-time: compile+first {compile_s:.2f} s, {len(idx)} steps in {t_loop:.3f} s; "
          f"max |reward batched - looped| = {agree:.2e}", flush=True)

    rate_b, rate_l = n_pairs / t_b, len(idx) / t_loop
    result = dict(
        device=f"{device.platform}:{device.device_kind}", jax=jax.__version__, waypoint=args.waypoint,
        pairs=n_pairs, batched_s=t_b, batched_steps_per_s=rate_b, batched_compile_s=compile_b,
        loop_steps=len(idx), loop_s=t_loop, loop_steps_per_s=rate_l, loop_compile_s=compile_s,
        speedup=rate_b / rate_l, full_table_loop_s_extrapolated=n_pairs * ep.n_steps / rate_l,
        full_table_batched_s=t_b * ep.n_steps, max_reward_diff=agree,
    )
    out = args.out or str(run.results_dir() / "bench_surrogate.json")
    files.write_json(out, result)
    print(f"wrote {out}")
    run.record_figures("bench_surrogate", result)
    print()
    print(table(
        ["mode", "steps", "wall [s]", "steps/s", f"{n_g}x{n_a}x{ep.n_steps} table by steps [s]"],
        [
            ["vmapped (one call)", n_pairs, t_b, f"{rate_b:,.0f}", f"{t_b * ep.n_steps:.2f}"],
            ["one at a time (Gym loop)", len(idx), t_loop, f"{rate_l:,.1f}",
             f"{n_pairs * ep.n_steps / rate_l:.1f} (extrapolated)"],
            ["speed-up", "", "", f"{rate_b / rate_l:,.0f}x", ""],
        ],
    ))
