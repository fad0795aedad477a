"""Compiled (numba) apparent contours: visibility, contour half-edges, linking and chaining
in one pass, with the same rules and the same output order as
:func:`reglib.apparent.apparent_contours` (the reference, compared in
``tests/reglib/test_apparent.py``).

The registration extracts the contours of every surface from every view at every iteration
(about 130 times per registration); in numpy each extraction cost ~0.3 ms of which most was
per-contour Python (linking loops, one object per contour) and the flattening into a
:class:`reglib.closest.ContourSet`. Here one call returns the flat arrays directly.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: error codes of :func:`contour_chains`
OK, TWICE, UNCLOSED = 0, 1, 2


@njit(cache=True)
def contour_chains(normals, ndc, twin, he_origin, he_dest, max_valence, c):
    """The apparent contours of one surface from the centre ``c`` (3,).

    Returns ``(chain, offsets, closed, path_ids, status)``: the contour half-edges in
    contour order, concatenated (E,); ``offsets`` (C + 1,); ``closed`` (C,) bool; the
    vertex ids of each contour's path, its first vertex repeated at the end when closed
    (E + C,); ``status`` :data:`OK`, or :data:`TWICE` / :data:`UNCLOSED` for the two
    inconsistencies the reference raises on. Open chains come first, in order of their
    first half-edge, then closed ones in order of their smallest half-edge.
    """
    n_faces = normals.shape[0]
    vis = np.empty(n_faces, dtype=np.bool_)
    for f in range(n_faces):
        vis[f] = ndc[f] - (normals[f, 0] * c[0] + normals[f, 1] * c[1]
                           + normals[f, 2] * c[2]) < 0.0
    n_he = twin.shape[0]
    pos = np.full(n_he, -1, dtype=np.int64)
    he_all = np.empty(n_he, dtype=np.int64)
    n = 0
    for f in range(n_faces):          # the half-edges in order, those of visible faces only
        if not vis[f]:
            continue
        for h in range(3 * f, 3 * f + 3):
            t = twin[h]
            if t >= 0 and not vis[t // 3]:
                pos[h] = n
                he_all[n] = h
                n += 1
    he = he_all[:n]
    # link: from the edge's twin, turn counter-clockwise about the destination vertex
    nxt = np.full(n, -1, dtype=np.int64)
    has_prev = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        h = he[i]
        o = twin[h]
        for _ in range(max_valence + 1):
            p = o - o % 3 + (o % 3 + 2) % 3      # the half-edge before o in its triangle
            cand = twin[p]
            if cand < 0:
                break                            # a boundary: the contour stops here
            if pos[cand] >= 0:
                nxt[i] = pos[cand]
                has_prev[pos[cand]] = True
                break
            if cand == twin[h]:
                break                            # a full turn (cannot happen; guarded)
            o = cand
    chain = np.empty(n, dtype=np.int64)
    offsets = np.zeros(n + 1, dtype=np.int64)
    closed = np.zeros(n, dtype=np.bool_)
    used = np.zeros(n, dtype=np.bool_)
    k = 0
    nc = 0
    status = OK
    for pass_closed in (False, True):
        for s in range(n):
            if used[s] or (not pass_closed and has_prev[s]):
                continue
            chain[k] = he[s]
            k += 1
            used[s] = True
            i = nxt[s]
            while i >= 0 and i != s:
                if used[i]:
                    status = TWICE
                    break
                chain[k] = he[i]
                k += 1
                used[i] = True
                i = nxt[i]
            if pass_closed and i != s:
                status = UNCLOSED
            closed[nc] = i == s
            nc += 1
            offsets[nc] = k
            if status != OK:
                break
        if status != OK:
            break
    path_ids = np.empty(k + nc, dtype=np.int64)
    for ci in range(nc):
        a, b = offsets[ci], offsets[ci + 1]
        for j in range(a, b):
            path_ids[j + ci] = he_origin[chain[j]]
        path_ids[b + ci] = he_dest[chain[b - 1]]
    return chain[:k], offsets[:nc + 1], closed[:nc], path_ids, status
