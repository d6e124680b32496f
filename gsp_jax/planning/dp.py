"""Exact DP over the discretised surrogate (the paper's Algorithm 1, Bellman backups).

Discrete state: (grasp g, waypoint t) with the tool exactly on waypoint t and every grasp realised by IK from
the fixed start configuration (the paper's Sec. IV-C). A step's reward depends on the previous grasp g only
through the redundant-action flag and the change term, which is the moving-wrench term of the *shared* grasp
(g without the link that moves: itself a grasp, realised at waypoint t); everything else is a function of the
new grasp g' and t. So the table

    reward[g, a, t], next_grasp[g, a], terminal[g, a, t]        (G x A x T = 288 x 17 x 16 for the paper's hand)

costs G x T distinct IK solves (4,608: each grasp at each waypoint, shared by the step that arrives there, the
step that leaves and the changes it holds the tool through), G x T x 3 wrench solves, and no per-(g, a) physics
at all -- against the paper's G x A x T = 78,336 environment steps (`Surrogate.step`). The reward is
`gsp_jax.surrogate.reward`'s, as in the step, and the surrogate gives every term: the arrival terms of each (g', t)
(`Surrogate.arrival_terms`), then each transition's (`Surrogate.every_transition`); this module only tabulates
them. Every action is applicable in every grasp (the null action keeps it, the others set one link), so no
transition is unreachable; a transition that collides or drops the tool gets R_MIN and ends the episode
(`terminal`), as do all transitions of the last step.

All functions take one episode; `jax.vmap` them over a batch (`scenario.stack`), episodes leading.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from gsp_jax.surrogate import protocols, reward as reward_lib
from gsp_jax.model.grasps import NULL, GraspSpace
from gsp_jax.surrogate.reward import RewardTerms
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import Contacts, State, Surrogate


@struct.dataclass
class Table:
    """The discretised problem of one episode. G grasps, A actions, T steps."""

    reward: jax.Array  # (G, A, T) reward of action a from grasp g at waypoint t
    next_grasp: jax.Array  # (G, A) int32 grasp after action a (independent of t)
    terminal: jax.Array  # (G, A, T) bool, the transition ends the episode (collision, fall, or last step)
    ik_error: jax.Array  # (G, T) IK error of each grasp realised at each waypoint [m] (for inspection)
    q: jax.Array  # (G, T, J) joint angles of each grasp realised at each waypoint (the discrete states' q)
    fall_risk: jax.Array | None = None  # (G, A, T) the learned physics term's fall probability of each transition
    # (`reward.RewardTerms.fall_risk`: what follows counts with `reward.chance_to_hold`); None without the term


@struct.dataclass
class Solution:
    """Bellman backup of a `Table` and the optimal sequence from the episode's start grasp."""

    value: jax.Array  # (G, T + 1) optimal reward-to-go of (grasp, waypoint); value[:, T] = 0
    policy: jax.Array  # (G, T) int32 optimal action
    actions: jax.Array  # (T,) int32 optimal actions from the start grasp (after the episode ended: ignored)
    grasps: jax.Array  # (T + 1,) int32 grasps along the optimal sequence (grasps[0] = start grasp)
    rewards: jax.Array  # (T,) rewards along it (0 after the episode ended; with the learned term expected rewards,
    # whose `reward.expected_return` is `ret`)
    alive: jax.Array  # (T,) bool, step t is part of the episode (the sequence has not ended before it)
    ret: jax.Array  # () optimal return from the start grasp = value[start, 0]


def build_table(sur: Surrogate, episode: Episode) -> Table:
    """The reward/transition table of one episode from G x T IK solves (see the module docstring): the surrogate's
    terms of every transition (`Surrogate.realise_every`, `arrival_terms`, `every_transition`), tabulated. A
    concrete episode is checked first (`Surrogate.check`)."""
    episode = sur.validate(episode)
    contacts = sur.realise_every(episode)
    return table_from_terms(sur, episode, sur.arrival_terms(episode, contacts), contacts)


def realise_all(sur: Surrogate, episode: Episode) -> Contacts:
    """`sur.realise_every(episode)`: every grasp realised at every waypoint, leaves (G, T, ...) (kept for
    `physics.calibration`, which builds candidates' tables from one set of contacts)."""
    return sur.realise_every(episode)


def grasp_terms(sur: Surrogate, episode: Episode, contacts: Contacts) -> RewardTerms:
    """`sur.arrival_terms(episode, contacts)`: the terms (G', T) of arriving in each grasp from each waypoint (kept
    for `physics.calibration`)."""
    return sur.arrival_terms(episode, contacts)


