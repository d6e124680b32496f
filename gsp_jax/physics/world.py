"""The world gap: what the planner does not know about the world its plan runs in (issue 85).

Every planner and the learned term plan with the episode's nominal tool, the model's frictions, contact softness,
joint dynamics and motors. A *world* is one episode's departure from them, drawn from a `Gap`: the tool's mass and
inertia, its centre of mass, the friction and contact softness of each finger link against the tool, each hand
joint's damping and armature, each motor's strength (the physics model's fields: `Scene.episode_fields(episode,
world)`), an actuation delay (both backends' steps) and noise on the tool pose and joint angles the controller and
the policy observe (`seen`; the falls and errors are measured on the simulated state). The controller still
believes the nominal episode (its feed-forward, its gains); nothing a planner is given changes.

    gap = world.Gap.named("gap")                      # or nominal (no gap: today's check, bit for bit), wide
    worlds = world.draw(gap, jax.random.PRNGKey(0), n, n_links, n_joints)  # World, leaves with a leading axis (n,)
    results = phys.simulate_batch(policy, episodes, backend="c", world=worlds)

Relative fields are half-widths of a uniform factor: `mass` 0.1 draws the mass x U(0.9, 1.1). `com` is a half-width
in metres per axis; `delay` the most control ticks a command waits (drawn 0..delay per episode); the noises are
standard deviations of what the controller observes each tick. Units: metres, radians, control ticks.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# the most a relative half-width may be: a factor of 1 - 0.9 = 0.1 at its lowest keeps every quantity positive
MOST_RELATIVE = 0.9
MOST_COM = 0.02  # [m] the most a centre of mass may move per axis (a tool's CoM known to within 2 cm)
MOST_DELAY = 20  # [control ticks]
MOST_NOISE = dict(pose_noise=0.02, angle_noise=0.2, joint_noise=0.2)  # [m], [rad], [rad]

RELATIVE = ("mass", "inertia", "friction", "softness", "damping", "armature", "strength")


@dataclasses.dataclass(frozen=True)
class Gap:
    """A distribution of worlds (see the module docstring). All zero: no gap."""

    mass: float = 0.0  # relative half-width of the tool's mass factor
    inertia: float = 0.0  # relative half-width of each principal inertia's factor (independent per axis)
    com: float = 0.0  # [m] half-width of the centre of mass's offset per axis (tool frame)
    friction: float = 0.0  # relative half-width of each finger link's friction factor against the tool
    softness: float = 0.0  # relative half-width of each finger link's contact time constant (solref[0]) factor
    damping: float = 0.0  # relative half-width of each hand joint's damping factor
    armature: float = 0.0  # relative half-width of each hand joint's armature factor
    strength: float = 0.0  # relative half-width of each motor's strength factor (its torque per command)
    delay: int = 0  # [control ticks] the most a command waits before it acts (0..delay, per episode)
    pose_noise: float = 0.0  # [m] std of the observed tool position, each tick
    angle_noise: float = 0.0  # [rad] std of the observed tool orientation (a rotation vector), each tick
    joint_noise: float = 0.0  # [rad] std of each observed joint angle, each tick

    def __post_init__(self):
        for name in RELATIVE:
            _check_range(name, getattr(self, name), MOST_RELATIVE, "a relative half-width")
        _check_range("com", self.com, MOST_COM, "metres per axis")
        for name, most in MOST_NOISE.items():
            _check_range(name, getattr(self, name), most, "a standard deviation")
        if isinstance(self.delay, bool) or not isinstance(self.delay, (int, np.integer)) or \
                not 0 <= self.delay <= MOST_DELAY:
            raise ValueError(f"Gap.delay must be an int of control ticks in [0, {MOST_DELAY}], got {self.delay!r}")

    @property
    def nominal(self) -> bool:
        """Whether this gap draws only the nominal world (every field zero)."""
        return all(getattr(self, f.name) == 0 for f in dataclasses.fields(self))

    @staticmethod
    def named(name: str) -> "Gap":
        """One of `LEVELS` by name (a ValueError naming the levels otherwise)."""
        if name not in LEVELS:
            raise ValueError(f"world: unknown level {name!r}; the levels are {sorted(LEVELS)}")
        return LEVELS[name]

    def replace(self, **changes) -> "Gap":
        return dataclasses.replace(self, **changes)

    def only(self, *names: str) -> "Gap":
        """This gap with only the fields `names` (the others zero: the model's); no names: this gap."""
        fields = [f.name for f in dataclasses.fields(self)]
        unknown = [n for n in names if n not in fields]
        if unknown:
            raise ValueError(f"Gap.only: unknown fields {unknown}; the fields are {fields}")
        return self if not names else Gap(**{n: getattr(self, n) for n in names})


def _check_range(name: str, value, most: float, what: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) or \
            not math.isfinite(value) or not 0.0 <= value <= most:
        raise ValueError(f"Gap.{name} must be {what} in [0, {most}], got {value!r}")


LEVELS = {
    "nominal": Gap(),
    # what a careful lab knows of its hand and tool: masses weighed, frictions and servos identified roughly
    "gap": Gap(mass=0.1, inertia=0.2, com=0.003, friction=0.25, softness=0.3, damping=0.3, armature=0.3, strength=0.15,
               delay=2, pose_noise=0.001, angle_noise=0.01, joint_noise=0.005),
    # twice that: a hand and tool taken from the shelf
    "wide": Gap(mass=0.2, inertia=0.4, com=0.006, friction=0.5, softness=0.6, damping=0.6, armature=0.6, strength=0.3,
                delay=4, pose_noise=0.002, angle_noise=0.02, joint_noise=0.01),
}


@struct.dataclass
class World:
    """One episode's world (vmap or `draw` adds a leading axis): factors on the nominal values, offsets, the delay
    and the observation noise's scales and key. L finger links that touch the tool, J hand joints."""

    mass: jax.Array  # () factor
    inertia: jax.Array  # (3,) factors
    com: jax.Array  # (3,) [m] offset, tool frame
    friction: jax.Array  # (L,) factors
    softness: jax.Array  # (L,) factors on the contact time constant
    damping: jax.Array  # (J,) factors
    armature: jax.Array  # (J,) factors
    strength: jax.Array  # (J,) factors
    delay: jax.Array  # () int32 control ticks
    noise: jax.Array  # (3,) float32 stds: tool position [m], orientation [rad], joint angles [rad]
    key: jax.Array  # (2,) uint32: the episode's observation noise


def nominal(n_links: int, n_joints: int) -> World:
    """The nominal world (no gap; one episode)."""
    one = lambda *s: jnp.ones(s, jnp.float32)  # noqa: E731
    return World(mass=one(), inertia=one(3), com=jnp.zeros(3, jnp.float32), friction=one(n_links),
                 softness=one(n_links), damping=one(n_joints), armature=one(n_joints), strength=one(n_joints),
                 delay=jnp.zeros((), jnp.int32), noise=jnp.zeros(3, jnp.float32), key=jnp.zeros(2, jnp.uint32))


def nominal_batch(n: int, n_links: int, n_joints: int) -> World:
    """`n` nominal worlds as numpy arrays (leading axis (n,)): a batch run without a world."""
    return jax.tree.map(lambda x: np.broadcast_to(np.asarray(x), (n, *np.shape(x))).copy(),
                        nominal(n_links, n_joints))


def draw_one(gap: Gap, key: jax.Array, n_links: int, n_joints: int) -> World:
    """One episode's world from `gap` (traceable; every draw from `key`)."""
    k = jax.random.split(key, 11)

    def factor(i, half, shape=()):
        return 1.0 + jnp.float32(half) * jax.random.uniform(k[i], shape, jnp.float32, -1.0, 1.0)

    return World(mass=factor(0, gap.mass), inertia=factor(1, gap.inertia, (3,)),
                 com=jnp.float32(gap.com) * jax.random.uniform(k[2], (3,), jnp.float32, -1.0, 1.0),
                 friction=factor(3, gap.friction, (n_links,)), softness=factor(4, gap.softness, (n_links,)),
                 damping=factor(5, gap.damping, (n_joints,)), armature=factor(6, gap.armature, (n_joints,)),
                 strength=factor(7, gap.strength, (n_joints,)),
                 delay=jax.random.randint(k[8], (), 0, gap.delay + 1, jnp.int32),
                 noise=jnp.array([gap.pose_noise, gap.angle_noise, gap.joint_noise], jnp.float32),
                 key=k[9])


def draw(gap: Gap, key: jax.Array, n: int, n_links: int, n_joints: int) -> World:
    """`n` episodes' worlds (each leaf with a leading axis (n,)), one key each split from `key`. The nominal gap
    draws `nominal` worlds exactly (factors 1, offsets and delay 0)."""
    if gap.nominal:
        return jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *x.shape)), nominal(n_links, n_joints))
    return jax.vmap(lambda k: draw_one(gap, k, n_links, n_joints))(jax.random.split(key, n))


