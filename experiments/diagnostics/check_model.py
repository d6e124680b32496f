"""`python -m experiments check-model PATH_OR_NAME`: every model convention a scene file breaks, in plain words.

Exits 1 and lists them if there is any (docs/your-model.md says what each convention is); otherwise prints what
the model is (links, options, grasps, actions, tool) and exits 0. Every command's `--model` runs the same check
first (`gsp_jax.model.check_model`).
"""
from __future__ import annotations

import argparse

from gsp_jax import model as model_lib


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="PATH_OR_NAME", help="a scene file (or a folder holding scene.xml), or a shipped name")


def main(args: argparse.Namespace) -> None:
    try:
        path = model_lib.resolve(args.scene)
    except model_lib.ModelError as e:
        raise SystemExit(str(e)) from None
    problems = model_lib.check_model(path)
    if problems:
        print(f"{path}: {len(problems)} problem(s) (see docs/your-model.md)")
        for p in problems:
            print(f"  - {p}")
        raise SystemExit(1)
    print(model_lib.load_model(path).describe())
    print("follows every convention")
