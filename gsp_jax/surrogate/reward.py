"""The shaped reward (the paper's Sec. IV-B, plus the grasp-change term): its configuration, its terms, and the pure
functions that turn solved IK and wrench problems into terms and terms into the reward. The surrogate's step
(`Surrogate.step`, `Surrogate.score`) and the DP table (`dp.table_from_terms`) both call these; neither assembles
the reward itself.

A decision at waypoint t moves the grasp g to g' (the null action keeps it; every other action sets one contact link
to one option). Its terms:

  (a) wrench_move   wrench error against gravity and the desired tool acceleration, g' realised by IK at the
                    *current* tool pose,
  (b) ik_next       IK error of g' realised at the *next* desired pose (waypoint t+1),
  (c) wrench_hold   wrench error against gravity with the contacts of that second IK,
  (d) wrench_ext    at the last step only: wrench error against gravity plus the external wrench w_ext,
  (e) redundant     1 if a non-null action left the grasp unchanged (the null action is free),
  (f) wrench_change when the grasp changes: wrench error of the *shared* grasp (g without the link that moves,
                    `GraspSpace.shared`; the contact controller unloads that link, moves it and loads it again)
                    realised at the current pose, against the same moving wrench as (a): the links that stay
                    must carry the tool through the change. 0 for the null action, and 0 at waypoints t <
                    `supported_steps`, where the tool still rests on its start support (the physics' pedestals
                    stay for the first segment).

(a)-(d) depend on the new grasp g' and the waypoint only (`arrival`); (e) and (f) are the previous grasp's part
(`with_previous`). A step's terms are built by these functions in the order `ORDER` names (each reads or
overwrites what the ones before it set). The reward is -(weighted sum), capped at `max_step_cost`, or `r_min` when
either IK collides, any wrench term leaves more than `fall_unmet` of its wrench unmet (the tool falls; (f) counts
when `change_falls`), or at the last step the forces the hand's motors can give leave more than `motor_fall_unmet`
of (d) unmet (`RewardTerms.motor_unmet`); `r_min` ends the episode.

The learned physics term (`Surrogate(learned=...)`, on by default where the model has weights; `learned=False`: the
paper's surrogate): a network fitted on a physics corpus of the model (`gsp_jax.surrogate.learned`) gives each
transition its probability p of a fall in the segment (`RewardTerms.fall_risk`), a chance node after the decision (the
paper's lookahead is expectimax). A transition with p above `risk_falls` is a fall; below it, the step's reward is its
expectation, (1 - p) times the analytic reward plus p times `r_min`, and what follows it counts only if the segment
held: every planner backs values up as reward + (1 - p) * value of the next state (`backed_up`, `expected_return`), so a
sequence's value is its expected return with a fall ending it at `r_min`. Without the term p = 0 and both are the plain
sums. The analytic terms stay: the network reads them (`learned.FEATURES`) and corrects them. The rule is written here
only: a step's chance to hold (`chance_to_hold`), its expected reward (`expected_reward`), the backup (`backed_up`), the
return walked forwards step by step (`accumulated`) or summed over a sequence (`expected_return`, `held_through`); every
planner, the environment and the offline returns call these.

The calibrated defaults (`CALIBRATED_FIELDS`) are read from the data file `models/reward_calibration.json`
(`CALIBRATION_JSON`), which `python -m experiments calibrate --write` writes through `write_calibration`: when the
first `RewardConfig` is built (`calibration`, cached), not when this module is imported.
"""
from __future__ import annotations

import dataclasses
import datetime
import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from gsp_jax.core import files
from gsp_jax.model.hand import MODELS_DIR
from gsp_jax.model.scenario import M0

CALIBRATION_JSON = MODELS_DIR / "reward_calibration.json"
# The fields of `RewardConfig` whose defaults the calibration chooses, and their types.
CALIBRATED_FIELDS = {"grip": float, "grip_scales_with_mass": bool, "fall_unmet": float, "w_wrench_change": float,
                     "change_falls": bool}
