"""Shared fixtures. JAX is forced onto the CPU before anything imports it (tests are small and deterministic).

Compiled programs are kept across runs in the user's cache folder: JAX's persistent compilation cache
(`gsp_jax.core.cache`), in `$XDG_CACHE_HOME` (or ~/.cache) / gsp_jax / xla-tests / <this CPU>. JAX's key holds the
program, the jax and XLA versions, the backend and XLA_FLAGS, so a changed program is compiled again and an
unchanged one is loaded: a second run traces and runs, it does not compile. Within one run the xdist workers share
the folder too (many tests jit the same surrogate, table and lookahead programs).

    GSP_JAX_TEST_CACHE unset      the folder above, kept
    GSP_JAX_TEST_CACHE=<folder>   that folder, kept (a subfolder per CPU is made inside it)
    GSP_JAX_TEST_CACHE=off        no cache at all: a cold run (also 0, none); it must pass too
"""
import os

os.environ["JAX_PLATFORMS"] = "cpu"
_SETTING = os.environ.get("GSP_JAX_TEST_CACHE", "").strip()
CACHE_OFF = _SETTING.lower() in ("off", "0", "none", "false")
_DEFAULT = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "gsp_jax", "xla-tests")
os.environ["GSP_JAX_CACHE"] = "off" if CACHE_OFF else (_SETTING or _DEFAULT)  # read by gsp_jax.core.cache

import gsp_jax  # noqa: E402

gsp_jax.enable_cache()  # importing the package changes no setting: the tests turn the cache on (GSP_JAX_CACHE above)

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from gsp_jax.planning import dp  # noqa: E402
from gsp_jax.solvers import ik  # noqa: E402
from gsp_jax.model import hand as hand_lib  # noqa: E402

# The tests' surrogate solves a table's IK problems with `ik.solve` vmapped (`IKConfig.lanes=False`), not in the
# batch-last form a CPU uses by default: the same solve to float32 rounding (tests/test_ik_lanes.py checks the two
# tables against each other), its program compiling in about a third of the time; the tests build dozens of
# tables of a few waypoints, where compiling, not running, is the cost (docs/performance.md).
TABLE_IK = ik.IKConfig(lanes=False)


# `make test` gives each xdist worker whole files (--dist loadfile), so a module's fixtures (the MJX runner, the
# lookahead's tables, PPO's trainer) are computed once per run, not once per worker; in this order
# (--no-loadscope-reorder), the longest files first, so that no worker is left with one of them at the end
LONGEST_FIRST = ("test_lookahead.py", "test_physics.py", "walkthrough.ipynb", "test_policies.py")


