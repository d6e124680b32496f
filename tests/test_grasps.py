"""The discrete grasp/action spaces (gsp_jax.model.grasps) against brute-force enumeration with itertools."""
import itertools

import numpy as np
import pytest

from gsp_jax.model import load as model_lib
from gsp_jax.model import grasps, scenario

COUNTS = (3, 3, 2, 4, 2, 2)  # the paper's option counts (option 0 = not in contact)


@pytest.fixture(scope="module")
def space():
    return model_lib.default_space()


@pytest.fixture(scope="module")
def all_options(space):
    return np.asarray(space.decode(np.arange(space.n_grasps)))


def test_counts_match_the_model(space, hand):
    assert space.n_options == COUNTS == tuple(hand.n_options)
    assert space.link_names == hand.link_names
    assert space.n_links == 6
    assert space.n_grasps == 288 == int(np.prod(COUNTS))


def test_decode_is_a_bijection_onto_all_option_tuples(space, all_options):
    assert all_options.shape == (288, 6)
    tuples = {tuple(int(x) for x in row) for row in all_options}
    assert len(tuples) == 288
    assert tuples == set(itertools.product(*(range(n) for n in COUNTS)))
    assert np.all(all_options >= 0) and np.all(all_options < np.asarray(COUNTS))


def test_encode_inverts_decode(space, all_options):
    np.testing.assert_array_equal(np.asarray(space.encode(all_options)), np.arange(288))
    for g in (0, 1, 95, 96, 287):  # scalar path too
        assert int(space.encode(space.decode(g))) == g


def test_mixed_radix_first_link_slowest(space):
    # itertools.product varies the last element fastest: its enumeration order is the grasp numbering
    for g, opts in enumerate(itertools.product(*(range(n) for n in COUNTS))):
        if g % 37 == 0 or g == 287:
            assert int(space.encode(np.array(opts))) == g
            assert tuple(np.asarray(space.decode(g)).tolist()) == opts


def test_seventeen_actions_null_then_every_link_option_pair(space):
    """Action 0 is the null action; actions 1..16 are the 16 (link, option) pairs, each once."""
    assert space.n_actions == 17 and grasps.NULL == 0
    assert len(space.action_link) == len(space.action_option) == 17
    assert space.action_link[0] == space.action_option[0] == -1
    pairs = list(zip(space.action_link[1:].tolist(), space.action_option[1:].tolist()))
    assert len(set(pairs)) == 16
    assert set(pairs) == {(li, o) for li, n in enumerate(COUNTS) for o in range(n)}


def test_apply_changes_at_most_one_link(space, all_options):
    g = np.repeat(np.arange(288), 17)
    a = np.tile(np.arange(17), 288)
    nxt, redundant = space.apply(g, a)
    nxt, redundant = np.asarray(nxt), np.asarray(redundant)
    assert nxt.shape == redundant.shape == (288 * 17,)
    assert np.all((nxt >= 0) & (nxt < 288))
    null = a == grasps.NULL
    # the null action keeps the grasp and is never redundant
    np.testing.assert_array_equal(nxt[null], g[null])
    assert not redundant[null].any()
    g, a, nxt, redundant = g[~null], a[~null], nxt[~null], redundant[~null]
    before, after = all_options[g], all_options[nxt]
    link, opt = space.action_link[a], space.action_option[a]
    rows = np.arange(len(g))
    # the action's link is set to the action's option ...
    np.testing.assert_array_equal(after[rows, link], opt)
    # ... and every other link is untouched
    mask = np.ones_like(before, dtype=bool)
    mask[rows, link] = False
    np.testing.assert_array_equal(after[mask], before[mask])
    # redundant exactly when a non-null action changed nothing
    np.testing.assert_array_equal(redundant, nxt == g)
    np.testing.assert_array_equal(redundant, before[rows, link] == opt)
    # every grasp has exactly one redundant action per link
    assert np.all(redundant.reshape(288, 16).sum(1) == 6)


