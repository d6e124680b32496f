"""`python -m experiments physics --set evalA|evalB|eval|all --policy dp-opt|dp-base|rl|random|four-tips|scripted|one-tip
[--backend mjx|c]`: grasp sequences executed by the contact controller in MuJoCo (MJX, one batch, or C MuJoCo), all
episodes together. At every waypoint the policy acts on the simulated state; `rl` reads all of it (closed loop),
`dp-opt` reads the grasp and waypoint; the others are fixed sequences (open loop):

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
`scripted`), the traces, an angle-trace PNG and (with --render) a key frame PNG and a GIF."""
from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import check_planners, results_dir, table
from gsp_jax import evaluation, files, physics, planners, policies, scenario, surrogate, wrench
from gsp_jax.stats import mean_ci



def least_friction(env: surrogate.Surrogate, grasp: int, episode: scenario.Episode) -> tuple[float, float]:
    """The least friction coefficient at which `grasp`'s nominal contacts can hold `episode`'s tool at rest (its
    weight about its CoM), however hard they press: `wrench.least_friction`'s bracket (lower, upper)."""
    opts = np.asarray(env.space.decode(grasp))
    links = np.flatnonzero(opts)
    h = env.hand
    weight = -float(episode.mass) * np.asarray(h.gravity, float)
    return wrench.least_friction(h.option_pos[links, opts[links]], h.option_normal[links, opts[links]],
                                 np.concatenate([weight, np.zeros(3)]), np.asarray(episode.com))


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
    p.add_argument("--render", action="store_true",
                   help="key frame PNG + GIF of one episode (--render-episode); needs MUJOCO_GL=egl|osmesa set")
    p.add_argument("--render-episode", default=None, help="which episode to render (a name in the printed table; "
                   "default the first); the key frame is the last frame before a fall, else the end of the hold")
    p.add_argument("--render-window", type=float, nargs=2, default=None, metavar=("FROM", "TO"),
                   help="render only this time window [s] into the GIF")


def make_policy(kind: str, set_name: str, episodes: dict, args=None):
    """(policy, policy_axis) of registered planner `kind` for a batch of named `episodes`, from a context with only
    what it reads (`planners.context_flags`)."""
    ctx = evaluation.context(set_name, episodes=episodes, policy_dir=getattr(args, "policy_dir", None),
                             **planners.context_flags([kind]))
    return planners.make(ctx, kind, dict(seed=getattr(args, "seed", 0)))


def result_rows(names, res: physics.Result) -> list[dict]:
    return [
        dict(episode=n, angle_error_deg=float(res.angle_error[i]), position_error_mm=1e3 * float(res.position_error[i]),
             max_lift_angle_deg=float(res.max_angle[i]), fell=bool(res.fell[i]), fall_time_s=float(res.fall_time[i]),
             grasps=[int(g) for g in res.grasps[i]])
        for i, n in enumerate(names)
    ]


