"""`python -m experiments demo [--episode NAME]`: the library's main job on one unseen episode, end to end.

    an unseen episode (default: the first evaluation episode, which no planner was trained or calibrated on)
      -> its DP table (every grasp x waypoint realised by IK and priced by the wrench solve)
      -> two plans: DP optimal (exact Bellman backup) and L1 (the paper's online lookahead over the PPO policy)
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

from experiments.common import results_dir, table
from experiments.paper import fig4a
from gsp_jax import dp, evaluation, files, physics, planners, scenario
from gsp_jax.grasps import NULL
from gsp_jax.surrogate import Surrogate

PLANNERS = ("dp-opt", "L1")
LABEL = {"dp-opt": "DP optimal", "L1": "L1 lookahead"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episode", default=None, help="an episode name from any set (default: the first of 'eval', "
                   "shift-6mm: the lift 6 mm lower, the torque +1 N m or the model's)")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF even where OpenGL is available")
    p.add_argument("--gif-from", default=None, help=argparse.SUPPRESS)  # (internal) render a saved trace, then stop


def _context(name: str | None) -> evaluation.Context:
    """The evaluation context of one episode of the model (`--model`; its table built here, timed by the caller).
    L1 looks ahead over the model's PPO policy where there is one, else over the DP baseline (the nominal
    episode's optimal sequence)."""
    sur = Surrogate()
    if name is None:
        name, episode = next(iter(scenario.episode_set("evalA", sur.model).items()))  # the first of 'eval'
    else:
        from experiments.diagnostics.surrogate import find_episode

        episode = find_episode(name)
    batch = scenario.stack([episode])
    tables = jax.block_until_ready(jax.jit(lambda b: dp.build_tables(sur, b))(batch))
    solutions = jax.jit(jax.vmap(dp.backup))(tables, batch.start_grasp)
    try:
        rl, source, base = *evaluation.load_rl(sur), None
    except FileNotFoundError:
        rl, base = None, evaluation.nominal_actions(sur)
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


