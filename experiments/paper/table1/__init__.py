"""`python -m experiments table1 [--set eval] [--batch N] [--repeats K] [--policies NAME ...]
[--lookahead table|cached|continuous] [--before] [--ik-unroll K] [--ahead K]`: the paper's Table 1, online
wall-clock time per unseen episode; `table1 --per-decision [--episodes N] [--policies ... L1-physics --k K ...]`:
the same planners' latency per decision, one episode at a time.

**Per episode** (`episode.py`): for each planner, the time to plan and run one unseen episode through the surrogate
from its start, as one jitted call. DP baseline and RL act per step (a sequence lookup, one network call) and run
the surrogate's step for each decision, either stepping after each or, as the decisions fix every grasp the episode
visits, all T transitions afterwards in one vmapped batch (`policies.rollout_batched`; both forms are timed, side by
side, and the warm time is the form `online.default_batched` picks: batched for DP baseline, and for RL on a GPU,
where RL's chain of decisions realises the states of `online.GPU_AHEAD` decisions in one batch: `--ahead`). DP optimal
first builds the episode's whole table and backs it up, then runs its policy in that table: from its start the
surrogate visits only the table's discrete states, so the table steps the episode exactly as the surrogate would
(`tests/test_env.py` checks the two step for step). L1 and L2 first build the episode's table too, then at every
step search in it (`--lookahead table`, the default: the root's children are the table's, for the same reason), or
step the root's actions in the surrogate and search below them in the table (`cached`), or search in the surrogate
alone (`continuous`); the episode moves on to the searched root child of the chosen action
(`lookahead.rollout_planned`). The table is built inside the timed call (the episode is unseen). `--before` also
times DP optimal, L1 and L2 as the code stood before the batch-last IK (the table's IK vmapped, L1/L2 `cached`),
side by side in the same run. Compilation (once per program, reused for every later episode of the same length) is
shown apart from the warm time (fastest of `--repeats` calls). With `--batch N`, also the time per episode when N
unseen episodes are planned in one vmapped call. On a GPU the surrogate's IK runs `GPU_IK_UNROLL` iterations per
loop trip (the same result; `--ik-unroll 1` for the plain loop). Writes results/table1/<platform>.json.

**Per decision** (`decisions.py`, `--per-decision`): an online planner meets one episode at a time. When the
episode is revealed it may prepare (*setup*: DP optimal solves the episode's table; L1/L2 build it, as the root's
successors are looked up in it), then it is asked for one action per waypoint from the surrogate's current,
continuous state (*decision*: the policy's `act`). Both are timed one call at a time, warm, on the planner's own
rollouts of `--episodes` evaluation episodes (default 7 x 16 = 112 decisions); the surrogate step that carries the
episode on is timed apart. `--policies ... L1-physics [--k 17 4]`: the physics-verified lookahead runs each episode
alone in C MuJoCo on every core; its decision is L1's ranking plus the k branches simulated to the episode's end,
its setup the episode's table; the episode's own simulation, which a robot would live through, is not counted.
Writes results/bench_latency/<platform>.json.

Both print their table, beside the paper's per-episode times, last.
"""
from __future__ import annotations

import argparse

import jax

from experiments import common
from experiments.common import Run
from experiments.paper.table1 import decisions, episode
from gsp_jax.planning import evaluation
from gsp_jax.core import files
from gsp_jax.planners import online, registry as planners

PAPER = episode.PAPER


