"""How precise the surrogate's float32 rewards are: the spread that the tests' tolerances are taken from.

The surrogate's rewards come out of iterative solvers (60 Levenberg-Marquardt IK iterations with an accept/reject
test, 150 projected-gradient wrench iterations) run in float32. Two computations of the same reward along two
paths (vmapped vs looped, table vs step, another CPU's instruction set) differ in the last bits, and the solvers
amplify those differences. This measures by how much, on whole DP tables (G x A x T rewards per episode),
against the native float32 table of the unperturbed episode:

* `isa=...`: the same table with XLA's CPU code generation restricted to an older instruction set
  (`XLA_FLAGS=--xla_cpu_max_isa=...`, a subprocess each): what another x86 CPU computes,
* `ulp k`: the episode's inputs (waypoints, mass, CoM, friction) each moved by +-1 ulp at random (seed k):
  the spread a last-bit difference anywhere upstream causes,
* `float64`: the same solvers in float64 (`jax_enable_x64`): the float32 rounding error itself.

Reported per comparison: the largest and the 99.9th percentile |reward difference| over entries where neither
fails, the same for the DP value of every (grasp, waypoint 0) and for the IK error, and the fraction of entries
whose outcome (fail or not) flips. The tests' tolerances (`tests/conftest.py`) cite these figures.

    python -m experiments precision                      # nominal + one evaluation-B episode, 16 waypoints
    python -m experiments precision --isa AVX2 SSE4_2 --ulp 4
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

EPISODES = {"nominal": ("nominal", "nominal"), "evalB": ("evalB", "mass1.5m0_comy+2cm")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", nargs="+", default=list(EPISODES), choices=list(EPISODES))
    p.add_argument("--isa", nargs="*", default=["AVX2", "SSE4_2"], help="XLA CPU instruction sets to compare")
    p.add_argument("--ulp", type=int, default=3, help="number of random 1-ulp input perturbations")
    p.add_argument("--no-float64", action="store_true", help="skip the float64 comparison")
    p.add_argument("--worker", help=argparse.SUPPRESS)  # internal: write tables to this .npz and exit
    p.add_argument("--perturb", type=int, default=-1, help=argparse.SUPPRESS)  # internal: ulp seed (-1: none)


def _episode(name: str, x64: bool):
    import jax.numpy as jnp

    from gsp_jax import scenario

    set_name, key = EPISODES[name]
    ep = scenario.episode_set(set_name)[key]
    if x64:
        ep = ep.replace(**{f: jnp.asarray(getattr(ep, f), jnp.float64) for f in ("waypoints", "quats", "dt", "w_ext", "mass", "inertia", "com", "friction")})
    return ep


def _perturbed(ep, seed: int):
    """Every float input of the episode that the surrogate reads moved by +-1 ulp (random signs from `seed`)."""
    import jax.numpy as jnp

    rng = np.random.default_rng(seed)

    def nudge(x):
        x = np.asarray(x)
        toward = np.where(rng.random(x.shape) < 0.5, -np.inf, np.inf).astype(x.dtype)  # x's dtype: its ulp
        return jnp.asarray(np.nextafter(x, toward))

    return ep.replace(waypoints=nudge(ep.waypoints), mass=nudge(ep.mass), com=nudge(ep.com), friction=nudge(ep.friction))


def _terms(env, ep, g, t):
    import jax.numpy as jnp
    tn = jnp.minimum(t + 1, ep.n_steps - 1)
    now = env.realise(g, ep.waypoints[t], ep.quats[t])
    nxt = env.realise(g, ep.waypoints[tn], ep.quats[tn])
    return env.score(ep, t, ep.waypoints[t], ep.quats[t], now, nxt, jnp.array(False))


def _worker(args) -> None:
    """Build the tables (and DP values) of the chosen episodes in this process and save them."""
    import jax
    import jax.numpy as jnp

    x64 = bool(jax.config.jax_enable_x64)
    from gsp_jax import dp
    from gsp_jax.surrogate import Surrogate

    env = Surrogate()
    out = {}
    solve = jax.jit(lambda e: dp.solve(env, e))
    for name in args.episodes:
        ep = _episode(name, x64)
        if args.perturb >= 0:
            ep = _perturbed(ep, args.perturb)
        table, sol = jax.block_until_ready(solve(ep))
        out[f"{name}/reward"] = np.asarray(table.reward, np.float64)
        out[f"{name}/terminal"] = np.asarray(table.terminal)
        out[f"{name}/ik_error"] = np.asarray(table.ik_error, np.float64)
        out[f"{name}/value"] = np.asarray(sol.value[:, 0], np.float64)
        terms = jax.jit(jax.vmap(jax.vmap(lambda g, t: _terms(env, ep, g, t), (None, 0)), (0, None)))(
            jnp.arange(env.space.n_grasps), jnp.arange(ep.n_steps))
        for k in ("wrench_move", "ik_next", "wrench_hold", "wrench_ext", "unmet", "reward"):
            out[f"{name}/{k}"] = np.asarray(getattr(terms, k), np.float64)
    np.savez(args.worker, **out)


def _run(tmp: str, label: str, episodes, isa: str | None = None, perturb: int = -1, x64: bool = False) -> dict:
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    if isa:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_cpu_max_isa={isa}".strip()
    if x64:
        env["JAX_ENABLE_X64"] = "1"
    path = os.path.join(tmp, f"{label.split()[0].replace('=', '_')}{perturb if perturb >= 0 else ''}.npz")
    cmd = [sys.executable, "-m", "experiments", "precision", "--worker", path, "--perturb", str(perturb), "--episodes", *episodes]
    print(f"  {label} ...", flush=True)
    subprocess.run(cmd, env=env, check=True)
    with np.load(path) as d:
        return {k: d[k] for k in d.files}


def _compare(ref: dict, other: dict, episodes, r_min: float) -> dict:
    dr, dv, dik, flips, n = [], [], [], 0, 0
    for name in episodes:
        a, b = ref[f"{name}/reward"], other[f"{name}/reward"]
        fail_a, fail_b = a <= r_min, b <= r_min
        both = ~fail_a & ~fail_b
        dr.append(np.abs(a - b)[both])
        flips += int(np.sum(fail_a != fail_b))
        n += a.size
        va, vb = ref[f"{name}/value"], other[f"{name}/value"]
        ok = (va > r_min) & (vb > r_min)
        dv.append(np.abs(va - vb)[ok])
        dik.append(np.abs(ref[f"{name}/ik_error"] - other[f"{name}/ik_error"]).ravel())
    dr, dv, dik = (np.concatenate(x) for x in (dr, dv, dik))
    return dict(
        reward_max=float(dr.max()),
        reward_p999=float(np.quantile(dr, 0.999)),
        reward_median=float(np.median(dr)),
        value_max=float(dv.max()),
        ik_max_mm=float(dik.max() * 1e3),
        ik_p999_mm=float(np.quantile(dik, 0.999) * 1e3),
        flip_fraction=flips / n,
    )


def main(args) -> None:
    if args.worker:
        return _worker(args)
    from experiments.common import results_dir, table
    from gsp_jax.surrogate import RewardConfig

    r_min = RewardConfig().r_min
    print(f"precision of the surrogate's rewards: DP tables of {', '.join(args.episodes)}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = str(results_dir("precision", "raw"))
        ref = _run(tmp, "native float32 (reference)", args.episodes)
        runs = {}
        for isa in args.isa:
            runs[f"isa={isa}"] = _run(tmp, f"isa={isa}", args.episodes, isa=isa)
        for k in range(args.ulp):
            runs[f"ulp {k}"] = _run(tmp, f"inputs +-1 ulp (seed {k})", args.episodes, perturb=k)
        if not args.no_float64:
            runs["float64"] = _run(tmp, "float64", args.episodes, x64=True)
    rows, result = [], {}
    for label, other in runs.items():
        c = _compare(ref, other, args.episodes, r_min)
        result[label] = c
        rows.append([label, f"{c['reward_max']:.2e}", f"{c['reward_p999']:.2e}", f"{c['reward_median']:.1e}",
                     f"{c['value_max']:.2e}", f"{c['ik_max_mm']:.2e}", f"{c['flip_fraction']:.1e}"])
    path = results_dir("precision") / "precision.json"
    path.write_text(json.dumps(dict(episodes=args.episodes, vs_native_float32=result), indent=1))
    n = sum(ref[f"{e}/reward"].size for e in args.episodes)
    print(f"\n{n} rewards compared with the native float32 table (|difference| where neither fails); {path}\n")
    print(table(["vs native float32", "reward max", "reward p99.9", "median", "DP value max", "IK err max [mm]",
                 "fail flips"], rows))
