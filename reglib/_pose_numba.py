"""Compiled (numba) kernel of the linearised pose iterations ("linear" and "robust").

The numpy implementation in :mod:`reglib.pose` is the reference; this kernel performs the
same arithmetic point by point without temporaries (normal equations accumulated in place,
the trust-region step on the 6x6 system), which is what makes a robust solve on 100 points
take tens of microseconds. ``tests/reglib/test_pose.py`` compares both on random cases.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from reglib.geometry import MAD_TO_SIGMA

STATUS_CONVERGED = 0
STATUS_MAX_ITER = 1
STATUS_FEW_WEIGHTS = 2
STATUS_SINGULAR = 3


@njit(cache=True)
def _cayley3(u):
    x, y, z = u[0], u[1], u[2]
    n = 1.0 + x * x + y * y + z * z
    Q = np.empty((3, 3))
    Q[0, 0] = (1 + x * x - y * y - z * z) / n
    Q[0, 1] = 2 * (x * y + z) / n
    Q[0, 2] = 2 * (x * z - y) / n
    Q[1, 0] = 2 * (x * y - z) / n
    Q[1, 1] = (1 - x * x + y * y - z * z) / n
    Q[1, 2] = 2 * (y * z + x) / n
    Q[2, 0] = 2 * (x * z + y) / n
    Q[2, 1] = 2 * (y * z - x) / n
    Q[2, 2] = (1 - x * x - y * y + z * z) / n
    return Q


@njit(cache=True)
def _trust_step(C, g, r):
    """Same problem as reglib.pose._trust_region_step; returns (u, t, ok)."""
    u = np.zeros(3)
    t = np.zeros(3)
    x = np.linalg.solve(C, -g)
    finite = True
    for k in range(6):
        if not np.isfinite(x[k]):
            finite = False
    if finite and (r <= 0 or x[0] * x[0] + x[1] * x[1] + x[2] * x[2] <= r * r):
        return x[:3].copy(), x[3:].copy(), True
    Cuu = C[:3, :3].copy()
    Cut = C[:3, 3:].copy()
    Ctt = C[3:, 3:].copy()
    Ctt_inv = np.linalg.pinv(Ctt, rcond=1e-13)
    K = Cut @ Ctt_inv
    S = Cuu - K @ Cut.T
    h = g[:3] - K @ g[3:]
    lam, Qe = np.linalg.eigh(S)
    if lam[2] <= 0 or lam[0] < 1e-14 * lam[2]:
        return u, t, False
    b = Qe.T @ h
    mu = 0.0
    if r > 0:
        q2 = 0.0
        for k in range(3):
            q2 += (b[k] / lam[k]) ** 2
        if q2 > r * r:
            for _ in range(60):
                q2 = 0.0
                dq = 0.0
                for k in range(3):
                    den = lam[k] + mu
                    q2 += (b[k] / den) ** 2
                    dq += b[k] * b[k] / den**3
                phi = 1.0 / np.sqrt(q2) - 1.0 / r
                if abs(phi) < 1e-13 / r:
                    break
                dphi = q2**-1.5 * dq
                mu_new = mu - phi / dphi
                mu = mu_new if mu_new > 0.5 * mu else 0.5 * mu
    bb = np.empty(3)
    for k in range(3):
        bb[k] = b[k] / (lam[k] + mu)
    u = -(Qe @ bb)
    t = -(Ctt_inv @ (g[3:] + Cut.T @ u))
    return u, t, True


@njit(cache=True, inline="always")
def _normal_equations(P, Nb, res, w, m0, m1, m2):
    """The weighted normal equations ``(C (6, 6), g (6,))`` of the linearised point-line
    residuals about the centroid ``m``: per point and basis vector ``n`` the row
    ``[2 n x (P - m), n]`` (the upper triangle summed, then mirrored). The sums are kept
    in scalars (each entry the same operations, in the same order, as the loop over a
    row array it replaced: ``C[a, b] += (w * row[a]) * row[b]``, ``g[a] += row[a] * (w *
    res)``)."""
    g0 = 0.0
    g1 = 0.0
    g2 = 0.0
    g3 = 0.0
    g4 = 0.0
    g5 = 0.0
    c00 = 0.0
    c01 = 0.0
    c02 = 0.0
    c03 = 0.0
    c04 = 0.0
    c05 = 0.0
    c11 = 0.0
    c12 = 0.0
    c13 = 0.0
    c14 = 0.0
    c15 = 0.0
    c22 = 0.0
    c23 = 0.0
    c24 = 0.0
    c25 = 0.0
    c33 = 0.0
    c34 = 0.0
    c35 = 0.0
    c44 = 0.0
    c45 = 0.0
    c55 = 0.0
    for i in range(P.shape[0]):
        wi = w[i]
        if wi == 0.0:
            continue
        px = P[i, 0] - m0
        py = P[i, 1] - m1
        pz = P[i, 2] - m2
        for k in range(2):
            nx = Nb[k, i, 0]
            ny = Nb[k, i, 1]
            nz = Nb[k, i, 2]
            r0 = 2.0 * (ny * pz - nz * py)
            r1 = 2.0 * (nz * px - nx * pz)
            r2 = 2.0 * (nx * py - ny * px)
            r3 = nx
            r4 = ny
            r5 = nz
            rk = wi * res[k, i]
            g0 += r0 * rk
            wa = wi * r0
            c00 += wa * r0
            c01 += wa * r1
            c02 += wa * r2
            c03 += wa * r3
            c04 += wa * r4
            c05 += wa * r5
            g1 += r1 * rk
            wa = wi * r1
            c11 += wa * r1
            c12 += wa * r2
            c13 += wa * r3
            c14 += wa * r4
            c15 += wa * r5
            g2 += r2 * rk
            wa = wi * r2
            c22 += wa * r2
            c23 += wa * r3
            c24 += wa * r4
            c25 += wa * r5
            g3 += r3 * rk
            wa = wi * r3
            c33 += wa * r3
            c34 += wa * r4
            c35 += wa * r5
            g4 += r4 * rk
            wa = wi * r4
            c44 += wa * r4
            c45 += wa * r5
            g5 += r5 * rk
            wa = wi * r5
            c55 += wa * r5
    C = np.empty((6, 6))
    g = np.empty(6)
    g[0] = g0
    C[0, 0] = c00
    C[0, 1] = C[1, 0] = c01
    C[0, 2] = C[2, 0] = c02
    C[0, 3] = C[3, 0] = c03
    C[0, 4] = C[4, 0] = c04
    C[0, 5] = C[5, 0] = c05
    g[1] = g1
    C[1, 1] = c11
    C[1, 2] = C[2, 1] = c12
    C[1, 3] = C[3, 1] = c13
    C[1, 4] = C[4, 1] = c14
    C[1, 5] = C[5, 1] = c15
    g[2] = g2
    C[2, 2] = c22
    C[2, 3] = C[3, 2] = c23
    C[2, 4] = C[4, 2] = c24
    C[2, 5] = C[5, 2] = c25
    g[3] = g3
    C[3, 3] = c33
    C[3, 4] = C[4, 3] = c34
    C[3, 5] = C[5, 3] = c35
    g[4] = g4
    C[4, 4] = c44
    C[4, 5] = C[5, 4] = c45
    g[5] = g5
    C[5, 5] = c55
    return C, g


@njit(cache=True)
def normal_equations_rows(P, Nb, res, w, m0, m1, m2):
    """:func:`_normal_equations` as it was written first, a row array per point and the
    sums in ``C`` itself: the twin the tests compare it with, bit for bit."""
    C = np.zeros((6, 6))
    g = np.zeros(6)
    row = np.empty(6)
    for i in range(P.shape[0]):
        wi = w[i]
        if wi == 0.0:
            continue
        px = P[i, 0] - m0
        py = P[i, 1] - m1
        pz = P[i, 2] - m2
        for k in range(2):
            nx = Nb[k, i, 0]
            ny = Nb[k, i, 1]
            nz = Nb[k, i, 2]
            row[0] = 2.0 * (ny * pz - nz * py)
            row[1] = 2.0 * (nz * px - nx * pz)
            row[2] = 2.0 * (nx * py - ny * px)
            row[3] = nx
            row[4] = ny
            row[5] = nz
            rk = wi * res[k, i]
            for aa in range(6):
                g[aa] += row[aa] * rk
                wa = wi * row[aa]
                for bb in range(aa, 6):
                    C[aa, bb] += wa * row[bb]
    for aa in range(6):
        for bb in range(aa):
            C[aa, bb] = C[bb, aa]
    return C, g


@njit(cache=True)
def normal_equations(P, Nb, res, w, m0, m1, m2):
    """:func:`_normal_equations`, callable from Python (the tests)."""
    return _normal_equations(P, Nb, res, w, m0, m1, m2)


@njit(cache=True)
def iterate(p, o, Nb, R0, t0, robust, r, max_iterations, tol, a, fixed_scale, scale,
            flat_cost):
    """Linearised iterations. Returns ``(R, t, iterations, status)``.

    Not robust ("linear"), it also stops, converged, when two iterations in a row changed
    the cost (sum of squared distances) by at most ``flat_cost`` of it (as the reference).
    """
    n = p.shape[0]
    R = R0.copy()
    tt = t0.copy()
    P = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            P[i, j] = R[j, 0] * p[i, 0] + R[j, 1] * p[i, 1] + R[j, 2] * p[i, 2] + tt[j]
    res = np.empty((2, n))
    dist = np.empty(n)
    w = np.ones(n)
    status = STATUS_MAX_ITER
    tol_t = tol * scale
    cost_prev = np.inf
    flat = 0
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 (returned)
        for i in range(n):
            dx = P[i, 0] - o[i, 0]
            dy = P[i, 1] - o[i, 1]
            dz = P[i, 2] - o[i, 2]
            r0 = Nb[0, i, 0] * dx + Nb[0, i, 1] * dy + Nb[0, i, 2] * dz
            r1 = Nb[1, i, 0] * dx + Nb[1, i, 1] * dy + Nb[1, i, 2] * dz
            res[0, i] = r0
            res[1, i] = r1
            dist[i] = np.sqrt(r0 * r0 + r1 * r1)
        if not robust:
            cost = 0.0
            for i in range(n):
                cost += dist[i] * dist[i]
            if abs(cost_prev - cost) <= flat_cost * cost_prev:
                flat += 1
            else:
                flat = 0
            cost_prev = cost
            if flat >= 2:
                status = STATUS_CONVERGED
                it -= 1
                break
        if robust:
            s = fixed_scale if fixed_scale > 0 else np.median(dist) / MAD_TO_SIGMA
            if s < 1e-12 * scale:
                s = 1e-12 * scale
            cnt = 0
            for i in range(n):
                z = dist[i] / s
                if z < a:
                    q = 1.0 - (z / a) ** 2
                    w[i] = q * q
                    cnt += 1
                else:
                    w[i] = 0.0
            if cnt < 3:
                status = STATUS_FEW_WEIGHTS
                break
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        ws = 0.0
        for i in range(n):
            m0 += w[i] * P[i, 0]
            m1 += w[i] * P[i, 1]
            m2 += w[i] * P[i, 2]
            ws += w[i]
        m0 /= ws
        m1 /= ws
        m2 /= ws
        C, g = _normal_equations(P, Nb, res, w, m0, m1, m2)
        u, t, ok = _trust_step(C, g, r)
        if not ok:
            status = STATUS_SINGULAR
            break
        Q = _cayley3(u)
        for i in range(n):
            px = P[i, 0] - m0
            py = P[i, 1] - m1
            pz = P[i, 2] - m2
            for j in range(3):
                P[i, j] = Q[j, 0] * px + Q[j, 1] * py + Q[j, 2] * pz
            P[i, 0] += m0 + t[0]
            P[i, 1] += m1 + t[1]
            P[i, 2] += m2 + t[2]
        m = np.array([m0, m1, m2])
        R = Q @ R
        tt = Q @ (tt - m) + m + t
        if u @ u < tol * tol and t @ t < tol_t * tol_t:
            status = STATUS_CONVERGED
            break
    return R, tt, it, status


@njit(cache=True)
def unit_cross(ax, ay, az, bx, by, bz):
    """The unit vector along ``a x b`` (scalars in, a 3-tuple out)."""
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    nc = np.sqrt(cx * cx + cy * cy + cz * cz)
    return cx / nc, cy / nc, cz / nc


@njit(cache=True)
def perp_basis(d):
    """Same as reglib.pose._perp_basis: (2, N, 3) unit vectors orthogonal to each row."""
    n = d.shape[0]
    out = np.empty((2, n, 3))
    for i in range(n):
        vx, vy, vz = d[i, 0], d[i, 1], d[i, 2]
        if abs(vx) > 0.9:  # a = e_y
            ax, ay, az = 0.0, 1.0, 0.0
        else:  # a = e_x
            ax, ay, az = 1.0, 0.0, 0.0
        n1x, n1y, n1z = unit_cross(ax, ay, az, vx, vy, vz)
        out[0, i, 0] = n1x
        out[0, i, 1] = n1y
        out[0, i, 2] = n1z
        out[1, i, 0] = vy * n1z - vz * n1y
        out[1, i, 1] = vz * n1x - vx * n1z
        out[1, i, 2] = vx * n1y - vy * n1x
    return out


@njit(cache=True)
def distances(p, o, d, R, t):
    """Point-line distances of the points moved by (R, t)."""
    n = p.shape[0]
    out = np.empty(n)
    for i in range(n):
        w = np.empty(3)
        for j in range(3):
            w[j] = R[j, 0] * p[i, 0] + R[j, 1] * p[i, 1] + R[j, 2] * p[i, 2] + t[j] - o[i, j]
        s = w[0] * d[i, 0] + w[1] * d[i, 1] + w[2] * d[i, 2]
        e0 = w[0] - s * d[i, 0]
        e1 = w[1] - s * d[i, 1]
        e2 = w[2] - s * d[i, 2]
        out[i] = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return out


IRLS_OK = 0
IRLS_FEW_WEIGHTS = 1
IRLS_UNDETERMINED = 2


@njit(cache=True)
def _rotvec_matrix(v):
    """The rotation matrix of a rotation vector, through the unit quaternion (the small-angle
    series below 1e-3 rad), as scipy's ``Rotation.from_rotvec(v).as_matrix()``."""
    th = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if th <= 1e-3:
        th2 = th * th
        s = 0.5 - th2 / 48.0 + th2 * th2 / 3840.0
    else:
        s = np.sin(th / 2.0) / th
    x, y, z, w = v[0] * s, v[1] * s, v[2] * s, np.cos(th / 2.0)
    Q = np.empty((3, 3))
    Q[0, 0] = w * w + x * x - y * y - z * z
    Q[0, 1] = 2.0 * (x * y - z * w)
    Q[0, 2] = 2.0 * (x * z + y * w)
    Q[1, 0] = 2.0 * (x * y + z * w)
    Q[1, 1] = w * w - x * x + y * y - z * z
    Q[1, 2] = 2.0 * (y * z - x * w)
    Q[2, 0] = 2.0 * (x * z - y * w)
    Q[2, 1] = 2.0 * (y * z + x * w)
    Q[2, 2] = w * w - x * x - y * y + z * z
    return Q


