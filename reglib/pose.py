"""Rigid pose from 3-D points and corresponding 3-D lines (Guéziec et al. 1998, s. IV-B).

Find ``R, t`` such that each moved point ``R @ p_i + t`` lies on its line ``(c_i, v_i)``,
by minimising the sum of squared point-line distances

    E(R, t) = sum_i |(I - v_i v_i^T)(R p_i + t - c_i)|^2 .

Four methods, one entry point :func:`solve_pose`:

``"lm"``
    Levenberg-Marquardt (``scipy.optimize.least_squares``) on the 3-vector residuals
    ``(I - v v^T)(Q(u) p + t - c)`` over Cayley parameters ``u`` and ``t``, with the analytic
    Jacobian (``dQ/du_k = -(I + Q) E_k (I + U)^-1``). The 3-vector residual has the same
    squared norm as the paper's scalar distance but stays smooth at zero, so three points
    are enough.
``"linear"``
    The paper's linearised problem: with ``Q ~ I - 2U`` the error is linear in ``(u, t)``;
    minimise it subject to ``|u| <= r`` (default 0.1), solved exactly (the translation is
    eliminated, then the trust-region problem in ``u`` is solved by eigen-decomposition and
    a secular equation, which is what the paper's generalized SVD computes), apply the exact
    Cayley rotation, iterate until the increments are small or the cost stops decreasing
    (two iterations in a row within ``FLAT_COST`` of it: on noisy data the increments
    shrink only linearly, and 10-25 iterations reach the cost of 100).
``"robust"``
    The same linearised step, each point weighted by Tukey's biweight of its distance
    (``a = 2``, scale ``s = median(d) / 0.6745``); the 6x6 normal equations are formed with
    vectorised numpy (no Python loop over points) and iterated.
``"ransac"``
    Beyond the paper: minimal samples of three point-line pairs solved exactly (all real
    solutions of the three distance constraints along the lines, found by bracketing a 1-D
    function and regula falsi), scored by their inliers (MSAC for ties), then refined by
    Tukey's biweight with a scale fixed from the inliers. Survives far more than 40 %
    outliers. The lines are rays from their origins (cheirality): a hypothesis that puts a
    sample point behind its origin is rejected and points behind never count as inliers, so
    the exact mirror pose of planar points behind the source cannot win. The hypothesis loop
    runs compiled (:mod:`reglib._ransac_numba`, about 12 us per trial) with the numpy loop
    kept as its reference. A pose with fewer inliers than :func:`ransac_min_inliers`, or one
    degree of freedom of which rests on one pair, is not converged.

Every method's answer is judged before ``converged`` is reported: the rank of the (weighted)
problem at the solution (parallel or identical lines, collinear points: undetermined) and,
unless ``cheirality=False``, no inlier behind its line's origin.

Linearisations rotate about the centroid of the current points, not about the origin, so
that the trust radius ``r`` means the same in mm-scale robot coordinates as in the unit
cube. All methods start from ``initial`` (default: identity, as in the paper).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from reglib.geometry import (
    MAD_TO_SIGMA,
    MAX_COORDINATE_MM,
    RigidTransform,
    as_lines,
    as_points,
    as_rigid_transform,
    cayley,
    robust_scale,
    skew,
)

__all__ = ["PoseResult", "solve_pose", "tukey_weights", "p3l_solutions", "MIN_POINTS",
           "ransac_min_inliers"]

Method = Literal["lm", "linear", "robust", "ransac"]
#: "linear" stops (converged) when two iterations in a row changed its cost by at most this
#: fraction of it: the cost stopped decreasing, the iterations only shuffle rounding errors
FLAT_COST = 1e-10
MIN_POINTS = {"lm": 3, "linear": 3, "robust": 4, "ransac": 4}  # robust: needs redundancy


@dataclass(frozen=True)
class PoseResult:
    """A pose estimate ``points -> lines``: ``R @ p + t`` lies on the lines.

    Attributes
    ----------
    R : (3, 3) rotation; t : (3,) translation (units of the input, e.g. mm).
    residuals : (N,) point-line distances at the solution (units of the input).
    weights : (N,) final per-point weights (1 for the unweighted methods; Tukey weights
        for "robust" and "ransac", 0 for rejected points).
    inliers : (N,) bool, ``weights > 0``.
    iterations : int, iterations (or function evaluations for "lm").
    converged : bool. False means the estimate is not to be trusted; ``message`` says why.
    The object is falsy when not converged.
    """

    R: np.ndarray
    t: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    inliers: np.ndarray
    iterations: int
    converged: bool
    method: str
    message: str = ""
    ransac_trials: int = 0

    def __bool__(self) -> bool:
        return bool(self.converged)

    @property
    def transform(self) -> RigidTransform:
        return RigidTransform(self.R, self.t)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals**2)))


# --------------------------------------------------------------------------- input checks
def _distinct_pairs(p, o, d, enough: int) -> int:
    """How many distinct (point, line) rows there are, counted up to ``enough`` (most inputs
    reach it within their first rows: the rows are read one at a time, not copied)."""
    seen = set()
    for i in range(len(p)):
        seen.add((p[i].tobytes(), o[i].tobytes(), d[i].tobytes()))
        if len(seen) >= enough:
            break
    return len(seen)


def _check_inputs(points, origins, directions, method: str):
    if method not in MIN_POINTS:
        raise ValueError(f"method: expected one of {sorted(MIN_POINTS)}, got {method!r}")
    p = as_points(points, "points")
    o, d = as_lines(origins, directions)
    if p.shape[0] != o.shape[0]:
        raise ValueError(
            f"points ({p.shape[0]}) and lines ({o.shape[0]}) must have the same number of rows"
        )
    need = MIN_POINTS[method]
    if p.shape[0] < need:
        raise ValueError(
            f"method {method!r} needs at least {need} point-line pairs, got {p.shape[0]}"
        )
    distinct = _distinct_pairs(p, o, d, need)
    if distinct < need:   # a review: 3 pairs repeated to 40 rows, RANSAC 57 mm off, converged
        raise ValueError(
            f"method {method!r} needs at least {need} distinct point-line pairs, got "
            f"{distinct} among {p.shape[0]} rows (repeated pairs count once)"
        )
    centered = p - p.mean(axis=0)
    ev = np.linalg.eigvalsh(centered.T @ centered)  # squared singular values, ascending
    s = np.sqrt(np.maximum(ev[::-1], 0.0))
    scale = max(s[0], 1e-300)
    if s[0] < 1e-12 * max(1.0, np.abs(p).max()):
        raise ValueError("points: all points coincide; the rotation is undetermined")
    if s[1] < 1e-7 * scale:
        raise ValueError(
            "points: all points are collinear; the rotation about their common line is "
            "undetermined"
        )
    # the lines: all parallel (a translation along them is free) or all one line
    ev_d = np.linalg.eigvalsh(d.T @ d / len(d))
    if not ev_d[1] > 1e-12:
        off = (o - o[0]) - np.outer((o - o[0]) @ d[0], d[0])
        if np.sqrt(np.max(np.sum(off * off, axis=1))) <= 1e-9 * max(1.0, np.abs(o).max()):
            raise ValueError("lines: all lines are the same line; the pose is undetermined "
                             "(degenerate geometry)")
        raise ValueError("lines: all lines are parallel; the translation along them is "
                         "undetermined (degenerate geometry)")
    return p, o, d


#: the largest iteration count and RANSAC sample count :func:`solve_pose` takes (RANSAC draws
#: its samples up front: 10**9 of them took 22 GB; 10**6 is 5,000 times the count that
#: reaches 99 % confidence with half the points outliers)
MAX_ITERATIONS = 100_000
MAX_TRIALS = 1_000_000


def _check_options(method, *, max_iterations, tol, r, tukey_a, threshold, max_trials,
                   confidence, backend):
    """Clear ValueErrors for option values :func:`solve_pose` cannot use."""
    if method not in MIN_POINTS:
        raise ValueError(f"method: expected one of {sorted(MIN_POINTS)}, got {method!r}")
    if backend not in ("auto", "numpy", "numba"):
        raise ValueError(f"backend: expected 'auto', 'numpy' or 'numba', got {backend!r}")

    def number(name, val, ok, what, allow_none=False):
        if val is None and allow_none:
            return
        # a real number, not text that float() would read ("1e-3" reached the compiled
        # solver and failed there with a typing error)
        if isinstance(val, bool) or not isinstance(val, numbers.Real):
            raise ValueError(f"{name}: expected {what}, got {val!r}")
        if not (np.isfinite(float(val)) and ok(float(val))):
            raise ValueError(f"{name}: expected {what}, got {val!r}")

    for name, val, top in (("max_iterations", max_iterations, MAX_ITERATIONS),
                           ("max_trials", max_trials, MAX_TRIALS)):
        if isinstance(val, bool) or not isinstance(val, int | np.integer) or not 1 <= val <= top:
            raise ValueError(f"{name}: expected an integer in [1, {top}], got {val!r}")
    number("tol", tol, lambda v: v >= 0, "a finite number >= 0")
    number("r", r, lambda v: v > 0, "a finite trust radius > 0 (or None)", allow_none=True)
    number("tukey_a", tukey_a, lambda v: v > 0, "a finite Tukey constant > 0")
    number("threshold", threshold, lambda v: v > 0, "a finite inlier distance > 0 (or None)",
           allow_none=True)
    number("confidence", confidence, lambda v: 0 < v < 1, "a probability in (0, 1)")


def _is_matrix_4x4(value) -> bool:
    """Whether ``value`` is array-like of shape (4, 4) (not a pair ``(R, t)``)."""
    if isinstance(value, RigidTransform | str | bytes):
        return False
    try:
        return np.shape(value) == (4, 4)
    except (TypeError, ValueError):     # ragged: a pair (R, t)
        return False


def _check_initial(initial) -> tuple[np.ndarray, np.ndarray]:
    """``initial`` as (R (3, 3), t (3,)): a rotation (orthonormal, det +1) and finite; a
    (4, 4) homogeneous matrix is read by :func:`reglib.geometry.as_rigid_transform`."""
    if _is_matrix_4x4(initial):
        T = as_rigid_transform(initial, "initial")
        initial = (T.R, T.t)
    try:
        R, t = (np.asarray(x, dtype=np.float64) for x in initial)
    except (TypeError, ValueError):
        raise ValueError("initial: expected a RigidTransform, a pair (R (3, 3), t (3,)) or a "
                         "(4, 4) matrix") from None
    if R.shape != (3, 3) or t.shape != (3,) or not (np.all(np.isfinite(R))
                                                    and np.all(np.isfinite(t))):
        raise ValueError(f"initial: expected a finite R (3, 3) and t (3,), got {R.shape} and "
                         f"{t.shape}")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("initial: R is not a rotation (R^T R = I and det R = +1 are needed)")
    if np.max(np.abs(t)) > MAX_COORDINATE_MM:
        raise ValueError(f"initial: translation up to {np.max(np.abs(t)):.3g} mm; expected the "
                         f"millimetres of a scene (|t| <= {MAX_COORDINATE_MM:g})")
    return R, t


# --------------------------------------------------------------------------- building blocks
def tukey_weights(z, a: float = 2.0) -> np.ndarray:
    """Tukey biweight ``psi(z)/z = (1 - (z/a)^2)^2`` for ``|z| < a``, else 0 (also for
    ``|z| = inf``). ValueError for a NaN residual (no weight is right for it) or an ``a``
    that is not a finite number > 0."""
    z = np.asarray(z, dtype=np.float64)
    if not (isinstance(a, numbers.Real) and np.isfinite(a) and a > 0):
        raise ValueError(f"tukey_weights: a must be a finite number > 0, got {a!r}")
    if np.isnan(z).any():
        raise ValueError(f"tukey_weights: {int(np.isnan(z).sum())} residual(s) are NaN")
    w = 1.0 - (z / a) ** 2
    return np.where(np.abs(z) < a, w * w, 0.0)


def _perp_basis(d):
    """Two unit vectors orthogonal to each direction: ``(2, N, 3)``; ``I - v v^T = n1 n1^T +
    n2 n2^T``, so a point-line residual is the 2-vector ``(n1.(P - o), n2.(P - o))``."""
    a = np.zeros_like(d)
    use_y = np.abs(d[:, 0]) > 0.9
    a[~use_y, 0] = 1.0
    a[use_y, 1] = 1.0
    n1 = _cross(a, d)
    n1 /= np.sqrt(np.sum(n1 * n1, axis=1, keepdims=True))
    n2 = _cross(d, n1)
    return np.stack([n1, n2])


def _cross(a, b):
    """Row-wise cross product of (..., 3) arrays (faster than np.cross for small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _linear_system(P, o, Nb, m, weights):
    """Normal equations of the linearised error about the centroid ``m``.

    ``P`` (N, 3) current points, ``o`` (N, 3) line origins, ``Nb`` (2, N, 3) from
    :func:`_perp_basis`. With ``Q ~ I - 2U`` the moved point is ``P + 2 (P - m) x u + t``;
    its residual along ``n`` is ``n.(P - o) + 2 (n x (P - m)).u + n.t`` (linear in u, t).
    Returns ``C`` (6, 6), ``g`` (6,): the step minimises ``x^T C x + 2 g^T x``; and the
    point-line distances (N,).
    """
    Pc = P - m
    A = np.empty((2, P.shape[0], 6))
    A[:, :, :3] = 2.0 * _cross(Nb, Pc[None])
    A[:, :, 3:] = Nb
    res = np.einsum("knj,nj->kn", Nb, P - o)  # (2, N)
    dist = np.sqrt(res[0] ** 2 + res[1] ** 2)
    if weights is not None:
        sw = np.sqrt(weights)
        A *= sw[None, :, None]
        res = res * sw[None, :]
    Af = A.reshape(-1, 6)
    return Af.T @ Af, Af.T @ res.reshape(-1), dist


def _trust_region_step(C, g, r):
    """Minimise ``x^T C x + 2 g^T x`` subject to ``|x[:3]| <= r`` exactly.

    The unconstrained minimiser is tried first; when its rotation part is longer than r,
    the translation is eliminated (Schur complement) and the trust-region subproblem
    ``min u^T S u + 2 h^T u, |u| <= r`` is solved through the eigen-decomposition of S and
    the secular equation ``|u(mu)| = r`` (Newton on ``1/|u| - 1/r``).
    Returns ``(u, t, ok)``; ``ok`` is False when the system is singular.
    """
    try:
        x = -np.linalg.solve(C, g)
    except np.linalg.LinAlgError:
        x = None
    if x is not None and np.all(np.isfinite(x)) and (r is None or x[:3] @ x[:3] <= r * r):
        return x[:3], x[3:], True
    Cuu, Cut, Ctt = C[:3, :3], C[:3, 3:], C[3:, 3:]
    gu, gt = g[:3], g[3:]
    Ctt_inv = np.linalg.pinv(Ctt, rcond=1e-13)
    K = Cut @ Ctt_inv
    S = Cuu - K @ Cut.T
    h = gu - K @ gt
    lam, Qe = np.linalg.eigh(S)
    if lam[-1] <= 0 or lam[0] < 1e-14 * lam[-1]:
        return np.zeros(3), np.zeros(3), False
    b = Qe.T @ h
    u = -Qe @ (b / lam)
    if r is not None and u @ u > r * r:
        mu = 0.0
        for _ in range(60):
            den = lam + mu
            q2 = np.sum((b / den) ** 2)
            phi = 1.0 / np.sqrt(q2) - 1.0 / r
            if abs(phi) < 1e-13 / r:
                break
            dphi = q2**-1.5 * np.sum(b * b / den**3)
            mu = max(mu - phi / dphi, 0.5 * mu)
        u = -Qe @ (b / (lam + mu))
    t = -Ctt_inv @ (gt + Cut.T @ u)
    return u, t, True


def _cayley3(u):
    """Cayley rotation of one (3,) vector (scalar code: cheaper than the general form)."""
    x, y, z = u
    n = 1.0 + x * x + y * y + z * z
    return np.array([
        [1 + x * x - y * y - z * z, 2 * (x * y + z), 2 * (x * z - y)],
        [2 * (x * y - z), 1 - x * x + y * y - z * z, 2 * (y * z + x)],
        [2 * (x * z + y), 2 * (y * z - x), 1 - x * x - y * y + z * z],
    ]) / n


def _compose(R, tt, Q, m, t):
    """Accumulate ``x -> Q (x - m) + m + t`` onto the pose ``x -> R x + tt``."""
    return Q @ R, Q @ (tt - m) + m + t


def _distances(P, o, d):
    w_ = P - o
    e = w_ - np.sum(w_ * d, axis=1, keepdims=True) * d
    return np.sqrt(np.sum(e * e, axis=1))


def _median(x):
    n = x.shape[0]
    k = n // 2
    part = np.partition(x, (k - 1, k) if n % 2 == 0 else k)
    return 0.5 * (part[k - 1] + part[k]) if n % 2 == 0 else part[k]


def _scale_of(points):
    """RMS distance of the points to their centroid (1.0 for a single point)."""
    c = points - points.mean(0)
    return float(np.sqrt(np.einsum("ij,ij->", c, c) / len(points))) or 1.0


# --------------------------------------------------------------------------- methods
def _numba_kernel():
    try:
        from reglib import _pose_numba
    except ImportError:  # numba missing: the numpy reference serves
        return None
    return _pose_numba


def _iterate_linearised(p, o, d, R0, t0, *, robust, r, max_iterations, tol, a,
                        fixed_scale=None, method, backend="auto"):
    scale = _scale_of(p)
    kernel = _numba_kernel() if backend in ("auto", "numba") else None
    if backend == "numba" and kernel is None:
        raise ValueError("backend 'numba' asked for but numba is not installed")
    if kernel is not None:
        Nb = kernel.perp_basis(d)
        R, tt, it, status = kernel.iterate(
            p, o, Nb, np.ascontiguousarray(R0, dtype=np.float64),
            np.ascontiguousarray(t0, dtype=np.float64), robust, r if r is not None else -1.0,
            max_iterations, tol, a, -1.0 if fixed_scale is None else float(fixed_scale), scale,
            FLAT_COST)
        messages = {
            0: "",
            1: f"no convergence after {max_iterations} iterations",
            2: f"fewer than 3 points kept by the biweight at iteration {it} "
               "(too many outliers or a start too far off)",
            3: f"singular linear system at iteration {it} (degenerate geometry)",
        }
        dist = kernel.distances(p, o, d, R, tt)
        if robust:
            s = fixed_scale if fixed_scale is not None else _median(dist) / MAD_TO_SIGMA
            weights = tukey_weights(dist / max(s, 1e-12 * scale), a)
        else:
            weights = np.ones(len(p))
        return PoseResult(R, tt, dist, weights, weights > 0, int(it), status == 0, method,
                          messages[int(status)])
    Nb = _perp_basis(d)
    R, tt = R0.copy(), t0.copy()
    P = p @ R.T + tt
    weights = None
    converged = False
    message = ""
    it = 0
    tol_t = tol * scale
    cost_prev, flat = np.inf, 0
    for it in range(1, max_iterations + 1):
        if robust:
            dist = _distances(P, o, d)
            s = fixed_scale if fixed_scale is not None else _median(dist) / MAD_TO_SIGMA
            s = max(s, 1e-12 * scale)
            weights = tukey_weights(dist / s, a)
            wsum = weights.sum()
            if np.count_nonzero(weights) < 3:
                message = (f"fewer than 3 points kept by the biweight at iteration {it} "
                           "(too many outliers or a start too far off)")
                break
            m = (weights @ P) / wsum
        else:
            m = P.mean(axis=0)
        C, g, dist = _linear_system(P, o, Nb, m, weights)
        if not robust:  # "linear": stop once the cost no longer decreases
            cost = float(dist @ dist)
            flat = flat + 1 if abs(cost_prev - cost) <= FLAT_COST * cost_prev else 0
            cost_prev = cost
            if flat >= 2:
                converged = True
                it -= 1  # no step taken in this iteration
                break
        u, t, ok = _trust_region_step(C, g, r)
        if not ok:
            message = f"singular linear system at iteration {it} (degenerate geometry)"
            break
        Q = _cayley3(u)
        P = (P - m) @ Q.T + (m + t)
        R, tt = _compose(R, tt, Q, m, t)
        if u @ u < tol * tol and t @ t < tol_t * tol_t:
            converged = True
            break
    else:
        message = f"no convergence after {max_iterations} iterations"
    dist = _distances(P, o, d)
    if robust and weights is not None:
        s = fixed_scale if fixed_scale is not None else _median(dist) / MAD_TO_SIGMA
        weights = tukey_weights(dist / max(s, 1e-12 * scale), a)
    else:
        weights = np.ones(len(p))
    return PoseResult(R, tt, dist, weights, weights > 0, it, converged, method, message)


def _solve_lm(p, o, d, R0, t0, *, max_iterations, tol):
    P0 = p @ R0.T + t0
    m = P0.mean(axis=0)
    Pc = P0 - m
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    E = skew(np.eye(3))  # E[k] = skew(e_k)
    scale = _scale_of(p)

    def fun(x):
        Q = cayley(x[:3])
        X = Pc @ Q.T + m + x[3:] - o
        return np.einsum("nij,nj->ni", M, X).ravel()

    def jac(x):
        u = x[:3]
        Q = cayley(u)
        inv = np.linalg.inv(np.eye(3) + skew(u))
        J = np.empty((len(p), 3, 6))
        for k in range(3):
            dQ = -(np.eye(3) + Q) @ E[k] @ inv
            J[:, :, k] = np.einsum("nij,nj->ni", M, Pc @ dQ.T)
        J[:, :, 3:] = M
        return J.reshape(-1, 6)

    sol = least_squares(fun, np.zeros(6), jac=jac, method="lm", xtol=tol, ftol=tol,
                        gtol=tol, x_scale=np.r_[1.0, 1.0, 1.0, scale, scale, scale],
                        max_nfev=max_iterations * 10)
    u, t = sol.x[:3], sol.x[3:]
    Q = cayley(u)
    R, tt = _compose(R0, t0, Q, m, t)
    dist = _distances(p @ R.T + tt, o, d)
    ok = bool(sol.success) and np.all(np.isfinite(sol.x))
    msg = "" if ok else f"least_squares: {sol.message}"
    w = np.ones(len(p))
    return PoseResult(R, tt, dist, w, w > 0, int(sol.nfev), ok, "lm", msg)


# --------------------------------------------------------------------------- minimal solver
def _kabsch(A, B):
    """Rotation and translation with ``R @ A_i + t = B_i`` (least squares); A, B (..., 3, 3)."""
    ma = A.mean(axis=-2, keepdims=True)
    mb = B.mean(axis=-2, keepdims=True)
    H = np.swapaxes(A - ma, -1, -2) @ (B - mb)
    U, _, Vt = np.linalg.svd(H)
    D = np.ones(H.shape[:-1])
    D[..., 2] = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    R = np.swapaxes(Vt, -1, -2) @ (D[..., :, None] * np.swapaxes(U, -1, -2))
    t = mb[..., 0, :] - np.einsum("...ij,...j->...i", R, ma[..., 0, :])
    return R, t


def p3l_solutions(p, o, d, *, grid: int = 200):
    """All poses that put three points exactly on three lines (generalised P3P).

    Parameters
    ----------
    p : (3, 3) points; o, d : (3, 3) line origins and unit directions.

    Returns
    -------
    Rs : (K, 3, 3), ts : (K, 3), the real solutions (K may be 0). Solutions are found by
    writing the points as ``X_i = o_i + lam_i d_i``: for a given ``lam_1`` the distance
    constraints to points 2 and 3 give ``lam_2``, ``lam_3`` in closed form (two branches
    each); the remaining constraint ``|X_2 - X_3| = |p_2 - p_3|`` is a 1-D function of
    ``lam_1`` on each of the four branches, whose sign changes on a grid are refined by
    a safeguarded regula falsi (Illinois) to machine precision. A tangential (double) root
    can be missed.
    """
    p = as_points(p, "p")
    o, d = as_lines(o, d)
    if p.shape != (3, 3) or o.shape != (3, 3):
        raise ValueError(f"p3l_solutions: expected three points and three lines, (3, 3) each, "
                         f"got p {p.shape}, o and d {o.shape}")
    return _p3l_solutions(p, o, d, grid=grid)


def _p3l_solutions(p, o, d, *, grid: int = 200):
    """:func:`p3l_solutions` on checked arrays (the RANSAC reference calls it per sample)."""
    D12 = np.sum((p[0] - p[1]) ** 2)
    D13 = np.sum((p[0] - p[2]) ** 2)
    D23 = np.sum((p[1] - p[2]) ** 2)
    # lam_1 interval where line j is within reach: |M_j (o1 + lam d1 - o_j)|^2 <= D1j
    lo, hi = -np.inf, np.inf
    for j, Dj in ((1, D12), (2, D13)):
        Mv = d[0] - (d[0] @ d[j]) * d[j]
        w0 = o[0] - o[j]
        Mw = w0 - (w0 @ d[j]) * d[j]
        A, B, Cc = Mv @ Mv, Mv @ Mw, Mw @ Mw - Dj
        if A < 1e-14:  # parallel lines: reachable everywhere or nowhere
            if Cc > 0:
                return np.empty((0, 3, 3)), np.empty((0, 3))
            continue
        disc = B * B - A * Cc
        if disc < 0:
            return np.empty((0, 3, 3)), np.empty((0, 3))
        sq = np.sqrt(disc)
        lo, hi = max(lo, (-B - sq) / A), min(hi, (-B + sq) / A)
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    # cosine-spaced grid, dense near the ends where the branches meet (sqrt behaviour)
    s = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, grid))
    lam = lo + (hi - lo) * s

    def f(lam1, sign2, sign3):
        X1 = o[0] + lam1[..., None] * d[0]
        a2 = X1 - o[1]
        b2 = a2 @ d[1]
        l2 = b2 + sign2 * np.sqrt(np.maximum(b2 * b2 - np.sum(a2 * a2, -1) + D12, 0.0))
        a3 = X1 - o[2]
        b3 = a3 @ d[2]
        l3 = b3 + sign3 * np.sqrt(np.maximum(b3 * b3 - np.sum(a3 * a3, -1) + D13, 0.0))
        X2 = o[1] + l2[..., None] * d[1]
        X3 = o[2] + l3[..., None] * d[2]
        return np.sum((X2 - X3) ** 2, -1) - D23, X1, X2, X3

    signs = np.array([(1, 1), (1, -1), (-1, 1), (-1, -1)], float)
    vals = f(lam[None, :], signs[:, :1], signs[:, 1:])[0]  # (4, grid)
    br, ix = np.nonzero(np.sign(vals[:, :-1]) * np.sign(vals[:, 1:]) <= 0)
    if br.size == 0:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    s2, s3 = signs[br, 0], signs[br, 1]
    a, b = lam[ix], lam[ix + 1]
    fa, fb = vals[br, ix], vals[br, ix + 1]
    # Illinois (modified regula falsi), vectorised over all brackets; falls back on
    # bisection steps when the secant point leaves the bracket.
    side = np.zeros(a.shape, dtype=np.int8)
    for _ in range(100):
        denom = fb - fa
        c = np.where(denom != 0, (a * fb - b * fa) / np.where(denom != 0, denom, 1.0),
                     0.5 * (a + b))
        bad = ~((c > np.minimum(a, b)) & (c < np.maximum(a, b)))
        c = np.where(bad, 0.5 * (a + b), c)
        fc = f(c, s2, s3)[0]
        left = np.sign(fa) * np.sign(fc) <= 0  # root in [a, c]
        # Illinois: halve the function value kept twice in a row
        fa = np.where(left, np.where(side == -1, 0.5 * fa, fa), fc)
        fb = np.where(left, fc, np.where(side == 1, 0.5 * fb, fb))
        a, b = np.where(left, a, c), np.where(left, c, b)
        side = np.where(left, -1, 1).astype(np.int8)
        if np.all(np.abs(b - a) <= 1e-15 * (1.0 + np.abs(a))) or np.all(fc == 0):
            break
    root = 0.5 * (a + b)
    val, X1, X2, X3 = f(root, s2, s3)
    ok = np.abs(val) < 1e-6 * max(D23, 1e-300)
    if not np.any(ok):
        return np.empty((0, 3, 3)), np.empty((0, 3))
    X = np.stack([X1[ok], X2[ok], X3[ok]], axis=1)  # (K, 3, 3)
    A = np.broadcast_to(p, X.shape)
    return _kabsch(A, X)


