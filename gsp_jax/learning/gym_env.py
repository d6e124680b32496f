"""Gymnasium views of `GraspEnv` for users of other RL libraries (Stable-Baselines3, CleanRL, ...).

Registered by `gsp_jax.register_gymnasium()` (and by importing this module) as `gsp_jax/GraspSequence-v0`:

    gsp_jax.register_gymnasium()
    env = gymnasium.make("gsp_jax/GraspSequence-v0", episodes="train", backend="table", render_mode="rgb_array")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)
    envs = gymnasium.make_vec("gsp_jax/GraspSequence-v0", num_envs=1024, vectorization_mode="vector_entry_point")

`model`: a shipped model's name or a scene file (`gsp_jax.load_model`; default: the shipped wrench). `episodes`:
any name `scenario.episode_set` accepts (train, val, eval, evalA, evalB, nominal, all), a JSON file
of episodes (`scenario.save`), or a dict of `Episode`s. `backend`: "table" (the episodes' DP tables, built once
with a progress bar: exact lookups, fast) or "surrogate" (three IK and four wrench solves per step). Within one
process, making the environment again with the same episodes, backend and surrogate reuses the built one (tables
and compiled steps), so `SyncVectorEnv` or SB3's `make_vec_env` of N copies builds and compiles once.

`GymGraspEnv`: one environment. Each `reset` starts a random episode of the set, drawn from the env's key
(`reset(seed=s)` seeds it; `options={"episode": i}` picks episode i); an episode terminates after its last
waypoint or on a collision or fall; nothing truncates. `info`: `episode_index`, `t`, `grasp` (ints). No key
collides with a name Gymnasium's or SB3's tools reserve (`episode`, `_episode`, `final_obs`, `final_info`,
`TimeLimit.truncated`, `terminal_observation`). `render_mode="rgb_array"`: `render()` is the scene at the current
state, (360, 480, 3) uint8, for `gymnasium.wrappers.RecordVideo` (needs `MUJOCO_GL=egl` or `osmesa` set before
mujoco is imported; see gsp_jax.physics.render).

`GraspVectorEnv`: N environments stepped by one jitted, vmapped call. Sub-environment i behaves exactly as a
`GymGraspEnv` reset with seed `seed + i` (as `SyncVectorEnv` seeds them) and autoresets by Gymnasium's
default rule (`AutoresetMode.NEXT_STEP`): the step after one that terminated ignores that sub-environment's
action and returns the first observation of its next episode, with reward 0 and terminated False.
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import hashlib
import pathlib

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

import gsp_jax
from gsp_jax.learning.env import GraspEnv

ENV_ID = gsp_jax.register_gymnasium()  # "gsp_jax/GraspSequence-v0", registered by this import too
BACKENDS = ("table", "surrogate")
_BUILT: collections.OrderedDict = collections.OrderedDict()  # (backend, episodes, surrogate digests) -> GraspEnv
_BUILT_MAX = 8  # built environments kept (a table-backed training set holds ~5 MB of tables)


def _named_episodes(episodes, model=None) -> dict:
    """The episodes argument of `make` as a dict name -> Episode (ValueError naming `episodes` otherwise)."""
    from gsp_jax.model import scenario

    if isinstance(episodes, dict):
        named = {k: scenario.validate(v, str(k), model=model) for k, v in episodes.items()}
    elif isinstance(episodes, (str, pathlib.Path)) and str(episodes).endswith(".json"):
        if not pathlib.Path(episodes).is_file():
            raise ValueError(f"episodes: no such JSON file {str(episodes)!r}")
        named = scenario.load(episodes, model)
    elif isinstance(episodes, str):
        try:
            named = scenario.episode_set(episodes, model)
        except ValueError as e:
            raise ValueError(f"episodes: {episodes!r} is neither an episode set nor a .json file ({e})") from None
    else:
        raise ValueError(f"episodes: {episodes!r} is not a set name, a .json path or a dict of episodes")
    if not named:
        raise ValueError(f"episodes: {episodes!r} holds no episode")
    lengths = {int(e.n_steps) for e in named.values()}
    if len(lengths) != 1:
        raise ValueError(f"episodes: all episodes need the same number of waypoints, got {sorted(lengths)}")
    return named


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for x in arrays:
        x = np.asarray(x)
        h.update(f"{x.dtype}{x.shape}".encode())
        h.update(x.tobytes())
    return h.hexdigest()


def _fingerprint(sur) -> str:
    """What a surrogate's DP tables depend on: its hand model's arrays and its reward, IK and wrench configs."""
    configs = repr((sur.reward_config, sur.ik_config, sur.wrench_config))
    hand = [getattr(sur.hand, f.name) for f in dataclasses.fields(sur.hand)]
    return _digest(np.frombuffer(configs.encode(), np.uint8), *hand)


def make_grasp_env(episodes="train", backend: str = "table", surrogate=None, progress: bool = True,
                   model=None) -> GraspEnv:
    """The brax `GraspEnv` (no auto-reset) of an episode set; see the module docstring for the arguments.
    Memoised per (backend, the episodes' contents, the surrogate's hand and configurations; `None`: the default
    `Surrogate()`): `gymnasium.make` deep-copies the arguments of a spec, so an equal surrogate must hit too."""
    from gsp_jax.planning import dp
    from gsp_jax.model import load as model_lib, scenario
    from gsp_jax.surrogate.step import Surrogate

    if backend not in BACKENDS:
        raise ValueError(f"backend: {backend!r} is not one of {BACKENDS}")
    if surrogate is not None and model is not None and surrogate.model is not model_lib.load_model(model):
        raise model_lib.ModelError(f"model: {model_lib.load_model(model).label} differs from the surrogate's "
                                   f"{surrogate.model.label}; give one of them")
    sur = surrogate or Surrogate(model)
    named = _named_episodes(episodes, sur.model)
    batch = scenario.stack(list(named.values()))
    key = (backend, _digest(*jax.tree.leaves(batch)), _fingerprint(sur))
    if key in _BUILT:
        _BUILT.move_to_end(key)
        return _BUILT[key]
    tables = None
    if backend == "table":
        build = jax.jit(lambda ep: dp.build_table(sur, ep))
        items = list(named.values())
        if progress:
            from tqdm.auto import tqdm

            items = tqdm(items, desc="DP tables", unit="episode")
        parts = [jax.block_until_ready(build(ep)) for ep in items]
        tables = jax.tree.map(lambda *xs: jnp.stack(xs), *parts)
    _BUILT[key] = env = GraspEnv(sur, batch, tables, auto_reset=False)
    while len(_BUILT) > _BUILT_MAX:
        _BUILT.popitem(last=False)
    return env


class _Renderer:
    """The scene at a surrogate state (hand joint angles, tool pose) as an RGB frame (H, W, 3) uint8. Needs an
    OpenGL backend (`MUJOCO_GL=egl`, set before mujoco is imported; see gsp_jax.physics.render)."""

    def __init__(self, hand, size=(360, 480), camera: str = "front"):
        import mujoco

        from gsp_jax.model import hand as hand_lib

        self.model = hand_lib.load_mjmodel(hand.source)  # the hand's own scene (ValueError if it has none)
        self.data = mujoco.MjData(self.model)
        tool = hand_lib.tool_body(self.model)
        joint = int(np.flatnonzero(self.model.jnt_bodyid == tool)[0])  # the tool's free joint: position, quaternion
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


def _absorbing(env: GraspEnv) -> GraspEnv:
    return env if not env.auto_reset else GraspEnv(env.surrogate, env.episodes, env.tables, auto_reset=False)


# Compiled once per GraspEnv object (static argument), shared by every Gymnasium env made over it.
_reset_to = jax.jit(GraspEnv.reset_to, static_argnums=0)
_step = jax.jit(GraspEnv.step, static_argnums=0)


class GymGraspEnv(gym.Env):
    """One environment over a `GraspEnv`'s episode set (see the module docstring). Observations
    (observation_size,) float32, actions in Discrete(17)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}  # one waypoint per 0.25 s

    def __init__(self, env: GraspEnv, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: {render_mode!r} is not None or 'rgb_array'")
        self.env = _absorbing(env)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.observation_size,), np.float32)
        self.action_space = gym.spaces.Discrete(self.env.action_size)
        self.render_mode = render_mode
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
        self._state = _reset_to(self.env, jnp.asarray(index, jnp.int32))
        return self._obs(), self._info()

    def step(self, action):
        if self._state is None:
            raise RuntimeError("step: call reset() first")
        self.env.space.check_actions(action)
        self._state = _step(self.env, self._state, jnp.asarray(int(action), jnp.int32))
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