@njit(cache=True)
def _irls_residuals(x, o, d, nrm, use_normals, r, dist):
    """Residuals into ``r`` (N, 3) (the scalar in column 0 with normals) and ``dist``."""
    for i in range(x.shape[0]):
        vx, vy, vz = x[i, 0] - o[i, 0], x[i, 1] - o[i, 1], x[i, 2] - o[i, 2]
        if use_normals:
            s = nrm[i, 0] * vx + nrm[i, 1] * vy + nrm[i, 2] * vz
            r[i, 0] = s
            dist[i] = abs(s)
        else:
            t = d[i, 0] * vx + d[i, 1] * vy + d[i, 2] * vz
            r[i, 0], r[i, 1], r[i, 2] = vx - t * d[i, 0], vy - t * d[i, 1], vz - t * d[i, 2]
            dist[i] = np.sqrt(r[i, 0] ** 2 + r[i, 1] ** 2 + r[i, 2] ** 2)


@njit(cache=True)
def _irls_weights(dist, robust, tukey_a, floor, w):
    if not robust:
        w[:] = 1.0
        return
    s = max(np.median(dist) / MAD_TO_SIGMA, floor)
    for i in range(dist.shape[0]):
        z = dist[i] / s
        if abs(z) < tukey_a:
            u = 1.0 - (z / tukey_a) ** 2
            w[i] = u * u
        else:
            w[i] = 0.0


