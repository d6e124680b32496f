"""Pictures of simulated episodes: frames from a `physics.Result.qpos` trace with mujoco's offscreen renderer.

Optional: needs an OpenGL backend, chosen by the `MUJOCO_GL` environment variable, which must be set before
anything imports mujoco (e.g. `MUJOCO_GL=egl python -m experiments physics --render`). `egl` works headless on
the CPU machines here; the GPU machines we measured on have no libEGL (there `MUJOCO_GL=egl` makes `import
mujoco` fail), so render from a saved `qpos` trace on a CPU. `osmesa` is the software fallback where installed.
Nothing else in the library imports this module, so the physics check runs without any GL.
"""
from __future__ import annotations

import pathlib

import mujoco
import numpy as np


def frames(model: mujoco.MjModel, qpos: np.ndarray, every: int = 1, camera: str = "front",
           size: tuple[int, int] = (360, 480)) -> np.ndarray:
    """RGB frames (N, H, W, 3) uint8 of the configurations qpos (K, nq), every `every`-th one."""
    qpos = np.asarray(qpos)
    if qpos.ndim != 2 or qpos.shape[1] != model.nq:
        raise ValueError(f"qpos must have shape (K, {model.nq}), got {qpos.shape}")
    data = mujoco.MjData(model)
    h, w = size
    out = []
    with mujoco.Renderer(model, h, w) as renderer:
        for q in qpos[::every]:
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=camera)
            out.append(renderer.render().copy())
    return np.stack(out)


def save_gif(path, images: np.ndarray, fps: float) -> pathlib.Path:
    """Write frames (N, H, W, 3) as an animated GIF (Pillow, which matplotlib already needs)."""
    from PIL import Image

    path = pathlib.Path(path)
    pil = [Image.fromarray(f) for f in images]
    pil[0].save(path, save_all=True, append_images=pil[1:], duration=int(round(1000 / fps)), loop=0)
    return path


def save_png(path, image: np.ndarray) -> pathlib.Path:
    from PIL import Image

    path = pathlib.Path(path)
    Image.fromarray(image).save(path)
    return path
