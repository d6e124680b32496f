"""`python -m experiments demo [--episode NAME]`: the library's main job on one unseen episode, end to end.

    an unseen episode (default: the first evaluation episode, which no planner was trained or calibrated on)
      -> its DP table (every grasp x waypoint realised by IK and priced by the wrench solve)
      -> two plans: DP optimal (exact Bellman backup) and L1 (the paper's online lookahead over the PPO policy);
         `--planners` any registered ones (e.g. `search`, the beam search)
      -> both executed closed loop by the contact controller in C MuJoCo
      -> a table (plan, surrogate return, held or fell, angle error under the final torque, planning time),
         a picture (each plan's grasp timeline above the physics angle trace) and, where an OpenGL backend is
         set (MUJOCO_GL=egl|osmesa), a GIF of the L1 plan in physics.

Writes results/demo/ (demo.json, demo.png, demo_L1.gif); prints the table last. CPU by default (`make demo`).
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.common import RESULTS, Run, table
from gsp_jax.planning import dp, evaluation
from gsp_jax.core import files
from gsp_jax import physics
from gsp_jax.planners import registry as planners
from gsp_jax.model import scenario
from gsp_jax.model.grasps import NULL
from gsp_jax.physics import c_backend
from gsp_jax.surrogate.step import Surrogate

PLANNERS = ("dp-opt", "L1")
LABEL = {"dp-opt": "DP optimal", "L1": "L1 lookahead"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episode", default=None, help="an episode name from any set (default: the first of 'eval', "
                   "shift-6mm: the lift 6 mm lower, the torque +1 N m or the model's)")
    p.add_argument("--planners", nargs="+", default=list(PLANNERS), metavar="NAME",
                   help="the registered planners to plan and run (default: dp-opt L1; e.g. search, the beam search)")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF even where OpenGL is available")
    p.add_argument("--gif-from", default=None, help=argparse.SUPPRESS)  # (internal) render a saved trace, then stop


def _context(name: str | None, sur: Surrogate) -> evaluation.Context:
    """The evaluation context of one episode of the surrogate's model (`--model`; its table built here, timed by
    the caller). L1 looks ahead over the model's PPO policy where there is one, else over the DP baseline (the
    nominal episode's optimal sequence)."""
    if name is None:
        name, episode = next(iter(scenario.episode_set("evalA", sur.model).items()))  # the first of 'eval'
    else:
        episode = scenario.find(name, sur.model)
    batch = scenario.stack([episode])
    tables = jax.block_until_ready(jax.jit(lambda b: dp.build_tables(sur, b))(batch))
    solutions = jax.jit(jax.vmap(dp.backup))(tables, batch.start_grasp)
    try:
        rl, source, base = *evaluation.load_rl(sur, results=RESULTS), None
    except FileNotFoundError:
        rl, base = None, evaluation.nominal_actions(sur, RESULTS / evaluation.TABLES)
        source = f"none for model {sur.model.name!r}: L1 looks ahead over the DP baseline"
    return evaluation.Context(sur, "demo", [name], batch, tables, solutions, base, rl, source)


def infeasible(ctx: evaluation.Context, i: int = 0) -> str | None:
    """Why no sequence holds episode i in the surrogate (`Surrogate.explain` of the sequence that holds longest,
    `dp.longest_surviving`), None if one does."""
    sur = ctx.surrogate
    if float(ctx.solutions.ret[i]) > sur.reward_config.r_min:
        return None
    episode, table = (jax.tree.map(lambda x: x[i], tree) for tree in (ctx.batch, ctx.tables))
    longest = dp.longest_surviving(table, episode.start_grasp, sur.reward_config.r_min)
    return sur.explain(episode, np.asarray(longest.actions))


def _timeline(phys: physics.Physics, n_steps: int) -> tuple[float, float, int]:
    """(control tick [s], segment [s], ticks in the episode) of an episode of n_steps waypoints in `phys`."""
    segment = phys.hold_time(n_steps) / n_steps
    return segment / phys.n_segment, segment, phys.n_ticks(n_steps)


def _runs(row: np.ndarray) -> list[tuple[int, int, int]]:
    """(first, length, value) of each run of equal values in a 1-D array."""
    cuts = np.flatnonzero(np.diff(row)) + 1
    starts = np.concatenate([[0], cuts])
    lengths = np.diff(np.concatenate([starts, [row.size]]))
    return [(int(s), int(n), int(row[s])) for s, n in zip(starts, lengths)]


