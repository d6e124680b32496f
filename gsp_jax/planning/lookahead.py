"""Online l-step lookahead with m-step policy rollouts (the paper's Algorithm 2), one jitted, vmappable search.

    found = lookahead.search(step_model, state, base, depth=2)     # SearchResult: action, q (A,), best path
    policy = lookahead.Lookahead(base, step_model, depth=1)         # act(state), like every other policy
    ret, final = lookahead.rollout(step_model, base, state)          # the base policy to the episode's end
    ret, final = lookahead.rollout_planned(policy, state)             # policy's episode, stepped by its own search

From `state` the search expands the complete tree of depth l over the A actions: every action path
(a_1 .. a_l) is scored by the sum of its l rewards plus its leaf's rollout value, the return of the base policy
run from the leaf for m further steps (to the episode's end by default, m = None), plus, optionally, a value
estimate (the PPO critic) of the state where the rollout was cut off. With the learned physics term each step is a
chance node (expectimax): what follows a step counts with its chance to hold (`reward.chance_to_hold` of
`terms.fall_risk`, `reward.backed_up`; 1 without the term, where the sums are plain). The search returns the
first action of the best path, and q[a] = the best score under first action a (Q-values, for inspection). A
finished state is absorbing (reward 0), so paths that end the episode early are scored by what they earned.

`step_model` is any step model (`protocols.StepModel`: `reset`, `step`, and `step_every`, which the root expands): the
`Surrogate` (IK + wrench solves; from any continuous state, e.g. the simulated one in the physics check) or
`dp.TableModel` (one episode's DP table: exact, and cheap, for the discrete states the surrogate visits). `base`
is any policy (`protocols.Policy`, `act(state)`):
DP, PPO's deterministic actor, or another lookahead. `depth` and `horizon` are static; everything else is
traced, so `jax.vmap` runs one search per (state, episode, policy parameters) in one XLA kernel.

Shared rollouts. Below the root every state is the surrogate's discrete state of its (grasp, waypoint): the tool
on the waypoint, the grasp realised by IK from the fixed start configuration, the velocity of the waypoint
move. So two live leaves (paths that have not ended) with the same grasp are the same state up to `terms`,
which no policy reads: the rollout runs once per distinct live leaf grasp. Paths that ended early stay frozen
where they ended (another waypoint) and are not rolled out. An action sets one link, so the leaves lie within
l link changes of the root's grasp: 11 distinct grasps for l = 1 and 51 for l = 2 with the paper's hand, against 17
and 289 leaves (the search rolls out one spare slot besides). Tests check the search against a plain recursive one
and a brute-force enumeration.
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.model.grasps import GraspSpace
from gsp_jax.planning import rollout as rollout_lib
from gsp_jax.surrogate import protocols, reward as reward_lib
from gsp_jax.surrogate.protocols import Policy, StepModel
from gsp_jax.surrogate.step import State

Value = Callable[[State], jax.Array]  # optional value estimate of a state, in reward units


@struct.dataclass
class SearchResult:
    """The result of one search (one state; vmap adds axes)."""

    action: jax.Array  # () int32, the first action of the best path
    q: jax.Array  # (A,) best path score under each first action
    path: jax.Array  # (l,) int32, the best action path (path[0] = action)
    value: jax.Array  # () q[action], the search's estimate of the return from `state`
    child: State  # the root's child under `action`: model.step(state, action)'s state, computed by the search
    reward: jax.Array  # () that step's reward


def rollout(step_model: StepModel, policy: Policy, state: State, horizon: int | None = None,
            value: Value | None = None):
    """Run `policy` from `state` for `horizon` steps (None: until the episode ends) in `model`; return
    (the (expected) sum of rewards [+ value(final) if the episode has not ended], final state): the walk of
    `planning.rollout.rollout` (under `vmap` it stops when every rollout of the batch has ended)."""
    traj = rollout_lib.rollout(step_model, policy, state, horizon)
    ret = traj.ret
    if value is not None:
        ret = ret + jnp.where(traj.final.done, 0.0, traj.hold * value(traj.final))
    return ret, traj.final


def rollout_planned(policy: "Lookahead", state: State, horizon: int | None = None):
    """`rollout(policy.model, policy, state, horizon)` without stepping `policy.model` again: each decision's
    search has already computed `model.step(state, action)` for every action at its root, so the episode moves on
    to the plan's `child` and earns its `reward`. The same transitions (the child comes from the root's vmapped
    step, so in float32 its last bits can differ from a single step's); one model step per decision fewer.
    Returns (the (expected) sum of rewards, final state); `planned` gives the whole `Trajectory`."""
    traj = planned(policy, state, horizon)
    return traj.ret, traj.final


def planned(policy: "Lookahead", state: State, horizon: int | None = None) -> rollout_lib.Trajectory:
    """The `Trajectory` of `rollout_planned`: `planning.rollout.walk` moving on to each search's root child."""

    def transition(s):
        found = policy.search(s)
        return found.action, found.child, found.reward

    return rollout_lib.walk(transition, state, state.episode.waypoints.shape[-2] if horizon is None else horizon)


