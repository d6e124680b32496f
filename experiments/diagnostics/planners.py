"""`python -m experiments planners [--plugin MODULE]`: every registered planner (`gsp_jax.planners.registry`), its
group, options with their defaults, what of the evaluation context it reads, and its first docstring line."""
from __future__ import annotations

import argparse
import textwrap

from experiments.common import Run, table
from gsp_jax.planners import registry as planners


def add_arguments(p: argparse.ArgumentParser) -> None:
    pass


def main(args: argparse.Namespace, run: Run) -> None:
    rows = []
    for row in planners.describe():
        options = ", ".join(f"{k}={v!r}" for k, v in row["options"].items()) or "-"
        backends = "any" if row["backends"] == "any" else "/".join(row["backends"])
        rows.append([row["name"], row["group"], options, ", ".join(row["needs"]) or "-", backends])
    print(table(["planner", "group", "options", "reads", "physics"], rows))
    print()
    for row in planners.describe():
        print(textwrap.fill(f"{row['name']}: {row['summary']}", 110, subsequent_indent="    "))