def _ransac_samples(rng, n: int, count: int) -> np.ndarray:
    """``count`` uniformly drawn triples of distinct indices in ``range(n)``: (count, 3)."""
    i0 = rng.integers(0, n, count)
    i1 = rng.integers(0, n - 1, count)
    i1 += i1 >= i0
    lo, hi = np.minimum(i0, i1), np.maximum(i0, i1)
    i2 = rng.integers(0, n - 2, count)
    i2 += i2 >= lo
    i2 += i2 >= hi
    return np.stack([i0, i1, i2], axis=1).astype(np.int64)


def _sample_is_degenerate(q) -> bool:
    """Three points (3, 3) nearly collinear: the doubled triangle area below 1e-6 of the
    longest squared side (the minimal problem is then ill-posed)."""
    u, v = q[1] - q[0], q[2] - q[0]
    area2 = np.sqrt(np.sum(np.cross(u, v) ** 2))
    return not area2 >= 1e-6 * max(u @ u, v @ v, (v - u) @ (v - u))


def _ransac_hypotheses_numpy(p, o, d, samples, thr, confidence, max_trials, grid,
                             cheirality):
    """The hypothesis loop in numpy: the reference of ``_ransac_numba.hypotheses`` (same
    arguments and returns; see there)."""
    n = len(p)
    best_R, best_t, best_count, best_cost = np.eye(3), np.zeros(3), -1, np.inf
    needed = max_trials
    trial = behind = 0
    while trial < min(needed, max_trials):
        idx = samples[trial]
        trial += 1
        if _sample_is_degenerate(p[idx]):
            continue
        Rs, ts = _p3l_solutions(p[idx], o[idx], d[idx], grid=grid)
        if len(Rs) == 0:
            continue
        if cheirality:  # the sample's own points in front of their lines' origins
            X = np.einsum("kij,nj->kni", Rs, p[idx]) + ts[:, None, :] - o[idx]
            front = np.all(np.sum(X * d[idx], axis=-1) > 0, axis=1)
            behind += int(np.count_nonzero(~front))
            Rs, ts = Rs[front], ts[front]
            if len(Rs) == 0:
                continue
        w_ = np.einsum("kij,nj->kni", Rs, p) + ts[:, None, :] - o  # (K, N, 3)
        s = np.sum(w_ * d, axis=-1)
        e = w_ - s[..., None] * d
        q = np.sum(e * e, axis=-1)
        inl = q < thr * thr
        if cheirality:
            inl &= s > 0
        counts = inl.sum(1)
        costs = np.sum(np.where(inl, q, thr * thr), axis=1)  # MSAC score for ties
        k = int(np.lexsort((costs, -counts))[0])
        if counts[k] > best_count or (counts[k] == best_count and costs[k] < best_cost):
            best_count, best_cost = int(counts[k]), float(costs[k])
            best_R, best_t = Rs[k], ts[k]
            frac = best_count / n
            if frac >= 1.0:
                needed = trial
            elif frac > 0:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(1 - frac**3)))
    return best_R, best_t, best_count, best_cost, trial, behind


