"""Atomic writes, checked reads and folder locks (`gsp_jax.core.files`): nothing intact is lost to a crash, a truncated
file is named, two runs on one folder are told apart."""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time

import pytest

from gsp_jax.core import files


def test_atomic_write_replaces_whole_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "out" / "r.json"
    files.write_json(path, {"a": 1})
    files.write_json(path, {"a": 2, "b": [1, 2]})
    assert json.loads(path.read_text()) == {"a": 2, "b": [1, 2]}
    assert [p.name for p in path.parent.iterdir()] == ["r.json"]


def test_a_crash_while_writing_keeps_the_old_file(tmp_path, monkeypatch):
    path = files.write_text(tmp_path / "r.txt", "intact")

    def crash(*args, **kwargs):
        raise KeyboardInterrupt("killed during the write")

    monkeypatch.setattr(os, "fsync", crash)
    with pytest.raises(KeyboardInterrupt):
        files.write_text(path, "half")
    assert path.read_text() == "intact" and [p.name for p in tmp_path.iterdir()] == ["r.txt"]


def test_a_truncated_result_is_named_and_recomputed(tmp_path):
    path = files.write_json(tmp_path / "dp-base.json", {"angle": [1.0, 2.0]})
    path.write_text(path.read_text()[:9])  # a crash of a plain open(..., "w") leaves this
    with pytest.raises(files.UnreadableFile, match=r"dp-base\.json: not readable JSON"):
        files.read_json(path)
    with pytest.warns(UserWarning, match=r"dp-base\.json: not readable JSON .* recomputing it"):
        assert files.reuse_json(path) is None
    assert files.reuse_json(tmp_path / "missing.json") is None
    files.write_json(path, {"angle": [1.0]})
    assert files.reuse_json(path) == {"angle": [1.0]}
    with pytest.warns(UserWarning, match="unexpected contents"):
        assert files.reuse_json(path, valid=lambda r: "fell" in r) is None


HOLD = """
import sys, time
from gsp_jax import files
with files.folder_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(60)
"""


def test_a_folder_in_use_is_refused_and_a_stale_lock_taken_over(tmp_path):
    owner = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "locked"
        with pytest.raises(files.FolderInUse, match=rf"{tmp_path}: in use by process {owner.pid}"):
            with files.folder_lock(tmp_path):
                pass
    finally:
        owner.kill()
        owner.wait()
    # the owner was killed: its lock is stale, and the next run takes it over
    assert (tmp_path / files.LOCK_NAME).exists()
    with pytest.warns(UserWarning, match=f"stale lock of process {owner.pid}"):
        with files.folder_lock(tmp_path):
            with files.folder_lock(tmp_path):  # re-entrant within a process
                assert json.loads((tmp_path / files.LOCK_NAME).read_text())["pid"] == os.getpid()
            assert (tmp_path / files.LOCK_NAME).exists()
    assert not (tmp_path / files.LOCK_NAME).exists()
    time.sleep(0)


def test_a_truncated_table_cache_is_rebuilt_and_a_broken_episode_file_named(tmp_path, sur, monkeypatch):
    """The DP table cache entry a crash truncated is named in a warning and rebuilt (the same tables); an episode
    file that is not UTF-8 or not JSON is refused naming the file. (The tables' builder is replaced by a cheap one
    with the tables' fields: what is tested is the cache file's handling.)"""
    import jax.numpy as jnp
    import numpy as np

    from gsp_jax.planning import dp, evaluation
    from gsp_jax.model import scenario

    def build(_, batch, batch_size=4):
        n, t = batch.mass.shape[0], batch.n_steps
        return dp.Table(reward=jnp.arange(n * 3 * 2 * t, dtype=jnp.float32).reshape(n, 3, 2, t),
                        next_grasp=jnp.zeros((n, 3, 2), jnp.int32), terminal=jnp.zeros((n, 3, 2, t), bool),
                        ik_error=jnp.zeros((n, 3, t)), q=jnp.zeros((n, 3, t, 2)))

    monkeypatch.setattr(dp, "build_tables", build)
    episodes = {"nominal": scenario.make_episode().head(2)}
    first = evaluation.dp_tables(sur, "t", episodes, cache=tmp_path)
    (entry,) = tmp_path.glob("t_*.npz")
    entry.write_bytes(entry.read_bytes()[:200])
    with pytest.warns(UserWarning, match=rf"{entry.name}: the cached DP tables cannot be read .*rebuilding"):
        again = evaluation.dp_tables(sur, "t", episodes, cache=tmp_path)
    np.testing.assert_array_equal(np.asarray(first.reward), np.asarray(again.reward))
    assert [p.name for p in tmp_path.iterdir()] == [entry.name]  # rewritten whole, no temporary left
    bad = tmp_path / "eps.json"
    bad.write_bytes(b"\xff\xfe{")
    with pytest.raises(scenario.EpisodeError, match=r"eps\.json: not readable JSON"):
        scenario.load(bad)


