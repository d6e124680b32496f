"""gsp_jax: grasp-sequence planning for in-hand tool manipulation, in pure JAX.

The public face is this package's names (`__all__`); a user imports only it:

    import gsp_jax as gsp
    model = gsp.load_model("wrench")                      # or an MJCF scene's path; gsp.check_model(path) first
    sur = gsp.Surrogate(model)                            # the surrogate step: sur.reset(episode), sur.step(s, a)
    episode = gsp.episode_set("eval", model)["mass1m0_comy+1cm"]
    ctx = gsp.context(episodes={"unseen": episode}, model=model)   # DP tables, the PPO policy, the DP baseline
    plan = gsp.plan(ctx, "L1")                            # a planner by name (gsp.planner_names()), its episode
    results = gsp.check(ctx, ["dp-opt", "L1"])            # the physics check: closed loop in C MuJoCo

The modules below (`gsp_jax.surrogate`, `gsp_jax.dp`, ...) are the library's inside: documented and importable for
those who extend it (docs/architecture.md), but their names may change; what this package exports stays.

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

_LAZY = {  # public name -> (module, attribute): imported on first use, so `import gsp_jax` stays quick
    "Surrogate": ("gsp_jax.surrogate", "Surrogate"),
    "RewardConfig": ("gsp_jax.reward", "RewardConfig"),
    "Episode": ("gsp_jax.scenario", "Episode"),
    "EpisodeError": ("gsp_jax.scenario", "EpisodeError"),
    "make_episode": ("gsp_jax.scenario", "make_episode"),
    "episode_set": ("gsp_jax.scenario", "episode_set"),
    "Context": ("gsp_jax.evaluation", "Context"),
    "context": ("gsp_jax.evaluation", "context"),
    "Lookahead": ("gsp_jax.policies", "Lookahead"),
    "load_network_policy": ("gsp_jax.policies", "load_network_policy"),
    "planner_names": ("gsp_jax.planners", "names"),
    "planner": ("gsp_jax.planners", "make"),
    "register_planner": ("gsp_jax.planners", "register"),
    "Plan": ("gsp_jax.planners", "Plan"),
    "plan": ("gsp_jax.planners", "plan"),
    "decide": ("gsp_jax.planners", "decide"),
    "check": ("gsp_jax.planners", "check"),
    "Physics": ("gsp_jax.physics", "Physics"),
    "PhysicsConfig": ("gsp_jax.physics", "PhysicsConfig"),
}

__all__ = ["CACHE_DIR", "Model", "ModelError", "check_model", "load_model", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'gsp_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
