"""Small helpers shared by the experiments: the run a command is given (`Run`: its model, learned term, --record),
the results folder, plain-text tables, timing, the paper's numbers, the fingerprint of a saved evaluation result."""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import pathlib
import subprocess
import sys
import time
from typing import TYPE_CHECKING

import jax
import numpy as np

from gsp_jax.core import distributed, files
from gsp_jax.model import hand
from gsp_jax.physics.config import DEFAULT_CONTROLLER

if TYPE_CHECKING:
    from gsp_jax.model.load import Model

RESULTS = pathlib.Path("results")


def results_dir(*parts: str, model=None, learned: bool = False, controller: str = DEFAULT_CONTROLLER,
                world: str = "nominal") -> pathlib.Path:
    """results/<parts> (created, and locked for this process); a command run for another model than the wrench
    (`model`, a `Model` or a name; None: the default) writes to results/<first part>-<model>/... (results/<model>
    for no parts) instead, one with the learned physics term (`learned`) to results/<first part>-learned/..., and
    one with another contact controller than the default (`controller`) to results/<first part>-<controller>/...,
    one in a world other than the nominal (`world`, a level of `gsp_jax.physics.world`) to
    results/<first part>-<world>/...: no model's, surrogate's, controller's or world's results overwrite another's. A
    command calls its run's (`Run.results_dir`)."""
    from gsp_jax.model import load as model_lib

    name = model_lib.load_model(model).name
    if name != model_lib.DEFAULT:
        parts = (f"{parts[0]}-{name}", *parts[1:]) if parts else (name,)
    if learned:
        parts = (f"{parts[0]}-learned", *parts[1:]) if parts else ("learned",)
    if controller != DEFAULT_CONTROLLER:
        parts = (f"{parts[0]}-{controller}", *parts[1:]) if parts else (controller,)
    if world != "nominal":
        parts = (f"{parts[0]}-{world}", *parts[1:]) if parts else (world,)
    path = RESULTS.joinpath(*parts)
    path.mkdir(parents=True, exist_ok=True)
    if distributed.is_main():  # the processes of one run (`--processes`) share process 0's lock
        files.hold(path)  # one command at a time writes a results folder (`files.FolderInUse` for a second)
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


PAPER = dict(  # the paper's numbers, printed beside ours
    table1_s={"dp-base": 1.34, "rl": 1.23, "L1": 2.68, "L2": 4.30, "dp-opt": 151.79},
    table1_machine="32-core Xeon Silver 4216, 2.1 GHz",
)
ROOT = pathlib.Path(__file__).resolve().parents[1]


def fingerprint_sources() -> list[pathlib.Path]:
    """The files `fingerprint` hashes, sorted: every module of the library (`gsp_jax/`, all its layers: the
    controller's too), the shipped models' XML and the physics experiments' runners."""
    package = pathlib.Path(hand.__file__).parents[1]  # gsp_jax/ (hand.py is in its model/ layer)
    sources = [*package.glob("**/*.py"), *hand.MODELS_DIR.glob("*.xml")]
    sources += [ROOT / "experiments" / f for f in ("physics/check.py", "paper/fig4b.py")]
    return sorted(sources)


def fingerprint(ctx) -> str:
    """Hash of what a saved result of an `evaluation.Context` depends on: the library and model sources, the physics
    experiments' sources, the episodes, the RL parameters (where the context has them)."""
    h = hashlib.sha256()
    for path in fingerprint_sources():
        h.update(path.read_bytes())
    h.update(ctx.surrogate.model.digest.encode())  # the model (its scene, includes resolved)
    h.update(ctx.surrogate.learned_tag.encode())  # the learned physics term ("" without one)
    h.update(repr(ctx.names).encode())
    for leaf in jax.tree.leaves(ctx.rl.params if ctx.rl is not None else ()):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()[:16]


DATA = ROOT / "docs" / "data"  # the current result of each benchmark and figure, and their histories


def device_slug() -> str:
    """A short name of the device the results come from: h100, h200, cpu..."""
    kind = jax.local_devices()[0].device_kind.lower()
    return next((g for g in ("h100", "h200", "a100", "l4") if g in kind), jax.default_backend())


