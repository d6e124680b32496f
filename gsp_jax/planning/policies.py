"""One policy interface for every planner: a policy is a pytree with `act(state) -> action` (`protocols.Policy`).

`act` takes one surrogate `State` (continuous state plus episode input) and returns an int32 action; it is
pure, so `jax.jit` and `jax.vmap` apply, and the surrogate evaluation, lookahead and the physics check call every
policy the same way. A policy may read any field of the state except `terms` (the last step's reward terms).

    DP baseline   SequencePolicy(solution of the nominal training episode .actions)   open loop
    DP optimal    TablePolicy(solution of the episode itself .policy)                  closed loop, (grasp, t)
    RL            NetworkPolicy(params, networks, space)                               deterministic PPO actor
    Ll (L1, L2)   Lookahead(base=any of these, model=surrogate, depth=l)               `gsp_jax.planning.lookahead`

A policy's episode in the surrogate `sur`: `rollout.rollout(sur, policy, sur.reset(episode))` (the one walker, a
`Trajectory`; `lookahead.rollout` its return and final state); `rollout_batched` runs the same episode with its
transitions in one batch.
"""
from __future__ import annotations

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.core import files
from gsp_jax.model import hand as hand_lib, load as model_lib, scenario as scenario_lib
from gsp_jax.surrogate import reward as reward_lib
from gsp_jax.surrogate.observation import observation, observation_size
from gsp_jax.model.grasps import GraspSpace
from gsp_jax.planning.lookahead import Lookahead  # re-exported: the Ll policies
from gsp_jax.ppo import networks as nets
from gsp_jax.ppo.checkpoint import load_policy, save_policy
from gsp_jax.ppo.config import PPOConfig
from gsp_jax.model.scenario import Episode
from gsp_jax.surrogate.step import State, Surrogate

__all__ = ["Lookahead", "NetworkPolicy", "SequencePolicy", "TablePolicy", "rollout_batched"]


@struct.dataclass
class TablePolicy:
    """Closed loop over the discrete state: action = table[grasp, t]. DP optimal is this with the DP policy
    solved on the evaluation episode itself."""

    table: jax.Array  # (G, T) int32
    space: GraspSpace | None = struct.field(pytree_node=False, default=None)  # checks the actions if given

    def __post_init__(self):
        _check_concrete(self.table, "TablePolicy.table", self.space)
        if self.space is not None and not isinstance(self.table, jax.core.Tracer) and np.ndim(self.table) == 2 \
                and np.shape(self.table)[0] != self.space.n_grasps:
            raise ValueError(f"TablePolicy.table: {np.shape(self.table)[0]} rows for the model's {self.space.n_grasps} "
                             "grasps (a table of another model?)")

    def act(self, state: State) -> jax.Array:
        return self.table[state.grasp, jnp.minimum(state.t, self.table.shape[1] - 1)]

    def act_table(self, n_grasps: int, n_steps: int) -> np.ndarray:
        """(..., n_grasps, n_steps) int32 numpy: `act` at every grasp and waypoint (it reads nothing else)."""
        table = np.asarray(self.table, np.int32)
        return table[..., np.minimum(np.arange(n_steps), table.shape[-1] - 1)]


@struct.dataclass
class SequencePolicy:
    """Open loop: action = actions[t]. DP baseline is this with the optimal sequence of the nominal training
    episode, replayed on an unseen one."""

    actions: jax.Array  # (T,) int32
    space: GraspSpace | None = struct.field(pytree_node=False, default=None)  # checks the actions if given

    def __post_init__(self):
        _check_concrete(self.actions, "SequencePolicy.actions", self.space)

    def act(self, state: State) -> jax.Array:
        return self.actions[jnp.minimum(state.t, self.actions.shape[0] - 1)]

    def act_table(self, n_grasps: int, n_steps: int) -> np.ndarray:
        """(..., n_grasps, n_steps) int32 numpy: `act` at every grasp and waypoint (it reads nothing else)."""
        actions = np.asarray(self.actions, np.int32)
        actions = actions[..., np.minimum(np.arange(n_steps), actions.shape[-1] - 1)]
        return np.broadcast_to(actions[..., None, :], actions.shape[:-1] + (n_grasps, n_steps))


@struct.dataclass
class NetworkPolicy:
    """A trained actor (RL in the paper), deterministic: the most probable action for the observation of the
    (continuous) state."""

    params: nets.Params
    networks: nets.Networks = struct.field(pytree_node=False)
    space: GraspSpace = struct.field(pytree_node=False)
    reward_scale: float = struct.field(pytree_node=False, default=PPOConfig.reward_scale)  # of the training run

    def act(self, state: State) -> jax.Array:
        return nets.mode(self.networks.logits(self.params, observation(self.space, state)))

    def value(self, state: State) -> jax.Array:
        """The critic's estimate of the return from `state`, in reward units (the lookahead's cut-off value)."""
        return self.networks.value(self.params, observation(self.space, state)) / self.reward_scale