def _picture(phys: physics.Physics, ctx, grasps: dict, res: dict, path) -> None:
    """Each plan's grasp timeline above both angle traces, on one time axis [s]. A timeline has a row per contact
    link and a bar per run of one contact option, named by where it touches the tool (`render.option_places`; the
    option's number where the name does not fit, every option listed at the right); blank: the link is not
    touching the tool. Segment k starts at waypoint k (its decision, k x segment seconds) and executes the grasp
    after decision k; the hold keeps the last grasp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from gsp_jax.physics import render

    space, links = ctx.surrogate.space, ctx.surrogate.hand.link_names
    places = render.option_places(phys.model)
    T = ctx.batch.n_steps
    tick, segment, n_ticks = _timeline(phys, T)
    end, hold = n_ticks * tick, phys.hold_time(T)
    colours = plt.get_cmap("Set2").colors
    fig, axes = plt.subplots(len(grasps) + 1, 1, figsize=(12.5, 0.32 * len(links) * len(grasps) + 4.2), sharex=True,
                             gridspec_kw=dict(height_ratios=[0.32 * len(links)] * len(grasps) + [2.6]))
    bars = []  # (axes, start [s], width [s], its name, its number)
    for ax, (name, g) in zip(axes, grasps.items()):
        opts = np.stack([np.asarray(space.decode(int(x))) for x in g], 1)  # (L, T) option after each decision
        opts = np.concatenate([opts, np.repeat(opts[:, -1:], phys.n_hold, 1)], 1)  # the hold keeps the last
        r = res[name]
        stop = float(r.fall_time[0]) if bool(r.fell[0]) else end  # the bars end where the tool fell
        for i, row in enumerate(opts):
            for first, n, o in _runs(row):
                if not o:
                    continue
                x0, w = first * segment, min(n * segment, stop - first * segment)
                if w <= 0:
                    continue
                ax.broken_barh([(x0, w)], (i - 0.4, 0.8), facecolors=colours[(o - 1) % len(colours)],
                               edgecolors="0.3", lw=0.5)
                bars.append((ax, x0, w, ax.text(x0 + w / 2, i, places[links[i]][o - 1], ha="center", va="center",
                                                fontsize=6.5), str(o)))
        if stop < end:
            ax.axvspan(stop, end, color="0.85", hatch="//", zorder=3)
            ax.text((stop + end) / 2, (len(links) - 1) / 2, f"fell at {stop:.2f} s", ha="center", va="center",
                    zorder=4, bbox=dict(facecolor="w", edgecolor="none"))
        ax.set_ylim(len(links) - 0.5, -0.5)
        ax.set_yticks(range(len(links)), links, fontsize=7)
        right = ax.twinx()
        right.set_ylim(ax.get_ylim())
        right.set_yticks(range(len(links)), ["   ".join(f"{k + 1}: {p}" for k, p in enumerate(places[link]))
                                             for link in links], fontsize=6)
        ax.text(1.005, 1.02, "each link's options (number: where it touches the tool)", transform=ax.transAxes,
                fontsize=7, va="bottom")
        for x in np.arange(T + 1) * segment:
            ax.axvline(x, color="0.85", lw=0.5, zorder=0)
        ax.axvline(hold, color="k", ls="--", lw=0.8)
        ax.set_title(f"{LABEL.get(name, name)}: where each link touches the tool after each decision", fontsize=9,
                     loc="left")
        ax.tick_params(labelbottom=True, labelsize=7)
    fig.legend(handles=[Patch(facecolor="w", edgecolor="0.6", label="blank: the link is not touching the tool")],
               loc="upper left", fontsize=8, frameon=False)
    waypoints = axes[0].secondary_xaxis("top")
    waypoints.set_xticks(np.arange(T) * segment, [str(k) if k % 2 == 0 else "" for k in range(T)], fontsize=6)
    waypoints.set_xlabel("waypoint (a decision at each)", fontsize=7)
    ax = axes[-1]
    for name, r in res.items():
        a = np.asarray(r.angle[0]).copy()
        if bool(r.fell[0]):
            a[int(round(float(r.fall_time[0]) / tick)) :] = np.nan
        ax.plot((np.arange(a.size) + 1) * tick, a, lw=1.2, label=LABEL.get(name, name))
    ax.axvline(hold, color="k", ls="--", lw=0.8)
    ax.text(hold, ax.get_ylim()[1] * 0.95, " hold: torque on", fontsize=8, va="top")
    for x in np.arange(T + 1) * segment:
        ax.axvline(x, color="0.9", lw=0.5, zorder=0)
    ax.set_xlim(0, end)
    ax.set_xticks(np.arange(0, end + 1e-9, 0.5))
    ax.set_xlabel("time [s] (grey lines: the waypoints, a decision at each; traces end where the tool fell)")
    ax.set_ylabel("tool angle error [deg]")
    ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(f"{ctx.names[0]} in C MuJoCo", fontsize=10)
    fig.tight_layout()
    renderer = fig.canvas.get_renderer()
    for ax, x0, w, text, number in bars:  # a name wider than its bar (measured once laid out): the number
        left, right = ax.transData.transform([(x0, 0), (x0 + w, 0)])[:, 0]
        if text.get_window_extent(renderer).width > 0.95 * (right - left):
            text.set_text(number)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _captions(phys: physics.Physics, ctx, r, every: int) -> list[str]:
    """The text of each GIF frame (every `every`-th control tick of result `r`, one episode): the simulated time,
    the waypoint, the grasp being executed (`GraspSpace.label`) and, in a segment that changes it, the change named
    by where the link goes on the tool; the hold and a fall named as they come."""
    from gsp_jax.physics import render

    space, places = ctx.surrogate.space, render.option_places(phys.model)
    T = ctx.batch.n_steps
    tick, _, n_ticks = _timeline(phys, T)
    grasps, actions = np.asarray(r.grasps[0]), np.asarray(r.actions[0])
    fell, fall_time = bool(r.fell[0]), float(r.fall_time[0])
    out = []
    for j in range(0, n_ticks, every):
        t = (j + 1) * tick
        k = min(j // phys.n_segment, T - 1)
        head = f"t = {t:.2f} s   " + (f"waypoint {k} of {T}" if t <= phys.hold_time(T) else "hold: torque on")
        lines = [head, f"grasp: {space.label(int(grasps[k]))}"]
        a = int(actions[k])
        if a != NULL and t <= phys.hold_time(T):
            link, option = space.link_names[space.action_link[a]], int(space.action_option[a])
            lines.append(f"{link} -> {places[link][option - 1] if option else 'off the tool'}")
        if fell and t >= fall_time:
            lines.append(f"FELL at {fall_time:.2f} s")
        out.append("\n".join(lines))
    return out


def _gif(phys: physics.Physics, ctx, r, stem):
    """Key frame PNG and GIF of one episode's result `r`, each frame captioned (`_captions`), drawn in a child
    process with MUJOCO_GL=egl unless the environment names a backend (it must be set before mujoco is imported,
    and where libEGL is missing the import fails: the child's failure then only skips the GIF). The child starts
    now; the function returned waits for it and gives the files written (none where it failed)."""
    import os
    import subprocess
    import sys

    from gsp_jax.physics import render

    tick = _timeline(phys, ctx.batch.n_steps)[0]
    every = max(1, int(round(1 / (render.GIF_FPS * tick))))
    trace = f"{stem}_qpos.npy"
    np.save(trace, np.asarray(r.qpos[0])[::every])
    files.write_json(f"{stem}_captions.json", _captions(phys, ctx, r, every))
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    child = subprocess.Popen([sys.executable, "-m", "experiments", "demo", "--gif-from", trace, "--model",
                              str(ctx.surrogate.model.path)], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)

    def done() -> list[str]:
        _, err = child.communicate()
        if child.returncode != 0:
            print(f"  GIF skipped (no OpenGL backend for MuJoCo? set MUJOCO_GL=egl or osmesa): "
                  f"{err.strip().splitlines()[-1:] or child.returncode}")
            return []
        return [f"{stem}_keyframe.png", f"{stem}.gif"]

    return done


def _render_gif(phys: physics.Physics, trace: str) -> None:
    """(The child of `_gif`) the GIF of a saved trace `<stem>_qpos.npy` (a frame each) with its captions
    `<stem>_captions.json`, and its last frame large as `<stem>_keyframe.png`."""
    from gsp_jax.physics import render

    stem = trace.removesuffix("_qpos.npy")
    qpos = np.load(trace)
    texts = files.read_json(f"{stem}_captions.json")
    render.save_png(f"{stem}_keyframe.png", render.caption(render.frames(phys.model, qpos[-1:], size=(480, 640)),
                                                           texts[-1:], size=18)[0])
    render.save_gif(f"{stem}.gif", render.caption(render.frames(phys.model, qpos), texts), fps=render.GIF_FPS)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [] if args.gif_from else [("demo",)]  # the GIF child renders for its parent


def main(args: argparse.Namespace, run: Run) -> None:
    if args.gif_from:
        _render_gif(physics.Physics(Surrogate(run.model, learned=run.learned), run.physics_config()), args.gif_from)
        return
    common.check_planners(args.planners, "--planners", "c")
    model = run.model
    out = run.results_dir("demo")  # results/demo-<model> for another model
    print(f"demo on JAX {jax.default_backend()}: one unseen episode of model {model.name!r}, planned by "
          f"{', '.join(LABEL.get(n, n) for n in args.planners)}, executed in C MuJoCo", flush=True)
    t0 = time.perf_counter()
    sur = Surrogate(model, learned=run.learned)
    phys = physics.Physics(sur, run.physics_config())
    native_code = c_backend.warm_up(phys)  # numba compiles C MuJoCo's native tick while XLA compiles the table
    ctx = _context(args.episode, sur)
    t_table = time.perf_counter() - t0
    print(f"  episode {ctx.names[0]}: DP table of {ctx.surrogate.space.n_grasps} grasps x {ctx.batch.n_steps} "
          f"waypoints built in {t_table:.1f} s (includes compiling)", flush=True)
    why = infeasible(ctx)
    if why:
        print(f"  no grasp sequence holds this episode in the surrogate: {why}", flush=True)
    plans, wall = {}, {}
    for name in args.planners:
        t1 = time.perf_counter()
        # the plan's episode stepped in its table
        plans[name] = float(planners.returns(ctx, name, "table", cached=True)[0])
        wall[name] = time.perf_counter() - t1
        print(f"  {LABEL.get(name, name)} planned in {wall[name]:.1f} s after the table (includes compiling)",
              flush=True)
    groups = [planners.make(ctx, name) for name in args.planners]
    t2 = time.perf_counter()
    native_code.result()  # compiled by now, or waited for here (counted in the physics' time)
    res = dict(zip(args.planners, phys.simulate_many(groups, ctx.batch, backend="c")))
    t_phys = time.perf_counter() - t2
    print(f"  physics: {len(args.planners)} closed-loop episodes in {t_phys:.1f} s (includes compiling)", flush=True)
    space = ctx.surrogate.space
    grasps = {n: [int(x) for x in np.asarray(r.grasps[0])] for n, r in res.items()}
    shown = args.planners[-1]  # the GIF's: the last planner's episode (L1 by default)
    gif = None if args.no_gif else _gif(phys, ctx, res[shown], out / f"demo_{shown}")  # drawn beside the picture
    _picture(phys, ctx, grasps, res, out / "demo.png")
    written = [str(out / "demo.png")] + ([] if gif is None else gif())
    rows, record = [], {}
    for name in args.planners:
        r = res[name]
        acts = jnp.asarray(r.actions[0])
        ret = float(dp.sequence_return(jax.tree.map(lambda x: x[0], ctx.tables), ctx.batch.start_grasp[0], acts))
        changes = [f"t{t}:{space.action_label(int(a))}" for t, a in enumerate(np.asarray(acts)) if a != NULL]
        fell = bool(r.fell[0])
        record[name] = dict(planned_return=plans[name], executed_actions=np.asarray(acts).tolist(),
                            surrogate_return=ret, executed_grasps=grasps[name],
                            fell=fell, fall_time_s=float(r.fall_time[0]), angle_error_deg=float(r.angle_error[0]),
                            plan_s=t_table + wall[name])
        rows.append([LABEL.get(name, name), " ".join(changes) or "keep", ret, "fell" if fell else "held",
                     float(r.angle_error[0]), t_table + wall[name]])
    files.write_json(out / "demo.json", dict(model=model.name, model_digest=model.digest, infeasible=why,
                                                   episode=ctx.names[0], platform=jax.default_backend(),
                                                   rl_policy=ctx.rl_source, table_s=t_table, physics_s=t_phys,
                                                   planners=record, files=written))
    print(f"wrote {', '.join(written + [str(out / 'demo.json')])}\n")
    print(f"{ctx.names[0]}: the grasp changes executed in C MuJoCo (closed loop: each decision on the simulated "
          "state), their return in the surrogate, the outcome")
    print(table(["planner", "changes", "return", "physics", "angle error [deg]", "plan time incl. compile [s]"], rows,
                ".2f"))
