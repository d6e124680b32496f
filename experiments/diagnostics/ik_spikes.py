"""`python -m experiments ik-spikes [--set eval] [--starts "0,-.3,-.3,0;0,-.3,0,0" ...]`: the IK's local minima,
measured. For every (grasp, waypoint) of every episode of a set, the IK error of the grasp, side by side: from the
model's start alone (`extra_starts=()`), with the library's `IKConfig()`, and once per `--starts` candidate (the
library's config with `IKConfig.extra_starts` replaced: per-finger joint offsets, one start per `;`; an empty
string is the start alone; by default the first candidate tried, docs/model.md). A *spike* is a collision-free IK
whose error exceeds 2 mm while both neighbouring waypoints of the same grasp are below 1 mm: a solution exists
nearby, so the solver stopped in a local minimum. Prints a small table last; writes
results/ik/<set>_spikes.json."""
from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import Run, table
from gsp_jax.core import files
from gsp_jax.solvers import ik
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate

SPIKE, NEIGHBOUR = 2e-3, 1e-3  # [m]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", choices=["nominal", "train", "val", "evalA", "evalB", "eval", "all"])
    p.add_argument("--starts", nargs="*", default=["0,-0.3,-0.3,0;0,-0.3,0,0"],
                   help="candidate extra starts, each replacing IKConfig().extra_starts: per-finger joint offsets, "
                        "starts separated by ';' ('' = the model's start alone)")


def _parse(spec: str) -> tuple:
    try:
        return tuple(tuple(float(v) for v in start.split(",")) for start in spec.split(";") if start.strip())
    except ValueError:
        raise SystemExit(f"--starts: expected comma-separated numbers, starts separated by ';', got {spec!r}")


def ik_table(env: surrogate.Surrogate, episodes: scenario.Episode):
    """IK error [m] and collision flag of every (episode, grasp, waypoint): (E, G, T) each."""
    grasps = jnp.arange(env.space.n_grasps)
    one = lambda g, p, q: env.realise(g, p, q).ik  # noqa: E731
    per_episode = jax.vmap(jax.vmap(one, (None, 0, 0)), (0, None, None))
    res = jax.jit(jax.vmap(per_episode, (None, 0, 0)))(grasps, episodes.waypoints, episodes.quats)
    return np.asarray(res.error), np.asarray(res.collision)


def spikes(err: np.ndarray, col: np.ndarray) -> np.ndarray:
    """(E, G, T-2) bool: interior waypoints where the IK spiked (see the module docstring)."""
    mid = err[..., 1:-1]
    return (mid > SPIKE) & (err[..., :-2] < NEIGHBOUR) & (err[..., 2:] < NEIGHBOUR) & ~col[..., 1:-1]


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("ik",)]


def main(args: argparse.Namespace, run: Run) -> None:
    episodes = scenario.episode_set(args.set, run.model)
    batch = scenario.stack(list(episodes.values()))
    default = ik.IKConfig()
    variants = {"start alone": dataclasses.replace(default, extra_starts=()), "IKConfig()": default}
    for spec in args.starts:
        variants[f"starts {spec}"] = dataclasses.replace(default, extra_starts=_parse(spec))
    rows, out = [], {}
    for name, cfg in variants.items():
        env = surrogate.Surrogate(run.model, ik_config=cfg, learned=run.learned)
        t0 = time.perf_counter()
        err, col = ik_table(env, batch)
        wall = time.perf_counter() - t0
        s = spikes(err, col)
        o = out[name] = dict(starts=1 + len(cfg.extra_starts), spikes=int(s.sum()),
                             spikes_per_episode=[int(x) for x in s.sum((1, 2))],
                             below_1mm_collision_free=int(np.sum((err < NEIGHBOUR) & ~col)),
                             collisions=int(col.sum()), median_error_mm=1e3 * float(np.median(err)), wall_s=wall)
        rows.append([name, o["starts"], o["spikes"], o["below_1mm_collision_free"], o["collisions"],
                     o["median_error_mm"], err.size, wall])
        print(f"{name}: {o['spikes']} spikes over {len(episodes)} episodes", flush=True)
    path = run.results_dir("ik") / f"{args.set}_spikes.json"
    files.write_json(path, dict(set=args.set, episodes=list(episodes), device=jax.local_devices()[0].device_kind,
                                    variants=out))
    print(f"wrote {path}\n")
    print(table(["IK", "starts", "spikes", "< 1 mm, collision-free", "collisions", "median error [mm]", "problems",
                 "first call [s]"], rows, ".2f"))
