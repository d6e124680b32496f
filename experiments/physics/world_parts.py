"""Which part of the world gap drops the tool: the planners' falls in C MuJoCo on a set's episodes in the whole gap
of a level and in each of its fields alone (the others as the model), every episode's world drawn from one seed
(`gsp_jax.physics.world`; docs/world.md).

    python -m experiments world-parts                                # the gap level, evaluation set, 2 planners
    python -m experiments world-parts --level wide --set stress --policies four-tips dp-opt L1
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from experiments import common
from experiments.common import Run, table
from gsp_jax import physics
from gsp_jax.core import files
from gsp_jax.physics import world as world_lib
from gsp_jax.planners import registry as planners
from gsp_jax.planning import evaluation


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--level", default="gap", choices=[n for n in world_lib.LEVELS if n != "nominal"],
                   help="the world level whose gap is taken apart (default gap)")
    p.add_argument("--set", default="eval", choices=["eval", "evalA", "evalB", "stress", "val"])
    p.add_argument("--episodes", type=int, default=None, help="only the first N episodes of the set")
    p.add_argument("--policies", nargs="+", default=["four-tips", "dp-opt"], metavar="NAME",
                   help="registered planners (default four-tips dp-opt)")
    p.add_argument("--seed", type=int, default=0, help="the seed of the episodes' worlds")
    p.add_argument("--policy-dir", default=None, help="where the RL policy is (for rl)")


def parts(gap: world_lib.Gap) -> list[str]:
    """'all', then each field of `gap` that is not zero."""
    return ["all"] + [f.name for f in dataclasses.fields(gap) if getattr(gap, f.name)]


def main(args: argparse.Namespace, run: Run) -> None:
    common.check_planners(args.policies, "--policies", "c")
    ctx = evaluation.context(args.set, args.episodes, args.policy_dir, model=run.model, results=common.RESULTS,
                             learned=run.learned, **planners.context_flags(args.policies))
    phys = physics.Physics(ctx.surrogate, run.physics_config())
    gap, n = world_lib.Gap.named(args.level), len(ctx.names)
    groups = [planners.make(ctx, name) for name in args.policies]
    print(f"world-parts: {n} episodes of '{args.set}' x {len(groups)} planners in C MuJoCo, the {args.level} "
          f"level whole and each of its {len(parts(gap)) - 1} fields alone", flush=True)
    rows, falls = [], {}
    for part in ["nominal", *parts(gap)]:
        worlds = None if part == "nominal" else world_lib.draw_for(
            gap if part == "all" else gap.only(part), args.seed, ctx.batch, ctx.surrogate.hand)
        t0 = time.perf_counter()
        res = phys.simulate_many(groups, ctx.batch, backend="c", world=worlds)
        falls[part] = {name: int(np.sum(r.fell)) for name, r in zip(args.policies, res)}
        held = {name: float(np.mean(np.asarray(r.angle_error)[~np.asarray(r.fell)])) if not np.all(r.fell)
                else None for name, r in zip(args.policies, res)}
        value = "" if part in ("nominal", "all") else getattr(gap, part)
        rows.append([part, str(value), *[f"{falls[part][p]} ({held[p]:.2f})" if held[p] is not None
                                         else f"{falls[part][p]}" for p in args.policies]])
        print(f"  {part}: falls {falls[part]} ({time.perf_counter() - t0:.0f} s)", flush=True)
    out = run.results_dir("world-parts") / f"{args.set}_{args.level}.json"
    files.write_json(out, dict(set=args.set, level=args.level, seed=args.seed, episodes=ctx.names,
                               gap=dataclasses.asdict(gap), falls=falls))
    print(f"wrote {out}\n")
    run.record_figures(f"world_parts_{args.set}_{args.level}", dict(episodes=n, falls=falls))
    print(table(["part of the gap", "half-width / most", *[f"{p} falls /{n} (held deg)" for p in args.policies]],
                rows))


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    return [("world-parts",)]
