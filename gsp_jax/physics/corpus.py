"""A physics corpus of one model: surrogate features of grasp-sequence transitions with what C MuJoCo did.

What a learned physics term is fitted on. Tools and tasks are drawn from `Distribution` (wider than the stress set
on every axis; no episode of a named set enters it), sequences come from the planners' tables (the four tips, DP
optimal), random surrogate-feasible ones and perturbations of those, and each runs closed loop in C MuJoCo. Per
transition (decision t of a sequence on an episode) it keeps the surrogate's features (`FEATURES`: the step's
reward terms, the motor check, the grasp change, the episode's parameters) and the physics outcome: the segment it
fell in, the episode's angle error and fall time.

    store = corpus.Store.open("results/corpus-wrench", sur.model)    # refuses another model's corpus, by name
    corpus.extend(store, sur, seeds=range(4), episodes=32)            # a shard a seed; a rerun skips the done ones

A `Store` is a folder of shards (`shard-<seed>.npz`, each written whole) and `manifest.json` (model name and
digest, the distribution, the physics settings its runs had, the features' names, per shard its seed, counts and
hash); a shard is listed only once
written, so a killed run loses at most the shard it was making and a rerun neither repeats nor loses one.

A corpus of a world gap (`gap`, a `gsp_jax.physics.world.Gap`: `corpus --world gap`) runs each episode in a world
drawn from it (one per episode, every sequence of it in that world; from the shard's seed, a stream apart from the
episodes' draw), hidden from the planners and from the features: a term fitted on it learns how often a transition
fails in worlds the planner does not know, not only in its own model. The manifest records the gap (`world`); a
corpus is extended and learned from only in the gap its runs had.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.core import distributed, files
from gsp_jax.planning import dp, evaluation, policies
from gsp_jax.surrogate import learned
from gsp_jax.model import scenario
from gsp_jax.physics import scene as scene_lib, world as world_lib
from gsp_jax.surrogate import step as surrogate_lib

VERSION = 1
HELD_OUT = ("stress", "stress-cal", "eval", "val", "variations")  # sets whose episodes never enter a corpus
FEATURES = learned.FEATURES  # one transition's features, in this order (float32)
LABELS = ("fell_here", "alive")  # per transition: fell in its segment; executed (the tool was held when it began)


class CorpusError(ValueError):
    """A corpus that cannot serve: another model's, a missing field, an unreadable shard."""


@dataclasses.dataclass(frozen=True)
class Distribution:
    """Tools and tasks, each parameter drawn independently and uniformly (the mass log-uniformly): mass factor
    [m0], finger-tool friction, final torque [x the model's torque] about a uniformly drawn axis (x, y, z or any unit
    vector), CoM offsets [cm], start/end height shift [mm], lateral end point [mm] along a path drawn from vertical,
    lateral x, lateral y and diagonal. The stress set spans 0.25-3 m0, mu 0.3-2, +-2 torques about x, y or z,
    +-2 cm, -6..12 mm and +-15 mm (`scenario.stress_set`). The offsets are the wrench's: `draw` scales them for a
    model with less room (`scenario.fit`: a narrower tool, a lower rest)."""

    mass: tuple[float, float] = (0.2, 3.5)
    friction: tuple[float, float] = (0.25, 2.2)
    torque: tuple[float, float] = (-2.4, 2.4)
    com_cm: tuple[float, float] = (-2.5, 2.5)
    shift_mm: tuple[float, float] = (-8.0, 14.0)
    lateral_mm: tuple[float, float] = (-18.0, 18.0)

    def __post_init__(self):
        for f in dataclasses.fields(self):
            lo, hi = getattr(self, f.name)
            if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
                raise ValueError(f"Distribution.{f.name}: expected (low, high) with low < high, got {(lo, hi)}")
        if self.mass[0] <= 0 or self.friction[0] <= 0:
            raise ValueError(f"Distribution: mass and friction must be positive, got mass {self.mass}, "
                             f"friction {self.friction}")


