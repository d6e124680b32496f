"""Tests of gsp_jax.ppo: the categorical distribution against float64 numpy, GAE against its definition, the
clipped PPO loss's gradient against its closed form, learning on a probe problem whose optimum the DP knows,
bit-exact checkpoint resume, config checks, and the policy save/load round trip.

No IK anywhere: the environments step synthetic `dp.Table`s (the real grasp space's transitions, hand-made
rewards) over real scenario episodes cut to T = 3 waypoints, with small networks, so every compiled function is
cheap. One Trainer is compiled per module; its one uninterrupted run on the probe is both the learning test and
the reference of the resume tests.
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import subprocess
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from scipy import stats  # noqa: E402

from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.core import files  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.learning.env import GraspEnv  # noqa: E402
from gsp_jax.ppo import losses  # noqa: E402
from gsp_jax.ppo import networks as nets  # noqa: E402
from gsp_jax.ppo import train as ppo  # noqa: E402

T = 3  # waypoints (decisions) of the probe episodes
SMALL = nets.NetworkConfig(hidden=(32, 32))


def _differing_leaves(a, b) -> list[str]:
    """Paths of the leaves of two pytrees (same structure) that are not exactly equal."""
    pa, ta = jax.tree_util.tree_flatten_with_path(a)
    pb, tb = jax.tree_util.tree_flatten_with_path(b)
    assert ta == tb, "tree structures differ"
    return [
        jax.tree_util.keystr(k) for (k, x), (_, y) in zip(pa, pb) if not np.array_equal(np.asarray(x), np.asarray(y))
    ]


# ------------------------------------------------------------------------------------------ 1. distribution
def _log_softmax64(logits):
    x = np.asarray(logits, np.float64)
    m = x.max(axis=-1, keepdims=True)
    return x - m - np.log(np.sum(np.exp(x - m), axis=-1, keepdims=True))


@pytest.mark.parametrize("scale", [1.0, 30.0, 1e3])
def test_log_prob_and_entropy_match_float64_softmax(scale):
    """log_prob and entropy equal a float64 numpy softmax computed by hand, for ordinary and large logits."""
    rng = np.random.default_rng(int(scale))
    logits = (rng.normal(size=(5, 7, 16)) * scale + rng.normal(size=(5, 7, 1)) * scale).astype(np.float32)
    action = rng.integers(0, 16, size=(5, 7))
    ref_logp = _log_softmax64(logits)
    want = np.take_along_axis(ref_logp, action[..., None], -1)[..., 0]
    got = np.asarray(nets.log_prob(jnp.asarray(logits), jnp.asarray(action)))
    assert got.shape == (5, 7) and np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * max(1.0, scale))
    p = np.exp(ref_logp)
    ref_ent = -np.sum(np.where(p > 0, p * ref_logp, 0.0), axis=-1)
    got_ent = np.asarray(nets.entropy(jnp.asarray(logits)))
    assert np.all(np.isfinite(got_ent)) and np.all(got_ent >= -1e-6) and np.all(got_ent <= np.log(16) + 1e-5)
    np.testing.assert_allclose(got_ent, ref_ent, rtol=1e-4, atol=1e-5)


def test_entropy_extremes():
    """Uniform logits have entropy log A; a one-hot (one logit 1e4 above the rest) has entropy 0."""
    np.testing.assert_allclose(nets.entropy(jnp.zeros((3, 16))), np.full(3, np.log(16)), rtol=1e-6)
    peaked = jnp.zeros(16).at[4].set(1e4)
    np.testing.assert_allclose(nets.entropy(peaked), 0.0, atol=1e-6)
    np.testing.assert_allclose(nets.log_prob(peaked, jnp.int32(4)), 0.0, atol=1e-6)


def test_sample_frequencies_match_softmax_and_mode_is_argmax():
    """200,000 samples from an explicit key: per-row chi-square against the softmax probabilities stays below the
    1e-6 tail quantile (a sampler of other probabilities exceeds it by far); mode is numpy's argmax."""
    rng = np.random.default_rng(3)
    logits = np.stack([rng.normal(size=16) * 1.5, np.linspace(-3, 3, 16)]).astype(np.float32)  # (2, 16)
    n = 200_000
    samples = np.asarray(nets.sample(jax.random.PRNGKey(42), jnp.broadcast_to(jnp.asarray(logits), (n, 2, 16))))
    assert samples.dtype == np.int32 and samples.shape == (n, 2)
    limit = stats.chi2.ppf(1 - 1e-6, df=15)
    for row in range(2):
        p = np.exp(_log_softmax64(logits[row]))
        counts = np.bincount(samples[:, row], minlength=16)
        chi2 = np.sum((counts - n * p) ** 2 / (n * p))
        assert chi2 < limit, f"row {row}: chi2 {chi2:.1f} >= {limit:.1f}; counts {counts}, expected {n * p}"
        wrong = np.exp(_log_softmax64(-logits[row]))  # the test discriminates: the reversed distribution fails
        assert np.sum((counts - n * wrong) ** 2 / (n * wrong)) > 100 * limit
    many = rng.normal(size=(50, 16)).astype(np.float32)
    np.testing.assert_array_equal(nets.mode(jnp.asarray(many)), np.argmax(many, axis=-1))
    ties = np.zeros((2, 16), np.float32)
    ties[0, [3, 9]] = 2.0
    ties[1, [0, 15]] = -1.0  # zeros elsewhere: the first maximum is index 1
    np.testing.assert_array_equal(nets.mode(jnp.asarray(ties)), [3, 1])


