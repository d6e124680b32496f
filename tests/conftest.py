"""Shared fixtures. JAX is forced onto the CPU before anything imports it (tests are small and deterministic).

XLA's backend optimisation level is lowered for the tests: the IK's scans take several seconds each to compile on
a small CPU, and at level 0 they compile about twice as fast, with the same results to float32 rounding. The
tests check semantics, not the speed of the generated code. Set GSP_TEST_XLA_OPT=1 to keep XLA's default.
"""
import os

os.environ["JAX_PLATFORMS"] = "cpu"
if os.environ.get("GSP_TEST_XLA_OPT") != "1" and "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import hand as hand_lib  # noqa: E402


@pytest.fixture(scope="session")
def hand():
    """The HandModel of models/scene.xml (cached by hand.load, so one object for the whole run)."""
    return hand_lib.load()


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
