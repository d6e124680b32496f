"""A learned physics term: the probability that a transition's segment ends in a fall, fitted on a physics corpus.

A discrete-time hazard: for each transition a run reached (`alive`), the chance that the tool falls during its
segment given the surrogate's features (`FEATURES`, `transition_features`): the mean probability of an ensemble of
small MLPs over standardised features, each trained by binary cross-entropy of its logit on the risk sets (optax
AdamW), split by episode into train / validation / test, stopped early on the validation loss.

    fitted = learned.fit(data["features"], data["fell_here"], data["alive"], data["episode"], key, model.digest)
    p = learned.hazard(fitted, features)          # (..., T) probability of a fall in each segment
    learned.save(fitted, path); learned.load(path, model)   # refused for another model, by name

`reliability` bins predicted against observed rates (a calibration picture); `gsp_jax.core.stats.auc` ranks them.
The reward turns the hazard into its learned physics term (`gsp_jax.surrogate.reward.with_risk`); the weights of a
model sit beside its scene file (`path_of`: models/scene.learned.npz for the shipped wrench).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import pathlib
import warnings
from typing import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from gsp_jax.core import files
from gsp_jax.surrogate import reward as reward_lib


EPISODE_FEATURES = ("mass", "friction", "force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z", "com_x",
                    "com_y", "com_z", "rise", "lateral")
STEP_FEATURES = ("t", "changed", "redundant", "wrench_move", "ik_next", "wrench_hold", "wrench_ext", "wrench_change",
                 "unmet_move", "unmet_hold", "unmet_ext", "unmet_change", "motor_unmet", "collision", "fall",
                 "reward", "links")
FEATURES = STEP_FEATURES + EPISODE_FEATURES  # one transition's features as a corpus keeps them, in order (float32)


def grasp_names(space) -> tuple[str, ...]:
    """The names of `grasp_features`' columns for a grasp space: "<link>=<option>" per link and option."""
    return tuple(f"{link}={o}" for link, n in zip(space.link_names, space.n_options) for o in range(n))


def input_names(space) -> tuple[str, ...]:
    """The network's inputs, in order: `FEATURES`, then the new grasp's options (`grasp_names`)."""
    return FEATURES + grasp_names(space)


def grasp_features(space, grasp) -> jax.Array:
    """(..., sum(n_options)) float32: each link's option in grasps (...) one-hot (`grasp_names`' order)."""
    options = space.decode(grasp)
    return jnp.concatenate([(options[..., link:link + 1] == jnp.arange(n)).astype(jnp.float32)
                            for link, n in enumerate(space.n_options)], -1)


def inputs(features, grasp, space) -> jax.Array:
    """(..., len(input_names(space))) float32: a transition's features (..., len(FEATURES)) and its new grasp
    (...) one-hot, broadcast together: what the network reads."""
    features, onehot = jnp.asarray(features, jnp.float32), grasp_features(space, grasp)
    lead = jnp.broadcast_shapes(features.shape[:-1], onehot.shape[:-1])
    return jnp.concatenate([jnp.broadcast_to(features, lead + features.shape[-1:]),
                            jnp.broadcast_to(onehot, lead + onehot.shape[-1:])], -1)


def episode_features(ep) -> jax.Array:
    """(len(EPISODE_FEATURES),) float32 of one episode (`scenario.Episode`): mass [kg], friction, the final external
    force [N] and torque [N m], the CoM offset [m], the rise and the lateral travel of the path [m]."""
    wp = ep.waypoints
    return jnp.concatenate([jnp.stack([ep.mass, ep.friction]), ep.w_ext, ep.com,
                            jnp.stack([wp[-1, 2] - wp[0, 2], jnp.linalg.norm(wp[-1, :2] - wp[0, :2])])]
                           ).astype(jnp.float32)