def test_transitions_table_is_apply_for_every_grasp_and_action(space):
    """The numpy table of next grasps (static work at trace time) is `apply`, entry by entry."""
    g, a = np.meshgrid(np.arange(288), np.arange(17), indexing="ij")
    np.testing.assert_array_equal(space.transitions, np.asarray(space.apply(g, a)[0]))
    assert space.transitions.shape == (288, 17) and space.transitions.dtype == np.int32


def test_shared_grasp_releases_exactly_the_moving_link(space, all_options):
    """`shared(g, a)`: the links that hold the tool while `a` executes -- `g` with the moved link released, and
    `g` itself when nothing moves (null or redundant). Against a per-link enumeration."""
    g = np.repeat(np.arange(288), 17)
    a = np.tile(np.arange(17), 288)
    shared = np.asarray(space.shared(g, a))
    nxt = np.asarray(space.apply(g, a)[0])
    for i in range(len(g)):
        expect = all_options[g[i]].copy()
        if nxt[i] != g[i]:
            expect[space.action_link[a[i]]] = 0
        np.testing.assert_array_equal(all_options[shared[i]], expect)
    # the shared links are common to both grasps
    assert np.all((all_options[shared] == 0) | (all_options[shared] == all_options[nxt]))


def test_apply_scalar(space):
    g = int(space.encode(np.array([1, 1, 0, 1, 0, 0])))
    a = space.action("middle_distal", 3)
    nxt, red = space.apply(g, a)
    assert tuple(np.asarray(space.decode(nxt)).tolist()) == (1, 1, 0, 3, 0, 0)
    assert not bool(red)
    nxt2, red2 = space.apply(nxt, a)
    assert int(nxt2) == int(nxt) and bool(red2)
    nxt3, red3 = space.apply(nxt, grasps.NULL)
    assert int(nxt3) == int(nxt) and not bool(red3)


def test_within_k_changes_is_what_k_actions_reach(space, all_options):
    """`within(g, k)` against brute force: exactly the grasps that differ from g in at most k links, each once,
    ordered by how many (g first), its prefixes the smaller balls; that is every grasp k actions can reach from g
    (breadth-first over all 17 actions); `rank_within` gives each one's position."""
    assert [space.n_within(k) for k in range(8)] == [1, 11, 51, 133, 224, 276, 288, 288]
    for g in (0, 137, 287):
        differ = (all_options != all_options[g]).sum(axis=1)
        reach = {g}
        for k in range(4):
            w = np.asarray(space.within(g, k))
            assert len(w) == len(set(w.tolist())) == space.n_within(k)
            assert set(w.tolist()) == set(np.flatnonzero(differ <= k).tolist()) == reach, (g, k)
            assert np.all(np.diff(differ[w]) >= 0) and w[0] == g
            np.testing.assert_array_equal(np.asarray(space.rank_within(g, w)), np.arange(len(w)))
            nxt, _ = space.apply(np.array(sorted(reach))[:, None], np.arange(space.n_actions))
            reach = set(np.asarray(nxt).ravel().tolist())


def test_action_by_link_name(space):
    """`action(link, option)` is the action whose link and option those are, and bad names or options raise."""
    for a in range(1, space.n_actions):
        link, opt = space.link_names[space.action_link[a]], int(space.action_option[a])
        assert space.action(link, opt) == a
    assert space.action_label(grasps.NULL) == "keep"
    with pytest.raises(ValueError, match="link"):
        space.action("pinky_distal", 1)
    with pytest.raises(ValueError, match="option"):
        space.action("ring_distal", 2)


def test_label_of_default_start_grasp(space):
    g = int(scenario.make_episode().start_grasp)
    assert tuple(np.asarray(space.decode(g)).tolist()) == scenario.START_OPTIONS
    assert space.label(g) == "T1 I1 . M1 . ."


def test_labels_are_distinct_and_readable(space):
    labels = [space.label(g) for g in range(288)]
    assert len(set(labels)) == 288
    assert space.label(0) == ". . . . . ."
    assert space.label(287) == "T2 I2 Im1 M3 Mm1 R1"


def test_action_labels(space):
    labels = [space.action_label(a) for a in range(17)]
    assert len(set(labels)) == 17
    assert labels[0] == "keep" and labels[1] == "thumb_distal->off"
    assert labels[-1] == "ring_distal->1"
