"""Bone surfaces from stacks of CT contours: tiling by dynamic programming, simplification.

Tiling (NOTES.md s2). Two adjacent closed contours A (m vertices, lower slice) and B (n
vertices, upper slice), both counter-clockwise seen from +z, each rolled so that vertex 0 of
each is a closest pair. A strip of m + n triangles between them is a monotone path on the
(m + 1) x (n + 1) grid graph from (0, 0) to (m, n): a step in i adds the triangle
(A_i, A_i+1, B_j), a step in j adds (A_i, B_j+1, B_j). Dynamic programming over the grid's
anti-diagonals finds the path of least total cost: the triangle area (``quality="area"``) or
minus the compactness (``"compactness"``: 4 sqrt(3) area / sum of squared sides, 1 for an
equilateral triangle). :func:`tile_pair` with ``method="brute_force"`` enumerates every path
(small contours only) and is the reference of the tests.

Branching (one contour above two, as at the condyles): the two contours are joined into one
by a bridge between their closest vertices (traversed once each way), and that keyhole contour
is tiled with the single one; the bridge edge gets one triangle from each side of the strip,
so the surface stays manifold. A branch is made only when the single contour overlaps both
(seen from above, :func:`contours_overlap`); when it overlaps one of them alone, as where
the lowest slice of a real femur cuts one condyle and the next one both, it is tiled with
that one and the other starts there as an open end (bridging it would join a condyle to
its neighbour's tip and give edges of four triangles). Other counts (three cross-sections in
a slice, as a ridge or an osteophyte of a real femur can make) are grouped by overlap: the
contours of each group are bridged into one loop per slice, nearest first, never at the ends
of the bridge the same slice got for its other strip. The result is a consistently oriented
manifold surface with boundary (normals point out of the bone); its ends are open.

Simplification within a tolerance, verified afterwards with exact closest points (and backed
off when over): by default each contour is reduced (Douglas-Peucker, scikit-image) and the
reduced contours tiled again, which keeps the surface manifold by construction; or quadric
edge collapse (``fast_simplification``, boundary kept) on the tiled surface, accepted only
when the result is still a manifold.

Nothing here sees the simulator: contours in, vertices (V, 3) mm and faces (F, 3) out.
"""

from __future__ import annotations

import itertools
import operator
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import fast_simplification
import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from reglib.contours import _polygon_area, contours_from_ct
from reglib.geometry import as_faces, as_points

__all__ = [
    "SURFACE_SIMPLIFY_TOL_MM",
    "Surface",
    "bridge_contours",
    "check_manifold",
    "contours_overlap",
    "points_in_polygon",
    "simplify_surface",
    "surface_distances",
    "surface_distances_fast",
    "surface_from_contours",
    "surface_from_ct",
    "tile_pair",
    "tileable_contours",
]

Quality = Literal["area", "compactness"]
#: simplification tolerance of the CT surfaces (mm); the paper simplified within 0.0-0.3 mm
SURFACE_SIMPLIFY_TOL_MM = 0.3


@dataclass(frozen=True)
class Surface:
    """A triangulated surface (mm, in the frame of its contours, the ct frame for CT).

    ``vertices`` (V, 3) float64; ``faces`` (F, 3) int64, counter-clockwise seen from outside
    the bone; ``info``: counts and tolerances of how it was made.
    """

    vertices: np.ndarray
    faces: np.ndarray
    info: dict = field(default_factory=dict)

    @property
    def n_triangles(self) -> int:
        return int(len(self.faces))