@njit(cache=True)
def _normals_system6(x, m, nrm, w, r, robust, A, b):
    """:func:`irls`'s normal equations with normals and six unknowns, into ``A`` (6, 6)
    and ``b`` (6,): per point the Jacobian row ``J = [y x n, n]`` (``y = x - m``),
    ``A[p, q] += J[p] * w * J[q]`` and ``b[p] -= J[p] * w * r``, each entry summed over the
    points in order as the generic loop of :func:`irls` does (the same floating-point
    operations), in scalars. Unweighted (``robust`` False: every weight is 1, so
    ``J[p] * w * J[q]`` equals ``J[q] * w * J[p]`` exactly), the lower triangle is the
    upper one's mirror."""
    m0, m1, m2 = m[0], m[1], m[2]
    b0 = 0.0
    a00 = 0.0
    a01 = 0.0
    a02 = 0.0
    a03 = 0.0
    a04 = 0.0
    a05 = 0.0
    b1 = 0.0
    a10 = 0.0
    a11 = 0.0
    a12 = 0.0
    a13 = 0.0
    a14 = 0.0
    a15 = 0.0
    b2 = 0.0
    a20 = 0.0
    a21 = 0.0
    a22 = 0.0
    a23 = 0.0
    a24 = 0.0
    a25 = 0.0
    b3 = 0.0
    a30 = 0.0
    a31 = 0.0
    a32 = 0.0
    a33 = 0.0
    a34 = 0.0
    a35 = 0.0
    b4 = 0.0
    a40 = 0.0
    a41 = 0.0
    a42 = 0.0
    a43 = 0.0
    a44 = 0.0
    a45 = 0.0
    b5 = 0.0
    a50 = 0.0
    a51 = 0.0
    a52 = 0.0
    a53 = 0.0
    a54 = 0.0
    a55 = 0.0
    for i in range(x.shape[0]):
        y0, y1, y2 = x[i, 0] - m0, x[i, 1] - m1, x[i, 2] - m2
        j3, j4, j5 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        j0 = y1 * j5 - y2 * j4
        j1 = y2 * j3 - y0 * j5
        j2 = y0 * j4 - y1 * j3
        wi = w[i]
        ri = r[i, 0]
        w0 = j0 * wi
        w1 = j1 * wi
        w2 = j2 * wi
        w3 = j3 * wi
        w4 = j4 * wi
        w5 = j5 * wi
        b0 -= w0 * ri
        b1 -= w1 * ri
        b2 -= w2 * ri
        b3 -= w3 * ri
        b4 -= w4 * ri
        b5 -= w5 * ri
        # the upper triangle with the diagonal in every case; the lower one only when the
        # weights differ (unweighted, it is the upper one's mirror, set below)
        a00 += w0 * j0
        a01 += w0 * j1
        a02 += w0 * j2
        a03 += w0 * j3
        a04 += w0 * j4
        a05 += w0 * j5
        a11 += w1 * j1
        a12 += w1 * j2
        a13 += w1 * j3
        a14 += w1 * j4
        a15 += w1 * j5
        a22 += w2 * j2
        a23 += w2 * j3
        a24 += w2 * j4
        a25 += w2 * j5
        a33 += w3 * j3
        a34 += w3 * j4
        a35 += w3 * j5
        a44 += w4 * j4
        a45 += w4 * j5
        a55 += w5 * j5
        if robust:
            a10 += w1 * j0
            a20 += w2 * j0
            a21 += w2 * j1
            a30 += w3 * j0
            a31 += w3 * j1
            a32 += w3 * j2
            a40 += w4 * j0
            a41 += w4 * j1
            a42 += w4 * j2
            a43 += w4 * j3
            a50 += w5 * j0
            a51 += w5 * j1
            a52 += w5 * j2
            a53 += w5 * j3
            a54 += w5 * j4
    b[0] = b0
    A[0, 0] = a00
    A[0, 1] = a01
    A[0, 2] = a02
    A[0, 3] = a03
    A[0, 4] = a04
    A[0, 5] = a05
    b[1] = b1
    A[1, 0] = a10 if robust else a01
    A[1, 1] = a11
    A[1, 2] = a12
    A[1, 3] = a13
    A[1, 4] = a14
    A[1, 5] = a15
    b[2] = b2
    A[2, 0] = a20 if robust else a02
    A[2, 1] = a21 if robust else a12
    A[2, 2] = a22
    A[2, 3] = a23
    A[2, 4] = a24
    A[2, 5] = a25
    b[3] = b3
    A[3, 0] = a30 if robust else a03
    A[3, 1] = a31 if robust else a13
    A[3, 2] = a32 if robust else a23
    A[3, 3] = a33
    A[3, 4] = a34
    A[3, 5] = a35
    b[4] = b4
    A[4, 0] = a40 if robust else a04
    A[4, 1] = a41 if robust else a14
    A[4, 2] = a42 if robust else a24
    A[4, 3] = a43 if robust else a34
    A[4, 4] = a44
    A[4, 5] = a45
    b[5] = b5
    A[5, 0] = a50 if robust else a05
    A[5, 1] = a51 if robust else a15
    A[5, 2] = a52 if robust else a25
    A[5, 3] = a53 if robust else a35
    A[5, 4] = a54 if robust else a45
    A[5, 5] = a55


