"""Wrench solve: contact forces in Coulomb friction cones that best realise a required wrench on the tool.

For K contacts at points p_k with inward unit normals n_k and friction coefficient mu, find forces f (K, 3)

    minimise   |S (G f - w)|^2 + rho * sum_k |f_k|^2     subject to   |f_k - (f_k . n_k) n_k| <= mu (f_k . n_k)

where G (6, 3K) maps contact forces to the net force and torque about `center`, w is the wrench the contacts
must supply, S = diag(1, 1, 1, 1/L, 1/L, 1/L) puts torques on the scale of forces (L = `torque_length`), and
rho penalises large forces (so a grasp of few, hard-pressed contacts scores worse than a spread one).
The objective value is the *wrench error*; `unmet` is the fraction |S(Gf - w)| / |S w| of the wrench that
the contacts cannot supply (the surrogate's falling test).

Solvers (`WrenchConfig.method`), both with a fixed iteration count (static shapes: under `vmap` a data-dependent
stop runs every problem to the slowest one's count, and a library solver with a stopping test was slower per batch,
docs/performance.md; a fixed count keeps the whole DP table one kernel); tests check both against scipy.

* "newton" (default): semismooth Newton on the problem's dual, a smooth concave function of 6 variables (one per
  wrench component) whose generalised Hessian is negative definite everywhere (`_solve_newton`): each iteration
  is one 6x6 solve plus a line search whose step sizes are tried side by side. On the DP tables' problems (3
  evaluation episodes, 41,472 solves) 10 iterations give every unmet fraction within 1.5e-5 of 3,000 projected-
  gradient iterations' (150 of those: 5e-3); on a GPU one step's depth is what counts, and 10 Newton iterations
  replace 150 gradient ones (the surrogate step's times: docs/lookahead.md).
* "apg": accelerated projected gradient. The problem is strongly convex (rho > 0), so the step 1/L_c (L_c =
  lambda_max(S G G^T S) + rho, from a 6x6 eigenvalue problem) and the constant momentum (sqrt(k) - 1) / (sqrt(k) +
  1), k = L_c / rho, converge linearly without restarts or a stopping test, but slowly: after 150 iterations the
  unmet fraction is still off by up to 5e-3. Cheap per iteration and warm-startable, so the physics' contact
  controller runs it at every control tick (`physics.controller`). The reference of its numba copy
  `physics.native._solve` (and of `native._project`, this `project_cone`), which must equal it; checked by
  `tests/test_native.py::test_native_force_solve_is_the_wrench_solve`.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct


@dataclasses.dataclass(frozen=True)
class WrenchConfig:
    method: str = "newton"  # "newton": semismooth Newton on the 6-dim dual; "apg": accelerated projected gradient
    iterations: int = 150  # fixed accelerated projected-gradient iterations ("apg")
    newton_iterations: int = 10  # fixed Newton iterations ("newton")
    line_search: int = 8  # step sizes 1, 1/2, .. 2^-(n-1) tried side by side per Newton iteration ("newton")
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
    motors: "MotorLimits | None" = None,
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
    `motors` (`MotorLimits`, "apg" only): the joint torques the forces cost, |J^T f + offset|_j, are kept within
    the motors' limits by a quadratic penalty on their excess (zero inside the limits, so it redistributes
    forces only where a motor would saturate; `error` includes it).
    Differentiable (fixed iterations in a `lax.scan`); `vmap` it over problems. Matmuls run in full float32.
    """
    if cfg.method not in ("newton", "apg"):
        raise ValueError(f"WrenchConfig.method: 'newton' or 'apg', got {cfg.method!r}")
    if motors is not None and cfg.method != "apg":
        raise ValueError(f"solve: motors need WrenchConfig.method 'apg', got {cfg.method!r}")
    with jax.default_matmul_precision("highest"):
        if cfg.method == "newton":
            return _solve_newton(points, normals, active, mu, wrench, center, cfg, init, prefer, grip)
        return _solve(points, normals, active, mu, wrench, center, cfg, init, prefer, grip, motors)