def transition_features(terms, t, changed, links, episode: jax.Array) -> jax.Array:
    """(..., len(FEATURES)) float32: the features of transitions from their analytic reward terms
    (`reward.RewardTerms`, leaves (...) and unmet (..., 4)), waypoint `t`, `changed` (the grasp changes), `links`
    (links in contact in the new grasp) and the episode's features (len(EPISODE_FEATURES),); all broadcast."""
    cols = [t, changed, terms.redundant, terms.wrench_move, terms.ik_next, terms.wrench_hold, terms.wrench_ext,
            terms.wrench_change, *jnp.moveaxis(terms.unmet, -1, 0), terms.motor_unmet, terms.collision, terms.fall,
            terms.reward, links]
    cols = jnp.broadcast_arrays(*[jnp.asarray(c, jnp.float32) for c in cols])
    steps = jnp.stack(cols, -1)
    return jnp.concatenate([steps, jnp.broadcast_to(episode, steps.shape[:-1] + episode.shape)], -1)


class LearnedTermError(ValueError):
    """Weights that cannot serve: another model's, another feature set, a missing field."""


@dataclasses.dataclass(frozen=True)
class FitConfig:
    hidden: Sequence[int] = (128, 128)  # ReLU MLP widths
    learning_rate: float = 3e-3
    weight_decay: float = 1e-2  # AdamW's (decoupled): the corpus overfits 64x64 at 1e-4 by epoch 20
    batch: int = 1024  # transitions per step
    epochs: int = 200  # at most, over the training transitions
    patience: int = 20  # epochs without a better validation loss before stopping
    split: tuple[float, float] = (0.7, 0.15)  # train, validation shares of the episodes (the rest: test)
    members: int = 5  # networks in the ensemble (their mean probability is the hazard)


class _MLP(nn.Module):
    hidden: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(1)(x)[..., 0]


@struct.dataclass
class Fitted:
    """A fitted hazard: the ensemble's parameters (each leaf with a leading axis of its K members), the features'
    mean and std (F,), and what it was fitted for."""

    params: dict
    mean: jax.Array  # (F,)
    std: jax.Array  # (F,)
    hidden: tuple = struct.field(pytree_node=False)
    features: tuple = struct.field(pytree_node=False)  # the feature names, in order
    digest: str = struct.field(pytree_node=False)  # the model's digest (`gsp_jax.model.load.Model.digest`)
    history: tuple = struct.field(pytree_node=False, default=())  # (epoch, train loss, validation loss) per epoch
    split: dict = struct.field(pytree_node=False, default_factory=dict)  # {"train"|"val"|"test": episode ids}


def hazard(fitted: Fitted, features: jax.Array) -> jax.Array:
    """(...,) probability in [0, 1] that the tool falls in each transition's segment (its inputs (..., F), `inputs`
    for the model's term): the mean of the ensemble members' probabilities."""
    x = (features - fitted.mean) / fitted.std
    logits = jax.vmap(lambda params: _MLP(fitted.hidden).apply(params, x))(fitted.params)  # (K, ...)
    return jnp.mean(jax.nn.sigmoid(logits), 0)


def split_episodes(episode: np.ndarray, key: jax.Array, shares=(0.7, 0.15)) -> dict[str, np.ndarray]:
    """The episode ids of `episode` (M,) shuffled by `key` into train / val / test (at least one each where there
    are three episodes or more): whole episodes, so no episode's runs are on both sides of a split."""
    ids = np.unique(episode)
    order = np.asarray(jax.random.permutation(key, len(ids)))
    n_train = max(1, int(round(shares[0] * len(ids))))
    n_val = max(1 if len(ids) >= 3 else 0, int(round(shares[1] * len(ids))))
    n_train = min(n_train, len(ids) - n_val - (1 if len(ids) >= 3 else 0))
    return dict(train=ids[order[:n_train]], val=ids[order[n_train:n_train + n_val]],
                test=ids[order[n_train + n_val:]])


def _loss(params, hidden, x, y, w):
    z = _MLP(hidden).apply(params, x)
    return jnp.sum(w * optax.sigmoid_binary_cross_entropy(z, y)) / jnp.maximum(jnp.sum(w), 1.0)


