"""`python -m experiments physics --set evalA|evalB|eval|all
--policy dp-opt|dp-base|rl|random|four-tips|scripted|one-tip [--backend mjx|c]`: grasp sequences executed by the
contact controller in MuJoCo (MJX, one batch, or C MuJoCo), all episodes together. At every waypoint the policy acts
on the simulated state; `rl` reads all of it (closed loop), `dp-opt` reads the grasp and waypoint; the others are
fixed sequences (open loop):

  four-tips  add the ring tip at waypoint 0 (T1 I1 . M1 . R1), then keep the grasp;
  scripted   three sequences on every episode: (i) `add-slide` adds the ring tip at waypoint 2, slides the middle
             tip M1 -> M2 at 6 and back at 10; `add-slide-ring0` the same with the ring tip added at 0 (the three-tip
             start grasp cannot hold the tool: it needs friction mu > 0.8, the episodes' mu, printed per sequence as
             its hardest grasp's least mu); (ii) `alternate` adds the ring tip at 0, then changes at every
             waypoint, sliding the middle tip between M2 and M1 (two four-contact grasps);
  one-tip    removes the middle tip at 0 and the thumb at 1: the index tip alone (must drop the tool).

Prints each episode's tool angle error under the final torque (180 when the tool fell or touched the table),
position error, largest tilt during the lift and fall time, and the mean with a 95% interval; writes
results/physics/<set>_<policy>[_c].json (`summary.falls`, `summary.mean_angle_error_deg`, per sequence for
`scripted`), the traces, an angle-trace PNG and (with --render) a key frame PNG and a GIF.

`--compare NAME ...` simulates nothing: it sets the saved MJX and C MuJoCo runs of those policies on --set side by
side (held/fell agreement, hold angles) and writes results/physics/<set>_agreement.json."""
from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import RESULTS, Run, check_planners, table
from gsp_jax.core import distributed, files
from gsp_jax.planning import evaluation, policies
from gsp_jax import physics
from gsp_jax.planners import registry as planners
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate
from gsp_jax.physics import report
from gsp_jax.physics import world as world_lib



def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="evalA", choices=["nominal", "train", "val", "evalA", "evalB", "eval", "all"])
    p.add_argument("--policy", default="dp-opt", metavar="NAME",
                   help="a registered planner (`python -m experiments planners`), or scripted (three fixed sequences)")
    p.add_argument("--policy-dir", default=None,
                   help="saved PPO policy for --policy rl (default: results/train/dp/seed0, else the shipped one)")
    p.add_argument("--episodes", type=int, default=None, help="only the first N episodes of the set")
    p.add_argument("--seed", type=int, default=0, help="for --policy random")
    p.add_argument("--backend", default="mjx", choices=physics.BACKENDS,
                   help="mjx: one XLA batch (GPU); c: C MuJoCo, the engine's reference implementation (CPU)")
    p.add_argument("--chunk", type=int, default=None, metavar="N",
                   help="C MuJoCo: the episodes in fixed chunks of N, one batch each, shared by several processes "
                        "(--processes; default: one chunk per process); the outcomes depend on the chunks, not on "
                        "the process count")
    p.add_argument("--render", action="store_true",
                   help="key frame PNG + GIF of one episode (--render-episode); needs MUJOCO_GL=egl|osmesa set")
    p.add_argument("--render-episode", default=None, help="which episode to render (a name in the printed table; "
                   "default the first); the key frame is the last frame before a fall, else the end of the hold")
    p.add_argument("--render-window", type=float, nargs=2, default=None, metavar=("FROM", "TO"),
                   help="render only this time window [s] into the GIF")
    p.add_argument("--compare", nargs="+", default=None, metavar="NAME",
                   help="no simulation: MJX against C MuJoCo on these policies' saved runs of --set (`physics --policy "
                        "NAME` with --backend mjx and with --backend c): held/fell agreement and hold angles")


def make_policy(kind: str, set_name: str, episodes: dict, args: argparse.Namespace, run: Run):
    """(policy, policy_axis) of registered planner `kind` for a batch of named `episodes` of `run`'s model, from a
    context with only what it reads (`planners.context_flags`)."""
    ctx = evaluation.context(set_name, episodes=episodes, policy_dir=getattr(args, "policy_dir", None), results=RESULTS,
                             model=run.model, learned=run.learned, **planners.context_flags([kind]))
    return planners.make(ctx, kind, dict(seed=getattr(args, "seed", 0)))


