"""`python -m experiments fig4a [--set eval] [--episodes N] [--backend table|surrogate]`: the paper's Fig. 4a.

Every policy (DP baseline, RL, L1, L2, DP optimal) runs each unseen evaluation episode in the surrogate, all
episodes of a policy in one vmapped program; the return is reported relative to DP optimal (return - DP optimal
return: 0 is optimal), with 95% t-intervals over episodes and a one-way repeated-measures ANOVA (episodes as
subjects) with Holm-corrected paired post-hoc tests (the paper's analysis), and beside it the rank-based Friedman
test with Wilcoxon post-hoc tests (returns with rare -200 falls are far from normal). `--backend surrogate` steps
the surrogate itself (three IK and four wrench solves per step, also inside the lookahead trees: a GPU job); `table`
steps the episodes' DP tables, which give the same MDP for the discrete states the surrogate visits from a reset
(tests check it) at a fraction of the cost (the CPU default). Writes results/fig4a/returns.json and fig4a.png;
prints the table last.
"""
from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from experiments import common
from experiments.common import Run, table
from gsp_jax.planning import evaluation
from gsp_jax.core import files, stats
from gsp_jax.planners import registry as planners

COMPARED = ("dp-base", "rl", "L1", "L2")  # relative to dp-opt


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", choices=["evalA", "evalB", "eval", "val"])
    p.add_argument("--episodes", type=int, default=None, help="only N episodes, spread over the set")
    p.add_argument("--backend", default=None, choices=["table", "surrogate"],
                   help="default: surrogate on a GPU, else table")
    p.add_argument("--policy-dir", default=None,
                   help="PPO policy (default: results/train/dp/seed0, else the shipped one)")
    common.add_lookahead_argument(p)


def evaluate(ctx: evaluation.Context, backend: str, out, cached: bool = True) -> dict:
    rets, wall = {}, {}
    for name in planners.names("paper"):
        t0 = time.perf_counter()
        rets[name] = np.asarray(planners.returns(ctx, name, backend, cached=cached))
        wall[name] = time.perf_counter() - t0
        print(f"  {name:8s} mean return {rets[name].mean():9.3f}   ({wall[name]:.1f} s incl. compile, {backend})",
              flush=True)
    gap = float(np.max(np.abs(rets["dp-opt"] - np.asarray(ctx.solutions.ret))))
    result = dict(set=ctx.set_name, episodes=ctx.names, backend=backend, rl_policy=ctx.rl_source,
                  returns={n: r.tolist() for n, r in rets.items()}, dp_opt_rollout_vs_table_max_abs=gap, wall_s=wall,
                  r_min=ctx.surrogate.reward_config.r_min)
    if backend == "surrogate":  # cross-check: the tables give the same returns
        result["table_vs_surrogate_max_abs"] = {
            n: float(np.max(np.abs(planners.returns(ctx, n, "table", cached=cached) - rets[n]))) for n in rets}
    result |= stats.relative_returns(rets, "dp-opt", COMPARED, result["r_min"])  # mean, CI, RM-ANOVA, rank tests
    files.write_json(out / "returns.json", result)
    common.fig4a_png(result["relative"], len(ctx.names), out / "fig4a.png")
    return result


def print_result(result: dict) -> None:
    print(result["anova_text"])
    rows = [[n, s["mean"], s["ci95"], f"{s['optimal']}/{len(result['episodes'])}", s["falls"]]
            for n, s in result["relative"].items()]
    print(table(["policy", "return - DP opt", "95% CI +-", "optimal on", "falls"], rows, ".3f"))


def figures(result: dict) -> dict:
    """Fig. 4a's figures for docs/data: per policy, the return relative to DP optimal (mean, 95% CI), how often
    optimal, falls."""
    return dict(set=result.get("set"), episodes=len(result["episodes"]), backend=result.get("backend"),
                relative=result["relative"])


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("fig4a",)]


def main(args: argparse.Namespace, run: Run) -> None:
    backend = args.backend or ("surrogate" if jax.default_backend() == "gpu" else "table")
    ctx = evaluation.context(args.set, args.episodes, args.policy_dir, model=run.model, results=common.RESULTS,
                             learned=run.learned)
    print(f"Fig. 4a: {len(ctx.names)} episodes of '{args.set}', backend {backend}, RL policy {ctx.rl_source}",
          flush=True)
    out = run.results_dir("fig4a")
    result = evaluate(ctx, backend, out, cached=args.lookahead == "cached")
    print(f"wrote {out / 'returns.json'}, {out / 'fig4a.png'}")
    run.record_figures("fig4a", figures(result))
    print_result(result)
