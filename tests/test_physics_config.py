"""`PhysicsConfig`: its fields nested by concern (at most 30 in all, every name one group's), errors that name the
field and its value, and what is not a setting: the physics step and the table's friction come from the scene
file, explicit joint damping is always on."""
from __future__ import annotations

import dataclasses
import os
import shutil

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from gsp_jax.model import hand as hand_lib, load as model_lib  # noqa: E402
from gsp_jax import physics  # noqa: E402
from gsp_jax.physics import config as config_lib  # noqa: E402


def _leaves(cls) -> list[str]:
    """Field names of a dataclass counted through its nested dataclasses."""
    out = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else None
        out += _leaves(type(default)) if dataclasses.is_dataclass(default) else [f.name]
    return out


def test_at_most_35_fields_each_name_in_one_group():
    """A small config (30 until the contact frames, `frames`, made the measured controller a setting, 31 until the
    predictive hold, `predictive`, 32 until the robust controller's `pose_filter` and `strength_rate`, 34 until its
    `radius_from`); each field name in one group."""
    names = _leaves(physics.PhysicsConfig)
    assert len(names) <= 35, names
    assert len(set(names)) == len(names), sorted(n for n in names if names.count(n) > 1)
    assert sorted(names) == sorted(config_lib.GROUP_OF)


def test_replace_by_name_changes_that_field_only():
    base = physics.PhysicsConfig()
    new = base.replace(hold=0.5, free_stiffness=2.0)
    assert new.timeline.hold == 0.5 and new.fingers.free_stiffness == 2.0
    assert new.timeline == dataclasses.replace(base.timeline, hold=0.5)
    assert new.fingers == dataclasses.replace(base.fingers, free_stiffness=2.0)
    assert (new.sim, new.controller, new.outcome) == (base.sim, base.controller, base.outcome)
    assert new.value("hold") == 0.5 and base.value("hold") == 1.0
    with pytest.raises(ValueError, match="PhysicsConfig has no field 'slide'"):
        base.replace(slide="contact")


@pytest.mark.parametrize("field, value, message", [
    ("tool_freq", -1, r"PhysicsConfig\.controller\.tool_freq must be > 0, got -1"),
    ("hold", 0.0, r"PhysicsConfig\.timeline\.hold must be > 0, got 0\.0"),
    ("feedback_floor", 0.0, r"PhysicsConfig\.controller\.feedback_floor must be > 0, got 0\.0"),
    ("free_stiffness", 0.0, r"PhysicsConfig\.fingers\.free_stiffness must be > 0, got 0\.0"),
    ("rotation_step", 0.0, r"PhysicsConfig\.controller\.rotation_step must be > 0, got 0\.0"),
    ("radius_from", "extents",
     r"PhysicsConfig\.controller\.radius_from must be one of \('extent', 'gyration'\), got 'extents'"),
    ("solver_iterations", 0, r"PhysicsConfig\.sim\.solver_iterations must be an int >= 1, got 0"),
    ("noslip_iterations", 2.5, r"PhysicsConfig\.sim\.noslip_iterations must be an int >= 0, got 2\.5"),
    ("finger_kd", -3.0, r"PhysicsConfig\.fingers\.finger_kd must be >= 0, got -3\.0"),
    ("fall_height", float("nan"), r"PhysicsConfig\.outcome\.fall_height must be finite, got nan"),
    ("friction_margin", 1.5, r"PhysicsConfig\.controller\.friction_margin must be in \(0, 1\], got 1\.5"),
    ("move", 0.3, r"PhysicsConfig\.timeline: unload \+ move \+ load must be <= a segment"),
])
def test_bad_settings_name_the_field_and_value(field, value, message):
    with pytest.raises(ValueError, match=message):
        physics.PhysicsConfig().replace(**{field: value})


def test_a_group_of_the_wrong_type_is_named():
    with pytest.raises(ValueError, match="PhysicsConfig.timeline must be a TimelineConfig"):
        physics.PhysicsConfig(timeline=physics.SimConfig())


def _scene_copy(tmp_path, timestep: str, table_friction: str):
    """The shipped wrench scene copied with another physics step and table friction; its `HandModel`."""
    for name in ("hand.xml", "wrench.xml"):
        shutil.copy(hand_lib.MODELS_DIR / name, tmp_path / name)
    text = (hand_lib.MODELS_DIR / "scene.xml").read_text()
    assert text.count('timestep="0.002"') == 1 and text.count('friction="0.6 0.01 0.001"') == 1
    text = text.replace('timestep="0.002"', f'timestep="{timestep}"')
    (tmp_path / "scene.xml").write_text(text.replace('friction="0.6 0.01 0.001"', f'friction="{table_friction}"'))
    return model_lib.load_hand(tmp_path / "scene.xml")


def _table_pairs(m: mujoco.MjModel) -> np.ndarray:
    table = hand_lib.table_geom(m)
    pairs = [p for p in range(m.npair) if table in (m.pair_geom1[p], m.pair_geom2[p])]
    assert pairs
    return m.pair_friction[pairs]


def test_the_physics_step_and_table_friction_are_the_scene_files(tmp_path):
    """The physics model keeps the scene file's `<option timestep>`, and every contact pair with the table takes the
    table geom's sliding friction (read back from MuJoCo's own compile of the file); the scene's control tick is that
    step (`Scene.timestep`). The solver settings are `config.sim`'s and the joints' damping is explicit
    (`mjDSBL_EULERDAMP`)."""
    shipped = physics.physics_model(model_lib.load_hand())
    file = mujoco.MjModel.from_xml_path(str(hand_lib.SCENE_XML))
    assert shipped.opt.timestep == file.opt.timestep
    np.testing.assert_array_equal(_table_pairs(shipped)[:, :2], file.geom_friction[hand_lib.table_geom(file), 0])

    hand = _scene_copy(tmp_path, "0.001", "0.9 0.01 0.001")
    config = physics.PhysicsConfig().replace(solver_iterations=7, noslip_iterations=3)
    scene = physics.Scene(hand, config)
    m = scene.model
    assert m.opt.timestep == 0.001 and scene.timestep == 0.001
    np.testing.assert_array_equal(_table_pairs(m)[:, :2], 0.9)
    assert (m.opt.iterations, m.opt.ls_iterations, m.opt.noslip_iterations) == (7, config.sim.ls_iterations, 3)
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_EULERDAMP
