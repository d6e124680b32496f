"""Lookahead verified in physics: Algorithm 2 with the simulator as its model (C MuJoCo).

At each decision of an episode the surrogate's lookahead (`root`, e.g. the cached L1) ranks the root actions by
its Q-values. Its `k` best, and each base policy's own action, are simulated from a copy of the current
simulated state (`c_backend.Snapshot`: MuJoCo's state rows and the controller's), closed loop to the end of the
episode, hold included: each candidate as the first action and a base policy after it (`FirstThen`), once under
every base policy of `bases`. The action taken is the one whose branch did best in physics: held first, then the
least hold angle error, then the surrogate's Q. The surrogate prunes and ranks, the physics decides. Every
decision's candidates and their outcomes are kept (`Decision`).

A rollout with several base policies (Bertsekas' rollout with multiple heuristics): as every base's own action
is among the candidates at every decision, the branch taken at one decision is continued, bit for bit, by a
candidate of the next (the physics is deterministic and a branch from a snapshot is the original run:
tests/test_physics.py). So the episode's outcome is never worse than the branch taken at its first decision,
and so never worse than any base policy run from the start: with `bases` (four tips, DP optimal), L1-physics
holds every episode that either holds.

    policy = PhysicsLookahead(root=L1, root_axis=axis, bases=((rl, None), (four_tips, None)), k=17)
    result = phys.simulate_batch(policy, episodes, backend="c")      # only the C backend can copy its state

The branches of all the lockstep's episodes at one decision run as one lockstep on every core, their decisions
(the bases' actions) on the CPU (`branch_device`). A branch is run once: the same candidate under the same base
is one branch, and the branch taken at one decision has already shown, under every base, what each base's own
action at the next decision leads to (the branches of a decision share the episode's past and continue it bit for
bit), so those outcomes are reused (`reuse`; `Decision.branches` counts the branches run).

Branching over worlds (`gap`, `worlds`): the simulator is the planner's model, and a hand and tool are never known
that well (docs/world.md). With a `world.Gap`, every branch runs once in each of `worlds` worlds drawn from it for
its episode (the planner's own guesses, fixed for the episode and drawn apart from the world the episode meets),
and a candidate is scored by the share of them it holds in, then its mean angle error: an action is good if it
holds in most of the worlds the planner cannot tell apart. The never-worse argument then holds in those worlds, not
in the one the episode meets.
"""
from __future__ import annotations

import dataclasses
import time
import zlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.physics.spec import HasSpec, PhysicsSpec, of


@struct.dataclass
class FirstThen:
    """`first` at segment `at`, the `base` policy at every other decision (a branch's policy)."""

    first: jax.Array  # () int32: the branch's first action
    at: jax.Array  # () int32: the segment (waypoint) of that action
    base: Any  # a policy (anything with `act(state)`)

    def act(self, state) -> jax.Array:
        return jnp.where(state.t == self.at, self.first, jnp.asarray(self.base.act(state), jnp.int32))


@dataclasses.dataclass(frozen=True)
class Decision:
    """One decision of one episode: the candidates per base policy and their branches' outcomes."""

    episode: int  # row of the policy's episode batch
    segment: int
    candidates: np.ndarray  # (B, slots) int32 first actions: the surrogate's k best (best first), then (with
    # `base_actions`) the base's own action
    q: np.ndarray  # (A,) the surrogate's Q-values of every root action
    fell: np.ndarray | None  # (B, slots) bool: the branch's tool fell (None: not branched, as with one candidate
    # or a tool that had already fallen: the surrogate's best is taken); (B, slots, W) over W worlds (`worlds`)
    angle_error: np.ndarray | None  # (B, slots) [deg] the branch's mean hold angle error (180 if it fell); (B,
    # slots, W) over worlds
    chosen: int  # the action taken
    base: int  # the base policy of the branch taken (-1: not branched)
    seconds: float  # wall time of the decision call that made it (every episode of the lockstep at once)
    branches: int = 0  # branches that call ran in physics (every episode of the lockstep at once): the others'
    # outcomes were known from earlier branches
    steps: int = 0  # the physics steps those branches took


