"""Calibrating the surrogate's reward against physics: candidate rewards, their DP tables with the IK shared, a pool
of grasp sequences per episode, the pool's physics outcomes, each candidate's scores, and the choice.

    configs = candidates()                                   # the grid (`GRID`): grip, fall threshold, change term
    tables = candidate_tables(configs, batch)                # one dp.Table per candidate, leaves (E, ...)
    pool = sequence_pool(configs, tables, nominal_tables, batch, n_random, seed)
    outcomes = simulate_pool(pool, episodes, "c", 512, cache_path, t0)
    rows, returns = score_candidates(configs, tables, batch, names, flat, angle, fell)
    verdict = choose(rows, incumbent=label(reward.RewardConfig()))

The choice: the candidate whose DP-optimal plans fall least, then the highest rank correlation; it replaces the
incumbent (today's calibration) only where a paired sign test over the episodes says it falls significantly less
(`ALPHA`). docs/calibration.md has what the sweeps measured.
"""
from __future__ import annotations

import dataclasses
import itertools
import time

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.planning import dp, evaluation, policies
from gsp_jax.core import files
from gsp_jax.model import load as model_lib, scenario
from gsp_jax.surrogate import reward, step as surrogate
from gsp_jax.physics.runner import Physics
from gsp_jax.core.stats import sign_test, spearman

GRID = dict(  # the candidates: every combination (docs/calibration.md: what earlier sweeps measured)
    grip=((0.0, False), (2.0, False), (4.0, False), (2.0, True), (4.0, True), (6.0, True)),  # (grip [N], x m / m0)
    fall_unmet=(0.15, 0.2, 0.25, 0.3),
    change=((0.0, False), (1.0, True), (5.0, True)),  # (w_wrench_change, change_falls): off / on / on, weighted 5
)
HOLDS = (0.0, 0.6, 0.9)
ALPHA = 0.05  # a challenger replaces the incumbent calibration only at this significance (`choose_and_write`)

def candidates() -> list[reward.RewardConfig]:
    base = reward.RewardConfig()
    return [dataclasses.replace(base, grip=gr, grip_scales_with_mass=gm, fall_unmet=fu, w_wrench_change=w,
                                change_falls=cf)
            for (gr, gm), fu, (w, cf) in itertools.product(GRID["grip"], GRID["fall_unmet"], GRID["change"])]


def label(cfg: reward.RewardConfig) -> str:
    change = f"w {cfg.w_wrench_change:g}" if cfg.change_falls or cfg.w_wrench_change else "off"
    grip = f"{cfg.grip:g} N x m/m0" if cfg.grip_scales_with_mass else f"{cfg.grip:g} N"
    return f"mu x1, grip {grip}, fall {cfg.fall_unmet:g}, change {change}"  # "mu x1": as the saved sweeps name it


def candidate_tables(configs, episodes: scenario.Episode, model=None) -> list[dp.Table]:
    """Every candidate's tables (leaves (E, ...)) for `model` (None: the default): IK once, wrench solves once per
    grip."""
    grip_key = lambda c: (c.grip, c.grip_scales_with_mass)  # noqa: E731
    base = surrogate.Surrogate(model, reward=configs[0], learned=False)  # the analytic reward is what is calibrated
    contacts = jax.jit(jax.vmap(lambda ep: dp.realise_all(base, ep)))(episodes)
    terms = {}
    for gr, gm in sorted({grip_key(c) for c in configs}):
        sur = base.replace(reward=dataclasses.replace(configs[0], grip=gr, grip_scales_with_mass=gm))
        terms[gr, gm] = jax.jit(jax.vmap(lambda ep, c: dp.grasp_terms(sur, ep, c)))(episodes, contacts)
    out = []
    for cfg in configs:
        sur = base.replace(reward=cfg)
        out.append(jax.jit(jax.vmap(lambda ep, t, c: dp.table_from_terms(sur, ep, t, c)))(
            episodes, terms[grip_key(cfg)], contacts))
    return out