RESULTS_HOLD = """
import time
from experiments.common import results_dir
results_dir("fig4b")
print("holding", flush=True)
time.sleep(60)
"""


def test_a_results_folder_is_one_commands_at_a_time(tmp_path):
    """A command's results folder (`experiments.common.results_dir`) is held until the process ends: a second
    process is refused naming the folder and the owner; the lock goes when the owner exits normally."""
    env = {**os.environ, "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1]), "JAX_PLATFORMS": "cpu"}
    owner = subprocess.Popen([sys.executable, "-c", RESULTS_HOLD], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                             text=True)
    try:
        assert owner.stdout.readline().strip() == "holding"
        second = subprocess.run([sys.executable, "-c",
                                 "from experiments.common import results_dir; results_dir('fig4b')"],
                                cwd=tmp_path, env=env, capture_output=True, text=True)
        assert second.returncode != 0
        assert f"results/fig4b: in use by process {owner.pid}" in second.stderr, second.stderr
    finally:
        owner.kill()
        owner.wait()
    done = subprocess.run([sys.executable, "-c", "from experiments.common import results_dir; results_dir('fig4b')"],
                          cwd=tmp_path, env=env, capture_output=True, text=True)  # takes over the stale lock
    assert done.returncode == 0 and "stale lock" in done.stderr, done.stderr
    assert not (tmp_path / "results" / "fig4b" / files.LOCK_NAME).exists()  # released at exit


FOLDERS_HOLD = """
import sys, time
from experiments.common import results_dir
for part in sys.argv[1:]:
    results_dir(part)
print("holding", flush=True)
time.sleep(120)
"""


def test_a_command_takes_its_folders_before_its_set_up(tmp_path, monkeypatch):
    """A second command on a busy results folder is refused before its set-up (`results_folders`, locked by
    `python -m experiments`), not after minutes of DP tables: `train --out X` and `envelope`."""
    from experiments import cli
    from experiments.physics import envelope

    env = {**os.environ, "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1]), "JAX_PLATFORMS": "cpu"}
    owner = subprocess.Popen([sys.executable, "-c", FOLDERS_HOLD, "train-x", "envelope"], cwd=tmp_path, env=env,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "holding"
        try:  # before the change: the DP tables first (minutes), then the refusal
            second = subprocess.run([sys.executable, "-m", "experiments", "train", "--out", "train-x", "--paper",
                                     "--seeds", "1",
                                     "--iterations", "1"], cwd=tmp_path, env=env, capture_output=True, text=True,
                                    timeout=90)
        except subprocess.TimeoutExpired:
            pytest.fail("train --out train-x on a busy folder was not refused before its set-up")
        assert second.returncode != 0
        assert f"train: results/train-x: in use by process {owner.pid}" in second.stderr, second.stderr
        assert "preset" not in second.stdout and not (tmp_path / "results" / "tables").exists()  # no set-up

        def set_up(*args, **kwargs):
            raise AssertionError("envelope set up on a busy folder")

        monkeypatch.chdir(tmp_path)
        monkeypatch.setattr(envelope.evaluation, "context", set_up)
        with pytest.raises(SystemExit) as stop:
            cli.main(["envelope", "--set", "eval", "--episodes", "1", "--random", "0", "--paper"])
        assert f"envelope: results/envelope: in use by process {owner.pid}" in str(stop.value), stop.value
    finally:
        owner.kill()
        owner.wait()


def test_every_command_writing_results_declares_its_folders():
    """A command module that calls `results_dir` says which folders it writes (`results_folders(args)`), so that
    `python -m experiments` takes their locks before the command's work."""
    import importlib.util

    from experiments.cli import COMMANDS

    for command, (module, _) in COMMANDS.items():
        spec = importlib.util.find_spec(module)
        source = pathlib.Path(spec.origin).read_text() if spec and spec.origin else ""
        if "results_dir(" in source:
            assert "\ndef results_folders(args" in source, f"{command} ({module}): no results_folders(args)"
