"""`python -m experiments bench-search`: the beam search (the planner `search`, `gsp_jax.planning.beam`) beside the DP
table on a grasp space the table holds, in one run: the time to plan one unseen episode (the table and its backup,
against the search at each `--widths`), the IK problems each realises (the search's: those of grasps it visits, and
with its static shapes' padding), and on an episode set how often the search's plan is DP optimal's (its return in
the episode's table against the optimum)."""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import Run, best_time, table, timed
from gsp_jax.core import files
from gsp_jax.model import scenario
from gsp_jax.planning import beam, dp
from gsp_jax.surrogate import step as surrogate

SAME = 1e-4  # a return "equal" to DP optimal's: within this share of it (float32 sums of rewards solved two ways)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", help="the episode set of the quality figures (default: eval)")
    p.add_argument("--episodes", type=int, default=None, help="the first N episodes of the set (default: all)")
    p.add_argument("--widths", type=int, nargs="+", default=[8, 12, 16], help="beam widths (grasps kept a waypoint)")
    p.add_argument("--timed", type=int, default=3, help="episodes of the set each planner is timed on, one at a time")
    p.add_argument("--no-table", action="store_true",
                   help="time the search alone (a grasp space whose tables take too long to build: no quality figures)")
    p.add_argument("--out", default=None)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.out else [()]


def _fastest(fn, episodes) -> tuple[float, float]:
    """(compile + first call, fastest warm call over `episodes`) [s] of `fn(episode)`, one episode at a time."""
    _, first = timed(fn, episodes[0])
    return first, min(best_time(fn, ep, repeats=1) for ep in episodes[1:] or episodes)


def main(args: argparse.Namespace, run: Run) -> None:
    bad = [w for w in args.widths if w < 1]
    if bad or args.timed < 1 or (args.episodes is not None and args.episodes < 1):
        raise SystemExit(f"--widths: positive ints, got {args.widths}; --timed and --episodes: >= 1, got "
                         f"{args.timed}, {args.episodes}")
    sur = surrogate.Surrogate(run.model, learned=run.learned)
    episodes = dict(list(scenario.episode_set(args.set, sur.model).items())[:args.episodes])
    batch = sur.validate(scenario.stack(list(episodes.values())))
    device = jax.local_devices()[0]
    n_g, n_t = sur.space.n_grasps, batch.n_steps
    print(f"device: {device.platform} ({device.device_kind}); model {sur.model.name!r}, {n_g} grasps x {n_t} "
          f"waypoints; {len(episodes)} episodes of {args.set!r}", flush=True)
    timed_eps = [jax.tree.map(lambda x, i=i: x[i], batch) for i in range(min(args.timed + 1, len(episodes)))]

    rows, tables, optimum, t_table = [], None, None, None
    if not args.no_table:
        solve = jax.jit(lambda ep: dp.solve(sur, ep)[1].ret)
        compile_table, t_table = _fastest(solve, timed_eps)
        print(f"DP table + backup: compile+first {compile_table:.1f} s, warm {t_table:.3f} s an episode", flush=True)
        tables = dp.build_tables(sur, batch, batch_size=4)
        optimum = np.asarray(jax.vmap(dp.backup)(tables, batch.start_grasp).ret)
        rows.append(dict(planner="DP table", width=n_g, per_episode_s=t_table, compile_s=compile_table,
                         ik=n_g * n_t, solved=n_g * n_t, equal=len(episodes), worst_gap=0.0,
                         within_1pct=len(episodes), dropped=0))
    for width in args.widths:
        config = beam.BeamConfig(width=width)
        sizes = config.sizes(sur)
        one = jax.jit(lambda ep, c=config: beam.plan(sur, ep, c).ret)
        compile_s, t_search = _fastest(one, timed_eps)
        found = beam.plan_batch(sur, batch, config, batch_size=4)
        row = dict(planner="search", width=width, per_episode_s=t_search, compile_s=compile_s,
                   ik=float(jnp.mean(found.realised)), solved=n_t * (sizes[1] + sizes[2]), equal=None,
                   worst_gap=None, within_1pct=None, dropped=int(jnp.sum(found.dropped)), sizes=list(sizes))
        if tables is not None:
            ret = np.asarray(jax.vmap(dp.sequence_return)(tables, batch.start_grasp, found.actions))
            gap = (optimum - ret) / np.maximum(np.abs(optimum), 1e-9)
            row.update(equal=int(np.sum(gap <= SAME)), worst_gap=float(gap.max()),
                       within_1pct=int(np.sum(gap <= 0.01)))
        rows.append(row)
        print(f"search width {width} (expand, fresh {sizes[1:]}): compile+first {compile_s:.1f} s, warm {t_search:.3f}"
              f" s an episode" + ("" if tables is None else f"; equal to DP optimal on {row['equal']} of "
                                  f"{len(episodes)}, worst gap {100 * row['worst_gap']:.2f}%"), flush=True)

    result = dict(device=f"{device.platform}:{device.device_kind}", model=sur.model.name, set=args.set,
                  episodes=len(episodes), grasps=n_g, waypoints=n_t, rows=rows)
    out = args.out or str(run.results_dir() / "bench_search.json")
    files.write_json(out, result)
    print(f"wrote {out}\n")
    run.record_figures("bench_search", result)
    print(table(["planner", "width", "an episode [s]", "vs table", "IK problems (padded)",
                 f"= DP optimal (of {len(episodes)})", "worst gap [%]", "left out"],
                [[r["planner"], r["width"], r["per_episode_s"],
                  "-" if t_table is None else f"{r['per_episode_s'] / t_table:.2f}x", f"{r['ik']:.0f} ({r['solved']})",
                  "-" if r["equal"] is None else r["equal"], "-" if r["worst_gap"] is None else 100 * r["worst_gap"],
                  r["dropped"]] for r in rows], ".3f"))
