"""`python -m experiments`'s set-up before JAX starts: XLA's GPU autotuner is off for every command but training's,
and a level the user set in XLA_FLAGS wins."""
from __future__ import annotations

import os

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
    """`--model` becomes the `Model` the command is given (`args.model`), and a command run by another inherits
    it; nothing of it stays in the process after the command (no process-wide model)."""
    from experiments import common
    from gsp_jax.model import load as model_lib

    seen = []
    monkeypatch.setattr("experiments.diagnostics.planners.main", lambda args: seen.append(args.model)
                        or (len(seen) == 1 and cli.run_command(["planners"])))
    cli.main(["planners", "--model", "hammer"])
    assert "model: hammer" in capsys.readouterr().out
    assert [m.name for m in seen] == ["hammer", "hammer"]  # the command, and the one it ran
    assert common.MODEL is None and model_lib.load_model().name == model_lib.DEFAULT
    cli.main(["planners"])
    assert seen[-1].name == model_lib.DEFAULT


def test_learned_is_handed_down_and_left_behind_nowhere(monkeypatch, capsys):
    """`--learned` becomes `args.learned`, which a command run by another inherits; no surrogate built outside
    the command has the learned term, during or after (no process-wide default)."""
    from experiments import common
    from gsp_jax.surrogate.step import Surrogate

    seen = []

    def main(args):
        seen.append((args.learned, common.learned_on(), Surrogate(args.model).learned is None))
        if len(seen) == 1:
            cli.run_command(["planners"])

    monkeypatch.setattr("experiments.diagnostics.planners.main", main)
    cli.main(["planners", "--learned"])
    assert "learned physics term:" in capsys.readouterr().out
    assert seen == [(True, True, True), (True, True, True)]  # the command, the one it ran; Surrogate() stays off
    assert common.LEARNED is False and not common.learned_on()
    cli.main(["planners"])
    assert seen[-1] == (False, False, True)
    assert Surrogate(learned=True).learned is not None  # the shipped wrench's weights, asked for by name