@dataclasses.dataclass(frozen=True)
class Run:
    """One run of a command: what `python -m experiments` makes of its options (`cli.main`) and hands to the command
    (`main(args, run)`), and what a pipeline hands the commands it runs (`cli.run_command(words, run)`: the same
    model, learned term and --record, and the record naming the outermost command). Nothing of it is kept in the
    process: a command knows its run only through this object."""

    model: Model | None = None  # the scene (`--model`; None: the default model, where the command takes no --model)
    learned: bool = False  # plan with the model's learned physics term (`Surrogate(learned=)`): where the model has
    # weights unless `--paper` (`cli.PAPER_BY_DEFAULT`: only with `--learned`)
    record: bool = False  # `--record`: `record_figures` writes to DATA (off: runs leave docs alone)
    command: tuple[str, ...] = ()  # the words of the command its records name (the outermost one's; (): sys.argv)
    controller: str = DEFAULT_CONTROLLER  # the contact controller in physics (`--controller`: `PhysicsConfig.named`)
    world: str = "nominal"  # the level of the world the plans run in (`--world`: `gsp_jax.physics.world.LEVELS`)
    world_seed: int = 0  # the seed of the episodes' worlds (`--world-seed`)
    world_only: tuple[str, ...] = ()  # only these fields of the level's gap (`--world-only`; (): all)

    @property
    def world_name(self) -> str:
        """The world's name in results and records: its level, and the gap's fields where `world_only` picks."""
        return "-".join((self.world, *self.world_only))

    def results_dir(self, *parts: str) -> pathlib.Path:
        """`results_dir` for this run's model, learned term, controller and world:
        results/<parts>[-<model>][-learned][-<controller>][-<world>]."""
        return results_dir(*parts, model=self.model, learned=self.learned, controller=self.controller,
                           world=self.world_name)

    @property
    def gap(self):
        """This run's world gap (`gsp_jax.physics.world.Gap`: its level, only `world_only`'s fields where it names
        any); None in the nominal world."""
        if self.world == "nominal":
            return None
        from gsp_jax.physics import world as world_lib

        return world_lib.Gap.named(self.world).only(*self.world_only)

    def worlds(self, episodes, hand):
        """The worlds of `episodes` (a batch: leading axis (N,)) in this run's `world` level, drawn from
        `world_seed` (only `world_only`'s fields of its gap, where it names any) for `hand` (a `HandModel`;
        `gsp_jax.physics.world.draw_for`: episode i's depends on the seed,
        i and N only, so a chunk of the set selects its rows); None in the nominal world (today's check, bit for
        bit)."""
        if self.gap is None:
            return None
        from gsp_jax.physics import world as world_lib

        return world_lib.draw_for(self.gap, self.world_seed, episodes, hand)

    def physics_config(self, **changes):
        """The `PhysicsConfig` of this run's contact controller (`PhysicsConfig.named`) with the model's own tuning
        of it where `calibrate --tune --write` made one (`tuning.config`), then `changes`."""
        from gsp_jax.model import load as model_lib
        from gsp_jax.physics import tuning

        return tuning.config(self.model or model_lib.load_model(None), self.controller, **changes)

    def record_figures(self, name: str, figures: dict, data: pathlib.Path | None = None) -> dict | None:
        """With `--record` (`record`): `figures` (a small JSON-able dict, the benchmark's printed table) become the
        current `docs/data/<name>_<device>.json` (`device_slug`: one current result per figure and machine) and a
        new line of `docs/data/history/<name>_<device>.jsonl`, one schema for all: {name, date, commit, device,
        command, figures}."""
        if not self.record or not distributed.is_main():  # several processes: process 0 records
            return None
        data = DATA if data is None else pathlib.Path(data)
        other = f"_{self.controller}" if self.controller != DEFAULT_CONTROLLER else ""
        other += f"_{self.world_name}".replace("-", "_") if self.world != "nominal" else ""
        name = f"{name}{'_learned' * self.learned}{other}_{device_slug()}"  # beside the default's figures
        try:
            commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=ROOT, capture_output=True,
                                    text=True, check=True).stdout.strip()
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                                   capture_output=True, text=True).stdout.strip()
            commit += "+dirty" if dirty else ""
        except (OSError, subprocess.CalledProcessError):  # a copy without git's history (a cluster's, a GPU host's)
            commit = os.environ.get("GSP_JAX_COMMIT", "unknown")  # the commit it was made from, where one says so
        row = dict(name=name, date=datetime.datetime.now().isoformat(timespec="minutes"), commit=commit,
                   device=f"{jax.local_devices()[0].device_kind} ({jax.default_backend()}, {os.cpu_count()} cores)",
                   command="python -m experiments " + " ".join(self.command or sys.argv[1:]), figures=figures)
        text = json.dumps(row, default=float)
        (data / "history").mkdir(parents=True, exist_ok=True)
        files.write_json(data / f"{name}.json", json.loads(text))
        with open(data / "history" / f"{name}.jsonl", "a") as f:
            f.write(text + "\n")
        print(f"recorded {name}: {data / (name + '.json')}", flush=True)
        return row