def _torque_axis(rng: np.random.Generator):
    kind = int(rng.integers(4))
    if kind < 3:
        return "xyz"[kind]
    v = rng.normal(size=3)
    return tuple(float(x) for x in v / np.linalg.norm(v))


def draw(dist: Distribution, seed: int, n: int, model=None) -> dict[str, scenario.Episode]:
    """`n` episodes of `model`'s tool drawn from `dist` with the seed `seed` (one seed, one set), named
    corpus<seed>-<i>. An episode equal to one of a held-out set's (`HELD_OUT`) is drawn again."""
    if n < 1:
        raise ValueError(f"n: at least one episode, got {n}")
    rng = np.random.default_rng([VERSION, seed])
    held = _held_out(model)
    t0, fit = scenario._torque(model), scenario.fit(model)
    out = {}
    while len(out) < n:
        path = ("vertical", "lateral-x", "lateral-y", "diagonal")[int(rng.integers(4))]
        lat = rng.uniform(*dist.lateral_mm)
        dx = lat * fit.lateral[0] if path in ("lateral-x", "diagonal") else 0.0
        dy = (lat if path == "lateral-y" else -lat if path == "diagonal" else 0.0) * fit.lateral[1]
        ep = scenario.make_episode(
            model=model, shift_mm=fit.shift(float(rng.uniform(*dist.shift_mm))),
            torque=float(rng.uniform(*dist.torque) * t0),
            mass_factor=float(np.exp(rng.uniform(*np.log(dist.mass)))), friction=float(rng.uniform(*dist.friction)),
            com_x_cm=float(rng.uniform(*dist.com_cm)) * fit.com[0],
            com_y_cm=float(rng.uniform(*dist.com_cm)) * fit.com[1],
            lateral_mm=(float(dx), float(dy)), torque_axis=_torque_axis(rng))
        if _key(ep) not in held:
            out[f"corpus{seed}-{len(out):04d}"] = ep
    return out


def _key(ep: scenario.Episode) -> bytes:
    return b"".join(np.asarray(x, np.float32).round(6).tobytes() for x in jax.tree.leaves(ep))


def _held_out(model) -> set[bytes]:
    return {_key(ep) for name in HELD_OUT for ep in scenario.episode_set(name, model).values()}


@jax.jit
def features(sur: surrogate_lib.Surrogate, episode: scenario.Episode, actions: jax.Array) -> jax.Array:
    """(T, len(FEATURES)) float32: each transition's features (`FEATURES`) along `actions` (T,) int32 from the
    episode's start: the analytic surrogate's terms of the step (its IK and wrench solves; never a learned term's),
    then the episode's parameters."""
    states, terms = surrogate_lib._replay(sur.analytic, episode, actions)
    new, _ = sur.space.apply(states.grasp, actions)
    return learned.transition_features(terms, states.t, new != states.grasp, sur.links(new),
                                       learned.episode_features(episode))


def run_features(sur: surrogate_lib.Surrogate, runs: scenario.Episode, actions) -> np.ndarray:
    """(M, T, len(FEATURES)) float32: `features` of M runs at once (`runs` stacked (M,), `actions` (M, T) int32), one
    program. A learned surrogate's runs get the analytic features too: its analytic twin is made here, outside the
    trace (made inside it, its arrays would be the trace's)."""
    return np.asarray(_run_features(sur.analytic, runs, jnp.asarray(actions)))


_run_features = jax.jit(jax.vmap(features, (None, 0, 0)))


def labels(fell: np.ndarray, fall_time: np.ndarray, T: int, n_segment: int, timestep: float) -> dict[str, np.ndarray]:
    """Per transition of M runs (fell (M,) bool, fall_time (M,) [s], -1 if held): `fell_here` (M, T) bool, the tool
    fell during segment t (for t = T - 1 the hold after it too), and `alive` (M, T) bool, it had not fallen when
    segment t began: a discrete-time hazard's events and risk sets."""
    tick = np.where(fell, np.round(np.asarray(fall_time) / timestep), np.inf)
    start = np.arange(T) * n_segment
    end = np.append(start[1:], np.inf)
    alive = tick[:, None] >= start[None]
    return dict(fell_here=alive & (tick[:, None] < end[None]), alive=alive)