def table_from_terms(sur: Surrogate, episode: Episode, plain: RewardTerms, contacts: Contacts) -> Table:
    """The table from the arrival terms of every grasp (`Surrogate.arrival_terms`) and the contacts they were
    scored from: each transition's terms from the surrogate (`Surrogate.every_transition`), the step that ends the
    episode (a collision, a fall, the last waypoint) marked terminal."""
    n_t = episode.n_steps
    next_grasp, terms = sur.every_transition(episode, plain)  # (G, A), (G, A, T)
    terminal = terms.collision | terms.fall | (jnp.arange(n_t, dtype=jnp.int32) == n_t - 1)[None, None, :]
    return Table(reward=terms.reward, next_grasp=next_grasp, terminal=terminal, ik_error=contacts.ik.error,
                 q=contacts.ik.q, fall_risk=None if sur.learned is None else terms.fall_risk)


def build_tables(sur: Surrogate, episodes: Episode, batch_size: int | None = None) -> Table:
    """Tables of a stacked episode set (leaves (N, ...)), `batch_size` episodes at a time (`lax.map`: one
    compilation, bounded memory; None = all at once). Concrete episodes are checked first (`Surrogate.check`)."""
    episodes = sur.validate(episodes)
    return jax.lax.map(lambda ep: build_table(sur, ep), episodes, batch_size=batch_size)


def backup(table: Table, start_grasp: jax.Array) -> Solution:
    """Bellman backups backwards in time (`lax.scan`), vectorised over grasps (with the learned term, expectimax:
    `reward.backed_up`); then the optimal sequence."""
    n_g, _, n_t = table.reward.shape

    def back(v_next, t):
        risk = None if table.fall_risk is None else table.fall_risk[:, :, t]
        q = reward_lib.backed_up(table.reward[:, :, t], risk, table.terminal[:, :, t], v_next[table.next_grasp])
        return jnp.max(q, axis=1), (jnp.max(q, axis=1), jnp.argmax(q, axis=1).astype(jnp.int32))

    _, (values, policy) = jax.lax.scan(back, jnp.zeros(n_g, table.reward.dtype), jnp.arange(n_t), reverse=True)
    value = jnp.concatenate([values.T, jnp.zeros((n_g, 1), values.dtype)], axis=1)  # (G, T + 1)
    policy = policy.T  # (G, T)

    start = jnp.asarray(start_grasp, jnp.int32)
    actions, grasps, rewards, _, alive = _replay(table, start, lambda g, t: policy[g, t])
    return Solution(
        value=value,
        policy=policy,
        actions=actions,
        grasps=jnp.concatenate([start[None], grasps]),
        rewards=rewards,
        alive=alive,
        ret=value[start, 0],
    )


def longest_surviving(table: Table, start_grasp: jax.Array, r_min: float) -> Solution:
    """The sequence that holds the tool longest (most steps before one whose reward is `r_min` or less), from the
    start grasp: where every sequence fails (the optimum's return is `r_min`), the optimum fails at once (a failure
    ends the costs), while this one shows where the tool is lost at the latest and why (`Surrogate.explain`)."""
    survived = (table.reward > r_min).astype(table.reward.dtype)
    return backup(table.replace(reward=survived, fall_risk=None), start_grasp)


def solve(sur: Surrogate, episode: Episode) -> tuple[Table, Solution]:
    """Table + backup for one episode (`vmap` it for a batch)."""
    table = build_table(sur, episode)
    return table, backup(table, episode.start_grasp)


def _replay(table: Table, start: jax.Array, choose):
    """Walk the table from grasp `start` with action = choose(grasp, t): actions (T,), grasps after each step
    (T,), rewards (T,; 0 once ended), fall risks (T,; 0 without the learned term) and alive (T,). The grasp stays
    put after the episode ended."""

    def step(carry, t):
        g, alive = carry
        a = choose(g, t)
        r = jnp.where(alive, table.reward[g, a, t], 0.0)
        p = jnp.zeros((), table.reward.dtype) if table.fall_risk is None else table.fall_risk[g, a, t]
        g_next = jnp.where(alive, table.next_grasp[g, a], g)
        return (g_next, alive & ~table.terminal[g, a, t]), (a, g_next, r, p, alive)

    _, out = jax.lax.scan(step, (start, jnp.array(True)), jnp.arange(table.reward.shape[2]))
    return out


def sequence_return(table: Table, start_grasp: jax.Array, actions: jax.Array) -> jax.Array:
    """(Expected) return of an open-loop action sequence (T,) replayed in a table from `start_grasp` (the DP
    baseline: a sequence solved on one episode, scored on another; `reward.expected_return`)."""
    _, _, rewards, risk, alive = _replay(table, jnp.asarray(start_grasp, jnp.int32), lambda g, t: actions[t])
    return reward_lib.expected_return(rewards, None if table.fall_risk is None else risk, alive)


