"""The physics check: grasp sequences executed by a contact controller in MuJoCo (MJX, or C MuJoCo as the
reference), batched over episodes and policies.

    phys = Physics()                                           # scene from models/scene.xml
    result = phys.simulate(policy, episode)                    # one episode in MJX: pure, jit- and vmap-able
    results = phys.simulate_batch(policies, episodes)          # many episodes as one XLA kernel
    results = phys.simulate_batch(policies, episodes, backend="c")   # the same, stepped by C MuJoCo

  config.py      PhysicsConfig: every gain, rate and threshold, with its reason
  scene.py       the physics model (contact spheres, explicit pairs), per-episode fields, observation, outcome
  controller.py  the contact controller: object impedance, force solve, Cartesian fingers, grasp changes
  runner.py      Physics: decisions, control ticks and the MJX runner
  c_backend.py   the same runner stepped by C MuJoCo
"""
from gsp_jax.physics.config import PhysicsConfig
from gsp_jax.physics.controller import Controller, ControllerState, Motion, reference_motion
from gsp_jax.physics.runner import BACKENDS, Physics, Result, check_episodes
from gsp_jax.physics.scene import SUPPORT, Observation, Scene, physics_model

__all__ = ["BACKENDS", "Controller", "ControllerState", "Motion", "Observation", "Physics",
           "PhysicsConfig", "Result", "Scene", "SUPPORT", "check_episodes", "physics_model",
           "reference_motion"]
