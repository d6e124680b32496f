"""The physics corpus (`gsp_jax.physics.corpus`): its distribution spans the stress set, one seed gives one set and no
held-out episode, the labels are a discrete-time hazard's events and risk sets, the store refuses another model's
corpus or a broken one by name, is extended only with the physics settings its runs had and resumes after a kill
with nothing lost or duplicated, and a real shard's features and labels agree with the surrogate and with C MuJoCo."""
from __future__ import annotations

import json
import types

import jax
import numpy as np
import pytest

from gsp_jax.model import load as model_lib
from gsp_jax.model import scenario
from gsp_jax.physics import corpus
from gsp_jax.physics.config import PhysicsConfig


def test_the_distribution_spans_the_stress_set():
    """Every stress episode's mass, friction, torque, CoM and path lie inside `Distribution()`'s ranges (the
    corpus draws at least as wide as the set it is judged on)."""
    d, nominal = corpus.Distribution(), scenario.make_episode()
    t0 = scenario._torque(None)
    for name, ep in scenario.stress_set().items():
        m = float(ep.mass / nominal.mass)
        assert d.mass[0] <= m <= d.mass[1], (name, m)
        assert d.friction[0] <= float(ep.friction) <= d.friction[1], name
        assert np.linalg.norm(ep.w_ext[3:]) <= max(map(abs, d.torque)) * t0 + 1e-6, name
        com = 100 * (np.asarray(ep.com) - np.asarray(nominal.com))[:2]
        assert np.all((d.com_cm[0] - 1e-6 <= com) & (com <= d.com_cm[1] + 1e-6)), (name, com)
        lateral = 1000 * np.abs(np.asarray(ep.waypoints[-1, :2] - nominal.waypoints[-1, :2]))
        assert np.all(lateral <= d.lateral_mm[1] + 1e-3), (name, lateral)
    with pytest.raises(ValueError, match=r"Distribution.friction: expected \(low, high\)"):
        corpus.Distribution(friction=(1.0, 0.5))


def test_one_seed_one_set_and_no_held_out_episode(monkeypatch):
    """`draw`: the same seed gives the same episodes, another seed others; an episode equal to a held-out set's is
    drawn again (a held-out set made of the first draw's episodes)."""
    d = corpus.Distribution()
    a, b, c = corpus.draw(d, 3, 4), corpus.draw(d, 3, 4), corpus.draw(d, 4, 4)
    assert list(a) == [f"corpus3-{i:04d}" for i in range(4)]
    for x, y in zip(a.values(), b.values()):
        jax.tree.map(np.testing.assert_array_equal, x, y)
    assert not np.array_equal(a["corpus3-0000"].mass, c["corpus4-0000"].mass)
    first = list(a.values())[:2]
    monkeypatch.setattr(corpus, "_held_out", lambda model: {corpus._key(e) for e in first})
    again = corpus.draw(d, 3, 4)
    keys = {corpus._key(e) for e in again.values()}
    assert not keys & {corpus._key(e) for e in first} and len(keys) == 4
    np.testing.assert_array_equal(again["corpus3-0000"].mass, a["corpus3-0002"].mass)  # the draws after them


def test_labels_are_the_hazards_events_and_risk_sets():
    """`labels` against a per-run loop: a run that fell at tick k fell in the segment holding k (the last one
    holds the hold too) and was alive in every segment that began at or before k; a held run, alive throughout."""
    T, n_seg, tick = 4, 10, 0.002
    fell = np.array([False, True, True, True, True])
    ticks = np.array([-1, 0, 9, 10, 57])
    got = corpus.labels(fell, np.where(fell, ticks * tick, -1.0), T, n_seg, tick)
    for i in range(len(fell)):
        for t in range(T):
            alive = not fell[i] or ticks[i] >= t * n_seg
            here = fell[i] and alive and (t == T - 1 or ticks[i] < (t + 1) * n_seg)
            assert got["alive"][i, t] == alive and got["fell_here"][i, t] == here, (i, t)
    assert np.array_equal(got["fell_here"].any(1), fell)