def fit(features: np.ndarray, fell_here: np.ndarray, alive: np.ndarray, episode: np.ndarray, key: jax.Array,
        digest: str, names: Sequence[str] = (), config: FitConfig = FitConfig(), progress: bool = False) -> Fitted:
    """Fit the hazard on M runs of T transitions: features (M, T, F), fell_here and alive (M, T) bool (a corpus's
    labels: only alive transitions count), episode (M,) ids for the split. Every draw from `key`. An ensemble of
    `config.members` networks on the same split (each its own initialisation and batch order, trained side by side
    under `vmap`), each member's parameters those of its epoch with the lowest validation loss."""
    features = np.asarray(features, np.float32)
    if features.ndim != 3 or fell_here.shape != features.shape[:2] or alive.shape != features.shape[:2]:
        raise ValueError(f"fit: features (M, T, F) with fell_here and alive (M, T), got {features.shape}, "
                         f"{np.shape(fell_here)}, {np.shape(alive)}")
    if not np.all(np.isfinite(features[alive])):
        raise ValueError("fit: the features of alive transitions must be finite")
    if config.members < 1:
        raise ValueError(f"fit: config.members: at least 1 network, got {config.members}")
    k_split, k_init, k_data = jax.random.split(key, 3)
    split = split_episodes(np.asarray(episode), k_split, config.split)

    def rows(ids):
        runs = np.isin(episode, ids)
        keep = alive[runs]
        return features[runs][keep], fell_here[runs][keep].astype(np.float32)

    (x_tr, y_tr), (x_va, y_va) = rows(split["train"]), rows(split["val"] if len(split["val"]) else split["train"])
    mean, std = x_tr.mean(0), np.maximum(x_tr.std(0), 1e-6)
    norm = lambda x: (x - mean) / std  # noqa: E731
    net = _MLP(tuple(config.hidden))
    K = config.members
    params = jax.vmap(lambda k: net.init(k, jnp.zeros((1, features.shape[-1]))))(jax.random.split(k_init, K))
    opt = optax.adamw(config.learning_rate, weight_decay=config.weight_decay)
    state = jax.vmap(opt.init)(params)
    B = min(config.batch, len(x_tr))
    n_batches = max(1, len(x_tr) // B)
    x_tr_n, x_va_n = jnp.asarray(norm(x_tr)), jnp.asarray(norm(x_va))
    y_tr, y_va, ones_va = jnp.asarray(y_tr), jnp.asarray(y_va), jnp.ones(len(x_va))

    def member_epoch(params, state, key):
        perm = jax.random.permutation(key, len(x_tr))[: n_batches * B].reshape(n_batches, B)

        def step(carry, idx):
            params, state = carry
            loss, grad = jax.value_and_grad(_loss)(params, net.hidden, x_tr_n[idx], y_tr[idx], jnp.ones(B))
            updates, state = opt.update(grad, state, params)
            return (optax.apply_updates(params, updates), state), loss

        (params, state), losses = jax.lax.scan(step, (params, state), perm)
        return params, state, jnp.mean(losses), _loss(params, net.hidden, x_va_n, y_va, ones_va)

    epoch = jax.jit(jax.vmap(member_epoch))
    best, best_loss, since, history = params, np.full(K, np.inf), np.zeros(K, int), []
    for e, k in enumerate(jax.random.split(k_data, config.epochs)):
        params, state, train_loss, val_loss = epoch(params, state, jax.random.split(k, K))
        val_loss = np.asarray(val_loss)
        history.append((e, float(np.mean(train_loss)), float(np.mean(val_loss))))
        better = val_loss < best_loss - 1e-6
        best = jax.tree.map(lambda b, p: jnp.where(better.reshape((K,) + (1,) * (p.ndim - 1)), p, b), best, params)
        best_loss, since = np.where(better, val_loss, best_loss), np.where(better, 0, since + 1)
        if progress and e % 10 == 0:
            print(f"  epoch {e}: train {float(np.mean(train_loss)):.4f}, validation {float(np.mean(val_loss)):.4f}"
                  f" (mean of {K})", flush=True)
        if np.all(since >= config.patience):
            break
    return Fitted(best, jnp.asarray(mean), jnp.asarray(std), tuple(config.hidden), tuple(names), digest,
                  tuple(history), {k: [int(i) for i in v] for k, v in split.items()})


def surrogate_alive(features: np.ndarray) -> np.ndarray:
    """(M, T) bool: the analytic surrogate had not ended the run before transition t (no collision or fall at an
    earlier step) -- the transitions a planner with the learned term can meet (features (M, T, F), `FEATURES`)."""
    ended = _ends(features)
    return np.cumsum(np.concatenate([np.zeros_like(ended[:, :1]), ended[:, :-1]], 1), 1) == 0


def _ends(features: np.ndarray) -> np.ndarray:
    """(...) bool: the analytic surrogate ends the run at this transition (a collision or a fall)."""
    return np.maximum(features[..., FEATURES.index("fall")], features[..., FEATURES.index("collision")]) > 0


def returns(features: np.ndarray, fall_risk: np.ndarray | None, cfg) -> tuple[np.ndarray, np.ndarray]:
    """(return (M,), feasible (M,) bool) of M runs of T transitions under the reward `cfg` (`reward.RewardConfig`)
    from their analytic features (M, T, F) and, with the learned term, each transition's fall risk (M, T) (None:
    without): the steps up to the first that ends the run (collision, analytic fall or a risk above
    `cfg.risk_falls`: r_min), each its expected reward, counted with the chance that the earlier segments held
    (`reward.total`, `reward.expected_return`, in float64)."""
    reward = np.asarray(features[..., FEATURES.index("reward")], np.float64)
    ends = _ends(features)
    p = np.zeros_like(reward)
    if fall_risk is not None:
        ends = ends | (np.asarray(fall_risk) > cfg.risk_falls)
        p = np.where(ends, 0.0, np.asarray(fall_risk, np.float64))
    before = np.cumsum(ends, 1) - ends == 0  # no earlier step ended the run
    step = np.where(ends, cfg.r_min, reward_lib.expected_reward(reward, p, cfg.r_min))
    hold = reward_lib.chance_to_hold(p)
    reach = np.cumprod(np.concatenate([np.ones_like(p[:, :1]), hold[:, :-1]], 1), 1)
    return np.sum(np.where(before, reach * step, 0.0), 1), ~np.any(ends, 1)


def reliability(p: np.ndarray, event: np.ndarray, bins: int = 10) -> list[dict]:
    """Predicted against observed: per probability bin (equal width in [0, 1]) its count, mean prediction and
    observed rate (a calibrated hazard has them equal)."""
    p, event = np.asarray(p, np.float64), np.asarray(event, bool)
    which = np.minimum((p * bins).astype(int), bins - 1)
    return [dict(low=b / bins, high=(b + 1) / bins, n=int(np.sum(which == b)),
                 predicted=float(p[which == b].mean()) if np.any(which == b) else float("nan"),
                 observed=float(event[which == b].mean()) if np.any(which == b) else float("nan"))
            for b in range(bins)]


# ---------------------------------------------------------------------------------------------------- files
def resolve(learned, model) -> "Fitted | None":
    """The weights a `Surrogate(learned=...)` uses for `model`: None (the default) the model's own where its scene
    has them (`path_of`), else none; False none (the paper's surrogate); True the model's own (`LearnedTermError`
    naming the model and the command that makes them where there are none); a `Fitted` or a weights file as given
    (checked: fitted for this model). Under None a weights file fitted for another version of the model (its scene
    edited since) is not used, with a warning naming it."""
    if learned is False:
        return None
    if learned is None:
        path = path_of(model)
        if not path.exists():
            return None
        try:
            return _own(path, model)
        except LearnedTermError as e:
            warnings.warn(f"{e}: planning without the learned physics term (`calibrate --learn --model "
                          f"{model.path}` fits it again)", stacklevel=3)
            return None
    if learned is True:
        path = path_of(model)
        if not path.exists():
            raise LearnedTermError(f"model {model.name!r} has no learned physics term ({path} is missing): "
                                   f"`python -m experiments calibrate --learn --model {model.path}` makes it")
        return _own(path, model)
    if isinstance(learned, Fitted):
        if learned.digest != model.digest:
            raise LearnedTermError(f"learned term fitted for another model (digest {learned.digest[:12]}), not "
                                   f"{model.name!r} (digest {model.digest[:12]})")
        if tuple(learned.features) != _names(model):
            raise LearnedTermError(f"learned term fitted on inputs {list(learned.features)}, not {list(_names(model))}"
                                   f" (`learned.input_names` of {model.name!r})")
        return learned
    return load(learned, model, _names(model))


_OWN: dict = {}  # (file, its mtime and size, the model's digest) -> Fitted: a model's own weights, read once


def _own(path: pathlib.Path, model) -> "Fitted":
    """A model's own weights file, read once per version of the file (every `Surrogate()` of the model asks)."""
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size, model.digest)
    if key not in _OWN:
        _OWN[key] = load(path, model, _names(model))
    return _OWN[key]


