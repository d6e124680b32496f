"""`python -m experiments envelope --set stress|eval [--random 8]`: do the plans hold where holding is possible?

Every episode of the set runs in C MuJoCo (one lockstep, `Physics.simulate_many`) under the constant four-tip grasp,
DP optimal, L1, L2 and RL (closed loop), and a pool of `--random` random surrogate-feasible grasp sequences (half of
them keeping each grasp with probability 0.8). Every fall is classified by the feasibility oracle
(`gsp_jax.physics.oracle`) on the grasps the run held: *necessary* (at some point no forces in the friction cones hold
the tool within the motors' limits), *controller* (forces exist everywhere: the controller let it fall) or
*undetermined* (the cone's outer and inner pyramids disagree). Beside it the oracle is asked at the configurations
the run *reached* (`Oracle.simulated`, the simulated joint angles and tool pose before each decision and at the
hold's start, up to the fall): a necessary fall *before* the point the oracle calls impossible is counted as
`early` (the controller dropped the tool before the grasp became impossible to hold). A planner's *regret* counts
the episodes where it fell while some other sequence of the pool (the four tips, another planner, a random one)
held.

On the pool the surrogate is judged as a predictor of physics: the share of the sequences it calls feasible that
hold, and how well its return separates holds from falls (AUC, pooled and within episodes) and ranks the angle
errors (Spearman). Writes results/envelope/<set>.json; prints the table last.
"""
from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.common import results_dir, table
from gsp_jax import dp, evaluation, files, physics, policies, scenario
from gsp_jax.physics.envelope import classify, summarise
from gsp_jax import planners as gsp_planners

PLANNERS = ("four-tips", "dp-opt", "L1", "L2", "rl")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="stress", choices=["stress", "stress-cal", "eval", "val", "train", "variations"])
    p.add_argument("--episodes", type=int, default=None, help="only N episodes, spread over the set")
    p.add_argument("--random", type=int, default=8, help="random surrogate-feasible sequences per episode")
    p.add_argument("--policies", nargs="+", default=list(PLANNERS), metavar="NAME",
                   help=f"registered planners to run (default: {' '.join(PLANNERS)}; rl only where the model has a "
                        "PPO policy); --plugin adds yours")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--policy-dir", default=None)
    p.add_argument("--jobs", type=int, default=None, help="processes classifying falls (default: the CPU cores)")
    p.add_argument("--physics-lookahead", type=int, default=0, metavar="K",
                   help="also L1-physics, branching L1's K best actions in physics at each decision (0: not run)")
    common.add_bases_argument(p)


