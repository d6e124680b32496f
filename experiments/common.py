"""Small helpers shared by the experiments: the results folder and plain-text tables."""
from __future__ import annotations

import pathlib
import time

import jax

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