@struct.dataclass
class MotorLimits:
    """The motors behind the contacts, for `solve`: contact forces f (K, 3) cost joint torques J^T f + offset."""

    jacobians: jax.Array  # (K, 3, J) d(contact point)/d(joint angles) of the link at each contact
    offset: jax.Array  # (J,) [N m] torques the motors give besides the contact forces (e.g. the fingers' gravity)
    limit: jax.Array  # (J,) [N m] > 0, the symmetric limit |tau_j| <= limit_j
    weight: float = 1.0  # the excess torque's weight, as weight |excess / L|^2 beside the wrench residual (1: the
    # controller's measured setting; 10 dropped a 2.5 m0 tool the plain solve holds)


def _solve(points, normals, active, mu, wrench, center, cfg, init=None, prefer=None, grip=0.0,
           motors=None) -> WrenchResult:
    dtype = points.dtype
    wrench, center, mu = (jnp.asarray(x, dtype) for x in (wrench, center, mu))  # one dtype (x64 mode mixes them)
    k = points.shape[0]
    scale = _scale(cfg, dtype)
    a = scale[:, None] * grasp_matrix(points, center) * jnp.repeat(active.astype(dtype), 3)[None]  # (6, 3K)
    base = (jnp.asarray(grip, dtype) * normals * active.astype(dtype)[:, None]).reshape(-1)  # (3K,) the grip
    b = scale * wrench - a @ base
    rho = cfg.force_penalty
    lip = jnp.linalg.eigvalsh(a @ a.T)[-1] + rho
    if motors is not None:  # torques t = jt x + t0 (J,), penalty (w / L^2) |relu(|t| - limit)|^2
        jt = (jnp.asarray(motors.jacobians, dtype) * active.astype(dtype)[:, None, None]).transpose(2, 0, 1)
        jt = jt.reshape(-1, 3 * k)  # (J, 3K)
        t0 = jnp.asarray(motors.offset, dtype) + jt @ base
        w_t = jnp.asarray(motors.weight, dtype) / cfg.torque_length**2
        lip = lip + w_t * jnp.linalg.eigvalsh(jt @ jt.T)[-1]

        def excess(x):
            t = jt @ x + t0
            return jnp.sign(t) * jax.nn.relu(jnp.abs(t) - motors.limit)
    kappa_sqrt = jnp.sqrt(lip / rho)
    beta = (kappa_sqrt - 1.0) / (kappa_sqrt + 1.0)
    mask = active.astype(dtype)[:, None]

    def project(x):
        return project_cone(x.reshape(k, 3), normals, mu).reshape(-1) * jnp.repeat(mask[:, 0], 3)

    def iteration(carry, _):
        x, x_prev = carry
        y = x + beta * (x - x_prev)
        grad = a.T @ (a @ y - b) + rho * (y - target)
        if motors is not None:
            grad = grad + w_t * (jt.T @ excess(y))
        return (project(y - grad / lip), x), None

    target = 0.0 if prefer is None else jnp.asarray(prefer, dtype).reshape(-1) * jnp.repeat(mask[:, 0], 3)
    x0 = jnp.zeros(3 * k, dtype) if init is None else project(jnp.asarray(init, dtype).reshape(-1) - base)
    (x, _), _ = jax.lax.scan(iteration, (x0, x0), None, length=cfg.iterations, unroll=cfg.unroll)
    result = _result(a, b, x, base, scale, wrench, rho)
    if motors is not None:
        result = result.replace(error=result.error + w_t * jnp.sum(excess(x) ** 2))
    return result


def _scale(cfg: WrenchConfig, dtype) -> jax.Array:
    """S (6,): 1 on the force rows, 1 / torque_length on the torque rows."""
    return jnp.asarray([1.0, 1.0, 1.0] + [1.0 / cfg.torque_length] * 3, dtype)


