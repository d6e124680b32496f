"""The policy's view of a surrogate state: what a robot observes or is told. One module below both the planners
(`policies`, `pretrain`) and the environments (`env`, `gym_env`), which all read it."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from gsp_jax.model.grasps import GraspSpace
from gsp_jax.surrogate.step import State


def observation_size(space: GraspSpace, n_steps: int, n_joints: int) -> int:
    return sum(space.n_options) + n_steps + 1 + n_joints + 3 + 4 + 6 + 3 + 3 + 6 + 1 + 3 + 1


def observation(space: GraspSpace, state: State) -> jax.Array:
    """The policy's view of a surrogate state, (observation_size,) float32 -- only what a robot observes or is
    told: the reference grasp (one-hot per link), time (one-hot and t/T), joint angles, tool pose and velocity,
    the next waypoint relative to the tool, the final waypoint, and the episode's external wrench, mass, CoM
    offset and friction. Continuous throughout, so the same policy acts in the physics check."""
    ep = state.episode
    n_t = ep.n_steps
    options = space.decode(state.grasp)
    grasp = jnp.concatenate([jax.nn.one_hot(options[i], n) for i, n in enumerate(space.n_options)])
    t = jnp.minimum(state.t, n_t - 1)
    nxt = ep.waypoints[jnp.minimum(state.t + 1, n_t - 1)]
    scalars = lambda *xs: jnp.stack([jnp.asarray(x, jnp.float32) for x in xs])  # noqa: E731
    return jnp.concatenate(
        [
            grasp,
            jax.nn.one_hot(t, n_t),
            scalars(state.t / n_t),
            state.q,
            state.tool_pos,
            state.tool_quat,
            state.tool_vel,
            nxt - state.tool_pos,
            ep.waypoints[-1],
            ep.w_ext,
            scalars(ep.mass),
            ep.com,
            scalars(ep.friction),
        ]
    ).astype(jnp.float32)
