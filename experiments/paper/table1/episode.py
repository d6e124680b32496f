"""Table 1's measure: the online wall-clock time of one unseen episode per planner, one jitted call from the
episode's start (see the `table1` command for what each planner does inside it).

    result = run(ctx, batch, repeats, out, lookahead="table")   # {policies: {name: {warm_s, compile_s, ...}}, ...}
"""
from __future__ import annotations

import dataclasses
import os
import time

import jax

from experiments import common
from experiments.common import table
from gsp_jax.planning import evaluation
from gsp_jax.core import files
from gsp_jax.planners import online, registry as planners

GPU_IK_UNROLL = 3  # IK iterations per loop trip on a GPU (`IKConfig.unroll`): each trip of XLA's loop costs a sync on
# the device, and more iterations a trip compile longer for little more; the same episodes at every unroll
# (timings: docs/lookahead.md)
PAPER = planners.names("paper")  # Table 1's rows: the paper's five planners, in its order
def before(ctx: evaluation.Context) -> evaluation.Context:
    """The context as the code stood before the batch-last IK: the table's IK `ik.solve` vmapped on every platform
    (not the CPU's batch-last form, `ik_lanes`); with `lookahead="cached"` its L1 and L2 are the planners of then."""
    return _with_ik_config(ctx, lanes=False)


def _with_ik_config(ctx: evaluation.Context, **changes) -> evaluation.Context:
    """The context with its surrogate's `IKConfig` fields replaced by `changes`."""
    sur = ctx.surrogate
    ik_config = dataclasses.replace(sur.ik_config, **changes)
    return dataclasses.replace(ctx, surrogate=sur.replace(ik_config=ik_config))


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


def run(ctx: evaluation.Context, batch: int, repeats: int, out, lookahead: str = "table",
        names=PAPER, ahead: int | None = None, compare_before: bool = False) -> dict:
    ahead = online.default_ahead() if ahead is None else ahead
    t_start = time.perf_counter()
    one = jax.tree.map(lambda x: x[0], ctx.batch)
    rows = {}
    for name in names:
        batched = online.default_batched(name)
        fn = online.episode_planner(ctx, name, lookahead, batched, ahead)
        compile_s, warm = measure(fn, one, repeats)
        row = dict(warm_s=warm, compile_s=compile_s)
        if name in online.BATCHED:  # both forms, side by side; warm_s is the platform's default
            other = measure(online.episode_planner(ctx, name, lookahead, not batched, ahead), one, repeats)[1]
            row |= dict(rollout="batched" if batched else "stepped", batched_warm_s=warm if batched else other,
                        stepped_warm_s=other if batched else warm)
        if compare_before and name in ("dp-opt", "L1", "L2"):  # the code before, in the same run
            c_old, w_old = measure(online.episode_planner(before(ctx), name, "cached", batched, ahead), one, repeats)
            row |= dict(before_warm_s=w_old, before_compile_s=c_old, speedup=w_old / warm)
        if batch:
            n = min(batch, len(ctx.names))
            many = jax.tree.map(lambda x: x[:n], ctx.batch)
            c_b, w_b = measure(jax.vmap(fn), many, repeats)
            row |= dict(batch=n, batch_warm_s=w_b, batch_compile_s=c_b, batch_per_episode_s=w_b / n)
        rows[name] = row
        print(f"  {name:8s} warm {warm:9.4f} s   compile {compile_s:7.1f} s" +
              (f"   (stepped {row['stepped_warm_s']:.4f} s, batched steps {row['batched_warm_s']:.4f} s)"
               if name in online.BATCHED else "") +
              (f"   before: {row['before_warm_s']:.4f} s ({row['speedup']:.1f}x)" if "before_warm_s" in row else "") +
              (f"   batch of {row['batch']}: {row['batch_per_episode_s']:.4f} s per episode" if batch else ""),
              flush=True)
    device = jax.local_devices()[0]
    result = dict(platform=device.platform, device=str(device.device_kind), episode=ctx.names[0], repeats=repeats,
                  ik_unroll=ctx.surrogate.ik_config.unroll, ahead=ahead, lookahead=lookahead,
                  policies=rows, paper=common.PAPER, wall_s=time.perf_counter() - t_start)
    if jax.default_backend() == "cpu":
        result["cores"] = os.cpu_count()
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        result["note"] = ("JAX's persistent compilation cache was on (JAX_COMPILATION_CACHE_DIR): "
                          "compile times may be cache hits")
    files.write_json(out / f"{device.platform}.json", result)
    return result


def figures(result: dict) -> dict:
    """Table 1's figures for docs/data: per policy, the warm online time of one unseen episode [s]."""
    return dict(episode=result["episode"], lookahead=result.get("lookahead"),
                warm_s={name: r["warm_s"] for name, r in result["policies"].items()},
                paper_s=result["paper"]["table1_s"])


def print_result(result: dict) -> None:
    batched = any("batch" in r for r in result["policies"].values())
    before = any("before_warm_s" in r for r in result["policies"].values())
    headers = ["policy", "paper [s]", f"ours warm [s] ({result['platform']})", "stepped / batched steps [s]",
               "compile [s]"]
    headers += ["per episode, batched [s]"] if batched else []
    headers += ["before issue 37 [s]", "speed-up"] if before else []
    rows = []
    for name, r in result["policies"].items():
        forms = f"{r['stepped_warm_s']:.4f} / {r['batched_warm_s']:.4f}" if "rollout" in r else "-"
        row = [name, common.PAPER["table1_s"][name], f"{r['warm_s']:.4f}", forms, f"{r['compile_s']:.1f}"]
        row += [f"{r['batch_per_episode_s']:.4f} (of {r['batch']})"] if batched else []
        row += (([f"{r['before_warm_s']:.4f}", f"{r['speedup']:.1f}x"] if "before_warm_s" in r else ["-", "-"])
                if before else [])
        rows.append(row)
    unroll = f"; IK unrolled {result['ik_unroll']}" if result.get("ik_unroll", 1) != 1 else ""
    unroll += f"; RL realises {result['ahead']} decisions' states a batch" if result.get("ahead", 1) != 1 else ""
    cores = f", {result['cores']} cores" if "cores" in result else ""
    print(f"Table 1: online wall-clock per unseen episode ({result['device']}{cores}{unroll}; L1/L2 search "
          f"{result.get('lookahead', 'cached')}; paper: {common.PAPER['table1_machine']})")
    print(table(headers, rows, ".2f"))


def with_ik_unroll(ctx: evaluation.Context, unroll: int | None) -> evaluation.Context:
    """The context with its surrogate's IK loop unrolled `unroll` iterations per trip (None: the platform's default,
    `GPU_IK_UNROLL` on a GPU, else as it is). Every planner built from the context then uses it."""
    if unroll is None:
        unroll = GPU_IK_UNROLL if jax.default_backend() == "gpu" else ctx.surrogate.ik_config.unroll
    if unroll < 1:
        raise ValueError(f"ik_unroll: expected an integer >= 1, got {unroll}")
    return _with_ik_config(ctx, unroll=unroll)