def trace_png(phys: physics.Physics, names, res: physics.Result, path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    angle = np.asarray(res.angle)
    t = (np.arange(angle.shape[1]) + 1) * phys.timestep
    fig, ax = plt.subplots(figsize=(8, 4))
    for i, n in enumerate(names):
        a = angle[i].copy()
        if res.fell[i]:
            a[int(round(float(res.fall_time[i]) / phys.timestep)) :] = np.nan
        ax.plot(t, a, lw=1, label=n if len(names) <= 10 else None)
    ax.axvline(phys.hold_time(scenario.N_WAYPOINTS), color="k", ls="--", lw=0.8)
    ax.text(phys.hold_time(scenario.N_WAYPOINTS), ax.get_ylim()[1] * 0.95, " torque on", fontsize=8, va="top")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("tool angle error [deg]")
    ax.set_title(title + " (lines end where the tool fell)")
    if len(names) <= 10:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def render_episode(phys: physics.Physics, qpos: np.ndarray, stem, window=None, key: int = -1) -> list:
    """Key frame (frame `key`) PNG and a GIF at 25 frames per simulated second (of the time `window`, default all);
    [] if no GL backend."""
    try:
        from gsp_jax import render
    except Exception as e:  # noqa: BLE001 - rendering is optional
        print(f"rendering skipped: {e}")
        return []
    try:
        every = max(1, int(round(0.04 / phys.timestep)))
        png = render.save_png(f"{stem}_keyframe.png", render.frames(phys.model, qpos[key][None], size=(480, 640))[0])
        lo, hi = (0, len(qpos)) if window is None else (int(window[0] / phys.timestep), int(window[1] / phys.timestep))
        gif = render.save_gif(f"{stem}.gif", render.frames(phys.model, qpos[lo:hi], every=every), fps=25)
        return [png, gif]
    except Exception as e:  # noqa: BLE001
        print(f"rendering skipped ({type(e).__name__}: {e}); set MUJOCO_GL=egl or osmesa")
        return []


def _summary(names, res, **extra) -> dict:
    mean, ci = mean_ci(res.angle_error)
    held = ~np.asarray(res.fell)
    return dict(episodes=len(names), falls=int(np.sum(res.fell)), mean_angle_error_deg=mean, ci95_deg=ci,
                mean_hold_angle_deg_where_held=float(np.mean(np.asarray(res.angle_error)[held])) if held.any() else None,
                max_lift_tilt_deg_where_held=float(np.max(np.asarray(res.max_angle)[held])) if held.any() else None,
                **extra)


def main(args: argparse.Namespace) -> None:
    if args.episodes is not None and args.episodes < 1:
        raise SystemExit(f"--episodes: {args.episodes} (must be >= 1)")
    if args.policy != "scripted":
        check_planners([args.policy], "--policy", args.backend)
    env = surrogate.Surrogate()
    episodes = scenario.episode_set(args.set)
    if args.episodes:
        episodes = dict(list(episodes.items())[: args.episodes])
    names = list(episodes)
    known = [f"{k}/{n}" for k in evaluation.scripted_sequences(env.space) for n in names] \
        if args.policy == "scripted" else names
    if args.render_episode is not None and args.render_episode not in known:  # before any work, not after it
        raise SystemExit(f"--render-episode: {args.render_episode!r} is not one of {', '.join(known)}")
    phys = physics.Physics(env)
    if args.policy == "scripted":  # every sequence on every episode, one batch
        seqs = evaluation.scripted_sequences(env.space)
        labels = [f"{k}/{n}" for k in seqs for n in names]
        batch = scenario.stack([episodes[n] for _ in seqs for n in names])
        policy, axis = policies.SequencePolicy(jnp.asarray(np.repeat(np.stack(list(seqs.values())), len(names), 0))), 0
    else:
        labels = names
        policy, axis = make_policy(args.policy, args.set, episodes, args)
        batch = scenario.stack(list(episodes.values()))
    print(f"physics check: {len(labels)} episodes of '{args.set}', policy {args.policy}, backend {args.backend}, "
          f"{phys.n_ticks(scenario.N_WAYPOINTS)} physics steps each "
          f"({jax.devices()[0].platform}; compiling first) ...", flush=True)
    t0 = time.perf_counter()
    res = jax.block_until_ready(phys.simulate_batch(policy, batch, axis, backend=args.backend, progress=True))
    wall = time.perf_counter() - t0
    rows = result_rows(labels, res)
    out = results_dir("physics")
    stem = out / (f"{args.set}_{args.policy}" + ("" if args.backend == "mjx" else f"_{args.backend}"))
    summary = dict(set=args.set, policy=args.policy, backend=args.backend, device=jax.devices()[0].device_kind,
                   **_summary(labels, res), wall_s_incl_compile=wall, config=dataclasses.asdict(phys.config),
                   timestep_s=phys.timestep)
    if args.policy == "scripted":
        summary["sequences"] = {}
        for i, k in enumerate(seqs):
            part = jax.tree.map(lambda x: x[i * len(names) : (i + 1) * len(names)], res)
            # the grasps the sequence holds the tool with (after each decision; the start grasp has the pedestals'
            # help), and the friction the hardest of them needs on any episode: where that exceeds the episodes'
            # mu, no controller can hold the tool
            held = {(int(g), n) for i_n, n in enumerate(names) for g in np.asarray(part.grasps[i_n])}
            by_com = {(g, tuple(np.asarray(episodes[n].com).tolist())): episodes[n] for g, n in held}  # mass scales out
            need = max(least_friction(env, g, ep) for (g, _), ep in by_com.items())  # the hardest, by its bracket
            summary["sequences"][k] = dict(actions=[int(a) for a in seqs[k]], least_friction_needed=need,
                                           episode_friction=sorted({float(e.friction) for e in episodes.values()}),
                                           **_summary(names, part))
    files.write_json(stem.with_suffix(".json"), dict(summary=summary, episodes=rows))
    files.savez(f"{stem}_trace.npz", compressed=True, angle=np.asarray(res.angle), qpos=np.asarray(res.qpos), names=labels)
    trace_png(phys, labels, res, f"{stem}_angle.png", f"{args.policy} on {args.set} ({args.backend})")
    written = [stem.with_suffix(".json"), f"{stem}_trace.npz", f"{stem}_angle.png"]
    if args.render:
        i = labels.index(args.render_episode) if args.render_episode else 0
        key = int(round(float(res.fall_time[i]) / phys.timestep)) - 2 if bool(res.fell[i]) else -1
        written += render_episode(phys, np.asarray(res.qpos[i]), f"{stem}_{labels[i].replace('/', '_')}",
                                args.render_window, key)
    print(table(["episode", "angle err [deg]", "pos err [mm]", "max lift tilt", "fell at [s]"],
                [[r["episode"], r["angle_error_deg"], r["position_error_mm"], r["max_lift_angle_deg"],
                  f"{r['fall_time_s']:.2f}" if r["fell"] else "-"] for r in rows], ".1f"))
    for k, part in summary.get("sequences", {"": summary}).items():
        print(f"\n{args.policy}{' ' + k if k else ''} on {args.set}: {part['falls']}/{part['episodes']} fell; mean angle "
              f"error {part['mean_angle_error_deg']:.1f} deg (95% CI +-{part['ci95_deg']:.1f}); where held: hold angle "
              f"{part['mean_hold_angle_deg_where_held']} deg, largest lift tilt {part['max_lift_tilt_deg_where_held']} deg"
              + ("; its hardest grasp needs mu > {:.4f} (bracket {:.4f}-{:.4f}; episodes: {})".format(
                  part["least_friction_needed"][0], *part["least_friction_needed"], part["episode_friction"])
                 if "least_friction_needed" in part else ""))
    print(f"{wall:.1f} s including compile\nwrote " + ", ".join(map(str, written)))
