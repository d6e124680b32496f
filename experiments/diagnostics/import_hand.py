"""`python -m experiments import-hand SRC OUT_DIR`: a published MJCF hand -> a hand file that follows the conventions.

Reads SRC (e.g. MuJoCo Menagerie's ``leap_hand/right_hand.xml``: box and mesh collision geoms, position servos),
writes OUT_DIR/hand.xml and copies the meshes it still uses to OUT_DIR/assets/. Every change is printed and written
into the file's header comment (`gsp_jax.importer`): the palm made the world's child (``--palm`` for one deeper
in the tree, its forearm and wrist dropped), non-round collision geoms replaced by fitted capsules or spheres (their
over-cover reported), servos replaced by torque motors (``--torque-limit`` where the file gives no force range),
the joints' damping, armature and friction loss set to the values the physics controller is tuned for. Then come
the steps left to the user: contact links, IK start, the tool and the scene, ``check-model``.
"""
from __future__ import annotations

import argparse
import pathlib
from typing import TYPE_CHECKING

import mujoco

from gsp_jax import importer

if TYPE_CHECKING:
    from experiments.common import Run


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("src", metavar="SRC", help="the hand's MJCF file")
    p.add_argument("out_dir", metavar="OUT_DIR", help="where hand.xml and assets/ are written")
    p.add_argument("--torque-limit", type=float, default=None, metavar="N_M",
                   help="the motor limit [N m] of joints whose actuators give none (a servo without forcerange, or "
                        "no actuator)")
    p.add_argument("--palm", default=None, metavar="BODY",
                   help="the hand's root body (default: the world's child with the most hinges below it); a deeper "
                        "body becomes the world's child and everything above it is dropped")
    p.add_argument("--palm-pos", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="the palm's position in the world [m]")
    p.add_argument("--palm-quat", type=float, nargs=4, default=None, metavar=("W", "X", "Y", "Z"),
                   help="the palm's orientation in the world (the palm should face down over the tool)")
    p.add_argument("--drop-visual", action="store_true",
                   help="remove the visual geoms (those that collide with nothing) and the meshes only they use")
    p.add_argument("--contact-links", nargs="+", default=None, metavar="BODY",
                   help="the contact links, in grasp order: writes gsp_contact_links and each one's site "
                   "contact_<link> (a finger's deepest link: a sphere at its geom's far end; another: a capsule along "
                   "its geom)")
    p.add_argument("--ik-start", type=float, nargs="+", default=None, metavar="RAD",
                   help="the IK's start, one angle per hand joint in joint order (gsp_ik_start)")
    p.add_argument("--drop-missing", action="store_true",
                   help="remove the collision geoms whose mesh files are missing (each reported: its body collides "
                        "with nothing there then), where the file cannot be had")
    p.add_argument("--drop-tendons", action="store_true",
                   help="remove every tendon (a tendon-driven hand's paths and springs, and the actuators that pull "
                        "them): each joint then gets a motor of its own (--torque-limit)")
    p.add_argument("--per-geom", action="store_true",
                   help="one fitted capsule per replaced geom (default: one per body, over all its geoms)")


def main(args: argparse.Namespace, run: Run) -> None:
    try:
        imported = importer.import_hand(args.src, torque_limit=args.torque_limit, palm=args.palm,
                                        palm_pos=args.palm_pos, palm_quat=args.palm_quat,
                                        drop_visual=args.drop_visual, drop_missing=args.drop_missing,
                                        drop_tendons=args.drop_tendons,
                                        per_geom=args.per_geom,
                                        contact_links=args.contact_links, start=args.ik_start)
        path = imported.write(args.out_dir)
    except importer.HandImportError as e:
        raise SystemExit(f"import-hand: {e}") from None
    print(f"{args.src}: {len(imported.changes)} change(s)")
    for line in imported.changes:
        print(f"  - {line}")
    fits = imported.replacements
    if fits:
        worst = max(fits, key=lambda r: r.over_cover)
        kinds = {k: sum(r.fit.kind == k for r in fits) for k in ("capsule", "sphere")}
        print(f"fitted: {kinds['capsule']} capsule(s), {kinds['sphere']} sphere(s); largest over-cover "
              f"{worst.over_cover * 1e3:.2f} mm (body {worst.body!r}: the largest distance from a point of the new "
              "geom's surface to the geoms it replaced)")
    try:
        mj_model = mujoco.MjModel.from_xml_path(str(path))
    except Exception as e:  # noqa: BLE001 -- MuJoCo's own message
        raise SystemExit(f"import-hand: the written {path} does not compile: {e}") from None
    print(f"wrote {path} ({mj_model.nbody - 1} bodies, {mj_model.njnt} joints, {mj_model.nu} motors, {mj_model.ngeom} "
          "geoms; MuJoCo compiles it)")
    print("next steps (docs/your-model.md):")
    for step in imported.next_steps():
        print(f"  - {step}")
    print(f"  (write scene.xml in {pathlib.Path(args.out_dir)}, beside hand.xml, so that the meshes in assets/ are "
          "found)")