def _ransac_kernel(backend):
    if backend == "numpy":
        return None
    try:
        from reglib import _ransac_numba
    except ImportError:  # numba missing: the numpy reference serves
        if backend == "numba":
            raise ValueError("backend 'numba' asked for but numba is not installed") from None
        return None
    return _ransac_numba


def ransac_min_inliers(n: int) -> int:
    """Fewest inliers (of ``n`` point-line pairs) for a RANSAC pose to mean anything.

    A minimal sample fits its own three pairs exactly, so three inliers say nothing; on
    random lines the best of 2000 hypotheses gathers up to two or three more by chance.
    Required: three pairs beyond the sample and a tenth of all pairs (below that the
    2000 trials find an all-inlier sample with less than 86 % probability anyway), but
    never more than ``n``.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"ransac_min_inliers: n: expected a whole number of pairs >= 0, got "
                         f"{n!r}")
    return int(min(n, max(6, np.ceil(0.1 * n))))


def _ransac_mirror(p, o, d, k, hypotheses, refine) -> int:
    """When a weak consensus (``k`` inliers, less than half the pairs) may be a pose found
    only because the pose that fits the pairs best lies behind the source (directions given
    reversed: the other solvers end there and their cheirality test says so; RANSAC's
    samples skip it and a chance pose gathers a third of the pairs, a held-out review): the
    same samples without the cheirality test (``hypotheses(cheirality)``: RANSAC's loop over
    its samples), the best hypothesis refined as RANSAC's own (``refine(R, t)`` -> its
    PoseResult). Returns how many pairs that mirror pose fits
    when it is more than :func:`ransac_min_inliers`, at least 1.5 times ``k``, and most of
    them lie behind their lines' origins; else 0."""
    n = len(p)
    R, t, count, *_ = hypotheses(False)
    if count < 3:
        return 0
    res = refine(np.asarray(R), np.asarray(t))
    inl = res.inliers
    m = int(np.count_nonzero(inl))
    if m < max(1.5 * k, ransac_min_inliers(n)):
        return 0
    behind = inl & ~(np.sum((p @ res.R.T + res.t - o) * d, axis=1) > 0)
    return m if np.count_nonzero(behind) > 0.5 * m else 0