@dataclasses.dataclass(eq=False)
class PhysicsLookahead:
    """The physics-verified lookahead policy (`L1-physics`). Not a JAX policy: the C backend's lockstep runs it
    (`Physics.simulate_many(..., backend="c")`). `decisions` collects every decision's `Decision` (appended)."""

    root: Any  # a policy with `search(state)` -> Q-values `.q` (A,) over the actions (`lookahead.Lookahead`)
    root_axis: Any  # its policy_axis (e.g. 0 for the tables of the cached L1)
    bases: tuple  # ((policy, policy_axis), ...): the policies the branches follow after their first action (axis
    # None: one for every branch; per episode, e.g. DP optimal's tables: each branch gets its episode's)
    k: int = 17  # the surrogate's best k root actions are candidates
    base_actions: bool = True  # each base's own action is a candidate too (under that base): never worse than a
    # base (module docstring); without it and with k = 1 the root's action is taken, nothing branched
    cores: int | None = None  # cores of the branches' lockstep (default: all)
    reuse: bool | None = None  # a branch whose outcome an earlier branch of the episode already gave is not run
    # again (that branch took the episode's actions so far, then this candidate, under the same base: the physics is
    # deterministic, so its outcome is this one's); False runs every branch (tests/test_physics.py compares). None:
    # on in the model, off with a `gap` (the episode's own state leaves the branches' worlds: docs/world.md)
    branch_device: str | None = "cpu"  # where the branches' decisions (the bases' actions) run: a CPU answers a
    # cheap base (a sequence, a DP table) faster than a GPU answers a call; None: JAX's default device
    workers: int | None = None  # its chunks (default as `c_backend.simulate`)
    gap: Any = None  # a `gsp_jax.physics.world.Gap`: every branch runs in `worlds` worlds drawn from it per episode
    # (module docstring); None: in the planner's own model
    worlds: int = 1  # worlds drawn per episode (with `gap`)
    world_seed: int = 0  # the seed of those worlds (a stream apart from `--world-seed`'s: `planned_worlds`)
    decisions: list = dataclasses.field(default_factory=list)
    _gathered: dict = dataclasses.field(default_factory=dict, repr=False)  # bases per set of branched rows
    _tables: dict = dataclasses.field(default_factory=dict, repr=False)  # waypoints -> `_tables`
    _known: dict = dataclasses.field(default_factory=dict, repr=False)  # (row, base, world, actions from the
    # start) -> (fell, angle error): the outcomes of the branches run so far in this episode
    _worlds: dict = dataclasses.field(default_factory=dict, repr=False)  # the episodes' ids -> `planned_worlds`

    def __post_init__(self):
        if not (isinstance(self.k, int) and self.k >= 1):
            raise ValueError(f"PhysicsLookahead.k must be an int >= 1, got {self.k!r}")
        if not (isinstance(self.bases, (tuple, list)) and self.bases
                and all(isinstance(b, (tuple, list)) and len(b) == 2 for b in self.bases)):
            raise ValueError(f"PhysicsLookahead.bases must be a non-empty sequence of (policy, policy_axis) pairs, "
                             f"got {self.bases!r}")
        self.bases = tuple(tuple(b) for b in self.bases)
        from gsp_jax.physics import world as world_lib

        if not (isinstance(self.worlds, int) and self.worlds >= 1):
            raise ValueError(f"PhysicsLookahead.worlds must be an int >= 1, got {self.worlds!r}")
        if self.gap is not None and not isinstance(self.gap, world_lib.Gap):
            raise ValueError(f"PhysicsLookahead.gap must be a world.Gap or None, got {self.gap!r}")
        if self.gap is not None and self.gap.nominal:
            self.gap = None  # the nominal gap's worlds are all the model: branch in it once
        if self.gap is None and self.worlds != 1:
            raise ValueError(f"PhysicsLookahead.worlds: {self.worlds} worlds need a gap to draw them from (gap=None "
                             "branches in the planner's own model)")
        if self.reuse is None:
            self.reuse = self.gap is None

    @property
    def n_worlds(self) -> int:
        """The worlds each branch runs in (1 without a gap)."""
        return 1 if self.gap is None else self.worlds

    def in_physics(self, spec: PhysicsSpec, snapshot, rows: np.ndarray, obs: np.ndarray, episodes, k: int,
                   n_steps: int):
        """The C backend's hook at segment k (`spec`: the lockstep's `Physics`): this segment's policy for the
        lockstep's episodes `rows` (their observations `obs`), from the lockstep's `snapshot` (None after the last
        decision): each episode's action at k chosen by branching in physics (`choose`), as a `c_backend.OpenLoop`
        (one per episode, axis 0)."""
        from gsp_jax.physics import c_backend

        actions = np.zeros((len(rows), n_steps), np.int32)
        if snapshot is not None:
            actions[:, k] = choose(self, spec, snapshot, rows, obs, episodes, k)
        return c_backend.OpenLoop(actions)


