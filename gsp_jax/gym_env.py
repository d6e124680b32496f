"""Gymnasium views of `GraspEnv` for users of other RL libraries (Stable-Baselines3, CleanRL, ...).

Registered on `import gsp_jax` as `gsp_jax/GraspSequence-v0`:

    env = gymnasium.make("gsp_jax/GraspSequence-v0", episodes="train", backend="table", render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)
    envs = gymnasium.make_vec("gsp_jax/GraspSequence-v0", num_envs=1024, vectorization_mode="vector_entry_point")

`episodes`: any name `scenario.episode_set` accepts (train, val, eval, evalA, evalB, nominal, all), a JSON file
of episodes (`scenario.save`), or a dict of `Episode`s. `backend`: "table" (the episodes' DP tables, built once
with a progress bar: exact lookups, fast) or "surrogate" (two IK and three wrench solves per step).

`GymGraspEnv`: one environment. Each `reset` starts a random episode of the set, drawn from the env's key
(`reset(seed=s)` seeds it; `options={"episode": i}` picks episode i); an episode terminates after its last
waypoint or on a collision or fall; nothing truncates. `info`: `episode_index`, `t`, `grasp` (the key `episode`
is left to Gymnasium's RecordEpisodeStatistics / SB3's Monitor).

`GraspVectorEnv`: N environments stepped by one jitted, vmapped call. Sub-environment i behaves exactly as a
`GymGraspEnv` reset with seed `seed + i` (as `SyncVectorEnv` seeds them) and autoresets by Gymnasium's
default rule (`AutoresetMode.NEXT_STEP`): the step after one that terminated ignores that sub-environment's
action and returns the first observation of its next episode, with reward 0 and terminated False.
"""
from __future__ import annotations

import pathlib

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from gsp_jax.env import GraspEnv

ENV_ID = "gsp_jax/GraspSequence-v0"
BACKENDS = ("table", "surrogate")


def make_grasp_env(episodes="train", backend: str = "table", surrogate=None, progress: bool = True) -> GraspEnv:
    """The brax `GraspEnv` (no auto-reset) of an episode set; see the module docstring for the arguments."""
    from gsp_jax import dp, scenario
    from gsp_jax.surrogate import Surrogate

    if backend not in BACKENDS:
        raise ValueError(f"backend: {backend!r} is not one of {BACKENDS}")
    if isinstance(episodes, dict):
        named = episodes
    elif isinstance(episodes, (str, pathlib.Path)) and str(episodes).endswith(".json"):
        if not pathlib.Path(episodes).is_file():
            raise ValueError(f"episodes: no such JSON file {str(episodes)!r}")
        named = scenario.load(episodes)
    elif isinstance(episodes, str):
        try:
            named = scenario.episode_set(episodes)
        except ValueError as e:
            raise ValueError(f"episodes: {episodes!r} is neither an episode set nor a .json file ({e})") from None
    else:
        raise ValueError(f"episodes: {episodes!r} is not a set name, a .json path or a dict of episodes")
    if not named:
        raise ValueError(f"episodes: {episodes!r} holds no episode")
    lengths = {int(e.n_steps) for e in named.values()}
    if len(lengths) != 1:
        raise ValueError(f"episodes: all episodes need the same number of waypoints, got {sorted(lengths)}")
    sur = surrogate or Surrogate()
    batch = scenario.stack(list(named.values()))
    tables = None
    if backend == "table":
        build = jax.jit(lambda ep: dp.build_table(sur, ep))
        parts = []
        items = list(named.values())
        if progress:
            from tqdm.auto import tqdm

            items = tqdm(items, desc="DP tables", unit="episode")
        for ep in items:
            parts.append(jax.block_until_ready(build(ep)))
        tables = jax.tree.map(lambda *xs: jnp.stack(xs), *parts)
    return GraspEnv(sur, batch, tables, auto_reset=False)


class _Renderer:
    """The scene at a surrogate state (hand joint angles, tool pose) as an RGB frame (H, W, 3) uint8. Needs an
    OpenGL backend (`MUJOCO_GL=egl`, set before mujoco is imported; see gsp_jax.render)."""

    def __init__(self, hand, size=(360, 480), camera: str = "front"):
        import mujoco

        from gsp_jax import hand as hand_lib

        self.model = hand_lib.load_mjmodel()
        self.data = mujoco.MjData(self.model)
        tool = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, hand_lib.TOOL_BODY)
        joint = int(np.flatnonzero(self.model.jnt_bodyid == tool)[0])
        self.tool_adr, self.hand_adr, self.camera = int(self.model.jnt_qposadr[joint]), hand.qpos_adr, camera
        try:
            self.renderer = mujoco.Renderer(self.model, *size)
        except mujoco.FatalError as e:
            raise RuntimeError(
                "render: MuJoCo has no OpenGL context; set MUJOCO_GL=egl (headless) or osmesa in the environment "
                f"before anything imports mujoco or gsp_jax ({e})"
            ) from e

    def __call__(self, sim) -> np.ndarray:
        import mujoco

        a = self.tool_adr
        self.data.qpos[:] = self.model.qpos0
        self.data.qpos[self.hand_adr] = np.asarray(sim.q)
        self.data.qpos[a : a + 3], self.data.qpos[a + 3 : a + 7] = np.asarray(sim.tool_pos), np.asarray(sim.tool_quat)
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self.camera)
        return self.renderer.render().copy()

    def close(self):
        self.renderer.close()


def _info(state) -> dict:
    sim = state.pipeline_state
    return {"episode_index": state.info["episode_index"], "t": sim.t, "grasp": sim.grasp}


