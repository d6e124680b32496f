"""The learned physics term (`gsp_jax.surrogate.learned`): the fit recovers a known synthetic hazard, the split keeps
episodes whole, and weights refuse another model or another feature set by name."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from gsp_jax.surrogate import learned
from gsp_jax.core import stats
from gsp_jax.model import load as model_lib


def _synthetic(n_runs=3000, T=4, seed=0):
    """Runs of T transitions with features x (M, T, 3) ~ N(0, 1) and a known hazard p = sigmoid(2 x0 - x1^2 - 1):
    each alive transition falls with probability p, after which the run is over."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n_runs, T, 3)).astype(np.float32)
    p = 1 / (1 + np.exp(-(2 * x[..., 0] - x[..., 1] ** 2 - 1)))
    fell = rng.uniform(size=p.shape) < p
    first = np.where(fell.any(1), fell.argmax(1), T)
    alive = np.arange(T)[None] <= first[:, None]
    return x, fell & alive, alive, np.arange(n_runs) // 3, p


def test_the_fit_recovers_a_known_hazard():
    x, fell_here, alive, episode, p = _synthetic()
    fitted = learned.fit(x, fell_here, alive, episode, jax.random.PRNGKey(0), "digest",
                         config=learned.FitConfig(hidden=(32, 32), epochs=80, patience=10, batch=512))
    test = np.isin(episode, fitted.split["test"])
    assert not set(fitted.split["train"]) & set(fitted.split["test"]) and test.any()
    got = np.asarray(learned.hazard(fitted, x[test]))[alive[test]]
    true = p[test][alive[test]]
    assert np.mean(np.abs(got - true)) < 0.04, np.mean(np.abs(got - true))
    events = fell_here[test][alive[test]]
    auc = lambda score: stats.auc(score[events], score[~events])  # noqa: E731  (P(a fall scores above a hold))
    assert auc(got) >= auc(true) - 0.02
    for b in learned.reliability(got, events, bins=5):
        if b["n"] >= 300:
            assert abs(b["predicted"] - b["observed"]) < 0.06, b


def test_weights_refuse_another_model_or_feature_set_by_name(tmp_path):
    x, fell_here, alive, episode, _ = _synthetic(n_runs=60)
    wrench, hammer = model_lib.load_model("wrench"), model_lib.load_model("hammer")
    names = ("a", "b", "c")
    fitted = learned.fit(x, fell_here, alive, episode, jax.random.PRNGKey(1), wrench.digest, names,
                         learned.FitConfig(hidden=(8,), epochs=3))
    path = learned.save(fitted, tmp_path / "hazard.npz")
    again = learned.load(path, wrench, names)
    np.testing.assert_array_equal(learned.hazard(again, x), learned.hazard(fitted, x))
    with pytest.raises(learned.LearnedTermError, match=r"fitted for another model .*not 'hammer'"):
        learned.load(path, hammer)
    with pytest.raises(learned.LearnedTermError, match=r"fitted on features \['a', 'b', 'c'\], not \['a', 'b'\]"):
        learned.load(path, wrench, ("a", "b"))
    with np.load(path) as d:
        np.savez(tmp_path / "broken.npz", **{k: d[k] for k in d.files if k != "std"})
    with pytest.raises(learned.LearnedTermError, match=r"broken.npz: no field 'std'"):
        learned.load(tmp_path / "broken.npz", wrench)


def test_an_ensemble_is_the_mean_of_its_members_and_one_network_saved_without_the_axis_loads(tmp_path):
    """The hazard of K networks is the mean of each one's own hazard; a file of one network written before
    ensembles (no members' axis, no `members` in its header) loads as an ensemble of one."""
    import json

    x, fell_here, alive, episode, _ = _synthetic(n_runs=60)
    wrench = model_lib.load_model("wrench")
    fitted = learned.fit(x, fell_here, alive, episode, jax.random.PRNGKey(2), wrench.digest, ("a", "b", "c"),
                         learned.FitConfig(hidden=(8,), epochs=3, members=3))
    one = lambda k: fitted.replace(params=jax.tree.map(lambda p: p[k:k + 1], fitted.params))  # noqa: E731
    members = np.stack([np.asarray(learned.hazard(one(k), x)) for k in range(3)])
    assert np.ptp(members, 0).max() > 1e-3  # the members differ
    np.testing.assert_allclose(learned.hazard(fitted, x), members.mean(0), rtol=1e-5, atol=1e-6)
    path = learned.save(one(1), tmp_path / "one.npz")
    with np.load(path) as d:
        old = {k: d[k][0] if k.startswith("param") else d[k] for k in d.files}
    header = json.loads(str(old["header"]))
    del header["members"]
    old["header"] = np.array(json.dumps(header))
    np.savez(tmp_path / "old.npz", **old)
    np.testing.assert_array_equal(learned.hazard(learned.load(tmp_path / "old.npz", wrench), x), members[1])