UNMET_TERMS = ("the wrench while moving (a)", "the hold at the next waypoint (c)",
               "the external wrench at the final pose (d)", "the shared grasp during the change (f)")


class CalibrationError(ValueError):
    """The reward's calibration file is missing or malformed; the message names the file and the field."""


def _checked(values, where: str) -> dict:
    """`values` as {field: value} of exactly `CALIBRATED_FIELDS`, each of its type (an int is a float); else
    CalibrationError naming `where` and the field."""
    if not isinstance(values, dict):
        raise CalibrationError(f"{where}: expected an object of {sorted(CALIBRATED_FIELDS)}, got {values!r}")
    missing, unknown = set(CALIBRATED_FIELDS) - set(values), set(values) - set(CALIBRATED_FIELDS)
    if missing or unknown:
        raise CalibrationError(f"{where}: fields missing {sorted(missing)}, unknown {sorted(unknown)} "
                               f"(expected exactly {sorted(CALIBRATED_FIELDS)})")
    out = {}
    for name, kind in CALIBRATED_FIELDS.items():
        value = values[name]
        if kind is bool:
            ok = isinstance(value, (bool, np.bool_))
        else:
            ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_)) \
                and bool(np.isfinite(value))
        if not ok:
            raise CalibrationError(f"{where}.{name}: expected a {'bool' if kind is bool else 'finite number'}, "
                                   f"got {value!r}")
        out[name] = kind(value)
    return out


def read_calibration(path: str | pathlib.Path = CALIBRATION_JSON) -> tuple[dict, dict]:
    """(calibrated, measured) from a calibration file: `calibrated` the `CALIBRATED_FIELDS` values, `measured`
    the figures the calibration measured for them (a flat object of numbers and strings; see `write_calibration`).
    CalibrationError naming the file and the field when it is missing or malformed."""
    path = pathlib.Path(path)
    try:
        data = files.read_json(path)
    except files.UnreadableFile as e:
        raise CalibrationError(f"the reward's calibration: {e} (`python -m experiments calibrate --write` writes "
                               "it)") from None
    if not isinstance(data, dict) or not {"calibrated", "measured"} <= set(data):
        raise CalibrationError(f"{path}: expected an object with 'calibrated' and 'measured', got "
                               f"{sorted(data) if isinstance(data, dict) else type(data).__name__}")
    measured = data["measured"]
    if not isinstance(measured, dict):
        raise CalibrationError(f"{path}: measured: expected an object, got {measured!r}")
    return _checked(data["calibrated"], f"{path}: calibrated"), measured


@functools.cache
def calibration() -> tuple[dict, dict]:
    """(calibrated, measured) of `CALIBRATION_JSON` (`read_calibration`), read once, when first asked for: the
    first `RewardConfig` built, or `CALIBRATED` / `MEASURED` read. `write_calibration` to that file reads it again."""
    return read_calibration()