def has_own(model) -> bool:
    """Whether `model`'s scene has weights fitted for it (what `Surrogate(model)` then uses by default)."""
    return resolve(None, model) is not None


def _names(model) -> tuple[str, ...]:
    from gsp_jax.model import grasps  # a model's grasp space

    return input_names(grasps.space_of(model.hand))


def path_of(model) -> pathlib.Path:
    """Where a model's weights live: beside its scene file, `<scene stem>.learned.npz` (a `gsp_jax.Model`)."""
    return model.path.with_name(model.path.stem + ".learned.npz")


def tag(fitted: Fitted) -> str:
    """A short hash of the weights (what a cache of results made with them is keyed on)."""
    h = hashlib.sha256(fitted.digest.encode())
    for leaf in jax.tree.leaves((fitted.params, fitted.mean, fitted.std)):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()[:12]


def save(fitted: Fitted, path) -> pathlib.Path:
    """Weights and their context in one .npz (written whole): parameters, mean, std, and a JSON header (the
    hidden widths, feature names, the model's digest, the history, the split)."""
    leaves, treedef = jax.tree.flatten(fitted.params)
    members = len(leaves[0])
    header = dict(hidden=list(fitted.hidden), members=members, features=list(fitted.features), digest=fitted.digest,
                  history=[list(h) for h in fitted.history], split=fitted.split, treedef=str(treedef))
    arrays = {f"param{i}": np.asarray(x) for i, x in enumerate(leaves)}
    return files.savez(path, mean=np.asarray(fitted.mean), std=np.asarray(fitted.std),
                       header=np.array(json.dumps(header)), **arrays)


