"""Tests of experiments/physics/rescore.py: a recorded pool's sequences rescored step by step equal their returns
replayed in the DP table (`calibration.candidate_tables`, itself tested against `dp.build_table`: the table scores
every (grasp, action, waypoint) through its own path), under the calibrated reward and a variant; bad --reward and
--pool inputs are named."""
from __future__ import annotations

import dataclasses
import json
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import tolerances as tol  # noqa: E402
from experiments.physics import rescore  # noqa: E402
from gsp_jax.physics import calibration  # noqa: E402
from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.surrogate import step as surrogate  # noqa: E402
from gsp_jax.surrogate.reward import RewardConfig  # noqa: E402


def test_rescored_returns_equal_the_tables_replay():
    ep = scenario.eval_set_b()["mass1.5m0_comy+1cm"].head(3)
    batch = scenario.stack([ep])
    sur = surrogate.Surrogate(learned=False)
    start = int(ep.start_grasp)
    space = sur.space
    # sequences as `envelope` records them (the grasp after each decision): hold, change and come back, a lone tip
    lone = int(space.encode(np.array([0, 1, 0, 0, 0, 0])))
    other = int(space.apply(jnp.int32(start), jnp.int32(3))[0])
    grasps = np.array([[[start] * 3], [[other, start, start]], [[lone] * 3]], np.int32)  # (G, N, T)
    keys, index, changed = rescore.step_states(sur, np.asarray(batch.start_grasp), grasps)
    contacts = rescore.realise_states(sur, batch, keys, 64)
    # the two candidates of test_calibrate (the same programs: the run's compilation cache serves both tests)
    base = RewardConfig()
    configs = [dataclasses.replace(base, grip=0.0, grip_scales_with_mass=False, fall_unmet=0.3, w_wrench_change=0.0,
                                   change_falls=False),
               dataclasses.replace(base, grip=2.0, grip_scales_with_mass=True, fall_unmet=0.2, w_wrench_change=5.0,
                                   change_falls=True)]
    tables = calibration.candidate_tables(configs, batch)
    for reward, tab in zip(configs, tables):
        returns, feasible = rescore.score_pool(reward, sur.hand, batch, contacts, index, changed, 7)
        table = jax.tree.map(lambda x: x[0], tab)
        for g in range(grasps.shape[0]):
            actions, prev = [], start
            for x in grasps[g, 0]:
                opts_p, opts_n = np.asarray(space.decode(prev)), np.asarray(space.decode(int(x)))
                link = np.flatnonzero(opts_p != opts_n)
                actions.append(0 if not len(link) else space.action(space.link_names[link[0]], int(opts_n[link[0]])))
                prev = int(x)
            rewards = np.asarray(dp.sequence_rewards(table, jnp.int32(start), jnp.asarray(actions, jnp.int32)))
            np.testing.assert_allclose(returns[g, 0], rewards.sum(), atol=4 * tol.REWARD_ATOL)
            assert feasible[g, 0] == bool(np.all(rewards > reward.r_min)), (g, rewards)
    assert not feasible[2, 0]  # a lone index tip drops the tool


def test_bad_inputs_are_named(tmp_path):
    base = RewardConfig()
    parsed = rescore.parse_reward("grip=8, change_falls=false", base)
    assert parsed.grip == 8.0 and parsed.change_falls is False and base.change_falls is True
    with pytest.raises(SystemExit, match="squeeze"):  # a field the reward no longer has
        rescore.parse_reward("squeeze=8", base)
    with pytest.raises(SystemExit, match="change_falls takes true or false"):
        rescore.parse_reward("change_falls=maybe", base)
    with pytest.raises(SystemExit, match="RewardConfig.grip"):
        rescore.parse_reward("grip=-1", base)
    with pytest.raises(SystemExit, match="no envelope result"):
        rescore.load_pool(str(tmp_path / "none.json"), None)
    (tmp_path / "x.json").write_text(json.dumps({"set": "stress"}))
    with pytest.raises(SystemExit, match="not an envelope result"):
        rescore.load_pool(str(tmp_path / "x.json"), None)
