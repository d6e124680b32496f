"""Shared fixtures. JAX is forced onto the CPU before anything imports it (tests are small and deterministic)."""
import os

os.environ["JAX_PLATFORMS"] = "cpu"

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


@pytest.fixture(scope="session")
def sur(hand):
    """A Surrogate of that hand (stateless, so one serves every module)."""
    from gsp_jax import surrogate

    return surrogate.Surrogate(hand)