def _solve_ransac(p, o, d, R0, t0, *, threshold, max_trials, confidence, rng,
                  max_iterations, tol, a, r, backend, cheirality=True, grid=200,
                  mirror_check=True):
    n = len(p)
    scale = _scale_of(p)
    thr = threshold if threshold is not None else 0.02 * scale
    try:
        rng = np.random.default_rng(rng)
    except (TypeError, ValueError):
        raise ValueError(f"rng: expected a seed (int >= 0) or a numpy Generator, got "
                         f"{rng!r}") from None
    samples = _ransac_samples(rng, n, max_trials)
    kernel = _ransac_kernel(backend)
    loop = kernel.hypotheses if kernel is not None else _ransac_hypotheses_numpy

    def hypotheses(cheirality):
        return loop(p, o, d, samples, float(thr), float(confidence), int(max_trials),
                    int(grid), bool(cheirality))

    best_R, best_t, best_count, _, trial, behind = hypotheses(cheirality)
    if best_count < 3:
        dist = _distances(p @ R0.T + t0, o, d)
        w = np.zeros(n)
        why = (f" ({behind} put their sample behind the lines' origins)" if behind else "")
        return PoseResult(R0, t0, dist, w, w > 0, 0, False, "ransac",
                          f"no minimal sample gave a pose in {trial} trials{why}", trial)
    best_R, best_t = np.asarray(best_R), np.asarray(best_t)

    def refine(R, t):
        # Tukey with a scale fixed from the inliers of the hypothesis
        dist = _distances(p @ R.T + t, o, d)
        inl = dist < thr
        s = max(robust_scale(dist[inl]), thr / (2 * a))
        return _iterate_linearised(p, o, d, R, t, robust=True, r=r,
                                   max_iterations=max_iterations, tol=tol, a=max(a, 3.0),
                                   fixed_scale=s, method="ransac", backend=backend)

    res = refine(best_R, best_t)
    converged, message = res.converged, res.message
    need = ransac_min_inliers(n)
    k = int(np.count_nonzero(res.inliers))
    if converged and k < need:
        converged, message = False, (
            f"only {k} of {n} pairs are inliers (the best hypothesis had {best_count}); at "
            f"least {need} are needed for the pose to mean anything (a minimal sample fits "
            "its own 3 exactly): the points do not fit the lines")
    if mirror_check and cheirality and (not converged or k < 0.5 * n):
        mirror = _ransac_mirror(p, o, d, k, hypotheses, refine)
        if mirror:
            converged, message = False, (
                f"{k} of {n} pairs fit the pose found, but {mirror} fit a pose that puts "
                "most of them behind their lines' origins (the mirror pose behind the "
                "source): are the lines' directions reversed?")
    return PoseResult(res.R, res.t, res.residuals, res.weights, res.inliers, res.iterations,
                      converged, "ransac", message, trial)


