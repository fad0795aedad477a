"""Compiled parts of the image snake (reglib.contours): the derivatives of a tensor-product
B-spline surface at scattered points, as ``scipy.interpolate.RectBivariateSpline(...)(x, y,
dx=1, grid=False)`` computes them from the same knots and coefficients.

scikit-image's ``active_contour`` evaluates the image's spline twice per iteration through
FITPACK, about 9 us a call whatever the number of points: 0.45 s of a capture-range trial's
3.3 s. The same de Boor recursion, compiled, is a few microseconds; the reference is
scipy's evaluation, compared in tests/reglib/test_contours.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _span(t, k, n_coef, v):
    """Index ``l`` with ``t[l] <= v < t[l+1]``, ``k <= l < n_coef`` (the last piece for
    ``v`` at the right end)."""
    lo, hi = k, n_coef - 1
    if v >= t[hi + 1]:
        return hi
    if v < t[lo]:
        return lo
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if t[mid] <= v:
            lo = mid
        else:
            hi = mid
    if t[hi] <= v:
        return hi
    return lo


@njit(cache=True)
def _basis(t, k, l, v, out, dout):
    """The ``k + 1`` non-zero B-splines of degree ``k`` at ``v`` on span ``l`` into
    ``out[:k + 1]`` and their derivatives into ``dout[:k + 1]`` (Cox-de Boor: the
    derivatives come from the degree-``k - 1`` values the recursion passes through)."""
    out[0] = 1.0
    for j in range(1, k + 1):
        if j == k:   # d/dv of the degree-k splines from the degree-(k-1) ones
            for r in range(k + 1):
                a = 0.0
                if r >= 1:
                    den = t[l + r] - t[l + r - k]
                    if den > 0:
                        a += out[r - 1] / den
                if r <= k - 1:
                    den = t[l + r + 1] - t[l + r + 1 - k]
                    if den > 0:
                        a -= out[r] / den
                dout[r] = k * a
        saved = 0.0
        for r in range(j):
            left = t[l + r + 1 - j]
            right = t[l + r + 1]
            w = out[r] / (right - left)
            out[r] = saved + (right - v) * w
            saved = (v - left) * w
        out[j] = saved
    if k == 0:
        dout[0] = 0.0


@njit(cache=True)
def spline_gradient(tx, ty, c, kx, ky, x, y, gx, gy):
    """``gx[i] = dS/dx`` and ``gy[i] = dS/dy`` of the spline surface ``S`` (knots ``tx``,
    ``ty``, coefficients ``c`` (nx - kx - 1) * (ny - ky - 1) row-major in x, degrees ``kx``,
    ``ky``) at the points ``(x[i], y[i])``."""
    nyc = len(ty) - ky - 1
    nxc = len(tx) - kx - 1
    bx = np.empty(kx + 1)
    dbx = np.empty(kx + 1)
    by = np.empty(ky + 1)
    dby = np.empty(ky + 1)
    for i in range(len(x)):
        # FITPACK clamps a point outside the knots' range to it
        xi = min(max(x[i], tx[kx]), tx[nxc])
        yi = min(max(y[i], ty[ky]), ty[nyc])
        lx = _span(tx, kx, nxc, xi)
        ly = _span(ty, ky, nyc, yi)
        _basis(tx, kx, lx, xi, bx, dbx)
        _basis(ty, ky, ly, yi, by, dby)
        sx = 0.0
        sy = 0.0
        for a in range(kx + 1):
            row = (lx - kx + a) * nyc
            for b in range(ky + 1):
                cv = c[row + ly - ky + b]
                sx += dbx[a] * by[b] * cv
                sy += bx[a] * dby[b] * cv
        gx[i] = sx
        gy[i] = sy


@njit(cache=True)
def snake_loop(inv, x, y, tx, ty, c, gamma, max_px_move, convergence, convergence_order,
               max_iter, sfixed, efixed, sfree, efree):
    """The explicit steps of the snake (reglib.contours._snake_steps) on ``x``, ``y`` (n,)
    px in place: image forces from :func:`spline_gradient`, the implicit shape step
    ``inv @ (gamma * x + fx)``, moves capped by ``max_px_move * tanh``, and the convergence
    test against the last ``convergence_order`` positions every ``convergence_order + 1``
    steps, as in scikit-image's active_contour. Returns the number of steps taken."""
    n = x.shape[0]
    fx = np.empty(n)
    fy = np.empty(n)
    bx = np.empty(n)
    by = np.empty(n)
    xsave = np.empty((convergence_order, n))
    ysave = np.empty((convergence_order, n))
    steps = 0
    for i in range(max_iter):
        steps = i + 1
        spline_gradient(tx, ty, c, 2, 2, x, y, fx, fy)
        if sfixed:
            fx[0] = 0.0
            fy[0] = 0.0
        if efixed:
            fx[n - 1] = 0.0
            fy[n - 1] = 0.0
        if sfree:
            fx[0] *= 2.0
            fy[0] *= 2.0
        if efree:
            fx[n - 1] *= 2.0
            fy[n - 1] *= 2.0
        for k in range(n):
            bx[k] = gamma * x[k] + fx[k]
            by[k] = gamma * y[k] + fy[k]
        xn = inv @ bx
        yn = inv @ by
        for k in range(n):
            dx = max_px_move * np.tanh(xn[k] - x[k])
            dy = max_px_move * np.tanh(yn[k] - y[k])
            if (sfixed and k == 0) or (efixed and k == n - 1):
                dx = 0.0
                dy = 0.0
            x[k] += dx
            y[k] += dy
        j = i % (convergence_order + 1)
        if j < convergence_order:
            for k in range(n):
                xsave[j, k] = x[k]
                ysave[j, k] = y[k]
        else:
            dist = np.inf
            for r in range(convergence_order):
                m = 0.0
                for k in range(n):
                    v = abs(xsave[r, k] - x[k]) + abs(ysave[r, k] - y[k])
                    if v > m:
                        m = v
                if m < dist:
                    dist = m
            if dist < convergence:
                break
    return steps