SHIPPED_POLICY = hand_lib.MODELS_DIR / "policies/ppo_dp_seed0"  # PPO with DP pretraining for the wrench, a GPU run
SHIPPED_POLICIES = {  # each shipped model's: `train --model NAME --seeds 1` on a GPU (docs/your-model.md)
    "wrench": SHIPPED_POLICY, "hammer": hand_lib.MODELS_DIR / "policies/hammer_ppo_dp_seed0",
    "allegro": hand_lib.MODELS_DIR / "policies/allegro_ppo_dp_seed0"}
SHIPPED_LEARNED_POLICIES = {  # trained with the model's learned physics term: `train --learned --seeds 1` on a GPU
    "wrench": hand_lib.MODELS_DIR / "policies/ppo_dp_learned"}


def shipped_policy(sur: Surrogate) -> pathlib.Path | None:
    """The PPO policy shipped for the surrogate's model, None if there is none (a model of your own). With the
    learned physics term, the one trained with it (`SHIPPED_LEARNED_POLICIES`) where one ships, else the analytic
    surrogate's."""
    model = model_lib.of_hand(sur.hand) if sur.hand.source else None
    shipped = model_lib.SHIPPED.get(model.name) if model is not None else None
    if shipped is None or model.path != shipped.resolve():
        return None
    learned = SHIPPED_LEARNED_POLICIES.get(model.name) if sur.learned is not None else None
    return learned or SHIPPED_POLICIES.get(model.name)


def load_network_policy(sur: Surrogate, path: str | pathlib.Path | None = None) -> NetworkPolicy:
    """The PPO policy saved at `path` (`ppo.train`'s `policy` folder; default: the one shipped with the package for
    the surrogate's model, `SHIPPED_POLICIES`) as a deterministic `NetworkPolicy` of the surrogate's grasp space,
    with its critic. A policy made for another model (its `<path>.model.json`, written by `save_network_policy`),
    or whose networks do not fit this model's observation and actions, is refused with a `ModelError` naming
    both."""
    model = model_lib.of_hand(sur.hand) if sur.hand.source else None
    if path is None:
        path = shipped_policy(sur)
        if path is None:
            raise FileNotFoundError("load_network_policy: no PPO policy ships for "
                                    f"{model.label if model else 'this model'};"
                                    " train one with `python -m experiments train --model ...` and give its path")
    path = pathlib.Path(path)
    if not path.exists():
        raise FileNotFoundError(f"load_network_policy: path: no PPO policy at {path}")
    made = model_tag(path)
    if made is not None and model is not None and made.get("digest") != model.digest:
        raise model_lib.ModelError(f"policy {path} was trained for model {made.get('name')!r} (digest "
                                   f"{made.get('digest')}), not for {model.label}; train one with "
                                   f"`python -m experiments train --model {model.name}`")
    obs = observation_size(sur.space, scenario_lib.N_WAYPOINTS, sur.hand.n_joints)
    networks = nets.make_networks(obs, sur.n_actions, nets.NetworkConfig())
    try:
        params = load_policy(path, networks)
    except ValueError as e:
        raise model_lib.ModelError(f"policy {path}: its networks do not fit {model.label if model else 'this model'} "
                                   f"(observation {obs}, {sur.n_actions} actions): it was trained for another model "
                                   f"({str(e).splitlines()[0][:200]})") from e
    return NetworkPolicy(params, networks, sur.space)


def model_tag(path: str | pathlib.Path) -> dict | None:
    """The model a saved policy was trained for ({name, digest, n_grasps, n_actions, learned} from
    `<path>.model.json`; `learned`: the learned physics term's `learned.tag`, "" for none), None if untagged."""
    tag = pathlib.Path(path).parent / f"{pathlib.Path(path).name}.model.json"
    return files.read_json(tag) if tag.is_file() else None


def save_network_policy(path: str | pathlib.Path, params: nets.Params, sur: Surrogate) -> None:
    """Write a policy (`ppo.checkpoint.save_policy`) and, beside it, the model it is for (`model_tag`)."""
    save_policy(path, params)
    m = sur.model
    tag = pathlib.Path(path).parent / f"{pathlib.Path(path).name}.model.json"
    files.write_json(tag, {"name": m.name, "digest": m.digest, "n_grasps": sur.space.n_grasps,
                           "n_actions": sur.n_actions, "learned": sur.learned_tag})