def _reset_one(env: GraspEnv, key):
    """A random episode from a sub-environment's key (GymGraspEnv.reset's draw): (next key, state)."""
    key, k = jax.random.split(key)
    return key, env.reset_to(jax.random.randint(k, (), 0, env.n_episodes))


@functools.partial(jax.jit, static_argnums=0)
def _vector_reset(env: GraspEnv, keys):
    """keys (N, 2) -> (next keys (N, 2), N states)."""
    return jax.vmap(functools.partial(_reset_one, env))(keys)


@functools.partial(jax.jit, static_argnums=0)
def _vector_step(env: GraspEnv, keys, state, actions, autoreset):
    """One NEXT_STEP-autoreset step of N sub-environments: keys (N, 2), state (N states), actions (N,) int32,
    autoreset (N,) bool (the previous step terminated there) -> (keys, states). Where autoreset: the reset state
    of the next episode drawn from that key (reward 0, done False), the action ignored; elsewhere: env.step."""
    keys_r, fresh = _vector_reset(env, keys)
    stepped = jax.vmap(env.step)(state, actions)
    pick = lambda a, b: jax.vmap(lambda r, x, y: jnp.where(r, x, y))(autoreset, a, b)  # noqa: E731
    state = jax.tree.map(pick, fresh, stepped)
    state = state.replace(reward=jnp.where(autoreset, 0.0, state.reward), done=jnp.where(autoreset, False, state.done))
    return jnp.where(autoreset[:, None], keys_r, keys), state


