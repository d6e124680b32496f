"""`python -m experiments bench-scale [--processes 1 2 4] [--cores-each C]`: how the sweeps scale with processes.

For each count N of `--processes`, one run of N processes on this host (`experiments.processes.launch`), each
pinned to `--cores-each` cores of its own and, where there are GPUs, to one GPU (round robin: with fewer GPUs than
processes they share): the work of N hosts of one GPU and C cores each. Every run does the same three things:

1. a physics sweep: `--episodes` tools and tasks drawn from the corpus distribution (wider than the stress set) x
   two sequences (the four tips, one tip) in C MuJoCo, in fixed chunks of `--chunk` episodes shared between the
   processes: episodes/s;
2. DP tables of `--tables` such episodes (`evaluation.dp_tables`), in whole batches of `--batch` shared between
   the processes: tables/s;
3. PPO (table backend), the data-parallel trainer over every process's device, `--envs` environments per
   process: environment steps/s of `--iterations` iterations (not where processes share a GPU: NCCL takes one
   process per GPU).

Each process compiles (runs its share once) before the clocks start; a figure is the time from a barrier to the
next, so the slowest process's. Prints, per N, the three rates, the speed-up and the efficiency (speed-up / N)
against one process, and whether the physics outcomes and the tables equal one process's, bit for bit.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pathlib
import time

from experiments.common import Run, table

PHYSICS_KINDS = ("four-tips", "one-tip")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--processes", dest="counts", type=int, nargs="+", default=None, metavar="N",
                   help="process counts to run (default: 1, 2, 4, ... up to the cores or GPUs)")
    p.add_argument("--cores-each", type=int, default=None, metavar="C",
                   help="cores per process (default: this host's cores / the largest count)")
    p.add_argument("--episodes", type=int, default=64, help="physics sweep: drawn episodes (x 2 sequences)")
    p.add_argument("--chunk", type=int, default=8, help="physics sweep: episodes per lockstep")
    p.add_argument("--tables", type=int, default=16, help="DP tables built")
    p.add_argument("--batch", type=int, default=4, help="DP tables per batch")
    p.add_argument("--envs", type=int, default=256, help="PPO environments per process")
    p.add_argument("--iterations", type=int, default=4, help="PPO iterations timed")
    p.add_argument("--steps", type=int, default=None, help="the episodes' first waypoints only (a quick run)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # a process of one run: its result file


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.worker else [("bench-scale",)]


# ------------------------------------------------------------------------------------------- one process's run
def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _clocked(name: str, fn) -> float:
    """Seconds from a barrier before `fn()` to a barrier after it: the slowest process's time."""
    from gsp_jax.core import distributed

    distributed.barrier(f"{name}-start")
    t0 = time.perf_counter()
    fn()
    distributed.barrier(f"{name}-end")
    return time.perf_counter() - t0


def worker(args: argparse.Namespace, run: Run) -> None:
    """One process of a run: the three workloads, each warmed then clocked; process 0 writes the result."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from gsp_jax.core import distributed
    from gsp_jax.planning import evaluation, policies
    from gsp_jax import physics
    from gsp_jax.model import scenario
    from gsp_jax.surrogate import step as surrogate
    from gsp_jax.physics import corpus

    phys = physics.Physics(surrogate.Surrogate(run.model, learned=run.learned), run.physics_config())
    sur = phys.surrogate
    P = distributed.count()
    cut = (lambda eps: {k: e.head(args.steps) for k, e in eps.items()}) if args.steps else (lambda eps: eps)

    # 1. physics sweep: this process's chunks, each both sequences in one lockstep
    batch = scenario.stack(list(cut(corpus.draw(corpus.Distribution(), args.seed, args.episodes, sur.model)).values()))
    T = batch.n_steps
    seqs = {"four-tips": evaluation.four_tips(sur.space, T), "one-tip": evaluation.one_tip(sur.space, T)}
    groups = [(policies.SequencePolicy(jnp.asarray(seqs[k]), sur.space), None) for k in PHYSICS_KINDS]
    pieces = distributed.chunks(args.episodes, args.chunk)
    mine = [pieces[c] for c in distributed.share(len(pieces))]
    pick = lambda idx: jax.tree.map(lambda x: x[idx], batch)  # noqa: E731
    out: dict[int, np.ndarray] = {}

    def sweep():
        for idx in mine:
            res = phys.simulate_many(groups, pick(idx), backend="c")
            out[int(idx[0])] = np.stack([np.asarray(r.fell) for r in res])  # (kinds, chunk)

    if mine:
        phys.simulate_many(groups, pick(mine[0]), backend="c")  # compile the controller and the decisions
    physics_s = _clocked("physics", sweep)
    every = distributed.gather_merged(out)
    fell = np.concatenate([every[k] for k in sorted(every)], axis=1)

    # 2. DP tables of a set (`evaluation.dp_tables`: each process its whole batches, gathered): once to compile,
    # then clocked
    eps = cut(corpus.draw(corpus.Distribution(), args.seed + 1, args.tables, sur.model))
    dp_batch = scenario.stack(list(eps.values()))
    evaluation.dp_tables(sur, "bench-scale", eps, batch_size=args.batch, cache=None)
    made = {}
    tables_s = _clocked("tables", lambda: made.update(
        tables=evaluation.dp_tables(sur, "bench-scale", eps, batch_size=args.batch, cache=None)))
    all_tables = made["tables"]

    # 3. PPO on those tables, the environments split over every process's device (not where processes share a
    # GPU: NCCL takes one process per GPU)
    gpus = distributed.gather(os.environ.get("CUDA_VISIBLE_DEVICES"))
    if jax.default_backend() == "gpu" and len(set(gpus)) < P:
        ppo_s, steps, envs = float("nan"), 0, 0
    else:
        ppo_s, steps, envs = _ppo(args, sur, dp_batch, all_tables, T)
    if not distributed.is_main():
        return
    device = jax.local_devices()[0]
    result = dict(processes=P, cores_each=len(os.sched_getaffinity(0)),
                  device=f"{device.device_kind} ({device.platform})",
                  physics_s=physics_s, physics_episodes=int(fell.size), physics_falls=int(fell.sum()),
                  physics_digest=_digest(fell), tables_s=tables_s, tables=args.tables,
                  tables_digest=_digest(np.asarray(all_tables.reward), np.asarray(all_tables.ik_error)),
                  ppo_s=ppo_s, ppo_env_steps=steps, ppo_envs=envs)
    pathlib.Path(args.worker).write_text(json.dumps(result))


def _ppo(args, sur, episodes, tables, T: int) -> tuple[float, int, int]:
    """(seconds, environment steps, environments) of `--iterations` PPO iterations after a first (compiling) one,
    the environments split over every process's device."""
    import jax

    from gsp_jax.core import distributed
    from gsp_jax.learning.env import GraspEnv
    from gsp_jax.ppo import networks as nets
    from gsp_jax.ppo import train as ppo

    env = GraspEnv(sur, episodes, tables)
    eval_env = GraspEnv(sur, episodes, tables, auto_reset=False)
    networks = nets.make_networks(env.observation_size, env.action_size, nets.NetworkConfig(hidden=(256, 256, 256)))
    cfg = ppo.PPOConfig(n_envs=args.envs * distributed.count(), unroll=T, minibatches=8,
                        max_iterations=args.iterations + 1)
    trainer = ppo.Trainer(env, networks, cfg, {"val": eval_env})
    state = {"ts": jax.block_until_ready(trainer.iteration(trainer.init(jax.random.PRNGKey(args.seed)))[0])}

    def iterations():
        for _ in range(args.iterations):
            state["ts"] = trainer.iteration(state["ts"])[0]
        jax.block_until_ready(state["ts"])

    return _clocked("ppo", iterations), args.iterations * cfg.n_envs * cfg.unroll, cfg.n_envs


