"""Every `python -m experiments` command runs in its quickest real form, in a fresh working directory (no results/
from an earlier run: the shipped policy, the committed model files), and writes what it says it writes.

Marked `commands` and left out of `make test` (one after another they take ~32 min on the H100 host, mostly
compiles; a 2-core CPU is slower): `make commands JOBS=8` runs them (the same lines 8 at a time took 7.8 min on the
H100 host). Within a group the order is the one a user follows: `physics-agree` reads what `physics` wrote in both
backends, `train-curves` what `train` wrote.
"""
from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]

# (command line, files it must write, relative to the working directory); the groups run in one directory each
QUICKEST = {
    "demo": [(["demo", "--no-gif"], ["results/demo-learned/demo.png"]),  # the wrench's learned term: the default
             (["demo", "--no-gif", "--paper"], ["results/demo/demo.png"])],
    "your-model": [(["check-model", "hammer", "--quick"], []),
                   (["demo", "--no-gif", "--model", "hammer"], ["results/demo-hammer-learned/demo.png"]),
                   (["import-hand", str(ROOT / "models" / "allegro" / "hand.xml"), "imported"], ["imported/hand.xml"])],
    # issue 83: a tool check-model accepts goes through every command that draws episodes (a round grip 2 cm across)
    "narrow-tool": [(["check-model", "screwdriver", "--quick"], []),
                    (["surrogate", "--model", "screwdriver", "--waypoints", "0"], []),
                    (["corpus", "--model", "screwdriver", "--shards", "1", "--episodes", "3", "--random", "1",
                      "--perturbed", "1", "--steps", "2"], ["results/corpus-screwdriver/manifest.json"]),
                    (["calibrate", "--learn", "--model", "screwdriver", "--shards", "1", "--episodes", "3",
                      "--epochs", "2", "--out", "w.npz"], ["w.npz"]),
                    (["envelope", "--model", "screwdriver", "--set", "stress", "--episodes", "1", "--random", "0",
                      "--policies", "four-tips", "dp-opt"], ["results/envelope-screwdriver/stress.json"]),
                    (["demo", "--no-gif", "--model", "screwdriver"], ["results/demo-screwdriver/demo.png"])],  # no term

    "hands": [(["hands", "--models", "screwdriver", "--episodes", "1", "--k", "1"],
               ["results/hands-learned/hands.json", "results/envelope-screwdriver/variations.json"])],
    "planners": [(["planners"], [])],
    "figures": [(["figures", "--list"], []), (["figures", "--stale"], [])],
    "surrogate": [(["surrogate", "--episode", "nominal", "--waypoints", "0"], [])],
    "bench-startup": [(["bench-startup", "--no-off", "--out", "s.json"], ["s.json"])],
    "bench-surrogate": [(["bench-surrogate", "--loop-steps", "17", "--repeats", "1", "--out", "b.json"], ["b.json"])],
    "bench-search": [(["bench-search", "--episodes", "2", "--widths", "4", "--timed", "1", "--out", "b.json"],
                      ["b.json"])],
    "bench-dp": [(["bench-dp", "--episodes", "2", "--loop-steps", "17", "--repeats", "1", "--out", "b.json"],
                  ["b.json"])],
    "bench-gym": [(["bench-gym", "--envs", "4", "--sync-max", "4", "--seconds", "1"], [])],
    "bench-scale": [(["bench-scale", "--processes", "1", "--cores-each", "1", "--episodes", "1", "--chunk", "1",
                      "--tables", "1", "--batch", "1", "--envs", "8", "--iterations", "1", "--steps", "2"],
                     ["results/bench-scale-learned/processes1.json"])],
    "dp": [(["dp", "--set", "nominal"], [])],
    "train": [(["train", "--preset", "quick", "--seeds", "1", "--iterations", "1", "--envs", "16", "--paper"],
               ["results/train/dp/seed0/history.json"]),
              (["train-curves", "--paper"], ["results/train/curves.json"])],
    "bench-ppo": [(["bench-ppo", "--preset", "quick", "--max-iterations", "1"], [])],
    "physics": [(["physics", "--set", "nominal", "--policy", "four-tips", "--backend", "c"],
                 ["results/physics-learned/nominal_four-tips_c.json"]),
                (["physics", "--set", "nominal", "--policy", "four-tips", "--backend", "mjx"],
                 ["results/physics-learned/nominal_four-tips.json"]),
                (["physics", "--set", "nominal", "--compare", "four-tips"],
                 ["results/physics-learned/nominal_agreement.json"]),
                (["--processes", "2", "physics", "--set", "nominal", "--policy", "scripted", "--backend", "c",
                  "--chunk", "2", "--paper"], ["results/physics/nominal_scripted_c.json"])],
    "bench-physics": [(["bench-physics", "--set", "nominal", "--waypoints", "2", "--backends", "c", "--cores", "1",
                        "--variant", "paper"], [])],
    "envelope": [(["envelope", "--set", "eval", "--episodes", "1", "--random", "0", "--physics-lookahead", "1",
                   "--bases", "four-tips", "--paper"], ["results/envelope/eval.json"]),
                 (["envelope", "--set", "eval", "--episodes", "1", "--random", "0", "--policies", "four-tips",
                   "--paper", "--world", "gap"], ["results/envelope-gap/eval.json"])],
    "world-parts": [(["world-parts", "--episodes", "1", "--policies", "four-tips", "--paper"],
                     ["results/world-parts/eval_gap.json"])],
    "rescore": [(["rescore", "--episodes", "2", "--reward", "grip=0,fall_unmet=0.2"],
                 ["results/rescore-learned/stress.json", "results/rescore-learned/stress.png"])],
    "calibrate": [(["calibrate", "--sets", "nominal", "--random", "1", "--backend", "c"],
                   ["results/calibrate/sweep.json"]),
                  (["calibrate", "--tune", "--model", "testhand", "--subset", "2", "--grid", "rotation_step=0.3,1"],
                   ["results/calibrate-controller-testhand/sweep.json"])],
    "corpus": [(["corpus", "--shards", "1", "--episodes", "3", "--random", "1", "--perturbed", "1", "--steps", "2"],
                ["results/corpus/manifest.json", "results/corpus/shard-000000.npz"]),
               (["calibrate", "--learn", "--shards", "1", "--episodes", "3", "--epochs", "2", "--out", "w.npz"],
                ["w.npz", "results/learn/report.json"]),  # its corpus run nested (`cli.run_command`): shard 0 held
               (["corpus", "--learned", "--shards", "1", "--episodes", "2", "--random", "1", "--perturbed", "0",
                 "--steps", "2"], ["results/corpus-learned/shard-000000.npz"]),  # the learned planners' sequences
               (["envelope", "--set", "eval", "--episodes", "1", "--random", "0", "--physics-lookahead", "0",
                 "--learned"],
                ["results/envelope-learned/eval.json"])],
    "fig4a": [(["fig4a", "--set", "evalA", "--episodes", "2", "--paper"], ["results/fig4a/returns.json"])],
    "fig4b": [(["fig4b", "--set", "evalA", "--episodes", "1", "--backend", "c", "--policies", "dp-base", "rl",
                "L1-physics", "--k", "1", "--bases", "four-tips", "--paper"],
               ["results/fig4b/rl.json", "results/fig4b/L1-physics.json"])],
    "table1": [(["table1", "--set", "evalA", "--repeats", "1", "--policies", "dp-base", "--paper"], []),
               (["table1", "--per-decision", "--episodes", "1", "--policies", "dp-base", "dp-opt", "L1-physics", "--k",
                 "1", "--bases", "four-tips", "--paper"], ["results/bench_latency/cpu.json"])],
    "ik-spikes": [(["ik-spikes", "--set", "nominal"], [])],
    "precision": [(["precision", "--episodes", "nominal", "--isa", "--ulp", "1", "--no-float64"], [])],
    "reproduce": [(["reproduce", "--report-only", "--out", "report"], ["report/REPORT.md"])],
}


