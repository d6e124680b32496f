"""Tolerances for comparing two float32 computations of the same surrogate quantity (vmapped vs looped, table vs
step, another CPU's instruction set), taken from the precision the solvers reach.

Measured with `python -m experiments precision` (results/precision/precision.json; 2-core Xeon with AVX-512,
2026-11-23): the reward terms of every (grasp, waypoint) of two 16-waypoint episodes (nominal, evalB
mass1.5m0_comy+2cm; 1,821 entries where neither computation fails, of 9,216) computed natively, against the same
with XLA's CPU code restricted to SSE4.2 (another CPU's last bits: the AMD AVX2 failures of issue 12 reproduce
there), with every episode input moved by +-1 ulp (3 seeds), and in float64:

* wrench terms and unmet fractions: |diff| 99th percentile 1.5e-6 .. 3.6e-6;
* the reward (dominated by the IK error term (b)): median 5e-7, 99th percentile 2.2e-4 .. 1.6e-3; the IK error
  itself: 99th percentile 8 .. 11 um. Then a tail of IK *bifurcations*: 0.6 .. 1.3 % of entries differ by more
  than 1e-3, up to 0.31 (an IK error 3.1 mm apart), where the Levenberg-Marquardt accept/reject test takes
  another branch and the solver stops elsewhere (mostly unconverged IK, > 1 mm error). No tolerance covers
  those and still tests anything;
* the DP value of every grasp at waypoint 0 (a max over actions, along converged grasps): at most 1.6e-4;
* fail/survive outcomes: at most 2 flips in 9,216 entries (a collision at its threshold).
(Restricted to AVX2 on that Xeon, XLA's code is bit-identical to native.)

So comparisons use a tolerance a few times the bulk precision and allow *rare ties*: entries outside it count as
solver bifurcations, and a test asserts there are at most `TIE_FRACTION` of them (none in small comparisons).
"""
from __future__ import annotations

import numpy as np

REWARD_ATOL = 3e-3  # one reward or term in reward units: 2x the largest 99th percentile (1.6e-3)
RETURN_ATOL = 1e-3  # a DP value or optimal return: 6x the largest measured (1.6e-4)
WRENCH_ATOL = 1e-5  # a wrench term or unmet fraction (normalised): 3x the largest 99th percentile (3.6e-6)
IK_ATOL = 3e-5  # an IK error [m]: 3x its largest 99th percentile (11 um); REWARD_ATOL at ik_scale = 1 cm
Q_ATOL = 1e-3  # joint angles [rad] of converged IK: rounding moves a joint along flat directions (~3e-5 rad seen)
TIE_FRACTION = 0.03  # at most this fraction of compared entries may be bifurcations (measured 0.6 .. 1.3 % > 1e-3)
FLIP_FRACTION = 1e-3  # at most this fraction of fail/survive outcomes may flip (measured <= 2 in 9,216: 2.2e-4)
UNMET_MARGIN = 5e-3  # a fall flag is compared only where unmet is this far from its threshold (>> its p99 3.6e-6)
# the physics status's tool angle, 2 arccos(q_ref . q) in float32, near 0: the dot resolves steps of 2^-24 below 1,
# so two computations a few ulps apart differ by 2 arccos(1 - k 2^-24): 0.040 deg at k = 1, 0.056 at 2 (seen under
# SSE4.2, tests/test_native.py), 0.069 at 3
STATUS_ANGLE_ATOL_DEG = float(np.degrees(2 * np.arccos(np.float64(1) - 3 * 2.0 ** -24)))


TIE_RATE = 0.013  # the largest measured rate of bifurcations (entries > 1e-3 apart), for small comparisons below


def small_sample_tie_fraction(n: int, confidence: float = 0.99) -> float:
    """A `tie_fraction` for a comparison of only n entries: the `confidence` quantile of the number of bifurcations
    at the measured rate (Binomial(n, TIE_RATE)), as a fraction of n. floor(TIE_FRACTION * n) allows a single tie in
    33 to 66 entries, which a CPU with other last bits exceeds by chance (59 converged IK problems of
    tests/test_ik_lanes.py: 2 ties on an AMD EPYC with AVX-512, before issue 48's changes as after)."""
    from scipy.stats import binom

    allowed = max(binom.ppf(confidence, n, TIE_RATE), np.floor(TIE_FRACTION * n))
    return float(allowed + 0.5) / max(n, 1)  # + 0.5: floor(fraction * n) gives `allowed` back despite rounding


def assert_close_with_rare_ties(actual, desired, atol: float, err_msg: str = "", tie_fraction: float = TIE_FRACTION):
    """Assert |actual - desired| <= atol except at no more than floor(tie_fraction * n) entries (bifurcations);
    returns the mask (same shape) of entries that agree, for comparing what depends on them."""
    a, d = np.asarray(actual, np.float64), np.asarray(desired, np.float64)
    assert a.shape == d.shape, (a.shape, d.shape)
    ok = np.abs(a - d) <= atol
    allowed = int(np.floor(tie_fraction * a.size))
    if np.sum(~ok) > allowed:
        idx = np.argwhere(~ok)[:5].tolist()
        raise AssertionError(
            f"{err_msg}: {int(np.sum(~ok))} of {a.size} entries differ by more than {atol:g} (at most {allowed} "
            f"solver ties allowed); first at {idx}: {a[~ok][:5].tolist()} vs {d[~ok][:5].tolist()}"
        )
    return ok
