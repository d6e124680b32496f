"""Episodes: the planner's input, the paper's episode sets, and their JSON files.

An `Episode` is a pytree of arrays, so a batch of episodes is one `Episode` whose leaves carry a leading axis
(`stack`), and every kernel can `vmap` over it. Units: metres, seconds, kilograms, newtons.
"""
from __future__ import annotations

import dataclasses
import pathlib
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.core import files
from gsp_jax.model import hand as hand_lib

N_WAYPOINTS = 16  # T: waypoints = decision steps of an episode
DT = 0.25  # nominal time between waypoints [s]
M0 = 0.35  # the shipped wrench's nominal mass [kg] (episodes take their tool's from its model file)
INERTIA0 = (2.5e-5, 1.1e-3, 1.12e-3)  # the shipped wrench's principal inertia about the CoM [kg m^2]
FRICTION0 = 0.8  # nominal finger-tool Coulomb friction coefficient
FRICTION_MAX = 3.0  # a plausible friction coefficient is in (0, FRICTION_MAX] (rubber on metal is ~1-2)
SCALE_MAX = 100.0  # an episode's mass is within this factor of its model's tool mass either way (its inertia within
# SCALE_MAX^2: a tool 100x as heavy and 10x as long); beyond that the model's hand is the wrong hand for the tool
DT_RANGE = (0.01, 10.0)  # [s] time between waypoints the surrogate accepts (the physics check runs its own `segment`)
MAX_WAYPOINTS = 19  # T at most: the default reward's failure (r_min -200) must cost more than any T steps held at
# its largest step cost (10), so that no plan prefers a fall (`RewardConfig.max_waypoints`)
Z_START, Z_END = 0.014, 0.06  # nominal start and end heights of the tool frame [m]
TORQUE0 = hand_lib.TASK_TORQUE  # the wrench's final external torque about +z through the CoM [N m] (a model's
# file may set its own, `HandModel.torque`: the episode sets scale their torques by it)
HEIGHT_SHIFTS_MM = (-6, -4, -2, 2, 4, 6, 8)
MASS_FACTORS = (0.5, 1.0, 1.5, 2.0)
COM_Y_OFFSETS_CM = (-2, -1, 0, 1, 2)
VALIDATION_SHIFTS_MM = (-5, -3, -1, 1, 3, 5, 7)
VALIDATION_MASS_FACTORS = (0.5, 0.75, 1.75, 2.0)
VALIDATION_COM_Y_CM = (-1.5, 1.5)
# Default start grasp (options per contact link, model order): thumb, index and middle distal on their first
# candidate contacts -- a three-fingertip grasp realised at waypoint 0.
START_OPTIONS = (1, 1, 0, 1, 0, 0)  # the shipped wrench's (models/wrench.xml: gsp_start_options)


@struct.dataclass
class Episode:
    """One episode's input. Shapes for a single episode; a batch adds a leading axis to every leaf."""

    waypoints: jax.Array  # (T, 3) desired tool position per waypoint, table frame [m]
    quats: jax.Array  # (T, 4) desired tool orientation per waypoint (w, x, y, z)
    dt: jax.Array  # () time between waypoints [s]
    w_ext: jax.Array  # (6,) external wrench held at the final pose: force [N], torque about the CoM [N m]
    mass: jax.Array  # () tool mass [kg]
    inertia: jax.Array  # (3,) principal moments of inertia about the CoM [kg m^2]
    com: jax.Array  # (3,) centre-of-mass offset in the tool frame [m]
    friction: jax.Array  # () finger-tool Coulomb friction coefficient
    start_grasp: jax.Array  # () int32, grasp index realised at waypoint 0

    @property
    def n_steps(self) -> int:
        return self.waypoints.shape[-2]

    def head(self, n: int) -> "Episode":
        """The same episode cut to its first n waypoints (reduced problems for tests and quick runs)."""
        return self.replace(waypoints=self.waypoints[..., :n, :], quats=self.quats[..., :n, :])


def min_jerk(z0: float, z1: float, n: int = N_WAYPOINTS) -> np.ndarray:
    """Heights (n,) on a minimum-jerk profile from z0 to z1 (zero velocity and acceleration at both ends)."""
    s = np.linspace(0.0, 1.0, n)
    return z0 + (z1 - z0) * (10 * s**3 - 15 * s**4 + 6 * s**5)


