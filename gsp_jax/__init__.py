"""gsp_jax: grasp-sequence planning for in-hand tool manipulation, in pure JAX.

The public face is this package's names (`__all__`); a user imports only it:

    import gsp_jax as gsp
    model = gsp.load_model("wrench")                      # or an MJCF scene's path; gsp.check_model(path) first
    sur = gsp.Surrogate(model)                            # the surrogate step: sur.reset(episode), sur.step(s, a)
    episode = gsp.episode_set("eval", model)["mass1m0_comy+1cm"]
    ctx = gsp.context(episodes={"unseen": episode}, model=model)   # DP tables, the PPO policy, the DP baseline
    plan = gsp.plan(ctx, "L1")                            # a planner by name (gsp.planner_names()), its episode
    results = gsp.check(ctx, ["dp-opt", "L1"])            # the physics check: closed loop in C MuJoCo

The modules below (`gsp_jax.surrogate.step`, `gsp_jax.planning.dp`, ...) are the library's inside: documented and
importable for those who extend it (docs/architecture.md), but their names may change; what this package exports
stays.

The library's folders are its layers, each importing only itself and the folders above it (docs/architecture.md):

    core/        files, the compilation cache, the platform, statistics, processes of one run
    ppo/         PPO itself (networks, losses, config, checkpoint, training loop): no domain import
    model/       an MJCF scene -> Model (load.py), hand arrays, kinematics, grasps, episodes (scenario.py)
    importer/    a published hand -> a hand file that follows the conventions
    solvers/     IK (ik.py, ik_lanes.py), contact forces in friction cones (wrench.py)
    surrogate/   one decision step (step.py: Surrogate.reset/step), the reward, the observation, the learned term
    planning/    the DP table and backup, Algorithm 2, policies, the evaluation context
    learning/    the surrogate as brax and Gymnasium envs, DP behaviour cloning, the paper's PPO recipe
    physics/     the physics check (MJX, C MuJoCo), the oracle, L1-physics, pictures
    planners/    every planner by name (registry.py), one unseen episode planned online

The surrogate step is `gsp_jax/surrogate/step.py`, `Surrogate.step`: `realise` (IK) at the current and next
waypoint, then `score` (wrench solves: the move, the hold, the hold under the external wrench, and the change when
changes are priced) -> `reward.arrival` and `reward.with_previous` (terms -> reward); the DP table scores with the
same functions (`reward.of_transitions`).

Importing the package changes no global setting: XLA's compilation cache on disk is turned on by `enable_cache()`
(the `python -m experiments` commands call it), and the Gymnasium environment by `register_gymnasium()`.
"""


def enable_cache() -> str | None:
    """Turn on XLA's compilation cache on disk (`gsp_jax.core.cache`: the user's cache folder, or $GSP_JAX_CACHE;
    GSP_JAX_CACHE=off leaves it off); returns its folder, or None. A later process that builds the same program
    loads it instead of compiling it."""
    from gsp_jax.core import cache

    return cache.enable()


def register_gymnasium() -> str:
    """Register the Gymnasium environment (`gsp_jax.learning.gym_env`) and return its id,
    ``"gsp_jax/GraspSequence-v0"``: `gymnasium.make(id, ...)` and `gymnasium.make_vec(id, ...)` then make it. Its
    modules are imported only when one is made. Registering twice is harmless."""
    import gymnasium

    env_id = "gsp_jax/GraspSequence-v0"
    if env_id not in gymnasium.registry:
        gymnasium.register(id=env_id, entry_point="gsp_jax.learning.gym_env:make",
                           vector_entry_point="gsp_jax.learning.gym_env:make_vector")
    return env_id


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

from gsp_jax.model.load import Model, ModelError, check_model, load_model  # noqa: E402  (the one door to a model)

_LAZY = {  # public name -> (module, attribute): imported on first use, so `import gsp_jax` stays quick
    "Surrogate": ("gsp_jax.surrogate.step", "Surrogate"),
    "RewardConfig": ("gsp_jax.surrogate.reward", "RewardConfig"),
    "Episode": ("gsp_jax.model.scenario", "Episode"),
    "EpisodeError": ("gsp_jax.model.scenario", "EpisodeError"),
    "make_episode": ("gsp_jax.model.scenario", "make_episode"),
    "episode_set": ("gsp_jax.model.scenario", "episode_set"),
    "Context": ("gsp_jax.planning.evaluation", "Context"),
    "context": ("gsp_jax.planning.evaluation", "context"),
    "Lookahead": ("gsp_jax.planning.policies", "Lookahead"),
    "load_network_policy": ("gsp_jax.planning.policies", "load_network_policy"),
    "planner_names": ("gsp_jax.planners.registry", "names"),
    "planner": ("gsp_jax.planners.registry", "make"),
    "register_planner": ("gsp_jax.planners.registry", "register"),
    "Plan": ("gsp_jax.planners.registry", "Plan"),
    "plan": ("gsp_jax.planners.registry", "plan"),
    "decide": ("gsp_jax.planners.registry", "decide"),
    "check": ("gsp_jax.planners.registry", "check"),
    "Physics": ("gsp_jax.physics", "Physics"),
    "PhysicsConfig": ("gsp_jax.physics", "PhysicsConfig"),
}

_MOVED = {  # `from gsp_jax import dp` as it read before the layer folders -> the module's place now
    "files": "gsp_jax.core.files", "cache": "gsp_jax.core.cache", "platform": "gsp_jax.core.platform",
    "stats": "gsp_jax.core.stats", "distributed": "gsp_jax.core.distributed", "hand": "gsp_jax.model.hand",
    "kinematics": "gsp_jax.model.kinematics", "grasps": "gsp_jax.model.grasps", "scenario": "gsp_jax.model.scenario",
    "ik": "gsp_jax.solvers.ik", "ik_lanes": "gsp_jax.solvers.ik_lanes", "wrench": "gsp_jax.solvers.wrench",
    "reward": "gsp_jax.surrogate.reward", "observation": "gsp_jax.surrogate.observation",
    "learned": "gsp_jax.surrogate.learned", "dp": "gsp_jax.planning.dp", "lookahead": "gsp_jax.planning.lookahead",
    "policies": "gsp_jax.planning.policies", "evaluation": "gsp_jax.planning.evaluation",
    "env": "gsp_jax.learning.env", "gym_env": "gsp_jax.learning.gym_env", "pretrain": "gsp_jax.learning.pretrain",
    "render": "gsp_jax.physics.render", "online": "gsp_jax.planners.online", "hand_import": "gsp_jax.importer",
}

__all__ = ["enable_cache", "register_gymnasium", "Model", "ModelError", "check_model", "load_model", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value
        return value
    if name in _MOVED:  # an old module path (before the layer folders): one release, with a warning
        import importlib
        import warnings

        warnings.warn(f"gsp_jax.{name} moved to {_MOVED[name]}; import it from there", DeprecationWarning,
                      stacklevel=2)
        return importlib.import_module(_MOVED[name])
    raise AttributeError(f"module 'gsp_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
