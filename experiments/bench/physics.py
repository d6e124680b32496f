"""`python -m experiments bench-physics`: the cost of the physics check against the engine's own speed, measured
side by side in one run, on one policy's batch of episodes (default the 27 evaluation episodes, four tips):

  engine alone   `mujoco.mj_step` on the same scene and the same states, one core: every state the runner stepped
                 (recorded from a one-core run) is loaded into an `MjData` and stepped once; only `mj_step` is
                 timed. This is the engine's limit: steps / s of one core.
  runner         `Physics.simulate_batch(..., backend="c")`: controller, decisions and physics, on 1, 2 and all
                 cores; the first call (a fresh `Physics`: compile included) and a warm one.

The runner's share of the engine's limit is its steps / s over (engine steps / s x cores). `--backends mjx c`
adds the MJX runner (one XLA batch); `--variant NAME:key=value,...` adds `PhysicsConfig` variants (their falls
show whether a cheaper setting changes the outcome), `--variant paper` or `--variant predictive` a named contact
controller beside the run's (the predictive hold's ratio counts its extra rollouts as cost: its steps are the plain
run's); `--waypoints 4` shortens the episodes for a quick run.
Writes JSON (`engine_steps_per_s_one_core`, and per row `runner_steps_per_s`, `cores`); prints a table last.
"""
from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import Run, table, timed
from gsp_jax.planning import evaluation, policies
from gsp_jax.core import files
from gsp_jax import physics
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate
from gsp_jax.physics import c_backend


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval")
    p.add_argument("--waypoints", type=int, default=scenario.N_WAYPOINTS, help="episode length (shorter: quicker)")
    p.add_argument("--variant", action="append", default=[],
                   help="NAME:key=value,... a PhysicsConfig variant (keys: field names of any group), or a named "
                        "contact controller alone (paper, predictive)")
    p.add_argument("--backends", nargs="+", default=["c"], choices=physics.BACKENDS)
    p.add_argument("--cores", nargs="+", type=int, default=None,
                   help="core counts for the C runner (default: 1, 2 and all)")
    p.add_argument("--workers", nargs="+", type=int, default=[0],
                   help="C runner chunks side by side (0: the default, one a core with >= 4 episodes each)")
    p.add_argument("--copies", type=int, default=1, help="the set repeated this many times (5: Fig. 4b's 135)")
    p.add_argument("--out", default=None)


def _variants(specs, base: physics.PhysicsConfig, named) -> list[tuple[str, physics.PhysicsConfig]]:
    """("default", base) then one (name, config) per `--variant`: a named contact controller alone (`paper`,
    `predictive`: `named(name)`, the run's tuning kept) or NAME:key=value,... over `base`."""
    out = [("default", base)]
    for spec in specs:
        name, _, body = spec.partition(":")
        if not body and name in physics.config.CONTROLLERS:
            out.append((name, named(name)))
            continue
        kw = {}
        for item in filter(None, body.split(",")):
            key, _, value = item.partition("=")
            if key not in physics.config.GROUP_OF:
                raise ValueError(f"--variant {spec!r}: PhysicsConfig has no field {key!r}")
            kw[key] = type(base.value(key))(value)
        out.append((name, base.replace(**kw)))
    return out


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.out else [("bench",)]


def main(args: argparse.Namespace, run: Run) -> None:
    env = surrogate.Surrogate(run.model, learned=run.learned)
    device = jax.local_devices()[0]
    if args.copies < 1:
        raise SystemExit(f"bench-physics: --copies must be >= 1, got {args.copies}")
    eps = [e.head(args.waypoints) for e in scenario.episode_set(args.set, env.model).values()] * args.copies
    batch = scenario.stack(eps)
    policy = policies.SequencePolicy(jnp.asarray(evaluation.four_tips(env.space, args.waypoints)))
    all_cores = c_backend.available_cores()
    core_counts = args.cores or sorted({1, min(2, all_cores), all_cores})
    for c in core_counts:
        if c < 1:
            raise SystemExit(f"bench-physics: --cores must be >= 1, got {c}")
    print(f"device: {device.platform} ({device.device_kind}); {all_cores} CPU cores; {len(eps)} episodes of "
          f"'{args.set}', four tips", flush=True)
    rows, engine = [], {}
    named = lambda name: dataclasses.replace(run, controller=name).physics_config()  # noqa: E731  (tuning kept)
    for name, config in _variants(args.variant, run.physics_config(), named):
        # the engine alone on the states of a one-core run (recorded once per variant)
        log = []
        phys = physics.Physics(env, config)
        c_backend.simulate(phys, [(policy, None)], batch, cores=1, workers=1, engine_log=log)
        engine[name], steps = c_backend.engine_alone(phys, batch, log)
        print(f"{name}: engine alone {engine[name]:,.0f} steps/s on one core ({steps:,} steps)", flush=True)
        for backend in args.backends:
            runs = [(c, w) for c in core_counts for w in args.workers] if backend == "c" else [(None, 0)]
            for cores, workers in runs:
                phys = physics.Physics(env, config)  # fresh: the first call compiles
                go = lambda: phys.simulate_many([(policy, None)], batch, backend=backend,  # noqa: E731
                                                **({} if cores is None
                                                   else dict(cores=cores, workers=workers or None)))[0]
                res, first = timed(go)
                _, warm = timed(go)
                rate = steps / warm
                share = rate / (engine[name] * cores) if cores else float("nan")
                rows.append([name, backend, cores or "-", workers or "auto", len(eps), first, warm, rate,
                             share, warm / (steps / engine[name]), int(np.sum(res.fell))])
                print(f"{name} {backend} cores {cores} workers {workers or 'auto'}: first call {first:.2f} s, warm "
                      f"{warm:.2f} s ({rate:,.0f} steps/s), {rows[-1][-1]} fell", flush=True)
    head = ["variant", "backend", "cores", "workers", "episodes", "first call [s]", "warm [s]", "runner steps/s",
            "share of engine limit", "warm / engine one core", "fell"]
    keys = ["variant", "backend", "cores", "workers", "episodes", "first_call_s", "warm_s", "runner_steps_per_s",
            "share_of_engine_limit", "warm_over_engine_one_core", "fell"]
    out = dict(device=f"{device.platform} ({device.device_kind})", cpu_cores=all_cores, waypoints=args.waypoints,
               steps=steps, engine_steps_per_s_one_core=engine["default"],
               engine_steps_per_s_one_core_by_variant=engine, engine_one_core_s=steps / engine["default"],
               rows=[dict(zip(keys, r)) for r in rows])
    path = args.out or run.results_dir("bench") / f"physics_{device.platform}.json"
    files.write_json(path, out)
    print(f"wrote {path}\n")
    print(f"engine alone (mj_step, one core, the same states): {engine['default']:,.0f} steps/s, "
          f"{steps / engine['default']:.2f} s for the batch's {steps:,} steps")
    run.record_figures("bench_physics", dict(head=head, rows=rows))
    print(table(head, rows, ".2f"))