@njit(cache=True)
def irls(x0, o, d, nrm, use_normals, fixed, use_fixed, robust, tukey_a, max_iterations, tol,
         need, generic=False):
    """:func:`reglib.pose._solve_irls` compiled (that numpy function is the reference,
    compared in ``tests/reglib/test_pose.py``). ``nrm`` is ignored unless ``use_normals``,
    ``fixed`` unless ``use_fixed``. Returns ``(R, t, dist, w, status)`` with status
    :data:`IRLS_OK`, :data:`IRLS_FEW_WEIGHTS` or :data:`IRLS_UNDETERMINED`. ``generic``:
    the normal equations by the general loop even where :func:`_normals_system6` serves
    (the same floating-point operations; the twin the tests compare bit for bit)."""
    n = x0.shape[0]
    x = x0.copy()
    dof = 3 if use_fixed else 6
    w = np.ones(n)
    scale = _kept_radius(x, w)
    R_tot = np.eye(3)
    t_tot = np.zeros(3)
    r = np.zeros((n, 3))
    dist = np.empty(n)
    m = np.empty(3)
    J = np.zeros((3, 6))
    for _ in range(max_iterations):
        _irls_residuals(x, o, d, nrm, use_normals, r, dist)
        _irls_weights(dist, robust, tukey_a, 1e-12 * scale, w)
        if robust:
            kept = 0
            for i in range(n):
                if w[i] != 0.0:
                    kept += 1
            if kept < need:
                return R_tot, t_tot, dist, w, IRLS_FEW_WEIGHTS
        if use_fixed:
            m[:] = fixed
        else:
            sw = 0.0
            m[:] = 0.0
            for i in range(n):
                sw += w[i]
                for k in range(3):
                    m[k] += w[i] * x[i, k]
            m /= sw
        A = np.zeros((dof, dof))
        b = np.zeros(dof)
        rows = 1 if use_normals else 3
        fast = use_normals and dof == 6 and not generic
        if fast:
            # the same sums, in the same order, with the loop bounds known to the compiler
            # (the generic loop below is the reference, compared in tests)
            _normals_system6(x, m, nrm, w, r, robust, A, b)
        for i in range(0 if fast else n):
            y0, y1, y2 = x[i, 0] - m[0], x[i, 1] - m[1], x[i, 2] - m[2]
            if use_normals:
                n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
                J[0, 0] = y1 * n2 - y2 * n1       # cross(y, n)
                J[0, 1] = y2 * n0 - y0 * n2
                J[0, 2] = y0 * n1 - y1 * n0
                J[0, 3], J[0, 4], J[0, 5] = n0, n1, n2
            else:
                # M = I - d d^T; columns: -M skew(y), then M
                d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
                for a in range(3):
                    Ma0 = (1.0 if a == 0 else 0.0) - d[i, a] * d0
                    Ma1 = (1.0 if a == 1 else 0.0) - d[i, a] * d1
                    Ma2 = (1.0 if a == 2 else 0.0) - d[i, a] * d2
                    # (M skew(y))[a, :] = (M[a,1] y2 - M[a,2] y1, M[a,2] y0 - M[a,0] y2,
                    #                      M[a,0] y1 - M[a,1] y0)
                    J[a, 0] = -(Ma1 * y2 - Ma2 * y1)
                    J[a, 1] = -(Ma2 * y0 - Ma0 * y2)
                    J[a, 2] = -(Ma0 * y1 - Ma1 * y0)
                    J[a, 3], J[a, 4], J[a, 5] = Ma0, Ma1, Ma2
            wi = w[i]
            for a in range(rows):
                for p in range(dof):
                    b[p] -= J[a, p] * wi * r[i, a]
                    for q in range(dof):
                        A[p, q] += J[a, p] * wi * J[a, q]
        sv = np.linalg.svd(A)[1]
        if sv[dof - 1] <= 1e-12 * max(sv[0], 1e-300):
            return R_tot, t_tot, dist, w, IRLS_UNDETERMINED
        delta = np.linalg.solve(A, b)
        Q = _rotvec_matrix(delta[:3])
        tau = np.zeros(3)
        if dof == 6:
            tau[:] = delta[3:]
        for i in range(n):
            y0, y1, y2 = x[i, 0] - m[0], x[i, 1] - m[1], x[i, 2] - m[2]
            for k in range(3):
                x[i, k] = Q[k, 0] * y0 + Q[k, 1] * y1 + Q[k, 2] * y2 + m[k] + tau[k]
        R_tot = Q @ R_tot
        t_tot = Q @ (t_tot - m) + m + tau
        if (delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2 < tol * tol
                and tau[0] ** 2 + tau[1] ** 2 + tau[2] ** 2 < (tol * scale) ** 2):
            break
    _irls_residuals(x, o, d, nrm, use_normals, r, dist)
    _irls_weights(dist, robust, tukey_a, 1e-12 * scale, w)
    return R_tot, t_tot, dist, w, IRLS_OK


