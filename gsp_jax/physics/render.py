"""Pictures of simulated episodes: frames from a `physics.Result.qpos` trace with mujoco's offscreen renderer.

The frames are drawn from a restyled copy of the model (the caller's model is never changed, see `styled`): each
finger in its own colour-blind-friendly colour (Okabe-Ito; `finger_colours()` gives them for a legend), found by
the name prefix of the body a geom hangs from (``thumb_*``, ``index_*``, ...); the tool steel blue-grey, the palm
dark grey, the table light, matte and drawn out to the horizon; a brighter headlight and soft shadows. The views
(`VIEWS`, free cameras): ``"closeup"`` (default) looks down obliquely from the handle's end, so the fingertips on
both sides of the handle show (thumb on -y, the other fingers on +y); ``"head"`` the same from the head's end;
``"side"`` the whole hand and the tool's height from the thumb's side. A camera of the model works too (``"front"``).

Optional: needs an OpenGL backend, chosen by the `MUJOCO_GL` environment variable, which must be set before
anything imports mujoco (e.g. `MUJOCO_GL=egl python -m experiments physics --render`). `egl` works headless where
libEGL is installed; where it is missing (some GPU machines: docs/calibration.md) `MUJOCO_GL=egl` makes `import
mujoco` fail, so render there from a saved `qpos` trace on a CPU. `osmesa` is the software fallback where installed.
Nothing else in the library imports this module, so the physics check runs without any GL.

Words for pictures need no GL: `option_places` names where each contact option touches the tool (from the model's
sites and the tool's geoms), `caption` writes lines of text onto frames (Pillow, which matplotlib already needs).
"""
from __future__ import annotations

import copy
import pathlib

import mujoco
import numpy as np

# Okabe-Ito colours, one per finger in the hand's order (the palm's children), cycled beyond four.
FINGER_PALETTE = ((0.835, 0.369, 0.0),  # vermillion (the wrench's hand: thumb)
                  (0.0, 0.447, 0.698),  # blue (index)
                  (0.0, 0.620, 0.451),  # bluish green (middle)
                  (0.800, 0.475, 0.655),  # reddish purple (ring)
                  (0.902, 0.624, 0.0),  # orange
                  (0.337, 0.706, 0.914))  # sky blue
PALM_RGB = (0.40, 0.40, 0.43)
TOOL_RGB = (0.45, 0.50, 0.58)  # steel
PEDESTAL_RGB = (0.80, 0.76, 0.68)
TABLE_SCALE = 50.0  # the table is drawn this much larger (no black sky behind the hand)
# Free cameras: lookat [m] (the tool lies at about (0.02, 0, 0.014 .. 0.06), the palm at z = 0.15),
# distance [m], azimuth and elevation [deg].
VIEWS = {"closeup": dict(lookat=(0.01, 0.0, 0.045), distance=0.30, azimuth=20.0, elevation=-30.0),  # handle end
         "head": dict(lookat=(0.01, 0.0, 0.045), distance=0.30, azimuth=160.0, elevation=-30.0),  # head end
         "side": dict(lookat=(0.01, 0.0, 0.075), distance=0.32, azimuth=90.0, elevation=-25.0)}  # thumb side


GIF_FPS = 25  # frames per simulated second in a GIF of an episode
FACES = {0: ("-x end", "+x end"), 1: ("-y side", "+y side"), 2: ("underside", "top")}  # outward normal's axis, sign


def _rotation(quat) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, np.float64))
    return mat.reshape(3, 3)


