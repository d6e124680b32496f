"""`python -m experiments calibrate [--sets train,val] [--random 16] [--backend c] [--write]`: the surrogate's reward
calibrated against the physics check, on the training and validation episodes only (never the evaluation set).

1. Every candidate `RewardConfig` of a grid (the wrench solves' grip, fixed or in proportion to the tool's mass, the
   fall threshold, the grasp-change term on or off) scores every episode's DP table. The IK is shared by all
   candidates (it does not depend on the reward), the wrench solves by all candidates of one grip.
2. A pool of grasp sequences per episode: each candidate's DP optimal and DP baseline (the nominal episode's
   optimal sequence), `--random` random sequences feasible under the candidates' tables in turn (holding the grasp
   with probability 0, 0.6 or 0.9), and the scripted references of `physics` (four tips, the alternating changes,
   add-and-slide, one tip). Duplicates are simulated once.
3. The pool through the physics check (`--backend c`: C MuJoCo on the CPU, the same controller as MJX), open loop.
   Outcomes are cached in results/calibrate/physics_<backend>.json, so an interrupted run resumes.
4. Per candidate: the Spearman rank correlation between each sequence's surrogate return and its simulated
   -angle error (180 deg when the tool fell), pooled; the share of surrogate-feasible sequences that hold; DP
   optimal's falls and grasp changes. The winner: the candidate whose DP-optimal plans fall least in physics, then
   the higher correlation. (A planner uses the surrogate through its optimum: correlation alone can pick a reward
   whose DP plans drop the tool far more often; docs/calibration.md.)

Prints the sweep as a table; writes results/calibrate/sweep.json, and with --write the winner into
models/reward_calibration.json (`reward.write_calibration`), where `RewardConfig` reads its defaults."""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import results_dir, table
from gsp_jax.stats import spearman
from gsp_jax import dp, evaluation, files, physics, policies, reward, scenario, surrogate

GRID = dict(  # the candidates: every combination (docs/calibration.md: what earlier sweeps measured)
    grip=((0.0, False), (2.0, False), (4.0, False), (2.0, True), (4.0, True), (6.0, True)),  # (grip [N], x m / m0)
    fall_unmet=(0.15, 0.2, 0.25, 0.3),
    change=((0.0, False), (1.0, True), (5.0, True)),  # (w_wrench_change, change_falls): off / on / on, weighted 5
)
HOLDS = (0.0, 0.6, 0.9)
ALPHA = 0.05  # a challenger replaces the incumbent calibration only at this significance (`choose_and_write`)
CALIBRATION_JSON = reward.CALIBRATION_JSON  # where `--write` puts the chosen defaults


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sets", default="train,val", help="comma-separated episode sets (never eval)")
    p.add_argument("--random", type=int, default=16, help="random feasible sequences per episode")
    p.add_argument("--backend", default="c", choices=physics.BACKENDS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=512, help="most sequences per physics batch")
    p.add_argument("--write", action="store_true", help="write the winner into models/reward_calibration.json")
    p.add_argument("--from-sweep", default=None, help="choose from a saved results/calibrate/sweep.json (no reruns)")


def candidates() -> list[reward.RewardConfig]:
    base = reward.RewardConfig()
    return [dataclasses.replace(base, grip=gr, grip_scales_with_mass=gm, fall_unmet=fu, w_wrench_change=w,
                                change_falls=cf)
            for (gr, gm), fu, (w, cf) in itertools.product(GRID["grip"], GRID["fall_unmet"], GRID["change"])]


def label(cfg: reward.RewardConfig) -> str:
    change = f"w {cfg.w_wrench_change:g}" if cfg.change_falls or cfg.w_wrench_change else "off"
    grip = f"{cfg.grip:g} N x m/m0" if cfg.grip_scales_with_mass else f"{cfg.grip:g} N"
    return f"mu x1, grip {grip}, fall {cfg.fall_unmet:g}, change {change}"  # "mu x1": as the saved sweeps name it