def draw_for(gap: Gap, seed: int, episodes, hand) -> World:
    """The worlds (numpy, leading axis (N,)) of `episodes` (a batch of N) for `hand` (a `HandModel`: its bodies
    that touch the tool, its joints), drawn from `gap` with `seed`: a command's (`--world`, `--world-seed`)."""
    n = int(np.shape(episodes.mass)[0])
    return jax.device_get(draw(gap, jax.random.PRNGKey(seed), n, len(hand.touch_tool), hand.n_joints))


def rows(world: World | None, idx) -> World | None:
    """The worlds of the episodes `idx` (an index array) of a batch's (None: None)."""
    return None if world is None else jax.tree.map(lambda x: np.asarray(x)[np.asarray(idx)], world)


def as_rows(world: World) -> list[dict]:
    """One JSON-able dict per episode of a batch's worlds (a result's record of the world each episode met):
    factors, offsets [m], delay [ticks], noise stds and key."""
    w = jax.device_get(world)
    n = int(np.shape(w.mass)[0])
    return [{f.name: np.asarray(getattr(w, f.name))[e].tolist() for f in dataclasses.fields(World)} for e in range(n)]


def digest(world: World) -> str:
    """16 hex digits of a batch's worlds (a saved result's key: another world, another result)."""
    import hashlib

    h = hashlib.sha256()
    for leaf in jax.tree.leaves(jax.device_get(world)):
        h.update(np.ascontiguousarray(leaf).tobytes())
    return h.hexdigest()[:16]


