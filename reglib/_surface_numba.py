"""Compiled (numba) least-cost tiling path between two contours (the paper's tiling by
dynamic programming; :func:`reglib.surface._dp`). The numpy recursion
(:func:`reglib.surface._dp_numpy`) and the brute force (:func:`reglib.surface._brute_force`)
are its references in ``tests/reglib/test_surface.py``."""

from __future__ import annotations

import numpy as np
from numba import njit


def backtrack(came_j: np.ndarray) -> np.ndarray:
    """The steps (0: in i, 1: in j) of the path ending at the last cell of ``came_j``
    ((m+1, n+1) bool, True where the cell was reached by a step in j). Plain Python for
    the numpy recursion (:func:`reglib.surface._dp_numpy`), compiled below for
    :func:`dp_kernel`."""
    m, n = came_j.shape[0] - 1, came_j.shape[1] - 1
    steps = np.empty(m + n, dtype=np.int8)
    i, j = m, n
    for k in range(m + n - 1, -1, -1):
        if came_j[i, j]:
            steps[k] = 1
            j -= 1
        else:
            steps[k] = 0
            i -= 1
    return steps


_backtrack_compiled = njit(cache=True)(backtrack)


@njit(cache=True)
def dp_kernel(cost_i, cost_j):
    """Least total cost from (0, 0) to (m, n) by unit steps in i (``cost_i[i, j]``, (m, n+1))
    or in j (``cost_j[i, j]``, (m+1, n)); returns ``(total, steps)``, ``steps[k]`` 0 for a
    step in i and 1 for a step in j; ties go to i."""
    m, n = cost_i.shape[0], cost_j.shape[1]
    total = np.full((m + 1, n + 1), np.inf)
    came_j = np.zeros((m + 1, n + 1), dtype=np.bool_)
    total[0, 0] = 0.0
    for i in range(m + 1):
        for j in range(n + 1):
            if i == 0 and j == 0:
                continue
            from_i = total[i - 1, j] + cost_i[i - 1, j] if i > 0 else np.inf
            from_j = total[i, j - 1] + cost_j[i, j - 1] if j > 0 else np.inf
            if from_j < from_i:
                total[i, j] = from_j
                came_j[i, j] = True
            else:
                total[i, j] = from_i
    return total[m, n], _backtrack_compiled(came_j)


@njit(cache=True)
def douglas_peucker(xy, tol):
    """Which vertices of the polyline ``xy`` (K, 2) the Douglas-Peucker reduction keeps
    within ``tol`` (a bool mask; the ends always): a segment's farthest vertex (the first
    of equals) is kept and the segment split there while it lies more than ``tol`` from the
    segment, the distance of a vertex being to the segment itself (to its nearer end when
    its projection falls outside, as for a zero-length segment). An explicit stack of
    index pairs replaces the recursion. ``skimage.measure.approximate_polygon`` is the
    reference (tests/reglib/test_surface.py)."""
    k = xy.shape[0]
    keep = np.zeros(k, dtype=np.bool_)
    if k == 0:
        return keep
    keep[0] = True
    keep[k - 1] = True
    stack = np.empty((k, 2), dtype=np.int64)
    stack[0, 0], stack[0, 1] = 0, k - 1
    top = 1
    while top > 0:
        top -= 1
        a, b = stack[top, 0], stack[top, 1]
        if b - a < 2:
            continue
        ax, ay = xy[a, 0], xy[a, 1]
        bx, by = xy[b, 0], xy[b, 1]
        ex, ey = bx - ax, by - ay
        length = np.sqrt(ex * ex + ey * ey)
        best = -1.0
        arg = -1
        for i in range(a + 1, b):
            px, py = xy[i, 0] - ax, xy[i, 1] - ay
            qx, qy = xy[i, 0] - bx, xy[i, 1] - by
            if px * ex + py * ey > 0 and -(qx * ex + qy * ey) > 0:
                dist = abs(px * ey - py * ex) / length
            else:
                dist = min(np.sqrt(px * px + py * py), np.sqrt(qx * qx + qy * qy))
            if dist > best:
                best = dist
                arg = i
        if best > tol:
            keep[arg] = True
            stack[top, 0], stack[top, 1] = arg, b
            top += 1
            stack[top, 0], stack[top, 1] = a, arg
            top += 1
    return keep
