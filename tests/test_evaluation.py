"""`gsp_jax.planning.evaluation`: the library's planners (registered in `gsp_jax.planners.registry`) and its reference
sequences."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from gsp_jax.planning import evaluation
from gsp_jax.model import grasps, scenario
from gsp_jax.planners import registry as planners


def _bare(sur, rl=None):
    """A context of one episode with nothing built (no tables, no PPO policy, no DP baseline)."""
    batch = scenario.stack([scenario.make_episode()])
    return evaluation.Context(sur, "test", ["nominal"], batch, None, None, None, rl, "")


@pytest.mark.parametrize("name", ["dp-base", "dp-opt", "random", "rl", "L1", "L2"])
def test_a_planner_missing_what_it_needs_is_refused_by_name(sur, name):
    with pytest.raises(ValueError, match=f"planner '{name}': the context was built without"):
        planners.make(_bare(sur), name)


def test_cached_lookahead_needs_the_tables_too(sur):
    rl = object()  # present: only the tables are missing
    with pytest.raises(ValueError, match="planner 'L1': the context was built without tables"):
        planners.make(_bare(sur, rl), "L1", cached=True)
    policy, axis = planners.make(_bare(sur, rl), "L1", cached=False)
    assert axis is None and policy.inner is None


def test_physics_lookahead_is_made_of_its_root_and_bases(sur):
    """`L1-physics` (continuous L1, no tables needed): the root L1 and one (policy, axis) per base, in order; bases
    that are not planners its branches can run are refused by name."""
    from gsp_jax.physics.verified import PhysicsLookahead

    ctx = _bare(sur, rl=object())
    policy, axis = planners.make(ctx, "L1-physics", cached=False, k=3, bases=("four-tips", "rl"))
    assert isinstance(policy, PhysicsLookahead) and axis is None and policy.k == 3
    assert policy.root.depth == 1 and [b[0] for b in policy.bases][1] is ctx.rl
    np.testing.assert_array_equal(policy.bases[0][0].actions, evaluation.four_tips(sur.space, ctx.batch.n_steps))
    with pytest.raises(ValueError, match="bases: 'dp-opt' cannot be built here: .* without solutions"):  # the
        # default's second base, DP optimal, needs the tables' solutions
        planners.make(ctx, "L1-physics", cached=False)
    for bad in ("rl", (), ("L1-physics",), ("random",)):
        with pytest.raises(ValueError, match="bases"):
            planners.make(ctx, "L1-physics", cached=False, bases=bad)


def test_reference_sequences_reach_their_grasps(sur):
    """four-tips adds the ring tip to the start grasp and keeps it; one-tip leaves the index tip alone."""
    space, start = sur.space, int(scenario.make_episode().start_grasp)

    def final(actions):
        g = start
        for a in actions:
            g = int(space.apply(g, int(a))[0])
        return np.asarray(space.decode(g))

    names = [n.split("_")[0] for n in sur.hand.link_names]
    tips = [n.endswith("distal") for n in sur.hand.link_names]
    four = final(evaluation.four_tips(space))
    assert {names[i] for i in np.flatnonzero(four)} == {"thumb", "index", "middle", "ring"}
    assert all(tips[i] for i in np.flatnonzero(four))
    one = final(evaluation.one_tip(space))
    assert [names[i] for i in np.flatnonzero(one)] == ["index"]
    policy, axis = planners.make(_bare(sur), "four-tips")
    assert axis is None and np.array_equal(np.asarray(policy.actions), evaluation.four_tips(space))
    assert (np.all(evaluation.one_tip(space)[2:] == grasps.NULL)
            and jnp.asarray(evaluation.one_tip(space)).dtype == jnp.int32)
    np.testing.assert_array_equal(evaluation.one_tip(space)[:2], [space.action("middle_distal", 0),
                                                                  space.action("thumb_distal", 0)])  # as written for it


def test_one_tip_leaves_one_contact_on_any_hand(small_model):
    """Issue 83: the one-tip sequence of any model (the test hand: three fingers) ends with one contact of its start
    grasp, the others let go one a waypoint."""
    from gsp_jax.model import grasps as grasps_lib

    space = grasps_lib.space_of(small_model.hand)
    g = int(space.encode(space.start_options))
    for a in evaluation.one_tip(space, 6):
        g = int(space.apply(g, int(a))[0])
    left = np.flatnonzero(np.asarray(space.decode(g)))
    assert len(left) == 1 and space.start_options[left[0]] > 0
