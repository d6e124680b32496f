"""How precise the surrogate's float32 rewards are: the spread that the tests' tolerances (tests/tolerances.py)
are taken from.

The rewards come out of iterative solvers (60 Levenberg-Marquardt IK iterations with an accept/reject test, 10
semismooth Newton wrench iterations) run in float32. Two computations of the same reward along two paths
(vmapped vs looped, table vs step, another CPU's instruction set) differ in the last bits, and the solvers
amplify those differences. This measures by how much, over the reward terms of every (grasp, waypoint) of an
episode (what the DP table is built from), against the native float32 computation of the unperturbed episode:

* `isa=...`: XLA's CPU code generation restricted to an older instruction set (`XLA_FLAGS=--xla_cpu_max_isa=...`,
  a subprocess each): what another x86 CPU computes,
* `inputs +-1 ulp`: the episode's inputs (waypoints, mass, CoM, friction) each moved by 1 ulp, random signs:
  the spread that a last-bit difference anywhere upstream causes,
* `float64`: the same solvers in float64 (`jax_enable_x64`).

Reported: |reward difference| (median, 99th percentile, share above 1e-3, largest) where neither computation
fails, the wrench terms' and the IK error's 99th percentiles, the largest DP value difference at waypoint 0, and
how many entries flip between failing and not. Raw runs are kept in results/precision/raw/ (`--reuse`).

    python -m experiments precision                      # nominal + one evaluation-B episode, 16 waypoints
    python -m experiments precision --isa AVX2 SSE4_2 --ulp 4
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from typing import TYPE_CHECKING

import numpy as np
from gsp_jax.core import files

if TYPE_CHECKING:
    from experiments.common import Run

EPISODES = {"nominal": ("nominal", "nominal"), "evalB": ("evalB", "mass1.5m0_comy+2cm")}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", nargs="+", default=list(EPISODES), choices=list(EPISODES))
    p.add_argument("--isa", nargs="*", default=["AVX2", "SSE4_2"], help="XLA CPU instruction sets to compare")
    p.add_argument("--ulp", type=int, default=3, help="number of random 1-ulp input perturbations")
    p.add_argument("--no-float64", action="store_true", help="skip the float64 comparison")
    p.add_argument("--reuse", action="store_true", help="compare the runs saved in results/precision/raw/ again")
    p.add_argument("--worker", help=argparse.SUPPRESS)  # internal: write tables to this .npz and exit
    p.add_argument("--perturb", type=int, default=-1, help=argparse.SUPPRESS)  # internal: ulp seed (-1: none)


def _episode(name: str, x64: bool):
    import jax.numpy as jnp

    from gsp_jax.model import scenario

    set_name, key = EPISODES[name]
    ep = scenario.episode_set(set_name)[key]
    if x64:
        ep = ep.replace(**{f: jnp.asarray(getattr(ep, f), jnp.float64)
                           for f in ("waypoints", "quats", "dt", "w_ext", "mass", "inertia", "com", "friction")})
    return ep


def _perturbed(ep, seed: int):
    """Every float input of the episode that the surrogate reads moved by +-1 ulp (random signs from `seed`)."""
    import jax.numpy as jnp

    rng = np.random.default_rng(seed)

    def nudge(x):
        x = np.asarray(x)
        toward = np.where(rng.random(x.shape) < 0.5, -np.inf, np.inf).astype(x.dtype)  # x's dtype: its ulp
        return jnp.asarray(np.nextafter(x, toward))

    return ep.replace(waypoints=nudge(ep.waypoints), mass=nudge(ep.mass), com=nudge(ep.com),
                      friction=nudge(ep.friction))


def _terms(env, ep, g, t):
    import jax.numpy as jnp
    tn = jnp.minimum(t + 1, ep.n_steps - 1)
    now = env.realise(g, ep.waypoints[t], ep.quats[t])
    nxt = env.realise(g, ep.waypoints[tn], ep.quats[tn])
    return env.score(ep, t, ep.waypoints[t], ep.quats[t], now, nxt, jnp.array(False))


def _worker(args) -> None:
    """The reward terms of every (grasp, waypoint) of the chosen episodes (as the DP table computes them, without
    the redundant flag) and their DP values, computed in this process; saved to args.worker."""
    import jax
    import jax.numpy as jnp

    from gsp_jax.planning import dp
    from gsp_jax.surrogate.step import Surrogate

    env = Surrogate()
    x64 = bool(jax.config.jax_enable_x64)

    @jax.jit
    def terms_and_values(ep):
        table, sol = dp.solve(env, ep)
        per = jax.vmap(jax.vmap(lambda g, t: _terms(env, ep, g, t), (None, 0)), (0, None))
        return per(jnp.arange(env.space.n_grasps), jnp.arange(ep.n_steps)), table.ik_error, sol.value[:, 0]

    out = {}
    for name in args.episodes:
        ep = _episode(name, x64)
        if args.perturb >= 0:
            ep = _perturbed(ep, args.perturb)
        terms, ik_error, value = jax.block_until_ready(terms_and_values(ep))
        out[f"{name}/ik_error"] = np.asarray(ik_error, np.float64)
        out[f"{name}/value"] = np.asarray(value, np.float64)
        out[f"{name}/failed"] = np.asarray(terms.collision | terms.fall)
        for k in ("wrench_move", "ik_next", "wrench_hold", "unmet", "reward"):
            out[f"{name}/{k}"] = np.asarray(getattr(terms, k), np.float64)
    np.savez(args.worker, **out)


def _run(path, label: str, episodes, isa: str | None = None, perturb: int = -1, x64: bool = False) -> None:
    """One worker process, with XLA's instruction set restricted (isa), inputs perturbed, or float64."""
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    if isa:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_cpu_max_isa={isa}".strip()
    if x64:
        env["JAX_ENABLE_X64"] = "1"
    cmd = [sys.executable, "-m", "experiments", "precision", "--worker", str(path), "--perturb", str(perturb),
           "--episodes", *episodes]
    print(f"  {label} ...", flush=True)
    subprocess.run(cmd, env=env, check=True)


