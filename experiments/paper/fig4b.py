"""`python -m experiments fig4b [--set eval] [--episodes N] [--policies ...]`: the paper's Fig. 4b.

The policies of Fig. 4a (or any registered planner, `--plugin` for yours) run closed loop in the physics check
(`gsp_jax.physics`; C MuJoCo by default, `--backend mjx` for MJX): at every waypoint each acts
on the simulated state (L1 and L2 search the surrogate from it), the contact controller executes the grasp, and
after the last waypoint the episode's torque is applied; the score is the mean tool angle error under it, 180 deg
when the tool fell or touched the table. All episodes of a policy run in one batch. Each policy's result is saved
as soon as it is done (results/fig4b/<policy>.json) and reused when the command runs again with the same episodes,
policy parameters and library sources (`--fresh` to redo), so an interrupted run loses only the policies in flight.
In C MuJoCo every policy's episodes run in one lockstep (5 x 27 = 135 episodes, one controller call per tick, the
physics on every core: `Physics.simulate_many`); `--chunk N` runs the episodes in fixed chunks of N instead, one
lockstep each, and several processes (`--processes`) share the chunks (default: one chunk per process); the outcomes
depend on the chunks, never on the process count. In MJX one batch per policy (`--jobs` side by side). Writes
fig4b.png; prints the table last.
"""
from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np

from experiments import common
from experiments.common import Run, table
from gsp_jax.physics import world as world_lib
from gsp_jax.physics.report import result_rows
from gsp_jax.core import distributed, files, stats
from gsp_jax.planning import evaluation
from gsp_jax import physics
from gsp_jax.planners import registry as planners


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval", choices=["evalA", "evalB", "eval", "val", "variations", "stress"],
                   help="the episodes (variations: the model's nominal lift and 8 one-at-a-time variations; stress: "
                   "120 drawn tools and tasks)")
    p.add_argument("--episodes", type=int, default=None, help="only N episodes, spread over the set")
    p.add_argument("--policies", nargs="+", default=list(planners.names("paper")), metavar="NAME",
                   help="the paper's five by default; L1-physics (C MuJoCo only) branches L1's candidates in physics")
    p.add_argument("--policy-dir", default=None)
    p.add_argument("--fresh", action="store_true", help="ignore saved per-policy results")
    p.add_argument("--backend", default="c", choices=physics.BACKENDS,
                   help="c (C MuJoCo, every published figure's; the default) or mjx (one XLA batch)")
    p.add_argument("--jobs", type=int, default=None,
                   help="MJX: policies run side by side (threads; default 1). C MuJoCo runs them all in one lockstep")
    p.add_argument("--warm", action="store_true", help="C MuJoCo: time the lockstep a second time (warm)")
    p.add_argument("--chunk", type=int, default=None, metavar="N",
                   help="C MuJoCo: episodes per lockstep (default: all of them, split evenly over --processes); "
                        "the outcomes depend on the chunks, not on the process count")
    p.add_argument("--k", type=int, default=evaluation.L1_PHYSICS["k"],
                   help="L1-physics: the surrogate's best k root actions are branched in physics at each decision")
    common.add_bases_argument(p)
    common.add_lookahead_argument(p)


