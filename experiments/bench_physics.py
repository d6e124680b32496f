"""`python -m experiments bench-physics`: simulated episodes per second of the MJX physics check, one batch of
`--batch` episodes against the same episodes run one at a time (the same jitted single-episode function called in
a Python loop), measured side by side in one run. The default is the full episode (16 waypoints + 1 s hold);
`--waypoints 4` shortens it for a quick run on a CPU."""
from __future__ import annotations

import argparse
import json

import jax

from experiments.common import results_dir, table, timed
from experiments.common import nominal_actions
from gsp_jax import physics, policies, scenario, surrogate


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=int, default=256, help="episodes in the batched run")
    p.add_argument("--loop", type=int, default=4, help="episodes run one at a time")
    p.add_argument("--waypoints", type=int, default=scenario.N_WAYPOINTS, help="episode length (shorter: quicker)")
    p.add_argument("--out", default=None)


def main(args: argparse.Namespace) -> None:
    env = surrogate.Surrogate()
    phys = physics.Physics(env)
    device = jax.devices()[0]
    evals = list(scenario.episode_set("eval").values())
    eps = [evals[i % len(evals)].head(args.waypoints) for i in range(max(args.batch, args.loop))]
    policy = policies.SequencePolicy(nominal_actions(env)[: args.waypoints])
    steps = phys.n_ticks(args.waypoints) * phys.config.control_every  # MJX steps per episode
    print(f"device: {device.platform} ({device.device_kind}); {steps} MJX steps per episode "
          f"({phys.model.npair} contact pairs)", flush=True)

    single = jax.jit(phys.simulate)
    _, c_single = timed(single, policy, eps[0])
    _, t_single = timed(lambda: [single(policy, e) for e in eps[: args.loop]])
    per_single = t_single / args.loop
    print(f"one at a time: compile+first {c_single:.1f} s, warm {per_single:.2f} s per episode", flush=True)

    batch = scenario.stack(eps[: args.batch])
    _, c_batch = timed(phys.simulate_batch, policy, batch)
    _, t_batch = timed(phys.simulate_batch, policy, batch)
    print(f"batch of {args.batch}: compile+first {c_batch:.1f} s, warm {t_batch:.2f} s", flush=True)

    rows = [
        ["one at a time", 1, c_single, per_single, 1 / per_single, steps / per_single, 1.0],
        ["one batch", args.batch, c_batch, t_batch, args.batch / t_batch, steps * args.batch / t_batch,
         per_single * args.batch / t_batch],
    ]
    out = dict(device=f"{device.platform} ({device.device_kind})", waypoints=args.waypoints, mjx_steps=steps,
               rows=[dict(zip(["mode", "batch", "compile_s", "warm_s", "episodes_per_s", "mjx_steps_per_s",
                               "speedup"], r)) for r in rows])
    path = args.out or results_dir("bench") / f"physics_{device.platform}.json"
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {path}\n")
    print(table(["mode", "batch", "compile [s]", "warm [s]", "episodes/s", "MJX steps/s", "speed-up"], rows, ".2f"))