def _result(a, b, x, base, scale, wrench, rho) -> WrenchResult:
    """The result of forces x (3K,) beyond the grip `base` (3K,), for the scaled problem (a (6, 3K), b (6,))."""
    res_scaled = a @ x - b
    return WrenchResult(
        forces=(x + base).reshape(-1, 3),
        residual=res_scaled / scale,
        error=jnp.sum(res_scaled**2) + rho * jnp.sum(x**2),
        unmet=jnp.sqrt(jnp.sum(res_scaled**2)) / jnp.sqrt(jnp.sum((scale * wrench) ** 2) + 1e-12),
    )


def assess(forces: jax.Array, points: jax.Array, active: jax.Array, wrench: jax.Array, center: jax.Array,
           cfg: WrenchConfig = WrenchConfig()) -> WrenchResult:
    """The `WrenchResult` of given contact forces (K, 3) (not a solve): the residual G f - w, the error
    |S(G f - w)|^2 + rho |f|^2 and the unmet fraction, on the active (K,) contacts. `solve`'s result (without a
    grip or `prefer`), recomputed for forces a hand delivers (`saturate`)."""
    dtype = points.dtype
    wrench, center = jnp.asarray(wrench, dtype), jnp.asarray(center, dtype)
    mask3 = jnp.repeat(active.astype(dtype), 3)
    scale = _scale(cfg, dtype)
    base = jnp.zeros_like(mask3)
    with jax.default_matmul_precision("highest"):
        a = scale[:, None] * grasp_matrix(points, center) * mask3[None]  # (6, 3K)
        return _result(a, scale * wrench - a @ base, forces.reshape(-1) * mask3 - base, base, scale, wrench,
                       cfg.force_penalty)


def saturate(forces: jax.Array, jacobians: jax.Array, limit: jax.Array, link_joints: jax.Array) -> jax.Array:
    """Contact forces (K, 3) as motors of symmetric torque limits (J,) deliver them: the joint torques the forces
    cost are tau = sum_k J_k^T f_k (jacobians (K, 3, J)), and each contact's force is scaled by min(1, limit_j /
    |tau_j|) over the joints that move its link (link_joints (K, J) bool), so a finger whose motor would saturate
    pushes proportionally less (its direction kept: a first-order model of the motors' clipping)."""
    with jax.default_matmul_precision("highest"):
        tau = jnp.einsum("kij,ki->j", jacobians, forces)
    over = jnp.abs(tau) / limit  # (J,) > 1 where a motor saturates
    worst = jnp.max(jnp.where(link_joints, over[None, :], 0.0), axis=-1)  # (K,)
    return forces * jnp.minimum(1.0, 1.0 / jnp.maximum(worst, 1e-12))[:, None]


def cone_jacobian(f: jax.Array, normal: jax.Array, mu: jax.Array) -> jax.Array:
    """Jacobian (..., 3, 3) of `project_cone` at f (..., 3): the identity inside the cone, zero in its polar cone,
    and on the boundary branch v v^T / (1 + mu^2) + (mu fn_b / |f_t|) (I - n n^T - u u^T), v = n + mu u, u the
    unit tangential direction, fn_b the projection's normal force. Symmetric, eigenvalues in [0, 1]."""
    fn = jnp.sum(f * normal, -1, keepdims=True)
    ft = f - fn * normal
    s = jnp.sqrt(jnp.sum(ft**2, -1, keepdims=True))
    inside = s <= mu * fn
    polar = mu * s <= -fn
    safe = jnp.where(inside | polar, 1.0, jnp.maximum(s, 1e-30))
    u = ft / safe
    v = normal + mu * u
    fn_b = (fn + mu * s) / (1.0 + mu**2)
    eye = jnp.eye(3, dtype=f.dtype)
    outer = lambda a, b: a[..., :, None] * b[..., None, :]  # noqa: E731
    boundary = outer(v, v) / (1.0 + mu**2)[..., None] + (mu * fn_b / safe)[..., None] * (
        eye - outer(normal, normal) - outer(u, u))
    return jnp.where(inside[..., None], eye, jnp.where(polar[..., None], 0.0, boundary))