def search(step_model, state: State, base, depth: int = 1, horizon: int | None = None, value: Value | None = None,
           inner=None) -> SearchResult:
    """Algorithm 2 from one state: the best first action of the depth-`depth` tree with rollouts of `base`
    (see the module docstring). Shapes for one state; `jax.vmap` over states / episodes / base parameters.
    `inner`: the model below the root (default `model`), e.g. the episode's `dp.TableModel`: every state below
    the root is a discrete (grasp, waypoint) state, so only the root's A transitions need `model`."""
    if depth < 1:
        raise ValueError(f"depth: the lookahead depth l must be >= 1, got {depth}")
    if horizon is not None and horizon < 0:
        raise ValueError(f"horizon: the rollout length m must be >= 0 or None (to the episode's end), got {horizon}")
    inner = step_model if inner is None else inner
    protocols.checked(step_model, base)
    protocols.checked(inner, where="inner")
    space: GraspSpace = step_model.space
    n_a = space.n_actions
    # children (A, ...), their rewards (A,); leaves (A^l, ...), path rewards and chances to hold (A^l,)
    (children, child_reward), (leaves, path_reward, path_hold) = _expand(step_model, state, depth, n_a, inner)

    # One rollout per distinct grasp among the live leaves (all at waypoint t + l); the paths that ended early
    # (frozen at an earlier waypoint) share one extra key and are scored 0 beyond their rewards.
    n_g = space.n_grasps
    key = jnp.where(leaves.done, n_g, leaves.grasp)
    _, first, inverse = jnp.unique(key, size=_ball_size(space, depth) + 1, fill_value=n_g, return_index=True,
                                   return_inverse=True)
    reps = jax.tree.map(lambda x: x[first], leaves)
    rep_value, _ = jax.vmap(lambda s: rollout(inner, base, s, horizon, value))(reps)
    leaf_value = jnp.where(leaves.done, 0.0, rep_value[inverse.reshape(-1)])

    scores = (path_reward + path_hold * leaf_value).reshape(n_a, -1)  # (A, A^(l-1))
    q = jnp.max(scores, axis=1)
    best = jnp.argmax(scores.reshape(-1)).astype(jnp.int32)
    path = jnp.stack([(best // n_a ** (depth - 1 - k)) % n_a for k in range(depth)]).astype(jnp.int32)
    action = path[0]
    child = jax.tree.map(lambda x: x[action], children)
    return SearchResult(action=action, q=q, path=path, value=q[action], child=child, reward=child_reward[action])


def _expand(step_model, state: State, depth: int, n_a: int, inner):
    """Every action path of length `depth` from `state`: (children (A leading), their rewards (A,)) and (the leaf
    states (A^depth leading), path rewards (A^depth,), the paths' chances to hold (A^depth,)): a path's reward is
    its first step's plus, where that segment held, the rest's (`reward.backed_up`). The first step in `model`, the
    deeper ones in `inner`."""
    children, rewards, _ = step_model.step_every(state)  # every action at once (`StepModel.step_every`)
    risk = children.terms.fall_risk  # (A,)
    hold = reward_lib.chance_to_hold(risk)
    if depth == 1:
        return (children, rewards), (children, rewards, hold)
    _, (leaves, sub, sub_hold) = jax.vmap(lambda s: _expand(inner, s, depth - 1, n_a, inner))(children)
    flat = jax.tree.map(lambda x: x.reshape(-1, *x.shape[2:]), leaves)  # (A * A^(d-1), ...)
    return (children, rewards), (flat, reward_lib.backed_up(rewards[:, None], risk[:, None], None, sub).reshape(-1),
                                 (hold[:, None] * sub_hold).reshape(-1))


_BALL_CACHE: dict = {}


def _ball_size(space: GraspSpace, depth: int) -> int:
    """Most distinct grasps one grasp reaches by paths of exactly `depth` actions (static; from the grasp space's
    transitions, so it holds for any action set)."""
    key = (tuple(np.asarray(space.n_options).tolist()), tuple(np.asarray(space.action_link).tolist()),
           tuple(np.asarray(space.action_option).tolist()), depth)
    if key not in _BALL_CACHE:
        adjacency = np.zeros((space.n_grasps, space.n_grasps), np.int64)
        adjacency[np.arange(space.n_grasps)[:, None], space.transitions] = 1
        reach = np.eye(space.n_grasps, dtype=np.int64)
        for _ in range(depth):
            reach = np.minimum(reach @ adjacency, 1)
        _BALL_CACHE[key] = int(min(reach.sum(axis=1).max(), space.n_actions**depth))
    return _BALL_CACHE[key]


@struct.dataclass
class Lookahead:
    """The lookahead policy Ll (L1, L2 of the paper): `act(state)` = `search(model, state, base, depth, horizon,
    value).action`. A pytree: the base policy's parameters (and a table model's arrays) are traced, the rest is
    static. `value` is an optional value estimate at the rollouts' cut-off (e.g. `NetworkPolicy.value`).
    `inner` (optional): the model below the root, e.g. `TableModel` of the episode's table built once when the
    episode is revealed (`cached`): the tree's interior and the rollouts become lookups, and only the root's A
    transitions run the continuous `model`."""

    base: Any
    model: Any
    depth: int = struct.field(pytree_node=False, default=1)
    horizon: int | None = struct.field(pytree_node=False, default=None)
    value: Any = None  # a pytree with `value(state)` (e.g. a NetworkPolicy), or None
    inner: Any = None  # the model below the root (None: `model`)

    def search(self, state: State) -> SearchResult:
        value = None if self.value is None else self.value.value
        return search(self.model, state, self.base, self.depth, self.horizon, value, self.inner)

    def act(self, state: State) -> jax.Array:
        return self.search(state).action
