"""Beam search over grasp changes: plans for grasp spaces the DP table cannot hold (the paper's future work).

The DP table (`planning.dp`) realises every grasp at every waypoint: G x T IK problems, 288 x 16 for the paper's hand,
but 10^4-10^6 grasps for a hand whose medial links and several options per link count. The search realises only the
grasps it visits. Forwards, one layer per waypoint t, it keeps a beam of at most `width` grasps; it steps each by every
action (a grasp's successors: itself and each one-link change), realises the distinct successors (at waypoint t and
t + 1, one batch of IK solves; a grasp realised at t + 1 in one layer serves as the next layer's "now" contacts) and
scores every transition with the surrogate's own terms (`Surrogate.score`, `reward.of_transitions`,
`Surrogate.with_learned`: the rewards the table would hold, the learned term included). The next beam is the `width`
successors of highest f = (expected) return so far + chance to hold so far x h, one entry per grasp, where the
heuristic h is the return of keeping the grasp to the end at the cost of its step now ((T - t - 1) x the null
action's reward from it, floored at -`max_step_cost`: its per-step cost is persistent along a path, so this ranks
grasps that hold cheaply first). Backwards, the Bellman backup (`reward.backed_up`, expectimax with the learned term)
over the states and transitions the beam kept gives each kept state its exact value within that subgraph, and the plan
is the best path through it: never worse than the best path the forward beam itself found, and, with the beam as
wide as the grasp space, exactly DP's optimum (tests/test_beam.py checks that, a narrow search against the same
search run on the DP table, and the search's rewards against the table's). A forward beam alone is not enough here:
with the learned term a path's worth is its return plus its chance to hold times what follows, so keeping one path
per grasp by the estimate can discard the better one.

Static shapes: every layer realises `expand` successors at waypoint t + 1 and `fresh` at waypoint t (the successors
the layer before did not realise there), padded; successors beyond them (the lowest-ranked parents' last) are left out
and counted (`Found.dropped`). One `lax.scan` over the waypoints forwards, one backwards, jit- and vmap-able over
episodes, so a batch of episodes is one XLA kernel, as the table is.

    found = beam.plan(sur, episode, beam.BeamConfig(width=16))   # Found: actions (T,), grasps, rewards, ret, counts
    found = beam.plan_batch(sur, episodes)                         # a stack of episodes, leaves (N, ...)

Registered as the planner `search` (`planners.registry`), and `search-L1`: L1 lookahead over the search's plan.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.model.grasps import NULL
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate import reward as reward_lib
from gsp_jax.surrogate.step import Surrogate

WIDTH = 16  # the beam's default width: on the evaluation and stress sets of the paper's hand (learned term on) the
# plan equals DP optimal's at 12 and above (docs/search.md)


@dataclasses.dataclass(frozen=True)
class BeamConfig:
    """The search's sizes (static). `width`: grasps kept per waypoint; `expand`: distinct successors realised per
    waypoint (None: `width` x the most successors of one grasp x 2/3, a multiple of 8, at most G); `fresh`: of those,
    realised anew at the current waypoint (None: `expand` // 2)."""

    width: int = WIDTH
    expand: int | None = None
    fresh: int | None = None

    def sizes(self, sur: Surrogate) -> tuple[int, int, int]:
        """(width, expand, fresh) for the surrogate's grasp space, the defaults filled in and checked: each an int,
        `expand` and `fresh` at least one grasp's successors (`Surrogate.every_sizes`), none above G; else a
        ValueError naming the field and the value."""
        n_g, succ = sur.space.n_grasps, sur.every_sizes[1]
        for name in ("width", "expand", "fresh"):
            v = getattr(self, name)
            if v is not None and (not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1):
                raise ValueError(f"BeamConfig.{name}: a positive int, got {v!r}")
        width = min(int(self.width), n_g)
        expand = self.expand if self.expand is not None else -(-width * succ * 2 // 3 // 8) * 8
        expand = min(int(expand), n_g)
        fresh = min(int(self.fresh if self.fresh is not None else max(expand // 2, succ)), expand)
        for name, v in (("expand", expand), ("fresh", fresh)):
            if v < min(succ, n_g):
                raise ValueError(f"BeamConfig.{name}: at least the {succ} successors of one grasp, got {v}")
        return width, expand, fresh


@struct.dataclass
class Found:
    """The search's plan of one episode (vmap adds axes). T waypoints."""

    actions: jax.Array  # (T,) int32: the plan (`grasps.NULL` once it has ended)
    grasps: jax.Array  # (T + 1,) int32: the grasps along it (grasps[0] the start grasp; kept once ended)
    rewards: jax.Array  # (T,) each step's (expected) reward; 0 once ended
    risks: jax.Array  # (T,) each step's learned fall probability (0 without the term, or once ended)
    alive: jax.Array  # (T,) bool: the step is part of the episode
    ret: jax.Array  # () the plan's (expected) return: its value in the searched subgraph
    realised: jax.Array  # () int32: IK problems solved for grasps of the search (the padding left out)
    dropped: jax.Array  # () int32: successors left out because a layer's `expand` or `fresh` was full


def plan(sur: Surrogate, episode: Episode, config: BeamConfig = BeamConfig()) -> Found:
    """The beam search's plan of one episode from its start grasp at waypoint 0 (see the module docstring); a
    concrete episode is checked first (`Surrogate.validate`)."""
    return _plan(sur, sur.validate(episode), config.sizes(sur))


def plan_batch(sur: Surrogate, episodes: Episode, config: BeamConfig = BeamConfig(),
               batch_size: int | None = None) -> Found:
    """`plan` of a stack of episodes (leaves (N, ...)), `batch_size` at a time (`lax.map`: one compilation, bounded
    memory; None: all at once, vmapped). Concrete episodes are checked first."""
    return _plan_batch(sur, sur.validate(episodes), config.sizes(sur), batch_size)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _plan_batch(sur: Surrogate, episodes: Episode, sizes: tuple[int, int, int], batch_size: int | None) -> Found:
    return jax.lax.map(lambda ep: _plan(sur, ep, sizes), episodes, batch_size=batch_size or episodes.mass.shape[0])


@functools.partial(jax.jit, static_argnums=2)
def _plan(sur: Surrogate, episode: Episode, sizes: tuple[int, int, int]) -> Found:
    found = _best_path(_forward(sur, episode, sizes), episode.n_steps)

    def step(g, a_alive):
        a, alive = a_alive
        g = jnp.where(alive, sur.space.apply(g, a)[0], g)
        return g, g

    _, after = jax.lax.scan(step, jnp.asarray(episode.start_grasp, jnp.int32), (found.actions, found.alive))
    return found.replace(grasps=jnp.concatenate([jnp.asarray(episode.start_grasp, jnp.int32)[None], after]))


def _first_distinct(values: jax.Array, ok: jax.Array, size: int, fill: int):
    """The first `size` distinct values of `values` (n,) where `ok`, in their order: (values (size,), ok (size,),
    how many distinct were left out)."""
    n = values.shape[0]
    keyed = jnp.where(ok, values, fill)
    order = jnp.argsort(keyed, stable=True)
    sorted_ = keyed[order]
    first_sorted = jnp.concatenate([jnp.ones(1, bool), sorted_[1:] != sorted_[:-1]])
    first = jnp.zeros(n, bool).at[order].set(first_sorted) & ok
    pos = jnp.nonzero(first, size=size, fill_value=n)[0]
    taken = pos < n
    return jnp.where(taken, values[jnp.minimum(pos, n - 1)], fill), taken, jnp.sum(first) - jnp.sum(taken)


def _lookup(keys: jax.Array, valid: jax.Array, x: jax.Array):
    """(slot, found) of values x (...) among sorted `keys` (K,) whose slots are `valid`."""
    slot = jnp.clip(jnp.searchsorted(keys, x), 0, keys.shape[0] - 1)
    return slot, (keys[slot] == x) & valid[slot]


def _forward(sur: Surrogate, episode: Episode, sizes: tuple[int, int, int]):
    """The forward beam: per waypoint the beam (B,), its transitions' rewards, risks, terminal flags, availability
    and next beam position (B, A), and counts."""
    width, expand, fresh = sizes
    space, cfg = sur.space, sur.reward_config
    n_g, n_a, n_t = space.n_grasps, space.n_actions, episode.n_steps
    actions = jnp.arange(n_a, dtype=jnp.int32)
    wp, quats = episode.waypoints, episode.quats
    fill = jnp.int32(n_g)  # a key after every grasp

    beam0 = jnp.full(width, episode.start_grasp, jnp.int32)
    valid0 = jnp.arange(width) == 0
    zeros_b = jnp.zeros(width, jnp.float32)
    probe = sur.realise(episode.start_grasp, wp[0], quats[0])
    cache0 = jax.tree.map(lambda x: jnp.zeros((expand,) + x.shape, x.dtype), probe)
    carry0 = (beam0, valid0, zeros_b, jnp.ones(width, jnp.float32), jnp.full(expand, fill), jnp.zeros(expand, bool),
              cache0, jnp.int32(0), jnp.int32(0))

    def layer(carry, t):
        beam, valid, acc, reach, c_keys, c_ok, cache, n_real, n_drop = carry
        t_next = jnp.minimum(t + 1, n_t - 1)
        new_grasp, redundant = space.apply(beam[:, None], actions[None, :])  # (B, A)
        changed = new_grasp != beam[:, None]
        shared = space.shared(beam[:, None], actions[None, :])
        # the distinct successors, best parents first (the beam is in order of f); then those not realised at t yet
        succ, succ_ok, lost = _first_distinct(new_grasp.reshape(-1), jnp.repeat(valid, n_a), expand, fill)
        c_slot, in_cache = _lookup(c_keys, c_ok, succ)
        need = succ_ok & ~in_cache
        f_pos = jnp.nonzero(need, size=fresh, fill_value=expand)[0]
        f_ok = f_pos < expand
        f_grasp = jnp.where(f_ok, succ[jnp.minimum(f_pos, expand - 1)], episode.start_grasp)
        f_index = jnp.zeros(expand, jnp.int32).at[f_pos].set(jnp.arange(fresh, dtype=jnp.int32), mode="drop")
        have = succ_ok & (in_cache | jnp.zeros(expand, bool).at[f_pos].set(True, mode="drop"))
        # one batch of IK: the fresh ones at waypoint t, every successor at t + 1
        grasps_in = jnp.concatenate([f_grasp, jnp.where(succ_ok, succ, episode.start_grasp)])
        pos_in = jnp.concatenate([jnp.broadcast_to(wp[t], (fresh, 3)), jnp.broadcast_to(wp[t_next], (expand, 3))])
        quat_in = jnp.concatenate([jnp.broadcast_to(quats[t], (fresh, 4)),
                                   jnp.broadcast_to(quats[t_next], (expand, 4))])
        realised = sur.realise_many(grasps_in, pos_in, quat_in)
        now = jax.tree.map(lambda c, r: jnp.where(_col(in_cache, c), c[c_slot], r[f_index]), cache, realised)
        nxt = jax.tree.map(lambda r: r[fresh:], realised)
        arrived = jax.vmap(lambda a, b: sur.score(episode, t, wp[t], quats[t], a, b, False))(now, nxt)
        # sorted by grasp for lookups
        order = jnp.argsort(jnp.where(have, succ, fill))
        keys, have_s = jnp.where(have, succ, fill)[order], have[order]
        arrived = jax.tree.map(lambda x: x[order][:, None], arrived)  # (K, 1, ...): one waypoint
        n_slot, n_found = _lookup(keys, have_s, new_grasp)
        s_slot, s_found = _lookup(keys, have_s, shared)
        usable = valid[:, None] & n_found & s_found
        terms = reward_lib.of_transitions(cfg, arrived, n_slot, redundant, changed, s_slot, t[None])
        terms = sur.with_learned(episode, t, new_grasp, changed, jax.tree.map(lambda x: x[:, :, 0], terms))
        reward, risk = terms.reward, terms.fall_risk
        terminal = terms.collision | terms.fall | (t >= n_t - 1)
        # the heuristic: keep each successor to the end at its step's cost now
        k_range = jnp.arange(expand, dtype=jnp.int32)
        null = reward_lib.of_transitions(cfg, arrived, k_range, jnp.zeros(expand, bool), jnp.zeros(expand, bool),
                                         k_range, t[None])
        null = sur.with_learned(episode, t, keys, False, jax.tree.map(lambda x: x[:, 0], null))
        h = (n_t - t - 1).astype(jnp.float32) * jnp.maximum(null.reward, -cfg.max_step_cost)
        # the next beam: per successor its best parent by f, then the `width` best successors
        acc2 = acc[:, None] + reach[:, None] * reward
        reach2 = reach[:, None] * reward_lib.chance_to_hold(risk)
        f = jnp.where(usable & ~terminal, acc2 + reach2 * h[n_slot], -jnp.inf).reshape(-1)
        slot_flat = n_slot.reshape(-1)
        best = jax.ops.segment_max(f, slot_flat, num_segments=expand)
        index = jnp.arange(f.shape[0], dtype=jnp.int32)
        pick = jax.ops.segment_min(jnp.where(f == best[slot_flat], index, f.shape[0]), slot_flat,
                                   num_segments=expand)
        top, slots = jax.lax.top_k(best, width)
        kept = jnp.isfinite(top)
        chosen = jnp.minimum(pick[slots], f.shape[0] - 1)
        beam_n = jnp.where(kept, keys[slots], episode.start_grasp)
        position = jnp.full(expand, -1, jnp.int32).at[slots].set(jnp.where(kept, jnp.arange(width), -1))
        next_pos = jnp.where(usable & ~terminal, position[n_slot], -1)
        # the contacts at t + 1 serve the next layer's "now"
        c_order = jnp.argsort(jnp.where(succ_ok, succ, fill))
        cache_n = jax.tree.map(lambda x: x[c_order], nxt)
        n_real = n_real + jnp.sum(f_ok) + jnp.sum(succ_ok)
        n_drop = n_drop + lost + jnp.sum(need) - jnp.sum(f_ok)
        out = (beam, valid, reward, risk, terminal, usable, next_pos)
        carry = (beam_n, kept, jnp.where(kept, acc2.reshape(-1)[chosen], 0.0),
                 jnp.where(kept, reach2.reshape(-1)[chosen], 0.0), jnp.where(succ_ok, succ, fill)[c_order],
                 succ_ok[c_order], cache_n, n_real, n_drop)
        return carry, out

    carry, per_layer = jax.lax.scan(layer, carry0, jnp.arange(n_t, dtype=jnp.int32))
    return per_layer, carry[-2], carry[-1]


def _col(mask: jax.Array, like: jax.Array) -> jax.Array:
    """`mask` (K,) shaped to broadcast against `like` (K, ...)."""
    return mask.reshape(mask.shape + (1,) * (like.ndim - 1))


def _best_path(layers, n_t: int) -> Found:
    """The Bellman backup over the kept states and transitions (backwards), then the best path from the start."""
    (beam, valid, reward, risk, terminal, usable, next_pos), n_real, n_drop = layers

    def back(v_next, k):
        into = v_next[jnp.maximum(next_pos[k], 0)]
        q = reward_lib.backed_up(reward[k], risk[k], terminal[k], into)
        q = jnp.where(usable[k] & (terminal[k] | (next_pos[k] >= 0)) & valid[k][:, None], q, -jnp.inf)
        return jnp.max(q, axis=1), (jnp.max(q, axis=1), jnp.argmax(q, axis=1).astype(jnp.int32))

    width = beam.shape[1]
    _, (value, policy) = jax.lax.scan(back, jnp.full(width, -jnp.inf), jnp.arange(n_t), reverse=True)

    def walk(carry, k):
        pos, alive = carry
        a = jnp.where(alive, policy[k, pos], NULL)
        r = jnp.where(alive, reward[k, pos, a], 0.0)
        p = jnp.where(alive, risk[k, pos, a], 0.0)
        ends = terminal[k, pos, a]
        return (jnp.where(alive & ~ends, next_pos[k, pos, a], pos), alive & ~ends), (a, r, p, alive)

    _, (acts, rewards, risks, alive) = jax.lax.scan(walk, (jnp.int32(0), jnp.array(True)), jnp.arange(n_t))
    return Found(actions=acts, grasps=jnp.zeros(n_t + 1, jnp.int32), rewards=rewards, risks=risks, alive=alive,
                 ret=value[0, 0], realised=n_real, dropped=n_drop)
