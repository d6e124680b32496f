"""The discrete grasp and action spaces.

A grasp gives every contact link one of its options (0 = "not in contact"); with the paper's counts
(3, 3, 2, 4, 2, 2) there are 288 grasps. Action 0 is the *null action*: it keeps the grasp (the paper, Sec. IV-A).
Every other action sets one link to one of its options ("moving only one finger at a time"), so there are
1 + 16 = 17 actions; a non-null action that sets a link to the option it already has leaves the grasp unchanged
and is *redundant* (the surrogate penalises it). Grasps are numbered in mixed radix, the first link varying
slowest; actions 1.. link by link, option by option.

Out-of-range actions. Every Python-level entry point (`Surrogate.step` and `GraspEnv.step` called with a concrete
action, the Gymnasium env, `policies.SequencePolicy` / `TablePolicy`) raises a ValueError naming the value
(`check_actions`). Inside `jit`/`vmap`, where nothing can raise, `apply` clips the action to [0, n_actions): -1
acts as action 0, n_actions and above as the last action. Validate actions before tracing, or wrap the jitted
function with `jax.experimental.checkify` around your own `checkify.check`.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from gsp_jax.model import hand as hand_lib

LINK_ABBREV = {"thumb": "T", "index": "I", "middle": "M", "ring": "R"}
NULL = 0  # the null action: keep the current grasp


@dataclasses.dataclass(frozen=True, eq=False)
class GraspSpace:
    n_options: tuple[int, ...]  # (L,) options per link, "not in contact" included
    link_names: tuple[str, ...]
    start_options: tuple[int, ...] = ()  # (L,) the model's default start grasp (`HandModel.start_options`)
    tip_options: tuple[int, ...] = ()  # (L,) the constant all-tips grasp (`HandModel.tip_options`)

    @functools.cached_property
    def radix(self) -> np.ndarray:  # (L,) place value of each link's option in the grasp index
        return np.cumprod((self.n_options[1:] + (1,))[::-1])[::-1].astype(np.int32)

    @property
    def n_links(self) -> int:
        return len(self.n_options)

    @property
    def n_grasps(self) -> int:
        return int(np.prod(self.n_options))

    @property
    def n_actions(self) -> int:
        return 1 + int(sum(self.n_options))

    @functools.cached_property
    def action_link(self) -> np.ndarray:  # (A,) link set by each action; -1 for the null action
        return np.concatenate([[-1], np.repeat(np.arange(self.n_links), self.n_options)]).astype(np.int32)

    @functools.cached_property
    def action_option(self) -> np.ndarray:  # (A,) option the action sets; -1 for the null action
        return np.concatenate([[-1]] + [np.arange(n) for n in self.n_options]).astype(np.int32)

    def decode(self, grasp: jax.Array) -> jax.Array:
        """Grasp index (...) -> per-link options (..., L)."""
        grasp = jnp.asarray(grasp, jnp.int32)
        return (grasp[..., None] // self.radix) % np.asarray(self.n_options, np.int32)

    def encode(self, options) -> jax.Array:
        """Per-link options (..., L) -> grasp index (...)."""
        return jnp.sum(jnp.asarray(options, jnp.int32) * self.radix, axis=-1)

    def check_actions(self, actions, field: str = "action") -> None:
        """Raise ValueError naming `field` and the first value outside [0, n_actions); traced values (inside
        `jit`/`vmap`) pass unchecked (see the module docstring)."""
        if isinstance(actions, jax.core.Tracer):
            return
        a = np.asarray(actions)
        if a.dtype.kind not in "iuf" or isinstance(actions, (bool, np.bool_)):  # a bool, a string, None, objects
            raise ValueError(f"{field}: {actions!r} is not an integer action (an int in [0, {self.n_actions}))")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{field}: {a[~np.isfinite(a)].ravel()[0]} is not an integer action")
        if not np.issubdtype(a.dtype, np.integer) and not np.all(a == np.round(a)):
            raise ValueError(f"{field}: {a.ravel()[a.ravel() != np.round(a.ravel())][0]} is not an integer action")
        bad = (a < 0) | (a >= self.n_actions)
        if np.any(bad):
            raise ValueError(f"{field}: {a[bad].ravel()[0]} is not in [0, {self.n_actions})")

    def checked(self, action, field: str = "action") -> jax.Array:
        """`action` as int32, checked (`check_actions`) if concrete, clipped into [0, n_actions) if traced."""
        self.check_actions(action, field)
        return jnp.clip(jnp.asarray(action, jnp.int32), 0, self.n_actions - 1)

    def _parts(self, grasp: jax.Array, action: jax.Array, xp=jnp):
        """(grasp, null?, option set, place value and current option of the action's link); broadcast, actions
        clipped into [0, n_actions) (traced: no check possible). `xp`: jax.numpy, or numpy for static tables."""
        grasp = xp.asarray(grasp, xp.int32)
        action = xp.clip(xp.asarray(action, xp.int32), 0, self.n_actions - 1)
        link = xp.maximum(xp.asarray(self.action_link)[action], 0)
        place = xp.asarray(self.radix)[link]
        current = (grasp // place) % xp.asarray(self.n_options, xp.int32)[link]
        return grasp, action == NULL, xp.asarray(self.action_option)[action], place, current

    def apply(self, grasp: jax.Array, action: jax.Array, xp=jnp) -> tuple[jax.Array, jax.Array]:
        """(next grasp, redundant?) after `action` from `grasp`; both broadcast. The null action keeps the grasp
        and is not redundant. Actions outside [0, n_actions) are clipped (see the module docstring)."""
        grasp, null, opt, place, current = self._parts(grasp, action, xp)
        return xp.where(null, grasp, grasp + (opt - current) * place), ~null & (opt == current)

    @functools.cached_property
    def transitions(self) -> np.ndarray:
        """(G, A) int32, numpy: `apply(g, a)`'s next grasp for every grasp and action, for static work at trace time
        (e.g. the lookahead's distinct leaves) without running JAX operations."""
        g, a = np.arange(self.n_grasps)[:, None], np.arange(self.n_actions)[None]
        return self.apply(g, a, np)[0].astype(np.int32)

    @functools.cached_property
    def shared_grasps(self) -> np.ndarray:
        """(G, A) int32, numpy: `shared(g, a)` for every grasp and action (static work, as `transitions`)."""
        g, a = np.arange(self.n_grasps)[:, None], np.arange(self.n_actions)[None]
        return self.shared(g, a, np).astype(np.int32)

    def shared(self, grasp: jax.Array, action: jax.Array, xp=jnp) -> jax.Array:
        """The grasp that holds the tool while `action` is executed from `grasp` (broadcast): `grasp` with the
        link the action moves released (the contact controller unloads it, moves it, then loads it again). The
        null action and a redundant one move nothing: `grasp` itself."""
        grasp, null, opt, place, current = self._parts(grasp, action, xp)
        return xp.where(~null & (opt != current), grasp - current * place, grasp)

    @functools.cached_property
    def _changes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every grasp index read as a change: per link, how many options on (mod its count) it moves that link
        (0: kept). (order, rank, count): the changes in order of how many links they move (stable), each change's
        position in that order, and how many move at most k links (k = 0..L)."""
        shifts = (np.arange(self.n_grasps)[:, None] // self.radix) % np.asarray(self.n_options)
        moved = (shifts != 0).sum(axis=1)
        order = np.argsort(moved, kind="stable").astype(np.int32)
        rank = np.empty_like(order)
        rank[order] = np.arange(self.n_grasps, dtype=np.int32)
        count = np.array([(moved <= k).sum() for k in range(self.n_links + 1)], np.int32)
        return order, rank, count

    def n_within(self, n_changes: int) -> int:
        """How many grasps differ from a given one in at most `n_changes` links (1, 11, 51, 133, ... for the
        paper's counts): every grasp `n_changes` actions can reach, as each action sets one link."""
        return int(self._changes[2][min(n_changes, self.n_links)])

    def within(self, grasp: jax.Array, n_changes: int) -> jax.Array:
        """(n_within(n_changes),) int32: the grasps that differ from `grasp` (scalar) in at most `n_changes` links,
        in a fixed order by how many (`grasp` itself first), so the first n_within(k) are those within k changes."""
        order = self._changes[0][: self.n_within(n_changes)]
        n = np.asarray(self.n_options, np.int32)
        return self.encode((self.decode(grasp) + self.decode(jnp.asarray(order))) % n)

    def rank_within(self, grasp: jax.Array, other: jax.Array) -> jax.Array:
        """Position of `other` in `within(grasp, k)` for any k at least the number of links they differ in."""
        n = np.asarray(self.n_options, np.int32)
        change = self.encode((self.decode(other) - self.decode(grasp)) % n)
        return jnp.asarray(self._changes[1])[change]

    def label(self, grasp: int) -> str:
        """Readable grasp, one token per link: e.g. 'T1 I1 . M2 . .' (letter = finger, digit = option)."""
        opts = np.asarray(self.decode(grasp))
        return " ".join(
            f"{LINK_ABBREV.get(n.split('_')[0], n[0].upper())}{'m' if n.endswith('medial') else ''}{o}" if o else "."
            for n, o in zip(self.link_names, opts)
        )

    def action(self, link: str, option: int) -> int:
        """The action that sets `link` (a name of `link_names`) to `option`."""
        if link not in self.link_names:
            raise ValueError(f"link: {link!r} is not one of {self.link_names}")
        li = self.link_names.index(link)
        if not 0 <= option < self.n_options[li]:
            raise ValueError(f"option: {option} is not in [0, {self.n_options[li]}) for link {link!r}")
        return int(np.flatnonzero((self.action_link == li) & (self.action_option == option))[0])

    def action_label(self, action: int) -> str:
        if action == NULL:
            return "keep"
        link, opt = self.link_names[self.action_link[action]], self.action_option[action]
        return f"{link}->{'off' if opt == 0 else opt}"


def space_of(hand: hand_lib.HandModel) -> GraspSpace:
    return _space(hand)


@functools.lru_cache(maxsize=16)
def _space(hand: hand_lib.HandModel) -> GraspSpace:  # one per hand object (hashed by identity)
    return GraspSpace(n_options=tuple(hand.n_options), link_names=hand.link_names, start_options=hand.start_options,
                      tip_options=hand.tip_options)
