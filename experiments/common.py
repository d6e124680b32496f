"""Small helpers shared by the experiments: the results folder, plain-text tables, timing, and cached DP tables."""
from __future__ import annotations

import dataclasses
import hashlib
import pathlib
import time

import jax
import numpy as np

from gsp_jax import dp, hand, scenario

RESULTS = pathlib.Path("results")


def results_dir(*parts: str) -> pathlib.Path:
    path = RESULTS.joinpath(*parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


def table(headers: list[str], rows: list[list], floatfmt: str = ".3f") -> str:
    """A fixed-width text table (right-aligned numbers)."""
    cells = [[f"{c:{floatfmt}}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    line = lambda r: "  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths)))  # noqa: E731
    return "\n".join([line(headers), "  ".join("-" * w for w in widths), *map(line, cells)])


def timed(fn, *args):
    """(output, seconds) of one call, waiting for the device to finish."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def best_time(fn, *args, repeats: int = 3) -> float:
    """Fastest of `repeats` warm calls (call once before to compile)."""
    return min(timed(fn, *args)[1] for _ in range(max(1, repeats)))


def dp_tables(env, set_name: str, episodes: dict, batch_size: int = 4):
    """The stacked `dp.Table`s of named episodes, cached under results/tables/ (keyed by the episodes, the model
    and the surrogate's configuration, so a change to any of them rebuilds). Builds `batch_size` at a time."""
    batch = scenario.stack(list(episodes.values()))
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(batch):
        h.update(np.asarray(leaf).tobytes())
    for path in sorted(pathlib.Path(hand.SCENE_XML).parent.glob("*.xml")):
        h.update(path.read_bytes())
    for cfg in (env.reward_config, env.ik_config, env.wrench_config):
        h.update(repr(dataclasses.asdict(cfg)).encode())
    path = results_dir("tables") / f"{set_name}_{h.hexdigest()[:12]}.npz"
    if path.exists():
        with np.load(path) as d:
            return dp.Table(**{k: jax.numpy.asarray(d[k]) for k in d.files})
    print(f"building DP tables for {len(episodes)} episodes of '{set_name}' (cached in {path}) ...", flush=True)
    t0 = time.perf_counter()
    tables = jax.block_until_ready(jax.jit(lambda b: dp.build_tables(env, b, batch_size))(batch))
    print(f"  {time.perf_counter() - t0:.1f} s", flush=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **{k: np.asarray(v) for k, v in vars(tables).items()})
    tmp.replace(path)
    return tables


def nominal_actions(env) -> jax.Array:
    """The DP baseline's open-loop sequence: the nominal training episode's optimal actions (T,)."""
    tables = dp_tables(env, "nominal", scenario.nominal())
    first = jax.tree.map(lambda x: x[0], tables)
    return dp.backup(first, scenario.make_episode().start_grasp).actions


def bar_png(path, names, means, cis, ylabel: str, title: str, color, ylim=None, symlog: float | None = None) -> None:
    """A bar chart of means with error bars (95% intervals); `symlog`: a symmetric-log y axis with this linear
    threshold, and a line at zero."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.bar(names, means, yerr=cis, capsize=6, color=color)
    if symlog is not None:
        ax.axhline(0, color="k", lw=0.8)
        ax.set_yscale("symlog", linthresh=symlog)
    if ylim is not None:
        ax.set_ylim(*ylim)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