def make_episode(
    shift_mm: float = 0.0,
    torque: float | None = None,
    mass_factor: float = 1.0,
    com_y_cm: float = 0.0,
    friction: float = FRICTION0,
    start_grasp: int | None = None,
    com_x_cm: float = 0.0,
    lateral_mm: tuple[float, float] = (0.0, 0.0),
    torque_axis="z",
    *,
    model=None,
    start=None,
    mass: float | None = None,
    inertia=None,
    com=None,
) -> Episode:
    """The nominal lift of `model`'s tool (a name, path or `gsp_jax.Model`; None: the shipped wrench) with the
    paper's variations: start and end heights shifted, torque (None: the model's, `HandModel.torque`), mass, CoM
    y-offset; and beyond them (the stress set):
    a CoM x-offset, a lateral end point (dx, dy) [mm] reached on the same minimum-jerk profile as the height, the
    final torque about x, y, z or any axis (`torque_axis`: a name or a 3-vector, normalised).

    The tool starts where the scene file rests it and rises `Z_END - Z_START` (4.6 cm). Mass, inertia and centre
    of mass are the file's, the first two times `mass_factor`, the last offset by (com_x_cm, com_y_cm, 0); `mass`
    [kg], `inertia` (3,) [kg m^2] and `com` (3,) [m, tool frame] set them absolutely instead. The start grasp is the
    model's default (`HandModel.start_options`), or `start` (a {link: option} dict or one option per link), or the
    grasp index `start_grasp`."""
    from gsp_jax.model import load as model_lib  # local: the model reads the files

    model = model_lib.load_model(model)
    hand, space = model.hand, model.space
    for name, value in (("shift_mm", shift_mm), ("torque", torque), ("mass_factor", mass_factor),
                        ("com_y_cm", com_y_cm), ("friction", friction), ("com_x_cm", com_x_cm), ("mass", mass)):
        _number(name, value, none=name in ("torque", "mass"))
    for k, value in enumerate(np.ravel(np.asarray(lateral_mm, dtype=object))):
        _number(f"lateral_mm[{k}]", value)
    if start_grasp is not None and not (isinstance(start_grasp, (int, np.integer))
                                        and not isinstance(start_grasp, bool)):
        raise EpisodeError(f"episode.start_grasp: {start_grasp!r} (must be an int grasp index)")
    if isinstance(torque_axis, str):
        if torque_axis not in ("x", "y", "z"):
            raise EpisodeError(f"episode.torque_axis: {torque_axis!r} (must be 'x', 'y', 'z' or a 3-vector)")
        axis = np.eye(3)["xyz".index(torque_axis)]
    else:
        axis = np.asarray(torque_axis, np.float64)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise EpisodeError(f"episode.torque_axis: {torque_axis!r} (must be 'x', 'y', 'z' or a nonzero 3-vector)")
        axis = axis / np.linalg.norm(axis)
    if start is not None and start_grasp is not None:
        raise EpisodeError("episode.start: give `start` (link options) or `start_grasp` (an index), not both")
    g0 = space.encode(start_options(space, hand.start_options if start is None else start)) if start_grasp is None \
        else start_grasp
    dz = shift_mm * 1e-3
    rest = hand.tool_rest
    z = min_jerk(rest[2] + dz, Z_END + (rest[2] - Z_START) + dz)
    x, y = (min_jerk(r, r + d * 1e-3) for r, d in zip(rest[:2], lateral_mm))
    waypoints = np.stack([x, y, z], -1)
    w_ext = np.zeros(6)
    w_ext[3:] = (hand.torque if torque is None else torque) * axis
    com = hand.tool_com + np.array([com_x_cm * 1e-2, com_y_cm * 1e-2, 0.0]) if com is None else com
    ep = Episode(
        waypoints=jnp.asarray(waypoints, jnp.float32),
        quats=jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0], jnp.float32), (N_WAYPOINTS, 1)),
        dt=jnp.asarray(DT, jnp.float32),
        w_ext=jnp.asarray(w_ext, jnp.float32),
        mass=jnp.asarray(hand.tool_mass * mass_factor if mass is None else mass, jnp.float32),
        inertia=jnp.asarray(np.asarray(hand.tool_inertia) * mass_factor if inertia is None else inertia, jnp.float32),
        com=jnp.asarray(com, jnp.float32),
        friction=jnp.asarray(friction, jnp.float32),
        start_grasp=jnp.asarray(g0, jnp.int32),
    )
    return validate(ep, model=model)


