"""Every planner by name: one registry that the library's planners and a user's own join alike.

    policy, axis = planners.make(ctx, "L2")          # ctx: `evaluation.context(...)`; axis 0: one policy per episode
    planners.names()                                 # every registered name
    planners.names("paper")                          # the paper's five, in its Table 1 order

    @planners.register("my-planner", needs=("tables",))
    def my_planner(ctx, *, hold: float = 0.5):
        '''Keep the grasp with probability `hold` ... (the first line is what `python -m experiments planners` shows)'''
        return policy, policy_axis

The library's planners register themselves at the end of this module. A builder takes the `evaluation.Context` of a
batch of N episodes and keyword options (with defaults: they are the planner's documented options) and returns (policy,
policy_axis): a policy for `physics.Physics.simulate` / `lookahead.rollout`, and 0 where it holds one policy per episode
(a pytree of axes for a composite), None where one policy serves all. `needs` names what of the context it reads
("tables", "solutions", "rl", "nominal", or "base": the lookahead's base, the RL policy or else the DP baseline; a
planner with a `cached` option reads the tables while it is on), so a command builds only that. The commands take any
registered name; `--plugin MODULE` imports a user's module (which registers its planners) first.
"""
from __future__ import annotations

import dataclasses
import inspect
from typing import Any, Callable

import jax
import jax.numpy as jnp

from gsp_jax.planning import beam, dp, evaluation, policies, rollout as rollout_lib
from gsp_jax.surrogate import reward as reward_lib
from gsp_jax.core import platform
from gsp_jax.model.grasps import NULL

NEEDS = ("tables", "solutions", "rl", "nominal", "base")
GROUPS = ("paper", "reference", "verified", "search", "user")


@dataclasses.dataclass(frozen=True)
class Planner:
    name: str
    build: Callable  # build(ctx, **options) -> (policy, policy_axis)
    group: str  # "paper" (the paper's five), "reference" (the physics check's),
    #             "verified" (branched in C MuJoCo), "search" (no table: `planning.beam`), "user"
    needs: tuple[str, ...]  # what of the context it reads (`NEEDS`)
    options: dict[str, Any]  # its keyword options and their defaults
    backends: tuple[str, ...] | None  # the physics backends it runs on (None: any)

    @property
    def summary(self) -> str:
        doc = inspect.getdoc(self.build) or ""
        return doc.split("\n\n")[0].replace("\n", " ")


_REGISTRY: dict[str, Planner] = {}


def register(name: str, *, group: str = "user", needs=(), backends=None):
    """Decorator: register `fn(ctx, **options) -> (policy, policy_axis)` as planner `name`. Its keyword-only
    parameters (with defaults) are its options; `needs` ⊆ `NEEDS`; `backends`: the physics backends it supports
    (None: all). Registering another function under a taken name is a ValueError (the same function again is not:
    a module imported twice)."""
    if not isinstance(name, str) or not name or any(c.isspace() for c in name):
        raise ValueError(f"planners.register: a name without spaces, got {name!r}")
    if group not in GROUPS:
        raise ValueError(f"planners.register({name!r}): group one of {GROUPS}, got {group!r}")
    bad = [n for n in needs if n not in NEEDS]
    if bad:
        raise ValueError(f"planners.register({name!r}): needs one of {NEEDS}, got {bad}")

    def decorate(fn: Callable) -> Callable:
        params = list(inspect.signature(fn).parameters.values())
        if not params or params[0].kind not in (params[0].POSITIONAL_ONLY, params[0].POSITIONAL_OR_KEYWORD):
            raise ValueError(f"planners.register({name!r}): the builder takes the context first, got {fn.__name__}"
                             f"{inspect.signature(fn)}")
        options = {p.name: p.default for p in params[1:] if p.kind is p.KEYWORD_ONLY}
        missing = [n for n, d in options.items() if d is inspect.Parameter.empty]
        if missing or any(p.kind not in (p.KEYWORD_ONLY,) for p in params[1:]):
            raise ValueError(f"planners.register({name!r}): options must be keyword-only with defaults "
                             f"(`def {fn.__name__}(ctx, *, option=default)`), got {inspect.signature(fn)}")
        old = _REGISTRY.get(name)
        if old is not None and (old.build.__module__, old.build.__qualname__) != (fn.__module__, fn.__qualname__):
            raise ValueError(f"planners.register: {name!r} is taken by {old.build.__module__}.{old.build.__qualname__}")
        _REGISTRY[name] = Planner(name, fn, group, tuple(needs), options, None if backends is None else tuple(backends))
        return fn

    return decorate


def names(group: str | None = None) -> tuple[str, ...]:
    """Registered planner names (of one group: `GROUPS`), in registration order."""
    return tuple(n for n, p in _REGISTRY.items() if group is None or p.group == group)