class GraspVectorEnv(VectorEnv):
    """N environments over one `GraspEnv`'s episode set, stepped by one jitted, vmapped call (see the module
    docstring for the autoreset rule and the seeding). `reset` -> obs (N, observation_size) float32, infos;
    `step(actions (N,) ints)` -> obs, rewards (N,) float64, terminated (N,) bool, truncated (N,) bool (all False),
    infos: `episode_index`, `t`, `grasp` (N,) int32, each with its `_name` mask (N,) bool (all True)."""

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, env: GraspEnv, num_envs: int):
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs: {num_envs!r} must be an int >= 1")
        self.env = _absorbing(env)
        self.num_envs = num_envs
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.observation_size,), np.float32)
        self.single_action_space = gym.spaces.Discrete(self.env.action_size)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(num_envs))  # before a seeded reset: keys 0..N-1
        self._state = None
        self._autoreset = jnp.zeros(num_envs, bool)

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        if options:
            raise ValueError(f"options: {sorted(options)} not supported by the vector env (seed only)")
        if seed is not None:
            seeds = list(seed) if isinstance(seed, (list, tuple)) else [seed + i for i in range(self.num_envs)]
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed: {len(seeds)} seeds for {self.num_envs} environments")
            self._keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(seeds))
        self._keys, self._state = _vector_reset(self.env, self._keys)
        self._autoreset = jnp.zeros(self.num_envs, bool)
        return self._obs(), self._infos()

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("step: call reset() first")
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,):
            raise ValueError(f"actions: shape {actions.shape}, expected ({self.num_envs},)")
        self.env.space.check_actions(actions, "actions")
        self._keys, self._state = _vector_step(
            self.env, self._keys, self._state, jnp.asarray(actions, jnp.int32), self._autoreset
        )
        self._autoreset = self._state.done
        terminated = np.asarray(self._state.done)
        rewards = np.asarray(self._state.reward, np.float64)
        return self._obs(), rewards, terminated, np.zeros_like(terminated), self._infos()

    def _obs(self) -> np.ndarray:
        return np.asarray(self._state.obs, np.float32)

    def _infos(self) -> dict:
        infos = {k: np.asarray(v) for k, v in _info(self._state).items()}
        return {**infos, **{f"_{k}": np.ones(self.num_envs, bool) for k in infos}}


def make(episodes="train", backend: str = "table", render_mode: str | None = None, surrogate=None,
         progress: bool = True, model=None) -> GymGraspEnv:
    """Entry point of `gymnasium.make(ENV_ID, ...)`; `progress`: the table-building progress bar; `model`: a
    shipped model's name or a scene path (None: the surrogate's, or the default model)."""
    return GymGraspEnv(make_grasp_env(episodes, backend, surrogate, progress, model), render_mode=render_mode)


def make_vector(num_envs: int = 1, episodes="train", backend: str = "table", surrogate=None, progress: bool = True,
                render_mode: str | None = None, max_episode_steps: int | None = None, model=None) -> GraspVectorEnv:
    """Vector entry point of `gymnasium.make_vec(ENV_ID, num_envs, vectorization_mode="vector_entry_point")`."""
    if render_mode is not None:
        raise ValueError(f"render_mode: {render_mode!r}; the vector env does not render (use the single env)")
    if max_episode_steps is not None:
        raise ValueError(
            f"max_episode_steps: {max_episode_steps!r}; the vector env does not truncate (episodes end after their "
            "waypoints); use vectorization_mode='sync' for a TimeLimit"
        )
    return GraspVectorEnv(make_grasp_env(episodes, backend, surrogate, progress, model), num_envs)
