"""`python -m experiments dp --set train|evalA|evalB|all`: exact DP over the discretised surrogate for every
episode of a set. Prints each episode's optimal return, the DP-baseline return (the nominal episode's optimal
sequence replayed), and the optimal grasp sequence; writes results/dp_<set>.json and a grasp-timeline PNG."""
from __future__ import annotations

import argparse
import re
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from experiments.common import Run, table
from gsp_jax.core import distributed, files
from gsp_jax.planning import dp
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="evalA", choices=["nominal", "train", "evalA", "evalB", "eval", "all"])
    p.add_argument("--chunk", type=int, default=4, help="episodes per vmapped call (memory vs. speed)")
    p.add_argument("--plot", default=None, help="episode whose grasp timeline is drawn (default: the first)")


def solve_set(env, episodes: dict, chunk: int, desc: str = "DP"):
    """Tables and solutions of named episodes, `chunk` episodes per vmapped call (split over the local devices),
    with a progress bar. Several processes (`--processes`): each solves a contiguous share of the chunks, and every
    process gets them all."""
    names = list(episodes)
    solve = distributed.over_local_devices(jax.vmap(lambda e: dp.solve(env, e)))  # a chunk over the local devices
    bar = tqdm(total=len(distributed.share(-(-len(names) // chunk))), desc=desc, unit="chunk")

    def one(idx):
        out = jax.device_get(solve(scenario.stack([episodes[names[i]] for i in idx])))
        bar.update()
        return out

    tables, sols = distributed.map_chunks(one, len(names), chunk, what="episodes")
    bar.close()
    return names, tables, sols


def timeline_png(env, name: str, grasps: np.ndarray, alive: np.ndarray, path) -> None:
    """Links x waypoints; each cell shows the link's contact option (blank: not in contact)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    opts = np.asarray(env.space.decode(jnp.asarray(grasps[1:])))  # (T, L): grasp in force after each step
    n_t, n_l = opts.shape
    fig, ax = plt.subplots(figsize=(0.55 * n_t + 2.5, 0.45 * n_l + 1.2))
    masked = np.ma.masked_where(opts.T == 0, opts.T)
    ax.imshow(masked, cmap="viridis", vmin=0, vmax=max(env.space.n_options), aspect="auto")
    for t in range(n_t):
        for link in range(n_l):
            if opts[t, link]:
                ax.text(t, link, str(opts[t, link]), ha="center", va="center", color="white", fontsize=9)
        if not alive[t]:
            ax.axvspan(t - 0.5, t + 0.5, color="0.85", zorder=0)
    ax.set_yticks(range(n_l), [n.replace("_", " ") for n in env.space.link_names])
    ax.set_xticks(range(n_t))
    ax.set_xlabel("waypoint")
    ax.set_title(f"DP-optimal grasp sequence: {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [()]  # results/ itself


def main(args: argparse.Namespace, run: Run) -> None:
    env = surrogate.Surrogate(run.model, learned=run.learned)
    episodes = scenario.episode_set(args.set, env.model)
    if args.plot is not None and args.plot not in episodes:
        raise SystemExit(f"--plot: episode {args.plot!r} is not in set {args.set!r}: {', '.join(episodes)}")
    t0 = time.perf_counter()
    names, tabs, sols = solve_set(env, episodes, args.chunk, desc=f"DP {args.set}")
    if "nominal" in names:  # the DP baseline: the nominal episode's optimal sequence
        nominal_actions = sols.actions[names.index("nominal")]
    else:
        nominal_actions = solve_set(env, scenario.nominal(env.model), 1, desc="DP nominal (baseline)")[2].actions[0]
    elapsed = time.perf_counter() - t0
    if not distributed.is_main():
        return  # process 0 writes
    baseline = jax.jit(jax.vmap(dp.sequence_return, (0, 0, None)))(
        tabs, jnp.asarray([int(episodes[n].start_grasp) for n in names]), jnp.asarray(nominal_actions)
    )
    rows, out = [], []
    grasps_ = np.asarray(sols.grasps)
    n_changes = np.sum((grasps_[:, 1:] != grasps_[:, :-1]) & np.asarray(sols.alive), axis=1)  # (E,) grasp changes
    for i, name in enumerate(names):
        labels = [env.space.label(int(g)) for g in sols.grasps[i]]
        rows.append([name, float(sols.ret[i]), float(baseline[i]), int(np.sum(sols.alive[i])), int(n_changes[i])])
        out.append(dict(
            episode=name, dp_optimal_return=float(sols.ret[i]), dp_baseline_return=float(baseline[i]),
            grasp_changes=int(n_changes[i]),
            actions=sols.actions[i].tolist(), grasps=sols.grasps[i].tolist(), grasp_labels=labels,
            rewards=sols.rewards[i].tolist(), alive=sols.alive[i].tolist(),
        ))
    for i, name in enumerate(names):
        changes = [f"{t}:[{out[i]['grasp_labels'][t + 1]}]" for t in range(len(sols.actions[i]))
                   if t == 0 or sols.grasps[i][t + 1] != sols.grasps[i][t]]
        print(f"{name}: start [{out[i]['grasp_labels'][0]}] -> " + " ".join(changes))
        if float(sols.ret[i]) <= env.reward_config.r_min:  # every sequence fails: say where and why
            tab = jax.tree.map(lambda x: x[i], tabs)  # (not `table`: the printing helper)
            longest = dp.longest_surviving(tab, episodes[name].start_grasp, env.reward_config.r_min)
            out[i]["infeasible"] = env.explain(episodes[name], np.asarray(longest.actions))
            print(f"  no grasp sequence holds {name} in the surrogate: {out[i]['infeasible']}")
    folder = run.results_dir()
    path = folder / f"dp_{args.set}.json"
    files.write_json(path, dict(set=args.set, seconds=elapsed, mean_grasp_changes=float(n_changes.mean()),
                                    episodes=out))
    plot = args.plot or names[0]
    png = folder / f"dp_timeline_{re.sub(r'[^A-Za-z0-9._-]', '_', plot)}.png"
    i = names.index(plot)
    timeline_png(env, plot, sols.grasps[i], sols.alive[i], png)
    print(f"\nwrote {path} and {png} ({elapsed:.1f} s incl. compile)\n")
    print(table(["episode", "DP optimal", "DP baseline", "steps", "grasp changes"], rows))
    print(f"mean grasp changes per episode (DP optimal): {n_changes.mean():.2f}")
