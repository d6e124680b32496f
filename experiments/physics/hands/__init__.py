"""`python -m experiments hands [--models M ...] [--episodes N] [--k K]`: a hands x tools table in C MuJoCo.

Each model (a hand with a tool: the shipped `wrench`, `screwdriver` and `hammer` on the paper's four-fingered hand,
the Allegro with the wrench and with the screwdriver, and any scene file given) runs its `variations` set (the
nominal lift, mass 0.5 / 1.5 / 2 m0, friction 0.5 / 1.2, the torque reversed, halved and 1.5 times) under DP
optimal, L1 and L1-physics in C MuJoCo, as `envelope --set variations --random 0 --policies dp-opt L1
--physics-lookahead K` does (each model's run is that command, nested: its results in
results/envelope-<model>[-learned]/variations.json, resumable), with the model's learned physics term where it has
one (`--paper`: none). Falls are classified by the feasibility oracle (controller: holding forces existed). A cell:
falls of N per planner, the controller's among them, and the episodes where L1-physics held while DP optimal or L1
fell.

Menagerie's published hands (`published.py`: the Shadow E3M5, the LEAP and the Sharpa Wave, each with the bar and
the screwdriver) join the table once imported: `--menagerie DIR` (a clone of mujoco_menagerie) imports each one
found under DIR into its cells under examples/published/ (not shipped); cells imported before run without it; the
others are listed with why. Prints the table last; writes results/hands[-learned]/hands.json; with --record,
docs/data/hands_<device>.json.
"""
from __future__ import annotations

import argparse
import dataclasses

import jax

from experiments.common import Run, table
from experiments.physics.hands import published
from gsp_jax.core import files
from gsp_jax.model import load as model_lib
from gsp_jax.model.hand import MODELS_DIR

MODELS = ("wrench", "screwdriver", "hammer", "allegro",  # (hand, tool) cells the library ships; and the Allegro's
          str(MODELS_DIR / "allegro-screwdriver" / "scene.xml"))  # screwdriver (a scene file, not a shipped name)
NAMED = {"wrench": ("four-fingered (ours)", "wrench bar"), "screwdriver": ("four-fingered (ours)", "screwdriver"),
         "hammer": ("four-fingered (ours)", "hammer"), "allegro": ("Allegro", "wrench bar"),
         "allegro-screwdriver": ("Allegro", "screwdriver"),
         **{f"{h}-{t}": (f"{published.HANDS[h].label} (Menagerie)", "wrench bar" if t == "bar" else t)
            for h, t in published.CELLS}}
PLANNERS = ("dp-opt", "L1", "L1-physics")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--models", nargs="+", default=None, metavar="NAME_OR_PATH",
                   help="the hand + tool scenes (default: wrench, screwdriver, hammer, allegro, "
                        "models/allegro-screwdriver and the published hands' cells imported)")
    p.add_argument("--menagerie", default=None, metavar="DIR",
                   help="a clone of github.com/google-deepmind/mujoco_menagerie: import its Shadow and LEAP into "
                        "their cells (examples/published/) first")
    p.add_argument("--episodes", type=int, default=None, help="only N of the 9 variations, spread over the set")
    p.add_argument("--k", type=int, default=2, help="L1-physics: L1's K best actions branched in physics")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    return [("hands",)]


def main(args: argparse.Namespace, run: Run) -> None:
    from experiments import cli

    if args.menagerie:
        try:
            published.install(args.menagerie)
        except published.importer.HandImportError as e:
            raise SystemExit(f"hands: {e}") from None
    ready = [(h, t) for h, t in published.CELLS if published.imported(h, t)]
    models = args.models or [*MODELS, *(str(published.cell_dir(h, t) / "scene.xml") for h, t in ready)]
    not_here = [(f"{published.HANDS[h].label} (Menagerie) x {t}", "not imported: `hands --menagerie DIR`")
                for h, t in published.CELLS if (h, t) not in ready and args.models is None] + list(published.NOT_HERE)
    cells = []
    for name in models:
        try:
            model = model_lib.load_model(name)
        except model_lib.ModelError as e:
            raise SystemExit(f"--models: {e}") from None
        words = ["envelope", "--model", str(model.path), "--set", "variations", "--random", "0", "--policies",
                 "dp-opt", "L1", "--physics-lookahead", str(args.k)]
        if args.episodes:
            words += ["--episodes", str(args.episodes)]
        print(f"hands: {model.name} ...", flush=True)
        # the model's learned term where it has one (`cli._learned`), unless --paper; only the table is recorded
        nested = cli.run_command(words, dataclasses.replace(run, record=False))
        result = files.read_json(nested.results_dir("envelope") / "variations.json")
        cells.append(_cell(model, result, term=nested.learned))
        # each hand's programs are its own (its arrays are constants of them): let go of them before the next, or a
        # dozen models' programs exhaust what LLVM may map
        jax.clear_caches()
    out = dict(cells=cells, not_here=[dict(hand=h, why=w) for h, w in not_here])
    path = run.results_dir("hands") / "hands.json"
    files.write_json(path, out)
    print(f"wrote {path}\n")
    run.record_figures("hands", dict(episodes=args.episodes or 9, k=args.k, cells=[
        {key: c[key] for key in ("model", "hand", "tool", "learned", "episodes", "physics_only", *PLANNERS)}
        for c in cells]))
    rows = [[c["hand"], c["tool"], "yes" if c["learned"] else "no",
             *[f"{c[p]['falls']}/{c['episodes']} ({c[p]['controller']})" for p in PLANNERS], c["physics_only"]]
            for c in cells]
    rows += [[h, "-", "-", "-", "-", "-", why] for h, why in not_here]
    print(table(["hand", "tool", "learned term", *[f"{p} falls (controller)" for p in PLANNERS],
                 "held by L1-physics only"], rows))


def _cell(model, result: dict, term: bool) -> dict:
    """One (hand, tool) cell of an envelope result: per planner its falls and the controller's, and the episodes
    where L1-physics held while DP optimal or L1 fell."""
    hand, tool = NAMED.get(model.name, (model.name, "its own"))
    kinds = result["summary"]["kinds"]
    fell = {}
    for row in result["sequences"]:
        fell.setdefault(row["kind"], {})[row["episode"]] = row["fell"]
    only = [e for e, f in fell.get("L1-physics", {}).items() if not f and (fell["dp-opt"][e] or fell["L1"][e])]
    return dict(model=model.name, hand=hand, tool=tool, learned=term, episodes=len(result["episodes"]),
                physics_only=len(only), physics_only_episodes=only,
                **{p: dict(falls=kinds[p]["falls"], controller=kinds[p]["controller"]) for p in PLANNERS})