def compare(out: pathlib.Path, set_name: str, names) -> None:
    """MJX against C MuJoCo, the same controller on the same sequences: from `out` (results/physics)/<set>_<policy>.json
    (MJX) and <set>_<policy>_c.json (C), per policy and over all, how often the two engines agree on held/fell and
    how far apart their hold angles are [deg] where both hold; writes `out`/<set>_agreement.json."""
    rows, fell_a, fell_b, diffs = [], [], [], []
    for policy in names:
        missing = [p.name for p in (out / f"{set_name}_{policy}.json", out / f"{set_name}_{policy}_c.json")
                   if not p.exists()]
        if missing:
            raise SystemExit(f"--compare {policy}: no {', '.join(missing)} in {out} (run `physics --set {set_name} "
                             f"--policy {policy}` with --backend mjx and with --backend c first)")
        a = files.read_json(out / f"{set_name}_{policy}.json")["episodes"]
        b = files.read_json(out / f"{set_name}_{policy}_c.json")["episodes"]
        if [r["episode"] for r in a] != [r["episode"] for r in b]:
            raise SystemExit(f"--compare {policy}: the MJX and C runs are of different episodes (rerun both)")
        fa, fb = np.array([r["fell"] for r in a]), np.array([r["fell"] for r in b])
        both = ~fa & ~fb
        d = np.abs(np.array([r["angle_error_deg"] for r in a]) - np.array([r["angle_error_deg"] for r in b]))[both]
        rows.append([policy, *_agreement(fa, fb, d)])
        fell_a += list(fa)
        fell_b += list(fb)
        diffs += list(d)
    rows.append(["all", *_agreement(np.array(fell_a), np.array(fell_b), np.array(diffs))])
    head = ["policy", "sequences", "both fell", "both held", "disagree", "agree [%]", "max |d angle| [deg]", "> 2 deg"]
    files.write_json(out / f"{set_name}_agreement.json", [dict(zip(head, r)) for r in rows])
    print(table(head, rows, ".1f"))


def _agreement(fa, fb, d) -> list:
    return [len(fa), int(np.sum(fa & fb)), int(np.sum(~fa & ~fb)), int(np.sum(fa != fb)),
            100 * float(np.mean(fa == fb)), float(d.max()) if d.size else float("nan"), int(np.sum(d > 2.0))]


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("physics",)]  # --compare reads it


