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
    Cayley rotation, iterate until the increments are small.
``"robust"``
    The same linearised step, each point weighted by Tukey's biweight of its distance
    (``a = 2``, scale ``s = median(d) / 0.6745``); the 6x6 normal equations are formed with
    vectorised numpy (no Python loop over points) and iterated.
``"ransac"``
    Beyond the paper: minimal samples of three point-line pairs solved exactly (all real
    solutions of the three distance constraints along the lines, found by bracketing a 1-D
    function and bisection), scored by their inliers, then refined by Tukey's biweight
    with a scale fixed from the inliers. Survives far more than 40 % outliers.

Linearisations rotate about the centroid of the current points, not about the origin, so
that the trust radius ``r`` means the same in mm-scale robot coordinates as in the unit
cube. All methods start from ``initial`` (default: identity, as in the paper).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import least_squares

from reglib.geometry import RigidTransform, as_lines, as_points, cayley, skew

__all__ = ["PoseResult", "solve_pose", "tukey_weights", "p3l_solutions", "MIN_POINTS"]

Method = Literal["lm", "linear", "robust", "ransac"]
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
    return p, o, d


# --------------------------------------------------------------------------- building blocks
def tukey_weights(z, a: float = 2.0) -> np.ndarray:
    """Tukey biweight ``psi(z)/z = (1 - (z/a)^2)^2`` for ``|z| < a``, else 0."""
    z = np.asarray(z, dtype=np.float64)
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
            max_iterations, tol, a, -1.0 if fixed_scale is None else float(fixed_scale), scale)
        messages = {
            0: "",
            1: f"no convergence after {max_iterations} iterations",
            2: f"fewer than 3 points kept by the biweight at iteration {it} "
               "(too many outliers or a start too far off)",
            3: f"singular linear system at iteration {it} (degenerate geometry)",
        }
        dist = kernel.distances(p, o, d, R, tt)
        if robust:
            s = fixed_scale if fixed_scale is not None else _median(dist) / 0.6745
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
    for it in range(1, max_iterations + 1):
        if robust:
            dist = _distances(P, o, d)
            s = fixed_scale if fixed_scale is not None else _median(dist) / 0.6745
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
        C, g, _ = _linear_system(P, o, Nb, m, weights)
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
        s = fixed_scale if fixed_scale is not None else _median(dist) / 0.6745
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
    p = np.asarray(p, float)
    o = np.asarray(o, float)
    d = np.asarray(d, float)
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


def _solve_ransac(p, o, d, R0, t0, *, threshold, max_trials, confidence, rng,
                  max_iterations, tol, a, r, backend):
    n = len(p)
    scale = _scale_of(p)
    thr = threshold if threshold is not None else 0.02 * scale
    rng = np.random.default_rng(rng)
    best_count, best_R, best_t, best_cost = -1, None, None, np.inf
    needed = max_trials
    trial = 0
    while trial < min(needed, max_trials):
        trial += 1
        idx = rng.choice(n, 3, replace=False)
        pi = p[idx]
        c = pi - pi.mean(0)
        sv = np.linalg.svd(c, compute_uv=False)
        if sv[1] < 1e-6 * max(sv[0], 1e-300):
            continue
        Rs, ts = p3l_solutions(pi, o[idx], d[idx])
        if len(Rs) == 0:
            continue
        P = np.einsum("kij,nj->kni", Rs, p) + ts[:, None, :]  # (K, N, 3)
        w_ = P - o
        e = w_ - np.sum(w_ * d, axis=-1, keepdims=True) * d
        dist = np.sqrt(np.sum(e * e, axis=-1))
        inl = dist < thr
        counts = inl.sum(1)
        costs = np.sum(np.minimum(dist, thr) ** 2, axis=1)  # MSAC score for ties
        k = int(np.lexsort((costs, -counts))[0])
        if counts[k] > best_count or (counts[k] == best_count and costs[k] < best_cost):
            best_count, best_cost = int(counts[k]), float(costs[k])
            best_R, best_t = Rs[k], ts[k]
            frac = best_count / n
            if frac >= 1.0:
                needed = trial
            elif frac > 0:
                needed = int(np.ceil(np.log(1 - confidence) / np.log(1 - frac**3)))
    if best_R is None or best_count < 3:
        dist = _distances(p @ R0.T + t0, o, d)
        w = np.zeros(n)
        return PoseResult(R0, t0, dist, w, w > 0, 0, False, "ransac",
                          f"no minimal sample gave a pose with >= 3 inliers in {trial} trials",
                          trial)
    # refine: Tukey with a scale fixed from the inliers of the best hypothesis
    dist = _distances(p @ best_R.T + best_t, o, d)
    inl = dist < thr
    s = max(np.median(dist[inl]) / 0.6745, thr / (2 * a))
    res = _iterate_linearised(p, o, d, best_R, best_t, robust=True, r=r,
                              max_iterations=max_iterations, tol=tol, a=max(a, 3.0),
                              fixed_scale=s, method="ransac", backend=backend)
    return PoseResult(res.R, res.t, res.residuals, res.weights, res.inliers, res.iterations,
                      res.converged, "ransac", res.message, trial)