def _compare(ref: dict, other: dict, episodes) -> dict:
    """Differences over every (grasp, waypoint) of the episodes: rewards and terms where neither fails."""
    cat = lambda key, mask=None: np.concatenate(  # noqa: E731
        [np.abs(ref[f"{e}/{key}"] - other[f"{e}/{key}"])[mask(e) if mask else ...].ravel() for e in episodes]
    )
    live = lambda e: ~ref[f"{e}/failed"] & ~other[f"{e}/failed"]  # noqa: E731
    dr, wrench = cat("reward", live), np.concatenate([cat("wrench_move", live), cat("wrench_hold", live),
                                                      cat("unmet", live)])
    value = cat("value", lambda e: (ref[f"{e}/value"] > -200) & (other[f"{e}/value"] > -200))
    flips = sum(int(np.sum(ref[f"{e}/failed"] != other[f"{e}/failed"])) for e in episodes)
    return dict(
        n=int(dr.size),
        reward_median=float(np.median(dr)),
        reward_p99=float(np.quantile(dr, 0.99)),
        reward_max=float(dr.max()),
        reward_above_1e3=float(np.mean(dr > 1e-3)),
        wrench_p99=float(np.quantile(wrench, 0.99)),
        wrench_max=float(wrench.max()),
        ik_p99_um=float(np.quantile(cat("ik_error"), 0.99) * 1e6),
        ik_max_um=float(cat("ik_error").max() * 1e6),
        value_max=float(value.max()),
        flips=flips,
        entries=int(sum(ref[f"{e}/failed"].size for e in episodes)),
    )


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.worker else [("precision",), ("precision", "raw")]  # a worker writes for its parent


def main(args: argparse.Namespace, run: Run) -> None:
    if args.worker:
        return _worker(args)
    from experiments.common import table

    raw = run.results_dir("precision", "raw")
    print(f"precision of the surrogate's float32 rewards: every (grasp, waypoint) of {', '.join(args.episodes)}",
          flush=True)
    runs = {"native": ("native float32 (reference)", {})}
    runs.update({f"isa_{isa}": (f"isa={isa}", dict(isa=isa)) for isa in args.isa})
    runs.update({f"ulp{k}": (f"inputs +-1 ulp (seed {k})", dict(perturb=k)) for k in range(args.ulp)})
    if not args.no_float64:
        runs["float64"] = ("float64", dict(x64=True))
    data = {}
    for key, (label, kw) in runs.items():
        path = raw / f"{key}.npz"
        if not (args.reuse and path.exists()):
            _run(path, label, args.episodes, **kw)
        with np.load(path) as d:
            data[key] = {k: d[k] for k in d.files}
    ref = data.pop("native")
    result = {runs[k][0]: _compare(ref, other, args.episodes) for k, other in data.items()}
    out = run.results_dir("precision") / "precision.json"
    files.write_json(out, dict(episodes=args.episodes, vs_native_float32=result))
    rows = [[label, f"{c['reward_median']:.1e}", f"{c['reward_p99']:.1e}", f"{100 * c['reward_above_1e3']:.2f}%",
             f"{c['reward_max']:.2e}", f"{c['wrench_p99']:.1e}", f"{c['ik_p99_um']:.2f}", f"{c['ik_max_um']:.0f}",
             f"{c['value_max']:.1e}", f"{c['flips']}/{c['entries']}"] for label, c in result.items()]
    print(f"\n|difference| from the native float32 computation, over (grasp, waypoint) entries where neither fails "
          f"({next(iter(result.values()))['n']} of them); {out}\n")
    print(table(["vs native float32", "reward median", "p99", "> 1e-3", "max", "wrench p99", "IK err p99 [um]",
                 "IK max [um]", "DP value max", "fail flips"], rows))