def _number(name: str, value, none: bool = False) -> None:
    """EpisodeError naming `name` unless `value` is a finite real number (None too where `none`): no bool, no
    string converted silently."""
    if value is None and none:
        return
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not np.isfinite(value):
        raise EpisodeError(f"episode.{name}: {value!r} (must be a finite number)")


def start_options(space, start) -> np.ndarray:
    """(L,) per-link options of a start grasp given as a {link: option} dict (links not named: off) or one
    option per link; raise EpisodeError naming the link or value that does not exist."""
    if isinstance(start, dict):
        options = np.zeros(space.n_links, np.int64)
        for link, opt in start.items():
            if link not in space.link_names:
                raise EpisodeError(f"episode.start: link {link!r} is not one of {space.link_names}")
            options[space.link_names.index(link)] = opt
    else:
        options = np.asarray(start)
        if options.shape != (space.n_links,):
            raise EpisodeError(f"episode.start: {list(np.ravel(start))} must give one option for each of the "
                               f"{space.n_links} links {space.link_names}")
    for link, opt, n in zip(space.link_names, options, space.n_options):
        if not (float(opt).is_integer() and 0 <= opt < n):
            raise EpisodeError(f"episode.start: option {opt} of link {link!r} is not in 0..{n - 1}")
    return options.astype(np.int32)


def _fmt_mm(mm: float) -> str:
    return f"{int(mm):+d}mm" if float(mm).is_integer() else f"{mm:+g}mm"


def _fmt_cm(cm: float) -> str:
    return f"{int(cm):+d}cm" if float(cm).is_integer() else f"{cm:+g}cm"


# The widest offsets any episode set draws, written for the shipped wrench (the corpus's: `corpus.Distribution`):
# a model with less room scales them down (`Fit`), a model with as much keeps them.
COM_REACH = 0.025  # [m] CoM offset along x or y (the wrench: its CoM 2.5 cm from the handle's faces)
DOWN_REACH = 0.008  # [m] start and end heights shifted down
UP_REACH = 0.014  # [m] ... and up
LATERAL_REACH = 0.018  # [m] the lift's end point moved along x or y


@dataclasses.dataclass(frozen=True)
class Fit:
    """The factors (each in [0, 1]) by which the episode sets' offsets, written in the wrench's centimetres and
    millimetres, are scaled for a model's tool and hand (`fit`): 1 where the model has the wrench's room."""

    com: tuple = (1.0, 1.0)  # CoM offsets along the tool's x, y
    down: float = 1.0  # height shifts below the rest
    up: float = 1.0  # height shifts above it
    lateral: tuple = (1.0, 1.0)  # the end point's moves along x, y

    def shift(self, mm):
        """Height shifts [mm] of the sets (a number or an array), scaled for the model."""
        return mm * np.where(np.less(mm, 0), self.down, self.up)


def fit(model=None) -> Fit:
    """How far `model`'s tool and hand let the sets move an episode (see `Fit`). A CoM offset along x or y
    reaches at most the tool's bounding box face nearest its file CoM (`COM_REACH` on the wrench: a round grip 2 cm
    across gets 0.4 of the wrench's offsets); the lift's start, end and lateral end point stay in the hand's reach
    box (`HandModel.workspace`). Room is counted in whole tenths of a millimetre, so the wrench's 1 is exact."""
    from gsp_jax.model import load as model_lib

    hand = model_lib.load_model(model).hand
    lo, hi = hand.tool_bounds()
    room = lambda d, reach: float(min(1.0, np.floor(max(d, 0.0) * 1e4 + 1e-6) / 1e4 / reach))  # noqa: E731
    com = tuple(room(min(hand.tool_com[k] - lo[k], hi[k] - hand.tool_com[k]), COM_REACH) for k in (0, 1))
    (wlo, whi), rest = hand.workspace, hand.tool_rest
    down = room(rest[2] - wlo[2], DOWN_REACH)
    up = room(whi[2] - (rest[2] + Z_END - Z_START), UP_REACH)
    lateral = tuple(room(min(rest[k] - wlo[k], whi[k] - rest[k]), LATERAL_REACH) for k in (0, 1))
    return Fit(com=com, down=down, up=up, lateral=lateral)


