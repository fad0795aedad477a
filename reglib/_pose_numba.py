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
    row = np.empty(6)
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
        C = np.zeros((6, 6))
        g = np.zeros(6)
        for i in range(n):
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
