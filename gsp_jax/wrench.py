"""Wrench solve: contact forces in Coulomb friction cones that best realise a required wrench on the tool.

For K contacts at points p_k with inward unit normals n_k and friction coefficient mu, find forces f (K, 3)

    minimise   |S (G f - w)|^2 + rho * sum_k |f_k|^2     subject to   |f_k - (f_k . n_k) n_k| <= mu (f_k . n_k)

where G (6, 3K) maps contact forces to the net force and torque about `center`, w is the wrench the contacts
must supply, S = diag(1, 1, 1, 1/L, 1/L, 1/L) puts torques on the scale of forces (L = `torque_length`), and
rho penalises large forces (so a grasp of few, hard-pressed contacts scores worse than a spread one).
The objective value is the *wrench error*; `unmet` is the fraction |S(Gf - w)| / |S w| of the wrench that
the contacts cannot supply (the surrogate's falling test).

Solver: accelerated projected gradient with a fixed iteration count. The problem is strongly convex (rho > 0),
so the step 1/L_c (L_c = lambda_max(S G G^T S) + rho, from a 6x6 eigenvalue problem) and the constant momentum
(sqrt(k) - 1) / (sqrt(k) + 1), k = L_c / rho, converge linearly without restarts or a stopping test. We
chose this over `jaxopt.ProjectedGradient`: under `vmap` its data-dependent stopping runs every problem to the
slowest one's count and it was ~7x slower per batch here (`../shared/ENVIRONMENT.md`), while a fixed count
keeps shapes static and the whole DP table one kernel; tests check the optimum against scipy.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct


@dataclasses.dataclass(frozen=True)
class WrenchConfig:
    iterations: int = 150  # fixed accelerated projected-gradient iterations
    unroll: int = 1  # iterations per loop trip (`lax.scan`'s unroll): the same result, fewer loop trips on a GPU
    force_penalty: float = 0.01  # rho, weight of sum |f_k|^2 against the squared wrench residual
    torque_length: float = 0.05  # L [m]: a torque of 1 N m weighs like a force of 1/L N


@struct.dataclass
class WrenchResult:
    """Shapes for one problem (vmap adds leading axes)."""

    forces: jax.Array  # (K, 3) contact forces on the tool, world frame [N]
    residual: jax.Array  # (6,) G f - w: force [N] and torque [N m] the contacts leave unmet
    error: jax.Array  # () wrench error |S(G f - w)|^2 + rho |f|^2 [N^2]
    unmet: jax.Array  # () |S(G f - w)| / |S w|, fraction of the required wrench not realised


def project_cone(f: jax.Array, normal: jax.Array, mu: jax.Array) -> jax.Array:
    """Euclidean projection of forces (..., 3) onto the friction cones {|f_t| <= mu f_n} around unit normals
    (..., 3); mu is a scalar or broadcasts against (..., 1)."""
    fn = jnp.sum(f * normal, -1, keepdims=True)
    ft = f - fn * normal
    ft_norm = jnp.sqrt(jnp.sum(ft**2, -1, keepdims=True) + 1e-30)
    inside = ft_norm <= mu * fn
    polar = mu * ft_norm <= -fn
    fn_b = (fn + mu * ft_norm) / (1.0 + mu**2)  # projection onto the boundary ray
    boundary = fn_b * normal + (mu * fn_b / ft_norm) * ft
    return jnp.where(inside, f, jnp.where(polar, 0.0, boundary))


def grasp_matrix(points: jax.Array, center: jax.Array, xp=jnp) -> jax.Array:
    """G (6, 3K): stacked [I; [p_k - c]x] so that G @ f.ravel() is the net (force, torque about `center`).
    `xp` is the array module: jax.numpy (traceable) or numpy (float64 inputs stay float64)."""
    r = points - center  # (K, 3)
    zero = xp.zeros_like(r[:, 0])
    cross = xp.stack(
        [
            xp.stack([zero, -r[:, 2], r[:, 1]], -1),
            xp.stack([r[:, 2], zero, -r[:, 0]], -1),
            xp.stack([-r[:, 1], r[:, 0], zero], -1),
        ],
        -2,
    )  # (K, 3, 3), cross[k] @ f = r_k x f
    eye = xp.broadcast_to(xp.eye(3, dtype=points.dtype), cross.shape)
    return xp.concatenate([eye, cross], axis=1).transpose(1, 0, 2).reshape(6, -1)


def solve(
    points: jax.Array,
    normals: jax.Array,
    active: jax.Array,
    mu: jax.Array,
    wrench: jax.Array,
    center: jax.Array,
    cfg: WrenchConfig = WrenchConfig(),
    init: jax.Array | None = None,
    prefer: jax.Array | None = None,
    grip: float = 0.0,
) -> WrenchResult:
    """Best contact forces for one problem.

    points (K, 3), normals (K, 3) inward unit normals, active (K,) bool (inactive contacts carry no force),
    mu () friction coefficient, wrench (6,) required net (force [N], torque [N m] about `center` (3,)).
    `init` (K, 3): forces to start from (a warm start, e.g. the previous control tick's; default zero).
    `prefer` (K, 3): forces the penalty pulls towards instead of zero, rho |f - prefer|^2 (e.g. a grip along the
    normals: the solution then squeezes as far as the cones and the wrench allow; `error` keeps rho |f|^2).
    `grip` [N] >= 0: every active contact must press with at least this force along its normal (a hand that
    squeezes, as the physics' contact controller does): forces are f_k = grip n_k + g_k with g_k in the cone, an
    inner approximation of {f_n >= grip, |f_t| <= mu f_n}; `error` penalises rho |g|^2 (`prefer` then pulls g),
    `forces` and `init` are total forces f, and `unmet` stays relative to `wrench`. A grasp whose contacts cannot
    all press at once without turning the tool (say two opposed side contacts at different x with nothing to
    balance them) then leaves the wrench unmet.
    Differentiable (fixed iterations in a `lax.scan`); `vmap` it over problems. Matmuls run in full float32.
    """
    with jax.default_matmul_precision("highest"):
        return _solve(points, normals, active, mu, wrench, center, cfg, init, prefer, grip)


def _solve(points, normals, active, mu, wrench, center, cfg, init=None, prefer=None, grip=0.0) -> WrenchResult:
    dtype = points.dtype
    wrench, center, mu = (jnp.asarray(x, dtype) for x in (wrench, center, mu))  # one dtype (x64 mode mixes them)
    k = points.shape[0]
    scale = jnp.asarray([1.0, 1.0, 1.0] + [1.0 / cfg.torque_length] * 3, dtype)
    a = scale[:, None] * grasp_matrix(points, center) * jnp.repeat(active.astype(dtype), 3)[None]  # (6, 3K)
    base = (jnp.asarray(grip, dtype) * normals * active.astype(dtype)[:, None]).reshape(-1)  # (3K,) the grip
    b = scale * wrench - a @ base
    rho = cfg.force_penalty
    lip = jnp.linalg.eigvalsh(a @ a.T)[-1] + rho
    kappa_sqrt = jnp.sqrt(lip / rho)
    beta = (kappa_sqrt - 1.0) / (kappa_sqrt + 1.0)
    mask = active.astype(dtype)[:, None]

    def project(x):
        return project_cone(x.reshape(k, 3), normals, mu).reshape(-1) * jnp.repeat(mask[:, 0], 3)

    def iteration(carry, _):
        x, x_prev = carry
        y = x + beta * (x - x_prev)
        grad = a.T @ (a @ y - b) + rho * (y - target)
        return (project(y - grad / lip), x), None

    target = 0.0 if prefer is None else jnp.asarray(prefer, dtype).reshape(-1) * jnp.repeat(mask[:, 0], 3)
    x0 = jnp.zeros(3 * k, dtype) if init is None else project(jnp.asarray(init, dtype).reshape(-1) - base)
    (x, _), _ = jax.lax.scan(iteration, (x0, x0), None, length=cfg.iterations, unroll=cfg.unroll)
    res_scaled = a @ x - b
    return WrenchResult(
        forces=(x + base).reshape(k, 3),
        residual=res_scaled / scale,
        error=jnp.sum(res_scaled**2) + rho * jnp.sum(x**2),
        unmet=jnp.sqrt(jnp.sum(res_scaled**2)) / jnp.sqrt(jnp.sum((scale * wrench) ** 2) + 1e-12),
    )


def least_friction(points, normals, wrench, center, facets: int = 64, tol: float = 1e-4,
                   max_mu: float = 1e6) -> tuple[float, float]:
    """The least friction coefficient at which point contacts can supply a wrench at all, however hard they press:
    the infimum of mu over which {f in the Coulomb cones, G f = wrench} is non-empty. numpy/scipy, not jittable: a
    diagnosis (is a grasp physically able to hold the tool?), not a kernel.

    points (K, 3), normals (K, 3) inward unit normals of the contacts that carry force, wrench (6,) (force [N],
    torque [N m] about `center` (3,)). Each cone is replaced by the `facets`-sided pyramid circumscribing it, which
    contains the cone and lies inside the cone of mu / cos(pi / facets); a linear programme (scipy HiGHS) decides
    feasibility, bisection on mu brackets the infimum. Returns (lower, upper): the cones of any mu > upper can
    supply the wrench, those of mu < lower cannot (the infimum itself may need unbounded forces); (max_mu, inf) if
    not even mu = max_mu suffices (e.g. every normal on one side)."""
    import numpy as np
    from scipy.optimize import linprog

    points, normals = np.asarray(points, float).reshape(-1, 3), np.asarray(normals, float).reshape(-1, 3)
    wrench, center = np.asarray(wrench, float).reshape(6), np.asarray(center, float).reshape(3)
    k = len(points)
    if k == 0 or len(normals) != k or not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise ValueError(f"least_friction: points and normals must be finite (K, 3) arrays with K >= 1, got "
                         f"{len(points)} points and {len(normals)} normals")
    if not (isinstance(facets, int) and facets >= 3):
        raise ValueError(f"least_friction: facets must be an int >= 3, got {facets!r}")
    g = grasp_matrix(points, center, xp=np)  # float64
    # the pyramid's facets, d . f <= mu n . f for `facets` directions d across each normal, and pushing only
    # (-n . f <= 0): rows (facets + 1) per contact, as D - mu N with D and N independent of mu
    angles = np.linspace(0.0, 2 * np.pi, facets, endpoint=False)
    d_rows, n_rows = np.zeros((k, facets + 1, 3 * k)), np.zeros((k, facets + 1, 3 * k))
    for i, n in enumerate(normals):
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        d_rows[i, :facets, 3 * i : 3 * i + 3] = np.cos(angles)[:, None] * t1 + np.sin(angles)[:, None] * t2
        n_rows[i, :facets, 3 * i : 3 * i + 3] = n
        d_rows[i, facets, 3 * i : 3 * i + 3] = -n
    d_rows, n_rows = d_rows.reshape(-1, 3 * k), n_rows.reshape(-1, 3 * k)

    def feasible(mu: float) -> bool:
        res = linprog(np.zeros(3 * k), A_ub=d_rows - mu * n_rows, b_ub=np.zeros(len(d_rows)), A_eq=g, b_eq=wrench,
                      bounds=[(None, None)] * (3 * k), method="highs")
        if res.status not in (0, 2):  # 0 solved, 2 infeasible; anything else would bias the bracket
            raise RuntimeError(f"least_friction: the LP at mu = {mu:g} ended with status {res.status}: {res.message}")
        return res.status == 0

    if feasible(0.0):
        return 0.0, 0.0
    lo, hi = 0.0, 1.0
    while not feasible(hi):
        if hi >= max_mu:
            return float(max_mu), float("inf")
        lo, hi = hi, min(10.0 * hi, max_mu)
    while hi - lo > tol * max(hi, 1e-3):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if feasible(mid) else (mid, hi)
    return float(lo), float(hi / np.cos(np.pi / facets))
