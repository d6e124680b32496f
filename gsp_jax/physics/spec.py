"""What the C backend reads of a `runner.Physics`: one frozen, typed record, built once by it (`Physics.spec`).

The C backend (`c_backend`, `native`) and a policy that decides in physics (`verified`, through its `in_physics`
hook) read named fields of a `PhysicsSpec`: the model and its scene, the config and the controller, the timeline, and
the JAX functions both backends share (`Physics`'s methods: a start, a decision, a control tick, its status, the
result), instead of reaching into a `Physics`. Their entry points take either (`of`).

    spec = phys.spec                        # or physics.spec.of(phys)
    c_backend.simulate(spec, groups, episodes)
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Hashable, Protocol, TypeVar

import jax
import mujoco
import numpy as np

from gsp_jax.model.grasps import GraspSpace
from gsp_jax.model.hand import HandModel
from gsp_jax.model.scenario import Episode
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.physics.controller import Controller, ControllerState
from gsp_jax.physics.scene import Observation, Scene

T = TypeVar("T")


@dataclasses.dataclass(frozen=True, eq=False)
class PhysicsSpec:
    """One `Physics` as its backends read it (numpy and JAX; nothing here runs on its own)."""

    # the model
    hand: HandModel
    space: GraspSpace
    scene: Scene  # the physics scene: its MuJoCo model, indices, per-episode fields, observation, outcome
    mj_model: mujoco.MjModel  # `scene.model`
    config: PhysicsConfig
    controller: Controller
    # the timeline
    timestep: float  # [s] a control tick: the scene's physics step
    n_segment: int  # control ticks per decision segment
    n_hold: int  # hold segments after the last waypoint
    # the JAX functions of one episode both backends share (`Physics`'s methods of the same names)
    start: Callable[[Episode], tuple[jax.Array, ControllerState]]  # (initial qpos, controller state)
    decide: Callable[..., tuple[jax.Array, jax.Array, ControllerState]]  # (policy, cs, obs, grasp, episode, k) ->
    # (action, grasp, controller state)
    tick: Callable[..., tuple[jax.Array, jax.Array, ControllerState]]  # (cs, obs, episode, j) -> (ctrl, ext, cs)
    check: Callable[[Observation, Episode, Any], tuple[jax.Array, jax.Array, jax.Array]]  # (angle, perr, fell)
    observed_state: Callable[..., Any]  # (obs, grasp, episode, k) -> the surrogate's `State` a policy reads
    hold_error: Callable[[Any, Any, int], jax.Array]  # (angle, fell, n_steps) -> the hold's mean angle error
    result: Callable[..., Any]  # (actions, grasps, angle, perr, qpos, fell, fall_tick, n_steps) -> `runner.Result`
    kept: Callable[[Hashable, Callable[[], T]], T]  # what a backend makes once per `Physics` (`Physics.kept`)
    nominal: Callable[[], Episode]  # the model's nominal episode (`scenario.make_episode(model=)`; a `ModelError`
    # for a hand not loaded from a scene file)

    def n_ticks(self, n_steps: int) -> int:
        """Control ticks of an episode with n_steps waypoints (the length of `Result.angle`)."""
        return (n_steps + self.n_hold) * self.n_segment

    def segment_start(self, k: int) -> np.float32:
        """[s] when segment k starts, float32 as `decide` computes it in JAX (k n_segment, then times the tick)."""
        return np.float32(k * self.n_segment) * np.float32(self.timestep)

    def hold_time(self, n_steps: int) -> float:
        """Simulated time at which the hold starts [s]."""
        return n_steps * self.n_segment * self.timestep


class HasSpec(Protocol):
    """Anything with a `PhysicsSpec` (a `runner.Physics`)."""

    spec: PhysicsSpec


def of(phys: PhysicsSpec | HasSpec) -> PhysicsSpec:
    """The spec of a `Physics` (its `spec`), or `phys` itself if it is one."""
    return phys if isinstance(phys, PhysicsSpec) else phys.spec
