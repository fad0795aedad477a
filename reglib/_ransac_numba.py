"""Compiled (numba) hypothesis loop of ``solve_pose(..., method="ransac")``.

The numpy implementation in :mod:`reglib.pose` (``_ransac_hypotheses_numpy`` and
:func:`reglib.pose.p3l_solutions`) is the reference; this kernel performs the same steps per
trial -- the same pre-drawn samples, the same degeneracy test of a sample, the same minimal
solver (bracketing of the 1-D constraint on the same cosine grid over the four branches,
refined by the same Illinois iteration), the same cheirality test and MSAC scoring and the
same adaptive stopping -- in scalar code without temporaries. The one difference: the
rotation of a minimal solution is built from the two congruent triangles' orthonormal frames
(exact for an exact solution) instead of the reference's SVD (Kabsch).
``tests/reglib/test_pose.py`` compares both on random cases.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from reglib._pose_numba import unit_cross

MAX_SOLUTIONS = 64  # 4 branches x brackets; real solutions are at most 8 (+ duplicates)


@njit(cache=True)
def _reach(x0, x1, x2, o, d, j, D):
    """Along line j, the two parameters ``b +- s`` at distance ``sqrt(D)`` from (x0, x1, x2)
    (``s`` is 0 where the line is out of reach, as the reference's clipped square root)."""
    a0 = x0 - o[j, 0]
    a1 = x1 - o[j, 1]
    a2 = x2 - o[j, 2]
    b = a0 * d[j, 0] + a1 * d[j, 1] + a2 * d[j, 2]
    q = b * b - (a0 * a0 + a1 * a1 + a2 * a2) + D
    return b, (np.sqrt(q) if q > 0.0 else 0.0)


@njit(cache=True)
def _gap(l2, l3, o, d, D23):
    """``|X2 - X3|^2 - D23`` for the points at l2 on line 1 and l3 on line 2."""
    s = 0.0
    for j in range(3):
        e = o[1, j] + l2 * d[1, j] - o[2, j] - l3 * d[2, j]
        s += e * e
    return s - D23


@njit(cache=True)
def _branch_values(lam, o, d, D12, D13, D23, out):
    """``|X2 - X3|^2 - D23`` of the four sign branches at ``lam`` (into out[4])."""
    x0 = o[0, 0] + lam * d[0, 0]
    x1 = o[0, 1] + lam * d[0, 1]
    x2 = o[0, 2] + lam * d[0, 2]
    b2, s2 = _reach(x0, x1, x2, o, d, 1, D12)
    b3, s3 = _reach(x0, x1, x2, o, d, 2, D13)
    out[0] = _gap(b2 + s2, b3 + s3, o, d, D23)
    out[1] = _gap(b2 + s2, b3 - s3, o, d, D23)
    out[2] = _gap(b2 - s2, b3 + s3, o, d, D23)
    out[3] = _gap(b2 - s2, b3 - s3, o, d, D23)


@njit(cache=True)
def _branch_value(lam, o, d, D12, D13, D23, sg2, sg3, X):
    """One branch's constraint value at ``lam``; the three points into X (3, 3)."""
    for j in range(3):
        X[0, j] = o[0, j] + lam * d[0, j]
    b2, s2 = _reach(X[0, 0], X[0, 1], X[0, 2], o, d, 1, D12)
    b3, s3 = _reach(X[0, 0], X[0, 1], X[0, 2], o, d, 2, D13)
    l2 = b2 + sg2 * s2
    l3 = b3 + sg3 * s3
    for j in range(3):
        X[1, j] = o[1, j] + l2 * d[1, j]
        X[2, j] = o[2, j] + l3 * d[2, j]
    return _gap(l2, l3, o, d, D23)


@njit(cache=True)
def _sign(x):
    return 1.0 if x > 0.0 else (-1.0 if x < 0.0 else 0.0)


@njit(cache=True)
def _frame(A, F):
    """Orthonormal frame (columns of F) of the triangle A[0], A[1], A[2]."""
    u0 = A[1, 0] - A[0, 0]
    u1 = A[1, 1] - A[0, 1]
    u2 = A[1, 2] - A[0, 2]
    v0 = A[2, 0] - A[0, 0]
    v1 = A[2, 1] - A[0, 1]
    v2 = A[2, 2] - A[0, 2]
    nu = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    u0 /= nu
    u1 /= nu
    u2 /= nu
    w0, w1, w2 = unit_cross(u0, u1, u2, v0, v1, v2)
    F[0, 0] = u0
    F[1, 0] = u1
    F[2, 0] = u2
    F[0, 1] = w1 * u2 - w2 * u1
    F[1, 1] = w2 * u0 - w0 * u2
    F[2, 1] = w0 * u1 - w1 * u0
    F[0, 2] = w0
    F[1, 2] = w1
    F[2, 2] = w2


@njit(cache=True)
def cosine_grid(grid):
    """``0.5 - 0.5 cos(pi i / (grid - 1))``, i < grid: the reference's grid on [0, 1]."""
    s = np.empty(grid)
    for i in range(grid):
        s[i] = 0.5 - 0.5 * np.cos(np.pi * i / (grid - 1))
    return s


@njit(cache=True)
def p3l(p, o, d, sgrid, Rs, ts):
    """All poses putting the three points ``p`` (3, 3) on the lines ``(o, d)`` (3, 3) each.

    Same algorithm as :func:`reglib.pose.p3l_solutions` on the grid ``sgrid`` (from
    :func:`cosine_grid`); solutions into ``Rs`` (K, 3, 3) and ``ts`` (K, 3); returns their
    number.
    """
    grid = sgrid.shape[0]
    D12 = 0.0
    D13 = 0.0
    D23 = 0.0
    for j in range(3):
        D12 += (p[0, j] - p[1, j]) ** 2
        D13 += (p[0, j] - p[2, j]) ** 2
        D23 += (p[1, j] - p[2, j]) ** 2
    lo = -np.inf
    hi = np.inf
    for jj in range(2):
        j = jj + 1
        Dj = D12 if j == 1 else D13
        dd = d[0, 0] * d[j, 0] + d[0, 1] * d[j, 1] + d[0, 2] * d[j, 2]
        Mv0 = d[0, 0] - dd * d[j, 0]
        Mv1 = d[0, 1] - dd * d[j, 1]
        Mv2 = d[0, 2] - dd * d[j, 2]
        w0 = o[0, 0] - o[j, 0]
        w1 = o[0, 1] - o[j, 1]
        w2 = o[0, 2] - o[j, 2]
        wd = w0 * d[j, 0] + w1 * d[j, 1] + w2 * d[j, 2]
        Mw0 = w0 - wd * d[j, 0]
        Mw1 = w1 - wd * d[j, 1]
        Mw2 = w2 - wd * d[j, 2]
        A = Mv0 * Mv0 + Mv1 * Mv1 + Mv2 * Mv2
        B = Mv0 * Mw0 + Mv1 * Mw1 + Mv2 * Mw2
        Cc = Mw0 * Mw0 + Mw1 * Mw1 + Mw2 * Mw2 - Dj
        if A < 1e-14:
            if Cc > 0:
                return 0
            continue
        disc = B * B - A * Cc
        if disc < 0:
            return 0
        sq = np.sqrt(disc)
        lo = max(lo, (-B - sq) / A)
        hi = min(hi, (-B + sq) / A)
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return 0
    lam = np.empty(grid)
    vals = np.empty((grid, 4))
    for i in range(grid):
        lam[i] = lo + (hi - lo) * sgrid[i]
        _branch_values(lam[i], o, d, D12, D13, D23, vals[i])
    X = np.empty((3, 3))
    Fp = np.empty((3, 3))
    Fx = np.empty((3, 3))
    _frame(p, Fp)
    mp0 = (p[0, 0] + p[1, 0] + p[2, 0]) / 3.0
    mp1 = (p[0, 1] + p[1, 1] + p[2, 1]) / 3.0
    mp2 = (p[0, 2] + p[1, 2] + p[2, 2]) / 3.0
    k = 0
    sgn2 = (1.0, 1.0, -1.0, -1.0)
    sgn3 = (1.0, -1.0, 1.0, -1.0)
    for br in range(4):  # the reference's bracket order: branch, then grid index
        sg2 = sgn2[br]
        sg3 = sgn3[br]
        for i in range(grid - 1):
            fa = vals[i, br]
            fb = vals[i + 1, br]
            if _sign(fa) * _sign(fb) > 0:
                continue
            a = lam[i]
            b = lam[i + 1]
            side = 0
            for _ in range(100):
                denom = fb - fa
                c = (a * fb - b * fa) / denom if denom != 0 else 0.5 * (a + b)
                if not (c > min(a, b) and c < max(a, b)):
                    c = 0.5 * (a + b)
                fc = _branch_value(c, o, d, D12, D13, D23, sg2, sg3, X)
                if _sign(fa) * _sign(fc) <= 0:  # root in [a, c]
                    if side == -1:
                        fa = 0.5 * fa
                    fb = fc
                    b = c
                    side = -1
                else:
                    if side == 1:
                        fb = 0.5 * fb
                    fa = fc
                    a = c
                    side = 1
                if abs(b - a) <= 1e-15 * (1.0 + abs(a)) or fc == 0:
                    break
            root = 0.5 * (a + b)
            val = _branch_value(root, o, d, D12, D13, D23, sg2, sg3, X)
            if not abs(val) < 1e-6 * max(D23, 1e-300):
                continue
            if k == Rs.shape[0]:
                return k
            _frame(X, Fx)
            for r in range(3):
                for c_ in range(3):
                    Rs[k, r, c_] = (Fx[r, 0] * Fp[c_, 0] + Fx[r, 1] * Fp[c_, 1]
                                    + Fx[r, 2] * Fp[c_, 2])
            for r in range(3):
                mx = (X[0, r] + X[1, r] + X[2, r]) / 3.0
                ts[k, r] = mx - (Rs[k, r, 0] * mp0 + Rs[k, r, 1] * mp1 + Rs[k, r, 2] * mp2)
            k += 1
    return k


@njit(cache=True)
def sample_is_degenerate(p, i0, i1, i2):
    """Same test as the reference: the triangle's doubled area below 1e-6 of its longest
    squared side (nearly collinear points: the minimal problem is ill-posed)."""
    u0 = p[i1, 0] - p[i0, 0]
    u1 = p[i1, 1] - p[i0, 1]
    u2 = p[i1, 2] - p[i0, 2]
    v0 = p[i2, 0] - p[i0, 0]
    v1 = p[i2, 1] - p[i0, 1]
    v2 = p[i2, 2] - p[i0, 2]
    c0 = u1 * v2 - u2 * v1
    c1 = u2 * v0 - u0 * v2
    c2 = u0 * v1 - u1 * v0
    area2 = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    w0 = v0 - u0
    w1 = v1 - u1
    w2 = v2 - u2
    L2 = max(u0 * u0 + u1 * u1 + u2 * u2, v0 * v0 + v1 * v1 + v2 * v2,
             w0 * w0 + w1 * w1 + w2 * w2)
    return not area2 >= 1e-6 * L2


@njit(cache=True)
def hypotheses(p, o, d, samples, thr, confidence, max_trials, grid, cheirality, prune=True):
    """The RANSAC hypothesis loop.

    Parameters
    ----------
    p, o, d : (N, 3) points, line origins, unit directions.
    samples : (T, 3) int64, distinct index triples drawn in advance (T >= max_trials).
    thr : inlier distance; confidence : stopping confidence; max_trials : trial limit.
    grid : grid size of the minimal solver; cheirality : require points in front of their
        lines' origins (sample points in front, else the hypothesis is rejected; points
        behind never count as inliers).
    prune : stop scoring a hypothesis once it cannot reach the best inlier count so far
        (the same result; False scores every pair of every hypothesis, the twin the tests
        compare with).

    Returns
    -------
    (R (3, 3), t (3,), best inlier count (-1: no hypothesis), best MSAC cost, trials,
     hypotheses rejected by cheirality)
    """
    n = p.shape[0]
    sgrid = cosine_grid(grid)
    Rs = np.empty((MAX_SOLUTIONS, 3, 3))
    ts = np.empty((MAX_SOLUTIONS, 3))
    pi = np.empty((3, 3))
    oi = np.empty((3, 3))
    di = np.empty((3, 3))
    best_R = np.eye(3)
    best_t = np.zeros(3)
    best_count = -1
    best_cost = np.inf
    needed = max_trials
    trial = 0
    behind = 0
    thr2 = thr * thr
    log_conf = np.log(1.0 - confidence)
    while trial < min(needed, max_trials):
        i0 = samples[trial, 0]
        i1 = samples[trial, 1]
        i2 = samples[trial, 2]
        trial += 1
        if sample_is_degenerate(p, i0, i1, i2):
            continue
        for r, ix in enumerate((i0, i1, i2)):
            for j in range(3):
                pi[r, j] = p[ix, j]
                oi[r, j] = o[ix, j]
                di[r, j] = d[ix, j]
        K = p3l(pi, oi, di, sgrid, Rs, ts)
        k_best = -1
        c_best = -1
        cost_best = np.inf
        for k in range(K):
            R = Rs[k]
            t = ts[k]
            if cheirality:
                front = True
                for ix in (i0, i1, i2):
                    dep = 0.0
                    for j in range(3):
                        x = R[j, 0] * p[ix, 0] + R[j, 1] * p[ix, 1] + R[j, 2] * p[ix, 2] + t[j]
                        dep += (x - o[ix, j]) * d[ix, j]
                    if not dep > 0.0:
                        front = False
                if not front:
                    behind += 1
                    continue
            cnt = 0
            cost = 0.0
            hopeless = False
            for i in range(n):
                w0 = R[0, 0] * p[i, 0] + R[0, 1] * p[i, 1] + R[0, 2] * p[i, 2] + t[0] - o[i, 0]
                w1 = R[1, 0] * p[i, 0] + R[1, 1] * p[i, 1] + R[1, 2] * p[i, 2] + t[1] - o[i, 1]
                w2 = R[2, 0] * p[i, 0] + R[2, 1] * p[i, 1] + R[2, 2] * p[i, 2] + t[2] - o[i, 2]
                s = w0 * d[i, 0] + w1 * d[i, 1] + w2 * d[i, 2]
                e0 = w0 - s * d[i, 0]
                e1 = w1 - s * d[i, 1]
                e2 = w2 - s * d[i, 2]
                q = e0 * e0 + e1 * e1 + e2 * e2
                if q < thr2 and (s > 0.0 or not cheirality):
                    cnt += 1
                    cost += q
                else:
                    cost += thr2
                    # even with every remaining pair an inlier it would count fewer than
                    # the best hypothesis so far: it cannot be kept (nor can it decide
                    # which of this sample's solutions is kept, which only matters when
                    # that one beats the best), so its scoring stops (exact, when early)
                    if prune and cnt + (n - 1 - i) < best_count:
                        hopeless = True
                        break
            if hopeless:
                continue
            if cnt > c_best or (cnt == c_best and cost < cost_best):
                k_best = k
                c_best = cnt
                cost_best = cost
        if k_best < 0:
            continue
        if c_best > best_count or (c_best == best_count and cost_best < best_cost):
            best_count = c_best
            best_cost = cost_best
            best_R = Rs[k_best].copy()
            best_t = ts[k_best].copy()
            frac = best_count / n
            if frac >= 1.0:
                needed = trial
            elif frac > 0:
                needed = int(np.ceil(log_conf / np.log(1.0 - frac**3)))
    return best_R, best_t, best_count, best_cost, trial, behind
