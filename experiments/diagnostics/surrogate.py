"""`python -m experiments surrogate`: the surrogate's reward terms for a few meaningful grasps, so a reader can
see the model behave physically (more, opposing contacts resist the final torque; unreachable grasps show
large IK errors; a lone fingertip lets the tool fall)."""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import Run, table
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate

# The paper hand's grasps: (description, per-link options in its links' order)
PAPER_LINKS = ("thumb_distal", "index_distal", "index_medial", "middle_distal", "middle_medial", "ring_distal")
GRASPS = [
    ("index tip alone", (0, 1, 0, 0, 0, 0)),
    ("thumb + index tips", (1, 1, 0, 0, 0, 0)),
    ("three tips (start grasp)", (1, 1, 0, 1, 0, 0)),
    ("four tips", (1, 1, 0, 1, 0, 1)),
    ("head pinch + under + ring", (2, 2, 0, 3, 0, 1)),
    ("five-contact power wrap", (1, 0, 1, 3, 1, 1)),
]


def grasps_of(space) -> list[tuple[str, tuple[int, ...]]]:
    """The grasps shown for a grasp space: `GRASPS` where its links are the paper hand's; for any other model
    (any number of contact links), the same kinds built from its own: one tip alone, the start grasp, every tip,
    every link on its first option, every link on its last."""
    if tuple(space.link_names) == PAPER_LINKS:
        return GRASPS
    n, tips = space.n_options, space.tip_options
    first_tip = next(i for i, o in enumerate(tips) if o)
    one = tuple(int(i == first_tip) for i in range(len(n)))
    out = [(f"{space.link_names[first_tip]} alone", one), ("start grasp", tuple(space.start_options)),
           ("every tip", tuple(tips)), ("every link, first option", (1,) * len(n)),
           ("every link, last option", tuple(k - 1 for k in n))]
    seen, unique = set(), []
    for desc, options in out:  # a model's start grasp may be its tips: each grasp once
        if options not in seen:
            seen.add(options)
            unique.append((desc, options))
    return unique


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episode", default="nominal", help="episode name from any set (default: nominal)")
    p.add_argument("--waypoints", default="0,5,10,15", help="comma-separated waypoint indices")


def main(args: argparse.Namespace, run: Run) -> None:
    ep = scenario.find(args.episode, run.model)
    ts = [int(t) for t in args.waypoints.split(",")]
    bad = [t for t in ts if not 0 <= t < ep.n_steps]
    if bad:
        raise SystemExit(f"--waypoints: {bad[0]} is out of range 0..{ep.n_steps - 1}")
    env = surrogate.Surrogate(run.model, learned=run.learned)
    space = env.space
    shown = grasps_of(space)
    gs = jnp.asarray([int(space.encode(o)) for _, o in shown], jnp.int32)

    @jax.jit
    def terms(g, t):
        pos, quat = ep.waypoints[t], ep.quats[t]
        tn = jnp.minimum(t + 1, ep.n_steps - 1)
        now = env.realise(g, pos, quat)
        nxt = env.realise(g, ep.waypoints[tn], ep.quats[tn])
        return env.score(ep, t, pos, quat, now, nxt, jnp.array(False)), nxt.ik.penetration

    grid_g, grid_t = jnp.meshgrid(gs, jnp.asarray(ts, jnp.int32), indexing="ij")
    print(f"episode {args.episode}: tool z {float(ep.waypoints[0, 2]):.3f} -> {float(ep.waypoints[-1, 2]):.3f} m, "
          f"mass {float(ep.mass):.3f} kg, friction {float(ep.friction):.2f}, "
          f"final torque {float(ep.w_ext[5]):+.1f} N m")
    print("computing (one vmapped call over grasps x waypoints) ...", flush=True)
    res, pen = jax.vmap(jax.vmap(terms))(grid_g, grid_t)
    res, pen = jax.tree.map(np.asarray, (res, pen))
    rows = []
    for i, (desc, _) in enumerate(shown):
        for j, t in enumerate(ts):
            status = "collision" if res.collision[i, j] else "FALL" if res.fall[i, j] else "ok"
            rows.append([
                f"{desc} [{space.label(int(gs[i]))}]" if j == 0 else "", t,
                float(res.wrench_move[i, j]), float(res.ik_next[i, j]) * 10.0, float(res.wrench_hold[i, j]),
                float(res.wrench_ext[i, j]) if t == ep.n_steps - 1 else "-",
                f"{100 * res.unmet[i, j].max():.0f}%", status, float(res.reward[i, j]),
            ])
    print(table(["grasp", "t", "(a) move", "(b) IK mm", "(c) hold", "(d) ext", "unmet", "status", "reward"], rows))
    print("(a), (c), (d): wrench errors / (m0 g)^2; (b): IK error at the next waypoint in mm; (d) only at the last "
          f"waypoint; unmet: worst fraction of a required wrench the contacts cannot supply (> "
          f"{env.reward_config.fall_unmet:.0%} = fall).")
