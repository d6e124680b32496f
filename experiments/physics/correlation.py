"""`python -m experiments physics-corr --set eval --random 8`: is the surrogate correlated with the physics? Runs
DP optimal, DP baseline and `--random` random feasible grasp sequences (half of them holding each grasp with probability 0.8) of every episode of a set through the MJX
physics check (open loop) and reports the Spearman rank correlation between each sequence's surrogate return and
its simulated angle error (180 when the tool fell): pooled over all sequences, and within each episode. Writes
results/physics/corr_<set>.json and a scatter PNG."""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.common import results_dir, table
from gsp_jax import dp, files, physics, policies, scenario, surrogate
from gsp_jax.evaluation import dp_tables, nominal_actions


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", choices=["nominal", "train", "val", "evalA", "evalB", "eval", "all"])
    p.add_argument("--random", type=int, default=8, help="random feasible sequences per episode")
    p.add_argument("--episodes", type=int, default=None, help="only the first N episodes of the set")
    p.add_argument("--chunk", type=int, default=512, help="sequences per MJX batch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", default="mjx", choices=physics.BACKENDS, help="mjx (one XLA batch) or c (C MuJoCo)")


def spearman(x, y) -> float:
    from scipy import stats

    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(stats.spearmanr(x, y).statistic)


def main(args: argparse.Namespace) -> None:
    env = surrogate.Surrogate()
    episodes = scenario.episode_set(args.set)
    if args.episodes:
        episodes = dict(list(episodes.items())[: args.episodes])
    names, batch = list(episodes), scenario.stack(list(episodes.values()))
    n_e, k = len(names), 2 + args.random
    tables = dp_tables(env, args.set, episodes)
    sols = jax.jit(jax.vmap(dp.backup))(tables, batch.start_grasp)
    base = jnp.broadcast_to(nominal_actions(env), sols.actions.shape)
    keys = jax.random.split(jax.random.PRNGKey(args.seed), n_e * args.random).reshape(n_e, args.random, 2)
    holds = jnp.where(jnp.arange(args.random) % 2 == 0, 0.0, 0.8)  # half of them change the grasp less often
    rand = jax.vmap(jax.vmap(dp.random_sequence, (None, None, 0, None, 0)), (0, 0, 0, None, None))(
        tables, batch.start_grasp, keys, env.reward_config.r_min, holds)  # (E, R, T)
    actions = jnp.concatenate([sols.actions[:, None], base[:, None], rand], axis=1)  # (E, K, T)
    kinds = ["dp-opt", "dp-base"] + [f"random{i}" for i in range(args.random)]
    returns = jax.vmap(jax.vmap(dp.sequence_return, (None, None, 0)), (0, 0, 0))(tables, batch.start_grasp, actions)

    phys = physics.Physics(env)
    flat_eps = jax.tree.map(lambda x: jnp.repeat(x, k, axis=0), batch)
    flat_act = actions.reshape(n_e * k, -1)
    print(f"surrogate vs physics: {n_e} episodes x {k} sequences = {n_e * k} physics episodes ({args.backend}) with JAX on "
          f"{jax.devices()[0].platform}, {args.chunk} per batch ...", flush=True)
    t0 = time.perf_counter()
    angle, fell = [], []
    for i in range(0, n_e * k, args.chunk):
        sl = slice(i, min(i + args.chunk, n_e * k))
        res = phys.simulate_batch(policies.SequencePolicy(flat_act[sl]), jax.tree.map(lambda x: x[sl], flat_eps), 0,
                                   backend=args.backend)
        angle.append(np.asarray(res.angle_error))
        fell.append(np.asarray(res.fell))
        print(f"  {sl.stop}/{n_e * k} done, {time.perf_counter() - t0:.0f} s", flush=True)
    wall = time.perf_counter() - t0
    angle = np.concatenate(angle).reshape(n_e, k)
    fell = np.concatenate(fell).reshape(n_e, k)
    ret = np.asarray(returns)
    failed_sur = ret <= env.reward_config.r_min + 1e-3 * abs(env.reward_config.r_min)

    pooled = spearman(ret.ravel(), -angle.ravel())
    within = np.array([spearman(ret[e], -angle[e]) for e in range(n_e)])
    finite = within[np.isfinite(within)]
    ok = ~failed_sur
    pooled_ok = spearman(ret[ok], -angle[ok]) if ok.sum() > 2 else float("nan")
    agree = float(np.mean(fell[failed_sur])) if failed_sur.any() else float("nan")
    summary = dict(
        set=args.set, episodes=n_e, sequences_per_episode=k, spearman_pooled=pooled,
        spearman_within_episode_mean=float(finite.mean()) if len(finite) else float("nan"),
        episodes_with_defined_within=int(len(finite)), spearman_pooled_surrogate_feasible=pooled_ok,
        surrogate_falls=int(failed_sur.sum()), of_which_fell_in_physics=agree,
        physics_falls_among_surrogate_feasible=float(np.mean(fell[ok])) if ok.any() else float("nan"),
        mean_angle_dp_opt=float(angle[:, 0].mean()), mean_angle_dp_base=float(angle[:, 1].mean()),
        wall_s_incl_compile=wall,
    )
    out = results_dir("physics")
    rows = [dict(episode=names[e], kind=kinds[j], surrogate_return=float(ret[e, j]), angle_error_deg=float(angle[e, j]),
                 fell=bool(fell[e, j]), actions=[int(a) for a in actions[e, j]]) for e in range(n_e) for j in range(k)]
    files.write_json(out / f"corr_{args.set}.json", dict(summary=summary, sequences=rows))
    common.record(f"physics_corr_{args.set}", summary)
    scatter_png(ret, angle, kinds, out / f"corr_{args.set}.png", summary)
    print(table(["episode", "DP opt ret", "angle", "DP base ret", "angle", "rho within"],
                [[names[e], float(ret[e, 0]), float(angle[e, 0]), float(ret[e, 1]), float(angle[e, 1]),
                  float(within[e])] for e in range(n_e)], ".2f"))
    print(f"\nSpearman rho (surrogate return vs -angle error): pooled {pooled:.3f} over {ret.size} sequences; "
          f"within episodes mean {summary['spearman_within_episode_mean']:.3f} ({len(finite)} episodes); "
          f"surrogate-feasible only {pooled_ok:.3f}")
    print(f"surrogate falls: {int(failed_sur.sum())}, of which fell in physics: {agree:.2f}; physics falls among "
          f"surrogate-feasible: {summary['physics_falls_among_surrogate_feasible']:.2f}")
    print(f"mean angle error: DP optimal {summary['mean_angle_dp_opt']:.1f} deg, DP baseline "
          f"{summary['mean_angle_dp_base']:.1f} deg; {wall:.0f} s including compile")
    print(f"wrote {out / f'corr_{args.set}.json'}, {out / f'corr_{args.set}.png'}")


def scatter_png(ret, angle, kinds, path, summary) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    styles = {"dp-opt": ("tab:green", "DP optimal"), "dp-base": ("tab:orange", "DP baseline")}
    ax.scatter(ret[:, 2:].ravel(), angle[:, 2:].ravel(), s=10, c="0.6", label="random feasible")
    for j, kind in enumerate(kinds[:2]):
        c, label = styles[kind]
        ax.scatter(ret[:, j], angle[:, j], s=18, c=c, label=label)
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlabel("surrogate return (symlog)")
    ax.set_ylabel("simulated angle error under the torque [deg]\n(180 = fell)")
    ax.set_title(f"surrogate vs MJX physics, {summary['set']}: Spearman {summary['spearman_pooled']:.2f}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
