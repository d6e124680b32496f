"""Shared fixtures. JAX is forced onto the CPU before anything imports it (tests are small and deterministic).

Compiled programs are shared between the tests and the xdist workers of one run through the package's persistent
compilation cache (`gsp_jax.cache`), here in a fresh folder of the run (many tests jit the same surrogate, table and
lookahead programs; compiling them is most of the suite's time on a CPU). The folder is removed at the end of the
run, so a run never loads what another run compiled; GSP_JAX_TEST_CACHE=off turns the cache off."""
import os
import tempfile

os.environ["JAX_PLATFORMS"] = "cpu"
CACHE_OFF = os.environ.get("GSP_JAX_TEST_CACHE", "").lower() in ("off", "0", "none")
# made here, in the process that starts the xdist workers, so they inherit one folder
if not CACHE_OFF and "_GSP_JAX_TEST_CACHE_DIR" not in os.environ:
    os.environ["_GSP_JAX_TEST_CACHE_DIR"] = tempfile.mkdtemp(prefix="gsp_jax_test_xla_")
os.environ["GSP_JAX_CACHE"] = "off" if CACHE_OFF else os.environ["_GSP_JAX_TEST_CACHE_DIR"]  # read by gsp_jax.cache

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from gsp_jax import dp, ik  # noqa: E402
from gsp_jax import hand as hand_lib  # noqa: E402

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


def pytest_sessionfinish(session, exitstatus):
    """The run's compilation cache goes with it (in the process that made it: not an xdist worker)."""
    import shutil

    if not CACHE_OFF and not hasattr(session.config, "workerinput"):
        shutil.rmtree(os.environ.pop("_GSP_JAX_TEST_CACHE_DIR", ""), ignore_errors=True)


@pytest.fixture(scope="session")
def hand():
    """The HandModel of the shipped wrench (`load_model().hand`: the default surrogate's own object)."""
    from gsp_jax import model as model_lib

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
    from gsp_jax import surrogate

    return surrogate.Surrogate(hand, ik_config=TABLE_IK)