# ---------------------------------------------------------------------------------------------------- main
def main(args: argparse.Namespace) -> None:
    common.check_planners(args.policies, "--policies", "c")
    common.check_planners(args.bases, "--bases")
    if args.random < 0:
        raise SystemExit(f"envelope: --random must be >= 0, got {args.random}")
    if args.physics_lookahead < 0:
        raise SystemExit(f"envelope: --physics-lookahead must be >= 0, got {args.physics_lookahead}")
    reads = gsp_planners.context_flags([*args.policies, *(["L1-physics", *args.bases] if args.physics_lookahead else [])])
    ctx = evaluation.context(args.set, args.episodes, args.policy_dir,  # the tables always: every sequence is scored
                             **(reads | dict(tables=True, nominal=reads["nominal"] or reads["rl"])))
    sur, N, T = ctx.surrogate, len(ctx.names), ctx.batch.n_steps
    planners = [p for p in args.policies if p != "rl" or ctx.rl is not None]  # a model without a PPO policy: no RL row
    planners += ["L1-physics"] if args.physics_lookahead else []
    groups = [gsp_planners.make(ctx, name, dict(k=args.physics_lookahead or 1, bases=tuple(args.bases)))
              for name in planners]
    keys = jax.random.split(jax.random.PRNGKey(args.seed), N * args.random).reshape(N, args.random, 2)
    holds = jnp.where(jnp.arange(args.random) % 2 == 0, 0.0, 0.8)
    rand = jax.vmap(jax.vmap(dp.random_sequence, (None, None, 0, None, 0)), (0, 0, 0, None, None))(
        ctx.tables, ctx.batch.start_grasp, keys, sur.reward_config.r_min, holds)  # (N, R, T)
    groups += [(policies.SequencePolicy(rand[:, r]), 0) for r in range(args.random)]
    kinds = planners + [f"random{r}" for r in range(args.random)]
    phys = physics.Physics(sur)
    print(f"envelope: {N} episodes of '{args.set}' x {len(kinds)} sequences = {N * len(kinds)} episodes in C MuJoCo "
          f"(JAX on {jax.default_backend()})", flush=True)
    t0 = time.perf_counter()
    res = phys.simulate_many(groups, ctx.batch, backend="c", progress=True)
    t_phys = time.perf_counter() - t0
    fell = np.stack([np.asarray(r.fell) for r in res])
    angle = np.stack([np.asarray(r.angle_error) for r in res])
    actions = jnp.stack([jnp.asarray(r.actions) for r in res])  # (G, N, T)
    rewards = jax.vmap(jax.vmap(dp.sequence_rewards), (None, 0, 0))(ctx.tables, jnp.broadcast_to(
        ctx.batch.start_grasp, actions.shape[:2]), actions)  # (G, N, T)
    feasible = np.asarray(jnp.all(rewards > sur.reward_config.r_min, -1))
    returns = np.asarray(jnp.sum(rewards, -1))
    print(f"  physics {t_phys:.0f} s; {int(fell.sum())} falls of {fell.size} to classify ...", flush=True)
    episodes = scenario.unstack(ctx.batch)
    falls = [(g, e) for g in range(len(kinds)) for e in range(N) if fell[g, e]]
    t1 = time.perf_counter()
    n_seg, tick = phys.n_segment, phys.timestep

    def reached(g, e):  # the configurations before each decision t >= 1 and at the hold's start; rows before the fall
        rows = np.asarray(res[g].qpos[e, n_seg - 1 :: n_seg][:T])
        fall_tick = int(round(float(res[g].fall_time[e]) / tick))
        return rows, int(np.sum(np.arange(1, T + 1) * n_seg - 1 < fall_tick))

    verdicts = classify(episodes, [(e, [int(x) for x in np.asarray(res[g].grasps[e])], *reached(g, e))
                                   for g, e in falls], args.jobs or os.cpu_count() or 1)
    classes = {ge: v[0] for ge, v in zip(falls, verdicts)}
    summary = summarise(kinds, fell, angle, feasible, returns, classes, {ge: v[3] for ge, v in zip(falls, verdicts)})
    verdict = dict(zip(falls, verdicts))

    def row(g, e):
        r = dict(kind=kinds[g], episode=ctx.names[e], fell=bool(fell[g, e]), angle_deg=float(angle[g, e]),
                 surrogate_feasible=bool(feasible[g, e]), surrogate_return=float(returns[g, e]),
                 grasps=[int(x) for x in np.asarray(res[g].grasps[e])])
        if (g, e) in verdict:
            r["oracle"] = dict(zip(("class", "worst_point", "worst_ratio", "early", "reached_worst_point",
                                    "reached_worst_ratio"), verdict[g, e]))
            r["fall_time"] = float(res[g].fall_time[e])
        return r

    out = dict(set=args.set, episodes=ctx.names, kinds=kinds, physics_s=t_phys, oracle_s=time.perf_counter() - t1,
               platform=jax.default_backend(), rl_policy=ctx.rl_source, summary=summary,
               sequences=[row(g, e) for g in range(len(kinds)) for e in range(N)])
    path = results_dir("envelope") / f"{args.set}.json"
    files.write_json(path, out)
    print(f"wrote {path}\n")
    common.record(f"envelope_{args.set}", dict(episodes=N, random=args.random, summary=summary))
    p = summary["pool"]
    print(f"pool: {p['sequences']} sequences, {p['surrogate_feasible']} surrogate-feasible, of those "
          f"{100 * p['feasible_hold_share']:.1f}% hold; AUC(return: hold vs fall) pooled {p['auc_pooled']:.2f}, "
          f"within episodes {p['auc_within_mean']:.2f} ({p['auc_within_episodes']} episodes); Spearman "
          f"rho(return, -angle) {p['spearman_pooled']:.2f}")
    rows = [[k, r["falls"], r["necessary"], r["early"], r["controller"], r["undetermined"], r["regret"],
             r["mean_angle_held_deg"]] for k, r in summary["kinds"].items() if k in planners or args.random <= 4]
    print(table(["sequence", f"falls /{N}", "necessary", "of them early", "controller", "undetermined", "regret",
                 "angle held [deg]"],
                rows, ".2f"))
