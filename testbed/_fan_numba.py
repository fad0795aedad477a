"""Compiled (numba) chords through closed meshes for a fan of rays from one point.

An X-ray frame is a fan: every ray starts at the focal spot ``s``. Seen from ``s``, a closed
mesh is a set of triangles on the image plane, and the length of a ray inside the mesh is the
signed sum over the triangles that cover the ray's image point of the distance to each
triangle's plane (exits ``+t``, entries ``-t``, clipped to ``[0, t_max]``): the rasterised
thickness of a mesh, computed on the CPU at exactly the rays' own image points (which follow
the intensifier's distortion, so no resampling).

Coordinates. With an orthonormal right-handed frame ``(e1, e2, a)`` (``a`` the fan's axis), a
point ``p`` projects to ``(X, Y) = ((p - s).e1 / z, (p - s).e2 / z)`` with depth
``z = (p - s).a > 0``; a ray of unit direction ``d`` to ``(d.e1 / d.a, d.e2 / d.a)``.

Exactness. For a point inside a projected triangle with barycentric coordinates ``l_k`` (from
the 2-D edge functions), the depth of the ray's hit on the triangle's plane is
``1 / sum_k l_k / z_k`` (perspective-correct interpolation, exact for a plane, and bounded by
the vertices' depths, so well conditioned even for triangles seen nearly edge-on), and
``t = z / (d.a)``. The triangle's orientation on the image plane gives the crossing's sense:
its signed area has the sign of ``(v_a - s) . n`` (``n`` the outward normal), positive for an
exit.

Watertightness. Each edge's function is evaluated in one canonical direction (lower vertex
index first) from the vertices' projections, so the two triangles that share an edge see
bit-identical values; a point exactly on an edge line is decided by a symbolic perturbation
of the point by ``(eps, eps^2)`` (the "top-left" rule), one perturbation for all edges. A
generic point is then covered by as many front-facing as back-facing triangles of a closed
mesh, and every crossing is counted once: no cracks, no doubles along shared edges. Float
rounding near a vertex can still break the balance for a ray; the count of covering
triangles is returned per ray (``balance``, +1 per exit, -1 per entry), and the caller
recasts the unbalanced rays with the exact double-precision reference.

The reference is :func:`testbed.raycast.mesh_chords` with ``engine="numpy"`` (trimesh's
brute-force ray-triangle test), compared on random meshes and fans in
``tests/testbed/test_raycast.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def bin_points(x, y, x0, y0, hx, hy, nx, ny):
    """Counting sort of image points into an ``nx`` x ``ny`` grid of cells of ``hx`` by
    ``hy`` from ``(x0, y0)`` (points outside are clamped into the border cells). Returns
    ``(start (nx*ny + 1,), order (N,))``: the points of cell ``c`` are
    ``order[start[c]:start[c + 1]]``."""
    n = x.shape[0]
    cell = np.empty(n, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(n):
        cx = int((x[i] - x0) / hx)
        cy = int((y[i] - y0) / hy)
        cx = min(max(cx, 0), nx - 1)
        cy = min(max(cy, 0), ny - 1)
        c = cy * nx + cx
        cell[i] = c
        start[c + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = cell[i]
        order[fill[c]] = i
        fill[c] += 1
    return start, order


@njit(cache=True, inline="always")
def _cell(v, lo, h, n):
    """The cell index of coordinate ``v`` in a row of ``n`` cells of side ``h`` from ``lo``,
    clamped to ``[0, n]`` before the integer conversion (a vertex projected far outside the
    rays' extent stays an in-range index)."""
    f = (v - lo) / h
    if f <= 0.0:
        return 0
    if f >= n:
        return n
    return int(f)


@njit(cache=True, inline="always")
def _perturbed_sign(dx, dy):
    """Sign of the edge function of an edge (dx, dy) at a point on the edge's line moved by
    (eps, eps^2): ``dx * eps^2 - dy * eps``."""
    if dy != 0.0:
        return -1.0 if dy > 0.0 else 1.0
    return 1.0 if dx > 0.0 else -1.0


@njit(cache=True, inline="always")
def _sorted_edge(px, py, qx, qy):
    """A triangle edge for :func:`_band_span`: lower-y end first, and its slope dx/dy (0
    when horizontal), computed once per triangle."""
    if py > qy:
        px, py, qx, qy = qx, qy, px, py
    k = (qx - px) / (qy - py) if qy != py else 0.0
    return px, py, qx, qy, k


@njit(cache=True, inline="always")
def _band_span(px, py, qx, qy, k, lo, hi, smin, smax):
    """Widen the x range ``[smin, smax]`` by the part of the edge P-Q (from
    :func:`_sorted_edge`, slope ``k``) with ``lo <= y <= hi`` (unchanged when the edge
    misses the band), rounded outwards by a relative 1e-12 so that the range never
    excludes a point that the exact edge tests include."""
    if qy < lo or py > hi:
        return smin, smax
    if qy == py:
        a, b = px, qx
    else:
        a = px + k * (max(py, lo) - py)
        b = px + k * (min(qy, hi) - py)
    if a > b:
        a, b = b, a
    pad = 1e-12 * (abs(a) + abs(b)) + 1e-300
    return min(smin, a - pad), max(smax, b + pad)


@njit(cache=True, inline="always")
def _edge(i, j, sig, vx, vy):
    """The edge i -> j of a triangle of orientation ``sig``, in canonical direction: origin,
    direction, ``g`` (the sign that makes ``g * E`` positive inside the triangle) and the
    tie-break sign ``g * perturbed sign``."""
    s = 1.0
    if j < i:
        i, j = j, i
        s = -1.0
    dx = vx[j] - vx[i]
    dy = vy[j] - vy[i]
    g = sig * s
    return vx[i], vy[i], dx, dy, g, g * _perturbed_sign(dx, dy)


@njit(cache=True, error_model="numpy")
def fan_chords(vx, vy, vz, faces, rays, start, x0, y0, hx, hy, nx, ny, acc):
    """Accumulate one closed mesh's chords for the binned rays.

    ``vx, vy, vz`` (V,): the vertices' image coordinates and depths (all ``vz > 0``);
    ``faces`` (F, 3) int, outward-oriented; ``rays`` (N, 4): per ray in bin order (``start``,
    from :func:`bin_points` with ``x0, y0, hx, hy, nx, ny``) its image point ``x, y``,
    ``t_scale = 1 / (d . a)`` and ``t_max`` mm (:func:`binned_fan`). Adds to ``acc`` (N, 2),
    also in bin order, the chord (mm, column 0) and the balance (column 1: +1 per exit, -1
    per entry, so 0 for every ray when the mesh's covering is consistent); :func:`finish`
    puts them in the rays' own order. In bin order consecutive rays of a cell are
    consecutive in memory (in the rays' order each addition was a scattered
    read-modify-write: the nine meshes of a patient frame took 36 ms that way, 23 ms this
    way). Each ray of a face's row span is tested without a branch (its three edge values
    and depth computed whatever the outcome, the sums added where it is inside, zero
    elsewhere) and the ray's four numbers and two sums lie side by side: the meshes of the
    four views' frames of experiment2 (1.0-1.2 million tests a frame, half of them inside)
    took 64.8 ms with a test per branch and four arrays of rays and two of sums, 57.3 ms so
    (timed alternately on an idle machine; 2-15 % a view), the same sums bit for bit (an
    addition of 0.0 leaves a sum as it was; numpy's error model, as a ray outside the face
    may divide by an exact zero, which Python's would raise for). Returns the range
    ``[lo, hi)`` of bin-order rays that may have been touched (what :func:`finish` reads).
    """
    x_end = x0 + nx * hx
    y_end = y0 + ny * hy
    lo = rays.shape[0]
    hi = 0
    for f in range(faces.shape[0]):
        ia, ib, ic = faces[f, 0], faces[f, 1], faces[f, 2]
        xa, ya, xb, yb, xc, yc = vx[ia], vy[ia], vx[ib], vy[ib], vx[ic], vy[ic]
        lox = min(xa, min(xb, xc))
        hix = max(xa, max(xb, xc))
        loy = min(ya, min(yb, yc))
        hiy = max(ya, max(yb, yc))
        if hix < x0 or lox > x_end or hiy < y0 or loy > y_end:
            continue                   # outside the rays' extent (e.g. outside the field)
        cx0 = _cell(lox, x0, hx, nx)
        cx1 = min(_cell(hix, x0, hx, nx), nx - 1)
        cy0 = _cell(loy, y0, hy, ny)
        cy1 = min(_cell(hiy, y0, hy, ny), ny - 1)
        if cx1 < cx0 or cy1 < cy0:
            continue
        area2 = (xb - xa) * (yc - ya) - (yb - ya) * (xc - xa)
        if area2 == 0.0:
            continue
        sig = 1.0 if area2 > 0.0 else -1.0
        # the edge opposite each vertex, in canonical direction (lower index first)
        p0x, p0y, d0x, d0y, g0, t0 = _edge(ib, ic, sig, vx, vy)
        p1x, p1y, d1x, d1y, g1, t1 = _edge(ic, ia, sig, vx, vy)
        p2x, p2y, d2x, d2y, g2, t2 = _edge(ia, ib, sig, vx, vy)
        inv_za, inv_zb, inv_zc = 1.0 / vz[ia], 1.0 / vz[ib], 1.0 / vz[ic]
        inv_area = 1.0 / area2
        e0x, e0y, e1x, e1y, k0 = _sorted_edge(xa, ya, xb, yb)
        f0x, f0y, f1x, f1y, k1 = _sorted_edge(xb, yb, xc, yc)
        g0x, g0y, g1x, g1y, k2 = _sorted_edge(xc, yc, xa, ya)
        # barycentric weight of each directed edge value, over the vertex's depth
        wa = sig * inv_area * inv_za
        wb = sig * inv_area * inv_zb
        wc = sig * inv_area * inv_zc
        for cy in range(cy0, cy1 + 1):
            # the triangle's x extent within this row of cells (its clipped edges)
            # (the band widened by 1e-9 of a cell: a point binned by rounding into this
            # row may lie a rounding error outside it)
            band_lo = y0 + cy * hy - 1e-9 * hy
            band_hi = y0 + (cy + 1) * hy + 1e-9 * hy
            slo, shi = _band_span(e0x, e0y, e1x, e1y, k0, band_lo, band_hi, hix, lox)
            slo, shi = _band_span(f0x, f0y, f1x, f1y, k1, band_lo, band_hi, slo, shi)
            slo, shi = _band_span(g0x, g0y, g1x, g1y, k2, band_lo, band_hi, slo, shi)
            if cy == 0:        # points clamped into the border rows: the whole extent
                slo, shi = lox, hix
            elif cy == ny - 1:
                slo, shi = lox, hix
            if shi < slo:
                continue
            rx0 = max(_cell(slo, x0, hx, nx), cx0)
            rx1 = min(_cell(shi, x0, hx, nx), cx1)
            if rx1 < rx0:
                continue
            lo = min(lo, start[cy * nx + rx0])
            hi = max(hi, start[cy * nx + rx1 + 1])
            for r in range(start[cy * nx + rx0], start[cy * nx + rx1 + 1]):
                x = rays[r, 0]
                y = rays[r, 1]
                # (x is within the row's span; y within the face's box, and each edge value
                # positive or zero with its tie-break sign: inside)
                v0 = g0 * (d0x * (y - p0y) - d0y * (x - p0x))
                v1 = g1 * (d1x * (y - p1y) - d1y * (x - p1x))
                v2 = g2 * (d2x * (y - p2y) - d2y * (x - p2x))
                inside = ((y >= loy) & (y <= hiy)
                          & ((v0 > 0.0) | ((v0 == 0.0) & (t0 >= 0.0)))
                          & ((v1 > 0.0) | ((v1 == 0.0) & (t1 >= 0.0)))
                          & ((v2 > 0.0) | ((v2 == 0.0) & (t2 >= 0.0))))
                # barycentrics (the directed edge functions over the signed area) over the
                # depths: the inverse depth of the hit, interpolated
                t = min(rays[r, 2] / (v0 * wa + v1 * wb + v2 * wc), rays[r, 3])
                acc[r, 0] += sig * t if inside else 0.0
                acc[r, 1] += sig if inside else 0.0
    return lo, hi


@njit(cache=True)
def finish(acc, order, out, lo, hi):
    """After every triangle of a mesh: ``out[order[r]] = acc[r, 0]`` (the chord) clamped at 0
    (rounding can leave -1e-13 on a ray that only grazes the mesh) for the rays ``lo <= r <
    hi`` that :func:`fan_chords` may have touched (``out`` holds zeros elsewhere); returns
    the rays (their own indices, ascending) whose crossings did not balance (``acc[r, 1]``),
    and zeroes ``acc`` (bin order) for the next mesh."""
    n_bad = 0
    for r in range(lo, hi):
        v = acc[r, 0]
        out[order[r]] = v if v > 0.0 else 0.0
        acc[r, 0] = 0.0
        if acc[r, 1] != 0.0:
            n_bad += 1
    bad = np.empty(n_bad, dtype=np.int64)
    k = 0
    for r in range(lo, hi):
        if acc[r, 1] != 0.0:
            bad[k] = order[r]
            k += 1
            acc[r, 1] = 0.0
    return np.sort(bad)


@njit(cache=True)
def fan_sphere_chords(centres, radii, box_lo, box_hi, ok, dirs, t_max, order, start, x0, y0,
                      hx, hy, nx, ny, source, out):
    """Add to ``out`` (N,) the length (mm) of every ray inside each sphere, analytically:
    only the rays binned in the cells of the sphere's image box (``box_lo``, ``box_hi``
    (K, 2), the image-plane bounds of the central projections of the sphere's bounding
    cube, which contain the sphere's image; all rays for a sphere with ``ok`` False) are
    visited. ``dirs`` (N, 3) and ``t_max`` (N,) in the rays' own order, ``source`` (3,).
    ``testbed.raycast.sphere_chords`` is the reference, compared in tests."""
    n_cells = nx * ny
    for k in range(centres.shape[0]):
        r2 = radii[k] * radii[k]
        if ok[k]:
            cx0 = _cell(box_lo[k, 0], x0, hx, nx)
            cx1 = min(_cell(box_hi[k, 0], x0, hx, nx), nx - 1)
            cy0 = _cell(box_lo[k, 1], y0, hy, ny)
            cy1 = min(_cell(box_hi[k, 1], y0, hy, ny), ny - 1)
            if (box_hi[k, 0] < x0 or box_lo[k, 0] > x0 + nx * hx or box_hi[k, 1] < y0
                    or box_lo[k, 1] > y0 + ny * hy or cx1 < cx0 or cy1 < cy0):
                continue
        else:
            cx0, cx1, cy0, cy1 = 0, nx - 1, 0, ny - 1
        wx = centres[k, 0] - source[0]
        wy = centres[k, 1] - source[1]
        wz = centres[k, 2] - source[2]
        ww = wx * wx + wy * wy + wz * wz
        for cy in range(cy0, cy1 + 1):
            for r in range(start[cy * nx + cx0], start[min(cy * nx + cx1 + 1, n_cells)]):
                i = order[r]
                b = wx * dirs[i, 0] + wy * dirs[i, 1] + wz * dirs[i, 2]   # closest approach
                perp2 = ww - b * b
                if perp2 >= r2:
                    continue
                hh = np.sqrt(r2 - perp2)
                t0 = min(max(b - hh, 0.0), t_max[i])
                t1 = min(max(b + hh, 0.0), t_max[i])
                out[i] += t1 - t0


@njit(cache=True)
def points_in_hull(uv, lo, hi, equations, margin):
    """Indices (ascending) of the points ``uv (M, 2)`` inside the box ``lo``-``hi`` and within
    ``margin`` of every half-plane ``nx x + ny y + off <= 0`` of ``equations (E, 3)`` (a
    convex hull's, outward unit normals); the rays of a fan that a small body can meet. The
    numpy form in ``SweepRenderer._inside_hull`` is the reference (same expressions)."""
    return points_in_hull_blocks(uv, np.full((1, 2), -np.inf), np.full((1, 2), np.inf),
                                 uv.shape[0], lo, hi, equations, margin)


@njit(cache=True, inline="always")
def _box_outside(x0, y0, x1, y1, equations, margin):
    """Whether the box ``[x0, x1] x [y0, y1]`` lies beyond one half-plane's margin at all
    four corners by more than 1e-6 (then no point of the box passes that half-plane's test:
    a linear function's largest value over a box is at a corner, and 1e-6 covers the
    rounding of the pixel-scale products many times over)."""
    for e in range(equations.shape[0]):
        a, b, c = equations[e, 0], equations[e, 1], equations[e, 2]
        lim = margin + 1e-6
        if (a * x0 + b * y0 + c > lim and a * x1 + b * y0 + c > lim
                and a * x0 + b * y1 + c > lim and a * x1 + b * y1 + c > lim):
            return True
    return False


@njit(cache=True)
def points_in_hull_blocks(uv, block_lo, block_hi, block, lo, hi, equations, margin):
    """:func:`points_in_hull` skipping the blocks of ``block`` consecutive points whose
    bounding boxes (:func:`block_boxes`) miss the box ``lo``-``hi`` (the same indices: a
    point outside that box is never kept). Rays in row-major order make compact blocks."""
    out = np.empty(uv.shape[0], np.int64)
    n = 0
    active = np.empty(equations.shape[0], np.int64)
    for b in range(block_lo.shape[0]):
        x0, y0, x1, y1 = block_lo[b, 0], block_lo[b, 1], block_hi[b, 0], block_hi[b, 1]
        if x1 < lo[0] or x0 > hi[0] or y1 < lo[1] or y0 > hi[1]:
            continue
        if _box_outside(x0, y0, x1, y1, equations, margin):
            continue
        # the half-planes the block's box straddles: one that holds the whole box within
        # its margin by more than 1e-6 at all four corners holds every point of the block
        # (the converse of _box_outside's argument), so only the others are tested
        na = 0
        lim = margin - 1e-6
        for e in range(equations.shape[0]):
            a, bb, c = equations[e, 0], equations[e, 1], equations[e, 2]
            if not (a * x0 + bb * y0 + c < lim and a * x1 + bb * y0 + c < lim
                    and a * x0 + bb * y1 + c < lim and a * x1 + bb * y1 + c < lim):
                active[na] = e
                na += 1
        for i in range(b * block, min((b + 1) * block, uv.shape[0])):
            x, y = uv[i, 0], uv[i, 1]
            if x < lo[0] or x > hi[0] or y < lo[1] or y > hi[1]:
                continue
            inside = True
            for j in range(na):
                e = active[j]
                if equations[e, 0] * x + equations[e, 1] * y + equations[e, 2] > margin:
                    inside = False
                    break
            if inside:
                out[n] = i
                n += 1
    return out[:n]


@njit(cache=True)
def block_boxes(uv, block):
    """Bounding boxes ``(lo (B, 2), hi (B, 2))`` of consecutive blocks of ``block`` points of
    ``uv (M, 2)`` (the last block may be shorter), for :func:`points_in_hull`."""
    m = uv.shape[0]
    nb = (m + block - 1) // block
    lo = np.empty((nb, 2))
    hi = np.empty((nb, 2))
    for b in range(nb):
        i0 = b * block
        lo[b, 0] = hi[b, 0] = uv[i0, 0]
        lo[b, 1] = hi[b, 1] = uv[i0, 1]
        for i in range(i0 + 1, min(i0 + block, m)):
            lo[b, 0] = min(lo[b, 0], uv[i, 0])
            hi[b, 0] = max(hi[b, 0], uv[i, 0])
            lo[b, 1] = min(lo[b, 1], uv[i, 1])
            hi[b, 1] = max(hi[b, 1], uv[i, 1])
    return lo, hi


@njit(cache=True)
def hull_equations(pts, flat_area):
    """Half-planes ``(E, 3)`` rows ``(nx, ny, offset)`` of the convex hull of ``pts (K, 2)``
    sorted by x then y (Andrew's monotone chain, counter-clockwise): outward unit normals,
    ``n . x + offset <= 0`` inside, as ``scipy.spatial.ConvexHull(pts).equations`` (its
    reference; the rows in another order). No rows (a flat hull, whose bounding box the
    caller uses) when the hull's area is at most ``flat_area``."""
    k = pts.shape[0]
    hull = np.empty(2 * k + 1, np.int64)
    m = 0
    for i in range(k):                       # lower chain
        while m >= 2 and _cross(pts, hull[m - 2], hull[m - 1], i) <= 0.0:
            m -= 1
        hull[m] = i
        m += 1
    low = m + 1
    for i in range(k - 2, -1, -1):           # upper chain
        while m >= low and _cross(pts, hull[m - 2], hull[m - 1], i) <= 0.0:
            m -= 1
        hull[m] = i
        m += 1
    m -= 1                                   # the first point closes the chain
    area = 0.0
    for j in range(m):
        a, b = hull[j], hull[(j + 1) % m]
        area += pts[a, 0] * pts[b, 1] - pts[b, 0] * pts[a, 1]
    if m < 3 or 0.5 * area <= flat_area:
        return np.zeros((0, 3))
    eq = np.empty((m, 3))
    for j in range(m):
        a, b = hull[j], hull[(j + 1) % m]
        dx, dy = pts[b, 0] - pts[a, 0], pts[b, 1] - pts[a, 1]
        norm = np.sqrt(dx * dx + dy * dy)
        nx, ny = dy / norm, -dx / norm         # outward of a counter-clockwise edge
        eq[j, 0], eq[j, 1] = nx, ny
        eq[j, 2] = -(nx * pts[a, 0] + ny * pts[a, 1])
    return eq


@njit(cache=True, inline="always")
def _cross(pts, o, a, b):
    return ((pts[a, 0] - pts[o, 0]) * (pts[b, 1] - pts[o, 1])
            - (pts[a, 1] - pts[o, 1]) * (pts[b, 0] - pts[o, 0]))


@njit(cache=True)
def source_near_bodies(pts, mesh_seg, centres, radii, src):
    """Whether the point ``src (3,)`` may lie inside one of a set of bodies, a fast filter of
    ``testbed.fluoroscope._check_source_outside`` (which the caller then runs, the exact
    test): True when ``src`` lies within the bounds (the exact minimum and maximum) of the
    points ``pts[mesh_seg[k, 0]:mesh_seg[k, 1]]`` of a mesh ``k``, or within a sphere
    ``centres (C, 3)``, ``radii (C,)`` enlarged by a relative 1e-9 (far more than the
    rounding of its distance); False when ``src`` is certainly outside them all."""
    for k in range(mesh_seg.shape[0]):
        i0, i1 = mesh_seg[k, 0], mesh_seg[k, 1]
        if i1 <= i0:
            continue
        inside = True
        for c in range(3):
            lo = hi = pts[i0, c]
            for i in range(i0 + 1, i1):
                lo = min(lo, pts[i, c])
                hi = max(hi, pts[i, c])
            if not (src[c] >= lo and src[c] <= hi):
                inside = False
                break
        if inside:
            return True
    for k in range(centres.shape[0]):
        dx = centres[k, 0] - src[0]
        dy = centres[k, 1] - src[1]
        dz = centres[k, 2] - src[2]
        if not dx * dx + dy * dy + dz * dz > radii[k] * radii[k] * (1.0 + 1e-9):
            return True
    return False


@njit(cache=True)
def projected_hull(q, principal_x, principal_y, sid, pixel, margin, flat_area):
    """The culling hull of the points ``q (K, 3)`` in the C-arm frame (source at the origin,
    +z the beam): their undistorted pixels (the pinhole expressions of
    ``CArm.project_undistorted``, term for term), ``lo``/``hi`` their bounds less/plus
    ``margin``, and :func:`hull_equations` of them sorted by x then y (as
    ``np.lexsort((y, x))``: points of equal x and y are equal, so the order among them does
    not change the rows). Returns ``(ok, pts (K, 2), lo, hi, equations)``; ``ok`` False (and
    nothing else computed) when a point lies at or behind the source (``q_z <= 1e-9``)."""
    k = q.shape[0]
    pts = np.empty((k, 2))
    lo = np.empty(2)
    hi = np.empty(2)
    for i in range(k):
        if q[i, 2] <= 1e-9:
            return False, pts, lo, hi, np.zeros((0, 3))
    for i in range(k):
        pts[i, 0] = principal_x + sid * q[i, 0] / (q[i, 2] * pixel)
        pts[i, 1] = principal_y + sid * q[i, 1] / (q[i, 2] * pixel)
    for c in range(2):
        a = b = pts[0, c]
        for i in range(1, k):
            a = min(a, pts[i, c])
            b = max(b, pts[i, c])
        lo[c] = a - margin
        hi[c] = b + margin
    by_y = np.argsort(pts[:, 1], kind="mergesort")
    xs = np.empty(k)
    for i in range(k):
        xs[i] = pts[by_y[i], 0]
    by_x = np.argsort(xs, kind="mergesort")
    srt = np.empty((k, 2))
    for i in range(k):
        j = by_y[by_x[i]]
        srt[i, 0] = pts[j, 0]
        srt[i, 1] = pts[j, 1]
    return True, pts, lo, hi, hull_equations(srt, flat_area)


@njit(cache=True)
def gather_rays(d, tm, a, idx):
    """``(d[idx], tm[idx], a[idx])`` of directions ``d (N, 3)`` and values ``tm``, ``a``
    (N,): the rows at the indices ``idx``, contiguous (numpy's gathers, the same values)."""
    m = idx.shape[0]
    dd = np.empty((m, 3))
    tt = np.empty(m)
    aa = np.empty(m)
    for i in range(m):
        j = idx[i]
        dd[i, 0] = d[j, 0]
        dd[i, 1] = d[j, 1]
        dd[i, 2] = d[j, 2]
        tt[i] = tm[j]
        aa[i] = a[j]
    return dd, tt, aa


@njit(cache=True)
def plane_coords(da, de1, de2):
    """The image-plane coordinates ``x = de1 / da``, ``y = de2 / da`` of a fan's rays (``da``,
    ``de1``, ``de2``: their directions' products with the plane's axis and in-plane unit
    vectors) and their bounds ``(x, y, x_min, y_min, x_max, y_max)``: ``FanRays``' numpy
    expressions, the same numbers (NaN bounds where a coordinate is NaN, as numpy's)."""
    n = da.shape[0]
    x = np.empty(n)
    y = np.empty(n)
    for i in range(n):
        x[i] = de1[i] / da[i]
        y[i] = de2[i] / da[i]
    x0 = x1 = x[0]
    y0 = y1 = y[0]
    nan_x = nan_y = False
    for i in range(n):
        x0 = min(x0, x[i])
        x1 = max(x1, x[i])
        y0 = min(y0, y[i])
        y1 = max(y1, y[i])
        nan_x |= np.isnan(x[i])
        nan_y |= np.isnan(y[i])
    if nan_x:                   # numpy's minimum and maximum propagate NaN
        x0 = x1 = np.nan
    if nan_y:
        y0 = y1 = np.nan
    return x, y, x0, y0, x1, y1


@njit(cache=True)
def binned_fan(x, y, da, t_max, x0, y0, hx, hy, nx, ny):
    """:func:`bin_points` of the rays' image points and their coordinates, ``1 / da`` and
    ``t_max`` in the bins' order, packed: ``(start, order, rays (N, 4))``, the columns of
    ``rays`` ``x, y, 1 / da, t_max`` (as ``FanRays``' numpy gathers, the same numbers)."""
    start, order = bin_points(x, y, x0, y0, hx, hy, nx, ny)
    n = order.shape[0]
    rays = np.empty((n, 4))
    for i in range(n):
        j = order[i]
        rays[i, 0] = x[j]
        rays[i, 1] = y[j]
        rays[i, 2] = 1.0 / da[j]
        rays[i, 3] = t_max[j]
    return start, order, rays


@njit(cache=True)
def sphere_image_boxes(z, u, v):
    """The image-plane boxes of spheres' bounding cubes from their corners' depths ``z`` and
    in-plane products ``u``, ``v`` (K, 8) (relative to the source): ``(ok (K,), lo (K, 2),
    hi (K, 2))``, ``ok`` where the cube lies wholly in front of the source (every depth
    above 1e-9); the corners' coordinates ``u / z``, ``v / z`` (depth 1 where not in
    front). ``FanRays.sphere_chords``' numpy expressions, the same numbers."""
    k = z.shape[0]
    ok = np.empty(k, np.bool_)
    lo = np.empty((k, 2))
    hi = np.empty((k, 2))
    for i in range(k):
        good = True
        for j in range(z.shape[1]):
            zj = z[i, j]
            good &= zj > 1e-9
            zs = zj if zj > 1e-9 else 1.0
            px = u[i, j] / zs
            py = v[i, j] / zs
            if j == 0:
                lo[i, 0] = hi[i, 0] = px
                lo[i, 1] = hi[i, 1] = py
            else:
                lo[i, 0] = _nan_min(lo[i, 0], px)
                hi[i, 0] = _nan_max(hi[i, 0], px)
                lo[i, 1] = _nan_min(lo[i, 1], py)
                hi[i, 1] = _nan_max(hi[i, 1], py)
        ok[i] = good
    return ok, lo, hi


@njit(cache=True, inline="always")
def _nan_min(a, b):
    """``np.minimum``'s NaN-propagating minimum of two numbers."""
    if np.isnan(a) or np.isnan(b):
        return np.nan
    return min(a, b)


@njit(cache=True, inline="always")
def _nan_max(a, b):
    """``np.maximum``'s NaN-propagating maximum of two numbers."""
    if np.isnan(a) or np.isnan(b):
        return np.nan
    return max(a, b)


@njit(cache=True)
def column_means(d):
    """``d.mean(axis=0)`` of a C-contiguous ``(N, K)`` array, ``K >= 2``, the same bits:
    numpy sums along the outer axis row by row, in order (no pairwise summation there; it
    sums a single column pairwise), then divides by N; here in one pass (a field's ~175k
    ray directions: 2.5 ms in numpy, whose inner loop is 3 elements long)."""
    n, k = d.shape
    out = np.zeros(k)
    if n == 0:
        out[:] = np.nan
        return out
    for j in range(k):
        out[j] = d[0, j]
    for i in range(1, n):
        for j in range(k):
            out[j] += d[i, j]
    for j in range(k):
        out[j] = out[j] / n
    return out
