"""`python -m experiments --record figures [--machine gpu|cpu] [--only NAME ...]`: every published figure, each by
its documented command at its documented size, recorded at the current commit; `figures --stale` says which
records the code has moved past, `figures --list` what each figure runs.

A *figure* here is a command behind the current records in `docs/data/` (the README's figures and the docs' that
cite a record): its words after `python -m experiments --record`, the records it writes (`<name>_<device>`), the
machine it belongs on (`gpu`: an H100/H200 host; `cpu`: the 2-core CPU the README names) and the code it measures
(git pathspecs). A record is *stale* when that code differs between the record's commit and the working tree
(`git diff`: a file changed, deleted or renamed; a new file counts once a measured one imports it), when it was made
from a tree with uncommitted changes (`+dirty`), or when it was made by another command than the figure's;
`tests/test_docs.py` fails on a stale record the README cites.

The figures run one after another (a failure is reported and the next one runs; the command exits non-zero at the
end if any failed). Prints a table last: each figure, its records, minutes and outcome.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
import traceback

import jax

from experiments import cli, common
from experiments.common import Run
from gsp_jax.model import load as model_lib
from gsp_jax.planning import policies

_PAPER = ("experiments/paper/reproduce.py", "experiments/paper/fig4a.py", "experiments/paper/fig4b.py",
          "experiments/paper/table1")  # what `reproduce` runs (it trains only where no PPO policy is shipped)
_LATENCY = ("table1", "--per-decision", "--episodes", "7", "--policies", "dp-base", "rl", "L1", "L2", "dp-opt",
            "L1-physics", "--paper")  # one episode at a time, on either machine


def _other_models() -> tuple[str, ...]:
    """Git pathspecs that leave out each shipped model but the default, its scene folder and its policy: every
    figure is the default model's, so another model's files are not code it measures."""
    specs = []
    for name, scene in model_lib.SHIPPED.items():
        if name != model_lib.DEFAULT:
            specs.append(f":(exclude){scene.parent.relative_to(common.ROOT)}")
            if name in policies.SHIPPED_POLICIES:  # the test model (testhand) ships none
                specs.append(f":(exclude){policies.SHIPPED_POLICIES[name].relative_to(common.ROOT)}*")
    return tuple(specs)


_LIBRARY = ("gsp_jax", "models", *_other_models(), "experiments/common.py", "experiments/cli.py",
            "experiments/__main__.py", "pyproject.toml", "requirements.lock")


@dataclasses.dataclass(frozen=True)
class Figure:
    """One command behind published records. `command`: its words after `python -m experiments --record`;
    `records`: the record names it writes (without the device suffix); `machine`: "gpu" or "cpu"; `measures`: git
    pathspecs of the code its numbers depend on; `minutes`: about how long it runs on its machine."""

    name: str
    command: tuple[str, ...]
    records: tuple[str, ...]
    machine: str
    measures: tuple[str, ...]
    minutes: float


FIGURES = (
    Figure("paper", ("reproduce", "--full", "--backend", "c", "--out", "docs/report"), ("fig4a", "table1", "fig4b"),
           "gpu", (*_LIBRARY, *_PAPER), 7.0),
    Figure("latency", _LATENCY, ("bench_latency",), "gpu", (*_LIBRARY, "experiments/paper/table1"), 2.5),
    # Fig. 4b alone on a CPU (the GPU host's `paper` figure also makes it): the paper's surrogate, C MuJoCo
    Figure("fig4b-cpu", ("fig4b", "--backend", "c", "--paper", "--fresh", "--policies", "dp-base", "rl", "L1", "L2",
                         "dp-opt", "L1-physics"), ("fig4b",), "cpu", (*_LIBRARY, "experiments/paper/fig4b.py"), 12.0),
    # the beam search beside the DP table (issue 86): time an episode, IK problems, plans equal to DP optimal's
    Figure("search-cpu", ("bench-search", "--learned"), ("bench_search_learned",), "cpu",
           (*_LIBRARY, "experiments/bench/search.py"), 8.0),
    Figure("latency-cpu", _LATENCY, ("bench_latency",), "cpu", (*_LIBRARY, "experiments/paper/table1"), 12.0),
    Figure("envelope-stress", ("envelope", "--set", "stress", "--random", "8", "--physics-lookahead", "2", "--bases",
                               "four-tips", "dp-opt", "--paper"), ("envelope_stress",), "gpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    Figure("envelope-eval", ("envelope", "--set", "eval", "--random", "8", "--physics-lookahead", "2", "--bases",
                             "four-tips", "dp-opt", "--paper"), ("envelope_eval",), "gpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 3.0),
    Figure("physics-cpu", ("bench-physics", "--backends", "c", "--paper", "--variant", "paper", "--variant",
                           "predictive"), ("bench_physics",), "cpu", (*_LIBRARY, "experiments/bench/physics.py"), 18.0),
    # the same with the learned physics term (`--learned`: the model's weights, `calibrate --learn`)
    Figure("envelope-stress-learned", ("envelope", "--set", "stress", "--random", "8", "--physics-lookahead", "2",
                                       "--bases", "four-tips", "dp-opt", "--learned"), ("envelope_stress_learned",),
           "gpu", (*_LIBRARY, "experiments/physics/envelope.py"), 6.0),
    Figure("envelope-eval-learned", ("envelope", "--set", "eval", "--random", "8", "--physics-lookahead", "2",
                                     "--bases", "four-tips", "dp-opt", "--learned"), ("envelope_eval_learned",), "gpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 2.0),
    Figure("latency-learned", ("table1", "--per-decision", "--episodes", "7", "--policies", "L1", "dp-opt",
                               "--learned"), ("bench_latency_learned",), "gpu",
           (*_LIBRARY, "experiments/paper/table1"), 1.5),
    # the contact controllers side by side on a CPU (issue 84): the default's measured frames and the paper's
    Figure("controller-stress-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies", "four-tips",
                                     "dp-opt", "L1", "L2", "--learned"), ("envelope_stress_learned",), "cpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    Figure("controller-stress-paper-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies", "four-tips",
                                           "dp-opt", "L1", "L2", "--learned", "--controller", "paper"),
           ("envelope_stress_learned_paper",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    Figure("controller-eval-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies", "four-tips", "dp-opt",
                                   "L1", "L2", "--learned"), ("envelope_eval_learned",), "cpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 2.5),
    Figure("controller-eval-paper-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies", "four-tips",
                                         "dp-opt", "L1", "L2", "--learned", "--controller", "paper"),
           ("envelope_eval_learned_paper",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 2.5),
    Figure("controller-stress-predictive-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies",
                                                "four-tips", "dp-opt", "L1", "L2", "--learned", "--controller",
                                                "predictive"), ("envelope_stress_learned_predictive",), "cpu",
           (*_LIBRARY, "experiments/physics/envelope.py"), 14.0),
    Figure("controller-eval-predictive-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies", "four-tips",
                                              "dp-opt", "L1", "L2", "--learned", "--controller", "predictive"),
           ("envelope_eval_learned_predictive",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 4.0),
    # the same planners in the gap level's worlds (issue 85, docs/world.md): plans made in the model, run where it
    # is not the world; and which part of the gap drops the tool
    Figure("fig4b-gap-cpu", ("fig4b", "--backend", "c", "--paper", "--fresh", "--policies", "dp-base", "rl", "L1",
                             "L2", "dp-opt", "L1-physics", "--world", "gap"), ("fig4b_gap",), "cpu",
           (*_LIBRARY, "experiments/paper/fig4b.py"), 12.0),
    Figure("controller-stress-gap-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies", "four-tips",
                                         "dp-opt", "L1", "L2", "--learned", "--world", "gap"),
           ("envelope_stress_learned_gap",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    Figure("controller-eval-gap-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies", "four-tips",
                                       "dp-opt", "L1", "L2", "--learned", "--world", "gap"),
           ("envelope_eval_learned_gap",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 2.5),
    Figure("world-parts-cpu", ("world-parts", "--learned"), ("world_parts_eval_gap_learned",), "cpu",
           (*_LIBRARY, "experiments/physics/world_parts.py"), 1.5),
    # the robust controller (a filtered pose, the motors' strengths estimated): the same sets, model and gap
    Figure("controller-eval-robust-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies", "four-tips",
                                          "dp-opt", "L1", "L2", "--learned", "--controller", "robust"),
           ("envelope_eval_learned_robust",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 2.5),
    Figure("controller-eval-robust-gap-cpu", ("envelope", "--set", "eval", "--random", "0", "--policies",
                                              "four-tips", "dp-opt", "L1", "L2", "--learned", "--controller",
                                              "robust", "--world", "gap"),
           ("envelope_eval_learned_robust_gap",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 2.5),
    Figure("controller-stress-robust-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies",
                                            "four-tips", "dp-opt", "L1", "L2", "--learned", "--controller",
                                            "robust"),
           ("envelope_stress_learned_robust",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    Figure("controller-stress-robust-gap-cpu", ("envelope", "--set", "stress", "--random", "0", "--policies",
                                                "four-tips", "dp-opt", "L1", "L2", "--learned", "--controller",
                                                "robust", "--world", "gap"),
           ("envelope_stress_learned_robust_gap",), "cpu", (*_LIBRARY, "experiments/physics/envelope.py"), 9.0),
    # the hands x tools table: every shipped model's files are what it measures (the default's learned term on);
    # its Menagerie rows need the hands imported once before (`hands --menagerie DIR`: examples/published/)
    Figure("hands", ("hands", "--learned"), ("hands_learned",), "cpu", ("gsp_jax", "models", "experiments/common.py",
           "experiments/cli.py", "experiments/__main__.py", "pyproject.toml", "requirements.lock",
           "experiments/physics/hands.py", "examples/published", "experiments/physics/envelope.py"),
           35.0),
)
# the surrogate's figures (Fig. 4a, Table 1) come from the same run as Fig. 4b, so `paper` measures the physics too


def machine() -> str:
    """"gpu" where JAX has a GPU, else "cpu"."""
    return "gpu" if jax.default_backend() == "gpu" else "cpu"


def by_record(name: str) -> Figure:
    """The figure whose command writes the record `name` (`<record>_<device>`, e.g. envelope_stress_h100)."""
    stem, _, device = name.rpartition("_")
    kind = "cpu" if device == "cpu" else "gpu"
    for fig in FIGURES:
        if stem in fig.records and fig.machine == kind:
            return fig
    raise KeyError(f"no figure writes the record {name!r} (experiments/paper/figures.py: FIGURES)")


def _git(*words: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *words], cwd=common.ROOT, capture_output=True, text=True)


def stale(record: dict) -> list[str]:
    """Why a record (a docs/data row: {name, commit, command, ...}) no longer stands for the code in the working
    tree: [] if it does. Needs the project's git history (a clone, not an archive)."""
    fig = by_record(record["name"])
    want = "python -m experiments --record " + " ".join(fig.command)
    why = [] if record["command"] == want else [f"made by `{record['command']}`, not `{want}`"]
    commit = record["commit"]
    if commit.endswith("+dirty"):
        return why + [f"made at {commit}: a tree with uncommitted changes"]
    if _git("cat-file", "-e", f"{commit}^{{commit}}").returncode:
        return why + [f"its commit {commit} is not in this repository's history"]
    changed = _git("diff", "--name-only", "--diff-filter=a", commit, "--", *fig.measures)  # a file added since is
    # reached only through a change to one it measures (an import), which counts
    if changed.returncode:
        raise RuntimeError(f"git diff failed: {changed.stderr.strip()}")
    files = changed.stdout.split()
    return why + ([f"the code it measures changed since {commit}: {', '.join(files[:6])}"
                   + (f" and {len(files) - 6} more" if len(files) > 6 else "")] if files else [])