def _at_least_one(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return int(text)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--policies", nargs="+", default=None, metavar="NAME",
                   help=f"which rows to time (default: all of {', '.join(PAPER)}; --per-decision also takes "
                        f"{', '.join(planners.names('verified'))})")
    p.add_argument("--policy-dir", default=None)
    common.add_lookahead_argument(p, root_in_table=True)
    g = p.add_argument_group("per episode (the default)")
    g.add_argument("--set", default="eval", choices=["evalA", "evalB", "eval"])
    g.add_argument("--batch", type=int, default=0, help="also time N episodes planned in one vmapped call (0: skip)")
    g.add_argument("--repeats", type=int, default=None,
                   help="warm calls per measurement (default 3 on a GPU, 1 on CPU)")
    g.add_argument("--ik-unroll", type=_at_least_one, default=None,
                   help="IK iterations per loop trip (`IKConfig.unroll`; "
                   f"the same result): default {episode.GPU_IK_UNROLL} on a GPU, 1 on a CPU "
                   "(where it only lengthens compiles)")
    g.add_argument("--ahead", type=_at_least_one, default=None,
                   help="batched RL: decisions per batch of realised states "
                   f"(`policies.rollout_batched`; the same episode): default {online.GPU_AHEAD} on a GPU, 1 on a CPU "
                   "(which pays for every state)")
    g.add_argument("--before", action="store_true", help="also time DP optimal, L1 and L2 as the code stood before the "
                   "batch-last IK (the table's IK vmapped, L1/L2's root in the surrogate), side by side in this run")
    g = p.add_argument_group("per decision (--per-decision)")
    g.add_argument("--per-decision", action="store_true", help="time each decision, one episode at a time")
    g.add_argument("--episodes", type=_at_least_one, default=7,
                   help="evaluation episodes (each gives up to 16 decisions)")
    g.add_argument("--k", nargs="+", type=_at_least_one, default=[evaluation.L1_PHYSICS["k"]],
                   help="L1-physics: the surrogate's best k root actions are branched per decision "
                   "(several: a row each)")
    common.add_bases_argument(g)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("bench_latency",)] if args.per_decision else [("table1",)]


def main(args: argparse.Namespace, run: Run) -> None:
    names = args.policies or list(PAPER)
    if args.per_decision:
        common.check_planners(names, "--policies", "c" if set(names) & set(planners.names("verified")) else None)
        allowed = PAPER + planners.names("verified")
    else:
        allowed = PAPER
    wrong = [n for n in names if n not in allowed]
    if wrong:
        raise SystemExit(f"table1: --policies {' '.join(wrong)}: "
                         f"{'--per-decision' if args.per_decision else 'per episode'} "
                         f"times {', '.join(allowed)}" + ("" if args.per_decision else " (L1-physics: --per-decision)"))
    return per_decision(args, run, names) if args.per_decision else per_episode(args, run, names)


def per_episode(args: argparse.Namespace, run: Run, names: list[str]) -> None:
    repeats = args.repeats or (3 if jax.default_backend() == "gpu" else 1)
    ctx = episode.with_ik_unroll(evaluation.context(args.set, 1 if not args.batch else args.batch, args.policy_dir,
                                                    model=run.model, results=common.RESULTS,
                                                    learned=run.learned), args.ik_unroll)
    print(f"Table 1 on {jax.local_devices()[0].device_kind}: episode {ctx.names[0]} ...", flush=True)
    result = episode.run(ctx, args.batch, repeats, run.results_dir("table1"), lookahead=args.lookahead,
                         names=tuple(n for n in PAPER if n in names), ahead=args.ahead, compare_before=args.before)
    run.record_figures("table1", episode.figures(result))
    episode.print_result(result)


def per_decision(args: argparse.Namespace, run: Run, names: list[str]) -> None:
    ctx = evaluation.context("eval", args.episodes, args.policy_dir, model=run.model, results=common.RESULTS,
                             learned=run.learned)
    print(f"table1 --per-decision on {jax.local_devices()[0].device_kind}: {len(ctx.names)} episodes ...", flush=True)
    # a decision starts from the surrogate's continuous state: the root is never in the table ("table" = "cached")
    result = decisions.run(ctx, names, cached=args.lookahead != "continuous", ks=args.k, bases=args.bases,
                           config=run.physics_config())
    out = run.results_dir("bench_latency") / f"{result['platform']}.json"
    files.write_json(out, result)
    print(f"wrote {out}\n")
    run.record_figures("bench_latency", dict(episodes=len(result["episodes"]), lookahead=result["lookahead"],
                                             policies={n: {k: v for k, v in r.items() if k != "returns"}
                                                       for n, r in result["policies"].items()}))
    decisions.print_result(result)
