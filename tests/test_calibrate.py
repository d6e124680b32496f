"""Tests of the calibration (`gsp_jax.physics.calibration`, the `calibrate` command): the candidate tables (IK shared
by all candidates, wrench solves by each grip) equal `dp.build_table` under each candidate's own surrogate; the winner
is the fewest DP-optimal falls, then the highest correlation; the evaluation episodes are refused."""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import dataclasses  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import tolerances as tol  # noqa: E402
from experiments import common  # noqa: E402
from experiments.physics import calibrate  # noqa: E402
from gsp_jax.physics import calibration  # noqa: E402
from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.surrogate import reward, step as surrogate  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.surrogate.reward import RewardConfig  # noqa: E402


def test_candidate_tables_equal_each_candidates_own_table(table_ik):
    """Two candidates that differ in every calibrated field (grip, its mass scaling, fall threshold, change term) on
    a 3-waypoint episode: the second's shared-IK table equals `dp.build_table` of a surrogate built with its config
    (the wrench terms of the other grip, or its reward settings, would not; one own table keeps the test's compile
    time down), and the two candidates' tables differ where their settings do."""
    base = RewardConfig()
    configs = [dataclasses.replace(base, grip=0.0, grip_scales_with_mass=False, fall_unmet=0.3, w_wrench_change=0.0,
                                   change_falls=False),
               dataclasses.replace(base, grip=2.0, grip_scales_with_mass=True, fall_unmet=0.2, w_wrench_change=5.0,
                                   change_falls=True)]
    ep = scenario.eval_set_b()["mass1.5m0_comy+1cm"].head(3)
    tables = calibration.candidate_tables(configs, scenario.stack([ep]))
    cfg, tab = configs[1], tables[1]
    own = jax.jit(lambda e: dp.build_table(surrogate.Surrogate(reward=cfg, ik_config=table_ik, learned=False), e))(ep)
    np.testing.assert_array_equal(np.asarray(tab.next_grasp[0]), np.asarray(own.next_grasp))
    tol.assert_close_with_rare_ties(np.asarray(tab.reward[0]).ravel(), np.asarray(own.reward).ravel(),
                                    tol.REWARD_ATOL, f"reward {calibration.label(cfg)}")
    # the candidates do differ: the change term and the stricter threshold fail more transitions
    r0, r1 = (np.asarray(t.reward[0]) for t in tables)
    assert (r1 == base.r_min).sum() > (r0 == base.r_min).sum()


def _sweep(rows):
    results = [dict(label=f"c{i}", spearman=rho, feasible=10, feasible_held=0.5, dp_opt_falls=falls,
                    dp_opt_angle=90.0, dp_opt_changes=2.0, config=dataclasses.asdict(RewardConfig()))
               for i, (rho, falls) in enumerate(rows)]
    return dict(sweep=results, episodes=["a", "b"], sets=["train"], backend="c", sequences=40,
                best_spearman=max(r for r, _ in rows if r == r), best_spearman_se=0.02, best_spearman_label="c0",
                rows=[[r["label"], r["spearman"], 10, 0.5, r["dp_opt_falls"], 90.0, 2.0] for r in results])


def test_winner_is_fewest_dp_optimal_falls_then_highest_rho(capsys):
    # a candidate with no feasible sequence (no correlation) never wins, however few its DP plans' falls
    assert calibrate.choose_and_write(_sweep([(0.5, 2), (0.4, 1), (0.45, 1), (float("nan"), 0)]),
                                      False)["label"] == "c2"
    assert calibrate.choose_and_write(_sweep([(0.5, 2), (0.4, 3)]), False)["label"] == "c0"
    assert "chosen" in capsys.readouterr().out


def test_incumbent_stays_unless_the_challenger_falls_significantly_less(capsys):
    """The incumbent (today's calibration, by its label) keeps its place against a challenger whose DP plans hold
    3 episodes more of 20 (p 0.25), and gives it up to one that holds 9 more and loses none (p 0.004)."""
    incumbent = calibration.label(RewardConfig())

    def sweep(challenger_fell):
        s = _sweep([(0.5, sum(challenger_fell)), (0.3, 12)])
        s["sweep"][1]["label"] = s["rows"][1][0] = incumbent
        s["sweep"][0]["dp_opt_fell"] = challenger_fell
        s["sweep"][1]["dp_opt_fell"] = [True] * 12 + [False] * 8
        s["episodes"] = [f"e{i}" for i in range(20)]
        return s

    assert calibrate.choose_and_write(sweep([True] * 9 + [False] * 11), False)["label"] == incumbent
    assert calibrate.choose_and_write(sweep([True] * 3 + [False] * 17), False)["label"] == "c0"
    assert "sign test" in capsys.readouterr().out


def test_evaluation_episodes_are_refused():
    args = argparse.Namespace(from_sweep=None, sets="train,eval", random=1, backend="c", seed=0, chunk=8, write=False)
    with pytest.raises(SystemExit, match="never uses the evaluation episodes"):
        calibrate.main(args, common.Run())


def test_write_targets_the_librarys_calibration_file(tmp_path, monkeypatch):
    """`calibrate --write` writes the chosen row to the data file `RewardConfig` reads its defaults from
    (`reward.CALIBRATION_JSON`): read back, the calibrated fields are the row's and the figures the sweep's."""
    assert calibrate.CALIBRATION_JSON == reward.CALIBRATION_JSON and calibrate.CALIBRATION_JSON.is_file()
    chosen = dataclasses.replace(RewardConfig(), grip=2.0, grip_scales_with_mass=False, fall_unmet=0.2,
                                 w_wrench_change=1.0, change_falls=False)
    row = dict(config=dataclasses.asdict(chosen), spearman=0.41234, feasible_held=0.7, dp_opt_falls=3,
               dp_opt_changes=2.345)
    summary = dict(sets=["train", "val"], backend="c", sequences=40, episodes=["a", "b"], best_spearman=0.5,
                   best_spearman_se=0.02)
    monkeypatch.setattr(calibrate, "CALIBRATION_JSON", tmp_path / "cal.json")
    calibrate.write_calibration(row, summary)
    values, measured = reward.read_calibration(tmp_path / "cal.json")
    assert values == dict(grip=2.0, grip_scales_with_mass=False, fall_unmet=0.2, w_wrench_change=1.0,
                          change_falls=False)
    assert measured["sets"] == "train+val" and measured["spearman"] == 0.412 and measured["dp_opt_falls"] == 3
    assert measured["episodes"] == 2


def test_a_learned_term_that_ranks_worse_is_not_installed():
    """Issue 83: the planner that holds is the default, so `calibrate --learn` installs a term beside its scene only
    where, on the test split, the return with it ranks hold against fall at least as well as without it; a split
    with no hold or no fall (AUC undefined) installs nothing."""
    assert calibrate.installs(dict(auc_return_learned=0.913, auc_return_analytic=0.606))
    assert calibrate.installs(dict(auc_return_learned=0.7, auc_return_analytic=0.7))
    assert not calibrate.installs(dict(auc_return_learned=0.38, auc_return_analytic=0.617))
    assert not calibrate.installs(dict(auc_return_learned=float("nan"), auc_return_analytic=float("nan")))
    assert not calibrate.installs(dict(auc_return_learned=0.9, auc_return_analytic=float("nan")))
