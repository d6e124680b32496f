"""What the evaluation experiments share: the unseen episodes, their DP tables, and the five policies of the paper
behind one interface (`act(state)`), built the same way for the surrogate evaluation (Fig. 4a), the physics check
(Fig. 4b) and the timing (Table 1).

    ctx = evaluation.context("eval", n_episodes=None)      # 27 evaluation episodes, tables, DP solutions, RL
    policy, axis = evaluation.make(ctx, "L2")               # axis: 0 if the policy differs per episode, else None
"""
from __future__ import annotations

import dataclasses
import hashlib
import pathlib

import jax
import numpy as np

from experiments.common import dp_tables, nominal_actions
from gsp_jax import dp, env as env_lib, hand, policies, scenario
from gsp_jax.surrogate import Surrogate

POLICIES = ("dp-base", "rl", "L1", "L2", "dp-opt")  # the paper's order (Table 1)
LOOKAHEAD_DEPTH = {"L1": 1, "L2": 2}
TRAINED_POLICY = pathlib.Path("results/train/dp/seed0/policy")  # what `python -m experiments train` writes
ROOT = pathlib.Path(__file__).resolve().parents[1]
SHIPPED_POLICY = policies.SHIPPED_POLICY  # a copy of results/train/dp/seed0/policy of a full GPU run
PAPER = dict(  # the paper's numbers, printed beside ours
    table1_s={"dp-base": 1.34, "rl": 1.23, "L1": 2.68, "L2": 4.30, "dp-opt": 151.79},
    table1_machine="32-core Xeon Silver 4216, 2.1 GHz",
)


@dataclasses.dataclass
class Context:
    surrogate: Surrogate
    set_name: str
    names: list[str]  # episode names
    batch: object  # stacked Episode (N, ...)
    tables: dp.Table  # stacked (N, ...), the episodes' DP tables
    solutions: dp.Solution  # stacked, DP optimal per episode
    nominal_actions: jax.Array  # (T,) the DP baseline: the nominal training episode's optimal sequence
    rl: policies.NetworkPolicy  # the PPO actor (deterministic), with its critic
    rl_source: str  # where the RL policy was read from

    def take(self, n: int | None) -> "Context":
        """The same context on `n` of its episodes, spread evenly (as `subset`): no new tables."""
        if n is None or n >= len(self.names):
            return self
        keep = spread(len(self.names), n)
        pick = lambda tree: jax.tree.map(lambda x: x[keep], tree)  # noqa: E731
        return dataclasses.replace(self, names=[self.names[i] for i in keep], batch=pick(self.batch),
                                   tables=pick(self.tables), solutions=pick(self.solutions))


def fingerprint(ctx: Context) -> str:
    """Hash of what a saved result depends on: the library and model sources, the episodes, the RL parameters."""
    h = hashlib.sha256()
    package = pathlib.Path(hand.__file__).parent
    sources = [*package.glob("**/*.py"), *hand.MODELS_DIR.glob("*.xml")]
    sources += [ROOT / "experiments" / f for f in ("evaluation.py", "physics.py", "fig4b.py")]
    for path in sorted(sources):
        h.update(path.read_bytes())
    h.update(repr(ctx.names).encode())
    for leaf in jax.tree.leaves(ctx.rl.params):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()[:16]


def spread(total: int, n: int) -> np.ndarray:
    """Indices of `n` of `total` items spread evenly, first and last included."""
    if n < 1:
        raise ValueError(f"episodes: need at least 1, got {n}")
    return np.unique(np.linspace(0, total - 1, n).round().astype(int))


def subset(episodes: dict, n: int | None) -> dict:
    """`n` episodes spread evenly over the set (both evaluation sets stay represented); all if n is None."""
    if n is None or n >= len(episodes):
        return episodes
    keep = spread(len(episodes), n)
    items = list(episodes.items())
    return dict(items[i] for i in keep)


def load_rl(sur: Surrogate, policy_dir: str | pathlib.Path | None = None) -> tuple[policies.NetworkPolicy, str]:
    """The PPO policy: `policy_dir` if given, else the one `train` wrote (results/train/dp/seed0), else the shipped
    copy under models/policies/ (`policies.load_network_policy`); and where it was read from."""
    candidates = [pathlib.Path(policy_dir)] if policy_dir else [TRAINED_POLICY, SHIPPED_POLICY]
    for path in candidates:
        if path.exists():
            shown = path.resolve().relative_to(ROOT) if path.resolve().is_relative_to(ROOT) else path
            return policies.load_network_policy(sur, path), str(shown)
    raise FileNotFoundError(
        f"policy_dir: no PPO policy at {', '.join(map(str, candidates))}; run `python -m experiments train --seeds 1`"
    )


def context(set_name: str = "eval", n_episodes: int | None = None, policy_dir=None) -> Context:
    sur = Surrogate()
    everything = scenario.episode_set(set_name)
    episodes = subset(everything, n_episodes)
    tag = set_name if len(episodes) == len(everything) else f"{set_name}{len(episodes)}"
    tables = dp_tables(sur, tag, episodes)
    batch = scenario.stack(list(episodes.values()))
    solutions = jax.jit(jax.vmap(dp.backup))(tables, batch.start_grasp)
    rl, source = load_rl(sur, policy_dir)
    return Context(sur, set_name, list(episodes), batch, tables, solutions, nominal_actions(sur), rl, source)


def add_lookahead_argument(p) -> None:
    p.add_argument("--lookahead", default="cached", choices=["cached", "continuous"],
                   help="L1/L2 below the root: the episode's table (exact, default) or the surrogate")


def make(ctx: Context, name: str, model=None, cached: bool = True):
    """(policy, policy_axis) of one of `POLICIES` for the context's episode batch. Lookahead steps its root in
    `model` (default: the surrogate itself, which acts from any continuous state) and, with `cached`, runs the
    tree's interior and its rollouts as lookups in each episode's table (`inner`; exact, as every state below the
    root is discrete; policy_axis is then a `Lookahead` of in_axes, 0 for the tables); without, all in `model`."""
    if name == "dp-base":
        return policies.SequencePolicy(ctx.nominal_actions), None
    if name == "dp-opt":
        return policies.TablePolicy(ctx.solutions.policy), 0
    if name == "rl":
        return ctx.rl, None
    if name in LOOKAHEAD_DEPTH:
        depth = LOOKAHEAD_DEPTH[name]
        if not cached:
            return policies.Lookahead(ctx.rl, model or ctx.surrogate, depth=depth), None
        inner = env_lib.TableModel(ctx.tables, ctx.surrogate.space)
        return (policies.Lookahead(ctx.rl, model or ctx.surrogate, depth=depth, inner=inner),
                policies.Lookahead(None, None, depth=depth, inner=0))
    raise ValueError(f"policy: expected one of {POLICIES}, got {name!r}")
