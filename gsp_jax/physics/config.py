"""`PhysicsConfig`: every setting of the physics check (simulation, timeline, controller, outcome) in one place,
each with the reason for its value."""
from __future__ import annotations

import dataclasses
import math

from gsp_jax import scenario


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Simulation, controller and outcome settings of the physics check."""

    # --- simulation
    timestep: float = 0.002  # [s] physics step (the scene's; contacts of 4 mm solref stay stable at it)
    control_every: int = 1  # physics steps per control tick: every step (measured: see README "physics check")
    solver_iterations: int = 20  # Newton iterations per step (MJX stops earlier when converged)
    ls_iterations: int = 20  # line-search iterations
    implicit_damping: bool = False  # Euler integrates the joints' damping implicitly (MuJoCo's default). Off: in
    # float32 MJX the Newton solve can stop unconverged (a failed line search ends it) when a link first touches,
    # and the implicit step then re-solves the accelerations from that solve's constraint forces, which are the new
    # contact's whole spring-damper response: the tool was kicked 2 mm in one tick (measured, MJX on an AMD CPU).
    # Explicit damping uses the solve's own accelerations and is stable here (timestep x damping / inertia = 0.1)
    noslip_iterations: int = 10  # C MuJoCo's noslip solver after each step's solve (MJX has none and ignores it):
    # MuJoCo's soft friction lets a contact creep under any tangential load, where Coulomb friction (the oracle's
    # model and the real fingertips') sticks inside the cone. Measured (C MuJoCo, four tips, 2-core): without it a
    # 3 m0 tool held still (first 3 waypoints, no torque) creeps out of the thumb after 1.1 s (the thumb's T/muN
    # 0.4 -> 0.75, then it lets go); with it T/muN stops at 0.57 and the tool holds. Stress envelope (H200 host)
    # falls 49 / 53 / 67 / 61 / 82 -> 44 / 49 / 64 / 58 / 84, four-tip controller falls 27 -> 22; the engine's
    # step 1.3-2.1x slower (the runner on all cores the same: the controller sets its time)
    spheres_per_capsule: int = 4  # contact spheres replacing each hand capsule (MJX misses tilted capsule-box)
    table_friction: float = 0.6
    pedestal_speed: float = 0.02  # [m/s] the start pedestals sink away after the first segment at this speed:
    # dropped at once, a tool the fingers hold by friction sags ~2 mm before the grip takes its weight (measured)
    # --- timeline
    segment: float = scenario.DT  # [s] between waypoints (episodes must have this dt)
    hold: float = 1.0  # [s] under the external wrench at the final pose, rounded to whole segments
    ramp: float = 0.1  # [s] for the external wrench to reach its full value
    # --- a grasp change (one link), inside one segment: unload, move, then load once in contact
    unload: float = 0.04  # [s] the leaving link's share of the wrench goes over to the links that stay
    move: float = 0.13  # [s] the link travels clear of the tool to its new contact (or to its parking point)
    load: float = 0.04  # [s] the arriving link takes its share, from the moment it is within contact_tol
    slide: str = "lift"  # a slide along one face: "lift" travels clear of the tool like any change, "contact"
    # stays on the face, pressed lightly; measured (C MuJoCo, 27 evaluation episodes, a slide at every waypoint,
    # with the Cartesian pull on free links that preceded `free_stiffness`): lift 3 falls, contact 12 (the sliding
    # tip drags the tool)
    slide_depth: float = 0.002  # [m] how far into the face a "contact" slide aims (a few newtons: the link is free)
    clearance: float = 0.012  # [m] how far off the surface a moving link travels (more than a fingertip radius)
    contact_tol: float = 0.0015  # [m] a link this close to the contact surface (along the normal) touches it
    reach_tol: float = 0.006  # [m] ... if also this close to its contact point across the surface (the surrogate's
    # IK accepts contacts within 5 mm)
    # --- controller: object-level impedance on the observed tool
    tool_freq: float = 10.0  # [Hz] natural frequency of the tool's pose error (mass- and inertia-normalised)
    tool_damping: float = 1.0  # damping ratio of the tool's pose error
    feedback_limit: float = 2.0  # the pose feedback's force is capped at this many tool weights (its torque at
    # as many weights x tool_radius; measured on the 27 evaluation episodes in C MuJoCo: 1 weight let light tools
    # lag and fall, 2 and 3 held alike)
    feedback_floor: float = 4.0  # [N] ... but never below this force: the hand's own drag (its joints' damping
    # reflected to the tips, 300-400 N s/m) does not scale with the tool's weight and ate a light tool's whole
    # feedback. Chosen on the envelope's calibration slice (`scenario.episode_set("stress-cal")`, four tips, C
    # MuJoCo: 0 / 4 N -> 30 / 26 falls, 13 / 9 where the oracle said forces exist; 0 evaluation falls either way)
    tool_radius: float = 0.05  # [m] rotational gains act as on a mass m at this radius (plus the tool's inertia)
    rotation_step: float = 1.0  # > 0: the rotational damping about each principal axis of the tool acts on at most
    # rotation_step / (tick kd) times the tool's own inertia there, so one tick takes at most this fraction of the
    # tool's angular velocity off (a discrete-time bound: above 1 the damping overshoots, alternates at the control
    # rate, and above 2 it grows); 0: the damping acts on the stiffness's inertia (the tool's + m tool_radius^2)
    # (there a tick took up to ~9x the roll rate off). Measured (C MuJoCo): a 2.5 m0 tool's roll alternating/smooth
    # energy 0.53 -> 0.006 (82 -> 0.013 with hand_compensation 0.3); stress envelope (H200 host) falls 49 / 53 / 66 /
    # 60 / 83 -> 49 / 53 / 67 / 61 / 82 (four tips / DP optimal / L1 / L2 / RL), regret down 1-3 each
    hand_compensation: float = 0.0  # > 0: the fingers holding the tool also get this fraction of the torques that
    # move their own inertia (armature included) with the tool's commanded acceleration (`reflected_force`); else
    # the commanded wrench must also accelerate the fingers, whose reflected inertia is several times a light tool's.
    # Off by default, measured (C MuJoCo): on the calibration slice (stress-cal + evaluation, four tips, 2-core)
    # 0 / 0.2 / 0.3 / 0.5 / 1.0 -> 27 / 26 / 26 / 25 / 25 stress-cal falls, 0 / 0 / 0 / 2 / 7 evaluation falls, held
    # angle 1.89 / 1.24 / 1.18 / 1.53 / 1.58 deg (evaluation 0.86 / 0.66 / 0.63 / 0.59 / 0.63 deg); at 0.3 on the
    # H200 host the stress envelope's DP optimal / L1 / L2 / RL falls 53 / 66 / 60 / 83 -> 49 / 62 / 58 / 71 (four
    # tips 49 -> 51), but it drops the lowest start's tool with the ring tip added at waypoint 0 (fell at 0.89 s;
    # `tests/test_physics.py`), which the default holds. The joints' damping compensated as well dropped 19
    # evaluation tools
    hand_reflected_mass: float = 1.0  # [kg] the most inertia a link's compensation assumes along any direction: a
    # near-straight finger cannot move its tip along itself, and its reflected inertia there grows without bound
    # (uncapped, 0.3 dropped 7 evaluation tools as the pedestals sank)
    feedforward_external: bool = True  # the known external wrench is fed forward (as when tightening a bolt)
    squeeze: float = 8.0  # [N] grip along each normal: the force solve's preferred forces (their null-space part)
    friction_margin: float = 0.7  # the force solve uses this fraction of the friction coefficient
    motor_margin: float = 0.0  # > 0: the force solve keeps the joint torques of the grip forces (with the fingers'
    # gravity) within this fraction of the motors' limits (`wrench.MotorLimits`, a penalty on the excess); 0: off,
    # the motors clip. Off by default, measured (C MuJoCo, four tips): 0.9 holds the 3 m0 nominal tool that falls
    # at 0.71 s without it, but on the calibration slice (stress-cal + evaluation) falls go 26 -> 33 (0.8: 32,
    # 1.0: 32; weights 0.3-3 alike), new falls at 4.3-4.8 s under the external torque: the solve then trades the
    # wrench for torque inside the 0.7 mu cones, where the clipped forces held
    motor_weight: float = 1.0  # the excess torque's weight in the force solve (`wrench.MotorLimits.weight`)
    force_iterations: int = 40  # projected-gradient iterations of the force solve per tick (warm-started)
    # --- controller: the fingers (Cartesian impedance through J^T from the measured joint state, no IK)
    finger_kp: float = 300.0  # [N/m] contact-point stiffness: 0.3 N per mm, a tenth of the grip forces
    finger_kd: float = 3.0  # [N s/m] contact-point damping (the joints add the model's own damping)
    held_stiffness_ratio: float = 0.1  # a touching link's stiffness across the surface, as a fraction: 4 links at
    # 30 N/m stay below the tool's own stiffness (m kp ~ 500 N/m), so a slip is corrected by the tool's wrench, not
    # followed by the fingers
    free_stiffness: float = 4.0  # [N m/rad] a free link (travelling, arriving, parked) is pulled by a joint-space
    # spring of this stiffness along the damped least-squares step to its target (0: a Cartesian spring J^T
    # finger_kp e, which barely moves a near-straight finger's tip along the finger: the ring tip added at
    # waypoint 0 of a low start arrived after the pedestals sank); chosen on the training and validation episodes
    # (C MuJoCo, 20 episodes x 3 sequences: 9 falls at 0, 2 at 3, 2 at 4, 3 at 5; at 10 the arrivals kicked the
    # tool: 23 of 27 evaluation episodes fell on the alternating sequence)
    free_damping: float = 0.02  # [m] the damped least-squares step's damping (bounds the pull where J is singular)
    posture_kp: float = 0.02  # [N m/rad] weak pull of every joint to its start angle (the fingers' spare DoF)
    gravity_compensation: bool = True  # add the fingers' own gravity and bias forces (MuJoCo's qfrc_bias)
    # --- outcome
    fall_angle: float = 90.0  # [deg] tool rotation from its reference beyond which it counts as fallen
    fall_distance: float = 0.03  # [m] tool position error beyond which it counts as fallen
    table_margin: float = 0.0005  # [m] lowest tool point below this height: touching the table
    fallen_error: float = 180.0  # [deg] the angle error reported for a fallen tool

    @property
    def tick(self) -> float:
        """[s] control period."""
        return self.timestep * self.control_every

    def ticks(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.tick)))

    @property
    def tool_gains(self) -> tuple[float, float]:
        """(kp [1/s^2], kd [1/s]) of the tool's pose error, per unit mass (translation) or per unit of the inertia
        the controller assumes (rotation: the tool's own plus its mass at `tool_radius`)."""
        w = 2 * math.pi * self.tool_freq
        return w * w, 2 * self.tool_damping * w

    def __post_init__(self):
        for name in ("timestep", "segment", "hold", "ramp", "unload", "move", "load", "slide_depth", "clearance",
                     "contact_tol", "reach_tol", "tool_freq", "feedback_limit", "tool_radius", "pedestal_speed",
                     "free_damping", "fall_angle", "fall_distance", "friction_margin", "hand_reflected_mass"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"PhysicsConfig.{name} must be > 0, got {value!r}")
        for name in ("control_every", "solver_iterations", "ls_iterations", "spheres_per_capsule", "force_iterations"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"PhysicsConfig.{name} must be an int >= 1, got {value!r}")
        if not (isinstance(self.noslip_iterations, int) and self.noslip_iterations >= 0):
            raise ValueError(f"PhysicsConfig.noslip_iterations must be an int >= 0, got {self.noslip_iterations!r}")
        for name in ("tool_damping", "held_stiffness_ratio", "squeeze", "finger_kp", "finger_kd", "posture_kp",
                     "free_stiffness", "feedback_floor", "rotation_step", "motor_margin", "motor_weight",
                     "hand_compensation"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value >= 0):
                raise ValueError(f"PhysicsConfig.{name} must be >= 0, got {value!r}")
        if self.unload + self.move + self.load > self.segment:
            raise ValueError(f"PhysicsConfig.unload + move + load must be <= segment ({self.segment} s), got "
                             f"{self.unload} + {self.move} + {self.load}")
        if self.slide not in ("lift", "contact"):
            raise ValueError(f"PhysicsConfig.slide must be 'lift' or 'contact', got {self.slide!r}")
        if self.friction_margin > 1:
            raise ValueError(f"PhysicsConfig.friction_margin must be in (0, 1], got {self.friction_margin}")