def _picture(phys: physics.Physics, ctx, grasps: dict, res: dict, path) -> None:
    """Each plan's grasp timeline (links x waypoints, coloured by option) above both angle traces."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    space, links = ctx.surrogate.space, ctx.surrogate.hand.link_names
    fig, axes = plt.subplots(len(grasps) + 1, 1, figsize=(8, 2.0 * len(grasps) + 3),
                             gridspec_kw=dict(height_ratios=[1] * len(grasps) + [1.6]))
    for ax, (name, g) in zip(axes, grasps.items()):
        opts = np.stack([np.asarray(space.decode(int(x))) for x in g], 1)  # (L, T)
        ax.imshow(np.where(opts > 0, opts, np.nan), aspect="auto", cmap="viridis", vmin=1, vmax=max(3, opts.max()),
                  interpolation="nearest")
        for (i, t), o in np.ndenumerate(opts):
            if o:
                ax.text(t, i, str(o), ha="center", va="center", fontsize=6, color="w")
        ax.set_yticks(range(len(links)), links, fontsize=7)
        ax.set_title(f"{LABEL[name]}: contact option of each link after each decision", fontsize=9)
        ax.set_xticks([])
    ax = axes[-1]
    tick = phys.timestep
    for name, r in res.items():
        a = np.asarray(r.angle[0]).copy()
        if bool(r.fell[0]):
            a[int(round(float(r.fall_time[0]) / tick)) :] = np.nan
        ax.plot((np.arange(a.size) + 1) * tick, a, lw=1.2, label=LABEL[name])
    hold = phys.hold_time(ctx.batch.n_steps)
    ax.axvline(hold, color="k", ls="--", lw=0.8)
    ax.text(hold, ax.get_ylim()[1] * 0.95, " torque on", fontsize=8, va="top")
    ax.set_xlabel("time [s] (a decision every segment; lines end where the tool fell)")
    ax.set_ylabel("tool angle error [deg]")
    ax.legend(fontsize=8)
    fig.suptitle(f"{ctx.names[0]} in C MuJoCo", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _gif(qpos: np.ndarray, stem) -> list[str]:
    """Key frame PNG and GIF of a trace (K, nq), drawn in a child process with MUJOCO_GL=egl unless the environment
    names a backend (it must be set before mujoco is imported, and where libEGL is missing the import fails: the
    child's failure then only skips the GIF)."""
    import os
    import subprocess
    import sys

    trace = f"{stem}_qpos.npy"
    np.save(trace, qpos)
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    from gsp_jax import model as model_lib

    run = subprocess.run([sys.executable, "-m", "experiments", "demo", "--gif-from", trace, "--model",
                          str(model_lib.load_model().path)], env=env, capture_output=True, text=True)
    if run.returncode != 0:
        print(f"  GIF skipped (no OpenGL backend for MuJoCo? set MUJOCO_GL=egl or osmesa): "
              f"{run.stderr.strip().splitlines()[-1:] or run.returncode}")
        return []
    return [f"{stem}_keyframe.png", f"{stem}.gif"]


def main(args: argparse.Namespace) -> None:
    if args.gif_from:
        from experiments.physics.check import render_episode

        stem = args.gif_from.removesuffix("_qpos.npy")
        if not render_episode(physics.Physics(Surrogate()), np.load(args.gif_from), stem):
            raise SystemExit(1)
        return
    from gsp_jax import model as model_lib

    model = model_lib.load_model()
    out = results_dir("demo")  # results/demo-<model> for another model
    print(f"demo on JAX {jax.default_backend()}: one unseen episode of model {model.name!r}, planned by DP optimal and "
          "L1, executed in C MuJoCo", flush=True)
    t0 = time.perf_counter()
    ctx = _context(args.episode)
    t_table = time.perf_counter() - t0
    print(f"  episode {ctx.names[0]}: DP table of {ctx.surrogate.space.n_grasps} grasps x {ctx.batch.n_steps} "
          f"waypoints built in {t_table:.1f} s (includes compiling)", flush=True)
    why = infeasible(ctx)
    if why:
        print(f"  no grasp sequence holds this episode in the surrogate: {why}", flush=True)
    plans, wall = {}, {}
    for name in PLANNERS:
        t1 = time.perf_counter()
        plans[name] = float(fig4a.returns(ctx, name, "table")[0])  # the plan's episode stepped in its table
        wall[name] = time.perf_counter() - t1
        print(f"  {LABEL[name]} planned in {wall[name]:.1f} s after the table (includes compiling)", flush=True)
    phys = physics.Physics(ctx.surrogate)
    groups = [planners.make(ctx, name) for name in PLANNERS]
    t2 = time.perf_counter()
    res = dict(zip(PLANNERS, phys.simulate_many(groups, ctx.batch, backend="c")))
    t_phys = time.perf_counter() - t2
    print(f"  physics: {len(PLANNERS)} closed-loop episodes in {t_phys:.1f} s (includes compiling)", flush=True)
    space = ctx.surrogate.space
    grasps = {n: [int(x) for x in np.asarray(r.grasps[0])] for n, r in res.items()}
    _picture(phys, ctx, grasps, res, out / "demo.png")
    written = [str(out / "demo.png")]
    if not args.no_gif:
        written += _gif(np.asarray(res["L1"].qpos[0]), out / "demo_L1")
    rows, record = [], {}
    for name in PLANNERS:
        r = res[name]
        acts = jnp.asarray(r.actions[0])
        ret = float(dp.sequence_return(jax.tree.map(lambda x: x[0], ctx.tables), ctx.batch.start_grasp[0], acts))
        changes = [f"t{t}:{space.action_label(int(a))}" for t, a in enumerate(np.asarray(acts)) if a != NULL]
        fell = bool(r.fell[0])
        record[name] = dict(planned_return=plans[name], executed_actions=np.asarray(acts).tolist(),
                            surrogate_return=ret, executed_grasps=grasps[name],
                            fell=fell, fall_time_s=float(r.fall_time[0]), angle_error_deg=float(r.angle_error[0]),
                            plan_s=t_table + wall[name])
        rows.append([LABEL[name], " ".join(changes) or "keep", ret, "fell" if fell else "held",
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