def test_every_command_has_a_quickest_form():
    from experiments.cli import COMMANDS

    covered = {line[2] if line[0] == "--processes" else line[0] for group in QUICKEST.values() for line, _ in group}
    assert covered == set(COMMANDS), sorted(set(COMMANDS) ^ covered)


@pytest.mark.commands
@pytest.mark.timeout(3600)
@pytest.mark.parametrize("group", sorted(QUICKEST))
def test_command_runs_in_its_quickest_form(group, tmp_path):
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)  # keeps the caller's
    env = dict(os.environ, PYTHONPATH=path, GSP_JAX_CACHE=os.environ.get("GSP_JAX_CACHE", "off"))
    if group == "reproduce":  # --report-only rebuilds the committed report's REPORT.md from its report.json
        (tmp_path / "report").mkdir()
        (tmp_path / "report" / "report.json").write_bytes((ROOT / "docs/report/report.json").read_bytes())
    for line, files in QUICKEST[group]:
        run = subprocess.run([sys.executable, "-m", "experiments", *line], cwd=tmp_path, env=env,
                             capture_output=True, text=True)
        assert run.returncode == 0, f"{' '.join(line)} failed:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
        for f in files:
            assert (tmp_path / f).is_file(), f"{' '.join(line)} did not write {f}"