def load(path, model, names: Sequence[str] | None = None) -> Fitted:
    """Weights saved by `save`, for `model` (a `gsp_jax.Model`): `LearnedTermError` naming the model where
    they were fitted for another model (its digest), other features than `names`, or lack a field."""
    path = pathlib.Path(path)
    try:
        with np.load(path) as d:
            data = {k: d[k] for k in d.files}
    except (OSError, ValueError) as e:
        raise LearnedTermError(f"{path}: not readable weights ({e})") from None
    for field in ("mean", "std", "header"):
        if field not in data:
            raise LearnedTermError(f"{path}: no field {field!r}")
    header = json.loads(str(data["header"]))
    if header["digest"] != model.digest:
        raise LearnedTermError(f"{path}: fitted for another model (digest {header['digest'][:12]}), not "
                               f"{model.name!r} (digest {model.digest[:12]})")
    if names is not None and list(names) != header["features"]:
        raise LearnedTermError(f"{path}: fitted on features {header['features']}, not {list(names)}")
    members = header.get("members")  # None: one network, saved without the members' axis
    template = _MLP(tuple(header["hidden"])).init(jax.random.PRNGKey(0), jnp.zeros((1, len(data["mean"]))))
    leaves, treedef = jax.tree.flatten(template)
    got = [data.get(f"param{i}") for i in range(len(leaves))]
    if any(g is None or g.shape != (() if members is None else (members,)) + t.shape for g, t in zip(got, leaves)):
        raise LearnedTermError(f"{path}: its parameters are not those of {members or 1} {header['hidden']} network(s)")
    got = [g[None] if members is None else g for g in got]
    return Fitted(jax.tree.unflatten(treedef, [jnp.asarray(g) for g in got]), jnp.asarray(data["mean"]),
                  jnp.asarray(data["std"]), tuple(header["hidden"]), tuple(header["features"]), header["digest"],
                  tuple(tuple(h) for h in header["history"]), header["split"])
