"""Compiled (numba) Step A: the closest segment of every contour to every line, pruned.

The kernel of ``closest_points(..., method="compiled")`` (:mod:`reglib.closest`). Per line,
the contours' blocks of consecutive segments are visited in order; a block's capsule (axis
from its first to its last vertex, radius ``eps``, the largest distance of its vertices
from the axis) gives the lower bound ``d(line, axis) - eps`` of its segments' distances,
and a block whose bound exceeds the contour's best distance so far (or, with ``within``,
the line's threshold ``max(within, nearest so far)``) is skipped; the other blocks'
segments are measured exactly. The same bounds as the numpy ``"blocks"`` method, in a loop
per line without temporaries. ``reference`` (the brute force of :mod:`reglib.closest`) is
compared with it on random cases in ``tests/reglib/test_closest.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from reglib._apparent_numba import OK, contour_chains
from reglib.geometry import line_segment_across

#: reglib.geometry's scalar line-segment geometry, compiled
_across = njit(cache=True, inline="always")(line_segment_across)


@njit(cache=True, inline="always")
def _line_segment_distance(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz):
    """reglib.geometry.line_segment_distance, compiled."""
    s, px, py, pz, qx, qy, qz = _across(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz)
    rx, ry, rz = px + s * qx, py + s * qy, pz + s * qz
    return np.sqrt(rx * rx + ry * ry + rz * rz)


@njit(cache=True, inline="always")
def _closest_row(ox, oy, oz, dx, dy, dz, starts, ends, block_a, block_b, block_eps,
                 block_seg0, contour_block0, sb_a, sb_b, sb_eps, contour_sb0, ratio, within,
                 sphere_c, sphere_r, warm, dist_row, seg_row, near0, measured):
    """:func:`closest_segments` for one line, into ``dist_row`` and ``seg_row`` (C,).
    Returns how many contours were measured (not skipped by their sphere), their indices in
    increasing order in ``measured[:count]``: the others hold ``inf`` and -1.

    ``warm`` (C,): per contour a segment measured first (-1: none), e.g. the previous
    line's; its distance bounds the contour's blocks from the start. Ties go to the lowest
    segment index, as without it, so a warm start changes nothing but the work: a block
    holding the contour's nearest segment is never skipped (its lower bound is at most that
    distance), and a contour left with an upper bound is one beyond the line's threshold,
    which the caller drops either way. The blocks are grouped ``ratio`` at a time under
    superblocks (``sb_*``, :func:`block_capsules` with ``ratio`` times the block size; their
    first superblock per contour ``contour_sb0``), tested first with the same bound.

    ``near0`` (-1: none): a contour whose warm segment is measured before the loop; its
    distance bounds the line's nearest distance from above from the first contour on, so
    that with ``within`` a far contour is skipped by its sphere even before the nearest
    one is reached. A larger threshold than the line's own only measures more, so the
    result is the same."""
    nc = contour_block0.shape[0] - 1
    count = 0
    nearest = np.inf
    if within >= 0.0 and near0 >= 0 and warm[near0] >= 0:
        w = warm[near0]
        nearest = _line_segment_distance(
            ox, oy, oz, dx, dy, dz, starts[w, 0], starts[w, 1], starts[w, 2],
            ends[w, 0], ends[w, 1], ends[w, 2])
    for c in range(nc):
        best = np.inf
        best_j = -1
        if within >= 0.0:
            t = within if within > nearest else nearest
            wx = sphere_c[c, 0] - ox
            wy = sphere_c[c, 1] - oy
            wz = sphere_c[c, 2] - oz
            wd = wx * dx + wy * dy + wz * dz
            px, py, pz = wx - wd * dx, wy - wd * dy, wz - wd * dz
            bound = t + 1e-7 * (1.0 + t) + sphere_r[c]
            if px * px + py * py + pz * pz > bound * bound:
                dist_row[c] = np.inf             # not computed
                seg_row[c] = -1
                continue
        w = warm[c]
        if w >= 0:
            best = _line_segment_distance(
                ox, oy, oz, dx, dy, dz, starts[w, 0], starts[w, 1], starts[w, 2],
                ends[w, 0], ends[w, 1], ends[w, 2])
            best_j = w
        t = within if within > nearest else nearest
        for m in range(contour_sb0[c], contour_sb0[c + 1]):
            limit = best
            if within >= 0.0 and t < limit:
                limit = t
            if _beyond(ox, oy, oz, dx, dy, dz, sb_a[m, 0], sb_a[m, 1], sb_a[m, 2],
                       sb_b[m, 0], sb_b[m, 1], sb_b[m, 2], sb_eps[m], limit):
                continue
            k0 = contour_block0[c] + (m - contour_sb0[c]) * ratio
            k1 = min(k0 + ratio, contour_block0[c + 1])
            for k in range(k0, k1):
                limit = best
                if within >= 0.0 and t < limit:
                    limit = t
                if _beyond(ox, oy, oz, dx, dy, dz, block_a[k, 0], block_a[k, 1],
                           block_a[k, 2], block_b[k, 0], block_b[k, 1], block_b[k, 2],
                           block_eps[k], limit):
                    continue
                for j in range(block_seg0[k], block_seg0[k + 1]):
                    r = _line_segment_distance(
                        ox, oy, oz, dx, dy, dz, starts[j, 0], starts[j, 1], starts[j, 2],
                        ends[j, 0], ends[j, 1], ends[j, 2])
                    if r < best or (r == best and j < best_j):
                        best = r
                        best_j = j
        dist_row[c] = best
        seg_row[c] = best_j
        measured[count] = c
        count += 1
        if best < nearest:
            nearest = best
    return count


@njit(cache=True, inline="always")
def _first_min(x):
    """The index of the first smallest finite value of ``x`` (-1: none)."""
    k = -1
    for c in range(x.shape[0]):
        if x[c] < np.inf and (k < 0 or x[c] < x[k]):
            k = c
    return k


@njit(cache=True, inline="always")
def _beyond(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz, eps, limit):
    """Whether the capsule of axis ``[a, b]`` and radius ``eps`` lies farther than
    ``limit`` (plus a relative 1e-7) from the line: ``distance - eps > limit``, compared in
    squares (no square root; both sides are >= 0)."""
    s, px, py, pz, qx, qy, qz = _across(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz)
    rx, ry, rz = px + s * qx, py + s * qy, pz + s * qz
    bound = limit + 1e-7 * (1.0 + limit) + eps
    return rx * rx + ry * ry + rz * rz > bound * bound


@njit(cache=True)
def closest_segments(o, d, starts, ends, block_a, block_b, block_eps, block_seg0,
                     contour_block0, sb_a, sb_b, sb_eps, contour_sb0, ratio, within, sphere_c,
                     sphere_r, warm_start=True):
    """Per (line, contour): the distance and index of the closest segment.

    Parameters
    ----------
    o, d : (N, 3) lines (unit d).
    starts, ends : (S, 3) segments.
    block_a, block_b, block_eps : (K, 3), (K, 3), (K,) the blocks' capsule axes and radii.
    block_seg0 : (K + 1,) the blocks' first segments (block k owns ``block_seg0[k]`` to
        ``block_seg0[k + 1]``).
    contour_block0 : (C + 1,) the contours' first blocks.
    sb_a, sb_b, sb_eps, contour_sb0, ratio : superblocks of ``ratio`` blocks each, tested
        before their blocks (:func:`block_capsules` with ``ratio`` times the block size).
    within : threshold of the line (mm), or a negative number for none.
    sphere_c, sphere_r : (C, 3), (C,) a sphere around each contour (:func:`contour_spheres`):
        with ``within``, a contour whose sphere lies beyond the line's threshold is skipped
        in one test instead of one per block.
    warm_start : measure first, per contour, the segment the previous line found (lines
        that follow each other along a contour meet it at nearby segments): the same result,
        less work (:func:`_closest_row`).

    Returns ``dist (N, C)`` (inf where not computed) and ``seg (N, C)`` (-1 there). With
    ``within >= 0`` the values are exact for every contour whose distance is at most
    ``max(within, nearest)``; others may be inf or an upper bound (the caller masks them).
    """
    n = o.shape[0]
    nc = contour_block0.shape[0] - 1
    dist = np.full((n, nc), np.inf)
    seg = np.full((n, nc), -1, dtype=np.int64)
    warm = np.full(nc, -1, dtype=np.int64)
    measured = np.empty(nc, dtype=np.int64)
    near = -1
    for i in range(n):
        _closest_row(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], starts, ends,
                     block_a, block_b, block_eps, block_seg0, contour_block0, sb_a, sb_b,
                     sb_eps, contour_sb0, ratio, within, sphere_c, sphere_r, warm, dist[i],
                     seg[i], near if warm_start else -1, measured)
        if warm_start:
            warm[:] = seg[i]
            near = _first_min(dist[i])
    return dist, seg


@njit(cache=True, inline="always")
def _pair(ox, oy, oz, dx, dy, dz, starts, ends, j):
    """The exact closest points of the line and segment ``j``: ``(dist, p0, p1, p2, q0, q1,
    q2)``, the arithmetic of ``reglib.closest._exact``."""
    ax, ay, az = starts[j, 0], starts[j, 1], starts[j, 2]
    bx, by, bz = ends[j, 0], ends[j, 1], ends[j, 2]
    s = _across(ox, oy, oz, dx, dy, dz, ax, ay, az, bx, by, bz)[0]
    p0, p1, p2 = ax + s * (bx - ax), ay + s * (by - ay), az + s * (bz - az)
    t = (p0 - ox) * dx + (p1 - oy) * dy + (p2 - oz) * dz
    q0, q1, q2 = ox + t * dx, oy + t * dy, oz + t * dz
    r0, r1, r2 = p0 - q0, p1 - q1, p2 - q2
    return np.sqrt(r0 ** 2 + r1 ** 2 + r2 ** 2), p0, p1, p2, q0, q1, q2


@njit(cache=True, inline="always")
def _tangent(unit, starts, ends, seg_contour, offsets, closed, g, p0, p1, p2):
    """The oriented contour direction at the point ``(p0, p1, p2)`` of segment ``g >= 0``
    (:meth:`reglib.closest.ContourSet.tangents`, one entry)."""
    c = seg_contour[g]
    lo, hi = offsets[c], offsets[c + 1] - 1
    prv = g - 1 if g > lo else (hi if closed[c] else -1)
    nxt = g + 1 if g < hi else (lo if closed[c] else -1)
    ds = (p0 - starts[g, 0]) ** 2 + (p1 - starts[g, 1]) ** 2 + (p2 - starts[g, 2]) ** 2
    de = (p0 - ends[g, 0]) ** 2 + (p1 - ends[g, 1]) ** 2 + (p2 - ends[g, 2]) ** 2
    at_start = np.sqrt(ds) <= 1e-9
    at_end = np.sqrt(de) <= 1e-9
    tx, ty, tz = unit[g, 0], unit[g, 1], unit[g, 2]
    if at_start and prv >= 0:
        tx += unit[prv, 0]
        ty += unit[prv, 1]
        tz += unit[prv, 2]
    elif at_end and not at_start and nxt >= 0:
        tx += unit[nxt, 0]
        ty += unit[nxt, 1]
        tz += unit[nxt, 2]
    tn = np.sqrt(tx * tx + ty * ty + tz * tz)
    if tn > 1e-12:
        return tx / tn, ty / tn, tz / tn
    return unit[g, 0], unit[g, 1], unit[g, 2]


@njit(cache=True)
def tangents(unit, starts, ends, seg_contour, offsets, closed, seg, p):
    """:meth:`reglib.closest.ContourSet.tangents` per entry, compiled (the numpy method is
    the reference, compared in tests): ``unit`` (S, 3) segment directions, ``seg`` (K,)
    segment indices (< 0: NaN), ``p`` (K, 3) points on them. Returns (K, 3)."""
    k_n = seg.shape[0]
    out = np.empty((k_n, 3))
    for k in range(k_n):
        g = seg[k]
        if g < 0:
            out[k, 0] = out[k, 1] = out[k, 2] = np.nan
            continue
        out[k, 0], out[k, 1], out[k, 2] = _tangent(unit, starts, ends, seg_contour, offsets,
                                                   closed, g, p[k, 0], p[k, 1], p[k, 2])
    return out


@njit(cache=True)
def match_lines(o, d, starts, ends, unit, seg_contour, offsets, closed, block_a, block_b,
                block_eps, block_seg0, contour_block0, sb_a, sb_b, sb_eps, contour_sb0, ratio,
                within, sphere_c, sphere_r, external, max_stab):
    """Steps A and B of one view in one pass per line, compiled: :func:`closest_segments`
    (warm-started), :func:`exact_pairs`, then :func:`reglib.closest.select_contours` (an
    external line takes the farthest contour it stabs within ``max_stab`` mm, else and for
    the other lines the closest) and the tangent there. The numpy chain of those steps is
    the reference, compared in tests.

    Returns ``sel (N,)`` contour index, ``seg (N,)`` segment (-1: none), ``p (N, 3)`` the
    selected closest point (NaN: none) and ``tangent (N, 3)`` (NaN: none)."""
    n = o.shape[0]
    nc = contour_block0.shape[0] - 1
    sel = np.zeros(n, dtype=np.int64)
    seg_out = np.full(n, -1, dtype=np.int64)
    p_out = np.full((n, 3), np.nan)
    t_out = np.full((n, 3), np.nan)
    dist_row = np.empty(nc)
    seg_row = np.full(nc, -1, dtype=np.int64)
    warm = np.full(nc, -1, dtype=np.int64)
    exd = np.empty(nc)
    pr = np.empty((nc, 3))
    qr = np.empty((nc, 3))
    # the contours measured for this line and the last (the others' rows are inf / -1,
    # and only the last line's measured contours hold a warm segment): the steps after
    # Step A visit these alone, in increasing order (a line meets 1-2 of the 10-40
    # contours; the loops over all of them were a third of the time)
    measured = np.empty(nc, dtype=np.int64)
    last = np.empty(nc, dtype=np.int64)
    n_last = 0
    near = -1
    for i in range(n):
        ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        count = _closest_row(ox, oy, oz, dx, dy, dz, starts, ends, block_a, block_b,
                             block_eps, block_seg0, contour_block0, sb_a, sb_b, sb_eps,
                             contour_sb0, ratio, within, sphere_c, sphere_r, warm, dist_row,
                             seg_row, near, measured)
        nearest = np.inf
        near = -1                            # the next line's first guess of its nearest
        for k in range(count):
            c = measured[k]
            if dist_row[c] < np.inf and (near < 0 or dist_row[c] < dist_row[near]):
                near = c
            nearest = min(nearest, dist_row[c])
        lim = np.inf
        if within >= 0.0:
            thr = max(within, nearest)
            lim = thr + 1e-7 * (1.0 + thr)
        for k in range(n_last):
            warm[last[k]] = -1
        chosen = -1                                  # the closest: first minimum
        for k in range(count):
            c = measured[k]
            last[k] = c
            j = seg_row[c]
            warm[c] = j
            if j < 0 or dist_row[c] > lim:
                exd[c] = np.inf
                seg_row[c] = -1
                continue
            exd[c], p0, p1, p2, q0, q1, q2 = _pair(ox, oy, oz, dx, dy, dz, starts, ends, j)
            pr[c, 0], pr[c, 1], pr[c, 2] = p0, p1, p2
            qr[c, 0], qr[c, 1], qr[c, 2] = q0, q1, q2
            if chosen < 0 or exd[c] < exd[chosen]:
                chosen = c
        n_last = count
        if chosen < 0:
            chosen = 0                               # no contour: row 0, as every row inf
        if external[i]:
            far = -1
            for k in range(count):
                c = measured[k]
                g = seg_row[c]
                if g < 0 or not exd[c] <= max_stab:
                    continue
                ex, ey, ez = _tangent(unit, starts, ends, seg_contour, offsets, closed, g,
                                      pr[c, 0], pr[c, 1], pr[c, 2])
                cx, cy, cz = ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx
                det = ((qr[c, 0] - pr[c, 0]) * cx + (qr[c, 1] - pr[c, 1]) * cy
                       + (qr[c, 2] - pr[c, 2]) * cz)
                if det > 0.0 and (far < 0 or exd[c] > exd[far]):
                    far = c
            if far >= 0:
                chosen = far
        sel[i] = chosen
        g = seg_row[chosen]           # -1 for a contour not measured or dropped
        if g >= 0:
            seg_out[i] = g
            p_out[i, 0], p_out[i, 1], p_out[i, 2] = pr[chosen, 0], pr[chosen, 1], pr[chosen, 2]
            t_out[i, 0], t_out[i, 1], t_out[i, 2] = _tangent(
                unit, starts, ends, seg_contour, offsets, closed, g, pr[chosen, 0],
                pr[chosen, 1], pr[chosen, 2])
    return sel, seg_out, p_out, t_out


@njit(cache=True)
def block_capsules(path, offsets, size):
    """The capsules of ``closest_segments``: each contour's segments cut into blocks of
    ``size``, per block the axis ``a -> b`` (its first and last vertex), the radius ``eps``
    (the largest distance of its vertices from the axis), its first global segment
    ``seg0`` (plus the segment count at the end) and each contour's first block ``cb0``
    (plus the block count). The numpy ``reglib.closest._block_capsules`` is the reference,
    compared in tests."""
    nc = offsets.shape[0] - 1
    nb = 0
    for c in range(nc):
        nb += (offsets[c + 1] - offsets[c] + size - 1) // size
    a = np.empty((nb, 3))
    b = np.empty((nb, 3))
    eps = np.empty(nb)
    seg0 = np.empty(nb + 1, dtype=np.int64)
    cb0 = np.empty(nc + 1, dtype=np.int64)
    k = 0
    for c in range(nc):
        cb0[c] = k
        base = offsets[c] + c                     # the contour's first path row
        nseg = offsets[c + 1] - offsets[c]
        for j0 in range(0, nseg, size):
            j1 = min(j0 + size, nseg)
            lo, hi = base + j0, base + j1
            ex = path[hi, 0] - path[lo, 0]
            ey = path[hi, 1] - path[lo, 1]
            ez = path[hi, 2] - path[lo, 2]
            ee = ex * ex + ey * ey + ez * ez
            m = 0.0
            for r in range(lo, hi + 1):
                wx = path[r, 0] - path[lo, 0]
                wy = path[r, 1] - path[lo, 1]
                wz = path[r, 2] - path[lo, 2]
                s = (wx * ex + wy * ey + wz * ez) / ee if ee > 0.0 else 0.0
                s = min(max(s, 0.0), 1.0)
                dx, dy, dz = wx - s * ex, wy - s * ey, wz - s * ez
                dist = np.sqrt(dx * dx + dy * dy + dz * dz)
                if dist > m:
                    m = dist
            for j in range(3):
                a[k, j] = path[lo, j]
                b[k, j] = path[hi, j]
            eps[k] = m
            seg0[k] = offsets[c] + j0
            k += 1
    seg0[nb] = offsets[nc]
    cb0[nc] = nb
    return a, b, eps, seg0, cb0


@njit(cache=True)
def contour_spheres(path, offsets):
    """A sphere around each contour: the centre of its vertices' bounding box and the
    largest distance of a vertex from it, ``(C, 3), (C,)``."""
    nc = offsets.shape[0] - 1
    c = np.empty((nc, 3))
    r = np.empty(nc)
    for k in range(nc):
        lo, hi = offsets[k] + k, offsets[k + 1] + k          # the contour's path rows
        for j in range(3):
            mn, mx = path[lo, j], path[lo, j]
            for i in range(lo, hi + 1):
                mn = min(mn, path[i, j])
                mx = max(mx, path[i, j])
            c[k, j] = 0.5 * (mn + mx)
        m = 0.0
        for i in range(lo, hi + 1):
            q = ((path[i, 0] - c[k, 0]) ** 2 + (path[i, 1] - c[k, 1]) ** 2
                 + (path[i, 2] - c[k, 2]) ** 2)
            if q > m:
                m = q
        r[k] = np.sqrt(m) * (1.0 + 1e-12) + 1e-12
    return c, r


@njit(cache=True)
def exact_pairs(o, d, starts, ends, dist_in, seg, within):
    """For each (line, contour) with a segment (``seg >= 0``): the exact distance and the
    closest points ``p`` (on the segment) and ``q`` (on the line), the arithmetic of
    ``reglib.closest._exact`` (the reference, compared in tests) per pair; with ``within >=
    0``, pairs whose ``dist_in`` lies beyond the line's threshold ``max(within, nearest)``
    are dropped first (``seg`` set to -1 in place), as the numpy caller did. Returns
    ``dist (N, C)`` (inf where none), ``p, q (N, C, 3)`` (NaN where none)."""
    n, nc = seg.shape
    dist = np.full((n, nc), np.inf)
    p = np.full((n, nc, 3), np.nan)
    q = np.full((n, nc, 3), np.nan)
    for i in range(n):
        lim = np.inf
        if within >= 0.0:
            nearest = np.inf
            for c in range(nc):
                nearest = min(nearest, dist_in[i, c])
            thr = max(within, nearest)
            lim = thr + 1e-7 * (1.0 + thr)
        ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        for c in range(nc):
            j = seg[i, c]
            if j < 0:
                continue
            if dist_in[i, c] > lim:
                seg[i, c] = -1
                continue
            dist[i, c], p0, p1, p2, q0, q1, q2 = _pair(ox, oy, oz, dx, dy, dz, starts, ends,
                                                       j)
            p[i, c, 0], p[i, c, 1], p[i, c, 2] = p0, p1, p2
            q[i, c, 0], q[i, c, 1], q[i, c, 2] = q0, q1, q2
    return dist, p, q


@njit(cache=True)
def view_contours(normals, ndc, twin, he_origin, he_dest, vertices, face0, max_valence, c):
    """The apparent contours of several surfaces from the centre ``c`` (3,) mm, as the
    arrays of a :class:`reglib.closest.ContourSet`: what
    ``ContourSet.from_surfaces`` builds (the reference, compared in tests), in one call.

    The surfaces are stacked: ``normals`` (F, 3) and ``ndc`` (F,) per face, ``twin``,
    ``he_origin``, ``he_dest`` (3F,) per half-edge, the twins local to their surface (a
    surface's half-edge ``h`` is its row ``3 * face0[k] + h``) and the vertex ids global
    (rows of ``vertices`` (V, 3)); surface ``k`` owns the faces ``face0[k]`` to
    ``face0[k + 1]``.

    Returns ``(starts, ends, path, offsets, closed, status)`` (``status`` as
    :func:`reglib._apparent_numba.contour_chains`; the first surface's non-OK status stops).
    """
    ns = face0.shape[0] - 1
    chains = []
    offs = []
    cls = []
    paths = []
    n_seg = 0
    n_con = 0
    status = OK
    for k in range(ns):
        f0, f1 = face0[k], face0[k + 1]
        h0, h1 = 3 * f0, 3 * f1
        chain, off, cl, pid, st = contour_chains(normals[f0:f1], ndc[f0:f1], twin[h0:h1],
                                                 he_origin[h0:h1], he_dest[h0:h1],
                                                 max_valence, c)
        if st != OK:
            status = st
            break
        chains.append(chain + h0)
        offs.append(off)
        cls.append(cl)
        paths.append(pid)
        n_seg += chain.shape[0]
        n_con += cl.shape[0]
    starts = np.empty((n_seg, 3))
    ends = np.empty((n_seg, 3))
    path = np.empty((n_seg + n_con, 3))
    offsets = np.zeros(n_con + 1, dtype=np.int64)
    closed = np.zeros(n_con, dtype=np.bool_)
    s = 0
    q = 0
    m = 0
    for k in range(len(chains)):
        chain, off, cl, pid = chains[k], offs[k], cls[k], paths[k]
        for j in range(chain.shape[0]):
            a, b = he_origin[chain[j]], he_dest[chain[j]]
            for x in range(3):
                starts[s + j, x] = vertices[a, x]
                ends[s + j, x] = vertices[b, x]
        for j in range(pid.shape[0]):
            for x in range(3):
                path[q + j, x] = vertices[pid[j], x]
        for j in range(cl.shape[0]):
            closed[m + j] = cl[j]
            offsets[m + j + 1] = off[j + 1] + s
        s += chain.shape[0]
        q += pid.shape[0]
        m += cl.shape[0]
    return starts, ends, path, offsets, closed, status


@njit(cache=True)
def segment_units(starts, ends, offsets):
    """Per segment its unit direction (a zero-length segment: its zero vector) and its
    contour index: ``ContourSet._unit`` and ``ContourSet.segment_contour``."""
    n = starts.shape[0]
    unit = np.empty((n, 3))
    for j in range(n):
        ex, ey, ez = ends[j, 0] - starts[j, 0], ends[j, 1] - starts[j, 1], ends[j, 2] - starts[j, 2]
        nn = np.sqrt(ex * ex + ey * ey + ez * ez)
        if not nn > 0.0:
            nn = 1.0
        unit[j, 0], unit[j, 1], unit[j, 2] = ex / nn, ey / nn, ez / nn
    seg_contour = np.empty(n, dtype=np.int64)
    for c in range(offsets.shape[0] - 1):
        for j in range(offsets[c], offsets[c + 1]):
            seg_contour[j] = c
    return unit, seg_contour


@njit(cache=True)
def match_views(o, d, external, view0, centres, normals, ndc, twin, he_origin, he_dest,
                vertices, face0, max_valence, within, max_stab, block, ratio, every):
    """:func:`match_lines` for several views at once, each against the apparent contours
    of the stacked surfaces (:func:`view_contours`) from its centre: the registration
    loop's matching in one call, without a Python object per view or contour.

    ``o, d`` (N, 3) the lines in the surfaces' frame, ``external`` (N,) bool, view ``v``
    owning rows ``view0[v]`` to ``view0[v + 1]``; ``centres`` (V, 3) the views' centres in
    the surfaces' frame; ``block`` and ``ratio`` the capsules' sizes (as
    :func:`reglib.closest._compiled_capsules`). Returns ``(p (N, 3), tangent (N, 3), bad,
    status)``: ``bad`` the first view showing no contour (-1: none; the views after it are
    not matched unless ``every``, and its own rows stay NaN) and ``status`` the contour
    extraction's (not OK: ``bad`` is that view). The per-view chain
    ``ContourSet.from_surfaces`` -> ``_match_contours`` is the reference, compared in
    tests."""
    n = o.shape[0]
    p = np.full((n, 3), np.nan)
    tan = np.full((n, 3), np.nan)
    bad = -1
    for v in range(view0.shape[0] - 1):
        starts, ends, path, offsets, closed, st = view_contours(
            normals, ndc, twin, he_origin, he_dest, vertices, face0, max_valence, centres[v])
        if st != OK:
            return p, tan, v, st
        if closed.shape[0] == 0:
            if bad < 0:
                bad = v
            if not every:
                return p, tan, v, OK
            continue
        unit, seg_contour = segment_units(starts, ends, offsets)
        a, b, eps, seg0, cb0 = block_capsules(path, offsets, block)
        sa, sb, seps, _, sb0 = block_capsules(path, offsets, block * ratio)
        sc, sr = contour_spheres(path, offsets)
        r0, r1 = view0[v], view0[v + 1]
        _, _, pv, tv = match_lines(o[r0:r1], d[r0:r1], starts, ends, unit, seg_contour,
                                   offsets, closed, a, b, eps, seg0, cb0, sa, sb, seps, sb0,
                                   ratio, within, sc, sr, external[r0:r1], max_stab)
        p[r0:r1] = pv
        tan[r0:r1] = tv
    return p, tan, bad, OK