def __getattr__(name: str):
    """`CALIBRATED` and `MEASURED`: the calibration file's two parts (`calibration`), read on first use."""
    if name in ("CALIBRATED", "MEASURED"):
        return calibration()[name == "MEASURED"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _Calibrated:
    """The default of a calibrated field of `RewardConfig`: the calibration file's value, read when the config is
    built (`calibration`)."""

    def __repr__(self) -> str:
        return "<calibrated>"


CALIBRATED_DEFAULT = _Calibrated()


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """Weights and thresholds of the shaped reward (one place for each). Defaults marked calibrated
    (`CALIBRATED_DEFAULT`) are read from `CALIBRATION_JSON` when a config is built (`calibration`)."""

    w_wrench_move: float = 1.0  # (a), >= 0
    w_ik: float = 1.0  # (b) per `ik_scale` of IK error, >= 0
    w_wrench_hold: float = 1.0  # (c), >= 0
    w_wrench_ext: float = 1.0  # (d), >= 0
    w_redundant: float = 0.05  # (e), >= 0
    w_wrench_change: float = CALIBRATED_DEFAULT  # (f), >= 0; calibrated
    change_falls: bool = CALIBRATED_DEFAULT  # (f) leaving more than fall_unmet unmet is a fall; calibrated
    supported_steps: int = 1  # int >= 0: (f) is 0 for decisions at waypoints t < this (the tool on its start support)
    grip: float = CALIBRATED_DEFAULT  # [N] >= 0: every realised contact presses with at least this; calibrated
    grip_scales_with_mass: bool = CALIBRATED_DEFAULT  # grip times m / m0 (the problem then stays
    # positively homogeneous in the tool's mass); calibrated
    ik_scale: float = 0.01  # [m] > 0: an IK error of ik_scale costs w_ik
    wrench_scale: float = (M0 * 9.81) ** 2  # [N^2] > 0: wrench errors are divided by this, (m0 g)^2
    contact_tol: float = 0.005  # [m] > 0: a link within this of its contact point carries force
    fall_unmet: float = CALIBRATED_DEFAULT  # > 0, a fraction: unmet share of a required wrench above which the
    # tool falls; calibrated
    motor_fall_unmet: float = 0.3  # > 0, a fraction (inf: no motor check): unmet share of the final wrench (d) under
    # the hand's motors' torque limits (`RewardTerms.motor_unmet`) above which the tool falls
    motor_iterations: int = 150  # int >= 1: iterations of that motor-limited wrench solve ("apg")
    max_step_cost: float = 10.0  # > 0: cap on a non-failing step's analytic cost ...
    r_min: float = -200.0  # < -max_step_cost: the reward of a failing step, below any T non-failing steps' sum
    risk_falls: float = 0.9  # in (0, 1): a transition whose learned fall probability exceeds this is a fall (a
    # tighter one leaves more episodes with no feasible sequence, where planners choose among falls:
    # docs/learned-physics.md)

    def __post_init__(self):
        for name in CALIBRATED_FIELDS:
            if getattr(self, name) is CALIBRATED_DEFAULT:
                object.__setattr__(self, name, calibration()[0][name])
        for name in ("w_wrench_move", "w_ik", "w_wrench_hold", "w_wrench_ext", "w_redundant", "w_wrench_change"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"RewardConfig.{name}: a weight must be >= 0, got {getattr(self, name)}")
        for name in ("ik_scale", "wrench_scale", "contact_tol", "fall_unmet", "motor_fall_unmet", "max_step_cost"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RewardConfig.{name}: must be > 0, got {getattr(self, name)}")
        if not self.grip >= 0:
            raise ValueError(f"RewardConfig.grip: must be >= 0 [N], got {self.grip}")
        for name in ("grip_scales_with_mass", "change_falls"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"RewardConfig.{name}: must be a bool, got {getattr(self, name)!r}")
        if not (isinstance(self.motor_iterations, int) and self.motor_iterations >= 1):
            raise ValueError(f"RewardConfig.motor_iterations: must be an int >= 1, got {self.motor_iterations!r}")
        if not (isinstance(self.supported_steps, int) and self.supported_steps >= 0):
            raise ValueError(f"RewardConfig.supported_steps: must be an int >= 0, got {self.supported_steps!r}")
        if not 0 < self.risk_falls < 1:
            raise ValueError(f"RewardConfig.risk_falls: must be in (0, 1), got {self.risk_falls}")
        if not self.r_min < -self.max_step_cost:
            raise ValueError(f"RewardConfig.r_min: must be < -max_step_cost = {-self.max_step_cost}, got {self.r_min}")

    @property
    def max_waypoints(self) -> int:
        """The most waypoints T an episode may have: failing (r_min) costs more than any T held steps (each at most
        the capped analytic cost)."""
        return int(np.ceil(-self.r_min / self.max_step_cost)) - 1

    @property
    def prices_changes(self) -> bool:
        """Whether the change term (f) enters the reward at all (a weight or its fall check)."""
        return self.w_wrench_change != 0 or self.change_falls


@struct.dataclass
class RewardTerms:
    """The reward of one step, term by term (unweighted, normalised as in `RewardConfig`). Shapes for one step."""

    wrench_move: jax.Array  # () (a) / wrench_scale
    ik_next: jax.Array  # () (b) / ik_scale
    wrench_hold: jax.Array  # () (c) / wrench_scale
    wrench_ext: jax.Array  # () (d) / wrench_scale; 0 before the last step
    redundant: jax.Array  # () (e) 0 or 1
    wrench_change: jax.Array  # () (f) / wrench_scale; 0 when the grasp does not change
    unmet: jax.Array  # (4,) unmet wrench fractions of (a), (c), (d), (f) (`UNMET_TERMS`)
    motor_unmet: jax.Array  # () unmet fraction of (d) (0 before the last step) with forces within the motors' torque
    # limits: solved with the limits, then each contact scaled down where its joints' limits still bind
    collision: jax.Array  # () bool
    fall: jax.Array  # () bool
    reward: jax.Array  # () the step's reward
    invalid: jax.Array  # () bool, the episode's inputs are out of range (`surrogate.episode_ok`): reward r_min, done
    fall_risk: jax.Array  # () the learned physics term's probability of a fall in this segment (0 without one): what
    # follows the step counts with 1 - fall_risk (`backed_up`)

    @classmethod
    def zeros(cls) -> "RewardTerms":
        z = jnp.zeros((), jnp.float32)
        f = jnp.array(False)
        return cls(z, z, z, z, z, z, jnp.zeros(4, jnp.float32), z, f, f, z, f, z)


def wrench_term(cfg: RewardConfig, solved) -> tuple[jax.Array, jax.Array]:
    """(normalised error, unmet fraction) of a solved wrench problem (`wrench.WrenchResult`; any leading shape)."""
    return solved.error / cfg.wrench_scale, solved.unmet


def arrival(cfg: RewardConfig, move, hold, ext, ik_next: jax.Array, collision: jax.Array, motor_unmet, is_last
            ) -> RewardTerms:
    """The terms of arriving in a grasp g' by a step from waypoint t, without the previous grasp's part (not
    redundant, no change; no fall or reward yet: `with_previous`). `move`, `hold`, `ext`: the solved wrench problems
    (a), (c), (d) (`wrench.WrenchResult`); `ik_next` () [m] the IK error of g' at waypoint t+1; `collision` () bool,
    either IK collides; `motor_unmet` () the unmet fraction of (d) under the motors (None: not checked, 0);
    `is_last` () bool, t is the last step (before it (d) and the motor check are 0)."""
    zero = jnp.zeros((), jnp.float32)
    motor_unmet = zero if motor_unmet is None else jnp.where(is_last, motor_unmet, 0.0)
    return RewardTerms(
        wrench_move=move.error / cfg.wrench_scale,
        ik_next=ik_next / cfg.ik_scale,
        wrench_hold=hold.error / cfg.wrench_scale,
        wrench_ext=jnp.where(is_last, ext.error / cfg.wrench_scale, 0.0),
        redundant=zero,
        wrench_change=zero,
        unmet=jnp.stack([move.unmet, hold.unmet, jnp.where(is_last, ext.unmet, 0.0), jnp.zeros(())]),
        motor_unmet=motor_unmet,
        collision=collision,
        fall=jnp.array(False),
        reward=jnp.zeros(()),
        invalid=jnp.array(False),
        fall_risk=zero,
    )


def with_previous(cfg: RewardConfig, terms: RewardTerms, redundant, changed, change_error, change_unmet, t
                  ) -> RewardTerms:
    """`terms` with the previous grasp's part set -- the redundant flag (e), and when `changed` at a waypoint `t` >=
    `supported_steps` the change term (f) (`change_error` normalised, `change_unmet` a fraction: the shared grasp's
    moving-wrench term) -- and the fall flag and the reward recomputed (the fall flag afresh: before `with_motor`,
    `with_risk` and `with_invalid`, `ORDER`). Broadcasts (the terms' leading shape)."""
    changed = jnp.asarray(changed, bool) & (jnp.asarray(t) >= cfg.supported_steps)
    shape = terms.wrench_move.shape
    change_error = jnp.broadcast_to(jnp.where(changed, change_error, 0.0), shape)
    change_unmet = jnp.broadcast_to(jnp.where(changed, change_unmet, 0.0), shape)
    unmet = jnp.concatenate([terms.unmet[..., :3], change_unmet[..., None]], axis=-1)
    counted = unmet if cfg.change_falls else unmet[..., :3]
    terms = terms.replace(
        redundant=jnp.broadcast_to(jnp.asarray(redundant, jnp.float32), shape),
        wrench_change=change_error,
        unmet=unmet,
        fall=jnp.any(counted > cfg.fall_unmet, axis=-1) | (terms.motor_unmet > cfg.motor_fall_unmet),
    )
    return terms.replace(reward=total(cfg, terms))


def with_motor(cfg: RewardConfig, terms: RewardTerms, motor_unmet) -> RewardTerms:
    """`terms` of steps scored without the motor check (`motor_unmet` 0: `Surrogate.score_deferred`) with it:
    `motor_unmet` (broadcasting with the terms; 0 where the step is not the last) set, the fall flag and the reward
    recomputed (after `with_previous`, before `with_risk`: `ORDER`). Broadcasts."""
    motor_unmet = jnp.broadcast_to(jnp.asarray(motor_unmet, jnp.float32), terms.wrench_move.shape)
    terms = terms.replace(motor_unmet=motor_unmet, fall=terms.fall | (motor_unmet > cfg.motor_fall_unmet))
    return terms.replace(reward=total(cfg, terms))


def of_transitions(cfg: RewardConfig, arrived: RewardTerms, next_grasp, redundant, changed, shared, t) -> RewardTerms:
    """The terms of many transitions at once from the arrival terms of every grasp (leaves (G, T, ...): `arrival` of
    each grasp at each waypoint): each transition reads its new grasp's terms, adds its redundant flag and, as its
    change term (f), the shared grasp's moving-wrench term (a) at its waypoint. `next_grasp`, `redundant`,
    `changed`, `shared` (the grasp that stays during the change): arrays of one shape S (e.g. (G, A)); `t` (T,)
    the waypoints. Returns terms with leaves (*S, T, ...)."""
    terms = jax.tree.map(lambda x: x[next_grasp], arrived)  # (*S, T, ...)
    if cfg.prices_changes:
        change_error, change_unmet = arrived.wrench_move[shared], arrived.unmet[shared][..., 0]
    else:
        change_error = change_unmet = jnp.zeros((), jnp.float32)
    return with_previous(cfg, terms, redundant[..., None], changed[..., None], change_error, change_unmet, t)


def with_risk(cfg: RewardConfig, terms: RewardTerms, fall_risk: jax.Array) -> RewardTerms:
    """`terms` with the learned physics term: `fall_risk` (same shape) the predicted probability of a fall in the
    segment; above `risk_falls` the step is a fall, and the reward is recomputed (`total`; after `with_motor`, before
    `with_invalid`: `ORDER`). Broadcasts."""
    fall_risk = jnp.asarray(fall_risk, jnp.float32)
    terms = terms.replace(fall_risk=fall_risk, fall=terms.fall | (fall_risk > cfg.risk_falls))
    return terms.replace(reward=total(cfg, terms))


def total(cfg: RewardConfig, terms: RewardTerms) -> jax.Array:
    """The shaped reward from a step's terms: `r_min` where `terms.fall` or `terms.collision`; else the analytic
    reward -(weighted sum capped at `max_step_cost`) held with 1 - fall_risk and `r_min` with fall_risk (its
    expectation over the learned term's chance node; the analytic reward itself without the term). Broadcasts."""
    cost = (
        cfg.w_wrench_move * terms.wrench_move
        + cfg.w_ik * terms.ik_next
        + cfg.w_wrench_hold * terms.wrench_hold
        + cfg.w_wrench_ext * terms.wrench_ext
        + cfg.w_redundant * terms.redundant
        + cfg.w_wrench_change * terms.wrench_change
    )
    held = -jnp.minimum(cost, cfg.max_step_cost)
    return jnp.where(terms.collision | terms.fall, cfg.r_min, expected_reward(held, terms.fall_risk, cfg.r_min))


# ------------------------------------------------------------------ the learned term's chance node, written once
def chance_to_hold(fall_risk):
    """A step's chance that its segment held: 1 - `fall_risk` (the learned physics term's chance node); 1.0 for
    None (no term). What follows a step counts with this. Any array type (numpy too); broadcasts."""
    return 1.0 if fall_risk is None else 1.0 - fall_risk


def expected_reward(held, fall_risk, r_min):
    """A step's expected reward over its chance node: the reward `held` if the segment held, `r_min` with chance
    `fall_risk` (a fall ends the run); `held` itself for None (no term), as `chance_to_hold`. Any array type (numpy
    too); broadcasts."""
    return held if fall_risk is None else chance_to_hold(fall_risk) * held + fall_risk * r_min


def backed_up(reward, fall_risk, terminal, value_next) -> jax.Array:
    """A transition's value: its (expected) `reward` plus, unless `terminal` (None: never), the next state's value
    where the segment held (`chance_to_hold`): the expectimax backup every planner uses (DP, lookahead, PPO's
    advantages). `fall_risk` None: 0. Broadcasts."""
    hold = chance_to_hold(fall_risk)
    if terminal is None:
        return reward + hold * value_next
    return reward + jnp.where(terminal, 0.0, hold * value_next)


def accumulated(ret, reach, reward, fall_risk) -> tuple[jax.Array, jax.Array]:
    """One step of an expected return walked forwards: (`ret` + `reach` * `reward`, `reach` * the step's chance to
    hold), where `reach` is the chance that every earlier segment held (1 at the start): the running return of a
    rollout (`planning.rollout`) and of the environment (`learning.env`). Broadcasts."""
    return ret + reach * reward, reach * chance_to_hold(fall_risk)


def expected_return(rewards, fall_risk, alive, reach=None) -> jax.Array:
    """The expected return of steps along the last axis: sum over t of alive_t * rewards_t * prod_{s<t} (1 -
    fall_risk_s) (`backed_up` unrolled; `fall_risk` None: the plain sum of the alive steps' rewards). `reach`: the
    products prod_{s<t} already walked (a rollout's `Trajectory.reach`; `fall_risk` then unread)."""
    rewards = jnp.where(alive, rewards, 0.0)
    if reach is not None:
        return jnp.sum(reach * rewards, -1)
    if fall_risk is None:
        return jnp.sum(rewards, -1)
    hold = chance_to_hold(jnp.where(alive, fall_risk, 0.0))
    reach = jnp.cumprod(jnp.concatenate([jnp.ones_like(hold[..., :1]), hold[..., :-1]], -1), -1)
    return jnp.sum(reach * rewards, -1)


def held_through(fall_risk, alive) -> jax.Array:
    """The chance that every segment of the `alive` steps along the last axis held: the product of their chances
    to hold (1 where no step has a fall risk)."""
    return jnp.prod(jnp.where(alive, chance_to_hold(fall_risk), 1.0), -1)


def with_invalid(cfg: RewardConfig, terms: RewardTerms, invalid) -> RewardTerms:
    """`terms` of a step whose episode inputs are `invalid` (() bool): flagged, and its reward `r_min`. The last
    of `ORDER`."""
    return terms.replace(invalid=invalid, reward=jnp.where(invalid, cfg.r_min, terms.reward))


ORDER = (arrival, with_previous, with_motor, with_risk, with_invalid)
"""The order in which a step's terms are built; a step may skip one (`with_motor` before the last step, `with_risk`
without the learned term) but never reorder them: `with_previous` sets the fall flag afresh from the unmet fractions
and the motor check, so the flags that `with_motor` and `with_risk` add come after it; the learned term reads the
analytic terms, the motor check's included (`learned.transition_features`), so `with_risk` comes after
`with_motor`; `with_invalid` overrides the reward that the others recompute (`total`), so it comes last. Every
`with_*` function of this module is in it (tests/test_reward.py)."""


def explain_failure(cfg: RewardConfig, terms: RewardTerms, t: int, grasp: str) -> str | None:
    """Why one step (its terms, one step's shapes) ends the episode, in words, or None if it does not: a collision,
    the final wrench beyond the motors, or the first wrench term more than `fall_unmet` unmet. `grasp` labels the
    step's new grasp."""
    if bool(terms.collision):
        return f"t={t}: the hand collides (with the tool, the table or itself) holding {grasp}"
    if not bool(terms.fall):
        return None
    if float(terms.motor_unmet) > cfg.motor_fall_unmet:
        return (f"t={t}: {UNMET_TERMS[2]} is beyond the hand's motors: {100 * float(terms.motor_unmet):.0f}% unmet "
                f"with forces within their torque limits (> {100 * cfg.motor_fall_unmet:.0f}%) with grasp {grasp}")
    unmet = np.asarray(terms.unmet)
    if not np.any(unmet[:4 if cfg.change_falls else 3] > cfg.fall_unmet):
        return (f"t={t}: the learned physics term gives a fall {100 * float(terms.fall_risk):.0f}% likely "
                f"(> {100 * cfg.risk_falls:.0f}%) with grasp {grasp}")
    k = int(np.argmax(unmet - cfg.fall_unmet > 0))
    return f"t={t}: {UNMET_TERMS[k]} is {100 * unmet[k]:.0f}% unmet (> {100 * cfg.fall_unmet:.0f}%) with grasp {grasp}"


def write_calibration(path: str | pathlib.Path, values: dict, measured: dict, written: str | None = None
                      ) -> pathlib.Path:
    """Write a calibration file (atomically): `values` the `CALIBRATED_FIELDS` (checked: exactly those fields, of
    their types, and a valid `RewardConfig`), `measured` the figures measured for them (a flat object of numbers and
    strings, e.g. sets, backend, sequences, spearman, feasible_held, dp_opt_falls, dp_opt_changes), `written` the
    date (default today, ISO). Returns the path; `read_calibration` reads it back."""
    values = _checked(dict(values), "write_calibration: values")
    try:
        RewardConfig(**values)
    except ValueError as e:
        raise CalibrationError(f"write_calibration: values: {e}") from None
    if not isinstance(measured, dict) or not all(
            isinstance(v, (str, int, float, bool)) or v is None for v in measured.values()):
        raise CalibrationError(f"write_calibration: measured: expected a flat object of numbers and strings, got "
                               f"{measured!r}")
    doc = {"about": "The reward's calibrated defaults (gsp_jax.surrogate.reward.RewardConfig) and what the "
                    "calibration measured for them. Written by `python -m experiments calibrate --write`; rerun it "
                    "rather than editing by "
                    "hand.",
           "written": written or datetime.date.today().isoformat(),
           "calibrated": values, "measured": dict(measured)}
    written_to = files.write_json(path, doc)
    if pathlib.Path(path).resolve() == CALIBRATION_JSON.resolve():
        calibration.cache_clear()  # the next RewardConfig built reads the new defaults
    return written_to
