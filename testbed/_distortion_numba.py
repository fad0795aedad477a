"""Compiled (numba) inverse of the intensifier distortion, point by point.

The numpy Newton iterations of :meth:`testbed.fluoroscope.Distortion.undistort` are the
reference; this kernel performs the same iteration per point (the same analytic Jacobian and
tolerance; the start is the reference's, or, along a row of pixels, a prediction from the
previous solutions) in scalar code, evaluating the distortion and its
Jacobian together; along a grid row each local term's sine and cosine follow from the
previous point's by angle addition (:func:`_distort_jac_rec`).
``tests/testbed/test_fluoroscope.py`` compares both on random distortions.
"""

from __future__ import annotations

import numpy as np
from numba import njit

WARM_PX = 2.0
"""Largest step (px, per axis) from the previous point for a warm start."""


@njit(cache=True, inline="always")
def _sincos_small(x):
    """sin and cos of ``|x| <= SMALL_RAD`` by their Taylor series to x^13 and x^14 (the next
    terms are below 2e-17 there), nested."""
    x2 = x * x
    s = x * (1.0 - x2 * _I6 * (1.0 - x2 * _I20 * (1.0 - x2 * _I42 * (1.0 - x2 * _I72 * (
        1.0 - x2 * _I110 * (1.0 - x2 * _I156))))))
    c = 1.0 - x2 * 0.5 * (1.0 - x2 * _I12 * (1.0 - x2 * _I30 * (1.0 - x2 * _I56 * (
        1.0 - x2 * _I90 * (1.0 - x2 * _I132 * (1.0 - x2 * _I182))))))
    return s, c


# reciprocals of the Taylor factors (multiplications, not divisions, in the loop)
_I6, _I20, _I42, _I72, _I110, _I156 = (1.0 / 6.0, 1.0 / 20.0, 1.0 / 42.0, 1.0 / 72.0,
                                       1.0 / 110.0, 1.0 / 156.0)
_I12, _I30, _I56, _I90, _I132, _I182 = (1.0 / 12.0, 1.0 / 30.0, 1.0 / 56.0, 1.0 / 90.0,
                                        1.0 / 132.0, 1.0 / 182.0)


SMALL_RAD = 0.5
"""Phase steps up to this (rad) are taken by the angle-addition recurrence."""
TINY_RAD = 2e-3
"""Phase steps up to this (rad) need only three Taylor terms."""


@njit(cache=True, inline="always", fastmath={"reassoc", "contract", "nsz"})
def _distort_jac_rec(ux, uy, cx, cy, r2, k1, k2, rot, sx, sy, amp, freq, phase, f_max,
                     S, C, ref):
    """distort(u) and its Jacobian at one undistorted point (see Distortion), for a
    sequence of nearby points: each local term's sine and
    cosine at ``u`` are those at the previous point ``ref[:2]`` (kept in ``S``, ``C``)
    turned by the phase step, by angle addition with a Taylor sine and cosine of the small
    step, instead of two library calls per term. ``ref[2] = 0`` (or a step above
    ``SMALL_RAD``) evaluates them directly and starts a new sequence. Equal to the direct
    evaluation to ~1e-13 over a row of a grid (rounding accumulates per step)."""
    px, py = ux - cx, uy - cy
    rho2 = (px * px + py * py) / r2
    g = 1.0 + k1 * rho2 + k2 * rho2 * rho2
    th = rot * rho2
    if abs(th) <= SMALL_RAD:
        sn, cs = _sincos_small(th)
    else:
        cs, sn = np.cos(th), np.sin(th)
    qx, qy = px * g, py * g
    fx = cx + cs * qx - sn * qy + sx
    fy = cy + sn * qx + cs * qy + sy
    dg = (2.0 / r2) * (k1 + 2.0 * k2 * rho2)
    dth = (2.0 / r2) * rot
    i00 = g + dg * px * px - dth * qy * px
    i01 = dg * px * py - dth * qy * py
    i10 = dg * py * px + dth * qx * px
    i11 = g + dg * py * py + dth * qx * py
    j00 = cs * i00 - sn * i10
    j01 = cs * i01 - sn * i11
    j10 = sn * i00 + cs * i10
    j11 = sn * i01 + cs * i11
    two_pi = 2.0 * np.pi
    ex, ey = ux - ref[0], uy - ref[1]
    step = two_pi * f_max * np.sqrt(ex * ex + ey * ey)    # the largest phase step (rad)
    rec = ref[2] > 0.0 and step <= SMALL_RAD
    tiny = step <= TINY_RAD
    for k in range(amp.shape[0]):
        if rec:
            x = two_pi * (freq[k, 0] * ex + freq[k, 1] * ey)
            if tiny:       # a Newton correction: three terms suffice (next below 1e-22)
                x2 = x * x
                sd = x * (1.0 - x2 * _I6 * (1.0 - x2 * _I20))
                cd = 1.0 - x2 * 0.5 * (1.0 - x2 * _I12 * (1.0 - x2 * _I30))
            else:
                sd, cd = _sincos_small(x)
            s = S[k] * cd + C[k] * sd
            c = C[k] * cd - S[k] * sd
        else:
            arg = two_pi * (px * freq[k, 0] + py * freq[k, 1]) + phase[k]
            s, c = np.sin(arg), np.cos(arg)
        S[k], C[k] = s, c
        fx += amp[k, 0] * s
        fy += amp[k, 1] * s
        j00 += c * amp[k, 0] * two_pi * freq[k, 0]
        j01 += c * amp[k, 0] * two_pi * freq[k, 1]
        j10 += c * amp[k, 1] * two_pi * freq[k, 0]
        j11 += c * amp[k, 1] * two_pi * freq[k, 1]
    ref[0], ref[1], ref[2] = ux, uy, 1.0
    return fx, fy, j00, j01, j10, j11


