"""Episodes and episode sets (gsp_jax.model.scenario): members and values of the paper's sets, JSON round trip, and
rejection of bad files with a message naming the field and the value."""
import collections
import json
import math
import re
import types
from unittest import mock

import numpy as np
import pytest

from gsp_jax.model import load as model_lib
from gsp_jax.model import scenario as sc

M0 = 0.35
Z0, Z1 = 0.014, 0.06
INERTIA0 = np.array([2.5e-5, 1.1e-3, 1.12e-3])


def _params(ep):
    """(shift_mm, torque_z, mass_factor, com_y_cm) read back from an episode's arrays, rounded."""
    shift = (float(ep.waypoints[0, 2]) - Z0) * 1e3
    return (
        round(shift, 3),  # float32 heights: the shift is good to ~1e-6 mm
        round(float(ep.w_ext[5]), 6),
        round(float(ep.mass) / M0, 6),
        round(float(ep.com[1]) * 1e2, 6),
    )


def _check_episode(ep, shift_mm, torque, mass_factor, com_y_cm):
    dz = shift_mm * 1e-3
    wp = np.asarray(ep.waypoints)
    assert wp.shape == (16, 3) and wp.dtype == np.float32
    np.testing.assert_allclose(wp[0], [0, 0, Z0 + dz], atol=1e-7)
    np.testing.assert_allclose(wp[-1], [0, 0, Z1 + dz], atol=1e-7)
    assert np.all(wp[:, :2] == 0.0)
    assert np.all(np.diff(wp[:, 2]) > 0)  # strictly rising
    # minimum-jerk: zero velocity at both ends -> the first and last steps are the smallest ones
    steps = np.diff(wp[:, 2])
    assert steps[0] < 0.01 * (Z1 - Z0) and steps[-1] < 0.01 * (Z1 - Z0)
    assert np.argmax(steps) in (7,)  # symmetric profile peaks in the middle step
    np.testing.assert_allclose(np.asarray(ep.quats), np.tile([1, 0, 0, 0], (16, 1)))
    w = np.asarray(ep.w_ext)
    np.testing.assert_array_equal(w[:5], 0.0)
    assert w[5] == pytest.approx(torque, abs=1e-7)
    assert np.sign(w[5]) == np.sign(torque) and abs(w[5]) == pytest.approx(1.0)
    assert float(ep.mass) == pytest.approx(M0 * mass_factor, rel=1e-6)
    np.testing.assert_allclose(np.asarray(ep.inertia), INERTIA0 * mass_factor, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ep.com), [0, com_y_cm * 1e-2, 0], atol=1e-8)
    assert float(ep.friction) == pytest.approx(0.8)
    assert float(ep.dt) == pytest.approx(0.25)
    assert tuple(np.asarray(model_lib.default_space().decode(ep.start_grasp)).tolist()) == (1, 1, 0, 1, 0, 0)
    sc.validate(ep, n_grasps=288)


def _expect(eps, expected):
    """eps (dict name -> Episode) has exactly the expected parameter tuples, each once, all valid."""
    assert len(set(eps)) == len(eps) == len(expected)
    got = collections.Counter(_params(e) for e in eps.values())
    want = collections.Counter((float(s), float(t), float(m), float(c)) for s, t, m, c in expected)
    assert got == want
    for ep in eps.values():
        _check_episode(ep, *_params(ep))


TRAIN = [(0, 1, 1, 0), (0, -1, 1, 0)] + [(s, -1, 1, 0) for s in (-6, -4, -2)] + [(s, 1, 1, 0) for s in (2, 4, 6, 8)]
EVAL_A = [(s, 1, 1, 0) for s in (-6, -4, -2)] + [(s, -1, 1, 0) for s in (2, 4, 6, 8)]
EVAL_B = [(0, 1, m, c) for m in (0.5, 1.0, 1.5, 2.0) for c in (-2, -1, 0, 1, 2)]


