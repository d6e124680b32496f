"""What the planners of a batch of unseen episodes are built from (`Context`: the episodes, their DP tables, the PPO
policy, the DP baseline), and the library's planners, registered by name in `gsp_jax.planners.registry`: the paper's
five (DP baseline, RL, L1, L2, DP optimal), the physics check's references (fixed grasp sequences, random feasible ones)
and L1-physics, built the same way for Fig. 4a, Fig. 4b, `envelope` and Table 1.

    ctx = evaluation.context("eval")                  # 27 evaluation episodes, their DP tables, the PPO policy
    policy, axis = planners.make(ctx, "L2")           # axis: 0 if the policy differs per episode, else None
    res = physics.Physics(ctx.surrogate).simulate(policy, ctx.batch, policy_axis=axis, backend="c")
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import pathlib
import time
import warnings
import zipfile

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.core import distributed, files
from gsp_jax.planning import dp, policies
from gsp_jax.model import grasps, load as model_lib, scenario
from gsp_jax.surrogate.step import Surrogate

L1_PHYSICS = dict(k=2, bases=("four-tips", "dp-opt"))  # its defaults: L1's 2 best and each base's own action,
# under the constant four-tip grasp and DP optimal (never worse than either); their falls and regret against other
# settings: docs/lookahead.md ("Lookahead verified in physics")
TRAINED_POLICY = pathlib.Path("dp", "seed0", "policy")  # the first seed's policy in a `train` folder of a results
# folder (what `python -m experiments train` writes: results/train/dp/seed0/policy)
SHIPPED_POLICY = policies.SHIPPED_POLICY  # a copy of results/train/dp/seed0/policy of a full GPU run
TABLES = "tables"  # the subfolder of a results folder where `context` keeps the DP tables it built


@dataclasses.dataclass
class Context:
    """What the planners of a batch of N episodes are built from. `tables` and `solutions` are None where no
    planner needs them (`context(..., tables=False)`), `rl` where the PPO policy was not loaded, `nominal_actions`
    where the DP baseline was not asked for."""

    surrogate: Surrogate
    set_name: str
    names: list[str]  # episode names
    batch: scenario.Episode  # stacked (N, ...)
    tables: dp.Table | None  # stacked (N, ...), the episodes' DP tables
    solutions: dp.Solution | None  # stacked, DP optimal per episode
    nominal_actions: jax.Array | None  # (T,) the DP baseline: the nominal training episode's optimal sequence
    rl: policies.NetworkPolicy | None  # the PPO actor (deterministic), with its critic
    rl_source: str  # where the RL policy was read from

    def take(self, n: int | None) -> "Context":
        """The same context on `n` of its episodes, spread evenly (as `subset`): no new tables."""
        if n is None or n >= len(self.names):
            return self
        return self.select(spread(len(self.names), n))

    def select(self, keep) -> "Context":
        """The same context on the episodes `keep` (indices): no new tables."""
        keep = np.asarray(keep, int)
        pick = lambda tree: jax.tree.map(lambda x: x[keep], tree)  # noqa: E731
        return dataclasses.replace(self, names=[self.names[i] for i in keep], batch=pick(self.batch),
                                   tables=pick(self.tables), solutions=pick(self.solutions))


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


def trained_policy(sur: Surrogate, results: str | pathlib.Path) -> pathlib.Path:
    """Where `python -m experiments train` writes the first seed's policy for the surrogate's model under the
    results folder `results`: <results>/train[-model][-learned]/dp/seed0/policy (`-learned` where the surrogate has
    the learned physics term)."""
    folder = "train" + ("" if sur.model.name == model_lib.DEFAULT else f"-{sur.model.name}")
    folder += "-learned" * (sur.learned is not None)
    return pathlib.Path(results, folder, TRAINED_POLICY)


def load_rl(sur: Surrogate, policy_dir: str | pathlib.Path | None = None,
            results: str | pathlib.Path | None = None) -> tuple[policies.NetworkPolicy, str]:
    """The PPO policy: `policy_dir` if given, else the one `train` wrote for the model under the results folder
    `results` (`trained_policy`; None: none looked for), else the one shipped for a shipped model
    (`policies.shipped_policy`); and where it was read from (with "trained without the learned term" or "with other
    learned weights" where the policy's reward differs from the surrogate's). A policy made for another model is
    refused (`policies.load_network_policy`)."""
    shipped = [p] if (p := policies.shipped_policy(sur)) is not None else []
    trained = [] if results is None else [trained_policy(sur, results)]
    candidates = [pathlib.Path(policy_dir)] if policy_dir else [*trained, *shipped]
    for path in candidates:
        if path.exists():
            here = pathlib.Path.cwd()
            shown = str(path.resolve().relative_to(here) if path.resolve().is_relative_to(here) else path)
            made = (policies.model_tag(path) or {}).get("learned", "")
            if made != sur.learned_tag:
                shown += (" (trained without the learned term)" if not made else
                          " (trained with other learned weights)" if sur.learned_tag else
                          " (trained with the learned term)")
            return policies.load_network_policy(sur, path), shown
    raise FileNotFoundError(
        f"policy_dir: no PPO policy at {', '.join(map(str, candidates))}; run `python -m experiments train --seeds 1"
        f"{'' if sur.model.name == model_lib.DEFAULT else ' --model ' + sur.model.name}`"
    )


def dp_tables(sur: Surrogate, set_name: str, episodes: dict, batch_size: int = 4,
              cache: pathlib.Path | None = None) -> dp.Table:
    """The stacked `dp.Table`s of named episodes, kept under `cache` (keyed by the episodes, the model files and
    the surrogate's configuration, so a change to any of them rebuilds; None: no cache). Builds `batch_size` at a
    time on each local device (all at once for a smaller set: the batch depends on the set, never on the process
    count); with several processes each builds its share of the batches."""
    batch = sur.validate(scenario.stack(list(episodes.values())))
    h = hashlib.sha256()
    for leaf in jax.tree.leaves(batch):
        h.update(np.asarray(leaf).tobytes())
    h.update(sur.model.digest.encode())  # the model's content (its files, includes resolved)
    h.update(sur.learned_tag.encode())  # the learned physics term's weights ("" without one)
    for cfg in (sur.reward_config, sur.ik_config, sur.wrench_config):
        h.update(repr(dataclasses.asdict(cfg)).encode())
    path = None if cache is None else pathlib.Path(cache) / f"{set_name}_{h.hexdigest()[:12]}.npz"
    if path is not None and path.exists():
        try:
            with np.load(path) as d:
                return dp.Table(**{k: jnp.asarray(d[k]) for k in d.files})
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, TypeError) as e:  # truncated by a crash
            warnings.warn(f"{path}: the cached DP tables cannot be read ({e}): rebuilding them", stacklevel=2)
    # each call builds one batch of `batch_size` on each local device (the last one filled up with copies), each
    # process a contiguous share of the batches: whatever the process count, every table comes from the same
    # program, to the last bit (over several local devices XLA's partitioned program: float rounding apart)
    n = len(episodes)
    batch_size = max(1, min(batch_size, n))  # one episode: one table built, not a batch of copies
    batches = distributed.share(-(-n // batch_size))
    mine = range(min(batches.start * batch_size, n), min(batches.stop * batch_size, n))
    print(f"building DP tables for {len(episodes)} episodes of '{set_name}'"
          + (f" (cached in {path})" if path else "")
          + (f", episodes {mine.start + 1}-{mine.stop} in this process" if distributed.count() > 1 else "") + " ...",
          flush=True)
    t0 = time.perf_counter()
    step, parts = batch_size * len(jax.local_devices()), []
    for i in range(mine.start, mine.stop, step):  # every call `step` episodes (one program): the last filled up
        idx = np.minimum(np.arange(i, i + step), mine.stop - 1)
        tables = table_builder()(sur, jax.tree.map(lambda x: x[idx], batch))
        parts.append(jax.tree.map(lambda x: np.asarray(x)[:min(step, mine.stop - i)], tables))
    parts = distributed.gather_joined(parts)
    tables = jax.tree.map(lambda *xs: jnp.concatenate([jnp.asarray(x) for x in xs]), *parts)
    print(f"  {time.perf_counter() - t0:.1f} s", flush=True)
    if path is not None and distributed.is_main():
        files.savez(path, **{k: np.asarray(v) for k, v in vars(tables).items() if v is not None})  # atomic
    return tables


@functools.cache
def table_builder():
    """`f(sur, episodes)`: the tables of stacked episodes (leaves (n, ...)), split over the local devices
    (`distributed.over_local_devices`); one jitted function for the process."""
    return distributed.over_local_devices(jax.vmap(dp.build_table, (None, 0)))


def nominal_actions(sur: Surrogate, cache: pathlib.Path | None = None) -> jax.Array:
    """The DP baseline's open-loop sequence: the nominal training episode's optimal actions (T,); its table kept
    under `cache` (`dp_tables`)."""
    nominal = scenario.nominal(sur.model)
    tables = dp_tables(sur, f"nominal-{sur.model.name}" if sur.model.name != model_lib.DEFAULT else "nominal", nominal,
                       cache=cache)
    first = jax.tree.map(lambda x: x[0], tables)
    return dp.backup(first, nominal["nominal"].start_grasp).actions


def four_tips(space: grasps.GraspSpace, n_steps: int = scenario.N_WAYPOINTS) -> np.ndarray:
    """(T,) the constant all-tips grasp from the model's start grasp: every fingertip link on its first option
    (`GraspSpace.tip_options`; the wrench's four tips T1 I1 . M1 . R1), reached one link per step, and that last
    action repeated (the wrench: add the ring tip at waypoint 0, then repeat it: a redundant action, the grasp
    kept)."""
    start, tips = space.start_options, space.tip_options
    if len(tips) != space.n_links or len(start) != space.n_links:
        raise ValueError("four_tips: the grasp space has no start and tip options (build it with grasps.space_of)")
    changes = [space.action(n, t) for n, s, t in zip(space.link_names, start, tips) if s != t]
    seq = changes[:n_steps] + [changes[-1] if changes else grasps.NULL] * max(0, n_steps - len(changes))
    return np.asarray(seq, np.int32)


def one_tip(space: grasps.GraspSpace, n_steps: int = scenario.N_WAYPOINTS) -> np.ndarray:
    """(T,) one contact of the start grasp alone (must drop): its second contact is kept, the others let go one a
    waypoint from the last link to the first, then keep. The wrench's start T1 I1 . M1: the index tip alone (the
    middle lets go at waypoint 0, the thumb at 1). Any model whose start grasp has a contact."""
    active = [i for i, o in enumerate(space.start_options) if o]
    if not active:
        raise ValueError("one_tip: the start grasp has no contact (build the space with grasps.space_of)")
    kept = active[1] if len(active) > 1 else active[0]
    seq = np.full(n_steps, grasps.NULL, np.int32)
    for t, i in enumerate([i for i in reversed(active) if i != kept][:n_steps]):
        seq[t] = space.action(space.link_names[i], 0)
    return seq


def scripted_sequences(space: grasps.GraspSpace, n_steps: int = scenario.N_WAYPOINTS) -> dict[str, np.ndarray]:
    """Three scripted sequences with grasp changes, (T,) actions each ("keep the grasp" is the null action):
    `add-slide` adds the ring tip at waypoint 2, slides the middle tip M1 -> M2 at 6 and back at 10;
    `add-slide-ring0` the same with the ring tip added at 0; `alternate` adds the ring tip at 0, then changes at
    every waypoint, sliding the middle tip between M2 and M1."""
    keep = grasps.NULL
    ring, m1, m2 = space.action("ring_distal", 1), space.action("middle_distal", 1), space.action("middle_distal", 2)
    add_slide = np.full(n_steps, keep)
    add_slide[2], add_slide[6], add_slide[10] = ring, m2, m1
    early = add_slide.copy()
    early[0], early[2] = ring, keep
    alternate = np.array([ring] + [m2 if t % 2 else m1 for t in range(1, n_steps)])
    return {"add-slide": add_slide.astype(np.int32), "add-slide-ring0": early.astype(np.int32),
            "alternate": alternate.astype(np.int32)}


def context(set_name: str = "eval", n_episodes: int | None = None, policy_dir=None, episodes: dict | None = None,
            tables: bool = True, rl: bool = True, nominal: bool = True, model=None,
            results: str | pathlib.Path | None = None, learned=None) -> Context:
    """The context of an episode set (`scenario.episode_set(set_name, model)`, or the named `episodes` given),
    `n_episodes` of it spread evenly (all if None), for `model` (a name, path or `Model`; None: the default): with
    their DP tables and solutions (`tables`), the PPO policy (`rl`, `load_rl(policy_dir, results)`) and the DP
    baseline's sequence (`nominal`: the nominal episode's table). With a results folder `results`, the tables are
    kept in its `TABLES` subfolder (built once) and the policy `train` wrote there is looked for; None: neither.
    `learned`: the surrogate's learned physics term, as `Surrogate(learned=)` takes it (None: the model's own where
    it has one; False: the paper's surrogate)."""
    cache = None if results is None else pathlib.Path(results, TABLES)
    sur = Surrogate(model, learned=learned)
    everything = scenario.episode_set(set_name, sur.model) if episodes is None else episodes
    chosen = subset(everything, n_episodes)
    tag = set_name if len(chosen) == len(everything) else f"{set_name}{len(chosen)}"
    batch = scenario.stack(list(chosen.values()))
    tabs = sols = None
    if tables:
        tabs = dp_tables(sur, tag, chosen, cache=cache)
        sols = jax.jit(jax.vmap(dp.backup))(tabs, batch.start_grasp)
    net, source = None, ""
    if rl:
        try:
            net, source = load_rl(sur, policy_dir, results)
        except FileNotFoundError:
            if policy_dir or sur.model.name == model_lib.DEFAULT or not nominal:
                raise
            source = (f"none for model {sur.model.name!r}: L1 and L2 look ahead over the DP baseline (train a PPO "
                      f"policy with `python -m experiments train --model {sur.model.name}`)")
            print(f"RL policy: {source}", flush=True)
    base = nominal_actions(sur, cache) if nominal else None
    return Context(sur, set_name, list(chosen), batch, tabs, sols, base, net, source)
