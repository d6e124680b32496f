"""The physics check: grasp sequences executed by a contact controller in MuJoCo (MJX, or C MuJoCo as the
reference), batched over episodes and policies.

    phys = Physics()                                           # scene from models/scene.xml
    result = phys.simulate(policy, episode)                    # one episode in MJX: pure, jit- and vmap-able
    results = phys.simulate_batch(policies, episodes)          # many episodes as one XLA kernel
    results = phys.simulate_batch(policies, episodes, backend="c")   # the same, stepped by C MuJoCo

  config.py      PhysicsConfig: the settings (gains, rates, thresholds), nested by concern
  scene.py       the physics model (contact spheres, explicit pairs), per-episode fields, observation, outcome
  controller.py  the contact controller: object impedance, force solve, Cartesian fingers, grasp changes
  runner.py      Physics: decisions, control ticks and the MJX runner
  c_backend.py   the same runner stepped by C MuJoCo
"""
from gsp_jax.physics.config import (ControllerConfig, FingerConfig, OutcomeConfig, PhysicsConfig, SimConfig,
                                    TimelineConfig)
from gsp_jax.physics.controller import Controller, ControllerState, Motion, reference_motion
from gsp_jax.physics.runner import BACKENDS, FALLEN_ERROR, Physics, Result, check_episodes
from gsp_jax.physics.scene import SUPPORT, Observation, Scene, physics_model

__all__ = ["BACKENDS", "Controller", "ControllerConfig", "ControllerState", "FALLEN_ERROR", "FingerConfig", "Motion",
           "Observation", "OutcomeConfig", "Physics", "PhysicsConfig", "Result", "Scene", "SimConfig", "SUPPORT",
           "TimelineConfig", "check_episodes", "physics_model", "reference_motion"]