def sequences(tables: dp.Table, solutions: dp.Solution, batch: scenario.Episode, space, r_min: float, seed: int,
              n_random: int, n_perturbed: int) -> tuple[list[str], np.ndarray]:
    """(kinds, actions (S, N, T) int32) for N episodes: the four tips, DP optimal, `n_random` random
    surrogate-feasible sequences (half keeping each grasp with probability 0.8) and `n_perturbed` perturbations (a
    DP-optimal or random sequence with one step's action replaced by another feasible one). Every draw from `seed`."""
    N, T = np.shape(batch.mass)[0], batch.n_steps
    four = np.broadcast_to(evaluation.four_tips(space, T), (N, T))
    kinds, seqs = ["four-tips", "dp-opt"], [four, np.asarray(solutions.actions)]
    if n_random:
        keys = jax.random.split(jax.random.PRNGKey(seed), N * n_random).reshape(N, n_random, 2)
        holds = jnp.where(jnp.arange(n_random) % 2 == 0, 0.0, 0.8)
        rand = jax.vmap(jax.vmap(dp.random_sequence, (None, None, 0, None, 0)), (0, 0, 0, None, None))(
            tables, batch.start_grasp, keys, r_min, holds)
        seqs += list(np.moveaxis(np.asarray(rand), 1, 0))
        kinds += [f"random{r}" for r in range(n_random)]
    base = np.stack(seqs[1:])  # DP optimal and the random ones
    rng = np.random.default_rng([VERSION, seed, 1])
    transitions = np.asarray(space.transitions)
    reward = np.asarray(tables.reward)
    for p in range(n_perturbed):
        out = np.empty((N, T), np.int32)
        for e in range(N):
            acts = base[rng.integers(len(base)), e].copy()
            t = int(rng.integers(T))
            g = int(np.asarray(batch.start_grasp)[e])
            for s in range(t):
                g = int(transitions[g, acts[s]])
            ok = np.flatnonzero(reward[e, g, :, t] > r_min)
            ok = ok[ok != acts[t]] if ok.size > 1 else ok
            if ok.size:
                acts[t] = rng.choice(ok)
            out[e] = acts
        seqs.append(out)
        kinds.append(f"perturbed{p}")
    return kinds, np.stack(seqs).astype(np.int32)


