"""`python -m experiments corpus [--model M] [--shards 40] [--episodes 64]`: a physics corpus of the model.

Each shard draws `--episodes` tools and tasks from `gsp_jax.physics.corpus.Distribution` (wider than the stress set;
no episode of a named set), builds their DP tables, and runs in C MuJoCo the four tips, DP optimal, `--random`
random surrogate-feasible sequences and `--perturbed` perturbations of those, keeping every transition's surrogate
features with what physics did (`gsp_jax.physics.corpus`). Shards go to results/corpus[-<model>]/ (`--folder`), each
written whole and then listed in its manifest: a killed run loses at most the shard it was making, and the same
command adds only the shards missing. With `--learned` the tables, and so the planners' sequences, are the learned
term's (features stay analytic). With `--world gap` each episode runs in a world drawn from the gap (from the shard's
seed; hidden from the planners and the features): a term fitted on it prices what the planner does not know
(results/corpus-gap/; docs/world.md). Prints the corpus's counts as a table last.
"""
from __future__ import annotations

import argparse
import pathlib
import time

from experiments.common import Run, table
from gsp_jax import physics
from gsp_jax.surrogate import step as surrogate
from gsp_jax.physics import corpus


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shards", type=int, default=40, help="shards to hold (seeds --first .. --first + shards - 1)")
    p.add_argument("--first", type=int, default=0, help="the first shard's seed")
    p.add_argument("--episodes", type=int, default=64, help="episodes drawn per shard")
    p.add_argument("--random", type=int, default=4, help="random surrogate-feasible sequences per episode")
    p.add_argument("--perturbed", type=int, default=2, help="perturbed sequences per episode")
    p.add_argument("--steps", type=int, default=None, help="the episodes' first waypoints only (a quick corpus)")
    p.add_argument("--folder", default=None, help="the corpus folder (default: results/corpus[-<model>])")
    p.add_argument("--cores", type=int, default=None, help="C MuJoCo processes (default: every core)")


def folder_of(args: argparse.Namespace, run: Run) -> pathlib.Path:
    return pathlib.Path(args.folder) if args.folder else run.results_dir("corpus")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.folder else [("corpus",)]


def check(args: argparse.Namespace) -> None:
    for name in ("shards", "episodes"):
        if getattr(args, name) < 1:
            raise SystemExit(f"corpus: --{name} must be >= 1, got {getattr(args, name)}")
    for name in ("random", "perturbed", "first"):
        if getattr(args, name) < 0:
            raise SystemExit(f"corpus: --{name} must be >= 0, got {getattr(args, name)}")
    if args.steps is not None and args.steps < 2:
        raise SystemExit(f"corpus: --steps must be >= 2, got {args.steps}")



def build(args: argparse.Namespace, run: Run) -> corpus.Store:
    """The corpus of `args` (of `run`'s model) extended to its shards; returns its store."""
    check(args)
    if run.world_seed:
        raise SystemExit(f"corpus: --world-seed {run.world_seed}: a corpus's worlds are drawn from each shard's seed "
                         "(--first picks the seeds)")
    phys = physics.Physics(surrogate.Surrogate(run.model, learned=run.learned), run.physics_config())
    folder = folder_of(args, run)
    try:
        store = corpus.Store.open(folder, phys.surrogate.model)
        corpus.check_physics(store, phys.config, run.gap)  # the runs it holds were this controller's, in this world
    except corpus.CorpusError as e:
        raise SystemExit(f"corpus: {e}") from None
    seeds = range(args.first, args.first + args.shards)
    todo = [s for s in seeds if s not in store.seeds]
    print(f"corpus: {folder}: {len(store.seeds)} shards held, {len(todo)} to run ({args.episodes} episodes each, "
          f"{2 + args.random + args.perturbed} sequences an episode)", flush=True)
    t0 = time.perf_counter()
    corpus.extend(store, phys, todo, args.episodes, args.random, args.perturbed, args.cores, progress=True,
                  n_steps=args.steps, gap=run.gap)
    if todo:
        print(f"corpus: {len(todo)} shards in {time.perf_counter() - t0:.0f} s", flush=True)
    return store


def summary(store: corpus.Store) -> list[list]:
    shards = store.manifest["shards"]
    runs = sum(s["runs"] for s in shards)
    falls = sum(s["falls"] for s in shards)
    return [["shards", len(shards)], ["episodes", sum(s["episodes"] for s in shards)], ["runs", runs],
            ["transitions", sum(s["transitions"] for s in shards)], ["falls", falls],
            ["fall share", f"{falls / max(runs, 1):.2f}"]]


def main(args: argparse.Namespace, run: Run) -> None:
    store = build(args, run)
    print(table(["corpus", str(store.folder)], summary(store)))
