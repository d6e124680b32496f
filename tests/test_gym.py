"""Gymnasium users' own tools on the registered environment (gsp_jax.gym_env): gymnasium.make and its env checker,
RecordEpisodeStatistics, the native vector env against Gymnasium's own SyncVectorEnv step for step (autoreset
included), RecordVideo, and clear errors for bad arguments.

Episodes: three reduced ones (T = 3 waypoints) written to a JSON file, so each table build is cheap.
"""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402

import gsp_jax  # noqa: E402, F401  (registers the environment)
from gsp_jax import scenario  # noqa: E402
from gsp_jax.gym_env import ENV_ID, GraspVectorEnv, GymGraspEnv, make_grasp_env  # noqa: E402

T = 3
N_ENVS = 6


@pytest.fixture(scope="module")
def episodes_json(tmp_path_factory):
    eps = {
        "nominal": scenario.make_episode().head(T),
        "shift+6": scenario.make_episode(shift_mm=6, torque=-1.0).head(T),
        "mass1.5": scenario.eval_set_b()["mass1.5m0_comy+2cm"].head(T),
    }
    path = tmp_path_factory.mktemp("episodes") / "episodes.json"
    scenario.save(path, eps)
    return path


@pytest.fixture(scope="module")
def grasp_env(episodes_json, sur):
    """The table-backed GraspEnv of those episodes, built once for the module."""
    return make_grasp_env(str(episodes_json), "table", sur, progress=False)


def test_make_passes_gymnasiums_env_checker_and_bad_arguments_name_themselves(episodes_json, sur, tmp_path):
    env = gym.make(ENV_ID, episodes=str(episodes_json), surrogate=sur)
    check_env(env.unwrapped, skip_render_check=True)  # rendering needs GL: test_record_video
    assert env.action_space == gym.spaces.Discrete(16) and env.unwrapped.env.backend == "table"
    assert env.unwrapped.env.n_episodes == 3
    with pytest.raises(ValueError, match=r"episodes: 'nope' is neither an episode set"):
        gym.make(ENV_ID, episodes="nope")
    with pytest.raises(ValueError, match=r"episodes: no such JSON file"):
        gym.make(ENV_ID, episodes=str(tmp_path / "missing.json"))
    with pytest.raises(ValueError, match=r"backend: 'gpu' is not one of"):
        gym.make(ENV_ID, episodes=str(episodes_json), backend="gpu")
    with pytest.raises(ValueError, match=r"render_mode: 'human'"):
        gym.make(ENV_ID, episodes=str(episodes_json), render_mode="human", surrogate=sur)
    with pytest.raises(ValueError, match=r"num_envs: 0"):
        gym.make_vec(ENV_ID, num_envs=0, vectorization_mode="vector_entry_point", episodes=str(episodes_json))


def test_record_episode_statistics_sums_the_rewards(grasp_env):
    """Gymnasium's RecordEpisodeStatistics (SB3's Monitor reads the same key) over whole episodes: its
    info['episode'] is {r: the sum of the rewards, l: the number of steps}."""
    env = gym.wrappers.RecordEpisodeStatistics(GymGraspEnv(grasp_env))
    rng = np.random.default_rng(0)
    for seed in range(4):
        env.reset(seed=seed)
        total, steps, done = 0.0, 0, False
        while not done:
            _, reward, terminated, truncated, info = env.step(int(rng.integers(0, 16)))
            total, steps, done = total + reward, steps + 1, terminated or truncated
        assert info["episode"]["l"] == steps and 1 <= steps <= T
        assert info["episode"]["r"] == pytest.approx(total, abs=1e-9)
        assert "episode_index" in info and 0 <= info["episode_index"] < 3


def test_vector_env_equals_gymnasiums_sync_vector_env_step_for_step(grasp_env):
    """The native vector env (one vmapped call) and Gymnasium's SyncVectorEnv of N GymGraspEnvs, seeded alike,
    give the same observations, rewards, terminations and infos at every step, across autoresets."""
    native = GraspVectorEnv(grasp_env, N_ENVS)
    sync = gym.vector.SyncVectorEnv([lambda: GymGraspEnv(grasp_env) for _ in range(N_ENVS)])
    assert native.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    (o1, i1), (o2, i2) = native.reset(seed=7), sync.reset(seed=7)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(i1["episode_index"], i2["episode_index"])
    rng = np.random.default_rng(1)
    resets = 0
    for step in range(4 * T):
        # mostly "hold" the grasp (survives longer), sometimes a random action
        actions = np.where(rng.random(N_ENVS) < 0.7, 3, rng.integers(0, 16, N_ENVS))
        r1, r2 = native.step(actions), sync.step(actions)
        for name, a, b in zip(("obs", "reward", "terminated", "truncated"), r1[:4], r2[:4]):
            np.testing.assert_array_equal(a, b, err_msg=f"step {step}: {name}")
        for key in ("episode_index", "t", "grasp"):
            np.testing.assert_array_equal(r1[4][key], r2[4][key], err_msg=f"step {step}: info {key}")
        resets += int(np.sum(r1[4]["t"] == 0))
    assert resets >= N_ENVS  # autoresets happened (each env ran several episodes)
    assert isinstance(native, gym.vector.VectorEnv) and native.action_space.shape == (N_ENVS,)
    with pytest.raises(ValueError, match=r"actions: 16 is not in \[0, 16\)"):
        native.step(np.full(N_ENVS, 16))


def test_make_vec_uses_the_native_vector_env(episodes_json):
    envs = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", episodes=str(episodes_json))
    assert isinstance(envs, GraspVectorEnv) and envs.num_envs == 3
    obs, _ = envs.reset(seed=0)
    assert obs.shape == (3, envs.single_observation_space.shape[0]) and obs.dtype == np.float32


RECORD = """
import json, pathlib, sys
import gymnasium as gym, imageio.v3 as iio, numpy as np
import gsp_jax
from gsp_jax.gym_env import ENV_ID
out = pathlib.Path(sys.argv[2])
env = gym.make(ENV_ID, episodes=sys.argv[1], render_mode="rgb_array")
env = gym.wrappers.RecordVideo(env, str(out), episode_trigger=lambda e: True, disable_logger=True)
env.reset(seed=0)
done, steps = False, 0
while not done:
    _, _, term, trunc, _ = env.step(3)
    done, steps = term or trunc, steps + 1
env.close()
(video,) = out.glob("*.mp4")
frames = iio.imread(video)
print(json.dumps(dict(frames=int(frames.shape[0]), shape=list(frames.shape[1:]), steps=steps,
                      spread=float(frames.std()))))
"""


def test_record_video_writes_a_readable_file(episodes_json, tmp_path):
    """RecordVideo over one episode writes an MP4 whose frames read back (one per step plus the reset, 360x480,
    not blank). Rendering needs OpenGL: run with MUJOCO_GL=egl in a subprocess; skipped where none works."""
    env = dict(os.environ, MUJOCO_GL="egl", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(RECORD), str(episodes_json), str(tmp_path / "video")],
                          capture_output=True, text=True, env=env, timeout=600)
    if proc.returncode != 0 and ("OpenGL" in proc.stderr or "EGL" in proc.stderr):
        pytest.skip(f"no OpenGL here: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    import json

    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["frames"] == result["steps"] + 1 and result["shape"] == [360, 480, 3], result
    assert result["spread"] > 10  # a picture, not a blank frame