@njit(cache=True, inline="always")
def _kept_radius(P, weights):
    """RMS distance of the points with ``weights > 0`` from their (plain) centroid, 1 when
    it is 0 or no point is kept (:func:`reglib.pose._scale_of`)."""
    k = 0
    c = np.zeros(3)
    for i in range(P.shape[0]):
        if weights[i] > 0.0:
            k += 1
            for j in range(3):
                c[j] += P[i, j]
    if k == 0:
        return 1.0
    for j in range(3):
        c[j] /= k
    ss = 0.0
    for i in range(P.shape[0]):
        if weights[i] > 0.0:
            for j in range(3):
                ss += (P[i, j] - c[j]) ** 2
    size = np.sqrt(ss / k)
    return size if size > 0.0 else 1.0


@njit(cache=True, inline="always")
def _kept_centroid(P, weights):
    """The ``weights``-weighted centroid of the points with ``weights > 0`` and the weights'
    sum: ``((3,), float)``, the centroid zero when the sum is 0."""
    ws = 0.0
    m = np.zeros(3)
    for i in range(P.shape[0]):
        if weights[i] > 0.0:
            ws += weights[i]
            for j in range(3):
                m[j] += weights[i] * P[i, j]
    if ws > 0.0:
        for j in range(3):
            m[j] /= ws
    return m, ws