def evaluate(ctx: evaluation.Context, names, out, fresh: bool = False, backend: str = "c", cached: bool = True,
        jobs: int | None = None, warm: bool = False, k: int = evaluation.L1_PHYSICS["k"],
        bases=evaluation.L1_PHYSICS["bases"], chunk: int | None = None, config=None, worlds=None,
        world_name: str = "nominal") -> dict:
    """Fig. 4b's result per policy (saved results reused); `jobs` policies at a time (default as `--jobs`); in C
    MuJoCo the episodes in chunks of `chunk` (`lockstep`; default: one chunk per process). With several processes
    only process 0 saves and returns the results (the others return {}). `config`: the `PhysicsConfig` (default:
    `PhysicsConfig()`, the default controller). `worlds`: the episodes' worlds (`gsp_jax.physics.world.World`,
    ctx's episodes' leading axis; None: the nominal world), drawn at the level `world_name`."""
    phys = physics.Physics(ctx.surrogate, config or physics.PhysicsConfig())
    n_episodes = len(ctx.names)
    chunk = distributed.chunk_size(n_episodes, chunk)
    stamp = f"{common.fingerprint(ctx)}-{backend}" + ("" if cached else "-continuous") + (
        f"-k{k}-" + "+".join(bases) if any("bases" in planners.get(n).options for n in names) else "") + (
        f"-chunk{chunk}" if backend == "c" and chunk < n_episodes else "") + (
        "" if worlds is None else f"-world-{world_lib.digest(worlds)}")
    jobs = 1 if jobs is None else jobs
    if jobs < 1:
        raise ValueError(f"jobs (--jobs) must be >= 1, got {jobs}")
    results, todo = {}, []
    for name in names:
        path = out / f"{name}.json"
        saved = (files.reuse_json(path, lambda r: isinstance(r, dict)) or {}) if not fresh else {}  # a truncated
        # file (a crash while writing it, before writes were atomic) is named in a warning and recomputed
        if saved.get("fingerprint") == stamp:
            results[name] = saved
            print(f"  {name:8s} (saved) mean angle error {saved['mean_deg']:.1f} deg", flush=True)
        else:
            todo.append(name)

    def save(name, res, wall):
        mean, ci = stats.mean_ci(res.angle_error)
        rows = result_rows(ctx.names, res)
        result = dict(policy=name, episodes=ctx.names, rl_policy=ctx.rl_source, mean_deg=mean, ci95_deg=ci,
                      falls=int(np.sum(res.fell)), held=[r for r in rows if not r["fell"]], per_episode=rows,
                      wall_s_incl_compile=wall, jobs=jobs, platform=jax.default_backend(), backend=backend,
                      fingerprint=stamp, world=world_name,
                      **(dict(k=k, bases=list(bases)) if "bases" in planners.get(name).options else {}),
                      **({} if worlds is None else dict(worlds=world_lib.as_rows(worlds))))
        files.write_json(out / f"{name}.json", result)
        print(f"  {name:8s} mean angle error {mean:.1f} deg (+-{ci:.1f}), {result['falls']}/{len(ctx.names)} "
              f"fell ({wall:.1f} s incl. compile)", flush=True)
        return result

    def simulate(name):
        policy, axis = planners.make(ctx, name, dict(cached=cached, k=k, bases=bases))
        t0 = time.perf_counter()
        res = jax.block_until_ready(phys.simulate_batch(policy, ctx.batch, axis, backend=backend, world=worlds))
        return save(name, res, time.perf_counter() - t0)

    t0 = time.perf_counter()
    if backend == "c" and todo:  # every policy's episodes of a chunk in one lockstep on every core
        options = dict(cached=cached, k=k, bases=bases)
        res = lockstep(ctx, phys, todo, options, chunk, worlds=worlds)
        if not distributed.is_main():
            return {}  # process 0 saves, draws and records
        wall = time.perf_counter() - t0
        done = {name: save(name, r, wall) for name, r in zip(todo, res)}
        if warm:  # the same lockstep again in this process: compiled, the policies' tables built
            t1 = time.perf_counter()
            again = lockstep(ctx, phys, todo, options, chunk, shared=False, worlds=worlds)
            warm_s = time.perf_counter() - t1
            same = all(np.array_equal(a.fell, b.fell) for a, b in zip(res, again))
            print(f"  warm: the {len(todo)} policies x {len(ctx.names)} episodes again in {warm_s:.2f} s "
                  f"(falls {'the same' if same else 'DIFFERENT'})", flush=True)
            for name in todo:
                done[name]["lockstep_warm_s"] = warm_s
                files.write_json(out / f"{name}.json", done[name])
    else:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            done = dict(zip(todo, pool.map(simulate, todo)))
    if todo:
        lockstep_s = -(-n_episodes // chunk)
        how = (f"{lockstep_s} lockstep{'s' * (lockstep_s > 1)}" if backend == "c" else f"{jobs} at a time")
        print(f"  {len(todo)} policies in {time.perf_counter() - t0:.1f} s ({how}, compile included)", flush=True)
    results = {name: results.get(name) or done[name] for name in names}
    common.fig4b_png(results, len(ctx.names), out / "fig4b.png")
    return results


def lockstep(ctx: evaluation.Context, phys: physics.Physics, names, options: dict, chunk: int,
             shared: bool = True, worlds=None) -> list:
    """Each policy's `Result` (numpy, stacked over all of ctx's episodes) in C MuJoCo: the episodes in fixed chunks
    of `chunk`, each chunk every policy in one lockstep (`Physics.simulate_many`). With several processes
    (`shared`) each runs its share of the chunks and every process gets every result (`distributed.gather`): the
    chunks fix the programs and their inputs, so the results are one process's, bit for bit. `worlds`: as
    `evaluate`'s."""
    def one(idx):
        sub = ctx.select(idx)
        return phys.simulate_many([planners.make(sub, name, options) for name in names], sub.batch, backend="c",
                                  progress=True, world=world_lib.rows(worlds, idx))

    return distributed.map_chunks(one, len(ctx.names), chunk, shared, what="episodes")


def print_result(results: dict) -> None:
    rows = [[n, r["mean_deg"], r["ci95_deg"], f"{r['falls']}/{len(r['episodes'])}"] for n, r in results.items()]
    print(table(["policy", "angle error [deg]", "95% CI +-", "fell"], rows, ".1f"))


def figures(results: dict) -> dict:
    """Fig. 4b's figures for docs/data: per policy, falls and the tool angle error (mean, 95% CI) in physics."""
    return {name: dict(episodes=len(r["episodes"]), falls=r["falls"], mean_deg=r["mean_deg"], ci95_deg=r["ci95_deg"],
                       backend=r.get("backend")) for name, r in results.items()}


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("fig4b",)]


def main(args: argparse.Namespace, run: Run) -> None:
    common.check_planners(args.policies, "--policies", args.backend)
    common.check_planners(args.bases, "--bases")
    if args.backend != "c" and distributed.count() > 1:
        raise SystemExit(f"fig4b: --backend {args.backend} runs as one process (an XLA batch per policy); "
                         f"only C MuJoCo's chunks are shared by --processes")
    ctx = evaluation.context(args.set, args.episodes, args.policy_dir, model=run.model, results=common.RESULTS,
                             learned=run.learned,
                             # only what the policies read
                             **planners.context_flags([*args.policies,
                                                       *(args.bases if 'L1-physics' in args.policies else ())]))
    print(f"Fig. 4b: {len(ctx.names)} episodes of '{args.set}' in {args.backend} (JAX on {jax.default_backend()}), "
          f"RL policy {ctx.rl_source}", flush=True)
    out = run.results_dir("fig4b")
    results = evaluate(ctx, args.policies, out, args.fresh, args.backend, cached=args.lookahead == "cached",
                       jobs=args.jobs, warm=args.warm, k=args.k, bases=args.bases, chunk=args.chunk,
                       config=run.physics_config(), worlds=run.worlds(ctx.batch, ctx.surrogate.hand),
                       world_name=run.world_name)
    if not distributed.is_main():
        return
    print(f"wrote {out}/<policy>.json, {out / 'fig4b.png'}")
    run.record_figures("fig4b", figures(results))
    print_result(results)
