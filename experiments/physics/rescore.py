"""`python -m experiments rescore [--pool FILE] [--reward field=value,... ...]`: a recorded envelope pool's physics
outcomes scored under other rewards, with no new physics.

`envelope` writes every (sequence, episode) it simulated with its grasps and physics outcome. Here each step of each
sequence is scored again by the surrogate (`Surrogate.score`: the IK of every state the pool visits once, then only
the wrench solves per reward), so a candidate reward is judged against physics in seconds instead of a GPU run: the
share of the sequences it calls feasible that held, how well its return separates holds from falls (AUC, pooled and
within episodes) and its Spearman rho with -angle error (`envelope.summarise`). The pool stays what the planners of
the recorded run chose: a reward whose own optimum differs is judged on its ranking of this pool, not on its plans
(for those, rerun `envelope` with it as the default).

The first row is the calibrated reward; each `--reward` adds one, as fields of `reward.RewardConfig` to change (e.g.
`--reward grip=0 --reward grip=2,grip_scales_with_mass=false,fall_unmet=0.2`). Beside the pooled Spearman rho the
table gives its mean within episodes, and a scatter of the calibrated reward's returns against the simulated angle
errors shows the pool. Prints a table; writes results/rescore/<set>.json and <set>.png. (A pool of your own:
`envelope --set S --random R` records one, in C MuJoCo.) Several processes (`--processes N`) share the states and
steps in fixed chunks of `--batch`; process 0 writes.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import ROOT, Run, table
from gsp_jax.physics.envelope import summarise
from gsp_jax.core import distributed, files, stats
from gsp_jax.surrogate import reward as reward_lib, step as surrogate
from gsp_jax.model import scenario

DEFAULT_POOL = ROOT / "docs" / "history" / "2026-11-27" / "envelope" / "stress_reached_h100.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pool", default=str(DEFAULT_POOL), help="an envelope result (results/envelope/<set>.json)")
    p.add_argument("--reward", action="append", default=[], metavar="FIELD=VALUE,...",
                   help="a RewardConfig variant to score (repeatable)")
    p.add_argument("--episodes", type=int, default=None, help="only the pool's first N episodes")
    p.add_argument("--batch", type=int, default=2048, help="states or steps vmapped at a time")


def parse_reward(text: str, base: reward_lib.RewardConfig) -> reward_lib.RewardConfig:
    """`base` with the fields of 'field=value,...' replaced (each value read as the field's type)."""
    fields = {f.name for f in dataclasses.fields(base)}
    changes = {}
    for part in filter(None, (s.strip() for s in text.split(","))):
        name, sep, value = part.partition("=")
        if not sep or name not in fields:
            raise SystemExit(f"--reward: expected FIELD=VALUE with a RewardConfig field, got {part!r} "
                             f"(fields: {', '.join(sorted(fields))})")
        kind = type(getattr(base, name))
        if kind is bool:
            if value.lower() not in ("true", "false", "1", "0"):
                raise SystemExit(f"--reward: {name} takes true or false, got {value!r}")
            changes[name] = value.lower() in ("true", "1")
        else:
            try:
                changes[name] = kind(value)
            except ValueError:
                raise SystemExit(f"--reward: {name} takes a {kind.__name__}, got {value!r}") from None
    try:
        return dataclasses.replace(base, **changes)
    except ValueError as e:
        raise SystemExit(f"--reward {text!r}: {e}") from None


def load_pool(path: str, n_episodes: int | None, model=None):
    """(set name, episode names (N,), the batch, kinds (G,), grasps (G, N, T), fell (G, N), angle (G, N)) of an
    envelope result of `model` (None: the default), its sequences laid out kind by kind as `envelope` writes
    them."""
    file = pathlib.Path(path)
    if not file.is_file():
        raise SystemExit(f"--pool: no envelope result at {path!r} (python -m experiments envelope writes one)")
    data = files.read_json(file)
    missing = {"set", "episodes", "kinds", "sequences"} - set(data)
    if missing:
        raise SystemExit(f"--pool: {path!r} is not an envelope result (missing {sorted(missing)})")
    names, kinds = data["episodes"], data["kinds"]
    seqs = data["sequences"]
    if len(seqs) != len(names) * len(kinds):
        raise SystemExit(f"--pool: {len(seqs)} sequences for {len(kinds)} kinds x {len(names)} episodes")
    keep = names[:n_episodes] if n_episodes else names
    episodes = scenario.episode_set(data["set"], model)
    batch = scenario.stack([episodes[n] for n in keep])
    rows = np.array([[seqs[g * len(names) + e] for e in range(len(keep))] for g in range(len(kinds))], object)
    grasps = np.array([[r["grasps"] for r in row] for row in rows], np.int32)
    fell = np.array([[r["fell"] for r in row] for row in rows], bool)
    angle = np.array([[r["angle_deg"] for r in row] for row in rows], float)
    return data["set"], keep, batch, kinds, grasps, fell, angle


def step_states(sur: surrogate.Surrogate, start: np.ndarray, grasps: np.ndarray):
    """The states a pool's steps read: for every step (g, e, t) the new grasp at waypoints t and t+1 and the shared
    grasp (what stays during a change) at t. Returns the distinct (episode, grasp, waypoint) keys (S, 3) and, per
    step, the indices of its three states into them (3, G, N, T), and whether the step changes the grasp."""
    G, N, T = grasps.shape
    prev = np.concatenate([np.broadcast_to(start[None, :, None], (G, N, 1)), grasps[..., :-1]], -1)
    decode = jax.jit(jax.vmap(sur.space.decode))
    old, new = (np.asarray(decode(jnp.asarray(x.ravel()))).reshape(G, N, T, -1) for x in (prev, grasps))
    shared = np.asarray(jax.jit(jax.vmap(sur.space.encode))(jnp.asarray(np.where(old != new, 0, new).reshape(
        -1, new.shape[-1])))).reshape(G, N, T)
    e = np.broadcast_to(np.arange(N)[None, :, None], (G, N, T))
    t = np.broadcast_to(np.arange(T), (G, N, T))
    wanted = np.stack([np.stack([e, grasps, t], -1), np.stack([e, grasps, np.minimum(t + 1, T - 1)], -1),
                       np.stack([e, shared, t], -1)])  # (3, G, N, T, 3)
    keys, index = np.unique(wanted.reshape(-1, 3), axis=0, return_inverse=True)
    return keys, index.reshape(3, G, N, T), grasps != prev


def realise_states(sur: surrogate.Surrogate, batch: scenario.Episode, keys: np.ndarray, size: int):
    """`Surrogate.realise` of every (episode, grasp, waypoint) key (S, 3), `size` at a time: Contacts (S, ...),
    numpy. Several processes share the chunks of `size` (`distributed.map_chunks`; each one program, vmapped)."""
    def one(key):
        ep = jax.tree.map(lambda x: x[key[0]], batch)
        return sur.realise(key[1], ep.waypoints[key[2]], ep.quats[key[2]])

    run = jax.jit(jax.vmap(one))
    return distributed.map_chunks(lambda idx: _cut(run(jnp.asarray(_filled(keys, idx, size), jnp.int32)), len(idx)),
                                  len(keys), size, what="states")


def score_pool(reward: reward_lib.RewardConfig, hand, batch, contacts, index, changed, size: int):
    """(returns (G, N), feasible (G, N)) of the pool's sequences under `reward`: each step scored as a DP table
    scores it (the tool on its waypoint, the change term from the shared grasp), summed up to the first step that
    ends the episode. The steps go `size` at a time, shared by several processes as `realise_states`."""
    sur = surrogate.Surrogate(hand=hand, reward=reward)
    _, G, N, T = index.shape
    contacts = jax.tree.map(jnp.asarray, contacts)  # on the device once, not once per chunk

    def step(contacts, e, t, a, b, c, ch):
        ep = jax.tree.map(lambda x: x[e], batch)
        pick = lambda i: jax.tree.map(lambda x: x[i], contacts)  # noqa: E731
        terms = sur.score(ep, t, ep.waypoints[t], ep.quats[t], pick(a), pick(b), False, pick(c), ch)
        return terms.reward, terms.fall | terms.collision

    e = np.broadcast_to(np.arange(N)[None, :, None], (G, N, T)).ravel()
    t = np.broadcast_to(np.arange(T), (G, N, T)).ravel()
    columns = np.stack([e, t, index[0].ravel(), index[1].ravel(), index[2].ravel(), changed.ravel()], -1)  # (steps, 6)
    run = jax.jit(jax.vmap(lambda cs, x: step(cs, *x), (None, 0)))
    r, end = (x.reshape(G, N, T) for x in distributed.map_chunks(
        lambda idx: _cut(run(contacts, jnp.asarray(_filled(columns, idx, size), jnp.int32)), len(idx)),
        len(columns), size, what="steps"))
    alive = np.concatenate([np.ones((G, N, 1), bool), np.cumsum(end, -1)[..., :-1] == 0], -1)
    return np.sum(np.where(alive, r, 0.0), -1), ~np.any(end, -1)


def _filled(rows: np.ndarray, idx: np.ndarray, size: int) -> np.ndarray:
    """rows[idx] filled up to `size` rows with copies of the last (every chunk one program)."""
    return rows[np.concatenate([idx, np.full(size - len(idx), idx[-1])])]


def _cut(tree, n: int):
    """The first n rows of every leaf, as numpy."""
    return jax.tree.map(lambda x: np.asarray(x)[:n], tree)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("rescore",)]


