"""`python -m experiments bench-physics`: the cost of the physics check, one policy's batch of episodes (default
the 27 evaluation episodes with the four-tip grasp), stepped by MJX (one XLA batch) and by C MuJoCo (lockstep, one
JAX controller call per tick for the whole batch), measured side by side in one run: the first call (compile
included, what a user waits for) and a second, warm call; with the falls of each, so a faster setting that
changes the outcome shows. `--variant NAME:key=value,...` adds `PhysicsConfig` variants (e.g.
`ctrl2:control_every=2`); `--waypoints 4` shortens the episodes for a quick run on a CPU."""
from __future__ import annotations

import argparse
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import results_dir, table, timed
from gsp_jax import physics, policies, scenario, surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval")
    p.add_argument("--waypoints", type=int, default=scenario.N_WAYPOINTS, help="episode length (shorter: quicker)")
    p.add_argument("--variant", action="append", default=[], help="NAME:key=value,... a PhysicsConfig variant")
    p.add_argument("--backends", nargs="+", default=list(physics.BACKENDS), choices=physics.BACKENDS)
    p.add_argument("--out", default=None)


def _variants(specs) -> list[tuple[str, physics.PhysicsConfig]]:
    out = [("default", physics.PhysicsConfig())]
    for spec in specs:
        name, _, body = spec.partition(":")
        kw = {}
        for item in filter(None, body.split(",")):
            key, _, value = item.partition("=")
            field = {f.name: f for f in dataclasses.fields(physics.PhysicsConfig)}.get(key)
            if field is None:
                raise ValueError(f"--variant {spec!r}: PhysicsConfig has no field {key!r}")
            kw[key] = type(getattr(physics.PhysicsConfig(), key))(value)
        out.append((name, physics.PhysicsConfig(**kw)))
    return out


def main(args: argparse.Namespace) -> None:
    env = surrogate.Surrogate()
    device = jax.devices()[0]
    eps = [e.head(args.waypoints) for e in scenario.episode_set(args.set).values()]
    batch = scenario.stack(eps)
    ring = env.space.action("ring_distal", 1)
    policy = policies.SequencePolicy(jnp.full(args.waypoints, ring, jnp.int32))
    print(f"device: {device.platform} ({device.device_kind}); {len(eps)} episodes of '{args.set}', four tips", flush=True)
    rows = []
    for name, config in _variants(args.variant):
        phys = physics.Physics(env, config)
        steps = phys.n_ticks(args.waypoints) * config.control_every
        for backend in args.backends:
            run = lambda: jax.block_until_ready(phys.simulate_batch(policy, batch, backend=backend))  # noqa: E731
            res, first = timed(run)
            _, warm = timed(run)
            rows.append([name, backend, len(eps), first, warm, len(eps) / warm, steps * len(eps) / warm,
                         int(np.sum(res.fell))])
            print(f"{name} {backend}: first call {first:.1f} s, warm {warm:.1f} s, {rows[-1][-1]} fell", flush=True)
    head = ["variant", "backend", "episodes", "first call [s]", "warm [s]", "episodes/s", "steps/s", "fell"]
    out = dict(device=f"{device.platform} ({device.device_kind})", waypoints=args.waypoints,
               rows=[dict(zip(head, r)) for r in rows])
    path = args.out or results_dir("bench") / f"physics_{device.platform}.json"
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {path}\n")
    print(table(head, rows, ".2f"))
