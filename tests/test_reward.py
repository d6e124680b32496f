"""Tests of gsp_jax.surrogate.reward: the calibration file (read, refused when missing or malformed, written and read
back), the reward of a step's terms against a plain numpy reference, the previous grasp's part (the start support, the
change term's fall check, the motor check), and the table's transitions against the step's function applied one
transition at a time."""
from __future__ import annotations

import dataclasses
import json
import os
import types

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax.surrogate import reward  # noqa: E402
from gsp_jax.surrogate.reward import CalibrationError, RewardConfig, RewardTerms  # noqa: E402

CALIBRATED = dict(grip=4.0, grip_scales_with_mass=True, fall_unmet=0.3, w_wrench_change=5.0, change_falls=True)


def _write(path, calibrated=CALIBRATED, measured=None, **extra):
    path.write_text(json.dumps(dict(calibrated=calibrated, measured=measured or {"sequences": 1}, **extra)))
    return path


# ------------------------------------------------------------------------------------------ the calibration file
def test_defaults_are_the_shipped_calibration_file():
    """RewardConfig's calibrated defaults are the values of models/reward_calibration.json (read here with the json
    module, not the reader under test), and no other field of the file or of the config is calibrated."""
    data = json.loads(reward.CALIBRATION_JSON.read_text())
    assert reward.CALIBRATION_JSON.parent.name == "models"
    assert set(data["calibrated"]) == set(reward.CALIBRATED_FIELDS)
    cfg = RewardConfig()
    for name, value in data["calibrated"].items():
        assert getattr(cfg, name) == value and type(getattr(cfg, name)) is type(value), name
    assert reward.MEASURED == data["measured"]
    assert set(reward.CALIBRATED_FIELDS) < {f.name for f in dataclasses.fields(RewardConfig)}


def test_the_calibration_is_read_when_a_config_is_built_not_at_import(monkeypatch):
    """Importing the module reads no file: the calibrated defaults are read when the first `RewardConfig` is built (or
    `CALIBRATED` / `MEASURED` read), once (`calibration`, cached); a field given is not replaced."""
    reads = []

    def read(path=reward.CALIBRATION_JSON):
        reads.append(path)
        return dict(CALIBRATED, grip=7.5), {"sequences": 3}

    monkeypatch.setattr(reward, "read_calibration", read)
    reward.calibration.cache_clear()
    try:
        assert reads == []
        assert RewardConfig().grip == 7.5 and RewardConfig(grip=1.0).grip == 1.0
        assert reward.MEASURED == {"sequences": 3} and reward.CALIBRATED["grip"] == 7.5
        assert len(reads) == 1
        defaults = {f.name: f.default for f in dataclasses.fields(RewardConfig)}
        assert all(defaults[name] is reward.CALIBRATED_DEFAULT for name in reward.CALIBRATED_FIELDS)
    finally:
        reward.calibration.cache_clear()  # the real file again for the tests after this one
    with pytest.raises(AttributeError, match="no attribute 'CALIBRATE'"):
        reward.CALIBRATE  # noqa: B018


def test_the_order_of_the_terms_is_a_tuple_of_every_with_function():
    """`ORDER` names the order a step's terms are built in: `arrival`, then every `with_*` function of the module
    (a new one must take its place in it), `with_invalid` last; and it matters: `with_previous` sets the fall flag
    afresh, so applied after `with_risk` it would drop the learned term's fall."""
    assert reward.ORDER[0] is reward.arrival and reward.ORDER[-1] is reward.with_invalid
    withs = {name for name in vars(reward) if name.startswith("with_") and callable(getattr(reward, name))}
    assert {f.__name__ for f in reward.ORDER[1:]} == withs and len(reward.ORDER) == len(withs) + 1
    cfg = RewardConfig()
    terms = _random_terms(np.random.default_rng(3), (50,)).replace(  # nothing unmet: no analytic fall
        fall=jnp.zeros(50, bool), collision=jnp.zeros(50, bool), unmet=jnp.zeros((50, 4)), motor_unmet=jnp.zeros(50))
    risky = reward.with_risk(cfg, terms, jnp.full(50, 0.99, jnp.float32))  # above risk_falls: falls
    assert bool(jnp.all(risky.fall))
    args = (False, False, 0.0, 0.0, 1)
    in_order = reward.with_risk(cfg, reward.with_previous(cfg, terms, *args), jnp.full(50, 0.99, jnp.float32))
    reordered = reward.with_previous(cfg, risky, *args)
    assert bool(jnp.all(in_order.fall)) and not bool(jnp.any(reordered.fall))


