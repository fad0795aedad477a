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

from reglib.geometry import line_segment_distance

#: reglib.geometry's scalar line-segment distance, compiled
_line_segment_distance = njit(cache=True, inline="always")(line_segment_distance)


@njit(cache=True)
def closest_segments(o, d, starts, ends, block_a, block_b, block_eps, block_seg0,
                     contour_block0, within):
    """Per (line, contour): the distance and index of the closest segment.

    Parameters
    ----------
    o, d : (N, 3) lines (unit d).
    starts, ends : (S, 3) segments.
    block_a, block_b, block_eps : (K, 3), (K, 3), (K,) the blocks' capsule axes and radii.
    block_seg0 : (K + 1,) the blocks' first segments (block k owns ``block_seg0[k]`` to
        ``block_seg0[k + 1]``).
    contour_block0 : (C + 1,) the contours' first blocks.
    within : threshold of the line (mm), or a negative number for none.

    Returns ``dist (N, C)`` (inf where not computed) and ``seg (N, C)`` (-1 there). With
    ``within >= 0`` the values are exact for every contour whose distance is at most
    ``max(within, nearest)``; others may be inf or an upper bound (the caller masks them).
    """
    n = o.shape[0]
    nc = contour_block0.shape[0] - 1
    dist = np.full((n, nc), np.inf)
    seg = np.full((n, nc), -1, dtype=np.int64)
    for i in range(n):
        ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
        dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
        nearest = np.inf
        for c in range(nc):
            best = np.inf
            best_j = -1
            for k in range(contour_block0[c], contour_block0[c + 1]):
                limit = best
                if within >= 0.0:
                    t = within if within > nearest else nearest
                    if t < limit:
                        limit = t
                lower = _line_segment_distance(
                    ox, oy, oz, dx, dy, dz, block_a[k, 0], block_a[k, 1], block_a[k, 2],
                    block_b[k, 0], block_b[k, 1], block_b[k, 2]) - block_eps[k]
                if lower > limit + 1e-7 * (1.0 + limit):
                    continue
                for j in range(block_seg0[k], block_seg0[k + 1]):
                    r = _line_segment_distance(
                        ox, oy, oz, dx, dy, dz, starts[j, 0], starts[j, 1], starts[j, 2],
                        ends[j, 0], ends[j, 1], ends[j, 2])
                    if r < best:
                        best = r
                        best_j = j
            dist[i, c] = best
            seg[i, c] = best_j
            if best < nearest:
                nearest = best
    return dist, seg