def sequence_pool(configs, tables, nominal_tables, batch, n_random: int, seed: int,
                  model=None) -> list[list[tuple[str, tuple]]]:
    """Per episode, the distinct (kind, actions) sequences the candidates are scored on: the scripted ones, four
    tips, one tip, every candidate's DP optimum and DP baseline, and `n_random` random feasible ones (`model`'s
    grasp space; None: the default model)."""
    n_e, n_t = int(np.shape(batch.mass)[0]), scenario.N_WAYPOINTS
    backup = jax.jit(jax.vmap(dp.backup))
    pool: list[list[tuple[str, tuple]]] = [[] for _ in range(n_e)]

    def add(e, kind, actions):
        key = tuple(int(a) for a in actions)
        if key not in {k for _, k in pool[e]}:
            pool[e].append((kind, key))

    space = model_lib.load_model(model).space
    for name, seq in evaluation.scripted_sequences(space).items():
        for e in range(n_e):
            add(e, name, seq)
    for e in range(n_e):
        add(e, "four-tips", evaluation.four_tips(space, n_t))
        add(e, "one-tip", evaluation.one_tip(space, n_t))
    nominal = scenario.make_episode(model=model)
    for i, tab in enumerate(tables):
        opt = np.asarray(backup(tab, batch.start_grasp).actions)
        nom = jax.tree.map(lambda x: x[0], nominal_tables[i])
        base_seq = np.asarray(dp.backup(nom, nominal.start_grasp).actions)
        for e in range(n_e):
            add(e, "dp-opt", opt[e])
            add(e, "dp-base", base_seq)
    key = jax.random.PRNGKey(seed)
    sample = jax.jit(jax.vmap(dp.random_sequence, (0, 0, 0, None, None)), static_argnums=())
    for r in range(n_random):
        tab = tables[r % len(tables)]
        keys = jax.random.split(jax.random.fold_in(key, r), n_e)
        seqs = np.asarray(sample(tab, batch.start_grasp, keys, configs[0].r_min, HOLDS[r % len(HOLDS)]))
        for e in range(n_e):
            add(e, "random", seqs[e])
    return pool