def test_the_chance_node_rule_is_one_set_of_functions():
    """`chance_to_hold`, `expected_reward`, `accumulated`, `backed_up`, `expected_return` (with or without the
    walked reach) and `held_through` agree with each other, numpy or JAX, and are the plain sums without the term."""
    rng = np.random.default_rng(5)
    rewards = jnp.asarray(rng.uniform(-10, 0, (20, 6)), jnp.float32)
    risk = jnp.asarray(rng.uniform(0, 0.5, (20, 6)), jnp.float32)
    alive = jnp.asarray(np.arange(6)[None, :] < rng.integers(1, 7, (20, 1)))
    assert reward.chance_to_hold(None) == 1.0
    np.testing.assert_array_equal(reward.chance_to_hold(np.asarray([0.25])), [0.75])
    np.testing.assert_allclose(reward.expected_reward(np.float64(-4.0), np.float64(0.25), -200.0), -53.0)
    ret, reach, walked = jnp.zeros(20), jnp.ones(20), []
    for t in range(6):
        walked.append(reach)
        r, p = jnp.where(alive[:, t], rewards[:, t], 0.0), jnp.where(alive[:, t], risk[:, t], 0.0)
        ret, reach = reward.accumulated(ret, reach, r, p)
    value = jnp.zeros(20)
    for t in reversed(range(6)):
        value = jnp.where(alive[:, t], reward.backed_up(rewards[:, t], risk[:, t], t == 5, value), 0.0)
    expect = reward.expected_return(rewards, risk, alive)
    np.testing.assert_allclose(ret, expect, rtol=1e-5)
    np.testing.assert_allclose(value, expect, rtol=1e-5)
    np.testing.assert_allclose(reward.expected_return(rewards, None, alive, jnp.stack(walked, -1)), expect, rtol=1e-5)
    np.testing.assert_allclose(reward.held_through(jnp.where(alive, risk, 0.0), alive), reach, rtol=1e-5)
    np.testing.assert_array_equal(reward.backed_up(rewards, None, None, rewards), rewards + rewards)
    np.testing.assert_array_equal(reward.expected_return(rewards, None, alive),
                                  jnp.sum(jnp.where(alive, rewards, 0.0), -1))


def test_settings_not_adopted_are_gone():
    """The knobs measured and not adopted are no fields of the reward (docs/calibration.md keeps the measurements)."""
    names = {f.name for f in dataclasses.fields(RewardConfig)}
    assert not names & {"squeeze", "motors", "friction_scale"}
    with pytest.raises(TypeError, match="squeeze"):
        RewardConfig(squeeze=8.0)