# --------------------------------------------------------------------------- entry point
def solve_pose(points, origins, directions, method: Method = "robust", *, initial=None,
               max_iterations: int = 100, tol: float = 1e-12, r: float = 0.1,
               tukey_a: float = 2.0, threshold: float | None = None, max_trials: int = 2000,
               confidence: float = 0.999, rng=None, check: bool = True,
               backend: Literal["auto", "numpy", "numba"] = "auto") -> PoseResult:
    """Rigid transform that puts ``points`` on their ``lines``.

    Parameters
    ----------
    points : (N, 3) 3-D points in their own frame (e.g. ``ct``, mm).
    origins, directions : (N, 3) each; lines in the target frame (e.g. ``robot``), unit
        directions. Point i corresponds to line i.
    method : "lm" | "linear" | "robust" | "ransac" (see the module docstring).
    initial : RigidTransform or (R, t), the starting pose (default identity).
    max_iterations : iterations of the linearised methods (LM: 10x as many evaluations).
    tol : stop when the Cayley increment |u| < tol and |t| < tol * (size of the cloud).
    r : trust radius on the Cayley increment per iteration (paper: 0.1).
    tukey_a : Tukey's constant a, in units of the robust scale (paper: 2).
    threshold : "ransac" inlier distance (units of the input); default 2 % of the RMS radius
        of the point cloud.
    max_trials, confidence : "ransac" sampling limits.
    rng : seed or numpy Generator for "ransac".
    check : validate the input (shape, finite values, unit directions, degenerate points).
    backend : the linearised iterations run compiled with numba ("auto" when numba is
        installed) or in numpy (the reference implementation).

    Returns
    -------
    PoseResult (falsy when not converged; ``message`` says why).

    Raises
    ------
    ValueError for bad input: unknown method, fewer points than the method needs, NaN or
    inf, shapes that disagree, zero or non-unit directions, coincident or collinear points.
    """
    if check:
        p, o, d = _check_inputs(points, origins, directions, method)
    else:
        p, o, d = (np.asarray(x, dtype=np.float64) for x in (points, origins, directions))
    if initial is None:
        R0, t0 = np.eye(3), np.zeros(3)
    elif isinstance(initial, RigidTransform):
        R0, t0 = initial.R.copy(), initial.t.copy()
    else:
        R0, t0 = (np.asarray(x, dtype=np.float64) for x in initial)
    if method == "lm":
        return _solve_lm(p, o, d, R0, t0, max_iterations=max_iterations, tol=max(tol, 1e-15))
    if method == "linear":
        return _iterate_linearised(p, o, d, R0, t0, robust=False, r=r,
                                   max_iterations=max_iterations, tol=tol, a=tukey_a,
                                   method="linear", backend=backend)
    if method == "robust":
        return _iterate_linearised(p, o, d, R0, t0, robust=True, r=r,
                                   max_iterations=max_iterations, tol=tol, a=tukey_a,
                                   method="robust", backend=backend)
    return _solve_ransac(p, o, d, R0, t0, threshold=threshold, max_trials=max_trials,
                         confidence=confidence, rng=rng, max_iterations=max_iterations,
                         tol=tol, a=tukey_a, r=r, backend=backend)
