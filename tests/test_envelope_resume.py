"""`envelope` runs its episodes in chunks and keeps each finished one (results/envelope/<set>.parts/): a run that
fails part-way says where it stopped in one line and re-raises, and the same command continues from the kept chunks
to the result an uninterrupted run gives, bit for bit (C MuJoCo)."""
from __future__ import annotations

import json
import os
import pathlib
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from experiments import common
from experiments.__main__ import main
from experiments.physics import envelope
from gsp_jax import evaluation, physics, scenario

# 2 evaluation episodes x (the four tips, 1 random sequence), one episode a chunk: 2 chunks; falls classified here
LINE = ["envelope", "--set", "eval", "--episodes", "2", "--random", "1", "--policies", "four-tips", "--chunk", "1",
        "--jobs", "1"]
WAYPOINTS = 3
ROOT = pathlib.Path(__file__).resolve().parents[1]


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
    monkeypatch.setattr(common, "COMMAND", None)  # main sets it: not left to the other tests
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
    shutil.copytree(resumed / evaluation.TABLE_CACHE, fresh / evaluation.TABLE_CACHE)
    assert run(monkeypatch, fresh) == 2
    assert result(resumed) == result(fresh)


# ------------------------------------------------------------------------------------------- several processes
SHORT_PLUGIN = '''"""Every episode set cut to its first {w} waypoints, as the tests above cut them (`run`)."""
from gsp_jax import scenario

_episode_set = scenario.episode_set
scenario.episode_set = lambda name, model=None: {{k: e.head({w}) for k, e in _episode_set(name, model).items()}}
'''

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
    """`python -m experiments --processes n <LINE>` in `folder`, the episodes cut as `run` cuts them."""
    folder.mkdir(exist_ok=True)
    (folder / "short.py").write_text(SHORT_PLUGIN.format(w=WAYPOINTS))
    words = [*LINE, "--plugin", "short.py"] + [w for p in plugins for w in ("--plugin", p)]
    return subprocess.run([sys.executable, "-m", "experiments", "--processes", str(n), *words], cwd=folder,
                          capture_output=True, text=True, timeout=1200,
                          env=dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu"))


def test_two_processes_give_one_processs_result_bit_for_bit(monkeypatch, tmp_path):
    """`--processes 2`: the chunks and the DP tables split between two processes (CPU collectives), gathered by
    process 0, which alone writes: the result of one process, field for field, and no record of the other."""
    one, two = tmp_path / "one", tmp_path / "two"
    run(monkeypatch, one)
    proc = run_processes(two, 2)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "process 0 of 2 runs chunks 1-1" in proc.stdout
    assert "process 1 of 2 runs chunks 2-2" in (two / "results/processes/rank1.log").read_text()
    assert result(two) == result(one)
    assert len(list((two / "results/envelope/eval.parts").glob("*.npz"))) == 2  # each process kept its chunk


def test_a_killed_process_ends_the_run_naming_its_rank_and_the_finished_chunks_stay(monkeypatch, tmp_path):
    """Process 1 killed in its chunk: the run ends at once with an error naming process 1 and the signal (not a
    hang), process 0's finished chunk is kept, and one process continues from it to the uninterrupted result."""
    folder = tmp_path / "killed"
    folder.mkdir()
    (folder / "dying.py").write_text(DYING_PLUGIN)
    proc = run_processes(folder, 2, "dying.py")
    assert proc.returncode != 0
    assert "processes: process 1 was killed by signal 9 (SIGKILL); the others were stopped" in proc.stderr, \
        proc.stderr[-3000:]
    parts = folder / "results/envelope/eval.parts"
    assert [p.name.split("_", 1)[1] for p in parts.glob("*.npz")] == ["episodes1-1.npz"]
    with pytest.warns(UserWarning, match="stale lock of process"):  # process 0's, stopped by the launcher
        assert run(monkeypatch, folder) == 1  # only process 1's chunk is simulated again
    fresh = tmp_path / "fresh"
    run(monkeypatch, fresh)
    assert result(folder) == result(fresh)