def simulate_pool(pool, episodes: dict, backend: str, chunk_size: int, cache_path, t0: float, model=None) -> dict:
    """Every (episode, sequence) of the pool in `model`'s physics (None: the default model; `backend`, at most
    `chunk_size` a batch), cached in the JSON file `cache_path` (kept after each chunk, so an interrupted run resumes):
    {"<episode>|<actions>": [angle error [deg], fell]}. Prints progress against the start time `t0` [s,
    perf_counter]."""
    names = list(episodes)
    cache = files.reuse_json(cache_path, lambda c: isinstance(c, dict)) or {}  # unreadable: warned, resimulated
    todo = [(e, seq) for e in range(len(names)) for _, seq in pool[e] if pool_key(names, e, seq) not in cache]
    n_pool = sum(len(p) for p in pool)
    print(f"  pool: {n_pool} distinct (episode, sequence) pairs, {len(todo)} to simulate ({backend})", flush=True)
    phys = Physics(surrogate.Surrogate(model))
    n_chunks = max(1, -(-len(todo) // chunk_size))
    chunk = -(-len(todo) // n_chunks) if todo else 0  # equal chunks: one MJX compile
    for i in range(0, len(todo), max(chunk, 1)):
        part = todo[i:i + chunk]
        padded = part + [part[0]] * (chunk - len(part))  # the last chunk padded to the same shape
        eps = scenario.stack([episodes[names[e]] for e, _ in padded])
        acts = jnp.asarray([seq for _, seq in padded], jnp.int32)
        res = phys.simulate_batch(policies.SequencePolicy(acts), eps, 0, backend=backend)
        for j, (e, seq) in enumerate(part):
            cache[pool_key(names, e, seq)] = [float(res.angle_error[j]), bool(res.fell[j])]
        files.write_json(cache_path, cache, indent=None)
        print(f"  simulated {min(i + chunk, len(todo))}/{len(todo)}, {time.perf_counter() - t0:.0f} s", flush=True)
    return cache


def pool_key(names, e: int, seq) -> str:
    """The cache key of episode `names[e]` run with the action sequence `seq`."""
    return f"{names[e]}|{','.join(map(str, seq))}"


def score_candidates(configs, tables, batch, names, flat, angle, fell):
    """Each candidate's scores of the whole pool `flat` [(episode, kind, actions)]: its sweep row (correlation with
    physics, feasible share held, its DP optimum's falls, angle and changes), and its returns of the pool."""
    backup = jax.jit(jax.vmap(dp.backup))
    score = jax.jit(jax.vmap(dp.sequence_return, (0, 0, 0)))
    ep_idx = np.array([e for e, _, _ in flat])
    acts = jnp.asarray([seq for _, _, seq in flat], jnp.int32)
    results, rets = [], []
    for cfg, tab in zip(configs, tables):
        per_seq = jax.tree.map(lambda x: x[ep_idx], tab)
        ret = np.asarray(score(per_seq, batch.start_grasp[ep_idx], acts))
        feasible = ret > cfg.r_min + 1e-3 * abs(cfg.r_min)
        sol = backup(tab, batch.start_grasp)
        opt = np.asarray(sol.actions)
        opt_idx = [next(i for i, (e2, _, s) in enumerate(flat) if e2 == e and s == tuple(opt[e].tolist()))
                   for e in range(len(names))]
        rho = spearman(ret, -angle)
        held_feasible = float(np.mean(~fell[feasible])) if feasible.any() else float("nan")
        g = np.asarray(sol.grasps)
        changes = float(np.mean(np.sum((g[:, 1:] != g[:, :-1]) & np.asarray(sol.alive), axis=1)))
        results.append(dict(config=dataclasses.asdict(cfg), label=label(cfg), spearman=rho,
                            feasible=int(feasible.sum()), feasible_held=held_feasible,
                            dp_opt_falls=int(fell[opt_idx].sum()), dp_opt_fell=[bool(x) for x in fell[opt_idx]],
                            dp_opt_angle=float(angle[opt_idx].mean()),
                            dp_opt_changes=changes,
                            dp_opt_sequences={names[e]: [int(a) for a in opt[e]] for e in range(len(names))}))
        rets.append(ret)
    return results, rets


def choose(results: list[dict], incumbent: str | None) -> dict:
    """The verdict on a sweep's rows (`score_candidates`): the challenger (fewest DP-optimal falls, then the highest
    rho; a candidate under which no sequence is feasible has no rho and comes last), the incumbent row (labelled
    `incumbent`, if in the sweep), the sign test between them (`challenge`: held only by each, p, ALPHA) and the row
    chosen: the incumbent unless the challenger falls significantly less."""
    rho = np.nan_to_num(np.array([np.nan if r["spearman"] is None else r["spearman"] for r in results], float),
                        nan=-1.0)
    finite = np.isfinite([np.nan if r["spearman"] is None else r["spearman"] for r in results])
    best = min(range(len(results)), key=lambda i: (not finite[i], results[i]["dp_opt_falls"], -rho[i]))
    challenger = chosen = results[best]
    current = next((r for r in results if r["label"] == incumbent), None)
    out = dict(challenger=challenger, incumbent=current, challenge=None)
    if current is not None and current is not challenger and "dp_opt_fell" in current:
        wins, losses, p = sign_test(challenger["dp_opt_fell"], current["dp_opt_fell"])
        out["challenge"] = dict(challenger=challenger["label"], incumbent=current["label"], held_only_by=[wins, losses],
                                p=p, alpha=ALPHA)
        if p >= ALPHA:
            chosen = current
    return out | dict(chosen=chosen)


def measured(res: dict, summary: dict) -> dict:
    """What the sweep `summary` measured for its chosen row `res`, as `reward.write_calibration` records it."""
    return dict(  # on the calibration episodes, against the physics check
        sets="+".join(summary["sets"]), backend=summary["backend"], sequences=summary["sequences"],
        spearman=round(res["spearman"], 3),  # rank correlation of surrogate return and -simulated angle error, pooled
        feasible_held=round(res["feasible_held"], 3),  # share of the surrogate-feasible sequences that held
        dp_opt_falls=res["dp_opt_falls"], episodes=len(summary["episodes"]),  # DP-optimal plans that fell, of these
        dp_opt_changes=round(res["dp_opt_changes"], 2),  # mean grasp changes per episode of the DP-optimal plans
        best_spearman=round(summary["best_spearman"], 3),  # the sweep's highest correlation (another candidate) ...
        best_spearman_se=round(summary["best_spearman_se"], 3))  # ... and its cluster bootstrap SE