def pytest_collection_modifyitems(config, items):
    """The longest files' tests first (a stable sort: the others keep their order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="session")
def hand():
    """The HandModel of the shipped wrench (`load_model().hand`: the default surrogate's own object)."""
    from gsp_jax.model import load as model_lib

    return model_lib.load_model().hand


@pytest.fixture(scope="session")
def mjmodel():
    """The compiled MuJoCo model of models/scene.xml (the independent reference for kinematics)."""
    return hand_lib.load_mjmodel()


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def _random_q(hand, rng, n):
    lo, hi = hand.joint_range[:, 0], hand.joint_range[:, 1]
    return rng.uniform(lo, hi, size=(n, hand.n_joints)).astype(np.float32)


@pytest.fixture(scope="session")
def random_q():
    """random_q(hand, rng, n): n joint configurations (n, J), uniform within the joint limits, float32."""
    return _random_q


_BUILDERS: dict = {}  # id(sur) -> (sur, its jitted build_table): the surrogate kept so that its id stays its own
_BACKUP = jax.jit(dp.backup)


def _solve_each(sur, episodes):
    """(tables, solutions) of stacked episodes (leaves (N, ...)): each episode's table by one jitted
    `dp.build_table` closed over `sur` -- the program `gym_env.make_grasp_env` compiles -- then `dp.backup`, stacked.
    One program per surrogate and waypoint count serves every test module (through the run's compilation cache) and
    is traced once per worker, where each module's own jitted batch (`vmap`, `build_tables`) compiled another."""
    if id(sur) not in _BUILDERS:
        _BUILDERS[id(sur)] = (sur, jax.jit(lambda ep: dp.build_table(sur, ep)))
    build = _BUILDERS[id(sur)][1]
    parts = []
    for i in range(episodes.waypoints.shape[0]):
        ep = jax.tree.map(lambda x, i=i: x[i], episodes)
        table = build(ep)
        parts.append((table, _BACKUP(table, ep.start_grasp)))
    return jax.tree.map(lambda *xs: jnp.stack(xs), *parts)


@pytest.fixture(scope="session")
def solve_each():
    """solve_each(sur, episodes) -> (tables, solutions), leaves (N, ...): see `_solve_each`."""
    return _solve_each


@pytest.fixture(scope="session")
def table_ik():
    """`TABLE_IK`, for the tests that build their own surrogates."""
    return TABLE_IK


@pytest.fixture(scope="session")
def sur(hand):
    """A Surrogate of that hand (stateless, so one serves every module), its tables' IK vmapped (`TABLE_IK`)."""
    from gsp_jax.surrogate import step as surrogate

    return surrogate.Surrogate(hand, ik_config=TABLE_IK, learned=False)


# ------------------------------------------------------------------------------------------ the small test model
# `models/testhand` (shipped as "testhand"): three fingers of two hinges, a bar; 27 grasps x 10 actions where the
# paper's hand has 288 x 17. A test whose property does not depend on the model (DP against brute force, lookahead
# against its base policy, ...) runs on it: its programs are about as large (they are vectorised over the model's
# grasps, actions and joints), but they run on a tenth of the grasps, and a brute force over its sequences is 10^T,
# not 17^T. The paper model's end-to-end tests stay on `sur` above.
SMALL_MODEL = "testhand"


@pytest.fixture(scope="session")
def small_model():
    """The `Model` of the small test hand (`models/testhand/scene.xml`)."""
    from gsp_jax.model import load as model_lib

    return model_lib.load_model(SMALL_MODEL)


@pytest.fixture(scope="session")
def small_sur(small_model):
    """A Surrogate of the small test hand, its tables' IK vmapped (`TABLE_IK`), as `sur`."""
    from gsp_jax.surrogate import step as surrogate

    return surrogate.Surrogate(small_model, ik_config=TABLE_IK)


def small_episode_set(model) -> dict:
    """The small hand's evaluation-like episodes (16 waypoints each), named as the paper's sets name theirs: its
    nominal lift, the height shifts with the model's torque of either sign, and mass with centre-of-mass offsets
    along y (the bar is 3 cm across: the paper's +-2 cm do not fit it), which keep the centre of mass on the
    thumb-index pinch's line, and one along x, which takes it off."""
    from gsp_jax.model import scenario

    t0 = model.hand.torque

    def ep(**kw):
        return scenario.make_episode(model=model, **kw)

    return {"nominal": ep(),
            f"shift+4mm_{-t0:+g}Nm": ep(shift_mm=4, torque=-t0),
            f"shift-6mm_{t0:+g}Nm": ep(shift_mm=-6, torque=t0),
            "mass2m0_comy+1cm": ep(mass_factor=2.0, com_y_cm=1.0),
            "mass0.5m0_comy-1cm": ep(mass_factor=0.5, com_y_cm=-1.0),
            "mass1.5m0_comy+1cm": ep(mass_factor=1.5, com_y_cm=1.0),
            "mass1.5m0_comx+1cm": ep(mass_factor=1.5, com_x_cm=1.0)}


@pytest.fixture(scope="session")
def small_episodes(small_model):
    """name -> Episode: `small_episode_set` of the small hand."""
    return small_episode_set(small_model)


@pytest.fixture(scope="session")
def small_episode(small_episodes):
    """The small hand's nominal lift (16 waypoints)."""
    return small_episodes["nominal"]
