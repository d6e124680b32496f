"""Tests of the planner registry (`gsp_jax.planners.registry`): every planner of the project is registered, builders are
checked when they register and when they are made, and a planner written outside the package runs through the
commands (`--plugin`): `planners`, `fig4b` and `envelope` in C MuJoCo."""
from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gsp_jax.planning import evaluation
from gsp_jax.planners import registry as planners
from gsp_jax.model import scenario

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROJECT = ("dp-base", "rl", "L1", "L2", "dp-opt", "four-tips", "one-tip", "random", "L1-physics", "search",
           "search-L1")

PLUGIN = '''
import jax.numpy as jnp
from gsp_jax.planners import registry as planners
from gsp_jax.planning import policies


@planners.register("keep-start")
def keep_start(ctx, *, action: int = 0):
    """Keep the start grasp: `action` (the null action, 0) at every step."""
    return policies.SequencePolicy(jnp.full(ctx.batch.n_steps, action, jnp.int32), ctx.surrogate.space), None
'''


def test_every_planner_of_the_project_is_registered():
    assert planners.names() == PROJECT
    assert planners.names("paper") == ("dp-base", "rl", "L1", "L2", "dp-opt")  # Table 1's order
    assert planners.get("L1-physics").backends == ("c",)
    assert planners.needs(["dp-opt", "random"]) == {"solutions", "tables"}
    assert planners.needs("L1") == {"base", "tables"}  # cached by default: its tree reads the tables
    assert planners.context_flags(["four-tips"]) == dict(tables=False, rl=False, nominal=False)
    assert planners.context_flags(["dp-base"]) == dict(tables=False, rl=False, nominal=True)


def test_a_builder_is_checked_when_it_registers():
    with pytest.raises(ValueError, match="keyword-only with defaults"):
        planners.register("bad-options")(lambda ctx, k: None)
    with pytest.raises(ValueError, match="keyword-only with defaults"):
        planners.register("bad-default")(lambda ctx, *, k: None)
    with pytest.raises(ValueError, match="needs one of"):
        planners.register("bad-needs", needs=("everything",))
    with pytest.raises(ValueError, match="'four-tips' is taken by gsp_jax.planners.registry"):
        planners.register("four-tips")(lambda ctx: None)
    with pytest.raises(ValueError, match="without spaces"):
        planners.register("my planner")
    assert "bad-options" not in planners.names()


def test_make_names_options_and_what_the_context_lacks(sur):
    ctx = evaluation.context("nominal", tables=False, rl=False, nominal=False)
    policy, axis = planners.make(ctx, "four-tips")
    assert axis is None
    np.testing.assert_array_equal(np.asarray(policy.actions), evaluation.four_tips(sur.space))
    with pytest.raises(ValueError, match=r"planner 'four-tips': no option 'k' \(its options: none\)"):
        planners.make(ctx, "four-tips", k=2)
    planners.make(ctx, "four-tips", dict(k=2, cached=False))  # shared options go only where they are taken
    with pytest.raises(ValueError, match="planner 'dp-opt': the context was built without solutions"):
        planners.make(ctx, "dp-opt")
    with pytest.raises(ValueError, match="planner 'L1': the context was built without base or tables"):
        planners.make(ctx, "L1")
    with pytest.raises(ValueError, match=r"planner: 'mine' is not registered; registered: dp-base, .*--plugin"):
        planners.make(ctx, "mine")


def _run(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    run = subprocess.run([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env, capture_output=True,
                         text=True)
    assert run.returncode == 0, f"{args} failed:\n{run.stdout[-3000:]}\n{run.stderr[-3000:]}"
    return run.stdout


def test_a_planner_from_outside_the_package_runs_through_the_commands(tmp_path):
    (tmp_path / "mine.py").write_text(PLUGIN)
    listed = _run(["planners", "--plugin", "mine"], tmp_path)
    assert "keep-start" in listed and "action=0" in listed and "Keep the start grasp" in listed
    _run(["fig4b", "--plugin", "mine", "--set", "evalA", "--episodes", "1", "--backend", "c",
          "--policies", "keep-start", "four-tips", "--paper"], tmp_path)
    result = json.loads((tmp_path / "results/fig4b/keep-start.json").read_text())
    assert result["policy"] == "keep-start" and len(result["per_episode"]) == 1
    start = int(scenario.eval_set_a()[result["episodes"][0]].start_grasp)
    assert set(result["per_episode"][0]["grasps"]) == {start}  # it kept the start grasp throughout, in physics
    _run(["envelope", "--plugin", "mine", "--set", "eval", "--episodes", "1", "--random", "0",
          "--policies", "keep-start", "four-tips", "--paper"], tmp_path)
    kinds = json.loads((tmp_path / "results/envelope/eval.json").read_text())["kinds"]
    assert kinds == ["keep-start", "four-tips"]
    bad = subprocess.run([sys.executable, "-m", "experiments", "fig4b", "--policies", "keep-start", "--paper"],
                         cwd=tmp_path,
                         env=dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu"), capture_output=True,
                         text=True)
    assert bad.returncode != 0 and "--policies: planner: 'keep-start' is not registered" in bad.stderr, bad.stderr


@pytest.fixture(scope="module")
def small_context(sur, solve_each):
    """Two evaluation episodes cut to 6 waypoints, their DP tables, solutions and DP baseline (no PPO policy)."""
    a = scenario.eval_set_a()
    names = ["shift+4mm_-1Nm", "shift-6mm_+1Nm"]
    eps = scenario.stack([a[n].head(6) for n in names])
    tables, sols = solve_each(sur, eps)
    return evaluation.Context(sur, "test", names, eps, tables, sols, sols.actions[0], None, "")


def test_a_plan_is_the_planners_episode_in_its_table(small_context):
    """`planners.plan` (the public `gsp.plan`): DP optimal's plan is the DP solution (its return the Bellman
    optimum, its actions the optimal sequence while the episode lasts); every plan's return is what `returns` (a
    while loop, not a scan) gives and what `dp.sequence_return` scores its actions at; keeping the grasp after the
    end, and `changes` lists only the non-null actions."""
    from gsp_jax.planning import dp
    from gsp_jax.model.grasps import NULL

    ctx = small_context
    opt = planners.plan(ctx, "dp-opt")
    np.testing.assert_allclose(np.asarray(opt.ret), np.asarray(ctx.solutions.ret), atol=1e-5)
    assert opt.actions.shape == (2, 6) and opt.rewards.shape == (2, 6) and opt.episodes == ctx.names
    for name in ("dp-opt", "dp-base", "four-tips"):
        p = planners.plan(ctx, name)
        np.testing.assert_allclose(np.asarray(p.ret), np.asarray(planners.returns(ctx, name)), atol=1e-5)
        for i in range(2):
            table = jax.tree.map(lambda x, i=i: x[i], ctx.tables)
            scored = dp.sequence_return(table, ctx.batch.start_grasp[i], jnp.asarray(p.actions[i]))
            np.testing.assert_allclose(float(scored), float(p.ret[i]), atol=1e-5)
            acts = np.asarray(p.actions[i])
            assert len(p.changes(i)) == int(np.sum(acts != NULL))
    with pytest.raises(ValueError, match="backend must be 'table' or 'surrogate', got 'mjx'"):
        planners.plan(ctx, "dp-opt", backend="mjx")
