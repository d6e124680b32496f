"""Gymnasium users' own tools on the registered environment (gsp_jax.learning.gym_env): gymnasium.make and its env
checker, seeding and episode choice against the brax env and the DP, RecordEpisodeStatistics, the native vector env
against Gymnasium's own SyncVectorEnv step for step (autoreset included), RecordVideo, and clear errors for bad
arguments.

Episodes: three reduced ones (T = 3 waypoints) written to a JSON file, so each table build is cheap; the built
environment is memoised per process, so every test here shares one set of tables.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import gymnasium as gym  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402

import gsp_jax  # noqa: E402, F401  (registers the environment)
from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.learning.gym_env import ENV_ID, GraspVectorEnv, GymGraspEnv, make_grasp_env  # noqa: E402

T = 3  # waypoints of the reduced episodes
N_ENVS = 6
RESERVED = {"episode", "_episode", "final_obs", "final_info", "TimeLimit.truncated", "terminal_observation"}


@pytest.fixture(scope="module")
def episodes_json(tmp_path_factory):
    eps = {
        "nominal": scenario.make_episode().head(T),
        "shift+6": scenario.make_episode(shift_mm=6, torque=-1.0).head(T),
        "mass1.5": scenario.eval_set_b()["mass1.5m0_comy+1cm"].head(T),
    }
    path = tmp_path_factory.mktemp("episodes") / "episodes.json"
    scenario.save(path, eps)
    return path


@pytest.fixture(scope="module")
def grasp_env(episodes_json, sur):
    """The table-backed GraspEnv of those episodes (what gym.make builds; memoised, so built once)."""
    return make_grasp_env(str(episodes_json), "table", sur, progress=False)


@pytest.fixture(scope="module")
def solutions(grasp_env):
    """The DP solutions of the three tables (numpy): policy (3, G, T) optimal actions, ret (3,) optimal returns."""
    sols = jax.jit(jax.vmap(dp.backup))(grasp_env.tables, grasp_env.episodes.start_grasp)
    return jax.tree.map(np.asarray, sols)


def _make(episodes_json, sur, **kwargs):
    return gym.make(ENV_ID, episodes=str(episodes_json), surrogate=sur, progress=False, **kwargs)


def test_make_passes_gymnasiums_env_checker_and_reuses_the_built_env(episodes_json, sur, grasp_env):
    env = _make(episodes_json, sur)
    check_env(env.unwrapped, skip_render_check=True)  # rendering needs GL: test_record_video_writes_a_readable_file
    assert env.action_space == gym.spaces.Discrete(17) and env.unwrapped.env.backend == "table"
    assert env.unwrapped.env.n_episodes == 3 and env.unwrapped.env.n_steps == T
    assert env.unwrapped.env is grasp_env  # same episodes, backend and surrogate: tables built once
    # Gymnasium's own sync vectorisation of the registered id: N copies of that one built env
    sync = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync", episodes=str(episodes_json), surrogate=sur)
    assert all(e.unwrapped.env is grasp_env for e in sync.envs)


def test_seeding_episode_choice_and_dp_return(episodes_json, sur, grasp_env, solutions):
    """The same seed replays the same episode and observations whatever ran before; options={'episode': i} starts
    episode i with GraspEnv.reset_to's observation; the DP policy's episode terminates after T steps with the DP
    return; info carries exactly episode_index, t, grasp (no name Gymnasium or SB3 reserve)."""
    env = _make(episodes_json, sur)

    def run(seed):
        obs, info = env.reset(seed=seed)
        out = [obs]
        for a in (2, 5, 9):
            obs, _, terminated, _, _ = env.step(a)
            out.append(obs)
            if terminated:
                break
        return info["episode_index"], np.concatenate(out)

    seeds = list(range(12))
    first = [run(s) for s in seeds]
    again = [run(s) for s in reversed(seeds)][::-1]  # another order: the seed alone decides
    for s, (ep1, obs1), (ep2, obs2) in zip(seeds, first, again):
        assert ep1 == ep2, f"seed {s}"
        np.testing.assert_array_equal(obs1, obs2, err_msg=f"seed {s}")
    assert len({ep for ep, _ in first}) > 1  # the seed does choose among the episodes

    for i in range(3):
        obs, info = env.reset(options={"episode": i})
        assert set(info) == {"episode_index", "t", "grasp"} and not set(info) & RESERVED
        assert info["episode_index"] == i and info["t"] == 0 and info["grasp"] == int(grasp_env.episodes.start_grasp[i])
        np.testing.assert_array_equal(obs, np.asarray(grasp_env.reset_to(jnp.int32(i)).obs))
        total, terminated, steps = 0.0, False, 0
        while not terminated:
            obs, r, terminated, truncated, info = env.step(int(solutions.policy[i, info["grasp"], info["t"]]))
            assert not truncated and env.observation_space.contains(obs)
            total, steps = total + r, steps + 1
        assert steps == T
        np.testing.assert_allclose(total, solutions.ret[i], rtol=1e-5, atol=1e-5)  # the same table, summed


def test_record_episode_statistics_sums_the_rewards(grasp_env, solutions):
    """Gymnasium's RecordEpisodeStatistics (SB3's Monitor reads the same key) over whole episodes: info['episode']
    is {r: the sum of the step rewards, l: the number of steps}; on the DP policy's full episodes r is the DP
    return and l = T. Random actions (mostly ending early: a dropped tool) on other seeds."""
    env = gym.wrappers.RecordEpisodeStatistics(GymGraspEnv(grasp_env))
    rng = np.random.default_rng(0)
    for run in range(6):
        dp_policy = run < 3
        _, info = env.reset(seed=run, options={"episode": run} if dp_policy else None)
        total, steps, done = 0.0, 0, False
        while not done:
            action = solutions.policy[run, info["grasp"], info["t"]] if dp_policy else rng.integers(0, 17)
            _, reward, terminated, truncated, info = env.step(int(action))
            total, steps, done = total + reward, steps + 1, terminated or truncated
        assert info["episode"]["l"] == steps and 1 <= steps <= T
        assert info["episode"]["r"] == pytest.approx(total, abs=1e-9)
        if dp_policy:
            assert steps == T and info["episode"]["r"] == pytest.approx(float(solutions.ret[run]), abs=1e-6)
        assert 0 <= info["episode_index"] < 3


def test_vector_env_equals_gymnasiums_sync_vector_env_step_for_step(grasp_env):
    """The native vector env (one vmapped call) and Gymnasium's SyncVectorEnv of N GymGraspEnvs, seeded alike,
    give the same observations, rewards, terminations and infos at every step, across autoresets; and the step
    after a termination is the NEXT_STEP autoreset (reward 0, not terminated, t = 0, the action ignored)."""
    native = GraspVectorEnv(grasp_env, N_ENVS)
    sync = gym.vector.SyncVectorEnv([lambda: GymGraspEnv(grasp_env) for _ in range(N_ENVS)])
    assert native.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    (o1, i1), (o2, i2) = native.reset(seed=7), sync.reset(seed=7)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(i1["episode_index"], i2["episode_index"])
    rng = np.random.default_rng(1)
    terminated, autoresets = np.zeros(N_ENVS, bool), 0
    for step in range(4 * T):
        # mostly action 3 (index distal off: its three-finger grasp survives), sometimes a random one
        actions = np.where(rng.random(N_ENVS) < 0.7, 3, rng.integers(0, 17, N_ENVS))
        r1, r2 = native.step(actions), sync.step(actions)
        for name, a, b in zip(("obs", "reward", "terminated", "truncated"), r1[:4], r2[:4]):
            np.testing.assert_array_equal(a, b, err_msg=f"step {step}: {name}")
        for key in ("episode_index", "t", "grasp"):
            np.testing.assert_array_equal(r1[4][key], r2[4][key], err_msg=f"step {step}: info {key}")
        assert not set(r1[4]) & RESERVED
        reset = terminated  # the previous step terminated there: this step is the autoreset
        assert np.all(r1[1][reset] == 0) and not np.any(r1[2][reset]) and np.all(r1[4]["t"][reset] == 0)
        autoresets += int(reset.sum())
        terminated = r1[2]
    assert autoresets >= N_ENVS  # each env ran several episodes
    assert isinstance(native, gym.vector.VectorEnv) and native.action_space.shape == (N_ENVS,)
    with pytest.raises(ValueError, match=r"actions: 17 is not in \[0, 17\)"):
        native.step(np.full(N_ENVS, 17))


def test_make_vec_uses_the_native_vector_env(episodes_json, sur):
    envs = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", episodes=str(episodes_json),
                        surrogate=sur, progress=False)
    assert isinstance(envs, GraspVectorEnv) and envs.num_envs == 3
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (3, envs.single_observation_space.shape[0]) and obs.dtype == np.float32
    obs, reward, terminated, truncated, info = envs.step(np.array([3, 3, 3]))
    assert reward.shape == terminated.shape == truncated.shape == info["t"].shape == (3,)


def test_bad_arguments_raise_naming_the_argument(episodes_json, sur, tmp_path):
    bad = [
        (dict(episodes="nope"), r"episodes: 'nope' is neither an episode set"),
        (dict(episodes=str(tmp_path / "missing.json")), r"episodes: no such JSON file"),
        (dict(episodes=42), r"episodes: 42 is not a set name"),
        (dict(episodes={}), r"episodes: \{\} holds no episode"),
        (dict(episodes=str(episodes_json), backend="gpu"), r"backend: 'gpu' is not one of"),
        (dict(episodes=str(episodes_json), render_mode="human", surrogate=sur), r"render_mode: 'human'"),
    ]
    for kwargs, message in bad:
        with pytest.raises(ValueError, match=message):
            gym.make(ENV_ID, progress=False, **kwargs)
    mixed = {"a": scenario.make_episode().head(T), "b": scenario.make_episode().head(T + 1)}
    with pytest.raises(ValueError, match=r"episodes: all episodes need the same number of waypoints, got \[3, 4\]"):
        gym.make(ENV_ID, episodes=mixed)
    vec = dict(vectorization_mode="vector_entry_point", episodes=str(episodes_json), surrogate=sur, progress=False)
    for kwargs, message in [
        (dict(num_envs=0), r"num_envs: 0 must be an int >= 1"),
        (dict(num_envs=2, max_episode_steps=2), r"max_episode_steps: 2"),
        (dict(num_envs=2, render_mode="rgb_array"), r"render_mode: 'rgb_array'"),
    ]:
        with pytest.raises(ValueError, match=message):
            gym.make_vec(ENV_ID, **vec, **kwargs)
    env = _make(episodes_json, sur)
    with pytest.raises(ValueError, match=r"options\['episode'\]: 3 is not in \[0, 3\)"):
        env.reset(options={"episode": 3})
    env.reset(seed=0)
    for action in (-1, 17, 100):
        with pytest.raises(ValueError, match=rf"action: {action} is not in \[0, 17\)"):
            env.step(action)


RECORD = """
import json, pathlib, sys
import gymnasium as gym, imageio.v3 as iio, numpy as np
import gsp_jax
from gsp_jax.learning.gym_env import ENV_ID
gsp_jax.enable_cache()  # the run's test cache (GSP_JAX_CACHE, set by conftest.py)
out = pathlib.Path(sys.argv[2])
env = gym.make(ENV_ID, episodes=sys.argv[1], render_mode="rgb_array", progress=False)
env = gym.wrappers.RecordVideo(env, str(out), episode_trigger=lambda e: True, disable_logger=True)
env.reset(seed=0, options={"episode": 0})
done, steps = False, 0
while not done:
    _, _, term, trunc, _ = env.step(3)
    done, steps = term or trunc, steps + 1
env.close()
(video,) = out.glob("*.mp4")
frames = iio.imread(video)
print(json.dumps(dict(frames=int(frames.shape[0]), shape=list(frames.shape[1:]), steps=steps,
                      spread=float(frames.std()), change=float(np.abs(frames[-1] * 1.0 - frames[0]).mean()))))
"""


def test_record_video_writes_a_readable_file(episodes_json, tmp_path):
    """RecordVideo over one episode writes an MP4 whose frames read back (one per step plus the reset, 360x480,
    not blank, the tool moved between first and last). A fresh process builds its tables (programs from the test
    cache).
    Rendering needs OpenGL, chosen before mujoco is imported: MUJOCO_GL=egl in a subprocess; skipped if none works."""
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(RECORD), str(episodes_json), str(tmp_path / "video")],
                          capture_output=True, text=True, env=env, timeout=600)
    if proc.returncode != 0 and any(s in proc.stderr for s in ("OpenGL", "EGL", "GL context", "gladLoadGL")):
        pytest.skip(f"no OpenGL here: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["frames"] == result["steps"] + 1 and result["shape"] == [360, 480, 3], result
    assert result["spread"] > 10 and result["change"] > 0.5, result  # a picture, and the lift shows
