"""What a physics run's `Result` says, for people: per-episode rows, a summary, the angle traces as a PNG, a key
frame and GIF of one episode, and the least friction a grasp needs (the scripted sequences' check).

    rows = result_rows(names, res)                     # [{episode, angle_error_deg, position_error_mm, ...}]
    summary(names, res)                                # falls, mean angle error and its 95% CI, hold angles
    angle_png(phys, names, res, path, title)           # tool angle error [deg] against time [s]
"""
from __future__ import annotations

import numpy as np

from gsp_jax.model import scenario
from gsp_jax.solvers import wrench
from gsp_jax.core.stats import mean_ci


def least_friction(sur, grasp: int, episode: scenario.Episode) -> tuple[float, float]:
    """The least friction coefficient at which `grasp`'s nominal contacts can hold `episode`'s tool at rest (its
    weight about its CoM), however hard they press: `wrench.least_friction`'s bracket (lower, upper)."""
    opts = np.asarray(sur.space.decode(grasp))
    links = np.flatnonzero(opts)
    h = sur.hand
    weight = -float(episode.mass) * np.asarray(h.gravity, float)
    return wrench.least_friction(h.option_pos[links, opts[links]], h.option_normal[links, opts[links]],
                                 np.concatenate([weight, np.zeros(3)]), np.asarray(episode.com))


def result_rows(names, res) -> list[dict]:
    """One dict per episode of a `physics.Result` (angles [deg], position error [mm], fall time [s], the grasps
    held)."""
    return [
        dict(episode=n, angle_error_deg=float(res.angle_error[i]), position_error_mm=1e3 * float(res.position_error[i]),
             max_lift_angle_deg=float(res.max_angle[i]), fell=bool(res.fell[i]), fall_time_s=float(res.fall_time[i]),
             grasps=[int(g) for g in res.grasps[i]])
        for i, n in enumerate(names)
    ]


def summary(names, res, **extra) -> dict:
    """Falls, mean angle error [deg] with its 95% t-interval, and where held the hold angle and largest lift tilt."""
    mean, ci = mean_ci(res.angle_error)
    held = ~np.asarray(res.fell)
    return dict(episodes=len(names), falls=int(np.sum(res.fell)), mean_angle_error_deg=mean, ci95_deg=ci,
                mean_hold_angle_deg_where_held=(float(np.mean(np.asarray(res.angle_error)[held])) if held.any()
                                                else None),
                max_lift_tilt_deg_where_held=float(np.max(np.asarray(res.max_angle)[held])) if held.any() else None,
                **extra)


def angle_png(phys, names, res, path, title: str) -> None:
    """The tool's angle error [deg] against time [s] of every episode of `res` (lines end at a fall), to `path`."""
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


def render_episode(phys, qpos: np.ndarray, stem, window=None, key: int = -1) -> list:
    """Key frame (frame `key`) PNG and a GIF at `render.GIF_FPS` frames per simulated second (of the time
    `window`, default all); [] if no GL backend."""
    try:
        from gsp_jax.physics import render
    except Exception as e:  # noqa: BLE001 - rendering is optional
        print(f"rendering skipped: {e}")
        return []
    try:
        every = max(1, int(round(1 / (render.GIF_FPS * phys.timestep))))
        png = render.save_png(f"{stem}_keyframe.png", render.frames(phys.model, qpos[key][None], size=(480, 640))[0])
        lo, hi = (0, len(qpos)) if window is None else (int(window[0] / phys.timestep), int(window[1] / phys.timestep))
        gif = render.save_gif(f"{stem}.gif", render.frames(phys.model, qpos[lo:hi], every=every), fps=render.GIF_FPS)
        return [png, gif]
    except Exception as e:  # noqa: BLE001
        print(f"rendering skipped ({type(e).__name__}: {e}); set MUJOCO_GL=egl or osmesa")
        return []