def option_places(mj_model: mujoco.MjModel) -> dict[str, tuple[str, ...]]:
    """{contact link: (where its option k touches the tool, for k = 1, 2, ...)}: the tool geom nearest the option's
    site ``opt_<link>_<k>`` (the geom's name, or "geom <i>"), the face the finger pushes on (the site's inward z
    axis reversed, by its largest tool-frame component: "+y side", "underside", "-x end", ...) and the site's
    coordinate along the tool's longest axis [mm], e.g. "handle -y side, x -20 mm". Tool frame, as in the model;
    the tool's colliding geoms (by contact bits or by contact pairs)."""
    from gsp_jax.model import hand as hand_lib

    tool = hand_lib.tool_body(mj_model)
    paired = {int(g) for g in (*mj_model.pair_geom1, *mj_model.pair_geom2) if mj_model.geom_bodyid[g] == tool}
    geoms = hand_lib.tool_geoms(mj_model, tool) or sorted(paired)  # the physics scene collides by explicit pairs
    if not geoms:
        raise ValueError(f"model: the tool body {mj_model.body(tool).name!r} has no colliding geom")
    # each geom's box (its aabb, in its own frame) and that box's corners in the tool frame
    boxes = [(mj_model.geom_pos[g], _rotation(mj_model.geom_quat[g]), mj_model.geom_aabb[g, :3],
              mj_model.geom_aabb[g, 3:]) for g in geoms]
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    corners = np.concatenate([pos + (centre + signs * half) @ mat.T for pos, mat, centre, half in boxes])
    axis = int(np.argmax(np.ptp(corners, axis=0)))  # the tool's longest axis

    def signed_distance(point, box) -> float:  # to a geom's box: < 0 inside
        pos, mat, centre, half = box
        q = np.abs((point - pos) @ mat - centre) - half
        return float(np.linalg.norm(np.maximum(q, 0.0)) + min(q.max(), 0.0))

    places = {}
    for link in hand_lib.contact_links(mj_model):
        names, k = [], 1
        while (site := mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, f"opt_{link}_{k}")) >= 0:
            point = mj_model.site_pos[site]
            outward = -_rotation(mj_model.site_quat[site])[:, 2]
            face = int(np.argmax(np.abs(outward)))
            nearest = min(range(len(geoms)), key=lambda i: abs(signed_distance(point, boxes[i])))
            geom = mj_model.geom(geoms[nearest]).name or f"geom {geoms[nearest]}"
            names.append(f"{geom} {FACES[face][int(outward[face] > 0)]}, {'xyz'[axis]} {1000 * point[axis]:+.0f} mm")
            k += 1
        places[link] = tuple(names)
    return places


