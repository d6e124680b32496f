"""The native controller tick (`gsp_jax.physics.native`) against the JAX controller it was written from.

Tick by tick on recorded states: the C backend runs episodes with the JAX controller (`controller="jax"`), and
at every tick the native tick reads the same controller state and observation; its motor commands, external
wrench, next controller state and status must agree within the precision of the JAX controller's float32
arithmetic (the native one runs in float64). Outcomes: the same episodes with either controller hold or fall
alike and end at the same hold error.
"""
from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax import evaluation, physics, policies, scenario  # noqa: E402
from gsp_jax.physics import c_backend, native  # noqa: E402
from gsp_jax.surrogate import Surrogate  # noqa: E402

T = 4
CONFIG = physics.PhysicsConfig().replace(hold=0.25)


@pytest.fixture(scope="module")
def phys():
    return physics.Physics(Surrogate(), CONFIG)


@pytest.fixture(scope="module")
def episodes():
    """Three evaluation episodes (their first T waypoints) and a fourth with the CoM off-centre under a torque."""
    eps = [e.head(T) for e in list(scenario.eval_set_a().values())[:3]]
    eps.append(scenario.make_episode(mass_factor=2.0, com_y_cm=1.0).head(T))
    return scenario.stack(eps)


def _four_tips_then_changes(phys):
    """Four tips reached at the first waypoints, then the middle tip moved and moved back: every phase of a grasp
    change (unload, travel, arrive, load) in T segments."""
    sp = phys.space
    acts = np.asarray(evaluation.four_tips(sp, T)).copy()
    acts[-2:] = [sp.action("middle_distal", 2), sp.action("middle_distal", 1)]
    return policies.SequencePolicy(jnp.asarray(acts), sp)


def test_native_state_layout_is_the_flat_controller_state(phys, episodes):
    """`native.state_offsets` finds each field of a `ControllerState` where `ravel_pytree` puts it."""
    _, cs = jax.vmap(phys.start)(episodes)
    one = jax.tree.map(lambda x: np.asarray(x)[0], cs)
    flat = np.asarray(jax.flatten_util.ravel_pytree(jax.tree.map(lambda x: np.asarray(x, np.float32), one))[0])
    offsets = native.state_offsets(one)
    for name, start in offsets.items():
        value = np.asarray(getattr(one, name), np.float32).ravel()
        np.testing.assert_array_equal(flat[start:start + value.size], value, err_msg=name)


def test_native_tick_is_the_jax_tick_on_recorded_states(phys, episodes):
    """At every tick of four short episodes (JAX controller, C MuJoCo), the native tick from the same state and
    observation gives the JAX tick's motor commands (within 1e-4 N m), external wrench (1e-5 N), next controller state
    (within 1e-3 in force units: the warm-started force solves carry float32 rounding) and status: the angle
    within 0.05 deg (float32's arccos near 1 resolves ~0.02 deg), the same falls."""
    policy = _four_tips_then_changes(phys)
    run = c_backend._Lockstep(phys, [(policy, None)], episodes, 1, None, controller="jax")
    tick = c_backend.native_tick(phys)
    n, nu, nq = len(episodes.mass), phys.model.nu, phys.model.nq
    rows, worst = np.arange(n), {"ctrl": 0.0, "ext": 0.0, "cs": 0.0, "angle": 0.0}
    changing = 0
    for k in range(T + phys.n_hold):
        run.decide(k)
        eng = run.engine
        for i in range(phys.n_segment):
            j = k * phys.n_segment + i
            cs_native, out_native = run.cs.copy(), np.zeros_like(run.out)
            tick(j, rows, cs_native, eng.obs, run.ep_native, out_native)
            cs, out = run.pr.tick(run.cs, eng.obs, run.ep_flat, j)
            run.cs, out = np.array(cs), np.asarray(out)
            changing += int(np.sum(run.cs[:, tick.constants.cs_changed:tick.constants.cs_changed + phys.hand.n_links]))
            worst["ctrl"] = max(worst["ctrl"], np.abs(out_native[:, :nu] - out[:, :nu]).max())
            worst["ext"] = max(worst["ext"], np.abs(out_native[:, nu:nu + 6] - out[:, nu:nu + 6]).max())
            worst["cs"] = max(worst["cs"], np.abs(cs_native - run.cs).max())
            if j > 0:
                worst["angle"] = max(worst["angle"], np.abs(out_native[:, nu + 6] - out[:, nu + 6]).max())
                np.testing.assert_array_equal(out_native[:, -1], out[:, -1], err_msg=f"fell at tick {j}")
                run.record(rows, j - 1, out[:, nu + 6:], eng.obs[:, :nq])
            alive = rows[~run.fell]
            if alive.size:
                eng.step(tick.constants, alive, out, float(phys.scene.pedestal_drop(j * phys.timestep, xp=np)),
                         np.zeros(64))
    assert changing > 0  # grasp changes were under way
    assert worst["ctrl"] < 1e-4 and worst["ext"] < 1e-5 and worst["cs"] < 1e-3 and worst["angle"] < 0.05, worst
    assert not np.any(run.fell)


def test_native_and_jax_controllers_give_the_same_outcomes(phys, episodes):
    """The whole lockstep with either controller: the same falls, hold errors within 0.02 deg (the physics
    carries the last-bit differences forward: measured 6e-4 deg on the 27 evaluation episodes, full length)."""
    policy = _four_tips_then_changes(phys)
    res = {c: c_backend.simulate(phys, [(policy, None)], episodes, controller=c)[0] for c in c_backend.CONTROLLERS}
    np.testing.assert_array_equal(res["native"].fell, res["jax"].fell)
    np.testing.assert_array_equal(res["native"].grasps, res["jax"].grasps)
    np.testing.assert_allclose(res["native"].angle_error, res["jax"].angle_error, atol=0.02)
    assert not np.any(res["native"].fell)
    with pytest.raises(ValueError, match="controller"):
        c_backend.simulate(phys, [(policy, None)], episodes, controller="python")
