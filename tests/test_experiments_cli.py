"""`python -m experiments`'s set-up before JAX starts: XLA's GPU autotuner is off for every command but training's,
and a level the user set in XLA_FLAGS wins."""
from __future__ import annotations

import os
import pathlib

import pytest

from experiments import cli

LEVEL = "--xla_gpu_autotune_level"


@pytest.mark.parametrize("command", ["fig4b", "table1", "physics", "reproduce", None])
def test_evaluation_commands_pick_gpu_kernels_by_heuristics(monkeypatch, command):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=SSE4_2")
    cli.deterministic_gpu_kernels(command)
    assert os.environ["XLA_FLAGS"].split() == ["--xla_cpu_max_isa=SSE4_2", f"{LEVEL}=0"]


@pytest.mark.parametrize("command", cli.AUTOTUNED)
def test_training_keeps_the_autotuner(monkeypatch, command):
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    cli.deterministic_gpu_kernels(command)
    assert LEVEL not in os.environ.get("XLA_FLAGS", "")


def test_a_level_the_user_set_wins(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", f"{LEVEL}=4")
    cli.deterministic_gpu_kernels("fig4b")
    assert os.environ["XLA_FLAGS"] == f"{LEVEL}=4"


def test_every_autotuned_command_exists():
    assert set(cli.AUTOTUNED) <= set(cli.COMMANDS)


@pytest.mark.parametrize("option", ["--ik-unroll", "--ahead"])
@pytest.mark.parametrize("value", ["0", "-2", "three"])
def test_table1_rejects_a_count_below_one_by_name(monkeypatch, capsys, option, value):
    """`table1 --ik-unroll` (the IK's iterations per loop trip) and `--ahead` (batched RL's decisions per batch of
    realised states): anything but an integer >= 1 stops at the command line with the option and the value named,
    before any work starts."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setenv("GSP_JAX_CACHE", "off")
    with pytest.raises(SystemExit) as exit_:
        cli.main(["table1", option, value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert option in err and repr(value) in err, err


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_every_command_imports_and_describes_itself(monkeypatch, capsys, command):
    """`python -m experiments <command> --help` for every command: its module imports on a fresh clone, its options
    build, and its help names it (the CLI imports only the module of the command it runs)."""
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    with pytest.raises(SystemExit) as stop:
        cli.main([command, "--help"])
    assert stop.value.code == 0
    assert f"python -m experiments {command}" in capsys.readouterr().out


def test_the_command_list_describes_every_command(monkeypatch, capsys):
    """`python -m experiments --help` lists every command with its one-line help (a '%' in a help line, as in
    '95% CI', once broke it: argparse formats help strings)."""
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    monkeypatch.setenv("COLUMNS", "400")  # one line per command (argparse wraps at the terminal's width)
    with pytest.raises(SystemExit) as stop:
        cli.main(["--help"])
    assert stop.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    for command, (_, help_) in cli.COMMANDS.items():
        assert command in out and " ".join(help_.split()) in out, command


def test_every_command_lives_in_its_group():
    """The experiments are grouped by what they are: the paper's runs, benchmarks, the physics studies and
    diagnostics (the demo alone at the top)."""
    for command, (module, _) in cli.COMMANDS.items():
        group = module.split(".")[1]
        assert group in ("paper", "bench", "physics", "diagnostics") or module == "experiments.demo", (command, module)
        if command.startswith("bench-"):
            assert group == "bench", command


def test_a_commands_model_is_handed_down_and_left_behind_nowhere(monkeypatch, capsys):
    """`--model` becomes the `Model` of the command's run (`run.model`), and a command run by another
    (`cli.run_command(words, run)`) inherits it; nothing of it stays in the process after the command (no
    process-wide model), and the command's `args` no longer hold the option."""
    from experiments import common
    from gsp_jax.model import load as model_lib

    seen = []

    def main(args, run):
        seen.append(run.model)
        assert "model" not in args and "learned" not in args  # the run holds them, not `args`
        if len(seen) == 1:
            cli.run_command(["planners"], run)

    monkeypatch.setattr("experiments.diagnostics.planners.main", main)
    cli.main(["planners", "--model", "hammer"])
    assert "model: hammer" in capsys.readouterr().out
    assert [m.name for m in seen] == ["hammer", "hammer"]  # the command, and the one it ran
    assert not any(isinstance(v, model_lib.Model) for v in vars(common).values())  # no model kept in the module
    assert model_lib.load_model().name == model_lib.DEFAULT
    cli.main(["planners"])
    assert seen[-1].name == model_lib.DEFAULT


def test_learned_is_the_default_where_weights_exist_and_handed_down(monkeypatch, capsys, tmp_path):
    """Issue 83: a command plans with the learned physics term where the model has weights (the wrench does; the
    screwdriver does not), `--paper` without it, `--learned` with it or refused; a command run by another inherits
    its run's choice; the corpus (the term's own data) plans without it unless asked. `Surrogate(model)` alike:
    the term where the model has weights, `learned=False` the paper's surrogate."""
    from gsp_jax.surrogate.step import Surrogate

    seen = []

    def main(args, run):
        seen.append((run.learned, run.results_dir().name))
        assert "paper" not in args and "learned" not in args
        if len(seen) == 1:
            cli.run_command(["planners"], run)

    monkeypatch.setattr("experiments.diagnostics.planners.main", main)
    monkeypatch.setattr("experiments.common.RESULTS", tmp_path / "results")
    cli.main(["planners"])
    assert "learned physics term:" in capsys.readouterr().out
    assert seen == [(True, "learned"), (True, "learned")]  # the command, the one it ran
    seen.clear()
    cli.main(["planners", "--paper"])
    assert seen == [(False, "results"), (False, "results")]
    seen.clear()
    cli.main(["planners", "--model", "screwdriver"])  # no weights: the paper's surrogate, said by check-model
    assert seen[0] == (False, "screwdriver")
    with pytest.raises(SystemExit, match="screwdriver.*no learned physics term"):
        cli.main(["planners", "--model", "screwdriver", "--learned"])
    with pytest.raises(SystemExit, match="one or the other"):
        cli.main(["planners", "--learned", "--paper"])
    assert Surrogate().learned is not None and Surrogate(learned=False).learned is None
    assert Surrogate("screwdriver").learned is None
    monkeypatch.setattr("experiments.physics.corpus.main", lambda args, run: seen.append((run.learned, "corpus")))
    cli.main(["corpus"])
    assert seen[-1] == (False, "corpus")  # the term's own data: the analytic surrogate's plans


def test_record_and_its_command_are_handed_down_and_left_behind_nowhere(monkeypatch, tmp_path):
    """`--record` and the words a record names ride on the run: a command run by another records too, naming the
    outermost command (or the one its pipeline names, as `figures` does); the next command of the process, without
    --record, records nothing (no process-wide switch)."""
    import dataclasses

    from experiments import common

    rows = []

    def main(args, run):
        rows.append(run.record_figures("bench_x", {"n": len(rows)}, data=tmp_path))
        if len(rows) == 1:
            cli.run_command(["planners"], run)
            cli.run_command(["planners"], dataclasses.replace(run, command=("--record", "planners", "--plugin", "x")))

    monkeypatch.setattr("experiments.diagnostics.planners.main", main)
    monkeypatch.setattr(common, "device_slug", lambda: "cpu")
    cli.main(["--record", "planners"])
    assert [r["command"] for r in rows] == ["python -m experiments --record planners"] * 2 + [
        "python -m experiments --record planners --plugin x"]
    assert [r["figures"] for r in rows] == [{"n": 0}, {"n": 1}, {"n": 2}]
    history = (tmp_path / "history" / "bench_x_learned_cpu.jsonl").read_text().splitlines()  # the wrench's term
    assert len(history) == 3
    cli.main(["planners"])
    assert rows[-1] is None and len((tmp_path / "history" / "bench_x_learned_cpu.jsonl").read_text().splitlines()) == 3
    assert common.Run().record_figures("bench_x", {}, data=tmp_path) is None  # a run without --record


def test_no_module_of_the_commands_keeps_state():
    """No module of experiments/ declares a `global` or keeps the run in module-level names (`Run` is handed
    down instead)."""
    import ast

    root = pathlib.Path(cli.__file__).parent
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text())
        assert not any(isinstance(node, (ast.Global, ast.Nonlocal)) for node in ast.walk(tree)), path
        names = {t.id for node in tree.body if isinstance(node, (ast.Assign, ast.AnnAssign))
                 for t in (node.targets if isinstance(node, ast.Assign) else [node.target]) if isinstance(t, ast.Name)}
        assert not names & {"MODEL", "RECORD", "COMMAND", "LEARNED"}, (path, names)


