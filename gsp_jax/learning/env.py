"""The surrogate as a brax environment for RL: `reset(rng)`, `step(state, action)`, auto-reset, episode cycling.

    env = GraspEnv(surrogate, episodes)                      # episodes: a stacked batch (scenario.stack)
    env = GraspEnv(surrogate, episodes, tables=tables)        # the same MDP, stepped by table lookup
    state = env.reset(rng); state = env.step(state, action)   # brax.envs.base.State; vmap for many envs

`state.pipeline_state` is the surrogate `State` (continuous joint angles, tool pose and velocity, the episode),
`state.obs` its `observation`. When an episode ends the env moves on to the next episode of its set (cycling:
index + 1 mod N) and starts it afresh, so a batch of envs started on random episodes cycles the whole set.

Two backends, one MDP. From `reset` the surrogate only visits the DP's discrete states (the tool on a waypoint,
the grasp realised by IK from the fixed start configuration), so an episode set's DP tables (`dp.build_tables`:
reward, next grasp, terminal and joint angles per (grasp, waypoint)) step it exactly, with lookups instead of
the IK and wrench solves of a step; a test checks the two backends agree step for step. Use the table
backend for training on a fixed set, the surrogate backend (no tables) for continuous states and new episodes.
With tables, `pipeline_state.terms` carries the reward and the fall risk only (the other terms are not tabulated).

With the learned physics term a step's reward is its expectation over the term's chance node and `info["hold"]` the
chance its segment held (`reward.chance_to_hold` of `terms.fall_risk`): PPO weights what follows by it
(`ppo.losses.gae`), as the DP and the lookahead do (`reward.backed_up`); the running return is the expected one
(`reward.accumulated`). Without the term it is 1.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs import base as brax_base

from gsp_jax.planning import dp
from gsp_jax.planning.dp import TableModel  # noqa: F401  (its home is `planning.dp`: kept here only while
# experiments/paper/table1/decisions.py and the walkthrough notebook import it from this module)
from gsp_jax.surrogate import reward as reward_lib
from gsp_jax.surrogate.observation import observation, observation_size
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import State, Surrogate


class GraspEnv(brax_base.Env):
    """The grasp-sequence MDP over a set of episodes, as a brax `Env` (one environment; `jax.vmap` for many).

    Args:
      surrogate: the surrogate model (hand, rewards).
      episodes: the set, stacked: every leaf has a leading axis N (`scenario.stack`).
      tables: optional `dp.Table` per episode, stacked (N, ...) (`dp.build_tables`): the table backend.
      auto_reset: move on to the next episode when one ends (training); off, a finished state is absorbing.

    `state.info`: `episode_index` (index into the set; not `episode`, which Gymnasium tools reserve for episode
    statistics), `return` (running (expected) return of the current episode), `hold` (the chance the last step's
    segment held: `reward.chance_to_hold`, 1 without the term), `reach` (the chance every segment so far held).
    `state.metrics`: `episode_return` (the return of the episode that ended at this step; read it where `done`).
    """

    def __init__(self, surrogate: Surrogate, episodes: Episode, tables: dp.Table | None = None,
                 auto_reset: bool = True):
        if episodes.waypoints.ndim != 3:
            raise ValueError(
                f"episodes.waypoints: expected a stacked set (N, T, 3), got shape {tuple(episodes.waypoints.shape)}; "
                "use scenario.stack([...])"
            )
        n = episodes.waypoints.shape[0]
        if tables is not None and tables.reward.shape[0] != n:
            raise ValueError(f"tables.reward: leading axis {tables.reward.shape[0]} != number of episodes {n}")
        starts = np.asarray(episodes.start_grasp)
        bad = (starts < 0) | (starts >= surrogate.space.n_grasps)
        if np.any(bad):
            i = int(np.argmax(bad))
            raise ValueError(f"episodes.start_grasp[{i}]: {starts[i]} is not in [0, {surrogate.space.n_grasps})")
        self.surrogate, self.episodes, self.tables, self.auto_reset = surrogate, episodes, tables, auto_reset
        self.space = surrogate.space
        self.n_episodes, self.n_steps = n, episodes.waypoints.shape[1]

    # ---------------------------------------------------------------------------------------- brax API
    @property
    def observation_size(self) -> int:
        return observation_size(self.space, self.n_steps, self.surrogate.hand.n_joints)

    @property
    def action_size(self) -> int:
        return self.space.n_actions

    @property
    def backend(self) -> str:
        return "table" if self.tables is not None else "surrogate"

    def reset(self, rng: jax.Array) -> brax_base.State:
        """A random episode of the set, at its start."""
        idx = jax.random.randint(rng, (), 0, self.n_episodes)
        return self.reset_to(idx)

    def reset_to(self, index: jax.Array) -> brax_base.State:
        """Episode `index` of the set, at its start."""
        idx = jnp.asarray(index, jnp.int32)
        sim = self._start(idx)
        zero = jnp.zeros((), jnp.float32)
        return brax_base.State(
            pipeline_state=sim,
            obs=observation(self.space, sim),
            reward=zero,
            done=jnp.array(False),
            metrics={"episode_return": zero},
            info={"episode_index": idx, "return": zero, "hold": zero + 1.0, "reach": zero + 1.0},
        )

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        idx = state.info["episode_index"]
        action = self.space.checked(action)
        if self.tables is not None:
            sim, reward, done = dp.table_step(_TableView(self.tables, idx), state.pipeline_state, action)
        else:
            sim, reward, done = self.surrogate.step(state.pipeline_state, action)
        hold = reward_lib.chance_to_hold(sim.terms.fall_risk)
        ret, reach = reward_lib.accumulated(state.info["return"], state.info["reach"], reward, sim.terms.fall_risk)
        if self.auto_reset:
            idx_next = jnp.where(done, (idx + 1) % self.n_episodes, idx)
            fresh = self._start(idx_next)
            sim = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, sim)
        else:
            idx_next = idx
        return state.replace(
            pipeline_state=sim,
            obs=observation(self.space, sim),
            reward=reward,
            done=done,
            metrics={"episode_return": ret},
            info={"episode_index": idx_next, "return": jnp.where(done & self.auto_reset, 0.0, ret), "hold": hold,
                  "reach": jnp.where(done & self.auto_reset, 1.0, reach)},
        )

    # -------------------------------------------------------------------------------------------- helpers
    def episode(self, index: jax.Array) -> Episode:
        return jax.tree.map(lambda x: x[index], self.episodes)

    def _start(self, idx: jax.Array) -> State:
        ep = self.episode(idx)
        if self.tables is not None:
            return dp.table_state(ep, _TableView(self.tables, idx), ep.start_grasp, 0)
        return self.surrogate.reset(ep)


class _TableView:
    """Episode `idx` of stacked tables, indexed lazily: `view.reward[g, a, t]` gathers one element instead of
    copying the episode's whole (G, A, T) table per environment and step."""

    def __init__(self, tables: dp.Table, idx: jax.Array):
        self._tables, self._idx = tables, idx

    def __getattr__(self, name):
        array = getattr(self._tables, name)
        return None if array is None else _Indexed(array, self._idx)


class _Indexed:
    def __init__(self, array: jax.Array, idx: jax.Array):
        self._array, self._idx = array, idx

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        return self._array[(self._idx, *key)]
