"""`python -m experiments train-curves`: the paper's Fig. 3 from the runs of `python -m experiments train`
(results/train/{dp,none}/seed*/history.json): deterministic validation return (dark) and stochastic training
return (light) against PPO iterations, with and without DP pretraining, mean over seeds with a min-max band;
and the iterations each needs to reach the same validation return. Writes results/train/curves.png and
curves.json."""
from __future__ import annotations

import argparse

import numpy as np

from experiments.common import Run, table
from gsp_jax.core import files as files_lib

MODES = {"dp": "with DP pretraining", "none": "without pretraining"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="train", help="folder under results/ written by `train`")


def load_runs(root) -> dict[str, list[list[dict]]]:
    runs = {}
    for mode in MODES:
        files = sorted((root / mode).glob("seed*/history.json"))
        if files:
            runs[mode] = [files_lib.read_json(f) for f in files]
    return runs


def curves(histories: list[list[dict]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """Iterations (K,) and values (S, K) of `key` per seed, on the union of the seeds' iterations at which it
    was recorded; a seed that stopped early keeps its last value."""
    its = sorted({r["iteration"] for h in histories for r in h if key in r})
    values = []
    for h in histories:
        rec = {r["iteration"]: r[key] for r in h if key in r}
        row, last = [], np.nan
        for it in its:
            last = rec.get(it, last)
            row.append(last)
        values.append(row)
    return np.asarray(its), np.asarray(values, float)


def iterations_to(its: np.ndarray, mean: np.ndarray, target: float) -> int | None:
    hit = np.nonzero(mean >= target)[0]
    return int(its[hit[0]]) if hit.size else None


def summarise(runs: dict, best_so_far: bool = False) -> dict:
    """The common target (the best seed-mean validation return that every mode reaches) and the iterations each
    mode needs to reach it, from the seed-mean curves and per seed. With `best_so_far`, each seed's curve is the
    validation return of its best policy so far -- the policy early stopping deploys -- so a transient peak
    counts only if it is kept."""
    val = {}
    for m, h in runs.items():
        its, v = curves(h, "val_return")
        val[m] = (its, np.maximum.accumulate(v, axis=1) if best_so_far else v)
    target = min(np.max(np.nanmean(v, 0)) for _, v in val.values())
    out = {"target_val_return": float(target), "modes": {}}
    for m, (its, v) in val.items():
        out["modes"][m] = {
            "seeds": int(v.shape[0]),
            "iterations_to_target": iterations_to(its, np.nanmean(v, 0), target),
            "iterations_to_target_per_seed": [iterations_to(its, v[s], target) for s in range(v.shape[0])],
            "val_return_at_0": float(np.nanmean(v[:, 0])),
            "best_val_return": float(np.max(np.nanmean(v, 0))),
            "final_val_return": float(np.nanmean(v[:, -1])),
            "iterations_run": [int(h[-1]["iteration"]) for h in runs[m]],
        }
    dp_it, none_it = (out["modes"].get(m, {}).get("iterations_to_target") for m in ("dp", "none"))
    if dp_it is not None and none_it is not None:
        out["pretraining_speedup"] = float("inf") if dp_it == 0 else none_it / dp_it
    return out


def plot(runs: dict, reference: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"dp": "tab:blue", "none": "tab:orange"}
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for m, hist in runs.items():
        for key, alpha, style in (("train_return", 0.35, "-"), ("val_return", 1.0, "-")):
            its, v = curves(hist, key)
            mean = np.nanmean(v, 0)
            label = f"{MODES[m]}: {'validation (deterministic)' if key == 'val_return' else 'training (stochastic)'}"
            ax.plot(its, mean, style, color=colors[m], alpha=alpha, lw=2 if key == "val_return" else 1, label=label)
            ax.fill_between(its, np.nanmin(v, 0), np.nanmax(v, 0), color=colors[m], alpha=0.12 * alpha, lw=0)
        its, v = curves(hist, "val_return")
        best = np.nanmean(np.maximum.accumulate(v, axis=1), 0)
        ax.plot(its, best, "--", color=colors[m], lw=1, label=f"{MODES[m]}: best validated policy so far")
    if reference:
        ax.axhline(reference["val"]["dp_optimal"], color="k", ls=":", lw=1, label="DP optimal (validation)")
        ax.axhline(reference["val"]["dp_baseline"], color="0.4", ls="--", lw=1, label="DP baseline (validation)")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.set_ylim(top=-0.5)
    ax.set_xlabel("PPO iteration")
    ax.set_ylabel("mean return (symlog)")
    n_seeds = max(len(h) for h in runs.values())
    ax.set_title(f"PPO with and without DP pretraining ({n_seeds} seeds, mean and min-max)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [(args.out,)]


def main(args: argparse.Namespace, run: Run) -> None:
    root = run.results_dir(args.out)
    runs = load_runs(root)
    if not runs:
        raise SystemExit(f"train-curves: no runs under {root}/{{dp,none}}/seed*/history.json; "
                         "run `python -m experiments train` first")
    ref_file = root / "reference.json"
    reference = files_lib.read_json(ref_file) if ref_file.exists() else {}
    summary = {"raw": summarise(runs), "best_so_far": summarise(runs, best_so_far=True), "reference": reference}
    files_lib.write_json(root / "curves.json", summary)
    plot(runs, reference, root / "curves.png")
    if reference:
        print(f"validation set: DP optimal {reference['val']['dp_optimal']:.3f}, "
              f"DP baseline {reference['val']['dp_baseline']:.3f}")
    print(f"wrote {root / 'curves.png'} and {root / 'curves.json'}")
    for kind, title in (("raw", "validation return of the current policy"),
                        ("best_so_far", "validation return of the best policy so far (what early stopping deploys)")):
        s = summary[kind]
        print(f"\n{title}: target {s['target_val_return']:.3f} (the best seed-mean every mode reaches)")
        if "pretraining_speedup" in s:
            print(f"iterations to the target: {s['modes']['none']['iterations_to_target']} without pretraining, "
                  f"{s['modes']['dp']['iterations_to_target']} with: "
                  f"speed-up {s['pretraining_speedup']:.1f}x (paper: 4x)")
        rows = [
            [MODES[m], r["seeds"], r["val_return_at_0"], r["best_val_return"], r["final_val_return"],
             str(r["iterations_to_target"]), str(r["iterations_to_target_per_seed"])]
            for m, r in s["modes"].items()
        ]
        print(table(["", "seeds", "at 0", "best mean", "final mean", "iterations to target", "per seed"], rows))
