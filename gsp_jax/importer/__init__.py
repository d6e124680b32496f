"""A published MJCF hand -> a hand file that follows the model conventions (docs/your-model.md).

`import_hand(src, ...)` reads a hand file (e.g. MuJoCo Menagerie's LEAP or Shadow hand: box and mesh collision
geoms, position servos, tendons, a forearm and wrist) and edits its `mujoco.MjSpec` into a hand the project can
load, listing every change in plain words:

* the palm (the world's child with the most hinges below it, or a named body deeper in the tree) becomes the
  world's child at its pose in the file's zero configuration; what is above it (forearm, wrist joints and their
  geoms, actuators, sensors, excludes) and what else the world holds is dropped;
* every colliding geom below the palm that is not a capsule or a sphere is replaced by a fitted capsule (or
  sphere) that covers it, one per body (or one per geom), its contact attributes kept and the body's inertia pinned.
  The fit covers points whose convex hull contains the geoms (box corners, mesh vertices, polytopes around cylinders
  and ellipsoids): for each of the points' three principal directions, the axis line through the centre of the
  smallest circle around their projection, radii from that circle's (the smallest possible) up to the points'
  largest distance from their centroid, each with the shortest segment that covers every point; of those, the one
  with the least *over-cover* (the largest distance from a point of its surface to the replaced geoms: how far it
  reaches beyond them), the smallest by volume among those within `SEARCH_TOLERANCE` of it;
* every actuator that is not a plain joint torque motor becomes a `<motor>` on its joint (a tendon actuator one per
  joint of the tendon), with the actuator's force limit as its control range; every hinge gets exactly one motor;
* the hinges' damping, armature and friction loss become the values the physics controller is tuned for
  (`gsp_jax.model.hand.JOINT_DAMPING`, ...);
* a common name prefix that makes the finger names collide ("rh_") is stripped, the hand's `<option>` is dropped
  (the scene sets the physics), keyframes whose controls no longer fit are dropped.

`Imported.write(out_dir)` writes ``out_dir/hand.xml`` (its header comment: the changes, the source, what the user
must still add) and copies the mesh files it still uses to ``out_dir/assets/``. The model layer: numpy and MuJoCo
only. Lengths are in metres, angles in radians, torques in N m unless a name says otherwise.

The modules, each importing only those above it here (and `gsp_jax.model.hand`):

    fitting.py      a capsule or sphere fitted to a point set (numpy): `Fit`, `fit_round`, `min_circle`
    spec.py         MjSpec bookkeeping: delete with references, inventories, renaming, words; `HandImportError`
    geom_points.py  the points of a geom, distances to it, a fit's over-cover
    steps.py        the edits up to the new geoms: load, palm, joints, option, mesh files, inertia, geoms
    motors.py       the edits after them: motors, joint dynamics, names, keyframes, the palm's pose
    result.py       `import_hand` (the steps in order) -> `Imported`, which writes hand.xml and its assets
"""
from __future__ import annotations

from gsp_jax.importer.fitting import Fit, fit_round, min_circle, segment_distance
from gsp_jax.importer.result import Imported, import_hand
from gsp_jax.importer.spec import HandImportError
from gsp_jax.importer.steps import Replacement

__all__ = ["Fit", "HandImportError", "Imported", "Replacement", "fit_round", "import_hand", "min_circle",
           "segment_distance"]
