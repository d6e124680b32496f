"""`python -m experiments hands [--models M ...] [--episodes N] [--k K] [--policies ...]`: a hands x tools table.

Each model (a hand with a tool: the shipped `wrench`, `screwdriver` and `hammer` on the paper's four-fingered hand,
the Allegro with the wrench and with the screwdriver, and any scene file given) runs its `variations` set (the
nominal lift, mass 0.5 / 1.5 / 2 m0, friction 0.5 / 1.2, the torque reversed, halved and 1.5 times) under DP
optimal, L1 and L1-physics in C MuJoCo, as `envelope --set variations --random 0 --policies dp-opt L1
--physics-lookahead K` does (each model's run is that command, nested: its results in
results/envelope-<model>[-learned]/variations.json, resumable), with the model's learned physics term where it has
one (`--paper`: none). Falls are classified by the feasibility oracle (controller: holding forces existed). A cell:
falls of N per planner, the controller's among them, and the episodes where L1-physics held while DP optimal or L1
fell.

Menagerie's published hands (`HANDS` below: the Shadow E3M5, the LEAP and the Sharpa Wave, each with the bar and
the screwdriver) join the table once imported: `--menagerie DIR` (a clone of mujoco_menagerie) imports each one
found under DIR into its cells under examples/published/ (not shipped); cells imported before run without it; the
others are listed with why. Prints the table last; writes results/hands[-learned]/hands.json; with --record,
docs/data/hands_<device>.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import pathlib

import jax

from experiments.common import Run, table
from gsp_jax import importer
from gsp_jax.core import files
from gsp_jax.model import load as model_lib
from gsp_jax.model.hand import MODELS_DIR

# ---------------------------------------------------------------------------- Menagerie's published hands
# Published hands for the hands x tools table: MuJoCo Menagerie's files, imported where they are on disk.
#
# The library ships none of a published hand's files. Each `HANDS` entry is the user's part of `import-hand` for one
# of Menagerie's hands (the palm's pose, the contact links, the IK start: found with `check-model --place`
# and the link-reach sampling docs/your-model.md describes); each `CELLS` entry pairs a hand with a tool written for
# it (examples/published/<hand>-<tool>/: the tool's options on that hand's links, and a scene that includes the
# hand.xml that `install` writes beside it). `python -m experiments hands --menagerie DIR` (DIR a clone of
# github.com/google-deepmind/mujoco_menagerie) imports each hand whose file is under DIR into its cells; cells
# imported before run without DIR. Visual geoms are always dropped (a clone's visual meshes change nothing here).

ROOT = pathlib.Path(__file__).resolve().parents[2] / "examples" / "published"  # the checkout's: not in the wheel


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
    for hand, spec in HANDS.items():
        src = root / spec.source
        if not src.exists():
            log(f"hands: {spec.label}: {src} not found, its cells are skipped")
            continue
        result = importer.import_hand(src, torque_limit=spec.torque_limit, palm=spec.palm, palm_pos=spec.palm_pos,
                                      palm_quat=spec.palm_quat, drop_visual=True, drop_missing=spec.drop_missing,
                                      contact_links=list(spec.contact_links), start=list(spec.start))
        for tool in (t for h, t in CELLS if h == hand):  # one import, written into each of the hand's cells
            result.write(cell_dir(hand, tool))
            log(f"hands: imported {src} into {cell_dir(hand, tool)} ({len(result.changes)} changes)")
            done.append((hand, tool))
    return [c for c in CELLS if c in done]


MODELS = ("wrench", "screwdriver", "hammer", "allegro",  # (hand, tool) cells the library ships; and the Allegro's
          str(MODELS_DIR / "allegro-screwdriver" / "scene.xml"))  # screwdriver (a scene file, not a shipped name)
NAMED = {"wrench": ("four-fingered (ours)", "wrench bar"), "screwdriver": ("four-fingered (ours)", "screwdriver"),
         "hammer": ("four-fingered (ours)", "hammer"), "allegro": ("Allegro", "wrench bar"),
         "allegro-screwdriver": ("Allegro", "screwdriver"),
         **{f"{h}-{t}": (f"{HANDS[h].label} (Menagerie)", "wrench bar" if t == "bar" else t)
            for h, t in CELLS}}
PLANNERS = ("dp-opt", "L1")  # the default planners, with L1-physics where --k > 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", default=None, metavar="NAME_OR_PATH",
                   help="the hand + tool scenes (default: wrench, screwdriver, hammer, allegro, "
                        "models/allegro-screwdriver and the published hands' cells imported)")
    p.add_argument("--menagerie", default=None, metavar="DIR",
                   help="a clone of github.com/google-deepmind/mujoco_menagerie: import its Shadow, LEAP and Sharpa "
                        "Wave into their cells (examples/published/) first")
    p.add_argument("--episodes", type=int, default=None, help="only N of the 9 variations, spread over the set")
    p.add_argument("--k", type=int, default=2,
                   help="L1-physics: L1's K best actions branched in physics (0: no L1-physics column)")
    p.add_argument("--policies", nargs="+", default=list(PLANNERS), metavar="NAME",
                   help="the registered planners of each cell besides L1-physics (default: dp-opt L1; e.g. search "
                        "with --k 0 on a grasp space too large for a DP table)")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    return [("hands",)]


def main(args: argparse.Namespace, run: Run) -> None:
    from experiments import cli, common

    common.check_planners(args.policies, "--policies", "c")
    if args.k < 0 or "L1-physics" in args.policies:
        raise SystemExit(f"hands: --k >= 0 gives the L1-physics column (got --k {args.k}, --policies "
                         f"{' '.join(args.policies)})")
    planners = [*args.policies, *(["L1-physics"] if args.k else [])]

    if args.menagerie:
        try:
            install(args.menagerie)
        except importer.HandImportError as e:
            raise SystemExit(f"hands: {e}") from None
    ready = [(h, t) for h, t in CELLS if imported(h, t)]
    models = args.models or [*MODELS, *(str(cell_dir(h, t) / "scene.xml") for h, t in ready)]
    not_here = [(f"{HANDS[h].label} (Menagerie) x {t}", "not imported: `hands --menagerie DIR`")
                for h, t in CELLS if (h, t) not in ready and args.models is None]
    cells = []
    for name in models:
        try:
            model = model_lib.load_model(name)
        except model_lib.ModelError as e:
            raise SystemExit(f"--models: {e}") from None
        words = ["envelope", "--model", str(model.path), "--set", "variations", "--random", "0", "--policies",
                 *args.policies, "--physics-lookahead", str(args.k)]
        if args.episodes:
            words += ["--episodes", str(args.episodes)]
        print(f"hands: {model.name} ...", flush=True)
        # the model's learned term where it has one (`cli._learned`), unless --paper; only the table is recorded
        nested = cli.run_command(words, dataclasses.replace(run, record=False))
        result = files.read_json(nested.results_dir("envelope") / "variations.json")
        cells.append(_cell(model, result, term=nested.learned, planners=planners))
        # each hand's programs are its own (its arrays are constants of them): let go of them before the next, or a
        # dozen models' programs exhaust what LLVM may map
        jax.clear_caches()
    out = dict(cells=cells, not_here=[dict(hand=h, why=w) for h, w in not_here])
    path = run.results_dir("hands") / "hands.json"
    files.write_json(path, out)
    print(f"wrote {path}\n")
    run.record_figures("hands", dict(episodes=args.episodes or 9, k=args.k, cells=[
        {key: c[key] for key in ("model", "hand", "tool", "learned", "episodes", "physics_only", *planners)}
        for c in cells]))
    rows = [[c["hand"], c["tool"], "yes" if c["learned"] else "no",
             *[f"{c[p]['falls']}/{c['episodes']} ({c[p]['controller']})" for p in planners], c["physics_only"]]
            for c in cells]
    rows += [[h, "-", "-", *["-"] * (len(planners) + 1), why] for h, why in not_here]
    print(table(["hand", "tool", "learned term", *[f"{p} falls (controller)" for p in planners],
                 "held by L1-physics only"], rows))


def _cell(model, result: dict, term: bool, planners=(*PLANNERS, "L1-physics")) -> dict:
    """One (hand, tool) cell of an envelope result: per planner its falls and the controller's, and the episodes
    where L1-physics held while another of `planners` fell (none without L1-physics)."""
    hand, tool = NAMED.get(model.name, (model.name, "its own"))
    kinds = result["summary"]["kinds"]
    fell = {}
    for row in result["sequences"]:
        fell.setdefault(row["kind"], {})[row["episode"]] = row["fell"]
    others = [p for p in planners if p != "L1-physics"]
    only = [e for e, f in fell.get("L1-physics", {}).items() if not f and any(fell[p][e] for p in others)]
    return dict(model=model.name, hand=hand, tool=tool, learned=term, episodes=len(result["episodes"]),
                physics_only=len(only), physics_only_episodes=only,
                **{p: dict(falls=kinds[p]["falls"], controller=kinds[p]["controller"]) for p in planners})
