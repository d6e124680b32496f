"""`python -m experiments train --pretrain dp|none --seeds N`: PPO on the 9 training episodes (the environment
cycles them), validated on the validation set with the deterministic policy, early-stopped there; with
`--pretrain dp` the networks start from behaviour cloning of the training episodes' DP solutions.

Writes, per run, results/train/<pretrain>/seed<k>/: history.json (per iteration: stochastic training return,
deterministic validation and training-set returns, losses, env steps, wall time), policy/ (the best validated
policy, orbax), checkpoints/ (the run resumes from there when started again); and results/train/reference.json
(the DP returns to compare with). Steps are exact table lookups of the surrogate (see gsp_jax/learning/env.py). On a
host with several GPUs the environments are split over all of them (`gsp_jax.ppo.train`: data-parallel).
"""
from __future__ import annotations

import argparse

import jax
import numpy as np

from experiments.common import RESULTS, Run, table
from gsp_jax.core import distributed, files
from gsp_jax.planning import evaluation
from gsp_jax.learning.pipeline import PRESETS, run_seed, setup
from gsp_jax.surrogate.step import Surrogate

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pretrain", default="dp", choices=["dp", "none"])
    p.add_argument("--seeds", type=int, default=3, help="number of seeds (first-seed, first-seed + 1, ...)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--preset", choices=sorted(PRESETS), default=None, help="default: full on a GPU, else quick")
    p.add_argument("--iterations", type=int, default=None, help="PPO iterations (overrides the preset)")
    p.add_argument("--envs", type=int, default=None, help="parallel environments (overrides the preset)")
    p.add_argument("--patience", type=int, default=None, help="validations without improvement before stopping")
    p.add_argument("--out", default="train", help="folder under results/ (<folder>-<model> for another --model)")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [(args.out,)]


def main(args: argparse.Namespace, run: Run) -> None:
    if distributed.count() > 1:
        raise SystemExit("train: runs as one process (one writer of its checkpoints and policies); one process "
                         "already splits the environments over every GPU of its host (docs/scale.md)")
    preset = args.preset or ("full" if jax.default_backend() == "gpu" else "quick")
    s = setup(preset, args.iterations, args.envs, args.patience, table_cache=RESULTS / evaluation.TABLES,
              surrogate=Surrogate(run.model, learned=run.learned))
    root = run.results_dir(args.out)  # results/train-<model> for another model: where evaluation.load_rl looks
    files.write_json(root / "reference.json", {**s.reference, "preset": preset})
    print(
        f"preset {preset}: {s.ppo_config.n_envs} envs x {s.ppo_config.unroll} steps per iteration, "
        f"networks {tuple(s.networks.config.hidden)}, up to {s.ppo_config.max_iterations} iterations"
    )
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        result = run_seed(s, seed, args.pretrain, root / args.pretrain / f"seed{seed}")
        h = result.history
        vals = [r["val_return"] for r in h if "val_return" in r]
        rows.append(
            [seed, h[-1]["iteration"], vals[0], float(result.state.best_return), h[-1].get("train_return", np.nan),
             h[-1]["wall_s"]]
        )
    ref = s.reference
    print(
        f"\nDP references (mean return): validation set optimal {ref['val']['dp_optimal']:.3f}, baseline "
        f"{ref['val']['dp_baseline']:.3f}; training set optimal {ref['train']['dp_optimal']:.3f}, baseline "
        f"{ref['train']['dp_baseline']:.3f}"
    )
    print(f"\nPPO, pretrain={args.pretrain} (policies in {root / args.pretrain}/seed*/policy)")
    print(table(["seed", "iterations", "val return at 0", "best val return", "last train return (stoch.)", "wall s"],
                rows))
