"""Planning one unseen episode online, in one jitted call: the form the paper's Table 1 times.

    plan = online.episode_planner(ctx, "L1")  # episode -> return, the episode's table built inside the call
    ret = jax.jit(plan)(episode)

DP optimal builds the episode's table, backs it up and runs its policy in it; L1 and L2 search in the episode's
table (`lookahead="table"`: exact from the episode's start, whose discrete states are the table's), below the root
only (`"cached"`) or in the surrogate alone (`"continuous"`); DP baseline and RL act per step, their transitions
stepped after each decision or realised afterwards in one batch (`batched`, `ahead`).
"""
from __future__ import annotations

import jax

from gsp_jax.planning import dp, lookahead as lookahead_lib, policies, rollout as rollout_lib
from gsp_jax.planners import registry as planners
from gsp_jax.planning.dp import TableModel

GPU_AHEAD = 4  # RL's decisions per batch of realised states on a GPU (`policies.rollout_batched`'s `ahead`): a batch
# realises, for each of the next k decisions j < k, the grasps within j link changes (196 states at k = 4); the
# fastest k measured, the same episodes at every k (docs/lookahead.md)


BATCHED = ("dp-base", "rl")  # the policies whose episode can also run as one batch of transitions
LOOKAHEAD = ("table", "cached", "continuous")  # L1 and L2: root and interior in the table; interior only; neither


def default_batched(name: str) -> bool:
    """Whether `plan` batches policy `name`'s transitions by default: DP baseline always, RL on a GPU."""
    return name == "dp-base" or (name == "rl" and jax.default_backend() == "gpu")


def default_ahead() -> int:
    """Batched RL's decisions per batch of realised states: `GPU_AHEAD` on a GPU, 1 on a CPU."""
    return GPU_AHEAD if jax.default_backend() == "gpu" else 1


def episode_planner(ctx, name: str, lookahead: str = "table", batched: bool | None = None, ahead: int | None = None):
    """episode -> return for policy `name`, planned online on the surrogate. L1 and L2 (`lookahead`): "table" builds the
    unseen episode's table (as DP optimal does) and searches in it, root included: from its start the surrogate visits
    only the table's discrete states, so the root's children are the table's (exact, as for DP optimal); "cached" steps
    the root's actions in the surrogate and looks up below the root; "continuous" runs the whole search in the
    surrogate. With `batched`, DP baseline and RL run their decisions first and then all the episode's transitions as
    one vmapped batch (`policies.rollout_batched`), instead of stepping the surrogate after each decision: on a GPU a
    step's cost is its chain of dependent solves, not its arithmetic, so T steps in one batch cost about one. DP
    baseline's open-loop sequence needs no more work batched; RL's decisions each realise their state first (one IK a
    step more, a chain of T IKs left on the critical path), which a CPU, where a batch costs what its problems cost,
    pays in full; `ahead` (default `default_ahead`) realises the states of that many decisions in one batch, shortening
    the chain to T / ahead batched IKs. Default (`default_batched`): batched for DP baseline, and for RL on a GPU."""
    if lookahead not in LOOKAHEAD:
        raise ValueError(f"lookahead: one of {LOOKAHEAD}, got {lookahead!r}")
    sur = ctx.surrogate
    if batched is None:
        batched = default_batched(name)
    if name == "dp-opt":  # solve the unseen episode's whole table, then run its policy in that table
        def episode(ep):
            table, sol = dp.solve(sur, ep)
            model = TableModel(table, sur.space)  # from its start the surrogate only visits the table's states
            return rollout_lib.rollout(model, policies.TablePolicy(sol.policy), model.reset(ep)).ret
        return episode
    policy, _ = planners.make(ctx, name, dict(cached=False))
    if isinstance(policy, policies.Lookahead):  # each decision's search has stepped every action: the episode moves on
        def episode(ep):                    # to its child (`rollout_planned`) instead of stepping the surrogate again
            if lookahead == "continuous":
                return lookahead_lib.rollout_planned(policy, sur.reset(ep))[0]
            model = TableModel(dp.build_table(sur, ep), sur.space)  # the unseen episode's table, inside the timed call
            if lookahead == "table":
                return lookahead_lib.rollout_planned(policy.replace(model=model, inner=model), model.reset(ep))[0]
            return lookahead_lib.rollout_planned(policy.replace(inner=model), sur.reset(ep))[0]
        return episode
    if batched and name in BATCHED:
        ahead = default_ahead() if ahead is None else ahead
        return lambda ep: policies.rollout_batched(sur, policy, ep, ahead)[0]
    return lambda ep: rollout_lib.rollout(sur, policy, sur.reset(ep)).ret