def main(args: argparse.Namespace, run: Run) -> None:
    if args.batch < 1:
        raise SystemExit(f"--batch must be >= 1, got {args.batch}")
    base = reward_lib.RewardConfig()
    rewards = [("calibrated", base)] + [(text, parse_reward(text, base)) for text in args.reward]
    sur = surrogate.Surrogate(run.model, learned=run.learned)
    set_name, names, batch, kinds, grasps, fell, angle = load_pool(args.pool, args.episodes, sur.model)
    t0 = time.perf_counter()
    keys, index, changed = step_states(sur, np.asarray(batch.start_grasp), grasps)
    print(f"rescore: {grasps.shape[0]} x {len(names)} sequences of '{set_name}' ({grasps.size} steps, {len(keys)} "
          f"distinct states to realise) ...", flush=True)
    contacts = realise_states(sur, batch, keys, args.batch)
    print(f"  IK {time.perf_counter() - t0:.0f} s", flush=True)
    rows, out = [], []
    for label, reward in rewards:
        t1 = time.perf_counter()
        returns, feasible = score_pool(reward, sur.hand, batch, contacts, index, changed, args.batch)
        pool = summarise(kinds, fell, angle, feasible, returns, {})["pool"]
        within = [stats.spearman(returns[:, e], -angle[:, e]) for e in range(len(names))]
        within = [r for r in within if np.isfinite(r)]
        pool |= dict(spearman_within_mean=float(np.mean(within)) if within else float("nan"),
                     spearman_within_episodes=len(within))
        if not out and distributed.is_main():
            scatter_png(returns, angle, kinds, run.results_dir("rescore") / f"{set_name}.png", f"{set_name}, {label}",
                        pool)
        out.append(dict(reward=label, config=dataclasses.asdict(reward), **pool))
        rows.append([label, pool["surrogate_feasible"], pool["feasible_hold_share"], pool["auc_pooled"],
                     pool["auc_within_mean"], pool["spearman_pooled"], pool["spearman_within_mean"]])
        print(f"  {label}: {time.perf_counter() - t1:.0f} s", flush=True)
    if not distributed.is_main():
        return  # process 0 writes
    path = run.results_dir("rescore") / f"{set_name}.json"
    files.write_json(path, dict(pool=str(args.pool), set=set_name, episodes=names, sequences=int(fell.size),
                                    physics_falls=int(fell.sum()), rewards=out))
    print(f"wrote {path}\n")
    print(f"{fell.size} sequences of '{set_name}', {int(fell.sum())} fell in the recorded physics")
    print(table(["reward", "feasible", "of them held", "AUC pooled", "AUC within", "Spearman rho",
                 "rho within episodes"], rows))


def scatter_png(returns, angle, kinds, path, title: str, pool: dict) -> None:
    """Surrogate return (G, N) against the simulated angle error [deg] (180: fell), planners coloured, random grey."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for g, kind in enumerate(kinds):
        planner = not kind.startswith("random")
        ax.scatter(returns[g], angle[g], s=14 if planner else 8, c=None if planner else "0.65",
                   label=kind if planner else ("random feasible" if g == len(kinds) - 1 else None),
                   zorder=2 if planner else 1)
    ax.set_xscale("symlog", linthresh=1.0)
    ax.set_xlabel("surrogate return (symlog)")
    ax.set_ylabel("simulated angle error under the torque [deg]\n(180 = fell)")
    ax.set_title(f"surrogate vs physics, {title}: Spearman {pool['spearman_pooled']:.2f}")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