def get(name: str) -> Planner:
    if name not in _REGISTRY:
        raise ValueError(f"planner: {name!r} is not registered; registered: {', '.join(_REGISTRY)} "
                         f"(a planner of your own: `--plugin MODULE`, or import its module first)")
    return _REGISTRY[name]


def needs(names_: "str | list[str] | tuple[str, ...]") -> set[str]:
    """What of the context the planners `names_` read together with their default options (`NEEDS`)."""
    names_ = (names_,) if isinstance(names_, str) else names_
    return set().union(*(_reads(get(n), {}) for n in names_)) if names_ else set()


def _reads(p: Planner, options: dict) -> tuple[str, ...]:
    """`p.needs`, and the tables where its `cached` option (a lookahead's tree as table lookups) is on."""
    cached = "cached" in p.options and options.get("cached", p.options["cached"])
    return p.needs + (("tables",) if cached and "tables" not in p.needs else ())


def make(ctx, name: str, shared: dict | None = None, **options):
    """(policy, policy_axis) of planner `name` for the context's batch. `options`: the planner's own (an option it
    does not take is a ValueError naming its options); `shared`: options passed only to the planners that take
    them (a command's settings for every planner it runs, e.g. dict(cached=True, k=2))."""
    p = get(name)
    unknown = sorted(set(options) - set(p.options))
    if unknown:
        raise ValueError(f"planner {name!r}: no option {unknown[0]!r} (its options: "
                         f"{', '.join(p.options) or 'none'})")
    merged = {**{k: v for k, v in (shared or {}).items() if k in p.options}, **options}
    missing = [n for n in _reads(p, merged) if _lacks(ctx, n)]
    if missing:
        raise ValueError(f"planner {name!r}: the context was built without {' or '.join(missing)} (build it with "
                         f"`evaluation.context(..., **planners.context_flags([{name!r}]))`)")
    return p.build(ctx, **merged)


def context_flags(names_) -> dict[str, bool]:
    """`evaluation.context`'s tables / rl / nominal flags for running the planners `names_` (only what they read)."""
    need = needs(names_)
    return dict(tables=bool(need & {"tables", "solutions"}), rl=bool(need & {"rl", "base"}),
                nominal=bool(need & {"nominal", "base"}))


def _lacks(ctx, need: str) -> bool:
    if need == "base":
        return ctx.rl is None and ctx.nominal_actions is None
    attr = {"tables": "tables", "solutions": "solutions", "rl": "rl", "nominal": "nominal_actions"}[need]
    return getattr(ctx, attr) is None


def describe() -> list[dict]:
    """One row per planner: name, group, options (name=default), needs, backends, summary."""
    return [dict(name=p.name, group=p.group, options=dict(p.options), needs=list(_reads(p, {})),
                 backends=list(p.backends) if p.backends else "any", summary=p.summary) for p in _REGISTRY.values()]


def returns(ctx, name: str, backend: str = "table", **options):
    """Return of planner `name` on every episode of `ctx` (N,) float32, each episode stepped from its reset in its
    DP table (`backend="table"`: exact for the discrete states the surrogate visits) or in the surrogate itself
    (`"surrogate"`, a lookahead's tree included). `options` go to `make` as shared options (to the planner only
    where it takes them, e.g. `cached=True`)."""
    if backend not in ("table", "surrogate"):
        raise ValueError(f"returns: backend must be 'table' or 'surrogate', got {backend!r}")
    policy, axis = make(ctx, name, options)

    def one(ep, table, pol):
        return _walk(ctx, backend, ep, table, pol, None).ret

    return jax.jit(jax.vmap(one, (0, 0, axis)))(ctx.batch, ctx.tables, policy)


def _walk(ctx, backend: str, ep, table, pol, steps: int | None) -> rollout_lib.Trajectory:
    """Policy `pol`'s walk of episode `ep` from its reset, in its DP table or in the surrogate (a lookahead's root
    stepped in the same model): `planning.rollout`."""
    model = dp.TableModel(table, ctx.surrogate.space) if backend == "table" else ctx.surrogate
    if isinstance(pol, policies.Lookahead):
        pol = pol.replace(model=model)
    return rollout_lib.rollout(model, pol, model.reset(ep), steps)


@dataclasses.dataclass(frozen=True)
class Plan:
    """A planner's whole episode for each episode of a context, stepped from its reset (`plan`). Shapes: N episodes,
    T waypoints."""

    name: str  # the planner's registered name
    episodes: list[str]  # (N,) the episodes' names
    actions: jax.Array  # (N, T) int32: the decision at each waypoint (`grasps.NULL`, keep the grasp, once ended)
    rewards: jax.Array  # (N, T) float32: each step's reward (0 once the episode has ended)
    ret: jax.Array  # (N,) float32: the return, each reward weighted by the chance that the segments before held
    space: Any  # the model's `grasps.GraspSpace` (what the actions mean)

    def changes(self, i: int = 0) -> list[str]:
        """Episode i's grasp changes as "t<waypoint>:<link>-><option>" (keeping the grasp is left out)."""
        return [f"t{t}:{self.space.action_label(int(a))}" for t, a in enumerate(jax.device_get(self.actions[i]))
                if a != NULL]