# ------------------------------------------------------------------------------------------ 2. GAE
def _gae_by_definition(r, v, d, boot, gamma, lam):
    """A_u = sum_l (gamma lam)^(l-u) delta_l over the rest of u's episode segment in the rollout (stopping after
    the step that ends it), delta_l = r_l + gamma V_{l+1} [not if l ends the episode] - V_l, V_U = bootstrap.
    Plain loops in float64."""
    n_u, n_b = r.shape
    vv = np.concatenate([v, boot[None]], 0).astype(np.float64)
    adv = np.zeros((n_u, n_b))
    for b in range(n_b):
        for u in range(n_u):
            total = 0.0
            for k, step in enumerate(range(u, n_u)):
                delta = r[step, b] + (0.0 if d[step, b] else gamma * vv[step + 1, b]) - vv[step, b]
                total += (gamma * lam) ** k * delta
                if d[step, b]:
                    break
            adv[u, b] = total
    return adv


def _returns(r, d, boot, gamma):
    """Monte-Carlo returns within each episode segment: discounted rewards to the episode's end, plus the
    discounted bootstrap where the rollout ends first."""
    n_u, n_b = r.shape
    out = np.zeros((n_u, n_b))
    for b in range(n_b):
        for u in range(n_u):
            total, ended = 0.0, False
            for k, step in enumerate(range(u, n_u)):
                total += gamma**k * r[step, b]
                if d[step, b]:
                    ended = True
                    break
            if not ended:
                total += gamma ** (n_u - u) * boot[b]
            out[u, b] = total
    return out


def _rollout_data(seed, n_u=9, n_b=5):
    rng = np.random.default_rng(seed)
    r = rng.normal(size=(n_u, n_b)).astype(np.float32)
    v = rng.normal(size=(n_u, n_b)).astype(np.float32)
    d = rng.random((n_u, n_b)) < 0.25
    d[3, 0] = d[7, 0] = True  # dones in the middle, twice in one env
    d[:, 1] = False  # an env whose episode runs past the rollout
    d[-1, 2] = True  # one that ends exactly at the last step (no bootstrap)
    boot = rng.normal(size=n_b).astype(np.float32)
    return r, v, d, boot