class GymGraspEnv(gym.Env):
    """One environment over a `GraspEnv`'s episode set (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, env: GraspEnv, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: {render_mode!r} is not None or 'rgb_array'")
        self.env = GraspEnv(env.surrogate, env.episodes, env.tables, auto_reset=False)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.observation_size,), np.float32)
        self.action_space = gym.spaces.Discrete(self.env.action_size)
        self.render_mode = render_mode
        self._reset_to = jax.jit(self.env.reset_to)
        self._step = jax.jit(self.env.step)
        self._key = jax.random.PRNGKey(0)
        self._state = None
        self._renderer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, k = jax.random.split(self._key)
        index = (options or {}).get("episode")
        if index is None:
            index = jax.random.randint(k, (), 0, self.env.n_episodes)
        elif not 0 <= int(index) < self.env.n_episodes:
            raise ValueError(f"options['episode']: {index} is not in [0, {self.env.n_episodes})")
        self._state = self._reset_to(jnp.asarray(index, jnp.int32))
        return self._obs(), self._info()

    def step(self, action):
        if self._state is None:
            raise RuntimeError("step: call reset() first")
        self.env.space.check_actions(action)
        self._state = self._step(self._state, jnp.asarray(int(action), jnp.int32))
        return self._obs(), float(self._state.reward), bool(self._state.done), False, self._info()

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._state is None:
            raise RuntimeError("render: call reset() first")
        if self._renderer is None:
            self._renderer = _Renderer(self.env.surrogate.hand)
        return self._renderer(self._state.pipeline_state)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _obs(self) -> np.ndarray:
        return np.asarray(self._state.obs, np.float32)

    def _info(self) -> dict:
        return {k: int(v) for k, v in _info(self._state).items()}


class GraspVectorEnv(VectorEnv):
    """N environments over one `GraspEnv`'s episode set, stepped by one jitted, vmapped call (see the module
    docstring for the autoreset rule and the seeding)."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, env: GraspEnv, num_envs: int):
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs: {num_envs!r} must be an int >= 1")
        self.env = GraspEnv(env.surrogate, env.episodes, env.tables, auto_reset=False)
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.observation_size,), np.float32)
        self.single_action_space = gym.spaces.Discrete(self.env.action_size)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._reset = jax.jit(jax.vmap(self._reset_one))
        self._step = jax.jit(self._step_all)
        self._keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(num_envs))
        self._state = None
        self._autoreset = jnp.zeros(num_envs, bool)

    def _reset_one(self, key):
        """A random episode from the sub-environment's key (GymGraspEnv.reset's draw); (next key, state)."""
        key, k = jax.random.split(key)
        return key, self.env.reset_to(jax.random.randint(k, (), 0, self.env.n_episodes))

    def _step_all(self, keys, state, actions, autoreset):
        keys_r, fresh = jax.vmap(self._reset_one)(keys)
        stepped = jax.vmap(self.env.step)(state, actions)
        pick = lambda a, b: jax.vmap(lambda r, x, y: jnp.where(r, x, y))(autoreset, a, b)  # noqa: E731
        state = jax.tree.map(pick, fresh, stepped)
        state = state.replace(reward=jnp.where(autoreset, 0.0, state.reward), done=jnp.where(autoreset, False, state.done))
        return jnp.where(autoreset[:, None], keys_r, keys), state

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if options:
            raise ValueError(f"options: {sorted(options)} not supported by the vector env (seed only)")
        if seed is not None:
            seeds = list(seed) if isinstance(seed, (list, tuple)) else [seed + i for i in range(self.num_envs)]
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed: {len(seeds)} seeds for {self.num_envs} environments")
            self._keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
        self._keys, self._state = self._reset(self._keys)
        self._autoreset = jnp.zeros(self.num_envs, bool)
        return self._obs(), self._infos()

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("step: call reset() first")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,):
            raise ValueError(f"actions: shape {actions.shape}, expected ({self.num_envs},)")
        self.env.space.check_actions(actions, "actions")
        self._keys, self._state = self._step(self._keys, self._state, jnp.asarray(actions, jnp.int32), self._autoreset)
        self._autoreset = self._state.done
        s = self._state
        terminated = np.asarray(s.done)
        return self._obs(), np.asarray(s.reward, np.float64), terminated, np.zeros_like(terminated), self._infos()

    def _obs(self) -> np.ndarray:
        return np.asarray(self._state.obs, np.float32)

    def _infos(self) -> dict:
        infos = {k: np.asarray(v) for k, v in _info(self._state).items()}
        return {**infos, **{f"_{k}": np.ones(self.num_envs, bool) for k in infos}}


def make(episodes="train", backend: str = "table", render_mode: str | None = None, surrogate=None) -> GymGraspEnv:
    """Entry point of `gymnasium.make(ENV_ID, ...)`."""
    return GymGraspEnv(make_grasp_env(episodes, backend, surrogate), render_mode=render_mode)


def make_vector(num_envs: int = 1, episodes="train", backend: str = "table", surrogate=None, **kwargs) -> GraspVectorEnv:
    """Vector entry point of `gymnasium.make_vec(ENV_ID, num_envs, vectorization_mode="vector_entry_point")`."""
    unknown = sorted(set(kwargs) - {"render_mode", "max_episode_steps"})
    if unknown:
        raise ValueError(f"{unknown[0]}: unknown argument of {ENV_ID}")
    if kwargs.get("render_mode") is not None:
        raise ValueError(f"render_mode: {kwargs['render_mode']!r}; the vector env does not render (use the single env)")
    return GraspVectorEnv(make_grasp_env(episodes, backend, surrogate), num_envs)