@njit(cache=True, fastmath={"reassoc", "contract", "nsz"})
def undistort(d, cx, cy, radius, k1, k2, rot, sx, sy, amp, freq, phase, tol, max_iter,
              half_curvature, reach):
    """Undistorted pixels ``(N, 2)`` of distorted ``d (N, 2)``; ``ok`` False where the
    iteration did not reach ``tol`` px in ``max_iter`` steps.

    Starts: a point continuing an evenly spaced run of at least four solved points (a row of
    a pixel grid) starts from their cubic extrapolation (~1e-5 px off for the clinic's
    distortion); a point within ``WARM_PX`` of the previous one from the previous solution
    moved by the inverse Jacobian there (~1e-3 px off); others from the reference's start.
    A Newton step ``s`` is accepted without evaluating the residual again when
    ``half_curvature * |s|^2 < tol``, ``half_curvature`` half a bound of the distortion's
    second derivative within ``reach`` px of the centre
    (:meth:`testbed.fluoroscope.Distortion.curvature_bound`) and both ends of the step
    inside that disc: by Taylor's theorem the residual after the step is then below ``tol``,
    the reference's test. From the cubic start that is one evaluation of the distortion per
    pixel of a grid.
    """
    n = d.shape[0]
    r2 = radius * radius
    reach2 = reach * reach
    nk = amp.shape[0]
    S = np.zeros(nk)
    C = np.zeros(nk)
    ref = np.zeros(3)           # the point S and C belong to, and whether they are valid
    f_max = 0.0
    for k in range(nk):
        f_max = max(f_max, np.sqrt(freq[k, 0] ** 2 + freq[k, 1] ** 2))
    out = np.empty((n, 2))
    ok = np.ones(n, dtype=np.bool_)
    have_prev = False
    pdx = pdy = 0.0
    pj00 = pj01 = pj10 = pj11 = 0.0
    hist = np.zeros((4, 2))     # the last four solutions, the newest first
    run = 0                     # evenly spaced solved points ending at the previous one
    rex = rey = 0.0             # their spacing
    for i in range(n):
        dx, dy = d[i, 0], d[i, 1]
        ex, ey = dx - pdx, dy - pdy
        warm = have_prev and abs(ex) <= WARM_PX and abs(ey) <= WARM_PX
        if warm and run >= 4 and ex == rex and ey == rey:
            ux = 4.0 * hist[0, 0] - 6.0 * hist[1, 0] + 4.0 * hist[2, 0] - hist[3, 0]
            uy = 4.0 * hist[0, 1] - 6.0 * hist[1, 1] + 4.0 * hist[2, 1] - hist[3, 1]
        elif warm:
            det = pj00 * pj11 - pj01 * pj10
            ux = hist[0, 0] + (pj11 * ex - pj01 * ey) / det
            uy = hist[0, 1] + (-pj10 * ex + pj00 * ey) / det
        else:
            ref[2] = 0.0        # a new sequence: the phases evaluated directly again
            fx, fy, _, _, _, _ = _distort_jac_rec(dx, dy, cx, cy, r2, k1, k2, rot, sx, sy,
                                                  amp, freq, phase, f_max, S, C, ref)
            ux, uy = 2.0 * dx - fx, 2.0 * dy - fy
        done = False
        for _ in range(max_iter):
            fx, fy, j00, j01, j10, j11 = _distort_jac_rec(ux, uy, cx, cy, r2, k1, k2, rot,
                                                          sx, sy, amp, freq, phase, f_max,
                                                          S, C, ref)
            rx, ry = fx - dx, fy - dy
            if abs(rx) < tol and abs(ry) < tol:
                done = True
                break
            det = j00 * j11 - j01 * j10
            sx_ = (j11 * rx - j01 * ry) / det
            sy_ = (-j10 * rx + j00 * ry) / det
            before = (ux - cx) ** 2 + (uy - cy) ** 2
            ux -= sx_
            uy -= sy_
            if (half_curvature * (sx_ * sx_ + sy_ * sy_) < tol and before <= reach2
                    and (ux - cx) ** 2 + (uy - cy) ** 2 <= reach2):
                done = True     # the residual after this step is below tol (Taylor)
                break
        out[i, 0], out[i, 1] = ux, uy
        ok[i] = done
        if not done:
            run = 0
        elif have_prev and run >= 2 and ex == rex and ey == rey:
            run += 1
        elif have_prev:
            run, rex, rey = 2, ex, ey
        else:
            run = 1
        have_prev = done
        pdx, pdy = dx, dy
        for j in range(3, 0, -1):   # element by element: a row assignment would compile
            hist[j, 0] = hist[j - 1, 0]     # numba's shape-checked copy (+1 s first run)
            hist[j, 1] = hist[j - 1, 1]
        hist[0, 0], hist[0, 1] = ux, uy
        pj00, pj01, pj10, pj11 = j00, j01, j10, j11
    return out, ok