STRESS_SEED = 20261125

def _torque(model) -> float:
    """The final torque magnitude of a model's episodes [N m] (`HandModel.torque`; the wrench's: TORQUE0)."""
    from gsp_jax.model import load as model_lib

    return model_lib.load_model(model).hand.torque


def nominal(model=None) -> dict[str, Episode]:
    return {"nominal": make_episode(model=model, )}


def training_set(model=None) -> dict[str, Episode]:
    """The paper's 9 training episodes: nominal (+1 N m), nominal with -1 N m, and the seven height shifts with
    -1 N m for negative shifts and +1 N m for positive ones."""
    t0, f = _torque(model), fit(model)
    eps = {"nominal": make_episode(model=model), f"nominal_{-t0:+g}Nm": make_episode(model=model, torque=-t0)}
    for s in map(f.shift, HEIGHT_SHIFTS_MM):
        tau = -t0 if s < 0 else t0
        eps[f"shift{_fmt_mm(s)}_{tau:+g}Nm"] = make_episode(model=model, shift_mm=s, torque=tau)
    return eps


def eval_set_a(model=None) -> dict[str, Episode]:
    """Evaluation set A, path deviation (7): the height shifts with the torque sign flipped."""
    eps, t0, f = {}, _torque(model), fit(model)
    for s in map(f.shift, HEIGHT_SHIFTS_MM):
        tau = t0 if s < 0 else -t0
        eps[f"shift{_fmt_mm(s)}_{tau:+g}Nm"] = make_episode(model=model, shift_mm=s, torque=tau)
    return eps


def eval_set_b(model=None) -> dict[str, Episode]:
    """Evaluation set B, mass and centre of mass (20): mass x {0.5..2} m0 crossed with CoM y-offset -2..+2 cm."""
    k = fit(model).com[1]
    return {
        f"mass{f:g}m0_comy{_fmt_cm(c * k)}": make_episode(model=model, mass_factor=f, com_y_cm=c * k)
        for f in MASS_FACTORS
        for c in COM_Y_OFFSETS_CM
    }


def validation_set(model=None) -> dict[str, Episode]:
    """Validation set (ours; the paper does not list one) for PPO's early stop, disjoint from training and
    evaluation: the odd height shifts with set A's torque convention (positive shifts -1 N m), and mass
    0.5 / 0.75 / 1.75 / 2 m0 crossed with CoM y-offset -1.5 / +1.5 cm -- unseen variations of both evaluation kinds
    (15 episodes; the CoM offsets are not evaluation set B's, so the lightest and heaviest tools are in both)."""
    eps, t0, fitted = {}, _torque(model), fit(model)
    for s in map(fitted.shift, VALIDATION_SHIFTS_MM):
        tau = t0 if s < 0 else -t0
        eps[f"shift{_fmt_mm(s)}_{tau:+g}Nm"] = make_episode(model=model, shift_mm=s, torque=tau)
    for f in VALIDATION_MASS_FACTORS:
        for c in (c * fitted.com[1] for c in VALIDATION_COM_Y_CM):
            eps[f"mass{f:g}m0_comy{_fmt_cm(c)}"] = make_episode(model=model, mass_factor=f, com_y_cm=c)
    return eps


def variations_set(model=None) -> dict[str, Episode]:
    """A model's episode set (ours, for comparing models): the nominal lift and one variation at a time -- mass
    0.5 / 1.5 / 2 m0, friction 0.5 / 1.2, the torque reversed, halved and 1.5 times (9 episodes)."""
    t0 = _torque(model)
    eps = {"nominal": make_episode(model=model)}
    for f in (0.5, 1.5, 2.0):
        eps[f"mass{f:g}m0"] = make_episode(model=model, mass_factor=f)
    for mu in (0.5, 1.2):
        eps[f"mu{mu:g}"] = make_episode(model=model, friction=mu)
    for k in (-1.0, 0.5, 1.5):
        eps[f"torque{k * t0:+g}Nm"] = make_episode(model=model, torque=k * t0)
    return eps


STRESS_SEED = 20261125  # the stress set's draws: fixed, so the set is the same everywhere
STRESS_SIZE = 120


