"""The stress envelope's verdicts: every fall classified by the feasibility oracle, and a pool of physics outcomes
summarised against the surrogate (falls, necessary / controller / undetermined, regret, AUC, Spearman).

    verdicts = classify(episodes, jobs, processes)   # jobs: (episode index, grasps (T+1,), reached qpos (T, nq), rows)
    summary = summarise(kinds, fell, angle, feasible, returns, classes, early)
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

import jax
import numpy as np

from gsp_jax.model import scenario
from gsp_jax.core.stats import auc, spearman


# ------------------------------------------------------------------------------------------- the summary
PREDICTED_HOLD = 0.5  # a feasible sequence the learned term gives at least this chance to hold is predicted to hold


def summarise(kinds, fell, angle, feasible, returns, classes, early=None, hold=None) -> dict:
    """Per kind and over the pool. kinds (G,) names (the planners first, then random ones); fell, angle, feasible,
    returns (G, N) per sequence; classes {(g, e): "necessary" | "controller" | "undetermined"} for every fall;
    early {(g, e): bool}: a necessary fall that came before the point the oracle calls impossible; hold (G, N): the
    learned term's chance that each sequence holds (None without it), which adds the pool's `predicted_hold`
    (feasible sequences with a chance of at least `PREDICTED_HOLD`) and the share of them that held."""
    early = early or {}
    fell, angle = np.asarray(fell, bool), np.asarray(angle, float)
    feasible, returns = np.asarray(feasible, bool), np.asarray(returns, float)
    G, N = fell.shape
    held_any = ~fell  # (G, N)
    rows = {}
    for g, kind in enumerate(kinds):
        cls = [classes.get((g, e)) for e in range(N) if fell[g, e]]
        others = np.delete(held_any, g, axis=0).any(0)
        held = ~fell[g]
        rows[kind] = dict(
            episodes=N, falls=int(fell[g].sum()), necessary=cls.count("necessary"), controller=cls.count("controller"),
            undetermined=cls.count("undetermined"),
            early=sum(bool(early.get((g, e))) for e in range(N) if fell[g, e] and classes.get((g, e)) == "necessary"),
            regret=int(np.sum(fell[g] & others)),
            regret_episodes=[int(e) for e in np.flatnonzero(fell[g] & others)],
            mean_angle_held_deg=float(angle[g, held].mean()) if held.any() else float("nan"))
    within = [auc(returns[~fell[:, e] & feasible[:, e], e], returns[fell[:, e] & feasible[:, e], e]) for e in range(N)]
    within = [a for a in within if np.isfinite(a)]
    ok = feasible.ravel()
    rho = spearman(returns.ravel()[ok], -angle.ravel()[ok]) if ok.sum() > 2 else float("nan")
    pool = dict(sequences=int(G * N), surrogate_feasible=int(ok.sum()),
                feasible_hold_share=float(np.mean(~fell.ravel()[ok])) if ok.any() else float("nan"),
                auc_pooled=auc(returns.ravel()[ok & ~fell.ravel()], returns.ravel()[ok & fell.ravel()]),
                auc_within_mean=float(np.mean(within)) if within else float("nan"), auc_within_episodes=len(within),
                spearman_pooled=float(rho))
    if hold is not None:
        sure = ok & (np.asarray(hold, float).ravel() >= PREDICTED_HOLD)
        pool.update(predicted_hold=int(sure.sum()),
                    predicted_hold_share=float(np.mean(~fell.ravel()[sure])) if sure.any() else float("nan"))
    return dict(kinds=rows, pool=pool)


# ------------------------------------------------------------------------------------ the oracle, in processes
_ORACLE = None


def _start_worker(model_path) -> None:
    """A process's oracle, of the model at `model_path` (the caller's: a spawned process starts with the default)."""
    global _ORACLE
    jax.config.update("jax_platforms", "cpu")
    from gsp_jax.model import load as model_lib
    from gsp_jax.physics.oracle import Oracle
    from gsp_jax.physics.scene import Scene
    from gsp_jax.surrogate.step import Surrogate

    sur = Surrogate(model_lib.load_model(model_path), learned=False)  # the oracle reads forces, not the term
    _ORACLE = Oracle(sur, Scene(sur.hand))


def _point_time(point: str, n_steps: int) -> int:
    """The waypoint from which an oracle point matters ("t3", "t3 change": 3; "hold": T)."""
    return n_steps if point == "hold" else int(point.split()[0][1:])


def _classify(job) -> tuple:
    """(class, worst point, its ratio, fell before the first impossible point, the reached configurations' worst
    point, its ratio) of one fall."""
    episode, grasps, rows, fall_row = job  # rows (T, nq): before each decision t >= 1 and at the hold's start
    episode = scenario.from_dict(episode)
    v = _ORACLE.sequence(episode, grasps)
    point, ratio = v.worst
    sim = _ORACLE.simulated(episode, grasps, rows, 1, fall_row)
    first = min((_point_time(p, episode.n_steps) for p, r in zip(v.points, v.ratio_outer) if r > 1.0), default=None)
    early = first is not None and fall_row < first
    kind = "necessary" if v.impossible else "controller" if v.possible else "undetermined"
    return (kind, point, ratio, early, *sim.worst)


def classify(episodes: list, jobs: list, processes: int, model=None) -> list:
    """The oracle's class of each (episode index, grasps, reached configurations (T, nq), rows before the fall) in
    `jobs`, in `processes` processes (`_classify`), for `model` (a `Model`, name or path; None: the default)."""
    from gsp_jax.model import load as model_lib

    if not jobs:
        return []
    work = [(scenario.to_dict(episodes[job[0]]), *job[1:]) for job in jobs]
    path = str(model_lib.load_model(model).path)
    if processes <= 1:
        _start_worker(path)
        return [_classify(w) for w in work]
    import multiprocessing

    with ProcessPoolExecutor(processes, multiprocessing.get_context("spawn"), initializer=_start_worker,
                             initargs=(path,)) as pool:
        return list(pool.map(_classify, work, chunksize=max(1, len(work) // (4 * processes))))