def check(world, episodes, scene) -> None:
    """A ValueError naming the field where `world` (a `World` batch or None) does not fit `episodes` (their leading
    axis) and `scene` (its L touching bodies, J hand joints), or holds a non-finite or non-positive factor, an
    offset or a noise outside its range. Nothing to check inside a trace."""
    if world is None or isinstance(world.mass, jax.core.Tracer):
        return
    n, L, J = int(np.shape(episodes.mass)[0]), scene.n_touch, len(scene.hand_dof)
    shapes = dict(mass=(n,), inertia=(n, 3), com=(n, 3), friction=(n, L), softness=(n, L), damping=(n, J),
                  armature=(n, J), strength=(n, J), delay=(n,), noise=(n, 3), key=(n, 2))
    for name, shape in shapes.items():
        value = np.asarray(getattr(world, name))
        if value.shape != shape:
            raise ValueError(f"world.{name}: shape {shape} expected ({n} episodes, {L} touching bodies, {J} joints), "
                             f"got {value.shape}")
        if name in RELATIVE + ("inertia",) and not np.all(np.isfinite(value) & (value > 0)):
            raise ValueError(f"world.{name}: factors must be finite and > 0, got {value[~(value > 0)][:3].tolist()}")
        if name == "com" and not np.all(np.isfinite(value)):
            raise ValueError(f"world.com: offsets must be finite, got {value.tolist()}")
        if name == "delay" and not np.all((value >= 0) & (value <= MOST_DELAY)):
            raise ValueError(f"world.delay: control ticks in [0, {MOST_DELAY}] expected, got {value.tolist()}")
        if name == "noise":
            most = np.array(list(MOST_NOISE.values()), np.float32)
            if not np.all(np.isfinite(value) & (value >= 0) & (value <= most)):
                raise ValueError(f"world.noise: stds in [0, {most.tolist()}] (tool position [m], orientation [rad], "
                                 f"joint angles [rad]) expected, got {value[~np.all(value <= most, -1)][:2].tolist()}")