# --------------------------------------------------------------------------- entry point
# --------------------------------------------------------------------------- constrained IRLS
def _solve_irls(points, origins, directions, *, normals=None, fixed_point=None,
                robust: bool = True, tukey_a: float = 2.0, max_iterations: int = 20,
                tol: float = 1e-10, backend: str = "auto"):
    """Rigid update that puts ``points`` on their lines: robust Gauss-Newton (IRLS).

    The paper's linearised robust solver for the two cases of :func:`solve_pose`'s
    ``fixed_point`` and ``normals``: a rotation about a fixed point (experiment 1) and a
    residual measured only along a given normal of each line (the across-contour residual of
    :func:`reglib.register.register`). The update is
    linearised as ``x' = x + w x (x - m) + tau`` about the (weighted) centroid ``m`` of the
    points, or about ``fixed_point`` (then ``tau = 0``), and each step is applied exactly
    (rotation vector ``w``). Weights: Tukey's biweight, ``a = tukey_a``, scale
    ``median(|r|) / 0.6745``.

    Parameters
    ----------
    points : (N, 3) mm, the matched points with the current pose applied (lines' frame).
    origins, directions : (N, 3) mm and unit, the lines.
    normals : (N, 3) unit vectors orthogonal to the directions, or None. With normals the
        residual is the scalar ``n . (x - o)`` (distance to the plane through the line with
        normal n); without, the 3-vector ``(I - d d^T)(x - o)`` (distance to the line).
    fixed_point : (3,) mm or None; when given only a rotation about it is solved.

    Returns
    -------
    (update: RigidTransform in the lines' frame, residuals (N,) mm at the end,
     weights (N,), ok: bool, message: str)
    """
    x = np.array(points, dtype=np.float64)
    o, d = as_lines(origins, directions)
    if x.shape != o.shape:
        raise ValueError(f"points {x.shape} and lines {o.shape} must have the same shape")
    dof = 3 if fixed_point is not None else 6
    need = 2 if fixed_point is not None else 3
    if normals is not None:
        nrm = as_points(normals, "normals")
        if nrm.shape != x.shape:
            raise ValueError(f"normals {nrm.shape} must have the shape of points {x.shape}")
        norms = np.linalg.norm(nrm, axis=1)
        off = (np.abs(norms - 1.0) > 1e-6) & (norms > 0)
        if np.any(off):
            raise ValueError(f"normals: rows {np.flatnonzero(off)[:10].tolist()} are not unit "
                             "vectors (normalise them; an all-zero row is ignored)")
        if not np.any(norms > 0):
            raise ValueError("normals: every row is zero; nothing constrains the pose")
        slant = np.abs(np.einsum("ij,ij->i", nrm, d)) > 1e-6
        if np.any(slant):
            raise ValueError(f"normals: rows {np.flatnonzero(slant)[:10].tolist()} are not "
                             "orthogonal to their line's direction")
        need = dof
    if len(x) < need:
        raise ValueError(f"at least {need} point-line pairs are needed with "
                         f"{'normals' if normals is not None else 'a fixed point'}, "
                         f"got {len(x)}")
    f = None
    if fixed_point is not None:
        f = as_points(fixed_point, "fixed_point")
        if f.shape != (1, 3):
            raise ValueError(f"fixed_point: expected one (3,) point, got shape {f.shape}")
        f = f[0]
    kernel = _numba_kernel() if backend in ("auto", "numba") else None
    if backend == "numba" and kernel is None:
        raise ValueError("backend 'numba' asked for but numba is not installed")
    if kernel is not None:   # the same iterations compiled (reglib._pose_numba.irls)
        R, t, dist, w, status = kernel.irls(
            np.ascontiguousarray(x), np.ascontiguousarray(o), np.ascontiguousarray(d),
            np.ascontiguousarray(nrm) if normals is not None else np.zeros((0, 3)),
            normals is not None, f if f is not None else np.zeros(3), f is not None,
            bool(robust), float(tukey_a), int(max_iterations), float(tol), int(need),
            False)   # generic=False, given: a signature tools/precompile.py can compile
        message = {kernel.IRLS_OK: "",
                   kernel.IRLS_FEW_WEIGHTS: f"fewer than {need} matches kept by the biweight",
                   kernel.IRLS_UNDETERMINED: "the update is undetermined by the matches "
                                             "(degenerate geometry)"}[int(status)]
        return RigidTransform(R, t), dist, w, status == kernel.IRLS_OK, message
    M = None if normals is not None else np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    scale = float(np.sqrt(np.mean(np.sum((x - x.mean(0)) ** 2, axis=1)))) or 1.0
    R_tot, t_tot = np.eye(3), np.zeros(3)
    w = np.ones(len(x))

    def residuals(x):
        if M is None:
            r = np.einsum("ij,ij->i", nrm, x - o)
            return r[:, None], np.abs(r)
        r = np.einsum("nij,nj->ni", M, x - o)
        return r, np.linalg.norm(r, axis=1)

    ok, message = True, ""
    for _ in range(max_iterations):
        r, dist = residuals(x)
        if robust:
            s = max(robust_scale(dist), 1e-12 * scale)
            w = tukey_weights(dist / s, tukey_a)
            if np.count_nonzero(w) < need:
                return (RigidTransform(R_tot, t_tot), dist, w, False,
                        f"fewer than {need} matches kept by the biweight")
        m = f if f is not None else (w @ x) / w.sum()
        y = x - m
        if M is None:
            J = np.concatenate([np.cross(y, nrm), nrm], axis=1)[:, None, :dof]
        else:
            J = np.concatenate([-np.einsum("nij,njk->nik", M, skew(y)), M], axis=2)
            J = J[:, :, :dof]
        J2 = J.reshape(-1, dof)                     # one row per residual component
        wr = np.repeat(w, J.shape[1])
        A = J2.T @ (wr[:, None] * J2)
        b = -J2.T @ (wr * r.reshape(-1))
        sv = np.linalg.svd(A, compute_uv=False)
        if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
            return (RigidTransform(R_tot, t_tot), dist, w, False,
                    "the update is undetermined by the matches (degenerate geometry)")
        delta = np.linalg.solve(A, b)
        Q = Rotation.from_rotvec(delta[:3]).as_matrix()
        tau = delta[3:] if dof == 6 else np.zeros(3)
        x = y @ Q.T + m + tau
        R_tot, t_tot = Q @ R_tot, Q @ (t_tot - m) + m + tau
        if delta[:3] @ delta[:3] < tol * tol and tau @ tau < (tol * scale) ** 2:
            break
    _, dist = residuals(x)
    if robust:
        s = max(robust_scale(dist), 1e-12 * scale)
        w = tukey_weights(dist / s, tukey_a)
    return RigidTransform(R_tot, t_tot), dist, w, ok, message