def add_lookahead_argument(p, root_in_table: bool = False) -> None:
    """`--lookahead`: where L1/L2 search. `cached` (default): below the root in the episode's table (exact for the
    discrete states the surrogate visits), the root's actions stepped in the surrogate; `continuous`: all in the
    surrogate. With `root_in_table` (episodes planned from their start, never from a simulated state) also `table`,
    the default there: the root's children too are the table's."""
    choices = ["table", "cached", "continuous"] if root_in_table else ["cached", "continuous"]
    p.add_argument("--lookahead", default=choices[0], choices=choices,
                   help="L1/L2: "
                   + ("the episode's table for the whole search (exact from its start), " if root_in_table else "")
                   + "below the root in the episode's table (cached), or none (continuous)")


def check_planners(names, option: str = "--policies", backend: str | None = None) -> None:
    """SystemExit naming the option and the name unless each of `names` is a registered planner (after --plugin)
    that runs on the physics `backend` (None: no physics)."""
    from gsp_jax.planners import registry as planners

    for name in names:
        try:
            p = planners.get(name)
        except ValueError as e:
            raise SystemExit(f"{option}: {e}") from None
        if backend is not None and p.backends is not None and backend not in p.backends:
            raise SystemExit(f"{option}: {name} runs in physics on {'/'.join(p.backends)} only, not {backend!r} "
                             f"(--backend {p.backends[0]})")


def add_bases_argument(p) -> None:
    from gsp_jax.planning import evaluation

    p.add_argument("--bases", nargs="+", default=list(evaluation.L1_PHYSICS["bases"]), metavar="NAME",
                   help="L1-physics: the policies its branches follow after their first action (each candidate is "
                        "branched under each; several: never worse than any of them)")


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


def fig4a_png(relative: dict, n: int, path) -> None:
    """Fig. 4a: each policy's return relative to DP optimal (`stats.relative_returns`'s "relative") on n episodes."""
    names = list(relative)
    bar_png(path, names, [relative[k]["mean"] for k in names], [relative[k]["ci95"] for k in names],
            "return - DP optimal return (symlog)", f"Surrogate, {n} unseen episodes (95% CI)",
            ["#999999", "#4c72b0", "#55a868", "#2e7d32"][: len(names)],
            symlog=0.05)  # falls (-200) and the lookahead's hundredths on one axis


def fig4b_png(results: dict, n: int, path) -> None:
    """Fig. 4b: each policy's mean tool angle error [deg] in physics ({policy: {mean_deg, ci95_deg, backend}})."""
    names = list(results)
    engine = {"mjx": "MJX", "c": "C MuJoCo"}.get(next(iter(results.values())).get("backend", "mjx"), "MJX")
    bar_png(path, names, [results[k]["mean_deg"] for k in names],
            [np.nan_to_num(results[k]["ci95_deg"]) for k in names],
            "mean tool angle error [deg] (180 = fell)", f"{engine} physics, {n} unseen episodes (95% CI)", "#4c72b0",
            ylim=(0, 190))
