"""`PhysicsConfig`: the settings of the physics check, nested by concern.

    PhysicsConfig(sim=SimConfig(...), timeline=TimelineConfig(...), controller=ControllerConfig(...),
                  fingers=FingerConfig(...), outcome=OutcomeConfig(...))
    PhysicsConfig().replace(hold=0.5, free_stiffness=2.0)     # any field by its name (names are unique)

What is not here: the physics step and the table's friction are the scene file's (`<option timestep>`, the table
geom's sliding friction); a segment is an episode's `dt`, `scenario.DT`; the controller acts at every physics step.
Settings measured and removed: docs/physics.md ("Settings measured and removed").
"""
from __future__ import annotations

import dataclasses
import math

from gsp_jax.model import scenario


FRAMES = ("nominal", "measured")  # `ControllerConfig.frames`
RADII = ("extent", "gyration")  # `ControllerConfig.radius_from`


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check(obj, positive=(), nonnegative=(), counts=(), nonnegative_counts=(), finite=()) -> None:
    """ValueError naming `PhysicsConfig.<group>.<field>` and the value for the first field out of its range."""
    path = f"PhysicsConfig.{obj.GROUP}"
    for names, ok, rule in ((positive, lambda v: _number(v) and v > 0, "> 0"),
                            (nonnegative, lambda v: _number(v) and v >= 0, ">= 0"),
                            (counts, lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1,
                             "an int >= 1"),
                            (nonnegative_counts, lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
                             "an int >= 0"),
                            (finite, _number, "finite")):
        for name in names:
            value = getattr(obj, name)
            if not ok(value):
                raise ValueError(f"{path}.{name} must be {rule}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """The simulated scene: MuJoCo's solver, and the start pedestals."""

    GROUP = "sim"
    solver_iterations: int = 20  # >= 1: Newton iterations per physics step (MJX stops earlier when converged)
    ls_iterations: int = 20  # >= 1: line-search iterations per Newton iteration
    noslip_iterations: int = 10  # >= 0: C MuJoCo's noslip iterations after each step's solve, so contacts stick
    # inside the friction cone instead of creeping (MJX has no noslip solver and ignores it)
    pedestal_speed: float = 0.02  # [m/s] > 0: the start pedestals sink away at this speed after the first segment

    def __post_init__(self):
        _check(self, positive=("pedestal_speed",), counts=("solver_iterations", "ls_iterations"),
               nonnegative_counts=("noslip_iterations",))


@dataclasses.dataclass(frozen=True)
class TimelineConfig:
    """The hold after the last waypoint, and a grasp change (one link, inside one segment of `scenario.DT`
    seconds): the leaving link unloads, moves, then loads once it touches."""

    GROUP = "timeline"
    hold: float = 1.0  # [s] > 0: under the external wrench at the final pose, rounded to whole segments
    ramp: float = 0.1  # [s] > 0: for the external wrench to reach its full value
    unload: float = 0.04  # [s] > 0: the leaving link's share of the wrench goes over to the links that stay
    move: float = 0.13  # [s] > 0: the link travels clear of the tool to its new contact (or to its parking point)
    load: float = 0.04  # [s] > 0: the arriving link takes its share, from the moment it touches
    # unload + move + load <= scenario.DT
    standoff: float = 0.012  # [m] > 0: how far off the tool's surface a moving link travels
    touch_tol: float = 0.0015  # [m] > 0: a link this close to its contact surface (along the normal) touches it ...
    reach_tol: float = 0.006  # [m] > 0: ... if also this close to its contact point across the surface

    def __post_init__(self):
        _check(self, positive=("hold", "ramp", "unload", "move", "load", "standoff", "touch_tol", "reach_tol"))
        if self.unload + self.move + self.load > scenario.DT:
            raise ValueError(f"PhysicsConfig.timeline: unload + move + load must be <= a segment (scenario.DT = "
                             f"{scenario.DT} s), got {self.unload} + {self.move} + {self.load}")


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Object-level impedance on the observed tool, and the friction-cone force solve that spreads its wrench over
    the contacts."""

    GROUP = "controller"
    tool_freq: float = 10.0  # [Hz] > 0: natural frequency of the tool's pose error (mass- and inertia-normalised)
    tool_damping: float = 1.0  # >= 0: damping ratio of the tool's pose error (1: critical)
    feedback_limit: float = 2.0  # > 0: the pose feedback's force is capped at this many tool weights (its torque at
    # as many weights x tool_radius) ...
    feedback_floor: float = 4.0  # [N] > 0: ... but never below this force
    tool_radius: float | None = None  # [m] > 0: rotational gains act as on the tool's mass at this radius (plus its
    # inertia), the feedback torque's cap is the force's times it; None: the tool's own, as `radius_from` says
    # (`controller.rotation_radius`)
    radius_from: str = "extent"  # where `tool_radius` is None, the tool's own radius: "extent", half its longest
    # side (its contacts' lever), or "gyration", its largest radius of gyration sqrt(I_max / m) (the rotational
    # stiffness then at most 2 I_max about any axis: a slower loop that a motor delay of a few ticks leaves stable)
    rotation_step: float = 0.3  # > 0: the most of the tool's angular velocity one control tick's rotational damping
    # takes off, about each principal axis (a discrete-time bound: above 1 the damping overshoots, above 2 it grows)
    grip_force: float = 8.0  # [N] >= 0: the force solve's preferred force along every contact normal (the grip,
    # in the grasp matrix's null space)
    friction_margin: float = 1.0  # in (0, 1]: the force solve's friction coefficient, as a fraction of the tool's
    force_iterations: int = 40  # >= 1: projected-gradient iterations of the force solve per tick (warm-started)
    frames: str = "measured"  # the force solve's contact normals: "nominal" (each option's face normal, the paper's
    # controller) or "measured" (where a link touches, the tool surface's normal at the link's centre line as
    # observed: MuJoCo's sphere-box normal, tilted where a fingertip rests on an edge)
    pose_filter: float = 1.0  # in (0, 1]: the gain of a complementary filter on the observed tool pose and joint
    # angles: each tick the last estimate is carried forward by the measured velocities and moved this fraction of
    # the way to the observation (1: the observation as it is; a noisy pose estimate wants ~0.1)
    strength_rate: float = 0.0  # [1/s] >= 0: how fast each motor's strength (torque per command) is estimated from
    # the tool's pose feedback while it is held, the commands divided by the estimates (0: the model's motors; the
    # estimates' leak and deadband: `controller.STRENGTH_LEAK`, `STRENGTH_DEADBAND`)
    predictive: bool = False  # C MuJoCo only: before the hold, roll it out under a few settings of these gains and
    # keep, per episode, the one that holds best (`gsp_jax.physics.predictive`)

    @property
    def tool_gains(self) -> tuple[float, float]:
        """(kp [1/s^2], kd [1/s]) of the tool's pose error, per unit mass (translation) or per unit of the inertia
        the controller assumes (rotation: the tool's own plus its mass at `tool_radius`)."""
        w = 2 * math.pi * self.tool_freq
        return w * w, 2 * self.tool_damping * w

    def __post_init__(self):
        _check(self, positive=("tool_freq", "feedback_limit", "feedback_floor", "rotation_step", "friction_margin",
                               "pose_filter") + (("tool_radius",) if self.tool_radius is not None else ()),
               nonnegative=("tool_damping", "grip_force", "strength_rate"),
               counts=("force_iterations",))
        if self.pose_filter > 1:
            raise ValueError(f"PhysicsConfig.controller.pose_filter must be in (0, 1], got {self.pose_filter}")
        if self.radius_from not in RADII:
            raise ValueError(f"PhysicsConfig.controller.radius_from must be one of {RADII}, got {self.radius_from!r}")
        if self.frames not in FRAMES:
            raise ValueError(f"PhysicsConfig.controller.frames must be one of {FRAMES}, got {self.frames!r}")
        if not isinstance(self.predictive, bool):
            raise ValueError(f"PhysicsConfig.controller.predictive must be a bool, got {self.predictive!r}")
        if self.friction_margin > 1:
            raise ValueError(f"PhysicsConfig.controller.friction_margin must be in (0, 1], got {self.friction_margin}")


@dataclasses.dataclass(frozen=True)
class FingerConfig:
    """The fingers: Cartesian impedance through J^T at the measured joint angles (no IK while the tool is held)."""

    GROUP = "fingers"
    finger_kp: float = 300.0  # [N/m] >= 0: a tracked link's stiffness towards its target
    finger_kd: float = 3.0  # [N s/m] >= 0: a tracked link's damping (the joints add the model's own)
    held_stiffness_ratio: float = 0.1  # >= 0: a touching link's stiffness and damping across the surface, as a
    # fraction of finger_kp / finger_kd (along the normal: all of it)
    free_stiffness: float = 4.0  # [N m/rad] > 0: a free link (travelling, arriving, parked) is pulled by a
    # joint-space spring of this stiffness along the damped least-squares step to its target
    free_damping: float = 0.02  # [m] > 0: that step's damping (bounds the pull where the Jacobian is singular)
    posture_kp: float = 0.02  # [N m/rad] >= 0: pull of every joint to its start angle (the fingers' spare DoF)

    def __post_init__(self):
        _check(self, positive=("free_stiffness", "free_damping"),
               nonnegative=("finger_kp", "finger_kd", "held_stiffness_ratio", "posture_kp"))


@dataclasses.dataclass(frozen=True)
class OutcomeConfig:
    """When a simulated tool counts as fallen (any of these, or a non-finite state)."""

    GROUP = "outcome"
    fall_angle: float = 90.0  # [deg] > 0: rotation from its reference pose beyond which the tool has fallen
    fall_distance: float = 0.03  # [m] > 0: position error beyond which the tool has fallen
    fall_height: float = 0.0005  # [m]: after the first segment, the tool's lowest point below this height (world z;
    # the table's surface is 0) is a fall: it touches the table

    def __post_init__(self):
        _check(self, positive=("fall_angle", "fall_distance"), finite=("fall_height",))


CONTROLLERS = {  # named contact controllers: `PhysicsConfig.named(name)`; the fields each sets
    "measured": {},  # the default: the normals the contacts have, all of mu in them, the rotational gains' radius
    # the tool's own, its damping at most 0.3 of the tool's rate a tick (docs/physics.md, "Contact frames")
    "paper": dict(frames="nominal", friction_margin=0.7, tool_radius=0.05, rotation_step=1.0),  # the paper-era
    # controller: option normals, 70% of mu, rotational gains as of the tool's mass at 5 cm, damped to the bound
    "predictive": dict(predictive=True),  # the default with the predictive hold (C MuJoCo only)
    "robust": dict(pose_filter=0.1, strength_rate=0.3, radius_from="gyration"),  # the default with a filtered pose
    # estimate, the motors' strengths estimated while holding and the rotational gains at the tool's radius of
    # gyration: for a hand whose motors, delays and pose estimate are not the model's (docs/world.md, "A controller
    # for the gap")
}
DEFAULT_CONTROLLER = "measured"

GROUPS = {"sim": SimConfig, "timeline": TimelineConfig, "controller": ControllerConfig, "fingers": FingerConfig,
          "outcome": OutcomeConfig}


def _group_of() -> dict[str, str]:
    out = {}
    for group, cls in GROUPS.items():
        for f in dataclasses.fields(cls):
            if f.name in out:
                raise TypeError(f"PhysicsConfig: field {f.name!r} is in both {out[f.name]!r} and {group!r}")
            out[f.name] = group
    return out


GROUP_OF = _group_of()  # field name -> its group's name (every field name is one group's)


def _group(name: str) -> str:
    """The group of PhysicsConfig's field `name`; ValueError naming the fields if there is none."""
    if name not in GROUP_OF:
        raise ValueError(f"PhysicsConfig has no field {name!r} (fields: {', '.join(GROUP_OF)})")
    return GROUP_OF[name]


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """The physics check's settings, one group per concern (see the module docstring)."""

    sim: SimConfig = SimConfig()
    timeline: TimelineConfig = TimelineConfig()
    controller: ControllerConfig = ControllerConfig()
    fingers: FingerConfig = FingerConfig()
    outcome: OutcomeConfig = OutcomeConfig()

    def __post_init__(self):
        for group, cls in GROUPS.items():
            value = getattr(self, group)
            if not isinstance(value, cls):
                raise ValueError(f"PhysicsConfig.{group} must be a {cls.__name__}, got {value!r}")

    def replace(self, **changes) -> PhysicsConfig:
        """A copy with fields of any group changed by their names (`replace(hold=0.5, free_stiffness=2.0)`)."""
        by_group: dict[str, dict] = {}
        for name, value in changes.items():
            by_group.setdefault(_group(name), {})[name] = value
        return dataclasses.replace(self, **{g: dataclasses.replace(getattr(self, g), **kw)
                                            for g, kw in by_group.items()})

    @staticmethod
    def named(controller: str, **changes) -> PhysicsConfig:
        """The default config with the named contact controller's settings (`CONTROLLERS`: "paper", "measured"),
        then `changes` (`replace`)."""
        if controller not in CONTROLLERS:
            raise ValueError(f"controller must be one of {sorted(CONTROLLERS)}, got {controller!r}")
        return PhysicsConfig().replace(**CONTROLLERS[controller], **changes)

    @property
    def controller_name(self) -> str | None:
        """The name in `CONTROLLERS` whose settings this config's controller fields have (None: none of them)."""
        return next((n for n in CONTROLLERS if PhysicsConfig.named(n).controller == self.controller), None)

    def value(self, name: str):
        """The value of the field `name` of any group."""
        return getattr(getattr(self, _group(name)), name)