def main(args: argparse.Namespace, run: Run) -> None:
    if args.compare:
        return compare(run.results_dir("physics"), args.set, args.compare)
    if args.episodes is not None and args.episodes < 1:
        raise SystemExit(f"--episodes: {args.episodes} (must be >= 1)")
    if args.policy != "scripted":
        check_planners([args.policy], "--policy", args.backend)
    env = surrogate.Surrogate(run.model, learned=run.learned)
    episodes = scenario.episode_set(args.set, env.model)
    if args.episodes:
        episodes = dict(list(episodes.items())[: args.episodes])
    names = list(episodes)
    known = [f"{k}/{n}" for k in evaluation.scripted_sequences(env.space) for n in names] \
        if args.policy == "scripted" else names
    if args.render_episode is not None and args.render_episode not in known:  # before any work, not after it
        raise SystemExit(f"--render-episode: {args.render_episode!r} is not one of {', '.join(known)}")
    if args.backend != "c" and distributed.count() > 1:
        raise SystemExit(f"physics: --backend {args.backend} runs as one process (one XLA batch); only C MuJoCo's "
                         f"chunks are shared by --processes")
    phys = physics.Physics(env, run.physics_config())
    # each episode's world (None: nominal), one per episode name: every sequence on it meets the same world
    worlds = run.worlds(scenario.stack([episodes[n] for n in names]), env.hand)
    if args.policy == "scripted":  # every sequence on every episode, one batch
        seqs = evaluation.scripted_sequences(env.space)
        labels = [f"{k}/{n}" for k in seqs for n in names]
        each = np.repeat(np.stack(list(seqs.values())), len(names), 0)  # (labels, T): each label's sequence

        def made(idx):
            sub = [episodes[names[i % len(names)]] for i in idx]
            return policies.SequencePolicy(jnp.asarray(each[idx])), 0, scenario.stack(sub)
    else:
        labels = names

        def made(idx):
            sub = {names[i]: episodes[names[i]] for i in idx}
            return *make_policy(args.policy, args.set, sub, args, run), scenario.stack(list(sub.values()))
    try:
        chunk = distributed.chunk_size(len(labels), args.chunk)
    except ValueError as e:
        raise SystemExit(f"physics: {e}") from None
    print(f"physics check: {len(labels)} episodes of '{args.set}', policy {args.policy}, backend {args.backend}, "
          f"{phys.n_ticks(scenario.N_WAYPOINTS)} physics steps each "
          f"({jax.local_devices()[0].platform}; compiling first) ...", flush=True)
    t0 = time.perf_counter()

    def simulate(idx):
        policy, axis, batch = made(idx)
        world = world_lib.rows(worlds, np.asarray(idx) % len(names))
        return jax.device_get(phys.simulate_batch(policy, batch, axis, backend=args.backend, progress=True,
                                                  world=world))

    res = distributed.map_chunks(simulate, len(labels), chunk, what="episodes")
    wall = time.perf_counter() - t0
    if not distributed.is_main():
        return
    rows = report.result_rows(labels, res)
    out = run.results_dir("physics")
    stem = out / (f"{args.set}_{args.policy}" + ("" if args.backend == "mjx" else f"_{args.backend}"))
    summary = dict(set=args.set, policy=args.policy, backend=args.backend, device=jax.local_devices()[0].device_kind,
                   **report.summary(labels, res), wall_s_incl_compile=wall, chunk=chunk, processes=distributed.count(),
                   config=dataclasses.asdict(phys.config), timestep_s=phys.timestep, world=run.world_name,
                   **({} if worlds is None else dict(world_seed=run.world_seed, worlds=dict(
                       zip(names, world_lib.as_rows(worlds))))))
    if args.policy == "scripted":
        summary["sequences"] = {}
        for i, k in enumerate(seqs):
            part = jax.tree.map(lambda x: x[i * len(names) : (i + 1) * len(names)], res)
            # the grasps the sequence holds the tool with (after each decision; the start grasp has the pedestals'
            # help), and the friction the hardest of them needs on any episode: where that exceeds the episodes'
            # mu, no controller can hold the tool
            held = {(int(g), n) for i_n, n in enumerate(names) for g in np.asarray(part.grasps[i_n])}
            by_com = {(g, tuple(np.asarray(episodes[n].com).tolist())): episodes[n] for g, n in held}  # mass scales out
            # the hardest, by its bracket
            need = max(report.least_friction(env, g, ep) for (g, _), ep in by_com.items())
            summary["sequences"][k] = dict(actions=[int(a) for a in seqs[k]], least_friction_needed=need,
                                           episode_friction=sorted({float(e.friction) for e in episodes.values()}),
                                           **report.summary(names, part))
    files.write_json(stem.with_suffix(".json"), dict(summary=summary, episodes=rows))
    files.savez(f"{stem}_trace.npz", compressed=True, angle=np.asarray(res.angle), qpos=np.asarray(res.qpos),
                names=labels)
    report.angle_png(phys, labels, res, f"{stem}_angle.png", f"{args.policy} on {args.set} ({args.backend})")
    written = [stem.with_suffix(".json"), f"{stem}_trace.npz", f"{stem}_angle.png"]
    if args.render:
        i = labels.index(args.render_episode) if args.render_episode else 0
        key = int(round(float(res.fall_time[i]) / phys.timestep)) - 2 if bool(res.fell[i]) else -1
        written += report.render_episode(phys, np.asarray(res.qpos[i]), f"{stem}_{labels[i].replace('/', '_')}",
                                args.render_window, key)
    print(table(["episode", "angle err [deg]", "pos err [mm]", "max lift tilt", "fell at [s]"],
                [[r["episode"], r["angle_error_deg"], r["position_error_mm"], r["max_lift_angle_deg"],
                  f"{r['fall_time_s']:.2f}" if r["fell"] else "-"] for r in rows], ".1f"))
    for k, part in summary.get("sequences", {"": summary}).items():
        print(f"\n{args.policy}{' ' + k if k else ''} on {args.set}: {part['falls']}/{part['episodes']} fell; "
              f"mean angle error {part['mean_angle_error_deg']:.1f} deg (95% CI +-{part['ci95_deg']:.1f}); "
              f"where held: hold angle {part['mean_hold_angle_deg_where_held']} deg, "
              f"largest lift tilt {part['max_lift_tilt_deg_where_held']} deg"
              + ("; its hardest grasp needs mu > {:.4f} (bracket {:.4f}-{:.4f}; episodes: {})".format(
                  part["least_friction_needed"][0], *part["least_friction_needed"], part["episode_friction"])
                 if "least_friction_needed" in part else ""))
    print(f"{wall:.1f} s including compile\nwrote " + ", ".join(map(str, written)))
