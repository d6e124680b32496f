"""`python -m experiments check-model PATH_OR_NAME`: every problem a scene file has, in plain words, in one run.

1. The conventions (`gsp_jax.model.load.check_model`: the tool, the table, the contact links and options, the hand's
   joints, motors, geoms and IK start).
2. The joint dynamics against the controller's finger gains (`physics.preflight.joint_dynamics`).
3. On a file that loads: whether it has a learned physics term, the tool's clearance above the table, the start
   grasp's reach at waypoint 0 and its collisions at the lowest and highest starts the episodes use (each body and
   its depth), the hand's own geoms passing through each other or the table in MuJoCo, and (unless `--quick`) a dry
   run of the start grasp in C MuJoCo (`preflight.clearance`, `start_reach`, `start_band`, `hand_overlaps`,
   `dry_run`).
4. With `--reach`: each contact link alone on each option at the nominal lift's first and last waypoint (the IK's
   error [mm]), the options no link reaches, and a picture of them on the tool
   (results/check-model/reach-<model>.png).
5. With `--place`: the palm's 24 axis-aligned orientations screened by forward kinematics (which turn reaches the
   most options at both ends of the lift, and the flags for it), then palm positions searched for the one that
   reaches the most options with the start clear, each with an IK start drawn for it, and the flags that put the
   palm there and start the IK so (`physics.placement.orientations`, `search`, `ik_start`).

Exits 1 and lists the problems if there is any (docs/your-model.md says what each is); otherwise prints what the
model is and exits 0. Every command's `--model` runs the conventions first (`gsp_jax.model.load.require`).
"""
from __future__ import annotations

import argparse
import pathlib
from typing import TYPE_CHECKING

import numpy as np

from gsp_jax.model import load as model_lib

if TYPE_CHECKING:
    from experiments.common import Run


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="PATH_OR_NAME",
                   help="a scene file (or a folder holding scene.xml), or a shipped name")
    p.add_argument("--quick", action="store_true", help="the conventions, the joint dynamics and the start's reach "
                   "only: no dry run in C MuJoCo")
    p.add_argument("--reach", action="store_true", help="every link on every option at the lift's first and last "
                   "waypoint, and a picture (results/check-model/reach-<model>.png)")
    p.add_argument("--place", action="store_true", help="also search palm positions (z, then x, then y) for the one "
                   "whose fingers reach the most options at both ends of the lift with the start clear, and print "
                   "the flags that put it there (minutes: each candidate compiles its own IK)")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("check-model",)] if getattr(args, "reach", False) else []


def main(args: argparse.Namespace, run: Run) -> None:
    from gsp_jax.model import hand as hand_lib, scenario
    from gsp_jax.physics import preflight

    try:
        path = model_lib.resolve(args.scene)
    except model_lib.ModelError as e:
        raise SystemExit(str(e)) from None
    conventions = model_lib.check_model(path)
    problems = list(conventions)
    try:
        mj_model = hand_lib.load_mjmodel(path)
    except Exception:  # noqa: BLE001 -- the conventions' check reported MuJoCo's message
        mj_model = None
    if mj_model is not None and model_lib.hand_joints(mj_model):
        problems += preflight.joint_dynamics(mj_model)
    if not conventions:
        from gsp_jax.surrogate.step import Surrogate

        model = model_lib.load_model(path)
        sur = Surrogate(model, learned=False)  # the checks are the analytic surrogate's (the IK, the forces)
        print(model.describe())
        print(_learned_term(model))
        problems += preflight.clearance(sur)
        runnable = True
        try:
            scenario.make_episode(model=model)
        except scenario.EpisodeError as e:  # e.g. a tool resting outside the hand's reach box: nothing else can run
            problems.append(f"the nominal lift is not an episode of this model: {e}")
            runnable = False
        else:
            print("the start grasp at waypoint 0 (IK) and at the lowest and highest starts ...", flush=True)
            problems += preflight.start_reach(sur)
            problems += preflight.start_band(sur)
            problems += preflight.hand_overlaps(sur)
        if runnable and not getattr(args, "quick", False):
            print(f"a dry run in C MuJoCo: the start grasp held for {preflight.DRY_SEGMENTS * scenario.DT:g} s of the "
                  "nominal lift ...", flush=True)
            problems += preflight.dry_run(sur).problems()
        if runnable and getattr(args, "reach", False):
            print("every link on every option at the lift's first and last waypoint (IK) ...", flush=True)
            reach = preflight.reach(sur)
            print(reach.table())
            out = _picture(model, reach, run.results_dir("check-model"))
            problems += [f"no link reaches option {k} of {link!r} at the lift's first or last waypoint (IK error "
                         f"{np.nanmin(reach.error[reach.links.index(link), k]) * 1e3:.1f} mm)"
                         for link, k in reach.unreachable()]
            print(f"wrote {out}")
    if not conventions and getattr(args, "place", False):
        _place(path)
    if problems:
        print(f"{path}: {len(problems)} problem(s) (see docs/your-model.md)")
        for p in problems:
            print(f"  - {p}")
        raise SystemExit(1)
    print("follows every convention" + ("" if getattr(args, "quick", False) else "; the start holds in C MuJoCo"))


