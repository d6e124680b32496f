"""Where to put the palm: a search over palm positions for the one whose fingers reach the tool's options over the
lift and whose start grasp is clear over the heights the episodes start at (`check-model --place`).

    best = placement.search("path/to/scene.xml")[0]      # candidates, best first
    best.pos                                              # (3,) the palm's position [m]: `import-hand --palm-pos`

Each candidate is the scene with its palm body moved (the tool, the table and the reach box stay), loaded as a
model of its own and scored by the surrogate's IK (`preflight.reach`: every link on every option at the lift's
first and last waypoint; `preflight.start_band`: the start grasp at the lowest and highest starts). The search moves
the palm along z, then x, then y (coordinate descent, `STEPS`); each candidate compiles its own IK (the hand's
arrays are constants of the program), so a search of a dozen takes minutes on a CPU.
"""
from __future__ import annotations

import dataclasses
import hashlib
import pathlib

import mujoco
import numpy as np

from gsp_jax.model import load as model_lib
from gsp_jax.physics import preflight
from gsp_jax.surrogate.step import Surrogate

STEPS = ((2, 0.02), (0, 0.01), (1, 0.01))  # (axis, step [m]): z, then x, then y; each tried one step either way, twice


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One palm position and how the hand fares there."""

    offset: tuple[float, float, float]  # [m] the palm moved by, from the file's position
    pos: tuple[float, float, float]  # [m] the palm's position in the world
    both: int  # options reached at the lift's first and last waypoint
    either: int  # options reached at one of them at least
    options: int  # options in all
    clear: bool  # the start grasp reaches and collides nowhere over the band of start heights
    problems: tuple[str, ...]  # what `preflight.start_reach` and `start_band` say there

    def score(self) -> tuple:
        return (self.clear, self.both, self.either)


def _moved(path: pathlib.Path, palm: str, offset) -> tuple[pathlib.Path, tuple[float, ...]]:
    """The scene with its palm moved by `offset`, written beside it (its includes and meshes resolve alike), named
    by its content (a model is loaded once per path in a process); and the palm's new position."""
    spec = mujoco.MjSpec.from_file(str(path))
    body = spec.body(palm)
    body.pos = np.asarray(body.pos, np.float64) + np.asarray(offset, np.float64)
    xml = spec.to_xml()
    out = path.with_name(f".{path.stem}.place-{hashlib.sha256(xml.encode()).hexdigest()[:12]}.xml")
    out.write_text(xml)
    return out, tuple(float(x) for x in body.pos)


def evaluate(path, offset=(0.0, 0.0, 0.0)) -> Candidate:
    """`Candidate` of the scene at `path` with its palm moved by `offset` (3,) [m]."""
    path = pathlib.Path(model_lib.resolve(path))
    base = model_lib.load_model(path)
    palm = base.hand.body_names[0]
    moved, pos = _moved(path, palm, offset)
    try:
        model = model_lib.load_model(moved)
        sur = Surrogate(model, learned=False)
        reach = preflight.reach(sur)
        ok = np.nan_to_num(reach.error, nan=np.inf) <= reach.tolerance  # (L, K, 2)
        valid = np.isfinite(reach.error[..., 0])
        problems = tuple(preflight.start_reach(sur) + preflight.start_band(sur))
    finally:
        moved.unlink(missing_ok=True)
    return Candidate(offset=tuple(float(x) for x in offset), pos=pos, both=int(np.sum(ok.all(-1) & valid)),
                     either=int(np.sum(ok.any(-1) & valid)), options=int(valid.sum()), clear=not problems,
                     problems=problems)


def search(path, steps=STEPS, progress: bool = True) -> list[Candidate]:
    """Every palm position tried, best first (clear start, then options reached at both ends, then at one): from
    the file's position, along each (axis, step) of `steps` in turn, one step either way, kept where it scores
    better, again from there while it does (at most twice an axis)."""
    tried: dict[tuple, Candidate] = {}

    def at(offset) -> Candidate:
        key = tuple(round(float(x), 6) for x in offset)
        if key not in tried:
            tried[key] = evaluate(path, key)
            c = tried[key]
            if progress:
                print(f"  palm moved by {np.round(np.asarray(key) * 1e3, 1).tolist()} mm: {c.both} of {c.options} "
                      f"options reached at both ends, {c.either} at one; start {'clear' if c.clear else 'not clear'}",
                      flush=True)
        return tried[key]

    best = at((0.0, 0.0, 0.0))
    for axis, step in steps:
        for _ in range(2):
            moves = [np.add(best.offset, np.eye(3)[axis] * s) for s in (-step, step)]
            better = max((at(m) for m in moves), key=Candidate.score)
            if better.score() <= best.score():
                break
            best = better
    return sorted(tried.values(), key=Candidate.score, reverse=True)
