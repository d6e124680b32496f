"""gsp_jax: grasp-sequence planning for in-hand tool manipulation, in pure JAX.

Data flows one way:

    a scene (models/*.xml or yours) -> model.py (load_model, check_model) -> hand.py (constant arrays)
                                     -> kinematics.py, ik.py, wrench.py (kernels)
    reward.py (RewardConfig, its terms; models/reward_calibration.json) -> surrogate.py, dp.py
    scenario.py (Episode) -> surrogate.py (reset/step)               -> dp.py (table, Bellman backup)
                                                                     -> policies.py (one `act(state)` interface)
                                                                     -> planners.py (every planner by name)

The surrogate step is `surrogate.Surrogate.step`: `realise` (IK) at the current and next waypoint, then
`score` (wrench solves: the move, the hold, the hold under the external wrench, and the change when changes are
priced) -> `reward.arrival` and `reward.with_previous` (terms -> reward); the DP table scores with the same
functions (`reward.of_transitions`).
"""

from gsp_jax import cache as _cache

CACHE_DIR = _cache.enable()  # XLA's compiled programs on disk (gsp_jax.cache; GSP_JAX_CACHE=off turns it off)


def _import_mjx_quietly() -> None:
    """mujoco-mjx prints "Failed to import warp: ..." twice when it probes its optional NVIDIA Warp backend,
    which we do not use; import it once here with those two lines held back (anything else it prints passes)."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        import mujoco.mjx  # noqa: F401
    for line in buf.getvalue().splitlines():
        if not line.startswith(("Failed to import warp:", "Failed to import mujoco_warp:")):
            print(line)


_import_mjx_quietly()


def _register_gymnasium() -> None:
    """`gymnasium.make("gsp_jax/GraspSequence-v0", ...)` and `gymnasium.make_vec(...)` (gsp_jax.gym_env); the
    environment's modules are imported only when one is made."""
    import gymnasium

    if "gsp_jax/GraspSequence-v0" not in gymnasium.registry:
        gymnasium.register(
            id="gsp_jax/GraspSequence-v0",
            entry_point="gsp_jax.gym_env:make",
            vector_entry_point="gsp_jax.gym_env:make_vector",
        )


_register_gymnasium()

from gsp_jax.model import Model, ModelError, check_model, load_model  # noqa: E402  (the one door to a model)

__all__ = ["CACHE_DIR", "Model", "ModelError", "check_model", "load_model"]