def _rank_gram(P, d, weights):
    """The rank test's Jacobian ``J`` (2, K, 6) over the K pairs with ``weights > 0`` and
    its Gram matrix ``J^T J`` (6, 6) (see :func:`_undetermined`); the numpy reference of
    :func:`reglib._pose_numba.rank_gram`."""
    keep = weights > 0
    Pk, dk, wk = P[keep], d[keep], np.sqrt(weights[keep])
    m = (wk**2 @ Pk) / np.sum(wk**2)
    size = _scale_of(Pk)
    Nb = _perp_basis(dk)
    J = np.empty((2, len(Pk), 6))
    J[:, :, :3] = _cross(Nb, (Pk - m)[None]) / size
    J[:, :, 3:] = Nb
    J *= wk[None, :, None]
    Jf = J.reshape(-1, 6)
    return J, Jf.T @ Jf


def _undetermined(P, o, d, weights, *, single_pairs: bool = False) -> str:
    """Why the pose is not determined by the pairs at the moved points ``P`` (N, 3), or "".

    The rank test of the problem itself: the (weighted) Jacobian of the point-line residuals
    with respect to a rotation about the kept points' centroid (scaled by their RMS radius)
    and a translation must have rank 6. Parallel or identical lines (a translation along
    them is free), collinear points (a rotation about their line), lines in one plane with
    the points in it, and too few kept pairs all fail it. With ``single_pairs`` a pose one
    degree of freedom of which rests on a single pair fails too (the pair's leverage, the
    largest eigenvalue of its 2x2 block of ``J C^-1 J^T``, is 1: without it the rank drops;
    e.g. collinear inliers whose free rotation one outlier happens to fix). Exactly
    determined problems (three pairs) have leverage 1 everywhere, so only RANSAC, whose
    inliers must be redundant, asks for it.
    """
    keep = weights > 0
    k = int(np.count_nonzero(keep))
    if k < 3:
        return f"degenerate geometry: only {k} pairs kept, 3 at least are needed"
    kernel = _numba_kernel()
    if kernel is not None:   # the Gram matrix compiled, without J (reference: _rank_gram)
        args = (np.ascontiguousarray(P, dtype=np.float64),
                np.ascontiguousarray(d, dtype=np.float64),
                np.ascontiguousarray(weights, dtype=np.float64))
        gram = kernel.rank_gram(*args)
    else:
        J, gram = _rank_gram(P, d, weights)
    ev = np.linalg.eigvalsh(gram)
    if not ev[0] > 1e-12 * ev[-1]:
        rank = int(np.count_nonzero(ev > 1e-12 * ev[-1]))
        return (f"degenerate geometry: the {k} kept point-line pairs determine the pose only "
                f"up to {6 - rank} degree(s) of freedom (rank {rank} of 6: parallel or "
                "identical lines, collinear points, or points and lines in one plane)")
    if single_pairs:
        # compiled per pair (reference: _max_pair_leverage; RANSAC asks at each of its
        # loop's iterations, and the numpy Jacobian and solve were 0.6 ms of 3.8)
        lev = (kernel.max_pair_leverage(*args, gram) if kernel is not None
               else _max_pair_leverage(J, gram))
        if lev > 1.0 - 1e-6:
            return (f"degenerate geometry: one degree of freedom of the pose rests on a single "
                    f"pair of the {k} kept (its leverage is 1; without it the pose is "
                    "undetermined: e.g. collinear inliers and one stray pair)")
    return ""