def _solve_newton(points, normals, active, mu, wrench, center, cfg, init=None, prefer=None, grip=0.0) -> WrenchResult:
    """Semismooth Newton on the dual. With u = A x - b the problem is min |u|^2 + rho |x - t|^2 over x in the cones;
    its dual function of y (6,) is g(y) = -|y|^2/4 - y.b + rho |x(y) - t|^2 + y.A x(y), x(y) = P(t - A^T y / 2 rho)
    (P the cone projection), concave and smooth with gradient -y/2 - b + A x(y), and a generalised Hessian -(I/2 +
    A J A^T / 2 rho) (J = dP, block diagonal 3x3) that is negative definite everywhere. So each iteration is one 6x6
    solve, and the step along it is the best of `line_search` halvings tried side by side (no sequential
    backtracking); x(y) lies in the cones at every iterate, and y* = 2 (A x* - b) gives warm starts."""
    dtype = points.dtype
    wrench, center, mu = (jnp.asarray(x, dtype) for x in (wrench, center, mu))
    k = points.shape[0]
    scale = _scale(cfg, dtype)
    mask3 = jnp.repeat(active.astype(dtype), 3)
    a = scale[:, None] * grasp_matrix(points, center) * mask3[None]  # (6, 3K)
    base = (jnp.asarray(grip, dtype) * normals * active.astype(dtype)[:, None]).reshape(-1)
    b = scale * wrench - a @ base
    rho = jnp.asarray(cfg.force_penalty, dtype)
    target = jnp.zeros(3 * k, dtype) if prefer is None else jnp.asarray(prefer, dtype).reshape(-1) * mask3
    a_blocks = a.reshape(6, k, 3).transpose(1, 0, 2)  # (K, 6, 3)

    def primal(y):  # x(y) (..., 3K) for y (..., 6)
        z = target - (y @ a) / (2.0 * rho)
        return project_cone(z.reshape(*z.shape[:-1], k, 3), normals, mu).reshape(z.shape) * mask3

    def dual(y, x):  # g(y) with x = x(y), and its rounding scale (the sum of its terms' magnitudes)
        terms = (-jnp.sum(y**2, -1) / 4, -(y @ b), rho * jnp.sum((x - target) ** 2, -1), jnp.sum(y * (x @ a.T), -1))
        return sum(terms), sum(jnp.abs(t) for t in terms)

    steps = 0.5 ** jnp.arange(cfg.line_search, dtype=dtype)

    def iteration(carry, _):
        y, x, g = carry
        grad = -y / 2 - b + a @ x
        z = target - (a.T @ y) / (2.0 * rho)
        jac = cone_jacobian(z.reshape(k, 3), normals, mu) * active.astype(dtype)[:, None, None]  # (K, 3, 3)
        hess = jnp.eye(6, dtype=dtype) / 2 + jnp.einsum("kia,kab,kjb->ij", a_blocks, jac, a_blocks) / (2.0 * rho)
        d = jnp.linalg.solve(hess, grad)
        ys = y[None] + steps[:, None] * d[None]  # (n, 6)
        xs = primal(ys)
        gs, mag = dual(ys, xs)
        # near the optimum g is flat to within its rounding: the largest step within that of the best value wins,
        # and is taken unless it is clearly worse (else float32 noise in g would reject the last Newton steps)
        tol = 1e-6 * jnp.max(mag)
        i = jnp.argmax(gs >= jnp.max(gs) - tol)  # steps run from 1 down: the first such is the largest
        better = gs[i] >= g - tol
        return (jnp.where(better, ys[i], y), jnp.where(better, xs[i], x), jnp.where(better, gs[i], g)), None

    x0 = (primal(jnp.zeros(6, dtype)) if init is None else
          project_cone(jnp.asarray(init, dtype).reshape(k, 3) - base.reshape(k, 3), normals, mu).reshape(-1) * mask3)
    y0 = 2.0 * (a @ x0 - b)
    x0 = primal(y0)
    (y, x, _), _ = jax.lax.scan(iteration, (y0, x0, dual(y0, x0)[0]), None, length=cfg.newton_iterations,
                                unroll=cfg.unroll)
    return _result(a, b, x, base, scale, wrench, rho)


