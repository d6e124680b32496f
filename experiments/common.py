"""Small helpers shared by the experiments: the results folder and plain-text tables."""
from __future__ import annotations

import pathlib

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
