"""Lookahead verified in physics: Algorithm 2 with the simulator as its model (C MuJoCo).

At each decision of an episode the surrogate's lookahead (`root`, e.g. the cached L1) ranks the root actions by
its Q-values; the `k` best are each simulated from a copy of the current simulated state (`c_backend.Snapshot`:
MuJoCo's state rows and the controller's), closed loop to the end of the episode, hold included, with the
candidate as the first action and the `base` policy after it (`FirstThen`). The action taken is the one whose
branch did best in physics: held first, then the least hold angle error, then the surrogate's Q. The surrogate
prunes and ranks, the physics decides. Every decision's candidates and their outcomes are kept (`Decision`).

    policy = PhysicsLookahead(root=L1, root_axis=axis, base=rl, base_axis=None, k=17)
    result = phys.simulate_batch(policy, episodes, backend="c")      # only the C backend can copy its state

The branches of all the lockstep's episodes at one decision run as one lockstep of N x k rows on every core.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class FirstThen:
    """`first` at segment `at`, the `base` policy at every other decision (a branch's policy)."""

    first: jax.Array  # () int32: the branch's first action
    at: jax.Array  # () int32: the segment (waypoint) of that action
    base: Any  # a policy (anything with `act(state)`)

    def act(self, state) -> jax.Array:
        return jnp.where(state.t == self.at, self.first, jnp.asarray(self.base.act(state), jnp.int32))


@dataclasses.dataclass(frozen=True)
class Decision:
    """One decision of one episode: the candidates in the surrogate's order and their branches' outcomes."""

    episode: int  # row of the policy's episode batch
    segment: int
    candidates: np.ndarray  # (k,) int32 actions, the surrogate's best first
    q: np.ndarray  # (A,) the surrogate's Q-values of every root action
    fell: np.ndarray  # (k,) bool: the branch's tool fell
    angle_error: np.ndarray  # (k,) [deg] the branch's mean hold angle error (180 if it fell)
    chosen: int  # the action taken


@dataclasses.dataclass(eq=False)
class PhysicsLookahead:
    """The physics-verified lookahead policy (`L1-physics`). Not a JAX policy: the C backend's lockstep runs it
    (`Physics.simulate_many(..., backend="c")`). `decisions` collects every decision's `Decision` (appended)."""

    root: Any  # a policy with `plan(state)` -> Q-values `.q` (A,) over the actions (`lookahead.Lookahead`)
    root_axis: Any  # its policy_axis (e.g. 0 for the tables of the cached L1)
    base: Any  # the policy the branches follow after their first action (e.g. the RL policy)
    base_axis: Any = None  # its policy_axis: None (one base for every branch) or per episode (e.g. the cached L1's
    # tables: each branch gets its episode's)
    k: int = 17  # candidates simulated per decision (the surrogate's best k)
    cores: int | None = None  # cores of the branches' lockstep (default: all)
    workers: int | None = None  # its chunks (default as `c_backend.simulate`)
    decisions: list = dataclasses.field(default_factory=list)

    def __post_init__(self):
        if not (isinstance(self.k, int) and self.k >= 1):
            raise ValueError(f"PhysicsLookahead.k must be an int >= 1, got {self.k!r}")


def root_q(phys, root_axis, observe):
    """A jitted program: (root, obs_flat (N, nq + 2 nv), grasp (N,), episodes (N), k) -> (N, A) the root's Q;
    `observe` the C backend's flat-observation reader (`c_backend.programs(...).observe`)."""
    key = ("root_q", root_axis)
    if key not in phys._jitted:
        def q(root, obs_flat, grasp, episodes, k):
            return jax.vmap(lambda pol, o, g, e: pol.plan(phys.observed_state(o, g, e, k)).q,
                            in_axes=(root_axis, 0, 0, 0))(root, observe(obs_flat), grasp, episodes)

        phys._jitted[key] = jax.jit(q)
    return phys._jitted[key]


def _per_branch(base, axis, top: int):
    """The base policy for the N x top branches (episode-major): its per-episode leaves (axis 0) repeated."""
    if axis is None:
        return base
    return jax.tree.map(lambda ax, sub: sub if ax is None else jax.tree.map(lambda x: jnp.repeat(x, top, 0), sub),
                        axis, base, is_leaf=lambda x: x is None)


def choose(policy: PhysicsLookahead, phys, snapshot, rows: np.ndarray, obs: np.ndarray, episodes, k: int) -> np.ndarray:
    """(N,) the actions of the episodes `rows` of a lockstep at segment k (its `snapshot`, observations `obs`
    (N, ...), their `episodes`): the surrogate's k best, each branched to the episode's end in C MuJoCo."""
    from gsp_jax.physics import c_backend

    n, top = len(rows), min(policy.k, phys.space.n_actions)
    grasp = snapshot.grasp[rows]
    observe = c_backend.programs(phys, episodes).observe
    q = root_q(phys, policy.root_axis, observe)(policy.root, jnp.asarray(obs), jnp.asarray(grasp), episodes, k)
    q = np.asarray(q)
    cand = np.argsort(-q, axis=1, kind="stable")[:, :top].astype(np.int32)  # (N, top): ties keep the lower action
    branch_rows = np.repeat(rows, top)
    branch_eps = jax.tree.map(lambda x: np.repeat(np.asarray(x), top, 0), episodes)
    first = FirstThen(first=jnp.asarray(cand.ravel()), at=jnp.int32(k), base=_per_branch(policy.base,
                                                                                     policy.base_axis, top))
    axis = FirstThen(first=0, at=None, base=policy.base_axis)
    res = c_backend.simulate(phys, [(first, axis)], branch_eps, cores=policy.cores, workers=policy.workers,
                             start=snapshot.take(branch_rows))[0]
    fell, err = np.asarray(res.fell).reshape(n, top), np.asarray(res.angle_error).reshape(n, top)
    qk = np.take_along_axis(q, cand, 1)
    chosen = np.empty(n, np.int32)
    for i in range(n):  # held first, then the least angle error, then the surrogate's Q
        best = np.lexsort((-qk[i], err[i], fell[i]))[0]
        chosen[i] = cand[i, best]
        policy.decisions.append(Decision(int(i), k, cand[i], q[i], fell[i], err[i], int(chosen[i])))
    return chosen