@njit(cache=True)
def rank_gram(P, d, weights):
    """``J^T J`` (6, 6) of the rank test of :func:`reglib.pose._undetermined` over the pairs
    with ``weights > 0``: the weighted Jacobian of the point-line residuals at the points
    ``P`` (N, 3) on the lines of directions ``d`` (N, 3), with respect to a rotation about
    the kept points' weighted centroid (divided by their RMS radius about their plain
    centroid, 1 when 0) and a translation. ``reglib.pose._rank_gram`` is the reference,
    compared in tests."""
    n = P.shape[0]
    m, ws = _kept_centroid(P, weights)
    if ws == 0.0:
        return np.zeros((6, 6))
    size = _kept_radius(P, weights)
    # the normal equations' rows are [2 n x (Q - m), n]: with Q = m + (P - m) / (2 size)
    # they are the rank test's [n x (P - m) / size, n]
    Q = np.empty((n, 3))
    for i in range(n):
        for j in range(3):
            Q[i, j] = m[j] + (P[i, j] - m[j]) / (2.0 * size)
    G, _ = _normal_equations(Q, perp_basis(d), np.zeros((2, n)), weights, m[0], m[1], m[2])
    return G


@njit(cache=True)
def max_pair_leverage(P, d, weights, gram):
    """The largest leverage of one pair in the rank test of :func:`reglib.pose._undetermined`
    (``single_pairs``): over the pairs with ``weights > 0``, the largest eigenvalue of each
    pair's 2x2 block of ``J C^-1 J^T``, ``J`` the rank test's weighted Jacobian (the rows of
    :func:`rank_gram`, unscaled) and ``C = gram`` its Gram matrix (:func:`rank_gram`'s).
    Per pair without the (2K, 6) Jacobian the numpy reference builds
    (``reglib.pose._max_pair_leverage``, compared in tests); 0 when no pair is kept."""
    n = P.shape[0]
    m, ws = _kept_centroid(P, weights)
    if ws == 0.0:
        return 0.0
    size = _kept_radius(P, weights)
    Ci = np.linalg.inv(gram)
    Nb = perp_basis(d)
    J = np.empty((2, 6))
    G = np.empty((2, 6))
    best = 0.0
    for i in range(n):
        if not weights[i] > 0.0:
            continue
        sw = np.sqrt(weights[i])
        y0, y1, y2 = P[i, 0] - m[0], P[i, 1] - m[1], P[i, 2] - m[2]
        for r in range(2):
            n0, n1, n2 = Nb[r, i, 0], Nb[r, i, 1], Nb[r, i, 2]
            J[r, 0] = (n1 * y2 - n2 * y1) / size * sw
            J[r, 1] = (n2 * y0 - n0 * y2) / size * sw
            J[r, 2] = (n0 * y1 - n1 * y0) / size * sw
            J[r, 3] = n0 * sw
            J[r, 4] = n1 * sw
            J[r, 5] = n2 * sw
        for r in range(2):
            for a in range(6):
                s = 0.0
                for b in range(6):
                    s += Ci[a, b] * J[r, b]
                G[r, a] = s
        b00 = b01 = b10 = b11 = 0.0
        for a in range(6):
            b00 += J[0, a] * G[0, a]
            b01 += J[0, a] * G[1, a]
            b10 += J[1, a] * G[0, a]
            b11 += J[1, a] * G[1, a]
        tr = b00 + b11
        det = b00 * b11 - b01 * b10
        lev = 0.5 * tr + np.sqrt(max(0.25 * tr * tr - det, 0.0))
        if lev > best:
            best = lev
    return best