# ---------------------------------------------------------------------------------------------------- the store
@dataclasses.dataclass
class Store:
    """A corpus folder of one model: `manifest` (the parsed manifest.json) and its shards."""

    folder: pathlib.Path
    manifest: dict

    @classmethod
    def open(cls, folder, model, dist: Distribution | None = None) -> "Store":
        """The corpus in `folder` (created empty where there is none) for `model` (a `gsp_jax.model.load.Model`).
        `CorpusError` naming both where it holds another model's corpus (name and digest), another distribution,
        or a manifest without a field it needs."""
        folder = pathlib.Path(folder)
        path = folder / "manifest.json"
        dist = dist or Distribution()
        if not path.exists():
            manifest = dict(version=VERSION, model=model.name, digest=model.digest, features=list(FEATURES),
                            labels=list(LABELS), distribution=dataclasses.asdict(dist), shards=[])
            folder.mkdir(parents=True, exist_ok=True)
            files.write_json(path, manifest)
            return cls(folder, manifest)
        try:
            manifest = files.read_json(path)
        except (OSError, ValueError) as e:
            raise CorpusError(f"{path}: not a readable manifest ({e})") from None
        for field in ("version", "model", "digest", "features", "labels", "distribution", "shards"):
            if field not in manifest:
                raise CorpusError(f"{path}: the manifest has no field {field!r}")
        if manifest["digest"] != model.digest:
            raise CorpusError(f"{path}: a corpus of model {manifest['model']!r} (digest {manifest['digest'][:12]}), "
                              f"not of {model.name!r} (digest {model.digest[:12]})")
        if manifest["features"] != list(FEATURES) or manifest["version"] != VERSION:
            raise CorpusError(f"{path}: made with other features (version {manifest['version']}); start a new folder")
        if manifest["distribution"] != json.loads(json.dumps(dataclasses.asdict(dist))):
            raise CorpusError(f"{path}: drawn from {manifest['distribution']}, not {dataclasses.asdict(dist)}")
        return cls(folder, manifest)

    @property
    def seeds(self) -> set[int]:
        return {s["seed"] for s in self.manifest["shards"]}

    def add(self, seed: int, arrays: dict[str, np.ndarray]) -> None:
        """Write the shard of `seed` whole, then list it in the manifest (whole): a kill between the two leaves an
        unlisted shard that the next `add` of that seed replaces."""
        self.commit([self.put(seed, arrays)])

    def put(self, seed: int, arrays: dict[str, np.ndarray]) -> dict:
        """Write the shard of `seed` whole, unlisted; its manifest entry (for `commit`)."""
        if seed in self.seeds:
            raise CorpusError(f"{self.folder}: shard {seed} is already in the corpus")
        name = f"shard-{seed:06d}.npz"
        files.savez(self.folder / name, **arrays)
        digest = hashlib.sha256((self.folder / name).read_bytes()).hexdigest()[:16]
        alive = arrays["alive"]
        return dict(file=name, seed=int(seed), episodes=int(len(arrays["episode_names"])), runs=int(alive.shape[0]),
                    transitions=int(alive.sum()), falls=int(arrays["fell"].sum()), sha256=digest)

    def commit(self, entries: list[dict]) -> None:
        """List written shards (`put`'s entries, in this order) in the manifest, written whole."""
        self.manifest["shards"].extend(entries)
        files.write_json(self.folder / "manifest.json", self.manifest)

    def load(self) -> dict[str, np.ndarray]:
        """Every shard's arrays, concatenated along the runs (`episode_names` and `kinds` per run; `episode` is
        renumbered over the corpus, so a split by episode stays one). `CorpusError` naming a shard that is missing,
        altered (its hash) or lacks a field."""
        parts, offset = [], 0
        for s in self.manifest["shards"]:
            path = self.folder / s["file"]
            if not path.exists():
                raise CorpusError(f"{path}: listed in the manifest but missing")
            if hashlib.sha256(path.read_bytes()).hexdigest()[:16] != s["sha256"]:
                raise CorpusError(f"{path}: not the shard the manifest lists (its hash differs)")
            with np.load(path) as d:
                missing = [k for k in SHARD_FIELDS if k not in d.files]
                if missing:
                    raise CorpusError(f"{path}: no field {missing[0]!r}")
                part = {k: d[k] for k in SHARD_FIELDS}
            part["episode"] = part["episode"] + offset
            offset += len(part["episode_names"])
            parts.append(part)
        if not parts:
            raise CorpusError(f"{self.folder}: an empty corpus")
        out = {k: np.concatenate([p[k] for p in parts]) for k in SHARD_FIELDS if k != "episode_names"}
        out["episode_names"] = np.concatenate([p["episode_names"] for p in parts])
        return out


def solve_batch(sur: surrogate_lib.Surrogate, batch: scenario.Episode) -> tuple[dp.Table, dp.Solution]:
    """The tables and solutions of a stacked batch of episodes: one program, the batch split over the local
    devices (`distributed.over_local_devices`)."""
    return _solve_batch()(sur, batch)


@functools.cache
def _solve_batch():
    return distributed.over_local_devices(jax.vmap(dp.solve, (None, 0)))


