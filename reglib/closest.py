"""Closest points between X-ray paths (3-D lines) and apparent contours (3-D polylines).

Step A of the paper (Guezic et al. 1998, Section IV; ``paper/NOTES.md`` s3): for every line
and every contour, the point ``p`` of the contour closest to the line and the point ``q`` of
the line closest to ``p``. Step B: the *stabbing* test and the selection of one contour per
line.

Five exact ways to compute Step A, one interface (:func:`closest_points`):

``"compiled"`` (the registration's default)
    The same capsule bounds as ``"blocks"`` with one level of blocks of
    :data:`COMPILED_BLOCK` segments, in a compiled loop per line
    (:mod:`reglib._closest_numba`): a block is skipped when its lower bound exceeds the
    contour's best distance so far (or, with ``within_mm``, the line's threshold), the
    others' segments are measured exactly; then the exact points of the chosen segments.
``"blocks"`` (the default of :func:`closest_points`)
    The paper's bounding capsules as a fixed three-level hierarchy (blocks of 64 and of 8
    consecutive segments, then the segments), searched level by level for all lines at
    once so that numpy does the work: each block's capsule has its axis from the block's
    first to its last vertex and radius ``eps`` = the largest distance of its vertices from
    the axis; a (line, block) pair is split only while its lower bound ``d - eps`` does not
    exceed the best upper bound ``d + eps`` found so far, and the segments reached are
    measured exactly. With ``within_mm`` (what the registration loop uses) contours farther
    than ``max(within_mm, nearest)`` are skipped altogether, which is all Step B needs. No
    Python loop over lines or segments. It replaces the paper's priority queue (a loop per
    line) by a breadth-first pruning with the same bounds.
``"dense"``
    All line-segment pairs of a view at once, as one matrix product plus element-wise
    numpy on ``(N, S)`` arrays (coordinates re-centred on the contours so that the expanded
    squared distances keep their precision), then the exact distance recomputed for the
    winning segment of each (line, contour).
``"hierarchy"``
    The paper's method. Each contour gets a binary hierarchy of segments with capsule
    bounding regions (axis from the first to the last vertex of the part, radius ``eps`` =
    the largest distance of the part's vertices from that axis); a priority queue keyed on
    the lower bound ``d - eps`` is split until its lowest entry is a single segment, whose
    distance is then exact and no larger than any other entry's lower bound. The paper's
    radius ``r = (d2 - eps2 - d1 - eps1) / 2`` is kept per (line, contour). For the next
    line (lines sorted so that neighbours follow each other, e.g. along the image contour)
    the paper searches segment 1 directly when the line passes within ``r`` of ``q``; that
    shortcut is exact for points but not for lines (two lines close at ``q`` part further
    away), so here the previous line's segment instead gives an initial upper bound that
    prunes the queue, which keeps the result exact and the saving. Pure Python (a heap per
    line): slow in CPython, kept as the method of the paper and measured beside the others.
``"reference"``
    The plain brute force: every line against every segment with the textbook formula on
    ``(N, S, 3)`` arrays; the reference the tests compare the others with.

All of them return the same :class:`ClosestPoints` (to rounding; ties between segments that
meet at a vertex may report either segment).

Conventions: lines are ``origins (N, 3)`` mm and unit ``directions (N, 3)``; contours are in
the same frame as the lines; distances in mm.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np

from reglib.geometry import as_lines, as_points, line_segment_distance

__all__ = [
    "ClosestPoints",
    "ContourSet",
    "closest_points",
    "select_contours",
    "stabbing",
]

Method = Literal["compiled", "blocks", "dense", "hierarchy", "reference"]


# --------------------------------------------------------------------------- contours
@dataclass(frozen=True, eq=False)
class ContourSet:
    """Several oriented polylines flattened into one array of segments.

    Attributes
    ----------
    starts, ends : (S, 3) float64 ndarrays, mm; segment ``g`` runs from ``starts[g]`` to
        ``ends[g]`` (the contour's orientation: visible triangles on its left).
    offsets : (C + 1,) int64; contour ``c`` owns segments ``offsets[c]:offsets[c + 1]``
        (at least one each).
    closed : (C,) bool.
    path : (S + C, 3) float64, the vertices of each contour in order, a closed contour's
        first vertex repeated at its end; contour ``c``'s segment ``j`` joins
        ``path[offsets[c] + c + j]`` and the next row.
    """

    starts: np.ndarray
    ends: np.ndarray
    offsets: np.ndarray
    closed: np.ndarray
    path: np.ndarray

    @property
    def n_contours(self) -> int:
        return int(len(self.offsets) - 1)

    @property
    def n_segments(self) -> int:
        return int(len(self.starts))

    @cached_property
    def segment_contour(self) -> np.ndarray:
        """(S,) int64, contour index of each segment (computed once per set)."""
        return np.repeat(np.arange(self.n_contours), np.diff(self.offsets))

    @cached_property
    def _unit(self) -> np.ndarray:
        """(S, 3) unit direction of each segment (zero-length segments: their vector)."""
        e = self.ends - self.starts
        n = np.linalg.norm(e, axis=1, keepdims=True)
        return e / np.where(n > 0, n, 1.0)

    def tangents(self, segment, p, *, reference: bool = False) -> np.ndarray:
        """Oriented contour direction at points ``p (..., 3)`` lying on ``segment (...)``.

        Inside a segment: its unit direction. At a vertex (``p`` within 1e-9 mm of a segment
        end) the two segments meeting there are ambiguous, so the sum of their unit
        directions is used (normalised), whichever of them holds ``p``; at the free end of an
        open contour, the end segment's direction. Entries with ``segment < 0`` are NaN.
        Compiled (:func:`reglib._closest_numba.tangents`); ``reference=True`` is the numpy
        version, compared with it in tests.
        """
        seg = np.asarray(segment, dtype=np.int64)
        p = np.asarray(p, dtype=np.float64)
        if not reference:
            from reglib._closest_numba import tangents

            flat = tangents(self._unit, self.starts, self.ends, self.segment_contour,
                            self.offsets, self.closed, np.ascontiguousarray(seg.reshape(-1)),
                            np.ascontiguousarray(p.reshape(-1, 3)))
            return flat.reshape(seg.shape + (3,))
        valid = seg >= 0
        g = np.where(valid, seg, 0)
        u = self._unit
        c = self.segment_contour[g]
        lo, hi = self.offsets[c], self.offsets[c + 1] - 1
        closed = self.closed[c]
        prv = np.where(g > lo, g - 1, np.where(closed, hi, -1))
        nxt = np.where(g < hi, g + 1, np.where(closed, lo, -1))
        at_start = np.linalg.norm(p - self.starts[g], axis=-1) <= 1e-9
        at_end = np.linalg.norm(p - self.ends[g], axis=-1) <= 1e-9
        t = u[g].copy()
        add_prev = at_start & (prv >= 0)
        add_next = at_end & ~at_start & (nxt >= 0)
        t[add_prev] += u[prv[add_prev]]
        t[add_next] += u[nxt[add_next]]
        tn = np.linalg.norm(t, axis=-1, keepdims=True)
        t = np.where(tn > 1e-12, t / np.where(tn > 1e-12, tn, 1.0), u[g])
        t[~valid] = np.nan
        return t

    @classmethod
    def from_polylines(cls, polylines, closed) -> ContourSet:
        """From a list of ``(K_c, 3)`` vertex arrays (mm) and a list of ``closed`` flags.

        A closed polyline needs at least 2 vertices (it then has ``K_c`` segments), an open one
        at least 2 (``K_c - 1`` segments).
        """
        polylines = list(polylines)
        closed = [bool(c) for c in closed]
        if len(polylines) != len(closed):
            raise ValueError(
                f"polylines ({len(polylines)}) and closed flags ({len(closed)}) differ in number"
            )
        paths, nseg = [], []
        for i, (pts, cl) in enumerate(zip(polylines, closed)):
            pts = as_points(pts, f"polylines[{i}]")
            if len(pts) < 2:
                raise ValueError(f"polylines[{i}]: needs at least 2 vertices, got {len(pts)}")
            paths.append(np.vstack([pts, pts[:1]]) if cl else pts)
            nseg.append(len(pts) if cl else len(pts) - 1)
        if not paths:
            path = np.zeros((0, 3))
            starts = ends = np.zeros((0, 3))
        else:
            path = np.vstack(paths)
            keep_s = np.ones(len(path), dtype=bool)
            keep_e = np.ones(len(path), dtype=bool)
            ends_idx = np.cumsum([len(p) for p in paths])
            keep_s[ends_idx - 1] = False
            keep_e[np.r_[0, ends_idx[:-1]]] = False
            starts, ends = path[keep_s], path[keep_e]
        offsets = np.r_[0, np.cumsum(nseg)].astype(np.int64)
        return cls(starts=np.ascontiguousarray(starts), ends=np.ascontiguousarray(ends),
                   offsets=offsets, closed=np.array(closed, dtype=bool), path=path)

    @classmethod
    def from_surfaces(cls, surfaces, center) -> tuple[ContourSet, np.ndarray]:
        """The apparent contours of every surface (:class:`reglib.apparent.SurfaceTopology`,
        one frame) from ``center`` (3,) mm, in one set, and the surface index of each
        contour ``(C,)``: equal to ``from_contours`` of :func:`reglib.apparent.
        apparent_contours` surface after surface (the reference; compared in tests), built
        from the compiled :func:`reglib.apparent.contour_arrays` without a Python object
        per contour."""
        from reglib.apparent import contour_arrays

        starts, ends, paths, offsets, closed, owner = [], [], [], [np.zeros(1, np.int64)], [], []
        n_seg = 0
        for k, top in enumerate(surfaces):
            chain, off, cl, path_ids = contour_arrays(top, center)
            v = top.vertices
            starts.append(v[top.he_origin[chain]])
            ends.append(v[top.he_dest[chain]])
            paths.append(v[path_ids])
            offsets.append(off[1:] + n_seg)
            closed.append(cl)
            owner.append(np.full(len(cl), k, dtype=np.int64))
            n_seg += len(chain)
        if not owner:
            return cls.from_polylines([], []), np.zeros(0, dtype=np.int64)
        return cls(starts=np.ascontiguousarray(np.vstack(starts)),
                   ends=np.ascontiguousarray(np.vstack(ends)),
                   offsets=np.concatenate(offsets), closed=np.concatenate(closed),
                   path=np.vstack(paths)), np.concatenate(owner)

    @classmethod
    def from_contours(cls, contours) -> ContourSet:
        """From :class:`reglib.apparent.ApparentContour` objects (anything with ``points``
        and ``closed``)."""
        contours = list(contours)
        return cls.from_polylines([c.points for c in contours], [c.closed for c in contours])


@dataclass(frozen=True, eq=False)
class ClosestPoints:
    """Closest points between N lines and C contours.

    Attributes
    ----------
    distance : (N, C) float64, mm, distance from line n to contour c.
    p : (N, C, 3) float64, mm, closest point on the contour.
    q : (N, C, 3) float64, mm, point of the line closest to ``p``.
    segment : (N, C) int64, global index (into the ContourSet) of the segment holding ``p``.
    reuse_radius : (N, C) float64 or None, mm, the paper's ``r`` (hierarchy method only).
    """

    distance: np.ndarray
    p: np.ndarray
    q: np.ndarray
    segment: np.ndarray
    reuse_radius: np.ndarray | None = None


# --------------------------------------------------------------------------- exact kernels
def _exact(o, d, a, b):
    """Exact closest points of lines ``(o, d)`` and segments ``[a, b]`` paired row by row.

    All ``(..., 3)`` (broadcast); returns ``dist (...), p (..., 3), q (..., 3)``. Written
    component by component: numpy reductions over a length-3 last axis are several times
    slower than plain element-wise arithmetic.
    """
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    ex, ey, ez = b[..., 0] - ax, b[..., 1] - ay, b[..., 2] - az
    wx, wy, wz = ax - ox, ay - oy, az - oz
    wd = wx * dx + wy * dy + wz * dz
    ed = ex * dx + ey * dy + ez * dz
    px, py, pz = wx - wd * dx, wy - wd * dy, wz - wd * dz          # a - o, across the line
    qx, qy, qz = ex - ed * dx, ey - ed * dy, ez - ed * dz          # e, across the line
    qq = qx * qx + qy * qy + qz * qz
    pq = px * qx + py * qy + pz * qz
    pos = qq > 0.0
    s = np.where(pos, -pq / np.where(pos, qq, 1.0), 0.0)
    np.clip(s, 0.0, 1.0, out=s)
    p = np.stack([ax + s * ex, ay + s * ey, az + s * ez], axis=-1)
    t = (p[..., 0] - ox) * dx + (p[..., 1] - oy) * dy + (p[..., 2] - oz) * dz
    q = np.stack([ox + t * dx, oy + t * dy, oz + t * dz], axis=-1)
    r = p - q
    dist = np.sqrt(r[..., 0] ** 2 + r[..., 1] ** 2 + r[..., 2] ** 2)
    return dist, p, q


def _distance_only(o, d, a, b):
    """Line-segment distances as in :func:`_exact` (to rounding), without the points."""
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    wx, wy, wz = a[..., 0] - o[..., 0], a[..., 1] - o[..., 1], a[..., 2] - o[..., 2]
    ex, ey, ez = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1], b[..., 2] - a[..., 2]
    wd = wx * dx + wy * dy + wz * dz
    ed = ex * dx + ey * dy + ez * dz
    px, py, pz = wx - wd * dx, wy - wd * dy, wz - wd * dz
    qx, qy, qz = ex - ed * dx, ey - ed * dy, ez - ed * dz
    qq = qx * qx + qy * qy + qz * qz
    pos = qq > 0.0
    s = np.where(pos, -(px * qx + py * qy + pz * qz) / np.where(pos, qq, 1.0), 0.0)
    np.clip(s, 0.0, 1.0, out=s)
    rx, ry, rz = px + s * qx, py + s * qy, pz + s * qz
    return np.sqrt(rx * rx + ry * ry + rz * rz)


def _check(contours: ContourSet, origins, directions):
    if not isinstance(contours, ContourSet):
        raise ValueError(f"contours: expected a ContourSet, got {type(contours).__name__}")
    o, d = as_lines(origins, directions)
    return o, d


def _empty(n: int, c: int) -> ClosestPoints:
    return ClosestPoints(np.full((n, c), np.inf), np.full((n, c, 3), np.nan),
                         np.full((n, c, 3), np.nan), np.full((n, c), -1, dtype=np.int64))


def _finish(contours: ContourSet, o, d, seg, reuse=None) -> ClosestPoints:
    """Exact recomputation for the chosen segment of each (line, contour)."""
    n, c = seg.shape
    oo = np.broadcast_to(o[:, None, :], (n, c, 3))
    dd = np.broadcast_to(d[:, None, :], (n, c, 3))
    dist, p, q = _exact(oo, dd, contours.starts[seg], contours.ends[seg])
    return ClosestPoints(dist, p, q, seg, reuse)


def _closest_reference(contours: ContourSet, o, d) -> ClosestPoints:
    n = len(o)
    dist, _, _ = _exact(o[:, None, :], d[:, None, :], contours.starts[None], contours.ends[None])
    seg = np.empty((n, contours.n_contours), dtype=np.int64)
    for c in range(contours.n_contours):
        lo, hi = contours.offsets[c], contours.offsets[c + 1]
        seg[:, c] = lo + np.argmin(dist[:, lo:hi], axis=1)
    return _finish(contours, o, d, seg)


def _closest_dense(contours: ContourSet, o, d) -> ClosestPoints:
    """All pairs with matrix products; see the module docstring."""
    ref = 0.5 * (contours.starts.min(axis=0) + contours.starts.max(axis=0))
    a = contours.starts - ref
    e = contours.ends - contours.starts
    # re-base each line on its point closest to ``ref``: then (o - ref) . d = 0
    o0 = o - ref
    o0 = o0 - np.sum(o0 * d, axis=1, keepdims=True) * d
    left = np.vstack([a, e])                        # (2S, 3)
    right = np.hstack([d, o0]).reshape(-1, 2, 3)    # (N, 2, 3)
    G = right.reshape(-1, 3) @ left.T               # (2N, 2S): rows d_n, o_n; cols a, e
    G = G.reshape(len(o), 2, 2, -1)
    S = len(a)
    ad, ed = G[:, 0, 0, :], G[:, 0, 1, :]
    ao, eo = G[:, 1, 0, :], G[:, 1, 1, :]
    aa = np.einsum("ij,ij->i", a, a)
    ae = np.einsum("ij,ij->i", a, e)
    ee = np.einsum("ij,ij->i", e, e)
    oo = np.einsum("ij,ij->i", o0, o0)
    # w = a - o;  w.d = a.d (o.d = 0);  a' = w - (w.d) d;  e' = e - (e.d) d
    ape = ae - eo - ad * ed                          # a'.e'
    epe = ee - ed * ed                               # |e'|^2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.where(epe > 1e-300, -ape / epe, 0.0), 0.0, 1.0)
    d2 = (aa - 2.0 * ao) + oo[:, None] - ad * ad + s * (2.0 * ape + s * epe)
    offs = contours.offsets
    mins = np.minimum.reduceat(d2, offs[:-1], axis=1)            # (N, C)
    hit = d2 <= np.repeat(mins, np.diff(offs), axis=1)
    idx = np.where(hit, np.arange(S), S)
    seg = np.minimum.reduceat(idx, offs[:-1], axis=1).astype(np.int64)
    return _finish(contours, o, d, seg)


def _group_argmin(values: np.ndarray, group_starts: np.ndarray) -> np.ndarray:
    """Index (into ``values``) of the first minimum of each contiguous group."""
    mins = np.minimum.reduceat(values, group_starts)
    sizes = np.diff(np.r_[group_starts, len(values)])
    hit = values <= np.repeat(mins, sizes)
    idx = np.where(hit, np.arange(len(values)), len(values))
    return np.minimum.reduceat(idx, group_starts)


def _ranges(offsets: np.ndarray, size: int):
    """Blocks of ``size`` consecutive segments within each contour: ``(contour, j0, j1)``
    (local segment range ``[j0, j1)``), in contour order, and blocks per contour."""
    nseg = np.diff(offsets)
    nblk = -(-nseg // size)
    bc = np.repeat(np.arange(len(nseg)), nblk)
    j0 = (np.arange(nblk.sum()) - np.repeat(np.cumsum(nblk) - nblk, nblk)) * size
    return bc, j0, np.minimum(j0 + size, nseg[bc]), nblk


def _expand(counts: np.ndarray) -> np.ndarray:
    """``[0..counts[0]-1, 0..counts[1]-1, ...]``."""
    return np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)


def _block_capsules(contours: ContourSet, size: int):
    """The contours cut into blocks of ``size`` consecutive segments, in contour order:
    per block its contour ``bc``, local segment range ``[j0, j1)``, capsule axis ``a -> b``
    (its first and last vertex) and radius ``eps`` (the largest distance of its vertices
    from the axis); ``first`` is each contour's first block."""
    nc = contours.n_contours
    path = contours.path
    pbase = contours.offsets[:-1] + np.arange(nc)
    bc, j0, j1, nblk = _ranges(contours.offsets, size)
    lo, hi = pbase[bc] + j0, pbase[bc] + j1
    cnt = hi - lo + 1
    rows = np.repeat(lo, cnt) + _expand(cnt)
    owner = np.repeat(np.arange(len(lo)), cnt)
    dev = _point_segment_distances(path[rows], path[lo][owner], path[hi][owner])
    eps = np.maximum.reduceat(dev, np.r_[0, np.cumsum(cnt)[:-1]])
    first = np.r_[0, np.cumsum(nblk)[:-1]]        # first block of each contour
    return bc, j0, j1, path[lo], path[hi], eps, first


#: segments per block of the compiled method (measured: 8 fastest of 4-32 on the
#: registration's apparent contours)
COMPILED_BLOCK = 8
#: blocks per superblock of the compiled method
COMPILED_SUPER = 8


def _compiled_capsules(contours: ContourSet):
    """The compiled method's blocks and superblocks, and a sphere per contour."""
    from reglib._closest_numba import block_capsules, contour_spheres

    path = np.ascontiguousarray(contours.path)
    offsets = np.ascontiguousarray(contours.offsets)
    a, b, eps, seg0, cb0 = block_capsules(path, offsets, COMPILED_BLOCK)
    sa, sb, seps, _, sb0 = block_capsules(path, offsets, COMPILED_BLOCK * COMPILED_SUPER)
    return (a, b, eps, seg0, cb0, sa, sb, seps, sb0, COMPILED_SUPER), contour_spheres(path,
                                                                                     offsets)


def _closest_compiled(contours: ContourSet, o, d, within=None) -> ClosestPoints:
    """The capsule pruning compiled (:mod:`reglib._closest_numba`), one loop per line."""
    from reglib._closest_numba import closest_segments, exact_pairs

    blocks, spheres = _compiled_capsules(contours)
    dist, seg = closest_segments(np.ascontiguousarray(o), np.ascontiguousarray(d),
                                 np.ascontiguousarray(contours.starts),
                                 np.ascontiguousarray(contours.ends), *blocks,
                                 -1.0 if within is None else float(within), *spheres)
    # beyond the line's threshold: not computed, as "blocks" says; the rest exactly
    dist, p, q = exact_pairs(np.ascontiguousarray(o), np.ascontiguousarray(d),
                             np.ascontiguousarray(contours.starts),
                             np.ascontiguousarray(contours.ends), dist, seg,
                             -1.0 if within is None else float(within))
    return ClosestPoints(dist, p, q, seg)


def _closest_blocks(contours: ContourSet, o, d, within=None, sizes=(64, 8)) -> ClosestPoints:
    """Exact pruning over a fixed hierarchy of capsules, level by level for all lines.

    Level 0 cuts each contour into blocks of ``sizes[0]`` segments, the next levels into
    blocks of ``sizes[1]``, ... (each a multiple of the next), the last level is the
    segments. A block's capsule has its axis from the block's first to its last vertex and
    radius ``eps`` = the largest distance of its vertices from the axis. Every line is
    measured against every level-0 capsule; at each level the (line, block) pairs whose
    lower bound ``d - eps`` does not exceed the threshold are split into their children,
    and the segments reached at the end are measured exactly. The threshold is the best
    upper bound ``d + eps`` so far of the pair's contour, or with ``within`` of the line
    over all contours, raised to ``within`` (contours beyond it come back at infinity).
    """
    n, nc = len(o), contours.n_contours
    levels = [(size, *_block_capsules(contours, size)) for size in sizes]

    def threshold(li, key, upper):
        """Per pair: the best upper bound of its group (line, or line and contour)."""
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        best = np.minimum.reduceat(upper, starts)
        if within is not None:
            best = np.maximum(best, within)
        best = best + 1e-7 * (1.0 + best)
        return np.repeat(best, np.diff(np.r_[starts, len(key)]))

    # level 0: all lines against all top blocks
    size, bc, j0, j1, a, b, eps, first = levels[0]
    dist = _distance_only(o[:, None, :], d[:, None, :], a[None], b[None])
    li, bi = np.nonzero(np.ones(dist.shape, dtype=bool))
    dist, lower, upper = dist.reshape(-1), (dist - eps).reshape(-1), (dist + eps).reshape(-1)
    for level in range(len(levels) + 1):
        key = li if within is not None else li * nc + bc[bi]
        keep = lower <= threshold(li, key, upper)
        li, bi = li[keep], bi[keep]
        if level == len(levels):
            break
        # children of the kept blocks at the next level (or segments)
        c, pj0, pj1 = bc[bi], j0[bi], j1[bi]
        child = sizes[level + 1] if level + 1 < len(levels) else 1
        k0 = pj0 // child
        nch = -(-(pj1 - pj0) // child)
        li = np.repeat(li, nch)
        if level + 1 < len(levels):
            _, bc, j0, j1, a, b, eps, first = levels[level + 1]
            bi = np.repeat(first[c] + k0, nch) + _expand(nch)
            dist = _distance_only(o[li], d[li], a[bi], b[bi])
            lower, upper = dist - eps[bi], dist + eps[bi]
        else:
            seg = np.repeat(contours.offsets[c] + pj0, nch) + _expand(nch)
            dist, p, q = _exact(o[li], d[li], contours.starts[seg], contours.ends[seg])
            bc = contours.segment_contour
            bi = seg
            j0 = j1 = None
            lower = upper = dist
    # the kept segments, exact: first minimum per (line, contour)
    seg = bi
    dist, p, q = dist[keep], p[keep], q[keep]
    key = li * nc + bc[seg]
    out_d = np.full((n, nc), np.inf)
    out_p = np.full((n, nc, 3), np.nan)
    out_q = np.full((n, nc, 3), np.nan)
    out_s = np.full((n, nc), -1, dtype=np.int64)
    if len(key) == 0:
        return ClosestPoints(out_d, out_p, out_q, out_s)
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    win = _group_argmin(dist, starts)
    kk = key[starts]
    out_d.reshape(-1)[kk] = dist[win]
    out_p.reshape(-1, 3)[kk] = p[win]
    out_q.reshape(-1, 3)[kk] = q[win]
    out_s.reshape(-1)[kk] = seg[win]
    return ClosestPoints(out_d, out_p, out_q, out_s)


# --------------------------------------------------------------------------- hierarchy
@dataclass(frozen=True, eq=False)
class _Hierarchy:
    """Capsule trees of all contours of a ContourSet, as Python lists for a fast heap loop.

    ``nodes[k] = (ax, ay, az, bx, by, bz, eps, left, right, segment)``; ``roots[c]`` is the
    root node of contour ``c``; leaves have ``left = right = -1`` and ``segment >= 0``.
    """

    nodes: list
    roots: list
    leaf_of_segment: list


def _point_segment_distances(x, a, b):
    e = b - a
    ee = np.einsum("ij,ij->i", e, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(ee > 0.0, np.einsum("ij,ij->i", x - a, e) / np.where(ee > 0, ee, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return np.linalg.norm(x - (a + s[:, None] * e), axis=1)


def _build_hierarchy(contours: ContourSet) -> _Hierarchy:
    """Binary capsule hierarchy by halving vertex ranges, vectorised level by level."""
    path = contours.path
    nc = contours.n_contours
    nseg = np.diff(contours.offsets)
    pbase = contours.offsets[:-1] + np.arange(nc)       # first path row of each contour
    # level arrays: lo, hi path rows (inclusive range of vertices), parent, side
    lo = pbase.copy()
    hi = pbase + nseg
    parent = np.full(nc, -1)
    side = np.zeros(nc, dtype=np.int64)
    rows_lo, rows_hi, rows_eps, rows_parent, rows_side = [], [], [], [], []
    total = 0
    while lo.size:
        cnt = hi - lo + 1
        starts = np.repeat(lo, cnt)
        idx = starts + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        owner = np.repeat(np.arange(len(lo)), cnt)
        dist = _point_segment_distances(path[idx], path[lo][owner], path[hi][owner])
        eps = np.maximum.reduceat(dist, np.r_[0, np.cumsum(cnt)[:-1]])
        eps[cnt == 2] = 0.0
        rows_lo.append(lo)
        rows_hi.append(hi)
        rows_eps.append(eps)
        rows_parent.append(parent)
        rows_side.append(side)
        ids = total + np.arange(len(lo))
        total += len(lo)
        split = hi - lo > 1
        mid = (lo + hi) // 2
        lo, hi = np.r_[lo[split], mid[split]], np.r_[mid[split], hi[split]]
        parent = np.r_[ids[split], ids[split]]
        side = np.r_[np.zeros(split.sum(), dtype=np.int64), np.ones(split.sum(), dtype=np.int64)]
    lo = np.concatenate(rows_lo)
    hi = np.concatenate(rows_hi)
    eps = np.concatenate(rows_eps)
    parent = np.concatenate(rows_parent)
    side = np.concatenate(rows_side)
    m = len(lo)
    left = np.full(m, -1)
    right = np.full(m, -1)
    has = parent >= 0
    left[parent[has & (side == 0)]] = np.flatnonzero(has & (side == 0))
    right[parent[has & (side == 1)]] = np.flatnonzero(has & (side == 1))
    # path row -> global segment: row r of contour c is segment r - c (rows skip one per contour)
    row_contour = np.repeat(np.arange(nc), nseg + 1)
    segment = np.where(hi - lo == 1, lo - row_contour[lo], -1)
    a, b = path[lo], path[hi]
    nodes = list(zip(*(a.T.tolist()), *(b.T.tolist()), eps.tolist(), left.tolist(),
                     right.tolist(), segment.tolist()))
    leaf_of_segment = [0] * contours.n_segments
    for k in np.flatnonzero(segment >= 0).tolist():
        leaf_of_segment[segment[k]] = k
    return _Hierarchy(nodes=nodes, roots=list(range(nc)), leaf_of_segment=leaf_of_segment)


def _seg_line(node, ox, oy, oz, dx, dy, dz):
    """Distance (mm) from the line to the axis segment of ``node``."""
    return line_segment_distance(ox, oy, oz, dx, dy, dz, node[0], node[1], node[2],
                                 node[3], node[4], node[5])


def _search(h: _Hierarchy, root: int, line, upper: float, warm_leaf: int):
    """Best-first search for one line and one contour; returns (leaf node, r)."""
    nodes = h.nodes
    ox, oy, oz, dx, dy, dz = line
    slack = 1e-9
    best_leaf = warm_leaf
    node = nodes[root]
    d = _seg_line(node, ox, oy, oz, dx, dy, dz)
    heap = [(d - node[6], d + node[6], root)]
    while heap:
        lower, up, k = heapq.heappop(heap)
        node = nodes[k]
        if node[9] >= 0:                       # a single segment: exact and lowest
            if heap:
                nl, nu, _ = heap[0]
                r = 0.5 * (nl - up)
            else:
                r = math.inf
            return k, r
        for child in (node[7], node[8]):
            cn = nodes[child]
            dc = _seg_line(cn, ox, oy, oz, dx, dy, dz)
            lc = dc - cn[6]
            if lc <= upper + slack:
                heapq.heappush(heap, (lc, dc + cn[6], child))
                if cn[9] >= 0 and dc < upper:
                    upper = dc
                    best_leaf = child
    return best_leaf, math.inf


def _closest_hierarchy(contours: ContourSet, o, d) -> ClosestPoints:
    h = _build_hierarchy(contours)
    n, nc = len(o), contours.n_contours
    seg = np.empty((n, nc), dtype=np.int64)
    reuse = np.empty((n, nc))
    lines = np.hstack([o, d]).tolist()
    nodes = h.nodes
    for c in range(nc):
        root = h.roots[c]
        prev_leaf = -1
        for i, line in enumerate(lines):
            if prev_leaf >= 0:
                upper = _seg_line(nodes[prev_leaf], *line)
            else:
                upper = math.inf
            leaf, r = _search(h, root, line, upper, prev_leaf)
            seg[i, c] = nodes[leaf][9]
            reuse[i, c] = r
            prev_leaf = leaf
    return _finish(contours, o, d, seg, reuse)


_METHODS = {
    "compiled": _closest_compiled,
    "blocks": _closest_blocks,
    "dense": _closest_dense,
    "hierarchy": _closest_hierarchy,
    "reference": _closest_reference,
}


def closest_points(contours: ContourSet, origins, directions, *,
                   method: Method = "blocks", within_mm: float | None = None) -> ClosestPoints:
    """Closest point of every contour to every line (paper Step A), exactly.

    Parameters
    ----------
    contours : ContourSet (mm, same frame as the lines).
    origins, directions : (N, 3) mm and unit; lines sorted so that neighbours follow each
        other help ``"hierarchy"`` (warm start), and do not matter to the others.
    method : "blocks" (default: capsule hierarchy pruned level by level for all lines,
        vectorised), "compiled" (the same bounds in numba, a loop per line: 3-5x faster
        than "blocks" on the registration's contours; the registration's default),
        "dense" (all pairs by matrix products), "hierarchy" (the paper's capsule tree and
        priority queue, pure Python) or "reference" (plain brute force). See the module docstring.
    within_mm : only with "blocks" and "compiled": per line, contours farther than
        ``max(within_mm, distance to the nearest contour)`` are not computed and come back
        at ``inf`` distance (NaN points, segment -1). The nearest contour and every contour
        within ``within_mm`` are exact. This is all that :func:`select_contours` needs
        (with ``max_stab_distance_mm = within_mm``) and prunes most of the work.

    Returns
    -------
    ClosestPoints with ``(N, C)`` arrays; with no contour, ``(N, 0)`` arrays.
    """
    if method not in _METHODS:
        raise ValueError(f"method: expected one of {sorted(_METHODS)}, got {method!r}")
    o, d = _check(contours, origins, directions)
    if contours.n_contours == 0 or len(o) == 0:
        return _empty(len(o), contours.n_contours)
    if within_mm is not None:
        if method not in ("blocks", "compiled"):
            raise ValueError(f"within_mm is only supported by methods 'compiled' and 'blocks', "
                             f"not {method!r}")
        if not within_mm >= 0:
            raise ValueError(f"within_mm: expected a distance >= 0 mm, got {within_mm}")
        return _METHODS[method](contours, o, d, within=float(within_mm))
    return _METHODS[method](contours, o, d)


# --------------------------------------------------------------------------- step B
def stabbing(cp: ClosestPoints, contours: ContourSet, directions) -> np.ndarray:
    """Which contours each line stabs: ``(N, C)`` bool.

    Line n stabs contour c when ``q - p``, the oriented contour direction at ``p``
    (:meth:`ContourSet.tangents`) and the line direction form a right-handed frame:
    ``det[q - p, e, d] > 0``. For a contour with the
    visible triangles on its left this means the line passes on the side of the contour
    where the surface projects (it "enters" the surface's image).
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.shape != (cp.distance.shape[0], 3):
        raise ValueError(f"directions: expected shape {(cp.distance.shape[0], 3)}, got {d.shape}")
    if cp.distance.shape[1] == 0:
        return np.zeros(cp.distance.shape, dtype=bool)
    valid = cp.segment >= 0
    li, ci = np.nonzero(valid)
    e = contours.tangents(cp.segment[li, ci], cp.p[li, ci])
    det = np.einsum("kj,kj->k", cp.q[li, ci] - cp.p[li, ci], np.cross(e, d[li]))
    out = np.zeros(valid.shape, dtype=bool)
    out[li, ci] = det > 0.0
    return out


def select_contours(cp: ClosestPoints, contours: ContourSet, directions, external=None, *,
                    max_stab_distance_mm: float = np.inf) -> np.ndarray:
    """The paper's selection of one contour per line: ``(N,)`` int64 contour index.

    For a line from an *external* bone-contour pixel (``external[n]`` True): among the
    contours it stabs, the farthest one; if it stabs none, the closest one. For the other
    lines (internal contour pixels), the closest contour. -1 when there is no contour.

    Parameters
    ----------
    cp : ClosestPoints of these lines and ``contours``.
    directions : (N, 3) unit directions of the lines.
    external : (N,) bool or None (None: every line is external).
    max_stab_distance_mm : stabbed contours farther than this are not counted as stabbed
        (default: no limit, the paper's rule).
    """
    n, c = cp.distance.shape
    if c == 0:
        return np.full(n, -1, dtype=np.int64)
    ext = np.ones(n, dtype=bool) if external is None else np.asarray(external, dtype=bool)
    if ext.shape != (n,):
        raise ValueError(f"external: expected shape ({n},), got {ext.shape}")
    closest = np.argmin(cp.distance, axis=1)
    st = stabbing(cp, contours, directions) & (cp.distance <= max_stab_distance_mm)
    far = np.argmax(np.where(st, cp.distance, -np.inf), axis=1)
    use_far = ext & st.any(axis=1)
    return np.where(use_far, far, closest).astype(np.int64)


def match_contours(contours: ContourSet, origins, directions, external=None, *,
                   within_mm: float | None = None, max_stab_distance_mm: float = np.inf):
    """Steps A and B in one compiled pass (:func:`reglib._closest_numba.match_lines`): for
    each line the contour :func:`select_contours` takes and the closest point and tangent
    there. Equal to :func:`closest_points` (``method="compiled"``, ``within_mm``), then
    :func:`select_contours` and :meth:`ContourSet.tangents` at the selected points (the
    reference, compared in tests), without the ``(N, C)`` tables.

    Parameters as in those functions (``within_mm`` as in :func:`closest_points`; None for
    no threshold). Returns ``(sel (N,), segment (N,), points (N, 3), tangents (N, 3))``:
    contour index (-1 with no contour), segment (-1: none), mm and unit vectors (NaN where
    no segment was found).
    """
    o, d = _check(contours, origins, directions)
    n = len(o)
    ext = np.ones(n, dtype=bool) if external is None else np.asarray(external, dtype=bool)
    if ext.shape != (n,):
        raise ValueError(f"external: expected shape ({n},), got {ext.shape}")
    if within_mm is not None and not within_mm >= 0:
        raise ValueError(f"within_mm: expected a distance >= 0 mm, got {within_mm}")
    return _match_contours(contours, o, d, ext, within_mm, max_stab_distance_mm)


def _match_contours(contours: ContourSet, o, d, ext, within_mm, max_stab_distance_mm):
    """:func:`match_contours` on checked input: ``o, d`` (N, 3) float64 lines with unit
    directions, ``ext`` (N,) bool (the registration loop's lines, checked once by its
    views and moved rigidly)."""
    from reglib._closest_numba import match_lines

    n = len(o)
    if contours.n_contours == 0 or n == 0:
        return (np.full(n, -1, dtype=np.int64), np.full(n, -1, dtype=np.int64),
                np.full((n, 3), np.nan), np.full((n, 3), np.nan))
    blocks, spheres = _compiled_capsules(contours)
    return match_lines(np.ascontiguousarray(o), np.ascontiguousarray(d),
                       np.ascontiguousarray(contours.starts), np.ascontiguousarray(contours.ends),
                       contours._unit, contours.segment_contour,
                       np.ascontiguousarray(contours.offsets),
                       np.ascontiguousarray(contours.closed), *blocks,
                       -1.0 if within_mm is None else float(within_mm), *spheres,
                       np.ascontiguousarray(ext), float(max_stab_distance_mm))
