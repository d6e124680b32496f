"""What a step model and a policy offer: the two interfaces every planner, rollout and environment is written against.

    StepModel   reset(episode) -> state; step(state, action) -> (state, reward, done);
                step_every(state) -> the same with a leading axis A, every action at once; `space`, its actions
    Policy      act(state) -> action

A step model is `Surrogate` (IK and wrench solves, from any continuous state) or `planning.dp.TableModel` (one
episode's DP table: lookups, exact for the discrete states the surrogate visits from `reset`); a policy is any of
`planning.policies` or a `planning.lookahead.Lookahead`. Both are structural (`typing.Protocol`): a class of your own
that has the methods is one, no base class needed; `isinstance(x, StepModel)` checks that it has them. States are the
surrogate's `State`; a step of a finished state is absorbing (the state kept, reward 0, done).

`step_every` is what the lookahead's root expands (`lookahead.search`): a model with a cheaper way to step every
action than one step per action has it (`Surrogate.step_every` realises each distinct grasp once); a model without
one writes it as `step_each(self, state)`, its `step` vmapped over the actions.
"""
from __future__ import annotations

from typing import Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from gsp_jax.model.grasps import GraspSpace
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import State


@runtime_checkable
class StepModel(Protocol):
    """An MDP over the surrogate's states: what a rollout steps (`planning.rollout`) and a lookahead searches."""

    space: GraspSpace  # the grasps and actions (actions 0 .. space.n_actions - 1)

    def reset(self, episode: Episode) -> State:
        """The episode's start state."""
        ...

    def step(self, state: State, action: jax.Array) -> tuple[State, jax.Array, jax.Array]:
        """(next state, reward, done) of one action; absorbing once done (the state kept, reward 0)."""
        ...

    def step_every(self, state: State) -> tuple[State, jax.Array, jax.Array]:
        """`step(state, a)` for every action a at once: (next states, rewards, done), each with a leading axis A."""
        ...


@runtime_checkable
class Policy(Protocol):
    """A pure decision rule: jit- and vmap-able, reads any field of the state but `terms` (the last step's terms)."""

    def act(self, state: State) -> jax.Array:
        """() int32 the action at `state`."""
        ...


def step_each(step_model: StepModel, state: State) -> tuple[State, jax.Array, jax.Array]:
    """`model.step(state, a)` for every action a, vmapped: the `step_every` of a model without a cheaper one."""
    return jax.vmap(step_model.step, (None, 0))(state, jnp.arange(step_model.space.n_actions, dtype=jnp.int32))


def checked(step_model, policy=None, where: str = "step_model"):
    """`model` (and `policy`), having checked that they are a `StepModel` (and a `Policy`); else a TypeError naming
    what is missing. Returns `model`."""
    if not isinstance(step_model, StepModel):
        missing = [m for m in ("space", "reset", "step", "step_every") if not hasattr(step_model, m)]
        raise TypeError(f"{where}: a step model needs {', '.join(missing)} (`gsp_jax.surrogate.protocols.StepModel`; "
                        f"`step_every` can be `step_each(self, state)`), got {type(step_model).__name__}")
    if policy is not None and not isinstance(policy, Policy):
        raise TypeError(f"policy: a policy needs `act(state)` (`gsp_jax.surrogate.protocols.Policy`), got "
                        f"{type(policy).__name__}")
    return step_model