def candidate_tables(configs, episodes: scenario.Episode) -> list[dp.Table]:
    """Every candidate's tables (leaves (E, ...)): IK once, wrench solves once per grip."""
    grip_key = lambda c: (c.grip, c.grip_scales_with_mass)  # noqa: E731
    base = surrogate.Surrogate(reward=configs[0])
    contacts = jax.jit(jax.vmap(lambda ep: dp.realise_all(base, ep)))(episodes)
    terms = {}
    for gr, gm in sorted({grip_key(c) for c in configs}):
        sur = surrogate.Surrogate(hand=base.hand, reward=dataclasses.replace(configs[0], grip=gr,
                                                                             grip_scales_with_mass=gm))
        terms[gr, gm] = jax.jit(jax.vmap(lambda ep, c: dp.grasp_terms(sur, ep, c)))(episodes, contacts)
    out = []
    for cfg in configs:
        sur = surrogate.Surrogate(hand=base.hand, reward=cfg)
        out.append(jax.jit(jax.vmap(lambda ep, t, c: dp.table_from_terms(sur, ep, t, c)))(
            episodes, terms[grip_key(cfg)], contacts))
    return out


def _from_sweep(path: str, write: bool) -> None:
    """`--from-sweep`: choose (and with `write`, write) from a saved sweep."""
    summary = files.read_json(path)
    if "rows" not in summary:
        summary["rows"] = [[r["label"], r["spearman"], r["feasible"], r["feasible_held"], r["dp_opt_falls"],
                            r["dp_opt_angle"], r["dp_opt_changes"]] for r in summary["sweep"]]
    summary.setdefault("best_spearman_label", max(summary["sweep"], key=lambda r: np.nan_to_num(
        r["spearman"], nan=-1.0))["label"])
    cache_path = results_dir("calibrate") / f"physics_{summary['backend']}.json"
    if cache_path.exists():  # sweeps written before the per-episode falls were kept: read them off the cache
        cache = files.reuse_json(cache_path, lambda c: isinstance(c, dict)) or {}
        names = summary["episodes"]
        for r in summary["sweep"]:
            if "dp_opt_fell" in r or "dp_opt_sequences" not in r:
                continue
            keys = [pool_key(names, e, r["dp_opt_sequences"][n]) for e, n in enumerate(names)]
            if all(k in cache for k in keys):
                r["dp_opt_fell"] = [bool(cache[k][1]) for k in keys]
    choose_and_write(summary, write)


def sequence_pool(configs, tables, nominal_tables, batch, n_random: int, seed: int) -> list[list[tuple[str, tuple]]]:
    """Per episode, the distinct (kind, actions) sequences the candidates are scored on: the scripted ones, four
    tips, one tip, every candidate's DP optimum and DP baseline, and `n_random` random feasible ones."""
    n_e, n_t = int(np.shape(batch.mass)[0]), scenario.N_WAYPOINTS
    backup = jax.jit(jax.vmap(dp.backup))
    pool: list[list[tuple[str, tuple]]] = [[] for _ in range(n_e)]

    def add(e, kind, actions):
        key = tuple(int(a) for a in actions)
        if key not in {k for _, k in pool[e]}:
            pool[e].append((kind, key))

    space = surrogate.Surrogate().space
    for name, seq in evaluation.scripted_sequences(space).items():
        for e in range(n_e):
            add(e, name, seq)
    for e in range(n_e):
        add(e, "four-tips", evaluation.four_tips(space, n_t))
        add(e, "one-tip", evaluation.one_tip(space, n_t))
    nominal = scenario.make_episode()
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


def simulate_pool(pool, episodes: dict, backend: str, chunk_size: int, t0: float) -> dict:
    """Every (episode, sequence) of the pool in physics, cached in results/calibrate/physics_<backend>.json (kept
    after each chunk): {"<episode>|<actions>": [angle error, fell]}."""
    names = list(episodes)
    cache_path = results_dir("calibrate") / f"physics_{backend}.json"
    cache = files.reuse_json(cache_path, lambda c: isinstance(c, dict)) or {}  # unreadable: warned, resimulated
    todo = [(e, seq) for e in range(len(names)) for _, seq in pool[e] if pool_key(names, e, seq) not in cache]
    n_pool = sum(len(p) for p in pool)
    print(f"  pool: {n_pool} distinct (episode, sequence) pairs, {len(todo)} to simulate ({backend})", flush=True)
    phys = physics.Physics(surrogate.Surrogate())
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
        opt = np.asarray(backup(tab, batch.start_grasp).actions)
        opt_idx = [next(i for i, (e2, _, s) in enumerate(flat) if e2 == e and s == tuple(opt[e].tolist()))
                   for e in range(len(names))]
        rho = spearman(ret, -angle)
        held_feasible = float(np.mean(~fell[feasible])) if feasible.any() else float("nan")
        sol = backup(tab, batch.start_grasp)
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