def plan(ctx, name: str, backend: str = "table", **options) -> Plan:
    """Planner `name`'s episode for every episode of `ctx` (`evaluation.context`), stepped from its reset in its DP
    table (`backend="table"`) or in the surrogate (`"surrogate"`), as `returns` steps it; with the decisions and
    rewards kept. `options` as `returns` takes them."""
    if backend not in ("table", "surrogate"):
        raise ValueError(f"plan: backend must be 'table' or 'surrogate', got {backend!r}")
    if backend == "table" and ctx.tables is None:
        raise ValueError("plan: backend 'table' needs the context's DP tables (`evaluation.context(tables=True)`)")
    policy, axis = make(ctx, name, options)
    n_steps = int(ctx.batch.waypoints.shape[-2])

    def one(ep, table, pol):
        traj = _walk(ctx, backend, ep, table, pol, n_steps)  # the return as a sum of the weighted rewards, as
        # `Plan.ret` has always been summed (`traj.ret`, summed in walking order, can differ in float32's last bits)
        return traj.actions, traj.rewards, reward_lib.expected_return(traj.rewards, None, traj.alive, traj.reach)

    acts, rewards, ret = jax.jit(jax.vmap(one, (0, 0, axis)))(ctx.batch, ctx.tables, policy)
    return Plan(name, list(ctx.names), acts, rewards, ret, ctx.surrogate.space)


def check(ctx, names_: "str | list[str]", backend: str = "c", physics=None, **kwargs) -> dict:
    """The physics check of planners `names_` (one name or several) on every episode of `ctx`: each executed closed
    loop (every decision on the simulated state) in C MuJoCo (`backend="c"`) or MJX (`"mjx"`); {name:
    `physics.Result`}. `physics`: a `physics.Physics` of the context's surrogate to reuse (None: a new one, whose
    compiled programs go with it); `kwargs` go to `Physics.simulate_many` (`cores`, `workers`, `progress`)."""
    from gsp_jax.physics import Physics

    chosen = [names_] if isinstance(names_, str) else list(names_)
    phys = Physics(ctx.surrogate) if physics is None else physics
    results = phys.simulate_many([make(ctx, n) for n in chosen], ctx.batch, backend=backend, **kwargs)
    return dict(zip(chosen, results))


@jax.jit
def decide(policy, state):
    """`policy.act(state)`, jitted: one decision of any policy (`policies`, a planner's) from a surrogate state;
    () int32 for one state."""
    return policy.act(state)


# ------------------------------------------------------------------------------------------ the library's planners
def _base(ctx: evaluation.Context):
    """The lookahead's base: the PPO policy, or the DP baseline where the context has none."""
    return ctx.rl if ctx.rl is not None else policies.SequencePolicy(ctx.nominal_actions, ctx.surrogate.space)


@register("dp-base", group="paper", needs=("nominal",))
def _dp_base(ctx: evaluation.Context):
    """DP baseline: the nominal episode's optimal sequence, open loop, on every episode."""
    return policies.SequencePolicy(ctx.nominal_actions, ctx.surrogate.space), None


@register("rl", group="paper", needs=("rl",))
def _rl(ctx: evaluation.Context):
    """RL: the PPO policy (DP behaviour-cloning pretraining), deterministic."""
    return ctx.rl, None


def _lookahead(ctx: evaluation.Context, depth: int, step_model, cached: bool):
    sur = ctx.surrogate
    if not cached:
        return policies.Lookahead(_base(ctx), step_model or sur, depth=depth), None
    if ctx.tables is None:
        raise ValueError(f"L{depth} with cached=True: the context was built without tables")
    inner = dp.TableModel(ctx.tables, sur.space)
    return (policies.Lookahead(_base(ctx), step_model or sur, depth=depth, inner=inner),
            policies.Lookahead(None, None, depth=depth, inner=0))


@register("L1", group="paper", needs=("base",))
def _l1(ctx: evaluation.Context, *, cached: bool = True, step_model=None):
    """L1: one step of lookahead over the base policy's rollouts (`cached`: the tree's interior and rollouts as
    lookups in each episode's DP table, exact below the root; `model`: what steps the root, default the surrogate)."""
    return _lookahead(ctx, 1, step_model, cached)


@register("L2", group="paper", needs=("base",))
def _l2(ctx: evaluation.Context, *, cached: bool = True, step_model=None):
    """L2: two steps of lookahead over the base policy's rollouts (options as L1)."""
    return _lookahead(ctx, 2, step_model, cached)