def sequence_scores(table: Table, start_grasp: jax.Array, actions: jax.Array):
    """(rewards (T,), expected return (), predicted chance to hold ()) of an open-loop action sequence (T,) replayed
    once in a table from `start_grasp`: `sequence_rewards`, `sequence_return`, and the product over the steps it
    reached of (1 - fall risk), 1 without the learned term (meaningful for a sequence no step of which ends it)."""
    _, _, rewards, risk, alive = _replay(table, jnp.asarray(start_grasp, jnp.int32), lambda g, t: actions[t])
    return rewards, reward_lib.expected_return(rewards, risk, alive), reward_lib.held_through(risk, alive)


def sequence_rewards(table: Table, start_grasp: jax.Array, actions: jax.Array) -> jax.Array:
    """Rewards (T,) of an open-loop action sequence (T,) replayed in a table from `start_grasp`; a step the
    surrogate calls a fall or a collision has reward <= the table's R_min."""
    _, _, rewards, _, _ = _replay(table, jnp.asarray(start_grasp, jnp.int32), lambda g, t: actions[t])
    return rewards


def random_sequence(table: Table, start_grasp: jax.Array, key: jax.Array, r_min: float, hold: float = 0.0) -> jax.Array:
    """A random feasible action sequence (T,) int32: at every step, with probability `hold` the null action (keep
    the grasp) if it does not fail, otherwise an action drawn uniformly from those that do not fail (reward >
    r_min) from the current grasp (from all actions when every one fails). Sequences for probing the surrogate
    against the physics beyond the DP policies; `hold` > 0 gives fewer grasp changes."""
    keys = jax.random.split(key, 2 * table.reward.shape[2]).reshape(-1, 2, 2)

    def choose(g, t):
        ok = table.reward[g, :, t] > r_min
        ok = ok | ~jnp.any(ok)
        stay = jax.random.bernoulli(keys[t, 0], hold) & ok[NULL]
        logits = jnp.where(ok, 0.0, -jnp.inf)
        drawn = jax.random.categorical(keys[t, 1], logits)
        return jnp.where(stay, NULL, drawn).astype(jnp.int32)

    actions, _, _, _, _ = _replay(table, jnp.asarray(start_grasp, jnp.int32), choose)
    return actions


# ------------------------------------------------------------------------ one episode's table as a step model
def table_state(episode: Episode, table: Table, grasp: jax.Array, t: jax.Array) -> State:
    """`Surrogate.discrete_state(episode, grasp, t)` read from the episode's table (no IK). t may be T (over)."""
    n_t = episode.n_steps
    t = jnp.asarray(t, jnp.int32)
    tc = jnp.minimum(t, n_t - 1)
    pos = episode.waypoints[tc]
    prev = episode.waypoints[jnp.clip(t - 1, 0, n_t - 1)]
    return State(
        grasp=jnp.asarray(grasp, jnp.int32),
        t=t,
        q=table.q[grasp, tc],
        tool_pos=pos,
        tool_quat=episode.quats[tc],
        tool_vel=jnp.concatenate([(pos - prev) / episode.dt, jnp.zeros(3, jnp.float32)]),
        episode=episode,
        done=jnp.array(False),
        terms=RewardTerms.zeros(),
    )


def table_step(table: Table, state: State, action: jax.Array) -> tuple[State, jax.Array, jax.Array]:
    """`Surrogate.step` for a discrete state, read from the episode's table. Absorbing once done."""
    n_t = state.episode.n_steps
    tc = jnp.minimum(state.t, n_t - 1)
    g_next = table.next_grasp[state.grasp, action]
    reward = table.reward[state.grasp, action, tc]
    risk = jnp.zeros((), reward.dtype) if table.fall_risk is None else table.fall_risk[state.grasp, action, tc]
    moved = table_state(state.episode, table, g_next, state.t + 1)
    moved = moved.replace(done=table.terminal[state.grasp, action, tc],
                          terms=RewardTerms.zeros().replace(reward=reward, fall_risk=risk))
    out = jax.tree.map(lambda old, new: jnp.where(state.done, old, new), state, moved)
    return out, jnp.where(state.done, 0.0, reward), out.done


@struct.dataclass
class TableModel:
    """One episode's DP table as a step model (`protocols.StepModel`, like the `Surrogate`): exact for the discrete
    states the surrogate visits from `reset`, with lookups instead of IK and wrench solves. For lookahead over an
    episode whose table is already built (evaluation), or built when the episode is revealed (`planners.online`)."""

    table: Table  # one episode's table (no leading batch axis)
    space: GraspSpace = struct.field(pytree_node=False)

    def step(self, state: State, action: jax.Array) -> tuple[State, jax.Array, jax.Array]:
        return table_step(self.table, state, self.space.checked(action))

    def step_every(self, state: State) -> tuple[State, jax.Array, jax.Array]:
        """`step` of every action at once (leading axis A): the lookups vmapped (`protocols.step_each`)."""
        return protocols.step_each(self, state)

    def reset(self, episode: Episode) -> State:
        return table_state(episode, self.table, episode.start_grasp, 0)