def _arrays(seed: int, runs: int = 3, T: int = 2) -> dict:
    rng = np.random.default_rng(seed)
    fell = rng.uniform(size=runs) < 0.5
    lab = corpus.labels(fell, np.where(fell, 0.01, -1.0), T, 10, 0.002)
    return dict(features=rng.normal(size=(runs, T, len(corpus.FEATURES))).astype(np.float32), **lab, fell=fell,
                angle_error=np.where(fell, 180.0, 1.0), fall_time=np.where(fell, 0.01, -1.0),
                actions=np.zeros((runs, T), np.int32), grasps=np.zeros((runs, T), np.int32),
                episode=np.arange(runs, dtype=np.int32) % 2, kind=np.arange(runs, dtype=np.int32) // 2,
                kinds=np.array(["four-tips", "dp-opt"]), episode_names=np.array([f"s{seed}-a", f"s{seed}-b"]))


def test_the_store_refuses_another_models_corpus_and_a_broken_one_by_name(tmp_path):
    wrench, hammer = model_lib.load_model("wrench"), model_lib.load_model("hammer")
    store = corpus.Store.open(tmp_path, wrench)
    store.add(0, _arrays(0))
    with pytest.raises(corpus.CorpusError, match=r"a corpus of model 'wrench' .*not of 'hammer'"):
        corpus.Store.open(tmp_path, hammer)
    with pytest.raises(corpus.CorpusError, match="shard 0 is already in the corpus"):
        store.add(0, _arrays(0))
    (tmp_path / "shard-000000.npz").write_bytes(b"PK not that shard")
    with pytest.raises(corpus.CorpusError, match=r"shard-000000.npz: not the shard the manifest lists"):
        corpus.Store.open(tmp_path, wrench).load()
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    del manifest["digest"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(corpus.CorpusError, match=r"manifest.json: the manifest has no field 'digest'"):
        corpus.Store.open(tmp_path, wrench)


_PHYS = types.SimpleNamespace(config=PhysicsConfig())  # what `extend` reads of a `Physics` when `shard` is stubbed


def test_a_corpus_is_extended_only_with_the_physics_settings_its_runs_had(tmp_path, monkeypatch):
    """A corpus records the controller its runs had and the physics' revision: another controller (the paper's, a
    changed gain) or revision is refused by name, and so is a corpus made before corpora recorded it; the same
    settings extend it."""
    wrench = model_lib.load_model("wrench")
    monkeypatch.setattr(corpus, "shard", lambda phys, seed, *a, **k: _arrays(seed))
    corpus.extend(corpus.Store.open(tmp_path, wrench), _PHYS, [0], episodes=2, progress=False)
    store = corpus.Store.open(tmp_path, wrench)
    assert store.manifest["physics"]["controller"]["rotation_step"] == PhysicsConfig().controller.rotation_step
    paper = types.SimpleNamespace(config=PhysicsConfig.named("paper"))
    with pytest.raises(corpus.CorpusError, match=r"other physics settings \(.*controller\.frames 'measured' there, "
                                                 r"'nominal' here"):
        corpus.extend(store, paper, [1], episodes=2, progress=False)
    stiffer = types.SimpleNamespace(config=PhysicsConfig().replace(rotation_step=0.5))
    with pytest.raises(corpus.CorpusError, match=r"controller\.rotation_step 0\.3 there, 0\.5 here"):
        corpus.extend(store, stiffer, [1], episodes=2, progress=False)
    assert corpus.extend(store, _PHYS, [0, 1], episodes=2, progress=False) == [1]
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["physics_revision"] == 2
    del manifest["physics_revision"]  # made before the CoM offsets reached C MuJoCo
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(corpus.CorpusError, match=r"the physics' revision 1, this library simulates revision 2"):
        corpus.extend(corpus.Store.open(tmp_path, wrench), _PHYS, [2], episodes=2, progress=False)
    del manifest["physics"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(corpus.CorpusError, match=r"its 2 shards do not record the physics settings"):
        corpus.extend(corpus.Store.open(tmp_path, wrench), _PHYS, [2], episodes=2, progress=False)


def test_a_corpus_in_a_world_gap_records_it_draws_per_episode_and_is_not_mixed(tmp_path, monkeypatch):
    """`corpus --world gap`: every shard runs in worlds drawn from the gap (one per episode, from the shard's seed,
    apart from its episodes' draw); the manifest records the gap, and a corpus is extended only in its own world
    (a nominal corpus, one made before worlds included, refuses a gap and the other way round)."""
    from gsp_jax.physics import world

    wrench = model_lib.load_model("wrench")
    gap = world.Gap.named("gap")
    batch = scenario.stack(list(corpus.draw(corpus.Distribution(), 3, 4, wrench).values()))
    hand = wrench.hand
    assert corpus.worlds(None, 3, batch, hand) is None and corpus.worlds(world.Gap(), 3, batch, hand) is None
    w = corpus.worlds(gap, 3, batch, hand)
    assert np.asarray(w.friction).shape == (4, len(hand.touch_tool)) and len(set(np.asarray(w.mass).tolist())) == 4
    np.testing.assert_array_equal(w.strength, corpus.worlds(gap, 3, batch, hand).strength)  # one seed, one draw
    assert not np.array_equal(w.strength, corpus.worlds(gap, 4, batch, hand).strength)
    seen = []
    monkeypatch.setattr(corpus, "shard", lambda phys, seed, *a, **k: seen.append(a[-1]) or _arrays(seed))
    corpus.extend(corpus.Store.open(tmp_path / "gap", wrench), _PHYS, [0], episodes=2, progress=False, gap=gap)
    assert seen == [gap]
    store = corpus.Store.open(tmp_path / "gap", wrench)
    assert store.manifest["world"]["strength"] == gap.strength and store.manifest["world"]["delay"] == gap.delay
    with pytest.raises(corpus.CorpusError, match=r"its runs are in the gap \{.*\}, not in the nominal model"):
        corpus.extend(store, _PHYS, [1], episodes=2, progress=False)
    corpus.extend(corpus.Store.open(tmp_path / "nominal", wrench), _PHYS, [0], episodes=2, progress=False)
    nominal = corpus.Store.open(tmp_path / "nominal", wrench)
    assert nominal.manifest["world"] == {}
    with pytest.raises(corpus.CorpusError, match=r"its runs are in the nominal model \(no gap\), not in the gap"):
        corpus.extend(nominal, _PHYS, [1], episodes=2, progress=False, gap=gap)
    manifest = json.loads((tmp_path / "nominal" / "manifest.json").read_text())
    del manifest["world"]  # made before worlds: the model's runs
    (tmp_path / "nominal" / "manifest.json").write_text(json.dumps(manifest))
    assert corpus.extend(corpus.Store.open(tmp_path / "nominal", wrench), _PHYS, [1], episodes=2,
                         progress=False) == [1]


def test_extend_resumes_after_a_kill_with_nothing_lost_or_duplicated(tmp_path, monkeypatch):
    """A run killed after writing shard 1 but before listing it, then the same call again: every seed's shard once,
    the load their runs in seed order (episodes renumbered over the corpus)."""
    wrench = model_lib.load_model("wrench")
    monkeypatch.setattr(corpus, "shard", lambda phys, seed, *a, **k: _arrays(seed))
    store = corpus.Store.open(tmp_path, wrench)
    assert corpus.extend(store, _PHYS, [0], episodes=2, progress=False) == [0]
    real_write = corpus.files.write_json

    def killed(path, obj, **kw):  # the kill: the shard is on disk, the manifest is not rewritten
        if path.name == "manifest.json":
            raise KeyboardInterrupt
        return real_write(path, obj, **kw)

    monkeypatch.setattr(corpus.files, "write_json", killed)
    with pytest.raises(KeyboardInterrupt):
        corpus.extend(corpus.Store.open(tmp_path, wrench), _PHYS, [1, 2], episodes=2, progress=False)
    monkeypatch.setattr(corpus.files, "write_json", real_write)
    store = corpus.Store.open(tmp_path, wrench)
    assert store.seeds == {0}
    assert corpus.extend(store, _PHYS, [0, 1, 2], episodes=2, progress=False) == [1, 2]
    again = corpus.Store.open(tmp_path, wrench)
    assert [s["seed"] for s in again.manifest["shards"]] == [0, 1, 2]
    data = again.load()
    want = [_arrays(s) for s in (0, 1, 2)]
    np.testing.assert_array_equal(data["features"], np.concatenate([w["features"] for w in want]))
    np.testing.assert_array_equal(data["episode"], np.concatenate([w["episode"] + 2 * i for i, w in enumerate(want)]))
    assert list(data["episode_names"]) == [n for w in want for n in w["episode_names"]]


def test_a_real_shard_agrees_with_the_surrogate_and_c_mujoco():
    """Two drawn episodes (their first 2 waypoints) x (four tips, DP optimal, one random, one perturbation) in C
    MuJoCo: every feature finite; each transition's reward feature is the DP table's entry for it (the table's batched
    kernels against the surrogate's replay); the labels say a run fell exactly where C MuJoCo says it did, and the
    perturbation differs from its base in at most one step."""
    import jax.numpy as jnp

    from gsp_jax.planning import dp
    from gsp_jax import physics
    from gsp_jax.surrogate.step import Surrogate
    import tolerances as tol

    phys = physics.Physics(Surrogate(learned=False))
    got = corpus.shard(phys, seed=7, n_episodes=2, dist=corpus.Distribution(), n_random=1, n_perturbed=1, n_steps=2)
    M, T, F = got["features"].shape
    assert (M, T, F) == (8, 2, len(corpus.FEATURES)) and list(got["kinds"]) == ["four-tips", "dp-opt", "random0",
                                                                               "perturbed0"]
    assert np.all(np.isfinite(got["features"]))
    assert np.array_equal(got["fell_here"].any(1), got["fell"]) and np.all(got["alive"][:, 0])
    assert got["features"][:, :, corpus.FEATURES.index("t")].tolist() == [[0.0, 1.0]] * M
    batch = scenario.stack([e.head(2) for e in corpus.draw(corpus.Distribution(), 7, 2).values()])
    tables = corpus.solve_batch(phys.surrogate, batch)[0]  # the table's batched kernels (compiled for the shard)
    pick = lambda tree, e: jax.tree.map(lambda x: x[e], tree)  # noqa: E731
    want = np.stack([dp.sequence_rewards(pick(tables, int(e)), batch.start_grasp[int(e)], jnp.asarray(a))
                     for e, a in zip(got["episode"], got["actions"])])
    off = np.abs(got["features"][:, :, corpus.FEATURES.index("reward")] - want) > tol.REWARD_ATOL
    assert off.sum() <= 1, off  # at most one IK bifurcation (tests/tolerances.py: TIE_RATE) in 16 transitions
    pert, bases = got["actions"][got["kind"] == 3], got["actions"][(got["kind"] == 1) | (got["kind"] == 2)]
    for e in range(2):
        assert min(int(np.sum(pert[e] != b)) for b in bases[[e, e + 2]]) <= 1


def test_a_learned_surrogates_runs_get_the_analytic_features():
    """`corpus --learned` plans with the learned term but records the analytic features: `run_features` of the
    wrench's learned surrogate equals that of its analytic one, run for run (it once failed inside the trace)."""
    from gsp_jax.surrogate.step import Surrogate

    learned_sur = Surrogate(learned=True)
    assert learned_sur.learned is not None
    eps = [e.head(2) for e in corpus.draw(corpus.Distribution(), 3, 2).values()]
    runs = scenario.stack(eps)
    actions = np.array([[0, 5], [3, 0]], np.int32)
    got = corpus.run_features(learned_sur, runs, actions)
    want = corpus.run_features(Surrogate(learned=False), runs, actions)
    assert got.shape == (2, 2, len(corpus.FEATURES)) and np.all(np.isfinite(got))
    np.testing.assert_array_equal(got, want)