def test_the_surrogate_commands_grasps_fit_any_number_of_contact_links(small_model):
    """Issue 83: `python -m experiments surrogate --model` crashed on any model without the paper hand's six
    contact links (its grasps were written for them): another model gets the same kinds of grasps built from its
    own links, each a valid grasp of its space, each once; the paper's hand keeps its six."""
    from experiments.diagnostics import surrogate as command
    from gsp_jax.model import grasps, load as model_lib

    paper = grasps.space_of(model_lib.load_model("wrench").hand)
    assert command.grasps_of(paper) == command.GRASPS
    space = grasps.space_of(small_model.hand)
    shown = command.grasps_of(space)
    options = [o for _, o in shown]
    assert len(shown) >= 3 and len(set(options)) == len(options)
    for _, o in shown:
        assert len(o) == space.n_links and all(0 <= k < n for k, n in zip(o, space.n_options))
        assert 0 <= int(space.encode(o)) < space.n_grasps
    assert sum(1 for k in options[0] if k) == 1  # one contact alone


def test_controller_is_chosen_handed_down_and_names_results_and_records(monkeypatch, tmp_path):
    """Issue 84: `--controller paper` gives a simulating command the paper's controller's `PhysicsConfig`, results
    under results/<part>-paper and records named _paper; a command it runs inherits it; the default is the
    measured frames' (no suffix); a command that does not simulate has no such option."""
    from experiments import common

    seen = []

    def main(args, run):
        assert "controller" not in args
        seen.append((run.controller, run.physics_config().controller_name, run.results_dir("envelope").name,
                     run.record_figures("bench_x", {"n": 1}, data=tmp_path)["name"]))
        if len(seen) == 1:
            cli.run_command(["envelope"], run)

    monkeypatch.setattr("experiments.physics.envelope.main", main)
    monkeypatch.setattr(common, "RESULTS", tmp_path / "results")
    monkeypatch.setattr(common, "device_slug", lambda: "cpu")
    cli.main(["--record", "envelope", "--paper", "--controller", "paper"])
    assert seen == [("paper", "paper", "envelope-paper", "bench_x_paper_cpu")] * 2
    seen.clear()
    cli.main(["--record", "envelope", "--paper"])
    assert seen[0] == ("measured", "measured", "envelope", "bench_x_cpu")
    with pytest.raises(SystemExit):
        cli.main(["planners", "--controller", "paper"])