def _program(spec: PhysicsSpec, key, make):
    """`jax.jit(make())`, made once per Physics and key (`Physics.kept`)."""
    return spec.kept(key, lambda: jax.jit(make()))


def root_q(spec: PhysicsSpec, root_axis, observe):
    """A jitted program: (root, obs_flat (N, nq + 2 nv), grasp (N,), episodes (N), k) -> (N, A) the root's Q;
    `observe` the C backend's flat-observation reader (`c_backend.programs(...).observe`)."""
    return _program(spec, ("root_q", root_axis), lambda: lambda root, obs_flat, grasp, episodes, k: jax.vmap(
        lambda pol, o, g, e: pol.search(spec.observed_state(o, g, e, k)).q, in_axes=(root_axis, 0, 0, 0))(
        root, observe(obs_flat), grasp, episodes))


def base_action(spec: PhysicsSpec, axis, observe):
    """A jitted program: (base, obs_flat (N, ...), grasp (N,), episodes (N), k) -> (N,) the base's actions."""
    return _program(spec, ("base_action", axis), lambda: lambda base, obs_flat, grasp, episodes, k: jax.vmap(
        lambda pol, o, g, e: jnp.asarray(pol.act(spec.observed_state(o, g, e, k)), jnp.int32),
        in_axes=(axis, 0, 0, 0))(base, observe(obs_flat), grasp, episodes))


PLANNED_STREAM = 86  # the planner's worlds come from fold_in(PRNGKey(world_seed), PLANNED_STREAM)


def planned_worlds(policy: PhysicsLookahead, spec: PhysicsSpec | HasSpec, episodes):
    """The worlds the branches of `episodes` (a batch of E) run in: a `world.World` of E W rows (numpy), episode
    i's w-th at row i W + w, drawn from the policy's gap with a key of `world_seed` and the episode's own values (so
    an episode gets the same worlds in any batch or chunk; kept); None without a gap."""
    from gsp_jax.physics import world as world_lib

    if policy.gap is None:
        return None
    leaves = [np.asarray(x) for x in jax.tree.leaves(jax.device_get(episodes))]
    E, W = int(np.shape(episodes.mass)[0]), policy.worlds
    ids = [zlib.crc32(b"".join(np.ascontiguousarray(x[e]).tobytes() for x in leaves)) for e in range(E)]
    if tuple(ids) not in policy._worlds:
        scene = of(spec).scene
        base = jax.random.fold_in(jax.random.PRNGKey(policy.world_seed), PLANNED_STREAM)
        keys = jnp.stack([jax.random.fold_in(base, i & 0x7FFFFFFF) for i in ids])
        drawn = jax.vmap(lambda k: world_lib.draw(policy.gap, k, W, scene.n_touch, len(scene.hand_dof)))(keys)
        policy._worlds[tuple(ids)] = jax.tree.map(lambda x: np.asarray(x).reshape(E * W, *x.shape[2:]),
                                                  jax.device_get(drawn))
    return policy._worlds[tuple(ids)]


def _world_rows(policy: PhysicsLookahead, spec, episodes, i_, w_):
    """The planned worlds of branches (episode i_, world w_) (index arrays), or None without a gap."""
    from gsp_jax.physics import world as world_lib

    planned = planned_worlds(policy, spec, episodes)
    return None if planned is None else world_lib.rows(planned, np.asarray(i_) * policy.worlds + np.asarray(w_))


