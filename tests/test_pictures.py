"""Pictures that read without the code: where each contact option touches the tool (`render.option_places`), and
text written onto frames (`render.caption`). Neither needs an OpenGL backend."""
from __future__ import annotations

import numpy as np
import pytest

from gsp_jax.model import hand as hand_lib
from gsp_jax.physics import render


def test_option_places_name_the_wrench_options_as_its_model_file_describes_them():
    """The comments of models/wrench.xml, written by hand: the thumb on the -y faces of the handle and the head,
    the other fingers on +y faces, middle distal's third option under the handle; x of each site in mm."""
    places = render.option_places(hand_lib.load_mjmodel())
    assert places == {
        "thumb_distal": ("handle -y side, x -20 mm", "head -y side, x +65 mm"),
        "index_distal": ("handle +y side, x +30 mm", "head +y side, x +70 mm"),
        "index_medial": ("handle +y side, x +35 mm",),
        "middle_distal": ("handle +y side, x +0 mm", "handle +y side, x -30 mm", "handle underside, x +0 mm"),
        "middle_medial": ("handle +y side, x +0 mm",),
        "ring_distal": ("handle +y side, x -50 mm",),
    }


def test_option_places_cover_every_option_of_every_shipped_model():
    """One name per option (the grasp space's counts less "not in contact") for each shipped model, the physics
    scene (contacts by explicit pairs) naming the same places as the model file."""
    from gsp_jax.model import load as model_lib
    from gsp_jax import physics

    for scene in ("scene.xml", "hammer/scene.xml", "allegro/scene.xml"):
        model = hand_lib.load_mjmodel(hand_lib.MODELS_DIR / scene)
        hand = model_lib.load_hand(hand_lib.MODELS_DIR / scene)
        places = render.option_places(model)
        assert [len(places[link]) for link in hand.link_names] == [n - 1 for n in hand.n_options], scene
    sur_model = physics.Physics().model
    assert render.option_places(sur_model) == render.option_places(hand_lib.load_mjmodel())


def test_caption_writes_on_a_band_at_the_top_and_leaves_the_rest():
    frames = np.full((3, 120, 160, 3), 200, np.uint8)
    out = render.caption(frames, ["t = 0.00 s", "t = 0.04 s\ngrasp: T1 I1 . M1 . R1", ""], size=12)
    assert out.shape == frames.shape and out.dtype == np.uint8
    assert np.array_equal(frames, np.full_like(frames, 200))  # the input is kept
    assert np.array_equal(out[:, 60:], frames[:, 60:])  # below the band: untouched
    assert (out[:, :10] < 200).any(axis=(1, 2, 3)).all()  # the band darkens the top of every frame
    assert (out[1, :40] == 255).any() and (out[0, :20] == 255).any()  # white text on the frames that have it
    assert (out[1, 16:32] == 255).any() and not (out[0, 16:32] == 255).any()  # a second line only where given
    with pytest.raises(ValueError, match=r"texts: one per frame \(3\), got 2"):
        render.caption(frames, ["a", "b"])


def test_demo_captions_name_the_time_and_the_grasp_being_executed():
    """A GIF frame at time t shows the grasp after the decision at the last waypoint before t (waypoints every
    0.25 s, `scenario.DT`), the change that segment makes named by where it goes on the tool, the hold from 4 s
    (16 waypoints) and a fall from its time on."""
    import types

    from experiments import demo
    from gsp_jax import physics
    from gsp_jax.model import scenario
    from gsp_jax.surrogate.step import Surrogate

    sur = Surrogate(learned=False)
    phys, space, T = physics.Physics(sur), sur.space, scenario.N_WAYPOINTS
    start = space.encode(space.start_options)
    to_under = space.action("middle_distal", 3)
    later = space.apply(start, to_under)[0]
    grasps = np.array([int(start)] * 9 + [int(later)] * (T - 9))
    actions = np.zeros(T, np.int32)
    actions[9] = to_under
    r = types.SimpleNamespace(grasps=grasps[None], actions=actions[None], fell=np.array([True]),
                              fall_time=np.array([4.5]))
    ctx = types.SimpleNamespace(surrogate=sur, batch=types.SimpleNamespace(n_steps=T))
    tick = scenario.DT / phys.n_segment
    every = round(0.05 / tick)  # a frame every 0.05 s: frame i at (i * every + 1) ticks
    captions = demo._captions(phys, ctx, r, every)
    assert len(captions) == phys.n_ticks(T) // every
    at = lambda seconds: captions[round(seconds / 0.05)].split("\n")  # noqa: E731
    assert at(2.20) == ["t = 2.20 s   waypoint 8 of 16", f"grasp: {space.label(int(start))}"]
    assert at(2.30) == ["t = 2.30 s   waypoint 9 of 16", f"grasp: {space.label(int(later))}",
                        "middle_distal -> handle underside, x +0 mm"]
    assert at(2.55)[1:] == [f"grasp: {space.label(int(later))}"]  # the next segment keeps it: no change named
    assert at(4.20) == ["t = 4.20 s   hold: torque on", f"grasp: {space.label(int(later))}"]
    assert at(4.60)[-1] == "FELL at 4.50 s"