def _max_pair_leverage(J, gram) -> float:
    """The largest leverage of one pair (:func:`_undetermined`): the largest eigenvalue of
    each pair's 2x2 block of ``J C^-1 J^T``, ``J`` (2, K, 6) and ``C = gram`` from
    :func:`_rank_gram`. The numpy reference of ``_pose_numba.max_pair_leverage``."""
    k = J.shape[1]
    G = np.linalg.solve(gram, J.reshape(-1, 6).T).reshape(6, 2, k)
    B = np.einsum("rkj,jsk->krs", J, G)  # (k, 2, 2): each pair's block of J C^-1 J^T
    tr, det = B[:, 0, 0] + B[:, 1, 1], B[:, 0, 0] * B[:, 1, 1] - B[:, 0, 1] * B[:, 1, 0]
    return float(np.max(0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))))


def _verdict(res: PoseResult, p, o, d, cheirality: bool) -> PoseResult:
    """The solution's own checks: rank (a degenerate problem) and cheirality (a mirror
    pose with inliers behind their lines' origins) turn ``converged`` off."""
    if not res.converged:
        return res
    k = int(np.count_nonzero(res.inliers))
    if k == 3 < len(p) and res.method != "ransac":   # (RANSAC: ransac_min_inliers)
        # three pairs are six equations for the pose's six unknowns: the solver fits them
        # exactly whatever the pose, and the others, rejected, confirm nothing (a held-out
        # review: noise-free, 4 or 5 pairs, robust "converged" 0.2-1.4 units off)
        return replace(res, converged=False, message=(
            f"only 3 of {len(p)} pairs are inliers: three point-line pairs fit a pose "
            "exactly, so nothing confirms it"))
    P = p @ res.R.T + res.t
    why = _undetermined(P, o, d, res.weights, single_pairs=res.method == "ransac")
    if not why and cheirality:
        depth = np.sum((P - o) * d, axis=1)
        bad = res.inliers & ~(depth > 0)
        if np.any(bad):
            why = (f"cheirality: {int(np.count_nonzero(bad))} of the "
                   f"{int(np.count_nonzero(res.inliers))} inliers lie behind their lines' "
                   "origins (a mirror pose behind the source)")
    return res if not why else replace(res, converged=False, message=why)