def main(args: argparse.Namespace) -> None:
    if args.from_sweep:
        return _from_sweep(args.from_sweep, args.write)
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    if any(s.startswith("eval") or s == "all" for s in sets):
        raise SystemExit(f"--sets: calibration never uses the evaluation episodes, got {args.sets!r}")
    episodes = {}
    for s in sets:
        episodes.update(scenario.episode_set(s))
    names, batch = list(episodes), scenario.stack(list(episodes.values()))
    configs = candidates()
    t0 = time.perf_counter()
    print(f"calibrate: {len(configs)} candidate rewards x {len(names)} episodes ({'+'.join(sets)}) ...", flush=True)
    tables = candidate_tables(configs, batch)
    nominal_tables = candidate_tables(configs, scenario.stack([scenario.make_episode()]))
    print(f"  tables: {time.perf_counter() - t0:.0f} s", flush=True)
    pool = sequence_pool(configs, tables, nominal_tables, batch, args.random, args.seed)
    cache = simulate_pool(pool, episodes, args.backend, args.chunk, t0)
    flat = [(e, kind, seq) for e in range(len(names)) for kind, seq in pool[e]]
    angle = np.array([cache[pool_key(names, e, seq)][0] for e, _, seq in flat])
    fell = np.array([cache[pool_key(names, e, seq)][1] for e, _, seq in flat])
    results, rets = score_candidates(configs, tables, batch, names, flat, angle, fell)
    rho_all = np.nan_to_num(np.array([r["spearman"] for r in results]), nan=-1.0)
    top = int(np.argmax(rho_all))
    se = bootstrap_se(rets[top], angle, np.array([e for e, _, _ in flat]), args.seed)
    summary = dict(sets=sets, episodes=names, sequences=len(flat), physics_falls=int(fell.sum()),
                   best_spearman=float(rho_all[top]), best_spearman_se=se, best_spearman_label=results[top]["label"],
                   backend=args.backend, chosen=None, sweep=results,
                   kinds={k: int(sum(1 for _, kk, _ in flat if kk == k)) for k in sorted({k for _, k, _ in flat})},
                   wall_s=time.perf_counter() - t0,
                   rows=[[r["label"], r["spearman"], r["feasible"], r["feasible_held"], r["dp_opt_falls"],
                          r["dp_opt_angle"], r["dp_opt_changes"]] for r in results])
    print(f"\n{len(flat)} sequences on {len(names)} episodes ({'+'.join(sets)}), {int(fell.sum())} fell in physics "
          f"({args.backend}); {time.perf_counter() - t0:.0f} s")
    choose_and_write(summary, args.write)  # sets summary["chosen"]
    files.write_json(results_dir("calibrate") / "sweep.json", summary)