def stress_set(n: int = STRESS_SIZE, seed: int = STRESS_SEED, prefix: str = "stress", model=None) -> dict[str, Episode]:
    """The stress set (ours, beyond the paper): `n` unseen episodes spanning the envelope the planners must hold
    in, fixed and seeded, never used for calibration or training. Per episode, stratified over the set (each range
    cut into n strata, one draw per stratum, strata shuffled per parameter): mass 0.25-3 m0 (log-uniform), friction
    0.3-2, final torque -2..+2 N m about x, y or z (in turn), CoM x and y offsets -2..+2 cm, start/end height shift
    -6..+12 mm; the path vertical, lateral (end point up to 15 mm off along x or y) or diagonal (both), in turn.
    The offsets are the wrench's, scaled for a model with less room (`fit`)."""
    rng = np.random.default_rng(seed)

    def strata(lo, hi):
        return lo + (hi - lo) * (rng.permutation(n) + rng.uniform(size=n)) / n

    log_mass = strata(np.log(0.25), np.log(3.0))
    t0, f = _torque(model), fit(model)
    mu, torque, com_x, com_y = strata(0.3, 2.0), strata(-2.0, 2.0) * t0, strata(-2.0, 2.0), strata(-2.0, 2.0)
    shift, lat = strata(-6.0, 12.0), strata(-15.0, 15.0)
    com_x, com_y, shift = com_x * f.com[0], com_y * f.com[1], f.shift(shift)
    eps = {}
    for i in range(n):
        path = ("vertical", "lateral-x", "lateral-y", "diagonal")[i % 4]
        dx = lat[i] * f.lateral[0] if path in ("lateral-x", "diagonal") else 0.0
        dy = (lat[i] if path == "lateral-y" else -lat[i] if path == "diagonal" else 0.0) * f.lateral[1]
        axis = "xyz"[i % 3]
        m = float(np.exp(log_mass[i]))
        name = f"{prefix}{i:03d}_{m:.2f}m0_mu{mu[i]:.2f}_{axis}{torque[i]:+.1f}Nm_{path}"
        eps[name] = make_episode(model=model, shift_mm=round(float(shift[i]), 1), torque=round(float(torque[i]), 2),
                                 mass_factor=m, com_y_cm=round(float(com_y[i]), 2), friction=round(float(mu[i]), 3),
                                 com_x_cm=round(float(com_x[i]), 2),
                                 lateral_mm=(round(float(dx), 1), round(float(dy), 1)),
                                 torque_axis=axis)
    return eps


def stress_calibration_set(model=None) -> dict[str, Episode]:
    """A calibration slice of the envelope: 60 episodes drawn as the stress set's, with another seed (disjoint from
    it), for choosing controller and surrogate settings that the stress set then tests."""
    return stress_set(60, STRESS_SEED + 1, prefix="envcal", model=model)


SETS = {"nominal": nominal, "variations": variations_set, "train": training_set, "val": validation_set,
        "evalA": eval_set_a, "evalB": eval_set_b, "stress": stress_set, "stress-cal": stress_calibration_set}


def episode_set(name: str, model=None) -> dict[str, Episode]:
    """A named set: nominal, variations (`variations_set`), train, val, evalA, evalB, eval (A then B), all (train then
    eval), stress (the envelope; never part of "all": not for calibration or training) or stress-cal (the envelope's
    calibration slice, disjoint from stress)."""
    if name == "eval":
        return {**eval_set_a(model), **eval_set_b(model)}
    if name == "all":
        return {**training_set(model), **eval_set_a(model), **eval_set_b(model)}
    if name not in SETS:
        raise ValueError(f"episode set: unknown name {name!r}; choose from {sorted([*SETS, 'eval', 'all'])}")
    return SETS[name](model=model)


def find(name: str, model=None) -> Episode:
    """The episode called `name` in any named set of the model (sets the model's tool cannot take are skipped);
    `EpisodeError` naming the known ones if none has it."""
    found = {}
    for set_name in ("nominal", "variations", "train", "val", "evalA", "evalB", "stress"):
        try:
            found.update(episode_set(set_name, model))
        except EpisodeError:
            continue
    if name not in found:
        raise EpisodeError(f"episode: unknown episode {name!r}; known: {', '.join(found)}")
    return found[name]