# ------------------------------------------------------------------------------------------------ the runs
def counts_of(args: argparse.Namespace) -> list[int]:
    """The process counts: `--processes`, else 1, 2, 4, ... up to the cores (or GPUs where there are any)."""
    from experiments import processes

    if args.counts:
        if min(args.counts) < 1:
            raise SystemExit(f"bench-scale: --processes must be >= 1, got {args.counts}")
        return sorted(set(args.counts))
    most = len(processes.gpus()) or len(os.sched_getaffinity(0))
    return [n for n in (1, 2, 4, 8, 16) if n <= max(most, 1)]


def main(args: argparse.Namespace, run: Run) -> None:
    if args.worker:
        return worker(args, run)
    from experiments import processes

    counts = counts_of(args)
    cores = sorted(os.sched_getaffinity(0))
    each = args.cores_each or max(1, len(cores) // max(counts))
    if each * max(counts) > len(cores):
        raise SystemExit(f"bench-scale: --cores-each {each} x {max(counts)} processes needs {each * max(counts)} "
                         f"cores; this process may use {len(cores)}")
    for name in ("episodes", "chunk", "tables", "batch", "envs", "iterations"):
        if getattr(args, name) < 1:
            raise SystemExit(f"bench-scale: --{name} must be >= 1, got {getattr(args, name)}")
    out = run.results_dir("bench-scale")
    print(f"bench-scale: {counts} processes, {each} cores each; physics {args.episodes} episodes x "
          f"{len(PHYSICS_KINDS)} sequences, {args.tables} DP tables, PPO {args.envs} envs per process", flush=True)
    words = ["bench-scale", *(f"--{k}={getattr(args, k)}" for k in ("episodes", "chunk", "tables", "batch", "envs",
                                                                    "iterations", "seed")),
             *([f"--steps={args.steps}"] if args.steps else []), f"--model={run.model.path}"]
    runs = {}
    for n in counts:
        path = out / f"processes{n}.json"
        t0 = time.perf_counter()
        processes.launch(n, [*words, f"--worker={path.absolute()}"], cores=cores[:n * each])
        runs[n] = json.loads(path.read_text())
        print(f"  {n} process{'es' * (n > 1)}: done in {time.perf_counter() - t0:.0f} s", flush=True)
    one = runs[counts[0]]
    counted = dict(physics="physics_episodes", tables="tables", ppo="ppo_env_steps")
    rate = lambda r, k: r[counted[k]] / r[f"{k}_s"] if r[counted[k]] else float("nan")  # noqa: E731
    rows, figures = [], {}
    for n, r in runs.items():
        row = [n]
        for k in ("physics", "tables", "ppo"):
            speed = rate(r, k) / rate(one, k) * counts[0]
            row += [rate(r, k), speed, speed / n]
        same = r["physics_digest"] == one["physics_digest"] and r["tables_digest"] == one["tables_digest"]
        rows.append(row + ["yes" if same else "NO"])
        figures[str(n)] = dict(physics_episodes_per_s=rate(r, "physics"), tables_per_s=rate(r, "tables"),
                               ppo_env_steps_per_s=rate(r, "ppo"), outcomes_equal=same)
    run.record_figures("bench_scale", dict(cores_each=each, device=one["device"], episodes=args.episodes,
                                      tables=args.tables, envs_per_process=args.envs, runs=figures))
    print(f"\n{one['device']}, {each} cores per process")
    print(table(["processes", "physics ep/s", "x", "eff.", "DP tables/s", "x", "eff.", "PPO steps/s", "x", "eff.",
                 "outcomes = 1 process"], rows, ".2f"))