def choose_and_write(summary: dict, write: bool) -> dict:
    """Print the sweep, pick the winner and, with `write`, write it. The challenger is the candidate whose DP-optimal
    plans fall least, then the highest correlation (a candidate under which no sequence is feasible has no
    correlation and no meaningful optimum, and comes last). It replaces the incumbent (today's calibration, if it
    is in the sweep) only where it falls significantly less: a paired sign test over the episodes where exactly
    one of the two DP optima fell (`challenger_wins`). Single physics verdicts near the envelope's edge are last-bit
    decisions, so a few falls either way are noise."""
    results, n_e = summary["sweep"], len(summary["episodes"])
    print(table(["candidate reward", "rho", "feasible", "of them held", f"DP opt falls /{n_e}", "DP opt angle",
                 "DP opt changes"], summary["rows"], ".3f"))
    rho = np.nan_to_num(np.array([r["spearman"] for r in results]), nan=-1.0)
    finite = np.isfinite([np.nan if r["spearman"] is None else r["spearman"] for r in results])
    best = min(range(len(results)), key=lambda i: (not finite[i], results[i]["dp_opt_falls"], -rho[i]))
    challenger, chosen = results[best], results[best]
    incumbent = next((r for r in results if r["label"] == label(reward.RewardConfig())), None)
    print(f"\nhighest rho: {summary['best_spearman_label']} ({summary['best_spearman']:.3f} +- "
          f"{summary['best_spearman_se']:.3f}, bootstrap over episodes)")
    print(f"challenger (fewest DP-optimal falls, then rho): {challenger['label']} (rho {challenger['spearman']:.3f}, "
          f"DP optimal falls {challenger['dp_opt_falls']}/{n_e}, {challenger['dp_opt_changes']:.2f} grasp changes)")
    if incumbent is not None and incumbent is not challenger and "dp_opt_fell" in incumbent:
        wins, losses, p = challenger_wins(challenger["dp_opt_fell"], incumbent["dp_opt_fell"])
        summary["challenge"] = dict(challenger=challenger["label"], incumbent=incumbent["label"], held_only_by=[
            wins, losses], p=p, alpha=ALPHA)
        print(f"against the incumbent {incumbent['label']} (DP optimal falls {incumbent['dp_opt_falls']}/{n_e}): "
              f"the challenger alone holds {wins} episodes, the incumbent alone {losses}; sign test p = {p:.3f}")
        if p >= ALPHA:
            chosen = incumbent
    summary["chosen"] = chosen
    print(f"chosen: {chosen['label']}")
    if write:
        write_calibration(chosen, summary)
        print(f"wrote {CALIBRATION_JSON}")
    return chosen


def challenger_wins(challenger_fell, incumbent_fell) -> tuple[int, int, float]:
    """(episodes only the challenger's plan held, episodes only the incumbent's held, the two-sided exact sign
    test's p-value that they are equally likely) from the per-episode falls (E,) of two DP optima."""
    from scipy import stats

    c, i = np.asarray(challenger_fell, bool), np.asarray(incumbent_fell, bool)
    if c.shape != i.shape:
        raise ValueError(f"challenger_wins: falls of {c.shape} and {i.shape} episodes")
    wins, losses = int(np.sum(~c & i)), int(np.sum(c & ~i))
    p = 1.0 if wins + losses == 0 else float(stats.binomtest(wins, wins + losses, 0.5).pvalue)
    return wins, losses, p


def bootstrap_se(ret, angle, ep_idx, seed: int, n: int = 200) -> float:
    """Standard error of the pooled Spearman correlation, resampling whole episodes (their sequences are not
    independent)."""
    rng = np.random.default_rng(seed)
    eps = np.unique(ep_idx)
    by_ep = [np.flatnonzero(ep_idx == e) for e in eps]
    vals = []
    for _ in range(n):
        idx = np.concatenate([by_ep[i] for i in rng.integers(0, len(eps), len(eps))])
        vals.append(spearman(ret[idx], -angle[idx]))
    vals = np.asarray(vals)
    return float(np.nanstd(vals[np.isfinite(vals)])) if np.isfinite(vals).any() else float("nan")


def write_calibration(res: dict, summary: dict) -> None:
    """The chosen sweep row `res` and what the sweep measured for it, written to `CALIBRATION_JSON`."""
    cfg, default = res["config"], reward.RewardConfig()
    values = {k: cfg.get(k, getattr(default, k)) for k in reward.CALIBRATED_FIELDS}
    measured = dict(  # on the calibration episodes, against the physics check
        sets="+".join(summary["sets"]), backend=summary["backend"], sequences=summary["sequences"],
        spearman=round(res["spearman"], 3),  # rank correlation of surrogate return and -simulated angle error, pooled
        feasible_held=round(res["feasible_held"], 3),  # share of the surrogate-feasible sequences that held
        dp_opt_falls=res["dp_opt_falls"], episodes=len(summary["episodes"]),  # DP-optimal plans that fell, of these
        dp_opt_changes=round(res["dp_opt_changes"], 2),  # mean grasp changes per episode of the DP-optimal plans
        best_spearman=round(summary["best_spearman"], 3),  # the sweep's highest correlation (another candidate) ...
        best_spearman_se=round(summary["best_spearman_se"], 3))  # ... and its bootstrap SE (`choose_and_write`)
    reward.write_calibration(CALIBRATION_JSON, values, measured)