def stack(episodes: Sequence[Episode]) -> Episode:
    """A batch (leading axis) from a list of single episodes."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *episodes)


def unstack(batch: Episode) -> list[Episode]:
    n = batch.mass.shape[0]
    return [jax.tree.map(lambda x: x[i], batch) for i in range(n)]


# ----------------------------------------------------------------------------------------------- files + checks

_FIELDS = {  # name -> (shape, per-waypoint?)
    "waypoints": ((None, 3), True),
    "quats": ((None, 4), True),
    "dt": ((), False),
    "w_ext": ((6,), False),
    "mass": ((), False),
    "inertia": ((3,), False),
    "com": ((3,), False),
    "friction": ((), False),
    "start_grasp": ((), False),
}


class EpisodeError(ValueError):
    """An episode's input is invalid; the message names the field and the value."""


def validate(ep: Episode, name: str = "episode", n_grasps: int | None = None, hand=None, model=None,
             max_waypoints: int = MAX_WAYPOINTS) -> Episode:
    """Check one episode against its model (`model`: a name, path or `Model`, or its `hand`; default: the shipped
    wrench): raise `EpisodeError` naming the field and value on the first problem found. `n_grasps` defaults to
    the model's grasp count; `max_waypoints` is the reward's (`RewardConfig.max_waypoints`)."""
    from gsp_jax.model import grasps, load as model_lib  # local: both read the model file

    hand = hand or model_lib.load_model(model).hand
    n_grasps = grasps.space_of(hand).n_grasps if n_grasps is None else n_grasps
    t = None
    for field, (shape, per_wp) in _FIELDS.items():
        x = np.asarray(getattr(ep, field))
        want = tuple(t if d is None else d for d in shape) if per_wp and t is not None else shape
        if per_wp and t is None:
            if x.ndim != 2 or x.shape[1] != shape[1] or x.shape[0] < 2:
                raise EpisodeError(f"{name}.{field}: shape {x.shape}, expected (T >= 2, {shape[1]})")
            t = x.shape[0]
            if t > max_waypoints:
                raise EpisodeError(f"{name}.{field}: {t} waypoints (at most {max_waypoints}: the reward's failure "
                                   f"must cost more than any run of held steps)")
        elif x.shape != want:
            raise EpisodeError(f"{name}.{field}: shape {x.shape}, expected {want}")
        if not np.all(np.isfinite(x)):
            bad = x[~np.isfinite(x)].flat[0]
            raise EpisodeError(f"{name}.{field}: contains {bad} (values must be finite)")
    if not DT_RANGE[0] <= float(ep.dt) <= DT_RANGE[1]:
        raise EpisodeError(f"{name}.dt: {str(np.float32(float(ep.dt)))} s "
                           f"(must be in [{DT_RANGE[0]}, {DT_RANGE[1]}] s)")
    m0 = hand.tool_mass
    if not m0 / SCALE_MAX <= float(ep.mass) <= m0 * SCALE_MAX:
        raise EpisodeError(f"{name}.mass: {str(np.float32(float(ep.mass)))} kg "
                           f"(must be within {SCALE_MAX:g}x of the model's tool "
                           f"mass {m0:.4g} kg: [{m0 / SCALE_MAX:.4g}, {m0 * SCALE_MAX:.4g}] kg)")
    inertia = np.asarray(ep.inertia, np.float64)
    lo, hi = hand.tool_inertia.min() / SCALE_MAX**2, hand.tool_inertia.max() * SCALE_MAX**2
    if np.any((inertia < lo) | (inertia > hi)):
        raise EpisodeError(f"{name}.inertia: {inertia.tolist()} kg m^2 (each must be in [{lo:.3g}, {hi:.3g}]: within "
                           f"{SCALE_MAX**2:g}x of the model's tool's {hand.tool_inertia.round(8).tolist()})")
    if np.any(2 * inertia > inertia.sum() * (1 + 1e-4)):
        raise EpisodeError(f"{name}.inertia: {inertia.tolist()} kg m^2 (no body has these principal moments: each "
                           f"must be at most the sum of the other two)")
    if not 0 < float(ep.friction) <= FRICTION_MAX:
        raise EpisodeError(f"{name}.friction: {float(ep.friction)} (must be in (0, {FRICTION_MAX:g}])")
    lo, hi = hand.tool_bounds()
    com = np.asarray(ep.com)
    if np.any((com < lo) | (com > hi)):
        raise EpisodeError(
            f"{name}.com: {com.tolist()} is outside the tool (its bounding box in the tool frame: "
            f"{lo.round(4).tolist()} .. {hi.round(4).tolist()} m)"
        )
    norms = np.linalg.norm(np.asarray(ep.quats), axis=-1)
    if np.any(np.abs(norms - 1) > 1e-3):
        i = int(np.argmax(np.abs(norms - 1)))
        raise EpisodeError(f"{name}.quats[{i}]: norm {norms[i]:.4f} (must be a unit quaternion)")
    wp = np.asarray(ep.waypoints)
    lo, hi = hand.workspace.astype(np.float32)  # the waypoints are float32: a point on the edge is in the box
    out = np.any((wp < lo) | (wp > hi), axis=-1)
    if np.any(out):
        i = int(np.argmax(out))
        raise EpisodeError(
            f"{name}.waypoints[{i}]: {wp[i].tolist()} is out of the hand's reach "
            f"(table frame box {lo.tolist()} .. {hi.tolist()} m): rest the tool near the table's origin and move "
            "the palm to it, or widen the box (custom numeric gsp_workspace in the hand file)"
        )
    g = int(ep.start_grasp)
    if not 0 <= g < n_grasps:
        raise EpisodeError(f"{name}.start_grasp: {g} (must be in 0..{n_grasps - 1})")
    return ep