# a shard: M runs (episode x sequence) of T transitions, F features
SHARD_FIELDS = ("features", "fell_here", "alive", "fell", "angle_error", "fall_time", "actions", "grasps", "episode",
                "kind", "kinds", "episode_names")


WORLD_STREAM = 85  # the shard's worlds are drawn from fold_in(PRNGKey(seed), WORLD_STREAM): apart from its episodes


def worlds(gap, seed: int, batch: scenario.Episode, hand):
    """The worlds (numpy, leading axis (N,)) of a shard's episodes `batch` in `gap` (None or the nominal gap: None),
    drawn from the shard's `seed`."""
    if gap is None or gap.nominal:
        return None
    n = int(np.shape(batch.mass)[0])
    key = jax.random.fold_in(jax.random.PRNGKey(seed), WORLD_STREAM)
    return jax.device_get(world_lib.draw(gap, key, n, len(hand.touch_tool), hand.n_joints))


def shard(phys, seed: int, n_episodes: int, dist: Distribution, n_random: int, n_perturbed: int,
          cores: int | None = None, progress: bool = False, n_steps: int | None = None,
          gap=None) -> dict[str, np.ndarray]:
    """One shard: `n_episodes` drawn with `seed`, their DP tables, the sequences (`sequences`) run closed loop in C
    MuJoCo (each episode in its world of `gap` where one is given: `worlds`), each transition's features and labels.
    Arrays: features (M, T, F) float32, fell_here and alive (M, T) bool, fell (M,), angle_error (M,) [deg],
    fall_time (M,) [s], actions and grasps (M, T) int32, episode and kind (M,) int32 (indices into episode_names (N,)
    and kinds (S,)), M = N S runs. `n_steps`: the episodes' first
    waypoints only (a quick corpus; None: all)."""
    sur = phys.surrogate
    eps = draw(dist, seed, n_episodes, sur.model)
    if n_steps is not None:
        eps = {k: e.head(n_steps) for k, e in eps.items()}
    batch = scenario.stack(list(eps.values()))
    tables, solutions = solve_batch(sur, batch)
    kinds, acts = sequences(tables, solutions, batch, sur.space, sur.reward_config.r_min, seed, n_random,
                            n_perturbed)  # (S, N, T)
    groups = [(policies.SequencePolicy(jnp.asarray(a)), 0) for a in acts]
    res = phys.simulate_many(groups, batch, backend="c", cores=cores, progress=progress,
                             world=worlds(gap, seed, batch, sur.hand))
    S, N, T = acts.shape
    fell = np.stack([np.asarray(r.fell) for r in res]).reshape(-1)
    fall_time = np.stack([np.asarray(r.fall_time) for r in res]).reshape(-1)
    run_actions = np.stack([np.asarray(r.actions) for r in res]).reshape(-1, T)
    runs = jax.tree.map(lambda x: jnp.concatenate([x] * S), batch)  # run i: episode i % N, sequence i // N
    per_run = run_features(sur, runs, acts.reshape(S * N, T))
    lab = labels(fell, fall_time, T, phys.n_segment, phys.timestep)
    return dict(features=per_run.astype(np.float32), **lab, fell=fell, fall_time=fall_time,
                angle_error=np.stack([np.asarray(r.angle_error) for r in res]).reshape(-1),
                actions=run_actions.astype(np.int32),
                grasps=np.stack([np.asarray(r.grasps) for r in res]).reshape(-1, T).astype(np.int32),
                episode=np.tile(np.arange(N, dtype=np.int32), S), kind=np.repeat(np.arange(S, dtype=np.int32), N),
                kinds=np.array(kinds), episode_names=np.array(list(eps)))


def _gap_dict(gap) -> dict:
    """A gap as the manifest records it ({} for none or the nominal gap: every corpus made before worlds)."""
    return {} if gap is None or gap.nominal else json.loads(json.dumps(dataclasses.asdict(gap)))


