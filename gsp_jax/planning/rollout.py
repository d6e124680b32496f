"""One walker of an episode: a policy in a step model, from a state, for a number of steps, as one `Trajectory`.

    traj = rollout.rollout(model, policy, state, steps)    # model: a `protocols.StepModel`, policy: a `Policy`
    traj.ret, traj.final, traj.actions, traj.rewards      # the expected return, where it stopped, step by step

Every walk of the library goes through `walk`: the lookahead's rollouts and its episodes (`lookahead.rollout`,
`lookahead.rollout_planned`, which moves on to each search's own child), a planner's episode (`planners.registry.plan`,
`returns`) and the online one (`planners.online.episode_planner`). Each step's reward counts with the chance that every
earlier segment held (`reward.accumulated`: the learned physics term's chance node; 1 without the term, where the return
is the plain sum).

The walk is a `lax.while_loop` over at most `steps` steps that writes each step into the trajectory's arrays of
length `steps`: it stops when the episode ends, and under `vmap` when every walk of the batch has ended (a
`lax.scan` of `steps` steps would step on after the end: the lookahead's rollouts start mid-episode, at waypoint t
+ l, and would take all T steps where T - t - l remain). Steps not taken keep the arrays' fill: action
`grasps.NULL`, reward 0, alive False, the final grasp and chance to reach.
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

from gsp_jax.model.grasps import NULL
from gsp_jax.surrogate import protocols, reward as reward_lib
from gsp_jax.surrogate.protocols import Policy, StepModel
from gsp_jax.surrogate.step import State


@struct.dataclass
class Trajectory:
    """A walk of at most S steps (one walk; `vmap` adds leading axes). Step i goes from the state at waypoint t0 + i
    (t0 the start state's)."""

    actions: jax.Array  # (S,) int32 each step's action (`grasps.NULL` for a step not taken)
    rewards: jax.Array  # (S,) each step's (expected) reward (0 for a step not taken)
    reach: jax.Array  # (S,) the chance that every segment before step i held: the weight of rewards[i] in `ret`
    grasps: jax.Array  # (S,) int32 the grasp after each step (the final grasp for a step not taken)
    alive: jax.Array  # (S,) bool step i was taken (no earlier step ended the episode)
    ret: jax.Array  # () the expected return: each reward times its reach, summed in walking order
    hold: jax.Array  # () the chance that every segment walked held (the reach after the last step taken)
    final: State  # the state where the walk stopped (the episode's end, or after S steps)


def walk(transition: Callable, state: State, steps: int) -> Trajectory:
    """The walk of `transition(s) -> (action, next state, reward)` from `state` for at most `steps` (static) steps,
    stopping once a state is done (see the module docstring)."""
    one = jnp.ones((), jnp.float32)
    filled = dict(actions=jnp.full(steps, NULL, jnp.int32), rewards=jnp.zeros(steps, jnp.float32),
                  reach=jnp.ones(steps, jnp.float32), grasps=jnp.zeros(steps, jnp.int32),
                  alive=jnp.zeros(steps, bool))

    def cond(carry):
        i, s = carry[:2]
        return (i < steps) & ~s.done

    def body(carry):
        i, s, ret, reach, arrays = carry
        action, nxt, reward = transition(s)
        arrays = dict(actions=arrays["actions"].at[i].set(jnp.asarray(action, jnp.int32)),
                      rewards=arrays["rewards"].at[i].set(reward), reach=arrays["reach"].at[i].set(reach),
                      grasps=arrays["grasps"].at[i].set(nxt.grasp), alive=arrays["alive"].at[i].set(True))
        ret, reach = reward_lib.accumulated(ret, reach, reward, nxt.terms.fall_risk)
        return i + 1, nxt, ret, reach, arrays

    _, final, ret, hold, arrays = jax.lax.while_loop(cond, body, (jnp.int32(0), state, 0.0 * one, one, filled))
    alive = arrays["alive"]
    return Trajectory(actions=arrays["actions"], rewards=arrays["rewards"],
                      reach=jnp.where(alive, arrays["reach"], hold), grasps=jnp.where(alive, arrays["grasps"],
                                                                                     final.grasp),
                      alive=alive, ret=ret, hold=hold, final=final)


def rollout(step_model: StepModel, policy: Policy, state: State, steps: int | None = None) -> Trajectory:
    """`policy` run in `model` from `state` for at most `steps` steps (static; None: the episode's length T, which
    from any state reaches its end): each step `model.step(s, policy.act(s))`. jit- and vmap-able."""
    protocols.checked(step_model, policy)
    steps = state.episode.waypoints.shape[-2] if steps is None else steps

    def transition(s):
        action = policy.act(s)
        nxt, reward, _ = step_model.step(s, action)
        return action, nxt, reward

    return walk(transition, state, steps)


def sequence_scores(sur, episode, actions: jax.Array):
    """`planning.dp.sequence_scores` without a DP table: (rewards (T,), expected return (), predicted chance to hold
    ()) of an open-loop action sequence (T,) from the episode's start grasp, its T steps scored at once by the
    surrogate `sur` (`Surrogate.transitions`: the grasps along it are known before it is scored). Rewards are 0 once
    the sequence has ended (a fall, a collision); the return and the chance to hold count the steps before."""
    actions = jnp.asarray(actions, jnp.int32)

    def along(g, a):
        return sur.space.apply(g, a)[0], g

    _, before = jax.lax.scan(along, jnp.asarray(episode.start_grasp, jnp.int32), actions)
    moved, rewards, done = sur.transitions(episode, before, actions)
    alive = jnp.concatenate([jnp.ones(1, bool), ~jnp.cumsum(done)[:-1].astype(bool)])
    risk = None if sur.learned is None else moved.terms.fall_risk
    rewards = jnp.where(alive, rewards, 0.0)
    return rewards, reward_lib.expected_return(rewards, risk, alive), reward_lib.held_through(risk, alive)