def to_dict(ep: Episode) -> dict:
    return {f: np.asarray(getattr(ep, f)).tolist() for f in _FIELDS}


def from_dict(d: dict, name: str = "episode") -> Episode:
    missing = [f for f in _FIELDS if f not in d]
    if missing:
        raise EpisodeError(f"{name}.{missing[0]}: missing")
    unknown = sorted(set(d) - set(_FIELDS))
    if unknown:
        raise EpisodeError(f"{name}.{unknown[0]}: unknown field")
    g = d["start_grasp"]
    if not (_is_numeric(g) and np.ndim(g) == 0 and np.isfinite(g) and g == np.round(g) and 0 <= g < 2**31):
        raise EpisodeError(f"{name}.start_grasp: {g!r} (must be an integer grasp index)")
    arrays = {}
    for f in _FIELDS:
        if not _is_numeric(d[f]):
            raise EpisodeError(f"{name}.{f}: {d[f]!r} is not numeric")
        try:
            arrays[f] = jnp.asarray(d[f], jnp.int32 if f == "start_grasp" else jnp.float32)
        except (TypeError, ValueError) as e:  # ragged nesting
            raise EpisodeError(f"{name}.{f}: {d[f]!r} is not a rectangular array") from e
    return Episode(**arrays)


def _is_numeric(x) -> bool:
    """A number or a (nested) list of numbers; None (JSON null), strings and ragged lists are not."""
    if isinstance(x, (list, tuple)):
        return all(_is_numeric(v) for v in x)
    return isinstance(x, (int, float, np.number)) and not isinstance(x, bool)


def save(path: str | pathlib.Path, episodes: dict[str, Episode], model=None) -> None:
    """Write named episodes to a human-readable JSON file, with the model they are for (name and digest; None:
    the shipped wrench), which `load` checks."""
    from gsp_jax.model import load as model_lib

    m = model_lib.load_model(model)
    doc = {"format": "gsp_jax.episodes/1", "model": {"name": m.name, "digest": m.digest},
           "episodes": {k: to_dict(v) for k, v in episodes.items()}}
    files.write_json(pathlib.Path(path), doc)


def load(path: str | pathlib.Path, model=None) -> dict[str, Episode]:
    """Read and validate named episodes from a JSON file written by `save` (or by hand) for `model` (None: the
    shipped wrench). A file that names another model (its digest) is refused with an error naming both."""
    from gsp_jax.model import load as model_lib

    m = model_lib.load_model(model)
    try:
        doc = files.read_json(path)
    except files.UnreadableFile as e:  # missing, truncated, not JSON or not UTF-8
        raise EpisodeError(str(e)) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("episodes"), dict):
        raise EpisodeError(f"{path}: expected an object with an 'episodes' object")
    made = doc.get("model")
    if isinstance(made, dict) and made.get("digest") not in (None, m.digest):
        raise model_lib.ModelError(f"{path}: these episodes were made for model {made.get('name')!r} (digest "
                                   f"{made.get('digest')}), not for {m.label}")
    return {k: validate(from_dict(v, k), k, model=m) for k, v in doc["episodes"].items()}