def test_nominal_episode():
    ep = sc.make_episode()
    _check_episode(ep, 0, 1.0, 1.0, 0)
    assert _params(ep) == (0.0, 1.0, 1.0, 0.0)
    # the waypoints are the minimum-jerk heights
    s = np.linspace(0, 1, 16)
    min_jerk = Z0 + (Z1 - Z0) * (10 * s**3 - 15 * s**4 + 6 * s**5)
    np.testing.assert_allclose(np.asarray(ep.waypoints)[:, 2], min_jerk, atol=1e-7)


def test_training_set():
    eps = sc.training_set()
    assert len(eps) == 9
    _expect(eps, TRAIN)
    assert _params(eps["nominal"]) == (0.0, 1.0, 1.0, 0.0)


def test_eval_set_a():
    eps = sc.eval_set_a()
    assert len(eps) == 7
    _expect(eps, EVAL_A)


def test_eval_set_a_flips_the_training_torques():
    train = {p[0]: p[1] for p in map(_params, sc.training_set().values()) if p[0] != 0}
    evala = {p[0]: p[1] for p in map(_params, sc.eval_set_a().values())}
    assert set(train) == set(evala) == {-6.0, -4.0, -2.0, 2.0, 4.0, 6.0, 8.0}
    assert all(evala[s] == -train[s] for s in train)


def test_eval_set_b():
    eps = sc.eval_set_b()
    assert len(eps) == 20
    _expect(eps, EVAL_B)
    masses = sorted({round(float(e.mass), 6) for e in eps.values()})
    assert masses == [0.175, 0.35, 0.525, 0.7]
    com_y = sorted({round(float(e.com[1]), 6) for e in eps.values()})
    assert com_y == [-0.02, -0.01, 0.0, 0.01, 0.02]


def test_named_sets():
    assert len(sc.episode_set("nominal")) == 1
    assert [_params(e) for e in sc.episode_set("train").values()] == [_params(e) for e in sc.training_set().values()]
    ev = sc.episode_set("eval")
    assert len(ev) == 27
    _expect(ev, EVAL_A + EVAL_B)
    assert len(sc.episode_set("all")) == 36
    _expect(sc.episode_set("all"), TRAIN + EVAL_A + EVAL_B)
    with pytest.raises(ValueError, match="bogus"):
        sc.episode_set("bogus")


def test_stack_unstack_round_trip():
    eps = list(sc.eval_set_b().values())[:3]
    batch = sc.stack(eps)
    assert batch.waypoints.shape == (3, 16, 3) and batch.mass.shape == (3,)
    for a, b in zip(eps, sc.unstack(batch)):
        for f in sc._FIELDS:
            np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)))


# ------------------------------------------------------------------------------------------------- JSON files


def _assert_same(a, b):
    for f in sc._FIELDS:
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.dtype == y.dtype, f
        np.testing.assert_array_equal(x, y, err_msg=f)


def test_save_load_round_trip(tmp_path):
    eps = sc.episode_set("all")
    path = tmp_path / "all.json"
    sc.save(path, eps)
    back = sc.load(path)
    assert list(back) == list(eps)
    for k in eps:
        _assert_same(eps[k], back[k])
    # a second round trip writes the identical file
    path2 = tmp_path / "again.json"
    sc.save(path2, back)
    assert path2.read_text() == path.read_text()


def test_saved_file_is_readable_json(tmp_path):
    path = tmp_path / "n.json"
    sc.save(path, sc.nominal())
    doc = json.loads(path.read_text())
    assert doc["format"] == "gsp_jax.episodes/1"
    ep = doc["episodes"]["nominal"]
    assert set(ep) == set(sc._FIELDS)
    assert ep["mass"] == pytest.approx(0.35) and ep["w_ext"][5] == 1.0 and len(ep["waypoints"]) == 16


def _numbers(msg):
    return [float(x) for x in re.findall(r"[-+]?(?:\d+\.?\d*(?:[eE][-+]?\d+)?|nan|inf)", msg)]


def _write_bad(tmp_path, mutate):
    doc = {"format": "gsp_jax.episodes/1", "episodes": {"nominal": sc.to_dict(sc.make_episode())}}
    mutate(doc["episodes"]["nominal"])
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    return path