def test_a_missing_or_malformed_calibration_is_named(tmp_path):
    with pytest.raises(CalibrationError, match=r"none\.json: no such file.*calibrate --write"):
        reward.read_calibration(tmp_path / "none.json")
    (tmp_path / "cut.json").write_text('{"calibrated": {"grip": 4.')
    with pytest.raises(CalibrationError, match=r"cut\.json: not readable JSON"):
        reward.read_calibration(tmp_path / "cut.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(CalibrationError, match=r"list\.json: expected an object with 'calibrated' and 'measured'"):
        reward.read_calibration(tmp_path / "list.json")
    missing = {k: v for k, v in CALIBRATED.items() if k != "fall_unmet"}
    with pytest.raises(CalibrationError, match=r"calibrated: fields missing \['fall_unmet'\], unknown \[\]"):
        reward.read_calibration(_write(tmp_path / "m.json", missing))
    with pytest.raises(CalibrationError, match=r"unknown \['squeeze'\]"):
        reward.read_calibration(_write(tmp_path / "u.json", {**CALIBRATED, "squeeze": 8.0}))
    with pytest.raises(CalibrationError, match=r"calibrated\.grip: expected a finite number, got '4'"):
        reward.read_calibration(_write(tmp_path / "s.json", {**CALIBRATED, "grip": "4"}))
    with pytest.raises(CalibrationError, match=r"calibrated\.fall_unmet: expected a finite number, got True"):
        reward.read_calibration(_write(tmp_path / "b.json", {**CALIBRATED, "fall_unmet": True}))
    with pytest.raises(CalibrationError, match=r"calibrated\.change_falls: expected a bool, got 1"):
        reward.read_calibration(_write(tmp_path / "i.json", {**CALIBRATED, "change_falls": 1}))
    with pytest.raises(CalibrationError, match=r"measured: expected an object"):
        reward.read_calibration(_write(tmp_path / "x.json", measured=[0.5]))
    # an integer is a number: read as a float
    values, _ = reward.read_calibration(_write(tmp_path / "n.json", {**CALIBRATED, "grip": 4}))
    assert values["grip"] == 4.0 and type(values["grip"]) is float


def test_write_calibration_reads_back_and_refuses_what_is_no_reward(tmp_path):
    values = dict(grip=2.0, grip_scales_with_mass=False, fall_unmet=0.25, w_wrench_change=1.0, change_falls=False)
    measured = dict(sets="train+val", backend="c", sequences=40, spearman=0.412)
    path = reward.write_calibration(tmp_path / "cal.json", values, measured, written="2026-01-02")
    assert reward.read_calibration(path) == (values, measured)
    assert json.loads(path.read_text())["written"] == "2026-01-02"
    with pytest.raises(CalibrationError, match=r"RewardConfig\.fall_unmet: must be > 0, got 0\.0"):
        reward.write_calibration(tmp_path / "bad.json", {**values, "fall_unmet": 0.0}, measured)
    with pytest.raises(CalibrationError, match=r"values\.grip: expected a finite number, got nan"):
        reward.write_calibration(tmp_path / "bad.json", {**values, "grip": float("nan")}, measured)
    with pytest.raises(CalibrationError, match=r"measured: expected a flat object"):
        reward.write_calibration(tmp_path / "bad.json", values, dict(rows=[1, 2]))
    assert not (tmp_path / "bad.json").exists()


def test_config_checks_name_the_field():
    with pytest.raises(ValueError, match=r"RewardConfig\.change_falls: must be a bool, got 1"):
        RewardConfig(change_falls=1)
    with pytest.raises(ValueError, match=r"RewardConfig\.w_ik: a weight must be >= 0, got -1"):
        RewardConfig(w_ik=-1)
    with pytest.raises(ValueError, match=r"RewardConfig\.r_min: must be < -max_step_cost = -10\.0, got -5"):
        RewardConfig(r_min=-5)
    assert RewardConfig(w_wrench_change=0.0, change_falls=False).prices_changes is False
    assert RewardConfig(w_wrench_change=0.0, change_falls=True).prices_changes is True


# ------------------------------------------------------------------------------------------ terms -> reward
def _random_terms(rng, shape) -> RewardTerms:
    f = lambda *s: jnp.asarray(rng.uniform(0.0, 2.0, shape + s), jnp.float32)  # noqa: E731
    b = lambda p: jnp.asarray(rng.uniform(size=shape) < p)  # noqa: E731
    return RewardTerms(wrench_move=f(), ik_next=f(), wrench_hold=f(), wrench_ext=f(), redundant=f(),
                       wrench_change=f(), unmet=jnp.asarray(rng.uniform(0.0, 0.6, shape + (4,)), jnp.float32),
                       motor_unmet=jnp.asarray(rng.uniform(0.0, 0.6, shape), jnp.float32), collision=b(0.1),
                       fall=b(0.2), reward=f(), invalid=b(0.0), fall_risk=jnp.zeros(shape, jnp.float32))


def test_total_is_the_capped_weighted_sum_or_r_min():
    rng = np.random.default_rng(0)
    cfg = RewardConfig(w_wrench_move=0.5, w_ik=2.0, w_wrench_hold=1.5, w_wrench_ext=3.0, w_redundant=0.25,
                       w_wrench_change=4.0, max_step_cost=6.0, r_min=-100.0)
    terms = _random_terms(rng, (500,))
    got = np.asarray(reward.total(cfg, terms))
    t = {k: np.asarray(v, np.float64) for k, v in vars(terms).items()}
    cost = (0.5 * t["wrench_move"] + 2.0 * t["ik_next"] + 1.5 * t["wrench_hold"] + 3.0 * t["wrench_ext"]
            + 0.25 * t["redundant"] + 4.0 * t["wrench_change"])
    expect = np.where(t["collision"].astype(bool) | t["fall"].astype(bool), -100.0, -np.minimum(cost, 6.0))
    np.testing.assert_allclose(got, expect, rtol=1e-6)
    assert np.any(expect == -6.0) and np.any((expect > -6.0) & (expect < 0)) and np.any(expect == -100.0)


def test_the_learned_risk_is_a_chance_node_and_falls_above_its_threshold():
    """`with_risk`: below `risk_falls` the reward is the analytic one's expectation with a fall (r_min) of chance p;
    above it the step falls (r_min); p = 0 leaves the reward as it was. `backed_up` and `expected_return` agree
    with the expectation over every fall time, enumerated."""
    rng = np.random.default_rng(2)
    cfg = RewardConfig(risk_falls=0.4)
    terms = _random_terms(rng, (400,))
    plain = np.asarray(reward.total(cfg, terms), np.float64)
    p = rng.uniform(0.0, 0.8, 400).astype(np.float32)
    got = reward.with_risk(cfg, terms, p)
    expect = np.where(p > 0.4, cfg.r_min, np.where(plain == cfg.r_min, cfg.r_min, (1 - p) * plain + p * cfg.r_min))
    np.testing.assert_allclose(np.asarray(got.reward), expect, rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(got.fall), np.asarray(terms.fall) | (p > 0.4))
    assert np.any((p > 0.4) & ~np.asarray(terms.fall)) and np.any((p < 0.4) & (plain > cfg.r_min))
    np.testing.assert_array_equal(np.asarray(reward.with_risk(cfg, terms, np.zeros(400)).reward), plain)
    for bad in (dict(risk_falls=0.0), dict(risk_falls=1.0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            RewardConfig(**bad)
    # a sequence of T held rewards r_t with fall chances p_t: the expected return over the fall time k (the steps
    # before k earn r, the fall earns r_min and ends it) or no fall at all
    T = 6
    r = -rng.uniform(0.0, 10.0, T)
    q = rng.uniform(0.0, 0.5, T)
    alive = np.array([True] * 5 + [False])
    n = int(alive.sum())
    outcomes = [(np.prod(1 - q[:n]), np.sum(r[:n]))]
    outcomes += [(np.prod(1 - q[:k]) * q[k], np.sum(r[:k]) + cfg.r_min) for k in range(n)]
    want = sum(w * v for w, v in outcomes)
    step = (1 - q) * r + q * cfg.r_min  # `total`'s expected rewards
    np.testing.assert_allclose(float(reward.expected_return(jnp.asarray(step), jnp.asarray(q), jnp.asarray(alive))),
                               want, rtol=1e-5)
    value = 0.0
    for t in reversed(range(n)):
        value = float(reward.backed_up(step[t], q[t], t == n - 1, value))
    np.testing.assert_allclose(value, want, rtol=1e-5)
    np.testing.assert_allclose(float(reward.expected_return(jnp.asarray(r), None, jnp.asarray(alive))), r[:n].sum(),
                               rtol=1e-6)


def _arrival(cfg, rng, is_last, motor_unmet=0.1):
    def res():
        return types.SimpleNamespace(error=jnp.float32(rng.uniform(0, 50)), unmet=jnp.float32(rng.uniform(0, 0.2)))

    return reward.arrival(cfg, res(), res(), res(), jnp.float32(0.004), jnp.array(False),
                          None if motor_unmet is None else jnp.float32(motor_unmet), jnp.array(is_last))


def test_arrival_normalises_and_masks_the_final_terms():
    cfg = RewardConfig()
    rng = np.random.default_rng(1)
    move = types.SimpleNamespace(error=jnp.float32(3.0), unmet=jnp.float32(0.1))
    hold = types.SimpleNamespace(error=jnp.float32(5.0), unmet=jnp.float32(0.2))
    ext = types.SimpleNamespace(error=jnp.float32(7.0), unmet=jnp.float32(0.25))
    for last in (False, True):
        a = reward.arrival(cfg, move, hold, ext, jnp.float32(0.02), jnp.array(True), jnp.float32(0.9),
                           jnp.array(last))
        np.testing.assert_allclose([float(a.wrench_move), float(a.wrench_hold), float(a.ik_next)],
                                   [3.0 / cfg.wrench_scale, 5.0 / cfg.wrench_scale, 2.0], rtol=1e-6)
        np.testing.assert_allclose(float(a.wrench_ext), 7.0 / cfg.wrench_scale if last else 0.0, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(a.unmet), [0.1, 0.2, 0.25 if last else 0.0, 0.0], rtol=1e-6)
        np.testing.assert_allclose(float(a.motor_unmet), 0.9 if last else 0.0)
        assert bool(a.collision) and not bool(a.fall) and float(a.redundant) == 0 and float(a.wrench_change) == 0
    assert float(_arrival(cfg, rng, True, None).motor_unmet) == 0.0  # no motor check


def test_with_motor_equals_the_check_scored_in_arrival():
    """Terms scored without the motor check (0) and completed by `with_motor` equal those whose `arrival` had it, at
    the last step (a fall beyond `motor_fall_unmet`, r_min) and before it (the check given there as 0), batched."""
    cfg = RewardConfig()
    for unmet in (0.05, cfg.motor_fall_unmet + 0.01):
        for last in (False, True):
            rng, rng2 = np.random.default_rng(5), np.random.default_rng(5)
            want = reward.with_previous(cfg, _arrival(cfg, rng, last, unmet), True, True, 0.4, 0.1, 3)
            plain = reward.with_previous(cfg, _arrival(cfg, rng2, last, None), True, True, 0.4, 0.1, 3)
            got = reward.with_motor(cfg, plain, jnp.float32(unmet if last else 0.0))
            for name in ("reward", "fall", "motor_unmet", "unmet", "wrench_change"):
                np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), name)
            assert bool(got.fall) == (last and unmet > cfg.motor_fall_unmet)
    batch = jax.tree.map(lambda x: jnp.broadcast_to(x, (3,) + x.shape), plain)
    got = reward.with_motor(cfg, batch, jnp.asarray([0.0, 0.1, 0.9], jnp.float32))
    assert np.asarray(got.fall).tolist() == [False, False, True] and float(got.reward[2]) == cfg.r_min


def test_previous_grasp_part_prices_changes_past_the_start_support():
    """The change term counts only when the grasp changes at t >= supported_steps; it drops the tool (r_min) when
    more than fall_unmet of it is unmet, and only if change_falls; a final wrench beyond the motors drops it too."""
    rng = np.random.default_rng(2)
    cfg = RewardConfig(supported_steps=2)
    terms = _arrival(cfg, rng, False)
    base = float(reward.with_previous(cfg, terms, False, False, 0.0, 0.0, 5).reward)
    for t, changed, expect_change in ((1, True, False), (2, True, True), (5, False, False)):
        out = reward.with_previous(cfg, terms, False, changed, 0.5, 0.1, t)
        assert float(out.wrench_change) == (0.5 if expect_change else 0.0)
        np.testing.assert_allclose(float(out.reward), base - (cfg.w_wrench_change * 0.5 if expect_change else 0.0),
                                   rtol=1e-6)
    redundant = reward.with_previous(cfg, terms, True, False, 0.0, 0.0, 5)
    np.testing.assert_allclose(float(redundant.reward), base - cfg.w_redundant, rtol=1e-6)
    dropped = reward.with_previous(cfg, terms, False, True, 0.5, cfg.fall_unmet + 0.01, 2)
    assert bool(dropped.fall) and float(dropped.reward) == cfg.r_min
    lenient = dataclasses.replace(cfg, change_falls=False)
    kept = reward.with_previous(lenient, terms, False, True, 0.5, cfg.fall_unmet + 0.01, 2)
    assert not bool(kept.fall) and float(kept.reward) > cfg.r_min
    weak = _arrival(cfg, rng, True, motor_unmet=cfg.motor_fall_unmet + 0.01)
    assert bool(reward.with_previous(cfg, weak, False, False, 0.0, 0.0, 15).fall)
    assert not bool(reward.with_previous(dataclasses.replace(cfg, motor_fall_unmet=np.inf), weak, False, False, 0.0,
                                         0.0, 15).fall)
    invalid = reward.with_invalid(cfg, kept, jnp.array(True))
    assert bool(invalid.invalid) and float(invalid.reward) == cfg.r_min


@pytest.mark.parametrize("cfg", [RewardConfig(), RewardConfig(w_wrench_change=0.0, change_falls=False)])
def test_transitions_are_the_steps_reward_one_at_a_time(cfg):
    """`of_transitions` (the DP table's reward) against `with_previous` (the step's) called for each transition
    with the shared grasp's moving-wrench term as its change term (none where changes are not priced): equal, term
    by term."""
    rng = np.random.default_rng(3)
    n_g, n_a, n_t = 6, 4, 3
    arrived = _random_terms(rng, (n_g, n_t)).replace(
        collision=jnp.zeros((n_g, n_t), bool), fall=jnp.zeros((n_g, n_t), bool),
        redundant=jnp.zeros((n_g, n_t)), wrench_change=jnp.zeros((n_g, n_t)))
    arrived = arrived.replace(unmet=arrived.unmet.at[..., 3].set(0.0))
    next_grasp = jnp.asarray(rng.integers(0, n_g, (n_g, n_a)), jnp.int32)
    shared = jnp.asarray(rng.integers(0, n_g, (n_g, n_a)), jnp.int32)
    changed = next_grasp != jnp.arange(n_g)[:, None]
    redundant = ~changed & (jnp.arange(n_a) > 0)
    ts = jnp.arange(n_t, dtype=jnp.int32)
    table = jax.jit(lambda *a: reward.of_transitions(cfg, *a))(arrived, next_grasp, redundant, changed, shared, ts)
    assert table.reward.shape == (n_g, n_a, n_t)
    one = jax.jit(lambda *a: reward.with_previous(cfg, *a))
    n_fall = 0
    for g in range(n_g):
        for a in range(n_a):
            for t in range(n_t):
                new, sh = int(next_grasp[g, a]), int(shared[g, a])
                # the step solves the shared grasp only where changes are priced (`Surrogate.score`'s `during`)
                change = (arrived.wrench_move[sh, t], arrived.unmet[sh, t, 0]) if cfg.prices_changes else (0.0, 0.0)
                step = one(jax.tree.map(lambda x: x[new, t], arrived), redundant[g, a], changed[g, a], *change, t)
                for name, value in vars(step).items():
                    np.testing.assert_array_equal(np.asarray(getattr(table, name))[g, a, t], np.asarray(value),
                                                  err_msg=f"{name} at g={g} a={a} t={t}")
                n_fall += bool(step.fall)
    assert n_fall > 0  # some transitions fall, some do not
    assert n_fall < n_g * n_a * n_t


def test_explain_failure_names_the_term():
    cfg = RewardConfig()
    ok = RewardTerms.zeros()
    assert reward.explain_failure(cfg, ok, 3, "T1 I1") is None
    assert "collides" in reward.explain_failure(cfg, ok.replace(collision=jnp.array(True)), 3, "T1 I1")
    fell = ok.replace(fall=jnp.array(True), unmet=jnp.asarray([0.1, 0.45, 0.0, 0.0], jnp.float32))
    assert reward.explain_failure(cfg, fell, 4, "T1 I1") == (
        "t=4: the hold at the next waypoint (c) is 45% unmet (> 30%) with grasp T1 I1")
    motors = fell.replace(motor_unmet=jnp.float32(0.5), unmet=jnp.zeros(4, jnp.float32))
    assert reward.explain_failure(cfg, motors, 15, "T1").startswith("t=15: the external wrench at the final pose (d) "
                                                                    "is beyond the hand's motors: 50% unmet")
