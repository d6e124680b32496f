"""The predictive hold: a layer over the contact controller that looks ahead in C MuJoCo before the hold.

At the start of the hold (the segment after the last waypoint, before the external wrench ramps up) the controller
rolls the whole hold out from the state it has, once under its own settings and once under each of a few other
settings of its gains (`CANDIDATES`: the grip, the pose loop's stiffness, its damping bound, the friction it
allows, the radius its rotational gains act at, each relative to the run's own), and keeps, per episode, the one
that holds the tool with the smallest angle error; ties keep the earlier candidate, so its own settings win where
nothing does better. Its model is the simulator itself (as L1-physics's is): what it measures is how much holding a
controller could win by predicting, not how well it predicts a world unlike its model.

    phys = Physics(sur, PhysicsConfig.named("predictive"))     # or --controller predictive on any command
    phys.simulate_batch(policy, episodes, backend="c")         # C MuJoCo only; never worse than "measured"
    results, chosen = phys.simulate_predictive([(policy, None)], episodes)   # and which candidate each kept

Cost: C MuJoCo runs each episode up to the hold once, then the hold (its last `TimelineConfig.hold` seconds) once
per candidate, len(CANDIDATES) times.
"""
from __future__ import annotations

import jax
import numpy as np

from gsp_jax.physics import c_backend
from gsp_jax.physics import controller as controller_lib
from gsp_jax.physics.config import PhysicsConfig

# the candidates, each a set of fields scaled by a factor of the run's own value (the first: its own settings)
CANDIDATES: tuple[dict[str, float], ...] = (
    {},
    {"grip_force": 0.5}, {"grip_force": 1.5}, {"grip_force": 2.0},
    {"tool_freq": 1.5}, {"tool_freq": 2.0},
    {"rotation_step": 10 / 3},
    {"friction_margin": 0.85},
    {"tool_radius": 1.5},
)


def candidate_configs(config: PhysicsConfig, hand) -> list[PhysicsConfig]:
    """The settings the hold is rolled out under: `CANDIDATES` applied to `config` (its `predictive` off: the
    rollouts are the plain controller's), the rotational radius scaled from the model's (`rotation_radius`) where
    the config leaves it to the model, the damping bound at most 1."""
    base = config.replace(predictive=False)
    out = []
    for factors in CANDIDATES:
        changes = {}
        for name, factor in factors.items():
            value = controller_lib.rotation_radius(hand, base) if name == "tool_radius" else base.value(name)
            value = float(value) * factor
            changes[name] = min(value, 1.0) if name in ("rotation_step", "friction_margin") else value
        out.append(base.replace(**changes))
    return out


def choose(fell: np.ndarray, angle_error: np.ndarray) -> np.ndarray:
    """(R,) the index of the candidate each row keeps: held before fell, then the smallest angle error, then the
    first. `fell`, `angle_error`: (C, R)."""
    score = np.where(np.asarray(fell), np.inf, np.asarray(angle_error, np.float64))
    return np.argmin(score, axis=0)  # argmin keeps the first of equal scores


def simulate(spec, specs, policies, episodes, cores: int | None = None, progress: bool = False,
             workers: int | None = None, world=None) -> tuple[list, list[np.ndarray]]:
    """`Physics.simulate_many(..., backend="c")` with the predictive hold: every (policy, policy_axis) of
    `policies` runs the lift in one C MuJoCo lockstep under `spec` (the run's `PhysicsSpec`); from that snapshot
    the hold runs once under each of `specs` (the candidates', `candidate_configs`, the run's own first). Returns
    (results, chosen): per group a `runner.Result` of numpy arrays holding each row's chosen rollout (the whole
    episode), and the (R,) int32 candidate each row chose. With a `world` (`gsp_jax.physics.world`) the episodes run
    in it and the candidates are chosen by rollouts in the nominal model (the controller's), then the chosen ones
    run in the world."""
    groups = list(policies)
    snap = c_backend.simulate(spec, groups, episodes, cores=cores, progress=progress, workers=workers,
                              until=episodes.n_steps, world=world)  # the hold's first segment, before its decision
    # the rollouts are the controller's predictions: in its model (the nominal world), from the state it has
    runs = [c_backend.simulate(s, groups, episodes, cores=cores, workers=workers, start=snap) for s in specs]
    chosen = [choose(np.stack([np.asarray(run[g].fell) for run in runs]),
                     np.stack([np.asarray(run[g].angle_error) for run in runs])).astype(np.int32)
              for g in range(len(groups))]
    if world is not None:  # what happens is the world's: each candidate some row chose, run in it
        used = sorted({int(c) for best in chosen for c in best})
        in_world = {c: c_backend.simulate(specs[c], groups, episodes, cores=cores, workers=workers, start=snap,
                                          world=world) for c in used}
        runs = [in_world.get(c) or runs[c] for c in range(len(specs))]  # the others are never picked
    results = []
    for g, best in enumerate(chosen):
        per = [run[g] for run in runs]
        rows = np.arange(len(best))
        results.append(jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs])[best, rows], *per))
    return results, chosen