def _check_concrete(actions, field: str, space: GraspSpace | None) -> None:
    """Actions given to a policy from Python are checked against the model's action space (`space`; without one,
    that they are non-negative integers); values that JAX passes through when it rebuilds the policy inside a
    transformation are not: see `grasps`."""
    if isinstance(actions, (np.ndarray, jax.Array)) and not isinstance(actions, jax.core.Tracer):
        if space is not None:
            space.check_actions(actions, field)
        else:
            a = np.asarray(actions)
            bad = (a < 0) | (a != np.round(a))
            if np.any(bad):
                raise ValueError(f"{field}: {a[bad].ravel()[0]} is not an action (a non-negative integer)")


def rollout_batched(sur: Surrogate, policy, episode: Episode, ahead: int = 1) -> tuple[jax.Array, State]:
    """`rollout.rollout(sur, policy, sur.reset(episode))` with the transitions off the chain of decisions. From its
    start an episode visits only discrete states (grasp, t), and a step's next grasp follows from its action alone
    (`GraspSpace.apply`), so the grasps a policy visits are known before any reward is: all T transitions (their IK
    and wrench solves) then run as one vmapped batch (`Surrogate.transition`), and the return sums the rewards up to
    the first step that ends the episode (`reward.expected_return`). An open-loop `SequencePolicy` (DP baseline) needs
    nothing more. A closed-loop policy first walks its chain of decisions, which needs each state it acts on realised
    (an IK): `ahead` = k realises, in one batch, every state its next k decisions can reach -- the grasps within j link
    changes of the current one at waypoint t + j, j < k (1, 11, 51, 133 ... states: `GraspSpace.within`) -- so the
    chain is ceil(T / k) batched IKs long instead of T single ones. A GPU runs a small batch in about the time of
    one problem (k = 3: 63 states per batch); a CPU pays for every state (keep k = 1 there: one IK a step more than
    stepping). Realising all n_grasps x T states in one batch is slower on a GPU (docs/lookahead.md).
    For policies that act on a state's grasp, waypoint, joint angles and episode, not on the last step's `terms`
    (a discrete state's are zeros); a `Lookahead` would search from each state, but `lookahead.rollout_planned` reuses
    its search's steps instead. Returns (return, final state); the same episode as stepping, to float32 rounding
    (the batch's solves round in the last bits like a vmap's)."""
    if not isinstance(ahead, (int, np.integer)) or ahead < 1:
        raise ValueError(f"ahead: expected an integer >= 1, got {ahead!r}")
    n_t = episode.n_steps
    ts = jnp.arange(n_t, dtype=jnp.int32)
    start = jnp.asarray(episode.start_grasp, jnp.int32)
    space = sur.space
    if isinstance(policy, SequencePolicy):
        actions = policy.actions[jnp.minimum(ts, policy.actions.shape[0] - 1)]
        _, grasps = jax.lax.scan(lambda g, a: (space.apply(g, a)[0], g), start, actions)
    else:
        sizes = [space.n_within(j) for j in range(ahead)]
        offsets = np.cumsum([0] + sizes[:-1])
        lag = jnp.asarray(np.repeat(np.arange(ahead, dtype=np.int32), sizes))  # (B,) waypoint offset of each state

        def decide(g, t0):  # `ahead` decisions from grasp g at waypoint t0, on one batch of realised states
            reach = jnp.concatenate([space.within(g, j) for j in range(ahead)])
            states = jax.vmap(sur.discrete_state, (None, 0, 0))(episode, reach, jnp.minimum(t0 + lag, n_t - 1))
            h, visited, acts = g, [], []
            for j in range(ahead):
                at = offsets[j] + space.rank_within(g, h)
                a = policy.act(jax.tree.map(lambda x, at=at: x[at], states))
                visited, acts, h = visited + [h], acts + [a], space.apply(h, a)[0]
            return h, (jnp.stack(visited), jnp.stack(acts))

        n_blocks = -(-n_t // ahead)
        _, (grasps, actions) = jax.lax.scan(decide, start, jnp.arange(n_blocks, dtype=jnp.int32) * ahead)
        grasps, actions = grasps.reshape(-1)[:n_t], actions.reshape(-1)[:n_t]
    moved, rewards, ends = sur.transitions(episode, grasps, actions)  # the motor check for the last step only
    alive = jnp.cumsum(ends) - ends == 0  # no earlier step ended the episode
    final = jax.tree.map(lambda x: x[jnp.argmax(ends)], moved)  # the first step that ends it (the last one does)
    risk = None if sur.learned is None else moved.terms.fall_risk
    return reward_lib.expected_return(rewards, risk, alive), final