def _gather(policy: PhysicsLookahead, b: int, episodes: np.ndarray, slots: int):
    """Base b for the branches of `episodes` (indices into the policy's episode batch), `slots` each
    (episode-major): its per-episode leaves gathered; kept while the branched rows stay the same."""
    base, axis = policy.bases[b]
    if axis is None:
        return base
    key = (b, episodes.tobytes(), slots)
    if key not in policy._gathered:
        idx = jnp.asarray(np.repeat(episodes, slots))
        if len(policy._gathered) >= 4 * len(policy.bases):
            policy._gathered.pop(next(iter(policy._gathered)))
        policy._gathered[key] = jax.tree.map(
            lambda ax, sub: sub if ax is None else jax.tree.map(lambda x: jnp.take(x, idx, 0), sub),
            axis, base, is_leaf=lambda x: x is None)
    return policy._gathered[key]


def choose(policy: PhysicsLookahead, spec: PhysicsSpec, snapshot, rows: np.ndarray, obs: np.ndarray, episodes,
           k: int) -> np.ndarray:
    """(N,) the actions of the episodes `rows` of a lockstep at segment k (its `snapshot`, observations `obs`
    (N, ...), their `episodes`): every candidate branched under every base to the episode's end in C MuJoCo,
    the best branch's first action. An episode whose tool has fallen, or one candidate in all, takes the
    surrogate's best without branching (nothing to choose)."""
    from gsp_jax.physics import c_backend

    t0 = time.perf_counter()
    n, n_base, top, W = len(rows), len(policy.bases), min(policy.k, spec.space.n_actions), policy.n_worlds
    grasp = snapshot.grasp[rows]
    observe = c_backend.programs(spec, episodes).observe
    args = (jnp.asarray(obs), jnp.asarray(grasp), episodes, k)
    q = np.asarray(root_q(spec, policy.root_axis, observe)(policy.root, *args))
    best = np.argsort(-q, axis=1, kind="stable")[:, :top].astype(np.int32)  # (N, top): ties keep the lower action
    cand = np.broadcast_to(best, (n_base, n, top))
    if policy.base_actions and top < spec.space.n_actions:
        own = np.stack([np.asarray(base_action(spec, axis, observe)(base, *args)) for base, axis in policy.bases])
        cand = np.concatenate([cand, own[:, :, None]], 2)  # (B, N, slots)
    slots = cand.shape[2]
    chosen, chosen_base = best[:, 0].copy(), np.full(n, -1)
    fell, err = np.full((n_base, n, slots, W), np.nan), np.full((n_base, n, slots, W), np.nan)
    live = np.flatnonzero(~snapshot.fell[rows]) if n_base * slots > 1 else np.zeros(0, int)
    known, runs, stats = policy._known, 0, {"steps": 0}
    if k == 0:
        known.clear()
    if live.size:
        # a branch whose outcome an earlier branch already gave is not run again: that earlier branch took this
        # episode's actions so far and then this candidate, under the same base (the physics is deterministic)
        past = snapshot.actions[rows, :k]
        todo = [[] for _ in range(n_base)]  # per base: (episode, first action, world) to run
        for b in range(n_base):
            for i in live:
                for s_ in range(slots):
                    a = int(cand[b, i, s_])
                    for w in range(W):
                        got = known.get((int(rows[i]), b, w, tuple(past[i]) + (a,))) if policy.reuse else None
                        if got is not None:
                            fell[b, i, s_, w], err[b, i, s_, w] = got
                        elif (i, a, w) not in todo[b]:
                            todo[b].append((i, a, w))
        runs = sum(len(t) for t in todo)
        tables = _tables(policy, spec, episodes)
        if runs and tables is not None:  # every base reads only its grasp and waypoint: decided in numpy
            outcome = _run_tabled(policy, spec, snapshot, rows, episodes, k, todo, tables, n_base * n * slots * W,
                                  stats)
        elif runs:
            # each base's branches padded to a multiple of a quarter of the episodes' candidates (the branches'
            # programs are compiled per row count: padding repeats a branch; one episode: none)
            quarter = -(-n * slots * W // 4)
            padded = [(t * quarter)[:-(-len(t) // quarter) * quarter] for t in todo]  # a base with none: none
            _warm(policy, spec, snapshot, rows, episodes, k, padded, range(quarter, n * slots * W + 1, quarter))
            outcome = _run_branches(policy, spec, snapshot, rows, episodes, k, padded, stats)
        for b, t in enumerate(todo):
            for r, (i, a, w) in enumerate(t):
                f, e, acts = outcome[b][0][r], outcome[b][1][r], outcome[b][2][r]
                for m in range(k, len(acts)):  # this branch's outcome is every later candidate's on its path
                    known[(int(rows[i]), b, w, tuple(int(x) for x in acts[:m + 1]))] = (f, e)
                fell[b, i, cand[b, i] == a, w], err[b, i, cand[b, i] == a, w] = f, e
        share, mean_err = fell.mean(-1), err.mean(-1)  # over the worlds (one without a gap)
        for i in live:  # held (in most worlds) first, then the least angle error, then the surrogate's Q (then base,
            c = cand[:, i].ravel()  # slot order)
            pick = np.lexsort((-q[i, c], mean_err[:, i].ravel(), share[:, i].ravel()))[0]
            chosen[i], chosen_base[i] = c[pick], pick // slots
    seconds, branched = time.perf_counter() - t0, set(live.tolist())
    if W == 1:
        fell, err = fell[..., 0], err[..., 0]
    for i in range(n):
        b = i in branched
        policy.decisions.append(Decision(int(i), k, np.array(cand[:, i]), q[i], fell[:, i].astype(bool) if b else None,
                                         err[:, i] if b else None, int(chosen[i]), int(chosen_base[i]), seconds, runs,
                                         stats["steps"]))
    return chosen


def _tables(policy: PhysicsLookahead, spec: PhysicsSpec | HasSpec, episodes) -> list | None:
    """Per base, its actions at every grasp and waypoint ((E, G, T) at axis 0, else (1, G, T); kept), if every base
    reads only its grasp and waypoint (`c_backend.action_table`); else None."""
    from gsp_jax.physics import c_backend

    if episodes.n_steps not in policy._tables:
        E, G = int(np.shape(episodes.mass)[0]), of(spec).space.n_grasps
        made = [c_backend.action_table(base, axis, E if axis == 0 else 1, G, episodes.n_steps)
                for base, axis in policy.bases]
        policy._tables[episodes.n_steps] = None if any(t is None for t in made) else made
    return policy._tables[episodes.n_steps]


def _run_tabled(policy: PhysicsLookahead, spec: PhysicsSpec, snapshot, rows: np.ndarray, episodes, k: int, todo, tables,
                most: int, stats, warm_width: int | None = None):
    """`_run_branches` for bases that read only their grasp and waypoint (`tables`, per base (E or 1, G, T)): every
    branch of every base one row of a single group (`c_backend.ActionTable`: its first action at segment k, then
    its base's table), decided in numpy; only a segment where a grasp changes calls JAX (the new link's path).
    The rows are padded to a multiple of an eighth of `most` (the programs are compiled per row count: padding
    repeats a branch) and each count's programs compiled once per process (`warm_width`: a one-segment run of that
    many rows whose grasps all change, to compile them; returns nothing)."""
    from gsp_jax.physics import c_backend

    flat = [(b, i, a, w) for b, t in enumerate(todo) for i, a, w in t]
    step = max(1, most // 8)
    if warm_width is None:
        key = ("tabled-widths", len(rows), most, policy.branch_device)
        done = spec.kept(key, set)
        for w in range(step, -(-most // step) * step + 1, step):
            if w not in done:
                _run_tabled(policy, spec, snapshot, rows, episodes, k, todo, tables, most, {}, warm_width=w)
                done.add(w)
        width = -(-len(flat) // step) * step
    else:
        width = warm_width
    flat = (flat * width)[:width]  # padding repeats branches
    b_, i_, a_, w_ = (np.array(x) for x in zip(*flat))
    table = np.stack([tables[b][i if len(tables[b]) > 1 else 0] for b, i in zip(b_, i_)])  # (R, G, T) a copy
    if warm_width is not None:  # a first action that changes the grasp: the JAX decision runs (and compiles)
        g = snapshot.grasp[rows[i_]]
        a_ = np.argmax(spec.space.transitions[g] != g[:, None], 1).astype(np.int32)
    table[:, :, k] = a_[:, None]
    sub = jax.tree.map(lambda x: np.asarray(x)[i_], episodes)
    result = c_backend.simulate(spec, [(c_backend.ActionTable(table), 0)], [sub], cores=policy.cores,
                                workers=policy.workers, start=snapshot.take(rows[i_]), stats=stats,
                                device=policy.branch_device, until=k + 1 if warm_width else None, outcomes=True,
                                world=_world_rows(policy, spec, episodes, i_, w_))
    if warm_width is not None:
        return None
    fell, err, acts = result[0]
    ends = np.cumsum([len(t) for t in todo])
    return [None if not t else (fell[e - len(t):e], err[e - len(t):e], acts[e - len(t):e])
            for t, e in zip(todo, ends)]


def _warm(policy: PhysicsLookahead, spec: PhysicsSpec, snapshot, rows, episodes, k: int, todo, widths) -> None:
    """Compile, once per process, the branches' programs for every number of branches a decision can run
    (`widths` per base): a decision that first meets a new number would otherwise wait for its compiles (seconds,
    in the tail of the decision times). Each is a one-segment lockstep of the given branches repeated."""
    key = ("branch-widths", len(rows), len(todo), tuple(axis is None for _, axis in policy.bases),
           policy.branch_device)
    done = spec.kept(key, set)
    if all(len(t) == len(todo[0]) for t in todo):
        done.add(len(todo[0]))
    some = next(t for t in todo if t)
    for w in widths:
        if w not in done and k + 1 <= episodes.n_steps:
            _run_branches(policy, spec, snapshot, rows, episodes, k, [((t or some) * w)[:w] for t in todo], {},
                          until=k + 1)
            done.add(w)


def _run_branches(policy: PhysicsLookahead, spec: PhysicsSpec, snapshot, rows: np.ndarray, episodes, k: int, todo,
                  stats, until: int | None = None):
    """Per base b, the branches todo[b] = [(episode, first action, world), ...] (any number, none included) run from
    the snapshot to the episode's end in one C MuJoCo lockstep (each in its planned world: `planned_worlds`): per
    base (fell (R,), angle error (R,), actions (R, T)), None for a base with none; stats["steps"] grows by the
    physics steps taken. `until`: stop there instead and return the lockstep's `Snapshot`."""
    from gsp_jax.physics import c_backend

    bases = [b for b, t in enumerate(todo) if t]  # a base with no branch to run is left out
    idx = [np.array([i for i, _, _ in todo[b]]) for b in bases]  # per base (R_b,) episodes (indices into rows)
    first = [np.array([a for _, a, _ in todo[b]], np.int32) for b in bases]
    worlds = [_world_rows(policy, spec, episodes, idx[g], [w for _, _, w in todo[b]]) for g, b in enumerate(bases)]
    groups = [(FirstThen(first=jnp.asarray(first[g]), at=jnp.int32(k), base=_gather(policy, b, idx[g], 1)),
               FirstThen(first=0, at=None, base=policy.bases[b][1])) for g, b in enumerate(bases)]
    per_base = [jax.tree.map(lambda x, ib=ib: np.asarray(x)[ib], episodes) for ib in idx]
    every = np.concatenate(idx)
    results = c_backend.simulate(spec, groups, per_base, cores=policy.cores, workers=policy.workers,
                                 start=snapshot.take(rows[every]), stats=stats, device=policy.branch_device,
                                 until=until, outcomes=True, world=None if policy.gap is None else worlds)
    if until is not None:
        return results
    out = [None] * len(todo)
    for b, r in zip(bases, results):
        out[b] = r
    return out
