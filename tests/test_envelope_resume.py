"""`envelope` runs its episodes in chunks and keeps each finished one (results/envelope/<set>.parts/): a run that
fails part-way says where it stopped in one line and re-raises, and the same command continues from the kept chunks
to the result an uninterrupted run gives, bit for bit (C MuJoCo)."""
from __future__ import annotations

import json
import pathlib
import re
import shutil
import subprocess

import numpy as np
import pytest

import launch

from experiments.cli import main
from experiments.physics import envelope
from gsp_jax.planning import evaluation
from gsp_jax import physics
from gsp_jax.model import scenario

# 2 evaluation episodes x (the four tips, 1 random sequence), one episode a chunk: 2 chunks; falls classified here
LINE = ["envelope", "--set", "eval", "--episodes", "2", "--random", "1", "--policies", "four-tips", "--chunk", "1",
        "--jobs", "1", "--paper"]
WAYPOINTS = launch.WAYPOINTS


class Fault(RuntimeError):
    """The injected failure of a chunk's physics."""


def run(monkeypatch, folder: pathlib.Path, fail_at: int | None = None) -> int:
    """`python -m experiments <LINE>` in `folder`; `Physics.simulate_many`'s `fail_at`-th call (1-based) raises
    `Fault` (None: none). The number of its calls (chunks simulated)."""
    calls = []
    simulate_many = physics.Physics.simulate_many

    def counted(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == fail_at:
            raise Fault("injected in the second chunk")
        return simulate_many(self, *args, **kwargs)

    folder.mkdir(exist_ok=True)
    monkeypatch.chdir(folder)
    episode_set = scenario.episode_set  # the set's episodes to their first WAYPOINTS (a quick table and physics)
    monkeypatch.setattr(scenario, "episode_set", lambda name, model=None: {
        k: e.head(WAYPOINTS) for k, e in episode_set(name, model).items()})
    monkeypatch.setattr(physics.Physics, "simulate_many", counted)
    try:
        main(LINE)
    finally:
        monkeypatch.undo()
    return len(calls)


def result(folder: pathlib.Path) -> str:
    """The run's sequences and summary, as text (NaN compares equal to NaN; floats to the last bit)."""
    out = json.loads((folder / "results/envelope/eval.json").read_text())
    return json.dumps(dict(sequences=out["sequences"], summary=out["summary"]), sort_keys=True)


def test_a_failed_chunk_keeps_the_finished_ones_and_a_rerun_continues_from_them(monkeypatch, tmp_path, capsys):
    """A fault in the second chunk: one line naming the episodes, the cause and the folder, the first chunk kept; the
    same command again simulates only the second chunk (its unreadable file named and replaced) and writes the
    result of an uninterrupted run in a fresh folder, field for field."""
    resumed, fresh = tmp_path / "resumed", tmp_path / "fresh"
    parts = resumed / "results/envelope/eval.parts"

    with pytest.raises(Fault, match="injected in the second chunk"):
        run(monkeypatch, resumed, fail_at=2)
    err = capsys.readouterr().err
    stop = [line for line in err.splitlines() if line.startswith("envelope: stopped")]
    assert stop == ["envelope: stopped in episode 2 of 2 (chunk 2 of 2): Fault: injected in the second chunk; 1 "
                    "finished episodes kept in results/envelope/eval.parts (the same command continues from them)"], err
    kept = sorted(parts.glob("*.npz"))
    assert [p.name.split("_", 1)[1] for p in kept] == ["episodes1-1.npz"], kept
    assert not (resumed / "results/envelope/eval.json").exists()
    with np.load(kept[0]) as d:  # the outcomes the summary reads, and of the traces only the rows `reached` reads
        assert sorted(d.files) == sorted([*envelope.FIELDS, "seconds"])
        G, n, T = 2, 1, d["actions"].shape[-1]
        assert d["fell"].shape == (G, n) and d["grasps"].shape == (G, n, T) and d["reached"].shape[:3] == (G, n, T)

    # the second chunk's file, unreadable (as a disk might leave it): named in a warning, its episode run again
    broken = parts / kept[0].name.replace("episodes1-1", "episodes2-2")
    broken.write_bytes(b"PK\x03\x04 truncated")
    with pytest.warns(UserWarning, match=re.escape(f"{broken.relative_to(resumed)}: cannot be read")):
        assert run(monkeypatch, resumed) == 1  # only the chunk that did not finish
    assert "reusing 1 finished episodes of 2" in capsys.readouterr().out
    assert (resumed / "results/envelope/eval.json").is_file()
    assert sorted(p.name for p in parts.glob("*.npz")) == sorted([kept[0].name, broken.name])

    # uninterrupted, in a fresh folder; only the DP tables' cache is copied (building them is most of a run's time)
    cache = pathlib.Path("results", evaluation.TABLES)
    shutil.copytree(resumed / cache, fresh / cache)
    assert run(monkeypatch, fresh) == 2
    assert result(resumed) == result(fresh)


# ------------------------------------------------------------------------------------------- several processes
DYING_PLUGIN = '''"""Process 1 is killed (SIGKILL) in its first chunk's physics, once process 0's chunk is kept."""
import os, pathlib, signal, time

from gsp_jax import physics

if os.environ.get("GSP_JAX_PROCESS_ID") == "1":
    def dying(self, *args, **kwargs):
        deadline = time.monotonic() + 600
        while not list(pathlib.Path("results/envelope/eval.parts").glob("*_episodes1-1.npz")):
            if time.monotonic() > deadline:
                raise RuntimeError("process 0's chunk never came")
            time.sleep(0.2)
        os.kill(os.getpid(), signal.SIGKILL)

    physics.Physics.simulate_many = dying
'''


def run_processes(folder: pathlib.Path, n: int, *plugins: str) -> subprocess.CompletedProcess:
    """`python -m experiments --processes n <LINE>` in `folder` (`launch.run`); `plugins`: names of plugin files."""
    return launch.run(folder, n, LINE, {name: (folder / name).read_text() for name in plugins})


def test_kept_results_are_keyed_by_every_layer_of_the_library_and_the_controller():
    """Saved envelope chunks and Fig. 4b results are reused only for the code and controller that made them:
    `common.fingerprint` hashes every module of `gsp_jax` (the controller's and the native tick's too: a key over
    one layer reused a run of the paper's controller for the measured frames' default), and the chunks' key
    changes with the `PhysicsConfig`."""
    import argparse

    from experiments import common
    from experiments.physics import envelope
    from gsp_jax import physics

    sources = {p.relative_to(common.ROOT).as_posix() for p in common.fingerprint_sources()}
    for layer in ("core", "model", "solvers", "surrogate", "planning", "physics", "planners"):
        assert any(s.startswith(f"gsp_jax/{layer}/") for s in sources), layer
    assert {"gsp_jax/physics/controller.py", "gsp_jax/physics/native.py", "gsp_jax/physics/config.py"} <= sources

    class Ctx:  # what `fingerprint` reads of a context
        class surrogate:
            class model:
                digest = "m"
            learned_tag = ""
        names = ("a",)
        rl = None

    args = argparse.Namespace(random=0, seed=0, physics_lookahead=0, bases=["four-tips"], chunk=30)
    keys = {envelope.parts_key(Ctx, args, ["four-tips"], physics.PhysicsConfig.named(c)) for c in ("measured", "paper")}
    assert len(keys) == 2