def _lp_inputs(who: str, points, normals, wrench, center, facets):
    """The linear programmes' inputs as float64 arrays (points, unit normals (K, 3), wrench (6,), center (3,)),
    or a ValueError naming the bad one."""
    import numpy as np

    points, normals = np.asarray(points, float).reshape(-1, 3), np.asarray(normals, float).reshape(-1, 3)
    wrench, center = np.asarray(wrench, float).reshape(6), np.asarray(center, float).reshape(3)
    if len(points) == 0 or len(normals) != len(points) or not (np.all(np.isfinite(points)) and
                                                              np.all(np.isfinite(normals))):
        raise ValueError(f"{who}: points and normals must be finite (K, 3) arrays with K >= 1, got "
                         f"{len(points)} points and {len(normals)} normals")
    if not np.all(np.isfinite(wrench)):
        raise ValueError(f"{who}: wrench must be finite, got {wrench}")
    if not (isinstance(facets, int) and facets >= 3):
        raise ValueError(f"{who}: facets must be an int >= 3, got {facets!r}")
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True), wrench, center


def _pyramid_rows(normals, facets: int):
    """(D, N) with D - mu N <= 0 (rows of (3K,) force vectors) the `facets`-sided pyramids around unit `normals`
    (K, 3) that circumscribe the Coulomb cones of mu: per contact `facets` rows d . f <= mu n . f, d across n, and
    one pushing row -n . f <= 0."""
    import numpy as np

    k = len(normals)
    angles = np.linspace(0.0, 2 * np.pi, facets, endpoint=False)
    d_rows, n_rows = np.zeros((k, facets + 1, 3 * k)), np.zeros((k, facets + 1, 3 * k))
    for i, n in enumerate(normals):
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        d_rows[i, :facets, 3 * i : 3 * i + 3] = np.cos(angles)[:, None] * t1 + np.sin(angles)[:, None] * t2
        n_rows[i, :facets, 3 * i : 3 * i + 3] = n
        d_rows[i, facets, 3 * i : 3 * i + 3] = -n
    return d_rows.reshape(-1, 3 * k), n_rows.reshape(-1, 3 * k)


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

    points, normals, wrench, center = _lp_inputs("least_friction", points, normals, wrench, center, facets)
    k = len(points)
    g = grasp_matrix(points, center, xp=np)  # float64
    d_rows, n_rows = _pyramid_rows(normals, facets)

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


@dataclasses.dataclass(frozen=True)
class HoldMargin:
    """Whether any contact forces can hold a wrench, friction cones and motor limits both respected
    (`hold_margin`). `torque_ratio` is the least peak |joint torque| / limit over the forces that supply the wrench
    in the cones: <= 1 means the motors can give it; inf where the cones alone cannot supply the wrench."""

    torque_ratio_outer: float  # with each cone replaced by its circumscribing pyramid (a lower bound on the ratio)
    torque_ratio_inner: float  # with the inscribed pyramid (an upper bound: these forces lie inside the cones)
    forces: "object"  # (K, 3) forces attaining torque_ratio_inner (numpy), or None where none exist

    @property
    def impossible(self) -> bool:
        """No forces in the cones supply the wrench within the motor limits (certain: the outer bound exceeds 1)."""
        return self.torque_ratio_outer > 1.0

    @property
    def possible(self) -> bool:
        """Forces inside the cones (certain: the inscribed pyramids) supply the wrench within the motor limits."""
        return self.torque_ratio_inner <= 1.0


