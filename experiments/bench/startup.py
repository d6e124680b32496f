"""`python -m experiments bench-startup`: the README's Quickstart as a new user meets it, from a fresh process.

Each row is a new Python process that imports the library, builds `Surrogate()`, loads the shipped PPO policy, builds
L1 over it (`gsp.Lookahead(policy, sur, depth=1)`) and takes one decision, `gsp.decide(l1, sur.reset(ep))`, on
an unseen episode; then one decision on another episode, the warm decision (the fastest of three more on that
episode's start) and one DP table (`jax.jit(dp.solve)`). The processes run one after another, side by side in one
run: with the compilation cache off, with an empty cache folder, and with the cache that the previous process left
on disk (`gsp_jax.core.cache`). Times are wall-clock seconds from the process's start (the interpreter's own start
excluded). Writes results/bench/startup_<platform>.json; prints the table last.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from typing import TYPE_CHECKING

from gsp_jax.core import files

if TYPE_CHECKING:
    from experiments.common import Run

T0 = time.perf_counter()
CHILD_FLAG = "--child"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episode", type=int, default=0, help="index of the first episode in the evaluation set")
    p.add_argument("--other", type=int, default=5, help="index of the second episode in the evaluation set")
    p.add_argument("--no-off", action="store_true", help="skip the process with the cache off")
    p.add_argument("--out", default=None)


def child(first: int, other: int) -> dict:
    """The Quickstart in this process; seconds since the module was imported (`T0`)."""
    import jax

    import gsp_jax as gsp
    from gsp_jax.planning import dp

    out = dict(import_s=time.perf_counter() - T0)
    sur = gsp.Surrogate()
    episodes = list(gsp.episode_set("eval").values())
    l1 = gsp.Lookahead(gsp.load_network_policy(sur), sur, depth=1)

    def act(state):
        return gsp.decide(l1, state)
    int(act(sur.reset(episodes[first])))
    out["first_decision_s"] = time.perf_counter() - T0
    t = time.perf_counter()
    state = sur.reset(episodes[other])
    int(act(state))
    out["next_decision_s"] = time.perf_counter() - t
    warm = []
    for _ in range(3):
        t = time.perf_counter()
        int(act(state))
        warm.append(time.perf_counter() - t)
    out["warm_decision_s"] = min(warm)
    t = time.perf_counter()
    jax.block_until_ready(jax.jit(lambda e: dp.solve(sur, e))(episodes[first]))
    out["first_dp_table_s"] = time.perf_counter() - t
    out["platform"] = jax.local_devices()[0].platform
    out["device"] = jax.local_devices()[0].device_kind
    return out


def run_child(cache: str, args) -> dict:
    env = dict(os.environ, GSP_JAX_CACHE=cache)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    cmd = [sys.executable, "-m", "experiments.bench.startup", CHILD_FLAG, str(args.episode), str(args.other)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"bench-startup: the child process failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.out else [("bench",)]


def main(args: argparse.Namespace, run: Run) -> None:
    from experiments import common

    rows = {}
    with tempfile.TemporaryDirectory(prefix="gsp_jax_startup_") as folder:
        plan = ([] if args.no_off else [("cache off", "off")]) + [("empty cache", folder), ("cache on disk", folder)]
        for name, cache in plan:
            print(f"{name}: a fresh process ...", flush=True)
            rows[name] = run_child(cache, args)
            print(f"  {rows[name]}", flush=True)
    first = next(iter(rows.values()))
    result = dict(platform=first["platform"], device=first["device"], rows=rows)
    out = args.out or str(run.results_dir("bench") / f"startup_{first['platform']}.json")
    files.write_json(out, result)
    print(f"wrote {out}\n")
    run.record_figures("bench_startup", result)
    print(f"the Quickstart from a fresh process, {first['device']} ({first['platform']}), seconds")
    print(common.table(
        ["process", "import", "first L1 decision", "next decision (another episode)", "warm decision",
         "first DP table"],
        [[name, r["import_s"], r["first_decision_s"], r["next_decision_s"], r["warm_decision_s"],
          r["first_dp_table_s"]] for name, r in rows.items()], floatfmt=".2f"))


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == CHILD_FLAG:
    print(json.dumps(child(int(sys.argv[2]), int(sys.argv[3]))))