def check_physics(store: Store, config, gap=None) -> None:
    """The corpus's runs are of the physics settings `config` (a `PhysicsConfig`: the controller, its tuning, the
    timeline), of this library's physics (`scene.REVISION`) and of the world gap `gap` (None: the nominal model):
    a new corpus records all three (in its manifest, `physics`, `physics_revision`, `world`); `CorpusError` naming
    what differs where its shards were run with other settings, another revision or another gap, or where they were
    made before corpora recorded them (their runs may be another controller's). A corpus is extended and learned
    from only with the physics it was run with."""
    want = json.loads(json.dumps(dataclasses.asdict(config)))
    have = store.manifest.get("physics")
    if have is None:
        if store.manifest["shards"]:
            raise CorpusError(f"{store.folder}: its {len(store.manifest['shards'])} shards do not record the physics "
                              "settings they were run with (made before corpora did: their runs may be another "
                              "controller's); start a new folder (--folder) or remove this one")
        store.manifest["physics"] = want  # written with the first shard's listing
        store.manifest["physics_revision"] = scene_lib.REVISION
        store.manifest["world"] = _gap_dict(gap)
        return
    world = store.manifest.get("world", {})  # a corpus made before worlds: the nominal model's runs
    if world != _gap_dict(gap):
        name = lambda w: "the nominal model (no gap)" if not w else f"the gap {w}"  # noqa: E731
        raise CorpusError(f"{store.folder}: its runs are in {name(world)}, not in {name(_gap_dict(gap))} "
                          "(--world); start a new folder (--folder) or run in its world")
    revision = store.manifest.get("physics_revision", 1)
    if revision != scene_lib.REVISION:
        raise CorpusError(f"{store.folder}: its runs are of the physics' revision {revision}, this library simulates "
                          f"revision {scene_lib.REVISION} (`gsp_jax.physics.scene.REVISION`; CHANGELOG.md says what "
                          "changed); start a new folder (--folder) or remove this one")
    differ = [f"{group}.{name} {have.get(group, {}).get(name)!r} there, {value!r} here"
              for group, fields in want.items() for name, value in fields.items()
              if have.get(group, {}).get(name) != value]
    if differ:
        raise CorpusError(f"{store.folder}: its runs were made with other physics settings ({'; '.join(differ[:4])}"
                          f"{'; ...' if len(differ) > 4 else ''}); start a new folder (--folder) or run with those")


def extend(store: Store, phys, seeds, episodes: int, n_random: int = 4, n_perturbed: int = 2,
           cores: int | None = None, progress: bool = True, n_steps: int | None = None, gap=None) -> list[int]:
    """Add the shard of each seed in `seeds` that the corpus does not hold (`shard`, then `Store.add`; in worlds of
    `gap` where given): a run killed part-way loses only the shards it was making, and the same call again adds
    the rest. The seeds added.
    With several processes (`distributed`) the seeds go in rounds of one shard per process; each process writes
    its shard, process 0 lists the round's shards in seed order. A shard is the same in one process or several."""
    dist = Distribution(**{k: tuple(v) for k, v in store.manifest["distribution"].items()})
    check_physics(store, phys.config, gap)
    todo = [seed for seed in seeds if seed not in store.seeds]
    P = distributed.count()
    for r in range(0, len(todo), P):
        mine = todo[r:r + P][distributed.rank():distributed.rank() + 1]
        made = [store.put(seed, shard(phys, seed, episodes, dist, n_random, n_perturbed, cores, progress, n_steps,
                                         gap))
                for seed in mine]
        made = distributed.gather_joined(made)
        if distributed.is_main():
            store.commit(made)
        else:
            store.manifest["shards"].extend(made)  # as process 0 lists them, without writing
        if progress:
            for m in made:
                print(f"corpus: shard {m['seed']}: {m['runs']} runs, {m['transitions']} transitions, "
                      f"{m['falls']} falls ({len(store.seeds)} shards)", flush=True)
    return todo