@register("dp-opt", group="paper", needs=("solutions",))
def _dp_opt(ctx: evaluation.Context):
    """DP optimal: each episode's own optimal policy (its table solved exactly; knows the episode)."""
    return policies.TablePolicy(ctx.solutions.policy, ctx.surrogate.space), 0


@register("four-tips", group="reference")
def _four_tips(ctx: evaluation.Context):
    """The constant all-fingertips grasp, reached at the first waypoints and kept."""
    sur = ctx.surrogate
    return policies.SequencePolicy(jnp.asarray(evaluation.four_tips(sur.space, ctx.batch.n_steps)), sur.space), None


@register("one-tip", group="reference")
def _one_tip(ctx: evaluation.Context):
    """The index tip alone (lets the others go at the first waypoints): a grasp that must drop the tool."""
    sur = ctx.surrogate
    return policies.SequencePolicy(jnp.asarray(evaluation.one_tip(sur.space, ctx.batch.n_steps)), sur.space), None


@register("random", group="reference", needs=("tables",))
def _random(ctx: evaluation.Context, *, seed: int = 0, hold: float = 0.0):
    """One random feasible sequence per episode (`dp.random_sequence`: keep the grasp with probability `hold`)."""
    keys = jax.random.split(jax.random.PRNGKey(seed), len(ctx.names))
    actions = jax.vmap(dp.random_sequence, (0, 0, 0, None, None))(
        ctx.tables, ctx.batch.start_grasp, keys, ctx.surrogate.reward_config.r_min, hold)
    return policies.SequencePolicy(actions), 0


@register("L1-physics", group="verified", needs=("base",), backends=("c",))
def _l1_physics(ctx: evaluation.Context, *, k: int = evaluation.L1_PHYSICS["k"],
                bases: tuple = evaluation.L1_PHYSICS["bases"], cached: bool = True, step_model=None,
                worlds: int = 1, gap=None, world_seed: int = 0):
    """L1's `k` best root actions (and each base's own) at each decision, branched in C MuJoCo to the episode's end
    under each of `bases` (registered planners, e.g. ("four-tips", "dp-opt")); never worse than either base.
    `gap` (a level of `gsp_jax.physics.world.LEVELS` or a `world.Gap`; None: the planner's own model): each branch
    runs in `worlds` worlds drawn from it per episode (`world_seed`), an action scored by the share it holds in."""
    from gsp_jax.physics import world as world_lib
    from gsp_jax.physics.verified import PhysicsLookahead

    if isinstance(bases, str) or not bases or any(b not in names() or b == "L1-physics" for b in bases):
        raise ValueError(f"bases: one or more registered planners other than L1-physics, got {bases!r}")
    root_model = step_model
    if step_model is None and platform.current() == "cpu":  # online, the root's few dozen IK problems in the batch-last
        # form (`IKConfig.lanes`; its cost and gain: docs/performance.md), its compile kept on disk
        # (`gsp_jax.core.cache`)
        sur = ctx.surrogate
        root_model = sur.replace(ik_config=dataclasses.replace(sur.ik_config, lanes=True))
    root, axis = _lookahead(ctx, 1, root_model, cached)
    made = []
    for b in bases:
        try:
            made.append(make(ctx, b, dict(cached=cached, step_model=step_model)))
        except ValueError as e:
            raise ValueError(f"bases: {b!r} cannot be built here: {e}") from None
    if isinstance(gap, str):
        if gap not in world_lib.LEVELS:
            raise ValueError(f"gap: one of {list(world_lib.LEVELS)}, got {gap!r}")
        gap = world_lib.Gap.named(gap)
    return PhysicsLookahead(root, axis, tuple(made), k=k, gap=gap, worlds=worlds, world_seed=world_seed), None


@register("search", group="search")
def _search(ctx: evaluation.Context, *, width: int = beam.WIDTH):
    """Beam search over grasp changes: each episode planned once from its start, realising only the grasps it
    visits (`planning.beam`; no DP table, for grasp spaces a table cannot hold; `width` grasps kept per waypoint)."""
    found = beam.plan_batch(ctx.surrogate, ctx.batch, beam.BeamConfig(width=width))
    return policies.SequencePolicy(found.actions, ctx.surrogate.space), 0


@register("search-L1", group="search")
def _search_l1(ctx: evaluation.Context, *, width: int = beam.WIDTH, step_model=None):
    """L1 over the search's plan: one step of lookahead at each decision from the state it meets, the plan's rest as
    the rollouts' base, in the surrogate (`step_model`; no DP table)."""
    base, _ = _search(ctx, width=width)
    return policies.Lookahead(base, step_model or ctx.surrogate, depth=1), 0
