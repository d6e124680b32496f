"""Published hands for the hands x tools table: MuJoCo Menagerie's files, imported where they are on disk.

The library ships none of a published hand's files. Each `HANDS` entry is the user's part of `import-hand` for one
of Menagerie's hands (the palm's pose, the contact links, the IK start: found with `check-model --place`
and the link-reach sampling docs/your-model.md describes); each `CELLS` entry pairs a hand with a tool written for
it (examples/published/<hand>-<tool>/: the tool's options on that hand's links, and a scene that includes the
hand.xml that `install` writes beside it). `python -m experiments hands --menagerie DIR` (DIR a clone of
github.com/google-deepmind/mujoco_menagerie) imports each hand whose file is under DIR into its cells; cells
imported before run without DIR. Visual geoms are always dropped (a clone's visual meshes change nothing here).
"""
from __future__ import annotations

import dataclasses
import pathlib

from gsp_jax import importer

ROOT = pathlib.Path(__file__).resolve().parents[3] / "examples" / "published"  # the checkout's: not in the wheel


@dataclasses.dataclass(frozen=True)
class Published:
    """One published hand and the `import-hand` flags that put it over the tools (metres, radians)."""

    label: str  # the table's name for the hand
    source: str  # its file, relative to a Menagerie clone
    palm_pos: tuple[float, float, float]
    palm_quat: tuple[float, float, float, float]  # (w, x, y, z): palm face down, fingers towards +y
    contact_links: tuple[str, ...]
    start: tuple[float, ...]  # gsp_ik_start, one angle per hand joint in joint order
    palm: str | None = None  # the root body where it is not the world's child
    torque_limit: float | None = None  # [N m] for servos the file gives no force range
    drop_missing: bool = False  # collision geoms whose mesh files are absent removed (`import_hand`)


HANDS = {
    # forearm and wrist dropped (--palm rh_palm); its servos' force ranges (1-3 N m) become the motors' limits. The IK
    # start puts each tip near its first option at mid-lift: from the file's rest the thumb's IK stops 5 mm short
    # of the grip in the upper half of the lift.
    "shadow": Published(
        "Shadow E3M5", "shadow_hand/right_hand.xml", palm="rh_palm", palm_pos=(-0.01, -0.12, 0.09),
        palm_quat=(0.0, 0.0, 0.7071068, 0.7071068), contact_links=("thdistal", "ffdistal", "mfdistal", "rfdistal"),
        start=(0, 0.2, 0.9, 0.7) * 3 + (0, 0, 0.2, 0.9, 0.7) + (0.6, 1.08, -0.1, 0, 1.3)),
    # its 16 position servos have no force range: 0.9 N m (the Dynamixel XC330's stall torque as we recall it)
    "leap": Published(
        "LEAP", "leap_hand/right_hand.xml", palm_pos=(-0.037, 0.015, 0.145), palm_quat=(0.7071068, 0.0, 0.0, 0.7071068),
        contact_links=("th_ds", "if_ds", "mf_ds", "rf_ds"), torque_limit=0.9,
        start=(0.9, 0, 0.8, 0.6) * 3 + (1.2, 0.9, 0.4, 1.2)),
    # five fingers, 22 joints; the four tips of the thumb, index, middle and ring (the pinky rests). The palm and
    # start are `check-model --place`'s (the start drawn by `placement.ik_start`; from all zeros the fingers reach few
    # options at the top of the lift). The pinky metacarpal's only collision geom is a mesh (an STL file in a clone);
    # where it is absent the geom is dropped (that body, inside the palm's span, then collides with nothing).
    "sharpa": Published(
        "Sharpa Wave", "sharpa_wave/right_hand.xml", palm_pos=(0.0, -0.12, 0.11), palm_quat=(0.5, -0.5, 0.5, 0.5),
        contact_links=("thumb_DP", "index_DP", "middle_DP", "ring_DP"), drop_missing=True,
        start=(-1.06, 0.09, -0.63, 0.03, -1.56, -0.37, 0.09, -0.80, -1.11, -0.30, 0.04, -1.25, -0.41, -0.32, -0.03,
               -0.97, -0.53, 0, 0, 0, 0, 0)),
}
CELLS = (("shadow", "bar"), ("shadow", "screwdriver"), ("leap", "bar"), ("leap", "screwdriver"),
         ("sharpa", "bar"), ("sharpa", "screwdriver"))
NOT_HERE: tuple[tuple[str, str], ...] = ()


def cell_dir(hand: str, tool: str) -> pathlib.Path:
    return ROOT / f"{hand}-{tool}"


def imported(hand: str, tool: str) -> bool:
    """Whether the cell's hand.xml has been written (`install`)."""
    return (cell_dir(hand, tool) / "hand.xml").exists()


def install(menagerie: str | pathlib.Path, log=print) -> list[tuple[str, str]]:
    """Import every hand of `HANDS` whose file is under `menagerie` into each of its cells (hand.xml and the meshes
    it still uses, beside the cell's scene.xml); the cells imported, in `CELLS` order. Visual geoms are dropped (a
    clone without its visual meshes imports the same). Raises `importer.HandImportError` naming the file."""
    root = pathlib.Path(menagerie)
    if not root.is_dir():
        raise importer.HandImportError(f"--menagerie: {root} is not a folder (a clone of mujoco_menagerie)")
    done = []
    for hand, tool in CELLS:
        spec = HANDS[hand]
        src = root / spec.source
        if not src.exists():
            log(f"hands: {spec.label}: {src} not found, its cells are skipped")
            continue
        result = importer.import_hand(src, torque_limit=spec.torque_limit, palm=spec.palm, palm_pos=spec.palm_pos,
                                      palm_quat=spec.palm_quat, drop_visual=True, drop_missing=spec.drop_missing,
                                      per_geom=False,
                                      contact_links=list(spec.contact_links), start=list(spec.start))
        result.write(cell_dir(hand, tool))
        log(f"hands: imported {src} into {cell_dir(hand, tool)} ({len(result.changes)} changes)")
        done.append((hand, tool))
    return done
