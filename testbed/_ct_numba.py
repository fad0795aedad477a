"""Compiled (numba) section of a closed mesh by a plane z = const, rasterised into a CT slice's
pixel coverage.

:meth:`testbed.ct._MeshSlicer.crossings` and :meth:`testbed.ct._Accumulator.add` are the
numpy reference; :func:`add_section` does the same arithmetic per triangle and per row
crossing, in the same order (triangles by their lowest z, rows upward), so the coverage
sums are the reference's to the bit (``tests/testbed/test_ct.py`` compares them).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def add_section(tri, zmin, zmax, sign, z, y_rows, dy, x0, px, width, weight, part, full):
    """Add ``weight`` times the coverage of the section of the mesh at ``z`` to the
    accumulator arrays ``part`` and ``full`` (rows of ``y_rows``, ``width + 1`` columns).

    ``tri (T, 3, 3)`` the triangles sorted by ``zmin`` (their lowest z), ``zmax`` their
    highest z, ``sign`` the entry sign of each (+1 entering along +x); ``dy`` the spacing of
    ``y_rows``; a crossing at ``u = (x - x0) / px + 0.5`` adds ``weight * sign`` to
    ``full[row, floor(u) + 1]`` and ``weight * sign * (1 - frac(u))`` to
    ``part[row, floor(u)]`` (see ``testbed.ct._Accumulator``).
    """
    n_rows = y_rows.shape[0]
    y0 = y_rows[0]
    hi = np.searchsorted(zmin, z, side="left")      # zmin < z (a vertex at z is above:
    #                                                  the plane just below z, as the reference)
    pa = np.empty(2)
    pb = np.empty(2)
    for i in range(hi):
        if not zmax[i] >= z:
            continue
        n_above = 0
        first_above = -1
        first_below = -1
        for v in range(3):
            if tri[i, v, 2] >= z:
                n_above += 1
                if first_above < 0:
                    first_above = v
            elif first_below < 0:
                first_below = v
        if n_above != 1 and n_above != 2:
            continue
        lone_is_above = n_above == 1
        lone = first_above if lone_is_above else first_below
        for j in range(2):
            other = (lone + 1 + j) % 3
            if lone_is_above:
                lo, up = other, lone
            else:
                lo, up = lone, other
            s = (z - tri[i, lo, 2]) / (tri[i, up, 2] - tri[i, lo, 2])
            px_ = tri[i, lo, 0] + s * (tri[i, up, 0] - tri[i, lo, 0])
            py_ = tri[i, lo, 1] + s * (tri[i, up, 1] - tri[i, lo, 1])
            if j == 0:
                pa[0], pa[1] = px_, py_
            else:
                pb[0], pb[1] = px_, py_
        xa, ya, xb, yb = pa[0], pa[1], pb[0], pb[1]
        lo_y, hi_y = min(ya, yb), max(ya, yb)
        j0 = min(max(np.ceil((lo_y - y0) / dy), 0.0), float(n_rows))
        j1 = min(max(np.ceil((hi_y - y0) / dy), 0.0), float(n_rows))
        w = weight * sign[i]
        for r in range(int(j0), int(j1)):
            x = xa + (y_rows[r] - ya) * (xb - xa) / (yb - ya)
            u = min(max((x - x0) / px + 0.5, 0.0), float(width))
            fl = int(np.floor(u))
            full[r, min(fl + 1, width)] += w
            part[r, fl] += w * (1.0 - (u - fl))


@njit(cache=True)
def finish_slice(part, full, ss, width, base, out):
    """``out[:] = base + (part + cumsum(full, axis=1))[:, :width].reshape(n, ss, width)
    .mean(axis=1)`` (:meth:`testbed.ct._Accumulator.result`, then the mean of each pixel
    row's ``ss`` sub-rows as numpy takes it: the sub-rows summed in order, divided by
    ``ss``) without the intermediate arrays; the same arithmetic in the same order, so the
    same bits (``tests/testbed/test_ct.py`` compares them).

    ``part``, ``full`` ``(n * ss, width + 1)`` the accumulator's arrays (``full`` is left as
    it was), ``out`` ``(n, width)`` float64."""
    n = out.shape[0]
    row = np.empty(width)
    for i in range(n):
        for q in range(ss):
            r = i * ss + q
            s = full[r, 0]
            if q == 0:
                row[0] = part[r, 0] + s
            else:
                row[0] += part[r, 0] + s
            for c in range(1, width):
                s += full[r, c]
                if q == 0:
                    row[c] = part[r, c] + s
                else:
                    row[c] += part[r, c] + s
        for c in range(width):
            out[i, c] = base + row[c] / ss