@pytest.mark.parametrize("gamma,lam", [(0.9, 0.8), (0.99, 0.95), (1.0, 0.5)])
def test_gae_matches_definition_with_dones(gamma, lam):
    """losses.gae equals the explicit sum of discounted TD errors over each episode segment, and target = A + V."""
    r, v, d, boot = _rollout_data(0)
    adv, target = losses.gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), jnp.asarray(boot), gamma, lam)
    want = _gae_by_definition(r, v, d, boot, gamma, lam)
    np.testing.assert_allclose(adv, want, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(target, want + v, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_gae_lambda_one_targets_are_monte_carlo_returns(gamma):
    """With lambda = 1 the value targets are the (discounted) Monte-Carlo returns within each episode segment,
    plus the bootstrap where the rollout cuts an episode: independent of the values V."""
    r, v, d, boot = _rollout_data(1)
    _, target = losses.gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), jnp.asarray(boot), gamma, 1.0)
    np.testing.assert_allclose(target, _returns(r, d, boot, gamma), rtol=1e-5, atol=1e-5)
    _, target2 = losses.gae(jnp.asarray(r), jnp.asarray(v * 3 + 1), jnp.asarray(d), jnp.asarray(boot), gamma, 1.0)
    np.testing.assert_allclose(target2, target, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------------------------------ 3. PPO loss
class _DirectNets:
    """A stand-in for Networks whose 'parameters' are the logits (N, A) and values (N,) themselves, so the
    loss's gradient can be compared with its closed form per sample."""

    @staticmethod
    def logits(params, obs):
        return params["logits"]

    @staticmethod
    def value(params, obs):
        return params["value"]


def test_ppo_loss_gradient_matches_closed_form_with_clipping():
    """d loss / d logits and d loss / d values equal the closed form: per sample -(A_i / N) r_i (onehot - p)
    unless the clip is active (A > 0, r > 1 + eps or A < 0, r < 1 - eps: zero), plus the entropy bonus
    (ent_coef / N) p (log p + H), and vf_coef (V - target) / N for the critic. Checked at ratios 1, above and
    below the clip range, for both signs of the advantage; clip_fraction too."""
    rng = np.random.default_rng(5)
    n, a_n, clip, vf, ent = 16, 16, 0.2, 0.5, 0.01
    logits = rng.normal(size=(n, a_n)).astype(np.float32)
    value = rng.normal(size=n).astype(np.float32)
    target = rng.normal(size=n).astype(np.float32)
    action = rng.integers(0, a_n, n)
    logp = np.take_along_axis(_log_softmax64(logits), action[:, None], 1)[:, 0]
    log_ratio = np.tile([0.0, np.log(1.5), np.log(0.5), np.log(1.1)], n // 4)  # r = 1, 1.5, 0.5, 1.1
    adv = np.repeat([1.0, -1.0], n // 2) * rng.uniform(0.5, 2.0, n)  # both signs at every ratio
    adv -= adv.mean()  # normalisation then keeps the signs (std only rescales)
    batch = losses.Batch(
        obs=jnp.zeros((n, 1)),
        action=jnp.asarray(action, jnp.int32),
        log_prob=jnp.asarray(logp - log_ratio, jnp.float32),
        value=jnp.asarray(value),
        advantage=jnp.asarray(adv, jnp.float32),
        target=jnp.asarray(target),
    )
    params = {"logits": jnp.asarray(logits), "value": jnp.asarray(value)}
    loss_fn = lambda p, b: losses.ppo_loss(p, _DirectNets(), b, clip, vf, ent)  # noqa: E731
    loss_and_grad = jax.jit(jax.value_and_grad(loss_fn, has_aux=True))
    (loss, metrics), grads = loss_and_grad(params, batch)

    a_norm = (adv - adv.mean()) / (adv.std() + 1e-8)
    ratio = np.exp(log_ratio)
    clipped = ((a_norm > 0) & (ratio > 1 + clip)) | ((a_norm < 0) & (ratio < 1 - clip))
    lp = _log_softmax64(logits)
    p = np.exp(lp)
    onehot = np.eye(a_n)[action]
    h = -np.sum(p * lp, axis=1)
    g_policy = np.where(clipped[:, None], 0.0, -(a_norm * ratio)[:, None] * (onehot - p)) / n
    g_entropy = ent * p * (lp + h[:, None]) / n
    np.testing.assert_allclose(grads["logits"], g_policy + g_entropy, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(grads["value"], vf * (value - target) / n, rtol=1e-5, atol=1e-7)
    # the clipped samples' policy gradient vanishes: only the entropy term is left there
    np.testing.assert_allclose(np.asarray(grads["logits"])[clipped], g_entropy[clipped], atol=1e-6)
    assert clipped.sum() == n // 4  # r = 1.5 with A > 0 and r = 0.5 with A < 0
    # the loss value and the diagnostics against the same numpy quantities
    policy_loss = -np.mean(np.minimum(ratio * a_norm, np.clip(ratio, 1 - clip, 1 + clip) * a_norm))
    want = policy_loss + vf * 0.5 * np.mean((value - target) ** 2) - ent * np.mean(h)
    np.testing.assert_allclose(float(loss), want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["clip_fraction"]), np.mean(np.abs(ratio - 1) > clip), atol=1e-7)
    np.testing.assert_allclose(float(metrics["entropy"]), np.mean(h), rtol=1e-5)


# ------------------------------------------------------------------------------------------ 4. probe problem
def _probe_tables(space, start_grasps, seed) -> tuple[dp.Table, list[np.ndarray]]:
    """Synthetic tables (N, ...) over the real grasp space: reward -1 everywhere, except 0 for one action per step
    along one path from the episode's start grasp (that action only, and only from that path's grasp), and four
    actions that drop the tool at the first step (-5, terminal). Each episode has its own path. Returns the
    stacked tables and the paths' action sequences."""
    g_n, a_n = space.n_grasps, space.n_actions
    nxt = np.asarray(space.apply(jnp.arange(g_n)[:, None], jnp.arange(a_n)[None])[0], np.int32)
    rng = np.random.default_rng(seed)
    out, seqs = [], []
    for start in start_grasps:
        reward = np.full((g_n, a_n, T), -1.0, np.float32)
        terminal = np.zeros((g_n, a_n, T), bool)
        terminal[:, :, -1] = True
        seq = rng.choice(a_n, T, replace=False)
        g = int(start)
        for t, a in enumerate(seq):
            reward[g, a, t] = 0.0
            g = int(nxt[g, a])
        traps = rng.choice(np.setdiff1d(np.arange(a_n), seq), 4, replace=False)
        reward[int(start), traps, 0] = -5.0
        terminal[int(start), traps, 0] = True
        out.append(
            dp.Table(
                reward=reward,
                next_grasp=nxt,
                terminal=terminal,
                ik_error=np.zeros((g_n, T), np.float32),
                q=np.zeros((g_n, T, 16), np.float32),
            )
        )
        seqs.append(seq)
    return jax.tree.map(lambda *x: jnp.asarray(np.stack(x)), *out), seqs


@pytest.fixture(scope="module")
def probe(sur):
    """Two real episodes (nominal, +6 mm / -1 N m) cut to T, each with its own synthetic table: the training env
    (auto-reset), the evaluation env (absorbing) and the DP solutions."""
    episodes = scenario.stack([scenario.make_episode().head(T), scenario.make_episode(shift_mm=6, torque=-1.0).head(T)])
    tables, seqs = _probe_tables(sur.space, np.asarray(episodes.start_grasp), seed=0)
    sols = jax.vmap(dp.backup)(tables, episodes.start_grasp)
    env = GraspEnv(sur, episodes, tables=tables)
    eval_env = GraspEnv(sur, episodes, tables=tables, auto_reset=False)
    return dict(env=env, eval_env=eval_env, sols=sols, seqs=seqs, episodes=episodes)


CONFIG = ppo.PPOConfig(
    n_envs=64, unroll=T, epochs=4, minibatches=4, learning_rate=3e-3, max_iterations=40, eval_every=5,
    patience=0, checkpoint_every=10, reward_scale=1.0,
)
SEED = 1


@pytest.fixture(scope="module")
def trainer(probe, sur):
    """The module's one Trainer (compiled once): PPO on the probe, with two evaluation sets, 'val' (the probe, the
    early-stop set) and 'aux' (the same episodes, every reward -7, no early end; sorted before 'val', so a mix-up
    of the two would show)."""
    networks = nets.make_networks(probe["env"].observation_size, probe["env"].action_size, SMALL)
    tables = probe["eval_env"].tables
    constant = tables.replace(
        reward=jnp.full_like(tables.reward, -7.0), terminal=jnp.zeros_like(tables.terminal).at[..., -1].set(True)
    )
    aux = GraspEnv(sur, probe["episodes"], tables=constant, auto_reset=False)
    return ppo.Trainer(probe["env"], networks, CONFIG, eval_envs={"val": probe["eval_env"], "aux": aux})


@pytest.fixture(scope="module")
def uninterrupted(trainer, tmp_path_factory):
    """The module's reference PPO run: one call from iteration 0 to max_iterations, in its own checkpoint dir."""
    return ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path_factory.mktemp("full"), progress=False)


def test_ppo_learns_the_probe_optimum(probe, trainer, uninterrupted):
    """PPO's best validated policy, rolled out greedily (ppo.greedy_returns), earns the DP optimum on both
    episodes (within 0.5: any wrong action costs at least 1, so this is the designed sequence), having started
    well below it."""
    result = uninterrupted
    opt = np.asarray(probe["sols"].ret)
    greedy = np.asarray(jax.jit(lambda p: ppo.greedy_returns(probe["eval_env"], trainer.networks, p))(result.policy))
    start = result.history[0]["val_return"]
    assert start <= opt.mean() - 1.0, f"the untrained policy already solves the probe ({start})"
    np.testing.assert_allclose(greedy, opt, atol=0.5, err_msg=f"greedy {greedy}, DP optimum {opt}")
    # the recorded best validation return is that greedy return, on 'val' and not on 'aux' (constant -7 T)
    np.testing.assert_allclose(float(result.state.best_return), greedy.mean(), atol=1e-6)
    assert all(h["aux_return"] == -7.0 * T for h in result.history if "aux_return" in h)
    # history: one record per iteration, validations where eval_every says, parameters moved from the init
    iterations = list(range(CONFIG.max_iterations + 1))
    assert [h["iteration"] for h in result.history] == iterations
    assert [h["iteration"] for h in result.history if "val_return" in h] == iterations[:: CONFIG.eval_every]
    assert _differing_leaves(trainer.init(jax.random.PRNGKey(SEED)).params, result.state.params)


def test_target_kl_stops_the_iterations_remaining_steps(probe, trainer):
    """With target_kl tiny the first minibatch step (KL 0: the rollout's own policy, up to float32 last bits ~1e-14)
    is applied and every later one (KL of a step at lr 3e-3, far above 1e-6) is skipped; with None all epochs x
    minibatches steps are. The learning rate is the schedule's at the iteration's first step."""
    key = jax.random.PRNGKey(SEED)
    for target, steps in ((1e-6, 1), (None, CONFIG.epochs * CONFIG.minibatches)):
        cfg = dataclasses.replace(CONFIG, target_kl=target)
        tr = ppo.Trainer(probe["env"], trainer.networks, cfg, eval_envs={"val": probe["eval_env"]})
        ts0 = tr.init(key)
        ts1, metrics = tr.iteration(ts0)
        assert int(metrics["sgd_steps"]) == steps, (target, metrics)
        assert _differing_leaves(ts0.params, ts1.params)
        np.testing.assert_allclose(float(metrics["learning_rate"]), CONFIG.learning_rate, rtol=1e-6)
        if target is not None:
            assert float(metrics["approx_kl"]) > target  # the skipped minibatches' KL, measured and not acted on
    with pytest.raises(ValueError, match=r"PPOConfig\.target_kl\b"):
        ppo.PPOConfig(target_kl=0.0)


# ------------------------------------------------------------------------------------------ 5. checkpoints
def _assert_same_run(resumed: ppo.TrainResult, full: ppo.TrainResult):
    assert int(resumed.state.iteration) == int(full.state.iteration) == CONFIG.max_iterations
    assert not _differing_leaves(resumed.state.params, full.state.params)
    assert not _differing_leaves(resumed.state.best_params, full.state.best_params)
    bad = _differing_leaves(resumed.state, full.state)  # and everything else: Adam moments, envs, key, best return
    assert not bad, f"leaves differ after resume: {bad}"
    assert [h["iteration"] for h in resumed.history] == list(range(CONFIG.max_iterations + 1))
    for key in ("train_return", "val_return", "aux_return", "policy_loss", "value_loss", "entropy", "episodes"):
        assert [h.get(key) for h in resumed.history] == [h.get(key) for h in full.history], key


@pytest.mark.parametrize("stop_after", [20, 25])
def test_resume_after_stop_is_bit_exact(trainer, uninterrupted, tmp_path, stop_after):
    """train(stop_after=k) then train again in the same directory reaches max_iterations with every leaf of the
    final TrainState (params, best_params, Adam state, envs, key) and the history's returns and losses exactly
    equal to an uninterrupted run's; k = 20 is a checkpoint boundary (checkpoint_every = 10), k = 25 is not."""
    first = ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False, stop_after=stop_after)
    assert int(first.state.iteration) == stop_after and len(first.history) == stop_after + 1
    resumed = ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    _assert_same_run(resumed, uninterrupted)


def test_resume_after_kill_between_checkpoints_is_bit_exact(trainer, uninterrupted, tmp_path, monkeypatch):
    """A run killed (an exception) during iteration 25, after the checkpoint at 20, resumes from 20, redoes
    21..25 and ends bit-exactly where the uninterrupted run does."""
    real = trainer.iteration

    class Killed(Exception):
        pass

    def killed_at_25(ts):
        if int(ts.iteration) == 24:
            raise Killed
        return real(ts)

    monkeypatch.setattr(trainer, "iteration", killed_at_25)
    with pytest.raises(Killed):
        ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    monkeypatch.setattr(trainer, "iteration", real)
    saved = sorted(int(p.name) for p in (tmp_path / "checkpoints").iterdir() if p.name.isdigit())
    assert saved and max(saved) == 20, f"checkpoints on disk: {saved}"
    resumed = ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    _assert_same_run(resumed, uninterrupted)


@pytest.mark.parametrize("damage", ["array", "history"])
def test_resume_falls_back_past_a_truncated_checkpoint_step(trainer, uninterrupted, tmp_path, damage):
    """A crash that truncated the latest checkpoint step (an array file, or its history JSON) is reported with the
    step's path, and the run resumes from the step before it: nothing intact is lost, and it ends bit-exactly where
    the uninterrupted run does."""
    ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False, stop_after=20)  # steps 10 and 20
    step = tmp_path / "checkpoints" / "20"
    if damage == "history":
        victims = [p for p in step.rglob("*") if p.is_file() and p.parent.name == "history"]
    else:
        victims = [p for p in step.rglob("*") if p.is_file() and "state" in p.parts and p.stat().st_size > 64
                   and "d" in p.parent.name]
        victims = victims or [max((p for p in step.rglob("*") if p.is_file() and "state" in p.parts),
                                  key=lambda p: p.stat().st_size)]
    for v in victims:
        v.write_bytes(v.read_bytes()[: v.stat().st_size // 3])
    with pytest.warns(UserWarning, match=rf"checkpoint {step} cannot be read .*resuming from the step before it"):
        resumed = ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    _assert_same_run(resumed, uninterrupted)


def test_a_second_run_on_the_same_folder_is_refused(trainer, tmp_path):
    """Two runs on one checkpoint folder at once: the second is refused naming the folder and the first's process
    (the folder's lock); the first's checkpoints are untouched."""
    import subprocess
    import sys

    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom gsp_jax import files\n"
                               "with files.folder_lock(sys.argv[1]):\n    print('locked', flush=True)\n"
                               "    time.sleep(60)", str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(files.FolderInUse, match=rf"{tmp_path}: in use by process {holder.pid}"):
            ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False, stop_after=1)
        assert not (tmp_path / "checkpoints").exists()
    finally:
        holder.kill()
        holder.wait()


# ------------------------------------------------------------------------------------------ 6. config checks
def test_different_run_in_the_same_checkpoint_dir_is_refused(trainer, probe, tmp_path):
    """A checkpoint_dir holding a run refuses a different config, seed or network config (ValueError naming the
    field), and accepts the same run again."""
    ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False, stop_after=1)
    other_cfg = dataclasses.replace(CONFIG, learning_rate=2e-3)
    other = ppo.Trainer(probe["env"], trainer.networks, other_cfg, eval_envs={"val": probe["eval_env"]})
    with pytest.raises(ValueError, match=r"different config \(config\.learning_rate: 0\.003 -> 0\.002\)"):
        ppo.train(other, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    with pytest.raises(ValueError, match="different seed"):
        ppo.train(trainer, seed=SEED + 1, checkpoint_dir=tmp_path, progress=False, stop_after=1)
    wider = nets.make_networks(probe["env"].observation_size, 16, nets.NetworkConfig(hidden=(32, 32, 32)))
    other_nets = ppo.Trainer(probe["env"], wider, CONFIG, eval_envs={"val": probe["eval_env"]})
    with pytest.raises(ValueError, match="different networks"):
        ppo.train(other_nets, seed=SEED, checkpoint_dir=tmp_path, progress=False)
    again = ppo.train(trainer, seed=SEED, checkpoint_dir=tmp_path, progress=False, stop_after=1)
    assert int(again.state.iteration) == 1


@pytest.mark.parametrize(
    "kwargs,field",
    [
        (dict(n_envs=16, unroll=3, minibatches=5), "minibatches"),  # 48 is not a multiple of 5
        (dict(n_envs=0), "n_envs"),
        (dict(unroll=0), "unroll"),
        (dict(epochs=0), "epochs"),
        (dict(learning_rate=0.0), "learning_rate"),
        (dict(checkpoint_every=0), "checkpoint_every"),
    ],
)
def test_ppo_config_validation_names_the_field(kwargs, field):
    """An invalid PPOConfig raises ValueError naming PPOConfig.<field>."""
    with pytest.raises(ValueError, match=rf"PPOConfig\.{field}\b"):
        ppo.PPOConfig(**kwargs)


def test_valid_configs_and_trainer_arguments():
    """Configs at the edge of validity are accepted (minibatches dividing n_envs * unroll); a Trainer without
    evaluation envs is refused naming eval_envs."""
    ppo.PPOConfig(n_envs=16, unroll=3, minibatches=48)
    ppo.PPOConfig(n_envs=1, unroll=1, minibatches=1)
    with pytest.raises(ValueError, match="eval_envs"):
        ppo.Trainer(None, None, ppo.PPOConfig(n_envs=16, unroll=3, minibatches=4), eval_envs={})


# ------------------------------------------------------------------------------------------ 7. save / load
def test_save_and_load_policy_round_trip_is_exact(trainer, uninterrupted, probe, tmp_path):
    """save_policy then load_policy returns the trained Params exactly: same tree, array dtypes and shapes, every
    leaf equal, so the loaded policy's logits are identical; a missing path raises FileNotFoundError."""
    result = uninterrupted
    path = tmp_path / "policy"
    ppo.save_policy(path, result.policy)
    loaded = ppo.load_policy(path, trainer.networks)
    assert jax.tree.structure(loaded) == jax.tree.structure(result.policy)
    for x, y in zip(jax.tree.leaves(loaded), jax.tree.leaves(result.policy)):
        if np.ndim(y):  # (the normaliser's scalar std_eps comes back as the Python float the template holds)
            assert np.asarray(x).dtype == np.asarray(y).dtype and np.shape(x) == np.shape(y)
    assert not _differing_leaves(loaded, result.policy)
    # the loaded policy is not the fresh init the loader restores into
    assert _differing_leaves(loaded, trainer.networks.init(jax.random.PRNGKey(0)))
    obs = probe["env"].reset_to(0).obs
    np.testing.assert_array_equal(trainer.networks.logits(loaded, obs), trainer.networks.logits(result.policy, obs))
    with pytest.raises(FileNotFoundError):
        ppo.load_policy(tmp_path / "nothing_here", trainer.networks)


# ----------------------------------------------------------------------------------- 5. several devices
TWO_DEVICES = '''
import dataclasses, json
import jax, jax.numpy as jnp, numpy as np
import gsp_jax
gsp_jax.enable_cache()  # the run's test cache (GSP_JAX_CACHE, set by conftest)
from test_ppo import CONFIG, SMALL, T, _probe_tables
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate
from gsp_jax.learning.env import GraspEnv
from gsp_jax.ppo import networks as nets
from gsp_jax.ppo import train as ppo

assert len(jax.devices()) == 2, jax.devices()
sur = surrogate.Surrogate(learned=False)
episodes = scenario.stack([scenario.make_episode().head(T), scenario.make_episode(shift_mm=6, torque=-1.0).head(T)])
tables, _ = _probe_tables(sur.space, np.asarray(episodes.start_grasp), seed=0)
env, eval_env = GraspEnv(sur, episodes, tables=tables), GraspEnv(sur, episodes, tables=tables, auto_reset=False)
networks = nets.make_networks(env.observation_size, env.action_size, SMALL)
out = {}
# the same seed twice on two devices: the same curve, to the last bit
cfg = dataclasses.replace(CONFIG, max_iterations=8, eval_every=4)
two = ppo.Trainer(env, networks, cfg, {"val": eval_env})
runs = [ppo.train(two, seed=3, progress=False, checkpoint_dir=f"full{i}") for i in range(2)]
strip = lambda h: [{k: v for k, v in r.items() if k != "wall_s"} for r in h]
out["repeat_equal"] = strip(runs[0].history) == strip(runs[1].history)
out["env_devices"] = len(runs[0].state.env_state.obs.sharding.device_set)
# stopped at 4 and resumed on two devices: the uninterrupted curve; resumed on one device: it continues
ppo.train(two, seed=3, progress=False, checkpoint_dir="stopped", stop_after=4)
import shutil
shutil.copytree("stopped", "stopped_one")
out["resumed_equal"] = strip(ppo.train(two, seed=3, progress=False, checkpoint_dir="stopped").history) == strip(
    runs[0].history)
one = ppo.train(ppo.Trainer(env, networks, cfg, {"val": eval_env}, devices=jax.devices()[:1]), seed=3,
                progress=False, checkpoint_dir="stopped_one")
out["one_device_iterations"] = [h["iteration"] for h in one.history]
out["one_device_prefix_equal"] = strip(one.history[:5]) == strip(runs[0].history[:5])
# one whole-batch Adam step from the same start: the mean gradient over both devices' environments is the one
# device's gradient over all of them (the rows in another order: float rounding only)
step = dataclasses.replace(CONFIG, epochs=1, minibatches=1, target_kl=None)
params = {}
for name, devices in (("one", jax.devices()[:1]), ("two", jax.devices())):
    tr = ppo.Trainer(env, networks, step, {"val": eval_env}, devices=devices)
    ts, _ = tr.iteration(tr.init(jax.random.PRNGKey(3)))
    start = tr.init(jax.random.PRNGKey(3)).params
    params[name] = [np.asarray(x) for x in jax.tree.leaves((ts.params.actor, ts.params.critic))]
    params[name + "_moved"] = float(max(np.abs(np.asarray(a) - np.asarray(b)).max() for a, b in zip(
        jax.tree.leaves(ts.params.actor), jax.tree.leaves(start.actor))))
out["step_max_diff"] = float(max(np.abs(a - b).max() for a, b in zip(params["one"], params["two"])))
out["moved"] = params["one_moved"]
try:
    ppo.Trainer(env, networks, dataclasses.replace(CONFIG, n_envs=63, minibatches=1), {"val": eval_env})
except ValueError as e:
    out["error"] = str(e)
print("RESULT " + json.dumps(out))
'''


def test_data_parallel_on_two_devices_is_deterministic_and_averages_gradients_over_both(tmp_path):
    """PPO with its environments split over two (CPU) devices: the same seed gives the same curve twice, the
    environments live on both devices, a checkpoint resumes the run bit for bit (and on one device), and one
    whole-batch Adam step equals one device's step over the same environments (float rounding only: the
    all-reduced gradient is the mean over every device's rows)."""
    script = tmp_path / "two.py"
    script.write_text(TWO_DEVICES)
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=900, cwd=tmp_path,
                          env=dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="2",
                                   PYTHONPATH=os.pathsep.join([str(pathlib.Path(__file__).parent),
                                                               str(pathlib.Path(__file__).parents[1])])))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("RESULT ", 1)[1])
    assert out["repeat_equal"] and out["env_devices"] == 2
    assert out["resumed_equal"]  # a checkpoint of a run split over two devices resumes it bit for bit
    assert out["one_device_iterations"] == list(range(9)) and out["one_device_prefix_equal"]  # and on one device
    assert out["moved"] > 1e-4  # the step moved the weights ...
    assert out["step_max_diff"] < 1e-6 + 1e-3 * out["moved"], out  # ... and both ways the same
    assert "63 environments" in out["error"] and "2 devices" in out["error"], out["error"]