def _place(path) -> None:
    """The palm search (`placement.search`): its candidates as a table, the best one's position as flags."""
    from experiments.common import table
    from gsp_jax.physics import placement

    print("palm orientations (placement.orientations: the 24 axis-aligned turns, forward kinematics) ...", flush=True)
    poses = placement.orientations(path)
    _, own = placement.palm_pose(path)
    mine = [p for p in poses if abs(float(np.dot(p.quat, own))) > 0.999]
    print(table(["palm quat (w x y z)", "palm at [m]", "options at both ends", ""],
                [[" ".join(f"{q:.4g}" for q in p.quat), " ".join(f"{x:.2f}" for x in p.pos), f"{p.both}/{p.options}",
                  "the file's" if p in mine else ""] for p in poses[:5]]))
    best_turn = poses[0] if poses else None
    if best_turn and (not mine or best_turn.both > mine[0].both):
        quat, pos = " ".join(f"{q:.4g}" for q in best_turn.quat), " ".join(f"{x:.3f}" for x in best_turn.pos)
        print(f"turn the palm: `import-hand SRC OUT --palm-quat {quat} --palm-pos {pos}` reaches "
              f"{best_turn.both} of {best_turn.options} options by forward kinematics (the file's orientation: "
              f"{mine[0].both if mine else 'not axis-aligned'}); import so, then run --place again to settle the "
              "position and check collisions (no position search at this turn: the problems below are the file's "
              "as it stands)")
        return
    print("palm positions (placement.search: z, then x, then y) ...", flush=True)
    found = placement.search(path)
    rows = [[f"{np.round(np.asarray(c.offset) * 1e3, 1).tolist()}", f"{c.both}/{c.options}", c.either,
             "yes" if c.clear else "no"] for c in found]
    print(table(["palm moved by [mm]", "options at both ends", "at one", "start clear"], rows))
    best = found[0]
    x, y, z = best.pos
    start = " ".join(f"{q:.2f}" for q in best.start)
    if not best.clear:
        print(f"no palm position tried has a clear start grasp; the nearest, at the file's orientation, still has: "
              f"{'; '.join(best.problems)}. Another orientation (the screen above), other options or another tool "
              "may have one; this one may have none")
    where = ("the file's palm position scores best" if best.offset == (0.0, 0.0, 0.0)
             else f"best: the palm at {x:.4f} {y:.4f} {z:.4f} m")
    print(f"{where}, with the IK starting at {start}: `import-hand SRC OUT --palm-pos {x:.4f} {y:.4f} {z:.4f} "
          f"--ik-start {start}` (or set the palm body's pos and gsp_ik_start in the file)")


def _learned_term(model) -> str:
    """Whether the commands will plan with a learned physics term for `model`, and how to make one."""
    from gsp_jax.surrogate import learned

    path = learned.path_of(model)
    if learned.has_own(model):
        return f"  learned physics term: {path} (every command plans with it; --paper: without)"
    return (f"  learned physics term: none yet ({path.name} beside the scene), so the commands plan with the paper's "
            f"surrogate, which calls plans feasible that physics drops more often. `python -m experiments calibrate "
            f"--learn --model {model.path}` makes it: a corpus of 40 x 64 episodes in C MuJoCo, then the fit "
            "(24 shards took 6.3 min on the 16-core H200 host; on 2 cores hours: `--shards 2 --episodes 16` makes a "
            "first, rougher term in about 6 min)")


def _picture(model, reach, folder: pathlib.Path) -> pathlib.Path:
    """The tool from above with each option: green reached at both waypoints, orange at one, red at neither;
    written to `folder`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hand = model.hand
    hull = hand.tool_hull().reshape(-1, 8, 3)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for box in hull:
        lo, hi = box.min(0), box.max(0)
        ax.add_patch(plt.Rectangle(lo[:2] * 1e3, *(hi - lo)[:2] * 1e3, fill=False, color="0.5"))
    for li, link in enumerate(reach.links):
        for k in range(1, hand.n_options[li]):
            ok = reach.error[li, k] <= reach.tolerance
            colour = "tab:green" if ok.all() else "tab:orange" if ok.any() else "tab:red"
            x, y = hand.option_pos[li, k, :2] * 1e3
            ax.plot(x, y, "o", color=colour)
            ax.annotate(f"{link}:{k}", (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set(xlabel="tool x [mm]", ylabel="tool y [mm]", aspect="equal",
           title=f"{model.name}: options reached by the IK at the lift's first and last waypoint\n"
                 "green both, orange one, red neither")
    ax.autoscale_view()
    out = folder / f"reach-{model.name}.png"
    fig.savefig(out, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out
