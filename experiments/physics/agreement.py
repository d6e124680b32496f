"""`python -m experiments physics-agree [--set eval] [--policies four-tips scripted one-tip dp-opt]`: MJX against C
MuJoCo, the same controller on the same sequences. Reads results/physics/<set>_<policy>.json (MJX) and
<set>_<policy>_c.json (C), written by `python -m experiments physics ... [--backend c]`, and prints, per policy
and over all sequences, how often the two engines agree on held/fell and how far apart their hold angles are where
both hold; writes results/physics/<set>_agreement.json."""
from __future__ import annotations

import argparse
import json

import numpy as np

from experiments.common import results_dir, table
from gsp_jax import files


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="eval")
    p.add_argument("--policies", nargs="+", default=["four-tips", "scripted", "one-tip", "dp-opt"])


def main(args: argparse.Namespace) -> None:
    out = results_dir("physics")
    rows, fell_a, fell_b, diffs = [], [], [], []
    for policy in args.policies:
        a = files.read_json(out / f"{args.set}_{policy}.json")["episodes"]
        b = files.read_json(out / f"{args.set}_{policy}_c.json")["episodes"]
        assert [r["episode"] for r in a] == [r["episode"] for r in b], policy
        fa, fb = np.array([r["fell"] for r in a]), np.array([r["fell"] for r in b])
        both = ~fa & ~fb
        d = np.abs(np.array([r["angle_error_deg"] for r in a]) - np.array([r["angle_error_deg"] for r in b]))[both]
        rows.append([policy, len(a), int(np.sum(fa & fb)), int(np.sum(both)), int(np.sum(fa != fb)),
                     100 * float(np.mean(fa == fb)), float(d.max()) if d.size else float("nan"),
                     int(np.sum(d > 2.0))])
        fell_a += list(fa)
        fell_b += list(fb)
        diffs += list(d)
    fa, fb, d = np.array(fell_a), np.array(fell_b), np.array(diffs)
    rows.append(["all", len(fa), int(np.sum(fa & fb)), int(np.sum(~fa & ~fb)), int(np.sum(fa != fb)),
                 100 * float(np.mean(fa == fb)), float(d.max()) if d.size else float("nan"), int(np.sum(d > 2.0))])
    head = ["policy", "sequences", "both fell", "both held", "disagree", "agree [%]", "max |d angle| [deg]", "> 2 deg"]
    files.write_json(out / f"{args.set}_agreement.json", [dict(zip(head, r)) for r in rows])
    print(table(head, rows, ".1f"))