def start_commit() -> str | None:
    """The commit a figures run starts from (12 hex digits; `+dirty` where a tracked file other than the records and
    the report, docs/data and docs/report, differs from it), or None without git."""
    head = _git("rev-parse", "--short=12", "HEAD")
    if head.returncode:
        return None
    dirty = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)docs/data",
                 ":(exclude)docs/report")
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def records() -> dict[str, dict]:
    """Every current record in docs/data: {name: row}."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(common.DATA.glob("*.json"))}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--machine", choices=["gpu", "cpu"], default=None,
                   help="run the figures that belong on this machine (default: this one's)")
    p.add_argument("--only", nargs="+", default=None, metavar="NAME", choices=[f.name for f in FIGURES],
                   help="only these figures")
    p.add_argument("--stale", action="store_true", help="only list the records and whether each is stale")
    p.add_argument("--list", action="store_true", help="only list the figures and their commands")


def main(args: argparse.Namespace, run: Run) -> None:
    if args.list:
        print(common.table(["figure", "machine", "minutes", "records", "command"],
                           [[f.name, f.machine, f.minutes, " ".join(f.records), "python -m experiments --record "
                             + " ".join(f.command)] for f in FIGURES], ".1f"))
        return
    if args.stale:
        rows, reasons = [], []
        for name, row in records().items():
            try:
                why = stale(row)
                kind = "stale" if why else "current"
            except KeyError:
                why, kind = [], "no figure (kept as it is)"
            rows.append([name, row["commit"], kind])
            reasons += [f"{name}: {w}" for w in why]
        print("\n".join(reasons) + "\n" if reasons else "", end="")
        print(common.table(["record", "commit", "state"], rows))
        return
    if not run.record:
        print("figures: without --record the runs write no records (python -m experiments --record figures)",
              flush=True)
    where = args.machine or machine()
    chosen = [f for f in FIGURES if f.name in args.only] if args.only else [f for f in FIGURES if f.machine == where]
    print(f"figures: {len(chosen)} to run on this {where} host, about {sum(f.minutes for f in chosen):.0f} min: "
          f"{', '.join(f.name for f in chosen)}", flush=True)
    # every record of the run names the commit it started from: the records and the report the run writes itself
    # (tracked files) would otherwise make the later ones `+dirty` (`Run.record_figures` reads GSP_JAX_COMMIT where
    # git cannot answer)
    saved = {k: os.environ.get(k) for k in ("GSP_JAX_COMMIT", "GIT_DIR")}
    commit = start_commit()
    if commit is not None:
        os.environ.update(GSP_JAX_COMMIT=commit, GIT_DIR=os.devnull)
    try:
        rows, failed = _run(chosen, run)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    print()
    print(common.table(["figure", "records", "minutes", "outcome"], rows, ".1f"))
    if failed:
        raise SystemExit(f"figures: {len(failed)} of {len(chosen)} failed: {', '.join(failed)}")


def _run(chosen: list[Figure], run: Run) -> tuple[list[list], list[str]]:
    """Run each figure's command in this process within `run` (its records naming its own command): the table's
    rows and the names of the figures that failed."""
    rows, failed = [], []
    for i, fig in enumerate(chosen):
        words = (["--record"] if run.record else []) + list(fig.command)
        print(f"\n[{i + 1}/{len(chosen)}] {fig.name}: python -m experiments {' '.join(words)}", flush=True)
        t0 = time.perf_counter()
        try:
            cli.run_command(list(fig.command), dataclasses.replace(run, command=tuple(words)))  # its records name it
            outcome = "done"
        except (Exception, SystemExit) as e:  # one figure's failure does not stop the others
            cause = f"{type(e).__name__}: {e}".splitlines()[0]
            print(f"figures: {fig.name} failed: {cause}", file=sys.stderr, flush=True)
            traceback.print_exc()
            outcome, failed = f"FAILED ({cause[:60]})", failed + [fig.name]
        rows.append([fig.name, " ".join(fig.records), (time.perf_counter() - t0) / 60, outcome])
    return rows, failed