# ------------------------------------------------------------------------------------------ observation noise
# What the controller and the policy observe at control tick j is the state plus noise that is a function of the
# episode's key, j and the component only (a counter-based hash, the same in JAX and in the native controller:
# `native._seen_row`), so every backend and every continuation of a snapshot sees the same noise. Each component's
# noise is (u0 + u1 + u2 + u3 - 2) sqrt(3), four uniforms of 24 bits: zero mean, unit variance, within +-3.46.
# Components: 0..2 the tool's position, 3..5 its rotation vector (applied to first order, then normalised), 6 + i
# hand joint i.
HASH_MUL = (0x7FEB352D, 0x846CA68B)  # a 32-bit integer mixer's multipliers (xor-shift 16, 15, 16)
COMPONENTS = 64  # counter stride per tick: at most 58 hand joints
UNIT = 2.0 ** -24
SQRT3 = math.sqrt(3.0)


def _mix(x: jax.Array) -> jax.Array:
    """uint32 -> uint32, a bijective avalanche mixer."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(HASH_MUL[0])
    x = x ^ (x >> 15)
    x = x * jnp.uint32(HASH_MUL[1])
    return x ^ (x >> 16)


def unit_noise(key: jax.Array, j, component: jax.Array) -> jax.Array:
    """Zero-mean, unit-variance float32 noise (the shape of `component`, uint32 indices) at tick j (see above)."""
    key = jnp.asarray(key, jnp.uint32)
    base = (jnp.asarray(j, jnp.uint32) * jnp.uint32(COMPONENTS) + jnp.asarray(component, jnp.uint32)) * jnp.uint32(4)
    total = jnp.zeros(jnp.shape(component), jnp.float32)
    for m in range(4):
        h = _mix(_mix(_mix(base + jnp.uint32(m)) ^ key[0]) ^ key[1])
        total = total + (h >> 8).astype(jnp.float32) * jnp.float32(UNIT)
    return (total - jnp.float32(2.0)) * jnp.float32(SQRT3)


def seen(obs, world: World | None, j):
    """What the controller and the policy observe at control tick j of one episode in `world` (None: `obs`):
    `scene.Observation` with its tool pose and joint angles noised (velocities and bias as simulated)."""
    if world is None:
        return obs
    J = obs.q.shape[0]
    n = unit_noise(world.key, j, jnp.arange(6 + J, dtype=jnp.uint32))
    s = jnp.asarray(world.noise, jnp.float32)
    pos = obs.tool_pos + s[0] * n[0:3]
    r = s[1] * n[3:6]
    w, x, y, z = (obs.tool_quat[i] for i in range(4))
    turn = jnp.stack([-x * r[0] - y * r[1] - z * r[2], w * r[0] + y * r[2] - z * r[1],
                      w * r[1] + z * r[0] - x * r[2], w * r[2] + x * r[1] - y * r[0]])
    quat = obs.tool_quat + jnp.float32(0.5) * turn
    quat = jnp.where(s[1] > 0, quat / jnp.sqrt(jnp.sum(quat * quat)), obs.tool_quat)  # no noise: the same bits
    return obs.replace(q=obs.q + s[2] * n[6:], tool_pos=pos, tool_quat=quat)