def hold_margin(points, normals, mu, wrench, center, jacobians=None, torque_limit=None, bias=None,
                facets: int = 16) -> HoldMargin:
    """The least peak joint torque, relative to the motors' limits, with which point contacts hold a wrench: a
    linear programme (scipy HiGHS) over forces f (K, 3) on the tool and a ratio s,

        minimise s   subject to   G f = wrench,   f_k in the friction pyramid around n_k,
                                  -s limit_j <= (sum_k J_k^T f_k + bias)_j <= s limit_j   for every joint j,

    solved twice, with the `facets`-sided pyramids that circumscribe and that are inscribed in the Coulomb cones of
    `mu`, which bracket the cone's answer. numpy/scipy, not jittable: the feasibility oracle of the physics check
    (could *any* controller hold the tool here?), not a kernel.

    points (K, 3), normals (K, 3) inward unit normals, mu > 0, wrench (6,) the net force [N] and torque [N m] about
    `center` (3,) the contacts must supply. jacobians (K, 3, J): d(contact point)/d(joint angles) of the finger
    link at each contact, so joint torques J^T f make the fingers press with f on the tool; torque_limit (J,) > 0
    [N m]; bias (J,) torques the motors must give besides (the fingers' own gravity) [N m]. Without jacobians the
    ratio is 0 wherever the cones alone supply the wrench.
    """
    import numpy as np
    from scipy.optimize import linprog

    if not (np.isfinite(mu) and mu > 0):
        raise ValueError(f"hold_margin: mu must be finite and > 0, got {mu!r}")
    points, normals, wrench, center = _lp_inputs("hold_margin", points, normals, wrench, center, facets)
    k = len(points)
    if jacobians is not None:
        jac = np.asarray(jacobians, float)
        if jac.ndim != 3 or jac.shape[:2] != (k, 3):
            raise ValueError(f"hold_margin: jacobians must be (K={k}, 3, J), got shape {jac.shape}")
        limit = np.asarray(torque_limit, float).reshape(-1) if torque_limit is not None else None
        if limit is None or limit.shape != (jac.shape[2],) or not np.all(limit > 0):
            raise ValueError(f"hold_margin: torque_limit must be (J={jac.shape[2]},) and > 0, got {torque_limit!r}")
        bias = np.zeros_like(limit) if bias is None else np.asarray(bias, float).reshape(-1)
        if bias.shape != limit.shape or not np.all(np.isfinite(bias)):
            raise ValueError(f"hold_margin: bias must be finite (J={len(limit)},), got {bias!r}")
    g = grasp_matrix(points, center, xp=np)
    cone_rows, normal_rows = _pyramid_rows(normals, facets)

    def solve(mu_pyramid: float):
        # variables [f (3K), s]; d . f - mu n . f <= 0 per facet (the pyramid circumscribing the cone of mu_pyramid)
        a_ub = [np.hstack([cone_rows - mu_pyramid * normal_rows, np.zeros((len(cone_rows), 1))])]
        b_ub = [np.zeros(len(cone_rows))]
        if jacobians is not None:
            jt = jac.transpose(2, 0, 1).reshape(len(limit), 3 * k)  # (J, 3K): joint torques of the forces
            a_ub += [np.hstack([jt, -limit[:, None]]), np.hstack([-jt, -limit[:, None]])]
            b_ub += [-bias, bias]
        res = linprog(np.r_[np.zeros(3 * k), 1.0], A_ub=np.vstack(a_ub), b_ub=np.concatenate(b_ub),
                      A_eq=np.hstack([g, np.zeros((6, 1))]), b_eq=wrench,
                      bounds=[(None, None)] * (3 * k) + [(0.0, None)], method="highs")
        if res.status == 2:
            return float("inf"), None
        if res.status != 0:
            raise RuntimeError(f"hold_margin: the LP ended with status {res.status}: {res.message}")
        return float(res.x[-1]), res.x[:-1].reshape(k, 3)

    outer, _ = solve(mu)  # facets tangent to the cone: the pyramid contains it
    inner, forces = solve(mu * np.cos(np.pi / facets))  # corners on the cone: the pyramid lies inside it
    return HoldMargin(torque_ratio_outer=outer, torque_ratio_inner=inner, forces=forces)
