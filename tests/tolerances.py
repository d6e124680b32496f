"""Tolerances for comparing two float32 computations of the same surrogate quantity (vmapped vs looped, table vs
step, another CPU's instruction set), taken from the precision the solvers reach.

Measured with `python -m experiments precision` (results/precision/precision.json): the DP tables (288 grasps x
16 waypoints, nominal and evalB mass1.5m0_comy+2cm) computed natively on an AVX-512 Xeon, against the same with
XLA's CPU code restricted to SSE4.2 (another CPU's last bits) and with every episode input moved by +-1 ulp:

* wrench terms and unmet fractions: |diff| 99th percentile <= 1e-6, largest 4e-3 (where a contact's realisation
  flips at contact_tol);
* the IK error term (b) (and so the reward, which it dominates): median 5e-7, 99th percentile 1.0e-3 to 1.1e-3
  (an IK error reproducible to ~10 um), and a tail of IK *bifurcations*: 0.6-1.3 % of entries differ by more than
  1e-3, up to 0.31, where the Levenberg-Marquardt accept/reject test takes another branch and the solver stops
  elsewhere (mostly unconverged IK, > 1 mm error). No tolerance covers those and still tests anything;
* the DP value of every grasp at waypoint 0 (a max over actions, so along converged grasps): at most 1.6e-4;
* fail/survive outcomes: 1 flip in 4,608 (grasp, waypoint) entries, a collision at the threshold.

So comparisons use a tolerance a few times the bulk precision and allow *rare ties*: entries outside it count as
solver bifurcations, and a test asserts there are at most `TIE_FRACTION` of them (none in small comparisons).
"""
from __future__ import annotations

import numpy as np

REWARD_ATOL = 3e-3  # one reward or term in reward units: 3x the 99th percentile (1.0e-3 .. 1.1e-3)
RETURN_ATOL = 1e-3  # a DP value or optimal return: 6x the largest measured (1.6e-4)
WRENCH_ATOL = 1e-5  # a wrench term or unmet fraction (normalised): 10x the 99th percentile (<= 1e-6)
IK_ATOL = 3e-5  # an IK error [m]: 3x its 99th percentile (1e-5 m; REWARD_ATOL at ik_scale = 1 cm)
Q_ATOL = 1e-3  # joint angles [rad] of converged IK: rounding moves a joint along flat directions (~3e-5 rad seen)
TIE_FRACTION = 0.03  # at most this fraction of compared entries may be bifurcations (measured <= 1.3 % at 1e-3)
UNMET_MARGIN = 5e-3  # a fall flag is compared only where unmet is farther than this from the threshold (max 4e-3)


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