def caption(images: np.ndarray, texts: list[str], size: int = 14) -> np.ndarray:
    """Frames (N, H, W, 3) uint8 with texts[i] (lines split at "\n") written in white on a dark band across the top
    of frame i; a copy, the input is kept."""
    from PIL import Image, ImageDraw, ImageFont

    if len(texts) != len(images):
        raise ValueError(f"texts: one per frame ({len(images)}), got {len(texts)}")
    font = ImageFont.load_default(size=size)
    out = []
    for image, text in zip(images, texts):
        pil = Image.fromarray(np.asarray(image, np.uint8)).convert("RGBA")
        band = Image.new("RGBA", pil.size, (0, 0, 0, 0))
        draw = ImageDraw.Draw(band)
        lines = text.split("\n")
        step = int(round(1.3 * size))
        draw.rectangle([0, 0, pil.size[0], step * len(lines) + size // 2], fill=(0, 0, 0, 150))
        for i, line in enumerate(lines):
            draw.text((size // 2, size // 4 + step * i), line, fill=(255, 255, 255, 255), font=font)
        out.append(np.asarray(Image.alpha_composite(pil, band).convert("RGB")))
    return np.stack(out)


def _fingers(mj_model: mujoco.MjModel) -> tuple[int, list[int]]:
    """(the hand's root body, its children: one per finger), from the model's conventions (`gsp_jax.model.hand`)."""
    from gsp_jax.model import hand as hand_lib

    palm = hand_lib.hand_root(mj_model)
    return palm, [b for b in range(mj_model.nbody) if mj_model.body_parentid[b] == palm and b != palm]


def finger_colours(mj_model: mujoco.MjModel | None = None) -> dict[str, tuple[float, float, float]]:
    """{finger: (r, g, b) in [0, 1]}, the colours the frames give each finger (for a legend), named by the finger's
    first body's name up to "_" (default model: the shipped wrench's scene)."""
    from gsp_jax.model import hand as hand_lib

    mj_model = hand_lib.load_mjmodel() if mj_model is None else mj_model
    _, fingers = _fingers(mj_model)
    return {mj_model.body(f).name.split("_")[0]: FINGER_PALETTE[i % len(FINGER_PALETTE)] for i, f in enumerate(fingers)}


def styled(mj_model: mujoco.MjModel, size: tuple[int, int] = (0, 0)) -> mujoco.MjModel:
    """A copy of `model` restyled for pictures (colours, lights, an offscreen buffer of at least `size` (H, W))."""
    from gsp_jax.model import hand as hand_lib
    from gsp_jax.physics.scene import SUPPORT

    m = copy.deepcopy(mj_model)
    palm, fingers = _fingers(m)
    tool = hand_lib.tool_body(m)
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        while b and m.body_parentid[b] not in (palm, 0):
            b = int(m.body_parentid[b])
        if b in fingers:
            m.geom_rgba[g, :3] = FINGER_PALETTE[fingers.index(b) % len(FINGER_PALETTE)]
        elif m.geom_bodyid[g] == palm:
            m.geom_rgba[g, :3] = PALM_RGB
        elif m.geom_bodyid[g] == tool:
            m.geom_rgba[g, :3] = TOOL_RGB
        elif m.geom(g).name.startswith(SUPPORT):
            m.geom_rgba[g, :3] = PEDESTAL_RGB
    for g in np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_PLANE):  # the table: out to the horizon
        m.geom_size[g, :2] *= TABLE_SCALE
        if m.geom_matid[g] >= 0:
            m.mat_texrepeat[m.geom_matid[g]] *= TABLE_SCALE
    m.mat_reflectance[:] = 0.0  # no mirror image of the hand in the table
    m.vis.headlight.ambient[:] = 0.5
    m.vis.headlight.diffuse[:] = 0.4
    m.vis.headlight.specular[:] = 0.1
    m.light_diffuse[:] = 0.3  # soft shadows
    m.light_specular[:] = 0.2
    m.vis.global_.offheight = max(m.vis.global_.offheight, size[0])
    m.vis.global_.offwidth = max(m.vis.global_.offwidth, size[1])
    return m


def view_camera(name: str) -> mujoco.MjvCamera | str:
    """The free camera of a view in `VIEWS`, or `name` unchanged (a camera of the model)."""
    if name not in VIEWS:
        return name
    view, cam = VIEWS[name], mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = view["lookat"]
    cam.distance, cam.azimuth, cam.elevation = view["distance"], view["azimuth"], view["elevation"]
    return cam


def frames(mj_model: mujoco.MjModel, qpos: np.ndarray, every: int = 1, camera: str = "closeup",
           size: tuple[int, int] = (360, 480)) -> np.ndarray:
    """RGB frames (N, H, W, 3) uint8 of the configurations qpos (K, nq), every `every`-th one, seen from
    `camera` (a view in `VIEWS` or a camera of the model); `size` is (H, W)."""
    qpos = np.asarray(qpos)
    if qpos.ndim != 2 or qpos.shape[1] != mj_model.nq:
        raise ValueError(f"qpos must have shape (K, {mj_model.nq}), got {qpos.shape}")
    m = styled(mj_model, size)
    cam = view_camera(camera)
    data = mujoco.MjData(m)
    out = []
    with mujoco.Renderer(m, *size) as renderer:
        for q in qpos[::every]:
            data.qpos[:] = q
            mujoco.mj_forward(m, data)
            renderer.update_scene(data, camera=cam)
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