# --------------------------------------------------------------------------- helpers
def _as_contour(c, name: str) -> np.ndarray:
    p = np.asarray(c, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: a contour must have shape (K, 3) in mm, got {p.shape}")
    if len(p) < 3:
        raise ValueError(f"{name}: a contour needs at least 3 points, got {len(p)}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contour contains NaN or infinite values")
    return p


def _ccw(idx: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return idx if _polygon_area(pts[idx]) >= 0 else idx[::-1]


def _tri_cost(p, q, r, quality: Quality, *, reference: bool = False) -> np.ndarray:
    """Cost of the triangles ``(p, q, r)`` (broadcast (..., 3) arrays, mm). The area is
    made from the coordinates' planes ((...) arrays, contiguous): np.cross's and
    np.linalg.norm's products, differences and sum in their order, so the same bits (the
    interleaved (..., 3) arrays were 0.13 s of a run's 384 calls); ``reference=True`` runs
    np.cross and np.linalg.norm (compared in tests)."""
    if quality == "area" and not reference:
        p, q, r = np.asarray(p), np.asarray(q), np.asarray(r)
        a0, a1, a2 = (q[..., k] - p[..., k] for k in range(3))      # e1
        b0, b1, b2 = (r[..., k] - p[..., k] for k in range(3))      # e2
        c = a1 * b2
        c -= a2 * b1
        s = c * c
        np.multiply(a2, b0, out=c)
        c -= a0 * b2
        s += c * c
        np.multiply(a0, b1, out=c)
        c -= a1 * b0
        s += c * c
        np.sqrt(s, out=s)
        s *= 0.5
        return s
    e1, e2 = q - p, r - p
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=-1)
    if quality == "area":
        return area
    if quality == "compactness":
        s = np.sum(e1**2, -1) + np.sum(e2**2, -1) + np.sum((r - q) ** 2, -1)
        return -4.0 * np.sqrt(3.0) * area / np.maximum(s, 1e-300)
    raise ValueError(f"quality must be 'area' or 'compactness', got {quality!r}")


def _cost_tables(a: np.ndarray, b: np.ndarray, quality: Quality):
    """cost_i[i, j] of step (i, j) -> (i+1, j); cost_j[i, j] of step (i, j) -> (i, j+1)."""
    m, n = len(a), len(b)
    ai = a[np.arange(m + 1) % m]
    bj = b[np.arange(n + 1) % n]
    cost_i = _tri_cost(ai[:m, None], ai[1:, None], bj[None, :], quality)          # (m, n+1)
    cost_j = _tri_cost(ai[:, None], bj[None, 1:], bj[None, :n], quality)          # (m+1, n)
    return cost_i, cost_j


def _dp(cost_i: np.ndarray, cost_j: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-cost monotone path; returns (cost, steps) with steps[k] = 0 (i) or 1 (j).

    Compiled (:func:`reglib._surface_numba.dp_kernel`); :func:`_dp_numpy` is the same
    recursion by anti-diagonals in numpy and :func:`_brute_force` enumerates every path on
    small cases (both compared in ``tests/reglib/test_surface.py``). Ties go to the step in
    i, as in both.
    """
    from reglib._surface_numba import dp_kernel

    total, steps = dp_kernel(np.ascontiguousarray(cost_i, dtype=np.float64),
                             np.ascontiguousarray(cost_j, dtype=np.float64))
    return float(total), steps


def _dp_numpy(cost_i: np.ndarray, cost_j: np.ndarray) -> tuple[float, np.ndarray]:
    """:func:`_dp` in numpy, one anti-diagonal at a time (the reference)."""
    m, n = cost_i.shape[0], cost_j.shape[1]
    total = np.full((m + 1, n + 1), np.inf)
    came_j = np.zeros((m + 1, n + 1), dtype=bool)
    total[0, 0] = 0.0
    for d in range(1, m + n + 1):
        i = np.arange(max(0, d - n), min(m, d) + 1)
        j = d - i
        from_i = np.full(len(i), np.inf)
        ok = i > 0
        from_i[ok] = total[i[ok] - 1, j[ok]] + cost_i[i[ok] - 1, j[ok]]
        from_j = np.full(len(i), np.inf)
        ok = j > 0
        from_j[ok] = total[i[ok], j[ok] - 1] + cost_j[i[ok], j[ok] - 1]
        use_j = from_j < from_i
        total[i, j] = np.where(use_j, from_j, from_i)
        came_j[i, j] = use_j
    from reglib._surface_numba import backtrack

    return float(total[m, n]), backtrack(came_j)


def _brute_force(cost_i: np.ndarray, cost_j: np.ndarray) -> tuple[float, np.ndarray]:
    m, n = cost_i.shape[0], cost_j.shape[1]
    if m + n > 22:
        raise ValueError(f"brute force tiling is for small contours only (m + n = {m + n})")
    best, best_steps = np.inf, None
    for js in itertools.combinations(range(m + n), n):
        steps = np.zeros(m + n, dtype=np.int8)
        steps[list(js)] = 1
        i = j = 0
        c = 0.0
        for s in steps:
            if s:
                c += cost_j[i, j]
                j += 1
            else:
                c += cost_i[i, j]
                i += 1
        if c < best:
            best, best_steps = c, steps
    return float(best), best_steps


def _closest_pair(a: np.ndarray, b: np.ndarray) -> tuple[int, int]:
    d, j = cKDTree(b).query(a)
    i = int(np.argmin(d))
    return i, int(j[i])


def tile_pair(a, b, *, quality: Quality = "area", method: Literal["dp", "brute_force"] = "dp",
              start: tuple[int, int] | None = None):
    """Tile two closed contours with a strip of triangles.

    Parameters
    ----------
    a, b : (m, 3) and (n, 3) arrays, mm: the lower and the upper contour (any direction; they
        are used counter-clockwise seen from +z).
    quality : "area" (minimise the total area) or "compactness" (maximise the total).
    method : "dp" (dynamic programming, O(mn)) or "brute_force" (every path; m + n <= 22).
    start : indices of the starting pair; default a closest pair.

    Returns
    -------
    faces : (m + n, 3) int array of indices into ``vstack([a, b])`` (b's indices offset by
        m), oriented so that the normals point away from the contours' inside.
    cost : the total cost of the strip (area in mm^2, or minus the total compactness).
    """
    if method not in ("dp", "brute_force"):
        raise ValueError(f"tile_pair: method must be 'dp' or 'brute_force', got {method!r}")
    if quality not in ("area", "compactness"):
        raise ValueError(f"tile_pair: quality must be 'area' or 'compactness', got {quality!r}")
    a = _as_contour(a, "tile_pair a")
    b = _as_contour(b, "tile_pair b")
    if start is not None:
        try:
            s0, s1 = (operator.index(i) for i in start)
        except (TypeError, ValueError):
            raise ValueError(f"tile_pair: start must be a pair of vertex indices, got "
                             f"{start!r}") from None
        if not (0 <= s0 < len(a) and 0 <= s1 < len(b)):
            raise ValueError(f"tile_pair: start {start!r} is outside the contours' "
                             f"{len(a)} and {len(b)} vertices")
    ia = _ccw(np.arange(len(a)), a)
    ib = _ccw(np.arange(len(b)), b)
    if start is not None:
        start = (int(start[0]), int(start[1]) + len(a))
    return _tile_indices(ia, ib + len(a), np.vstack([a, b]), quality, method, start)


def _tile_indices(ia, ib, pts, quality, method, start):
    """Tile the index loops ``ia`` (lower) and ``ib`` (upper) into ``pts``; (faces, cost)."""
    pa, pb = pts[ia], pts[ib]
    if start is None:
        i0, j0 = _closest_pair(pa, pb)
    else:
        i0 = int(np.flatnonzero(ia == start[0])[0])
        j0 = int(np.flatnonzero(ib == start[1])[0])
    ia, ib = np.roll(ia, -i0), np.roll(ib, -j0)
    pa, pb = pts[ia], pts[ib]
    cost_i, cost_j = _cost_tables(pa, pb, quality)
    cost, steps = (_dp if method == "dp" else _brute_force)(cost_i, cost_j)
    la, lb = len(ia), len(ib)
    faces = np.empty((la + lb, 3), dtype=np.int64)
    i = j = 0
    for k, s in enumerate(steps):
        if s == 0:
            faces[k] = (ia[i % la], ia[(i + 1) % la], ib[j % lb])
            i += 1
        else:
            faces[k] = (ia[i % la], ib[(j + 1) % lb], ib[j % lb])
            j += 1
    return faces, cost


def bridge_contours(pts: np.ndarray, idx1: np.ndarray, idx2: np.ndarray) -> np.ndarray:
    """Join two counter-clockwise index loops into pts (V, 3) by a bridge between their
    closest vertices; returns the keyhole loop (the two bridge vertices appear twice)."""
    return bridge_loops(pts, [np.asarray(idx1), np.asarray(idx2)])


# --------------------------------------------------------------------------- surfaces
def _slice_list(slices) -> list[list[np.ndarray]]:
    out = []
    for k, s in enumerate(slices):
        cs = s.contours_ct if hasattr(s, "contours_ct") else s
        if isinstance(cs, np.ndarray) and cs.ndim == 2:
            cs = [cs]
        out.append([_as_contour(c, f"slice {k}, contour {j}") for j, c in enumerate(cs)])
        if not out[-1]:
            raise ValueError(f"slice {k} holds no contour")
    return out


def surface_from_contours(slices, *, quality: Quality = "area",
                          simplify_tol_mm: float | None = None,
                          simplify: Literal["contours", "quadric"] = "contours") -> Surface:
    """Tile a stack of slice contours into one surface, optionally simplified.

    Parameters
    ----------
    slices : sequence over slices (increasing z) of sequences of (K, 3) contours in mm (or
        :class:`reglib.contours.SliceContours`). Between neighbours, one contour is tiled
        with one, two with two when their nearest centroids pair contours that overlap,
        one with two by a bridge (branching); any other counts by their overlaps: each
        group of contours that overlap across the two slices is joined into one loop per
        slice by bridges, and a contour overlapping none is an open end.
    quality : tiling quality, "area" or "compactness".
    simplify_tol_mm : if given (0-0.3 mm is the paper's range), simplify within it.
    simplify : "contours" (default): every contour is reduced by Douglas-Peucker
        (``skimage.measure.approximate_polygon``) and the reduced contours are tiled again,
        the contour tolerance backed off until every vertex of the full surface lies within
        ``simplify_tol_mm`` of the result (the result's vertices lie on the full surface:
        they are a subset of its vertices); always a manifold. "quadric": edge collapse on
        the full surface, :func:`simplify_surface`.

    Returns
    -------
    Surface with ``info`` keys ``n_slices``, ``n_triangles_tiled``, ``simplify_tol_mm``,
    ``hausdorff_mm`` (the verified distance, 0 if not simplified), ``left_out_z_mm``: the
    z of slices left out when the whole stack could not be tiled because some slices'
    contours continue no neighbour's (the largest run of slices that continue one another
    is tiled; empty when none was left out).
    """
    stack = _slice_list(slices)
    if len(stack) < 2:
        raise ValueError(f"a surface needs at least 2 slices of contours, got {len(stack)}")
    z = [np.mean(np.concatenate(s)[:, 2]) for s in stack]
    if np.any(np.diff(z) <= 0):
        raise ValueError("slices must be given in order of increasing z")
    try:
        vertices, faces = _tile_stack(stack, quality)
        left_out = ()
    except ValueError:
        # a slice whose contours continue none of its neighbours' (a streak or a blob
        # outlined beyond the bone's end: a review's CT threshold of 150 HU, 2026-11-27)
        # ended the whole surface; the bone's own stack is tiled without it
        keep = _connected_slices(stack)
        if keep is None:
            raise
        left_out = tuple(float(z[k]) for k in range(len(stack)) if k not in keep)
        stack = [stack[k] for k in keep]
        vertices, faces = _tile_stack(stack, quality)
    surf = Surface(vertices, faces, {"n_slices": len(stack), "n_triangles_tiled": len(faces),
                                     "simplify_tol_mm": 0.0, "hausdorff_mm": 0.0,
                                     "left_out_z_mm": left_out})
    if simplify_tol_mm is not None and (isinstance(simplify_tol_mm, bool) or not isinstance(
            simplify_tol_mm, int | float | np.number) or not np.isfinite(simplify_tol_mm)):
        raise ValueError("surface_from_contours: simplify_tol_mm: expected a number of mm in "
                         f"[0, 5] or None, got {simplify_tol_mm!r}")
    if not simplify_tol_mm:
        return surf
    if simplify == "quadric":
        return simplify_surface(surf, simplify_tol_mm)
    if simplify != "contours":
        raise ValueError(f"simplify must be 'contours' or 'quadric', got {simplify!r}")
    if not 0 < simplify_tol_mm <= 5.0:
        raise ValueError(f"simplify tolerance must be in [0, 5] mm, got {simplify_tol_mm}")
    used = _used_points(vertices, faces)
    for frac in (1.0, 0.7, 0.5, 0.3):
        reduced = [[_decimate(c, frac * simplify_tol_mm) for c in s] for s in stack]
        try:
            v, f = _tile_stack(reduced, quality)
        except ValueError:  # a reduced contour that no strip tiles: reduce it less
            continue
        # The tolerance is measured at the data: the contour points (the full surface's
        # vertices) that its triangles use (_used_points). Between slices both surfaces
        # only interpolate the contours.
        h = float(surface_distances_fast(used, v, f, tol_mm=simplify_tol_mm).max())
        if h <= simplify_tol_mm:
            return Surface(v, f, dict(surf.info, simplify_tol_mm=simplify_tol_mm,
                                      hausdorff_mm=h, contour_tol_mm=frac * simplify_tol_mm))
    return surf


def _connected_slices(stack) -> list[int] | None:
    """The slices of the stack's largest run of slices that continue one another, each
    with a contour that overlaps one of the next slice's (seen along z); the run with the
    most contour area. None when every slice continues the next (nothing to leave out) or
    the run has fewer than 2 slices."""
    joined = [any(contours_overlap(a, b) for a in stack[k] for b in stack[k + 1])
              for k in range(len(stack) - 1)]
    if all(joined):
        return None
    runs, run = [], [0]
    for k, j in enumerate(joined):
        if j:
            run.append(k + 1)
        else:
            runs.append(run)
            run = [k + 1]
    runs.append(run)
    best = max(runs, key=lambda r: sum(abs(_polygon_area(c[:, :2])) for k in r
                                       for c in stack[k]))
    return best if len(best) >= 2 else None


def _decimate(c: np.ndarray, tol_mm: float, *, reference: bool = False) -> np.ndarray:
    """Douglas-Peucker reduction of a closed planar contour (K, 3) to within ``tol_mm``
    (compiled, :func:`reglib._surface_numba.douglas_peucker`; ``reference=True``:
    scikit-image's ``approximate_polygon``, whose module's import of scipy.signal alone
    took 0.5 s of a ``testbed run``)."""
    closed = np.vstack([c[:, :2], c[:1, :2]])
    if reference:
        from skimage.measure import approximate_polygon

        keep = approximate_polygon(closed, tolerance=tol_mm)[:-1]
        if len(keep) < 3:
            return c
        # approximate_polygon returns a subset of the input points: find their indices.
        _, idx = cKDTree(c[:, :2]).query(keep)
        idx = np.unique(idx)
    else:
        from reglib._surface_numba import douglas_peucker

        if not tol_mm > 0:
            return c
        idx = np.flatnonzero(douglas_peucker(np.ascontiguousarray(closed), float(tol_mm))[:-1])
    return c[idx] if len(idx) >= 3 else c


def _tile_stack(stack, quality):
    verts, offsets = [], []
    n = 0
    for s in stack:
        offs = []
        for c in s:
            offs.append(n)
            verts.append(c)
            n += len(c)
        offsets.append(offs)
    vertices = np.vstack(verts)
    loops = [[_ccw(np.arange(len(c)) + o, vertices) for c, o in zip(s, offs, strict=True)]
             for s, offs in zip(stack, offsets, strict=True)]
    faces = []
    ends: set[int] = set()   # the vertices that end a bridge already (a slice is bridged
    for k in range(len(stack) - 1):   # for the strip below it and again for the one above)
        for group in _match(loops[k], loops[k + 1], vertices, k):
            faces.append(_tile_group(*group, vertices, quality, ends))
    return vertices, np.vstack(faces)


def _tile_group(lo: list, hi: list, vertices, quality, ends: set) -> np.ndarray:
    """The strip between the loops ``lo`` of one slice and ``hi`` of the next (a group of
    :func:`_match`): each side bridged into one loop (:func:`bridge_loops`, avoiding and
    then adding to the bridge ends ``ends``). When the bridged loops cannot be tiled into a
    manifold strip, the largest loop of each side alone, if they overlap (the others are
    then open ends there)."""
    la, lb = (bridge_loops(vertices, x, avoid=ends) for x in (lo, hi))
    try:
        faces = _tile_strip(la, lb, vertices, quality)
    except ValueError:
        if len(lo) == len(hi) == 1:
            raise
        a, b = (max(x, key=lambda c: abs(_polygon_area(vertices[c]))) for x in (lo, hi))
        if not contours_overlap(vertices[a], vertices[b]):
            raise
        return _tile_strip(a, b, vertices, quality)
    for loop in (la, lb):    # a bridge end appears twice in its loop
        _, inverse, counts = np.unique(loop, return_inverse=True, return_counts=True)
        ends.update(loop[counts[inverse] > 1].tolist())
    return faces


def _strip_is_manifold(faces: np.ndarray) -> bool:
    """No edge of the strip in more than two of its triangles (edges as sorted 1-D keys: a
    key three times in a row is an edge of three or more)."""
    a = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2]])
    b = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    keys = np.sort(np.minimum(a, b) * (int(faces.max()) + 1) + np.maximum(a, b))
    return not bool(np.any(keys[2:] == keys[:-2]))


def _tile_strip(la, lb, vertices, quality, tries: int = 8) -> np.ndarray:
    """The least-cost strip between two loops from their closest pair; if its path runs
    along one loop from the start and back to the same vertices at the end (the cross edge
    to vertex 0 of a loop met twice: four triangles on one edge, seen on a snake contour
    that crossed itself on a grazed condyle), the strip from other start pairs: ``tries``
    vertices evenly around the longer loop, each with its closest vertex on the other."""
    faces = _tile_indices(la, lb, vertices, quality, "dp", None)[0]
    if _strip_is_manifold(faces):
        return faces
    if len(la) * len(lb) <= 256:  # small loops (e.g. simplified): every start pair
        starts = list(itertools.product(la.tolist(), lb.tolist()))
    else:
        swap = len(lb) > len(la)
        long_, short = (lb, la) if swap else (la, lb)
        starts = []
        for i in np.linspace(0, len(long_), tries, endpoint=False).astype(int):
            j = int(np.argmin(np.linalg.norm(vertices[short] - vertices[long_[i]], axis=1)))
            starts.append((short[j], long_[i]) if swap else (long_[i], short[j]))
    best = None
    for start in starts:
        f, cost = _tile_indices(la, lb, vertices, quality, "dp", start)
        if _strip_is_manifold(f) and (best is None or cost < best[1]):
            best = (f, cost)
    if best is None:
        raise ValueError("two contours cannot be tiled into a manifold strip from any of "
                         f"{len(starts) + 1} start pairs (a contour may cross itself)")
    return best[0]


def _match(lo, hi, vertices, k) -> list[tuple[list, list]]:
    """The groups of index loops to tile between slice k and k + 1, each ``(loops of slice
    k, loops of slice k + 1)``: one to one; two to two when their nearest centroids pair
    contours that overlap; one to two (a branching, the two bridged when the one overlaps
    both, else the one with the one it overlaps); any other counts by their overlaps
    (:func:`_match_overlaps`)."""
    if len(lo) == 1 and len(hi) == 1:
        return [([lo[0]], [hi[0]])]
    if len(lo) == len(hi) == 2:
        cl = np.array([vertices[x].mean(axis=0) for x in lo])
        ch = np.array([vertices[x].mean(axis=0) for x in hi])
        order = [int(np.argmin(np.linalg.norm(ch[:, :2] - c[:2], axis=1))) for c in cl]
        pairs = [([lo[i]], [hi[o]]) for i, o in enumerate(order)]
        if len(set(order)) == len(order) and all(
                contours_overlap(vertices[a[0]], vertices[b[0]]) for a, b in pairs):
            return pairs
        return _match_overlaps(lo, hi, vertices, k)
    if sorted((len(lo), len(hi))) == [1, 2]:
        one, two = (lo[0], hi) if len(lo) == 1 else (hi[0], lo)
        meets = [contours_overlap(vertices[one], vertices[c]) for c in two]
        if meets[0] != meets[1]:  # the single contour continues one of the two only
            match = two[0] if meets[0] else two[1]
            return [([lo[0]], [match]) if len(lo) == 1 else ([match], [hi[0]])]
        return [(list(lo), list(hi))]
    return _match_overlaps(lo, hi, vertices, k)


def _match_overlaps(lo, hi, vertices, k) -> list[tuple[list, list]]:
    """:func:`_match` for any counts of contours: the groups of contours that overlap (seen
    along z; the connected parts of the graph whose edges join a contour of slice k to one
    of slice k + 1 that it overlaps). A contour that overlaps none of the other slice is an
    open end there (a branch that starts or stops between the slices, as a condyle's tip or
    a ridge that a slice cuts off). ``ValueError`` when no contour of one slice overlaps one
    of the other."""
    n_lo = len(lo)
    parent = list(range(n_lo + len(hi)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, a in enumerate(lo):
        for j, b in enumerate(hi):
            if contours_overlap(vertices[a], vertices[b]):
                parent[root(i)] = root(n_lo + j)
    groups: dict[int, tuple[list, list]] = {}
    for i in range(len(parent)):
        side = 0 if i < n_lo else 1
        groups.setdefault(root(i), ([], []))[side].append(lo[i] if side == 0 else hi[i - n_lo])
    pairs = [g for g in groups.values() if g[0] and g[1]]
    if not pairs:
        raise ValueError(f"slices {k} and {k + 1} hold {len(lo)} and {len(hi)} contours, and "
                         "none of one slice overlaps one of the other (seen along z)")
    return pairs


def bridge_loops(pts: np.ndarray, loops: list[np.ndarray], *, avoid=()) -> np.ndarray:
    """One index loop from several counter-clockwise ones into ``pts`` (V, 3): starting from
    the first, each time the nearest remaining loop is bridged to it as
    :func:`bridge_contours` does, between the closest vertices that the joined loop holds
    once and that are not in ``avoid`` (a set of vertex indices: the ends of the bridges
    the same contours got for the strip on their other side, which would otherwise be
    chosen again and give the bridge's edge four triangles) where such vertices exist."""
    def usable(loop):   # positions of the loop's vertices a bridge may end at
        _, inverse, counts = np.unique(loop, return_inverse=True, return_counts=True)
        ok = (counts[inverse] == 1) & ~np.isin(loop, list(avoid))
        return np.flatnonzero(ok) if ok.any() else np.arange(len(loop))

    rest = list(loops)
    out = rest.pop(0)
    while rest:
        at_out = usable(out)
        tree = cKDTree(pts[out[at_out]])
        dist = [float(tree.query(pts[c[usable(c)]])[0].min()) for c in rest]
        nxt = rest.pop(int(np.argmin(dist)))
        at_nxt = usable(nxt)
        i, j = _closest_pair(pts[out[at_out]], pts[nxt[at_nxt]])
        l1 = np.roll(out, -int(at_out[i]))
        l2 = np.roll(nxt, -int(at_nxt[j]))
        out = np.concatenate([l1, l1[:1], l2, l2[:1]])
    return out


def points_in_polygon(points_xy, polygon_xy) -> np.ndarray:
    """Which of ``points_xy`` (N, 2) lie inside the closed polygon ``polygon_xy`` (K, 2)
    (crossing number; either orientation; a point on an edge may go either way)."""
    p = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    a = np.asarray(polygon_xy, dtype=np.float64).reshape(-1, 2)
    b = np.roll(a, -1, axis=0)
    x, y = p[:, :1], p[:, 1:]
    straddle = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[None, :, 0] + (y - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (
            b[None, :, 1] - a[None, :, 1])
    return np.count_nonzero(straddle & (x < x_cross), axis=1) % 2 == 1


def contours_overlap(c1, c2) -> bool:
    """Whether two closed contours (K, 2 or 3; their xy, seen along z) overlap: a vertex of
    either lies inside the other."""
    c1, c2 = np.asarray(c1)[:, :2], np.asarray(c2)[:, :2]
    return bool(points_in_polygon(c1, c2).any() or points_in_polygon(c2, c1).any())


def check_manifold(vertices, faces) -> dict:
    """Edge and orientation checks of a triangulated surface with boundary.

    Returns a dict: ``max_faces_per_edge`` (<= 2 for a manifold), ``oriented`` (every interior
    edge used once in each direction), ``boundary_edges``, ``single_fan`` (each vertex's
    triangles form one fan), ``manifold`` (all of these hold).
    """
    f = as_faces(faces, len(as_points(vertices, "vertices")))
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    und = np.sort(e, axis=1)
    _, inv, cnt = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    directed, dcnt = np.unique(e, axis=0, return_counts=True)
    oriented = bool(dcnt.max() == 1)
    # Vertex fans: the incidences (vertex v, triangle t) of one vertex are linked when two of
    # its triangles share an edge through v; a manifold vertex has one linked group.
    nf = len(f)
    tri = np.tile(np.arange(nf), 3)
    order = np.argsort(inv, kind="stable")
    inner = cnt[inv[order]] == 2
    first = order[inner][0::2]
    second = order[inner][1::2]
    t1, t2 = tri[first], tri[second]
    ends = und[first]
    inc_key = f.ravel() * nf + np.repeat(np.arange(nf), 3)    # incidence id -> sorted key
    srt = np.argsort(inc_key)
    sorted_key = inc_key[srt]
    links = []
    for end in (ends[:, 0], ends[:, 1]):
        ka = srt[np.searchsorted(sorted_key, end * nf + t1)]
        kb = srt[np.searchsorted(sorted_key, end * nf + t2)]
        links.append((ka, kb))
    la = np.concatenate([x[0] for x in links])
    lb = np.concatenate([x[1] for x in links])
    g = coo_matrix((np.ones(len(la)), (la, lb)), shape=(3 * nf, 3 * nf))
    _, lab = connected_components(g, directed=False)
    pairs = np.unique(np.column_stack([f.ravel(), lab]), axis=0)
    fans = np.bincount(pairs[:, 0])
    single_fan = bool(np.all(fans[np.unique(f)] == 1))
    out = {"max_faces_per_edge": int(cnt.max()), "oriented": oriented,
           "boundary_edges": int(np.sum(cnt == 1)), "single_fan": single_fan}
    out["manifold"] = out["max_faces_per_edge"] <= 2 and oriented and single_fan
    return out


# --------------------------------------------------------------------------- simplification
def surface_distances(points, vertices, faces) -> np.ndarray:
    """Exact distances (mm) from points (N, 3) to a triangulated surface (trimesh's r-tree
    closest-point query)."""
    v = as_points(vertices, "vertices", min_count=3)
    mesh = trimesh.Trimesh(v, as_faces(faces, len(v)), process=False)
    _, d, _ = trimesh.proximity.closest_point(mesh, as_points(points, "points"))
    return np.asarray(d)


def surface_distances_fast(points, vertices, faces, *, tol_mm: float, k: int = 8
                           ) -> np.ndarray:
    """Distances from points to a surface, exact wherever they exceed ``tol_mm``.

    First an upper bound: exact point-triangle distances to the ``k`` triangles whose
    centroids are nearest (a minimum over some triangles is never below the true distance).
    Points whose bound exceeds ``tol_mm`` get the exact distance of
    :func:`surface_distances`. So ``result <= tol_mm`` exactly where the true distance is.
    """
    p = as_points(points, "points")
    v = as_points(vertices, "vertices", min_count=3)
    f = as_faces(faces, len(v))
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise ValueError(f"k: expected an integer >= 1 (triangles tried per point), got {k!r}")
    if not (isinstance(tol_mm, int | float | np.number) and np.isfinite(tol_mm) and tol_mm >= 0):
        raise ValueError(f"tol_mm: expected a finite distance >= 0 mm, got {tol_mm!r}")
    tri = v[f]
    k = min(k, len(f))
    _, idx = cKDTree(tri.mean(axis=1)).query(p, k=k)
    idx = idx.reshape(len(p), k)
    cp = trimesh.triangles.closest_point(tri[idx.ravel()], np.repeat(p, k, axis=0))
    d = np.linalg.norm(cp - np.repeat(p, k, axis=0), axis=1).reshape(len(p), k).min(axis=1)
    over = d > tol_mm
    if np.any(over):
        d[over] = surface_distances(p[over], v, f)
    return d


def _compact(vertices, faces):
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]


def _used_points(vertices, faces):
    """The vertices some face uses (all of them for no faces): the points a surface is made
    of, at which a simplification's tolerance is checked. A point the tiling left unused is
    no part of the surface: experiment2's distal stack had 37, up to 1.93 mm off its
    triangles, every reduction failed on them, and the surface was registered unsimplified
    (12195 triangles where the paper's had 3913)."""
    return _compact(vertices, faces)[0] if len(faces) else vertices


def simplify_surface(surface: Surface, tol_mm: float, *,
                     reductions=(0.85, 0.7, 0.55, 0.4, 0.25, 0.1)) -> Surface:
    """Simplify a surface so that it stays within ``tol_mm`` of the original (both ways).

    Quadric edge collapse (fast_simplification, boundary preserved) at the largest of
    ``reductions`` (fractions of triangles removed) whose result is verified: the exact
    distances from the original vertices to the result and from the result's vertices to the
    original are all below ``tol_mm``, and the result is a manifold. If none passes, the
    surface is returned unsimplified.
    """
    if not 0 <= tol_mm <= 5.0:
        raise ValueError(f"simplify tolerance must be in [0, 5] mm, got {tol_mm}")
    if tol_mm == 0:
        return surface
    # fast_simplification (nanobind) refuses read-only arrays with a TypeError of its own
    # (np.load(mmap_mode="r"), a cache's frozen arrays; a review): writable copies
    v0 = np.array(surface.vertices, dtype=np.float64, order="C")
    f0 = np.array(surface.faces, dtype=np.int64, order="C")
    used = _used_points(v0, f0)
    for r in sorted(reductions, reverse=True):
        v, f = fast_simplification.simplify(v0, f0.astype(np.int32), target_reduction=r,
                                            preserve_border=True)
        v, f = _compact(np.asarray(v, np.float64), np.asarray(f, np.int64))
        if len(f) == 0 or not check_manifold(v, f)["manifold"]:
            continue
        h = max(surface_distances_fast(used, v, f, tol_mm=tol_mm).max(),
                surface_distances_fast(v, v0, f0, tol_mm=tol_mm).max())
        if h <= tol_mm:
            info = dict(surface.info, simplify_tol_mm=tol_mm, hausdorff_mm=float(h),
                        reduction=r)
            return Surface(v, f, info)
    return Surface(v0, f0, dict(surface.info, simplify_tol_mm=tol_mm, hausdorff_mm=0.0,
                                reduction=0.0))


def surface_from_ct(volume_hu, slice2ct, slice_indices: Sequence[int],
                    clicks_xy: Mapping[int, Sequence[np.ndarray]], *,
                    quality: Quality = "area",
                    simplify_tol_mm: float | None = SURFACE_SIMPLIFY_TOL_MM,
                    snake_options: dict | None = None):
    """One bone surface from CT slices: snake contours, tiling, simplification.

    Parameters
    ----------
    volume_hu, slice2ct, slice_indices, clicks_xy : as :func:`reglib.contours.contours_from_ct`
        (the slices of one region, e.g. the proximal or the distal femur, in increasing z).
    quality, simplify_tol_mm : as :func:`surface_from_contours`.
    snake_options : keyword options of :func:`reglib.contours.snake_contour`.

    Returns
    -------
    (Surface, list of SliceContours): the contours are all the snakes gave; those enclosing
    less than ``MIN_CONTOUR_AREA_MM2`` (or with fewer than 3 points) are not tiled.

    Raises ``ValueError`` when fewer than 2 slices keep a contour to tile.
    """
    slabs = slice_slabs(slice2ct, slice_indices)
    slabbed = None if all(len(s) == 1 for s in slabs) else _slab_volume(
        volume_hu, slice2ct, slabs, clicks_xy)
    if slabbed is None:     # every slice its own (or slabs that cannot be averaged: thinned)
        contours = contours_from_ct(volume_hu, slice2ct, [s[0] for s in slabs], clicks_xy,
                                    **(snake_options or {}))
    else:                   # each slab's contours named by its lowest slice
        vol, aff, clicks = slabbed
        contours = [replace(c, slice_index=slabs[c.slice_index][0]) for c in contours_from_ct(
            vol, aff, range(len(slabs)), clicks, **(snake_options or {}))]
    contours = sorted(contours, key=lambda s: s.z_mm)
    kept = tileable_contours([s.contours_ct for s in contours])
    if len(kept) < 2:
        raise ValueError(f"{len(kept)} slice(s) with a contour large enough to tile "
                         f"(at least 3 points enclosing {MIN_CONTOUR_AREA_MM2:g} mm^2); a "
                         "surface needs 2")
    surf = surface_from_contours(kept, quality=quality, simplify_tol_mm=simplify_tol_mm)
    return surf, contours


#: the least distance (mm) between the CT slices whose contours are tiled: the paper's
#: finest spacing (about 1 mm near the pins, NOTES.md s2). A contour lies a fraction of a
#: pixel (0.1-0.3 mm) off the outline across it; tiled between slices much closer than
#: that, it tilts the surface's normals far from the bone's, and the apparent contours the
#: registration matches follow the noise (a cylinder of 0.2 mm slices in the tests: half
#: its wall's faces tilted more than 0.3 out of plane). Closer slices are averaged into
#: slabs of about this thickness, as a radiologist reformats thin slices, which also lowers
#: their noise by the square root of their count.
MIN_SLICE_GAP_MM = 1.0


def _per_slice_affine(aff: np.ndarray, k: int) -> np.ndarray:
    """(4, 4): ``(col, row, 0, 1)`` of slice ``k`` to ct mm, from a (K, 4, 4) stack of such
    matrices or one (4, 4) voxel affine of ``(col, row, slice, 1)``
    (:func:`reglib.contours._slice_affine` with the slice coordinate folded in)."""
    from reglib.contours import _slice_affine

    a, kk = _slice_affine(aff, k)
    if kk == 0.0:
        return a
    out = a.copy()
    out[:, 3] = a @ [0.0, 0.0, kk, 1.0]
    return out


def slice_slabs(slice2ct, slice_indices: Sequence[int]) -> list[list[int]]:
    """The slices grouped into slabs to contour: from the lowest up, each slab the slices
    (by z) within :data:`MIN_SLICE_GAP_MM` (or one in-plane pixel, if larger) of its lowest
    one. Slices that far apart or farther are a slab each (the shipped schedules' 1 mm and
    coarser slices are all their own). Indices outside the volume are left alone, for
    :func:`reglib.contours.contours_from_ct` to refuse naming them."""
    from reglib.contours import _pixel_mm

    aff = np.asarray(slice2ct, dtype=np.float64)
    ks = [int(k) for k in slice_indices]
    if len(ks) < 2 or (aff.ndim == 3 and not all(0 <= k < len(aff) for k in ks)):
        return [[k] for k in ks]
    z = [float(_per_slice_affine(aff, k)[2, 3]) for k in ks]
    gap = max(MIN_SLICE_GAP_MM, _pixel_mm(aff))
    slabs: list[list[int]] = []
    z0 = -np.inf
    for i in np.argsort(z, kind="stable"):
        if z[i] - z0 < gap * (1 - 1e-9):
            slabs[-1].append(ks[i])
        else:
            slabs.append([ks[i]])
            z0 = z[i]
    return slabs


def _slab_volume(volume_hu, slice2ct, slabs, clicks_xy):
    """``(volume (S, rows, cols), affines (S, 4, 4), clicks by slab)``: each slab's slices
    averaged, at their mean affine; a slab's clicks are those of its lowest clicked slice.
    None when the slices of a slab differ in-plane (then they cannot be averaged)."""
    vol = np.asarray(volume_hu)
    aff = np.asarray(slice2ct, dtype=np.float64)
    images, affines, clicks = [], [], {}
    for j, slab in enumerate(slabs):
        a = np.stack([_per_slice_affine(aff, k) for k in slab])
        if np.abs(a[:, :, :2] - a[0, :, :2]).max() > 1e-6 \
                or np.abs(a[:, :2, 3] - a[0, :2, 3]).max() > 1e-6:
            return None
        images.append(vol[slab].astype(np.float64).mean(axis=0))
        affines.append(a.mean(axis=0))
        clicked = [k for k in sorted(slab) if k in clicks_xy]
        if clicked:
            clicks[j] = clicks_xy[clicked[0]]
    if not clicks:
        return None
    return np.stack(images), np.stack(affines), clicks


#: the smallest cross-section (mm^2) a CT contour must enclose to be tiled: a snake on the
#: tip of a condyle that a slice only grazes can shrink to a point or a segment; left out,
#: the contour above it is the surface's open end there
MIN_CONTOUR_AREA_MM2 = 2.0


def tileable_contours(slices) -> list[list[np.ndarray]]:
    """The slices' contours (a sequence over slices of sequences of (K, 3) mm arrays) without
    those too small to tile: fewer than 3 points, not finite, or enclosing less than
    :data:`MIN_CONTOUR_AREA_MM2` (a snake on the tip of a condyle that the slice grazes); a
    slice left without a contour is left out."""
    def ok(c):
        p = np.asarray(c, dtype=np.float64)
        return bool(p.ndim == 2 and p.shape[1] == 3 and len(p) >= 3
                    and np.all(np.isfinite(p))
                    and abs(_polygon_area(p)) >= MIN_CONTOUR_AREA_MM2)

    return [cs for cs in ([np.asarray(c, dtype=np.float64) for c in s if ok(c)]
                          for s in slices) if cs]