def _set_wp(i, j, v):
    def f(d):
        d["waypoints"][i][j] = v

    return f


BAD = {
    # id: (mutation, field named in the message, value(s) the message must show; None: no number to check)
    "waypoints_two_columns": (lambda d: d.update(waypoints=[w[:2] for w in d["waypoints"]]), "waypoints", (16, 2)),
    "waypoints_flat": (lambda d: d.update(waypoints=d["waypoints"][0]), "waypoints", (3,)),
    "waypoints_one_row": (lambda d: d.update(waypoints=d["waypoints"][:1], quats=d["quats"][:1]), "waypoints", (1, 3)),
    "quats_length_mismatch": (lambda d: d.update(waypoints=d["waypoints"][:5]), "quats", (16, 4)),
    "w_ext_nan": (lambda d: d["w_ext"].__setitem__(2, float("nan")), "w_ext", ("nan",)),
    "w_ext_inf": (lambda d: d["w_ext"].__setitem__(0, float("inf")), "w_ext", ("inf",)),
    "w_ext_shape": (lambda d: d.update(w_ext=d["w_ext"][:5]), "w_ext", (5,)),
    "mass_negative": (lambda d: d.update(mass=-0.35), "mass", (-0.35,)),
    "mass_zero": (lambda d: d.update(mass=0.0), "mass", (0.0,)),
    "friction_zero": (lambda d: d.update(friction=0.0), "friction", (0.0,)),
    "friction_negative": (lambda d: d.update(friction=-0.1), "friction", (-0.1,)),
    "dt_zero": (lambda d: d.update(dt=0.0), "dt", (0.0,)),
    "inertia_negative": (lambda d: d["inertia"].__setitem__(1, -1e-3), "inertia", (-1e-3,)),
    "waypoint_too_high": (_set_wp(5, 2, 0.5), "waypoints[5]", (0.5,)),
    "waypoint_below_table": (_set_wp(0, 2, -0.01), "waypoints[0]", (-0.01,)),
    "waypoint_too_far_sideways": (_set_wp(9, 0, 0.2), "waypoints[9]", (0.2,)),
    "quat_not_unit": (lambda d: d["quats"].__setitem__(3, [2.0, 0, 0, 0]), "quats[3]", (2.0,)),
    "missing_field": (lambda d: d.pop("com"), "com", None),
    "non_numeric_scalar": (lambda d: d.update(mass="heavy"), "mass", None),
    "non_numeric_in_list": (lambda d: d.update(com=[0.0, "a", 0.0]), "com", None),
    "unknown_field": (lambda d: d.update(colour=[1, 0, 0]), "colour", None),
    "start_grasp_fraction": (lambda d: d.update(start_grasp=1.5), "start_grasp", (1.5,)),
    "start_grasp_out_of_range": (lambda d: d.update(start_grasp=288), "start_grasp", (288,)),
    "start_grasp_negative": (lambda d: d.update(start_grasp=-1), "start_grasp", (-1,)),
    "start_grasp_far_out": (lambda d: d.update(start_grasp=999), "start_grasp", (999,)),
    "com_outside_the_tool": (lambda d: d["com"].__setitem__(1, 1.0), "com", (1.0,)),
    "com_just_below_the_tool": (lambda d: d["com"].__setitem__(2, -0.007), "com", (-0.007,)),
    "friction_implausibly_high": (lambda d: d.update(friction=3.5), "friction", (3.5,)),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_files_are_rejected_naming_field_and_value(tmp_path, case):
    mutate, field, values = BAD[case]
    path = _write_bad(tmp_path, mutate)
    with pytest.raises(sc.EpisodeError) as info:
        sc.load(path)
    msg = str(info.value)
    assert f"nominal.{field}" in msg, msg
    if case == "missing_field":
        assert "missing" in msg
    elif case == "unknown_field":
        assert "unknown" in msg
    elif case.startswith("non_numeric"):
        assert "not numeric" in msg and ("'heavy'" in msg or "'a'" in msg), msg
    else:
        nums = _numbers(msg.split(":", 1)[1])
        for v in values:
            if isinstance(v, str):
                assert v in msg.lower(), msg
            else:
                # the value (float32-rounded after reading) appears among the message's numbers
                assert any(math.isclose(n, v, rel_tol=1e-6, abs_tol=1e-9) for n in nums), (v, msg)


def test_json_null_value_is_rejected_with_episode_error(tmp_path):
    """A JSON null (e.g. a blanked value in a hand-edited file) must give an EpisodeError naming the field."""
    path = _write_bad(tmp_path, lambda d: d.update(mass=None))
    with pytest.raises(sc.EpisodeError, match=r"nominal\.mass"):
        sc.load(path)


def test_malformed_documents_are_rejected(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(sc.EpisodeError, match="not readable JSON"):
        sc.load(p)
    p.write_text(json.dumps({"episodes": []}))
    with pytest.raises(sc.EpisodeError, match="episodes"):
        sc.load(p)


def test_valid_edited_file_is_accepted(tmp_path):
    """Rejection is specific: in-range edits load, with the edited values."""
    def edit(d):
        d["mass"] = 0.5
        d["friction"] = 0.3
        d["waypoints"][-1][2] = 0.099

    back = sc.load(_write_bad(tmp_path, edit))["nominal"]
    assert float(back.mass) == pytest.approx(0.5)
    assert float(back.friction) == pytest.approx(0.3)
    assert float(back.waypoints[-1, 2]) == pytest.approx(0.099)


def test_make_episode_rejects_what_validate_rejects():
    """The constructor users call directly checks its result too: no silent episode with a CoM off the tool."""
    with pytest.raises(sc.EpisodeError, match=r"episode\.com: \[0\.0, 1\.0"):
        sc.make_episode(com_y_cm=100)
    with pytest.raises(sc.EpisodeError, match=r"episode\.start_grasp: 999"):
        sc.make_episode(start_grasp=999)
    with pytest.raises(sc.EpisodeError, match=r"episode\.friction: 5\.0"):
        sc.make_episode(friction=5.0)
    assert float(sc.make_episode(friction=sc.FRICTION_MAX).friction) == sc.FRICTION_MAX  # the bound is allowed


def test_tool_bounds_enclose_the_boxes(hand):
    """The CoM check's box: the tool model's boxes (handle and head) span x -9..10 cm, y and z a few mm."""
    lo, hi = hand.tool_bounds()
    np.testing.assert_allclose(lo, [-0.09, -0.025, -0.006], atol=1e-9)
    np.testing.assert_allclose(hi, [0.10, 0.025, 0.006], atol=1e-9)


def test_validate_accepts_every_set_member():
    for name, ep in sc.episode_set("all").items():
        sc.validate(ep, name, n_grasps=288)


def _leaves(ep):
    return [getattr(ep, f) for f in ("waypoints", "quats", "dt", "w_ext", "mass", "inertia", "com", "friction",
                                     "start_grasp")]


def test_stress_set_spans_the_envelope_and_is_fixed():
    """The stress set: >= 100 valid episodes, the same on every call (seeded), spanning mass 0.25-3 m0, friction
    0.3-2, torques about x, y and z up to 2 N m, CoM offsets inside the tool, vertical, lateral and diagonal paths;
    disjoint from every set used for training, calibration or evaluation."""
    stress = sc.episode_set("stress")
    again = sc.stress_set()
    assert len(stress) >= 100 and list(stress) == list(again)
    for a, b in zip(stress.values(), again.values()):
        for x, y in zip(_leaves(a), _leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    m = np.array([float(e.mass) for e in stress.values()]) / sc.M0
    mu = np.array([float(e.friction) for e in stress.values()])
    w = np.stack([np.asarray(e.w_ext) for e in stress.values()])
    end = np.stack([np.asarray(e.waypoints[-1]) for e in stress.values()])
    assert m.min() < 0.3 and m.max() > 2.7 and mu.min() < 0.35 and mu.max() > 1.9
    assert np.all(np.abs(w[:, :3]) == 0) and np.abs(w[:, 3:]).max() > 1.9
    for axis in range(3):
        assert np.sum(np.abs(w[:, 3 + axis]) > 0) >= len(stress) // 4  # each axis about a third of the set
    lateral = np.abs(end[:, :2]) > 1e-4
    assert np.any(lateral[:, 0] & ~lateral[:, 1]) and np.any(lateral[:, 1] & ~lateral[:, 0]) and np.any(lateral.all(1))
    assert not set(stress) & (set(sc.episode_set("all")) | set(sc.episode_set("val")))
    cal = sc.episode_set("stress-cal")
    assert len(cal) == 60 and not set(cal) & set(stress)
    assert not any(np.array_equal(np.asarray(a.w_ext), np.asarray(b.w_ext)) and float(a.mass) == float(b.mass)
                   for a in cal.values() for b in stress.values())
    with pytest.raises(sc.EpisodeError, match="torque_axis"):
        sc.make_episode(torque_axis="w")


def test_the_sets_fit_a_narrow_tool():
    """Issue 83: every episode set and the corpus draw for a tool check-model accepts, however narrow: the
    screwdriver's round grip is 2 cm across (1 cm from its CoM to the grip's faces), so its CoM offsets are 0.4 of
    the wrench's and still span the room; the wrench keeps its sets (its fit is 1 everywhere)."""
    from gsp_jax.physics import corpus

    assert sc.fit("wrench") == sc.Fit() and sc.fit("hammer") == sc.Fit()
    fit = sc.fit("screwdriver")
    assert fit.com[1] == pytest.approx(0.4) and fit.com[0] == 1.0 and fit.down == fit.up == 1.0
    hand = model_lib.load_model("screwdriver").hand
    lo, hi = hand.tool_bounds()
    sets = {name: sc.episode_set(name, "screwdriver") for name in ("all", "val", "variations", "stress", "stress-cal")}
    sets["corpus"] = corpus.draw(corpus.Distribution(), 3, 40, "screwdriver")
    for name, eps in sets.items():
        com = np.stack([np.asarray(e.com) for e in eps.values()])
        assert np.all((com >= lo) & (com <= hi)), name
    offset = np.stack([np.asarray(e.com) for e in sets["corpus"].values()]) - hand.tool_com
    assert np.abs(offset[:, 1]).max() > 0.8 * 0.01 and np.abs(offset[:, 0]).max() > 0.02  # the room is used
    assert "mass1m0_comy+0.8cm" in sets["all"]  # evaluation set B's +2 cm, scaled to the grip: named as it is
    names = list(sc.eval_set_b())
    assert names[:5] == [f"mass0.5m0_comy{c:+d}cm" for c in (-2, -1, 0, 1, 2)]  # the wrench's names as before


def test_fit_keeps_within_the_hands_reach_and_the_tools_box():
    """The fit's factors: the room a model has over the room the sets were written for, capped at 1, in whole
    tenths of a millimetre (the wrench's exactly 1); a tool whose CoM sits on a face gets none (factor 0)."""
    room = sc.COM_REACH * 0.5
    fake = types.SimpleNamespace(tool_bounds=lambda: (np.array([-0.1, -room, -0.01]), np.array([0.1, room, 0.01])),
                                 tool_com=np.zeros(3), workspace=np.array([[-0.05, -0.05, 0.005], [0.05, 0.05, 0.1]]),
                                 tool_rest=np.array([0.0, 0.0, 0.014]))
    with mock.patch.object(model_lib, "load_model", return_value=types.SimpleNamespace(hand=fake)):
        assert sc.fit("x") == sc.Fit(com=(1.0, 0.5))
        fake.tool_rest = np.array([0.0, 0.04, 0.009])  # 4 mm above the reach's floor, 1 cm from its side
        f = sc.fit("x")
        assert f.down == pytest.approx(0.5) and f.lateral == (1.0, pytest.approx(10 / 18)) and f.up == 1.0
        assert f.shift(-6) == pytest.approx(-3) and f.shift(12) == 12
        fake.tool_com = np.array([0.0, room, 0.0])
        assert sc.fit("x").com[1] == 0.0
