"""A Gymnasium view of `GraspEnv` for users of other RL libraries (stable-baselines3, CleanRL, ...).

    env = GymGraspEnv(GraspEnv(surrogate, episodes, tables))    # gymnasium.Env, one environment
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(action)

One episode per `reset` (a random episode of the set, drawn from the seeded key; `options={"episode": i}`
picks one); the episode terminates after its last waypoint or on a collision or fall; there is no truncation.
Steps are jitted single-environment calls: for throughput, vmap `GraspEnv` itself.
"""
from __future__ import annotations

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.env import GraspEnv


class GymGraspEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, env: GraspEnv):
        self.env = GraspEnv(env.surrogate, env.episodes, env.tables, auto_reset=False)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.env.observation_size,), np.float32)
        self.action_space = gym.spaces.Discrete(self.env.action_size)
        self._reset_to = jax.jit(self.env.reset_to)
        self._step = jax.jit(self.env.step)
        self._key = jax.random.PRNGKey(0)
        self._state = None

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

    def _obs(self) -> np.ndarray:
        return np.asarray(self._state.obs, np.float32)

    def _info(self) -> dict:
        sim = self._state.pipeline_state
        return {"episode_index": int(self._state.info["episode_index"]), "t": int(sim.t), "grasp": int(sim.grasp)}