def solve_pose(points, origins, directions, method: Method = "robust", *, initial=None,
               max_iterations: int = 100, tol: float = 1e-12, r: float = 0.1,
               tukey_a: float = 2.0, threshold: float | None = None, max_trials: int = 2000,
               confidence: float = 0.999, rng=0, check: bool = True,
               backend: Literal["auto", "numpy", "numba"] = "auto", normals=None,
               fixed_point=None, cheirality: bool = True,
               mirror_check: bool = True) -> PoseResult:
    """Rigid transform that puts ``points`` on their ``lines``.

    Parameters
    ----------
    points : (N, 3) 3-D points in their own frame (e.g. ``ct``, mm).
    origins, directions : (N, 3) each; lines in the target frame (e.g. ``robot``), unit
        directions. Point i corresponds to line i.
    method : "lm" | "linear" | "robust" | "ransac" (see the module docstring).
    initial : RigidTransform, (R, t) or a (4, 4) matrix, the starting pose (default
        identity); R must be a rotation (``R^T R = I``, ``det R = +1``) and both finite,
        else ValueError.
    max_iterations : iterations of the linearised methods (LM: 10x as many evaluations).
    tol : stop when the Cayley increment |u| < tol and |t| < tol * (size of the cloud).
        "linear" also stops, converged, when its cost (the sum of squared distances) stopped
        decreasing: two iterations in a row changed it by at most 1e-10 of itself.
    r : trust radius on the Cayley increment per iteration (paper: 0.1).
    tukey_a : Tukey's constant a, in units of the robust scale (paper: 2).
    threshold : "ransac" inlier distance (units of the input); default 2 % of the RMS radius
        of the point cloud.
    max_trials, confidence : "ransac" sampling limits.
    rng : seed or numpy Generator for "ransac" (default 0: the same call, the same pose).
    check : validate the input (shape, finite values, unit directions, degenerate points
        and lines).
    backend : the linearised iterations and the RANSAC hypothesis loop run compiled with
        numba ("auto" when numba is installed) or in numpy (the reference implementation).
    normals : (N, 3) unit vectors orthogonal to the directions, or None. Given, the residual
        of a pair is only its component along the normal (the distance to the plane through
        the line with that normal: the across-contour residual of the registration loop).
    fixed_point : (3,) point (target frame) or None. Given, only a rotation about it is
        solved (the paper's experiment 1, a located pin).
        With ``normals`` or ``fixed_point`` the solve is a Gauss-Newton IRLS
        (:func:`_solve_irls`), Tukey-weighted for "robust" and unweighted for "linear";
        ``max_iterations`` and ``tol`` apply to it, and "lm" and "ransac" are refused.
    cheirality : the lines are rays leaving their origins along their directions (X-ray
        paths from the source): "ransac" rejects a hypothesis that puts one of its sample
        points behind its origin and never counts a point behind as an inlier, and no
        method reports ``converged`` when an inlier lies behind its origin (the mirror
        pose that planar points admit). False: full lines, origins anywhere on them.
    mirror_check : "ransac" with ``cheirality`` only: when its consensus is weak (less than
        half the pairs) or it did not converge, the same samples are tried without the
        cheirality test, and a pose that fits far more pairs with most of them behind their
        origins (the lines' directions given reversed) makes the result not converged,
        saying so. About as much again as the RANSAC itself when it runs; a caller that
        judges the final pose's cheirality itself (``reglib.register``, whose matches are
        often under half inliers) turns it off.

    Returns
    -------
    PoseResult (falsy when not converged; ``message`` says why). Besides the method's own
    failures, ``converged`` is False for a degenerate problem (the kept pairs determine the
    pose only up to some motion: the rank test), for a cheirality violation, and for a
    "ransac" pose with fewer inliers than :func:`ransac_min_inliers`.

    Raises
    ------
    ValueError for bad input: unknown method, fewer points than the method needs, NaN or
    inf, shapes that disagree, zero or non-unit directions, coincident or collinear points,
    parallel or identical lines, an ``initial`` that is not a rigid transform, and
    option values out of range (``tukey_a``, ``tol``, ``r``, ``threshold``,
    ``max_iterations``, ``max_trials``, ``confidence``).
    """
    _check_options(method, max_iterations=max_iterations, tol=tol, r=r, tukey_a=tukey_a,
                   threshold=threshold, max_trials=max_trials, confidence=confidence,
                   backend=backend)
    for name, flag in (("cheirality", cheirality), ("check", check),
                       ("mirror_check", mirror_check)):
        if not isinstance(flag, bool | np.bool_):
            raise ValueError(f"{name}: expected True or False, got {flag!r}")
    if normals is not None or fixed_point is not None:
        if method not in ("robust", "linear"):
            raise ValueError(f"method {method!r} cannot solve with normals or a fixed point; "
                             "use 'robust' or 'linear'")
        x = as_points(points, "points")
        T0 = (RigidTransform(np.eye(3), np.zeros(3)) if initial is None
              else initial if isinstance(initial, RigidTransform)
              else RigidTransform(*_check_initial(initial)))
        U, dist, w, ok, msg = _solve_irls(T0.apply(x), origins, directions, normals=normals,
                                          fixed_point=fixed_point, robust=method == "robust",
                                          tukey_a=tukey_a, max_iterations=max_iterations,
                                          tol=max(tol, 1e-10), backend=backend)
        T = U @ T0
        res = PoseResult(T.R, T.t, dist, w, w > 0, max_iterations, bool(ok), method, msg)
        if res.converged and cheirality:
            o, d = as_lines(origins, directions)
            depth = np.sum((T.apply(x) - o) * d, axis=1)
            bad = res.inliers & ~(depth > 0)
            if np.any(bad):
                res = replace(res, converged=False, message=(
                    f"cheirality: {int(np.count_nonzero(bad))} of the "
                    f"{int(np.count_nonzero(res.inliers))} inliers lie behind their lines' "
                    "origins (a mirror pose behind the source)"))
        return res
    if initial is None:
        R0, t0 = np.eye(3), np.zeros(3)
    elif isinstance(initial, RigidTransform):
        R0, t0 = initial.R.copy(), initial.t.copy()
    else:
        R0, t0 = _check_initial(initial)
    if check:
        p, o, d = _check_inputs(points, origins, directions, method)
    else:
        p, o, d = (np.asarray(x, dtype=np.float64) for x in (points, origins, directions))
    if method == "lm":
        res = _solve_lm(p, o, d, R0, t0, max_iterations=max_iterations, tol=max(tol, 1e-15))
    elif method in ("linear", "robust"):
        res = _iterate_linearised(p, o, d, R0, t0, robust=method == "robust", r=r,
                                  max_iterations=max_iterations, tol=tol, a=tukey_a,
                                  method=method, backend=backend)
    else:
        res = _solve_ransac(p, o, d, R0, t0, threshold=threshold, max_trials=max_trials,
                            confidence=confidence, rng=rng, max_iterations=max_iterations,
                            tol=tol, a=tukey_a, r=r, backend=backend, cheirality=cheirality,
                            mirror_check=bool(mirror_check))
    return _verdict(res, p, o, d, cheirality)
