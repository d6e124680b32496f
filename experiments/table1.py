"""`python -m experiments table1 [--set eval] [--batch N] [--repeats K]`: the paper's Table 1, online wall-clock
time per unseen episode.

For each policy, the time to plan and run one unseen episode through the surrogate from its start, as an online
planner would: DP baseline and RL act per step (a sequence lookup, one network call) and step the surrogate; L1 and
L2 first build the episode's table (`--lookahead cached`, the default), then at every step search from the
surrogate's state with the tree's interior and rollouts as lookups in it (`continuous`: all in the surrogate), and
move the episode on to the searched root child of the chosen action (the search has already stepped the surrogate
with every action: `lookahead.rollout_planned`); DP optimal first builds the episode's whole table and backs it up,
then runs its policy in that table: from its start the surrogate visits only the table's discrete states, so the
table steps the episode exactly as the surrogate would (`tests/test_env.py` checks the two step for step) and the
surrogate's 16 steps would recompute what the table holds. Compilation (once per program, reused for every later
episode of the same length) is shown apart from the warm time (fastest of `--repeats` calls). With `--batch N`, also
the time per episode when N unseen episodes are planned in one vmapped call. Writes results/table1/<platform>.json;
prints the table, beside the paper's, last.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import jax

from experiments import evaluation
from experiments.common import results_dir, table
from gsp_jax import dp, lookahead, policies
from gsp_jax.env import TableModel


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", choices=["evalA", "evalB", "eval"])
    p.add_argument("--batch", type=int, default=0, help="also time N episodes planned in one vmapped call (0: skip)")
    p.add_argument("--repeats", type=int, default=None, help="warm calls per measurement (default 3 on a GPU, 1 on CPU)")
    p.add_argument("--policy-dir", default=None)
    evaluation.add_lookahead_argument(p)


def planner(ctx: evaluation.Context, name: str, cached: bool = True):
    """episode -> return for policy `name`, planned online on the surrogate. With `cached`, L1 and L2 first
    build the unseen episode's table (as DP optimal does) and search below the root by lookups in it."""
    sur = ctx.surrogate
    if name == "dp-opt":  # solve the unseen episode's whole table, then run its policy in that table
        def plan(ep):
            table, sol = dp.solve(sur, ep)
            model = TableModel(table, sur.space)  # from its start the surrogate only visits the table's states
            return lookahead.rollout(model, policies.TablePolicy(sol.policy), model.reset(ep))[0]
        return plan
    policy, _ = evaluation.make(ctx, name, cached=False)
    if name in evaluation.LOOKAHEAD_DEPTH:  # each decision's search has stepped every action: the episode moves on
        def plan(ep):                       # to its child (`rollout_planned`) instead of stepping the surrogate again
            # cached: the unseen episode's table is built inside the timed call
            searcher = policy.replace(inner=TableModel(dp.build_table(sur, ep), sur.space)) if cached else policy
            return lookahead.rollout_planned(searcher, sur.reset(ep))[0]
        return plan
    return lambda ep: lookahead.rollout(sur, policy, sur.reset(ep))[0]


def measure(fn, arg, repeats: int) -> tuple[float, float]:
    """(compile s, warm s) of jit(fn)(arg)."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(arg).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(arg))  # first run (allocations)
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(arg))
        warm.append(time.perf_counter() - t0)
    return compile_s, min(warm)


def run(ctx: evaluation.Context, batch: int, repeats: int, out, cached: bool = True) -> dict:
    t_start = time.perf_counter()
    one = jax.tree.map(lambda x: x[0], ctx.batch)
    rows = {}
    for name in evaluation.POLICIES:
        fn = planner(ctx, name, cached)
        compile_s, warm = measure(fn, one, repeats)
        row = dict(warm_s=warm, compile_s=compile_s)
        if batch:
            n = min(batch, len(ctx.names))
            many = jax.tree.map(lambda x: x[:n], ctx.batch)
            c_b, w_b = measure(jax.vmap(fn), many, repeats)
            row |= dict(batch=n, batch_warm_s=w_b, batch_compile_s=c_b, batch_per_episode_s=w_b / n)
        rows[name] = row
        print(f"  {name:8s} warm {warm:9.4f} s   compile {compile_s:7.1f} s" +
              (f"   batch of {row['batch']}: {row['batch_per_episode_s']:.4f} s per episode" if batch else ""), flush=True)
    device = jax.devices()[0]
    result = dict(platform=device.platform, device=str(device.device_kind), episode=ctx.names[0], repeats=repeats,
                  lookahead="cached" if cached else "continuous",
                  policies=rows, paper=evaluation.PAPER, wall_s=time.perf_counter() - t_start)
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        result["note"] = "JAX's persistent compilation cache was on (JAX_COMPILATION_CACHE_DIR): compile times may be cache hits"
    (out / f"{device.platform}.json").write_text(json.dumps(result, indent=1))
    return result


def print_result(result: dict) -> None:
    batched = any("batch" in r for r in result["policies"].values())
    headers = ["policy", "paper [s]", f"ours warm [s] ({result['platform']})", "compile [s]"]
    headers += ["per episode, batched [s]"] if batched else []
    rows = []
    for name, r in result["policies"].items():
        row = [name, evaluation.PAPER["table1_s"][name], f"{r['warm_s']:.4f}", f"{r['compile_s']:.1f}"]
        rows.append(row + ([f"{r['batch_per_episode_s']:.4f} (of {r['batch']})"] if batched else []))
    print(f"Table 1: online wall-clock per unseen episode ({result['device']}; paper: {evaluation.PAPER['table1_machine']})")
    print(table(headers, rows, ".2f"))


def main(args: argparse.Namespace) -> None:
    repeats = args.repeats or (3 if jax.default_backend() == "gpu" else 1)
    ctx = evaluation.context(args.set, 1 if not args.batch else args.batch, args.policy_dir)
    print(f"Table 1 on {jax.devices()[0].device_kind}: episode {ctx.names[0]} ...", flush=True)
    result = run(ctx, args.batch, repeats, results_dir("table1"), cached=args.lookahead == "cached")
    print_result(result)
