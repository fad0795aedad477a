"""Compiled (numba) chords through convex meshes by half-space clipping.

A convex closed mesh is the intersection of the half-spaces ``n_f . (x - v_f) <= 0`` of its
faces (outward unit normals ``n_f``, a vertex ``v_f`` of each face). Along a ray
``o + t d`` each face bounds ``t`` from one side, so the segment ``[0, t_max]`` inside the
mesh is ``[max(0, entries), min(t_max, exits)]`` (Cyrus-Beck clipping): one pass over the
faces per ray, no ray casting and no restarts. :func:`testbed.raycast.mesh_chords` with
``engine="numpy"`` (trimesh's brute-force ray-triangle test) is the reference, compared on
random convex meshes and rays in ``tests/testbed/test_raycast.py``.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def convex_chords(o, d, t_max, normals, offsets):
    """Length (mm) of each segment ``o + t d, 0 <= t <= t_max`` inside the convex body
    ``{x : normals @ x <= offsets}``; ``o, d`` (N, 3), ``t_max`` (N,), ``normals`` (F, 3)
    outward unit, ``offsets`` (F,) = ``n_f . v_f``."""
    n = o.shape[0]
    out = np.zeros(n)
    for i in range(n):
        lo, hi = 0.0, t_max[i]
        for f in range(normals.shape[0]):
            a = (normals[f, 0] * o[i, 0] + normals[f, 1] * o[i, 1] + normals[f, 2] * o[i, 2]
                 - offsets[f])
            b = normals[f, 0] * d[i, 0] + normals[f, 1] * d[i, 1] + normals[f, 2] * d[i, 2]
            if b > 0.0:
                t = -a / b
                if t < hi:
                    hi = t
            elif b < 0.0:
                t = -a / b
                if t > lo:
                    lo = t
            elif a > 0.0:      # parallel to the face and outside its plane
                hi = -1.0
            if hi <= lo:
                break
        if hi > lo:
            out[i] = hi - lo
    return out


@njit(cache=True, error_model="numpy")
def convex_chords_fan(source, dx, dy, dz, t_max, normals, offsets):
    """:func:`convex_chords` for rays that all start at ``source`` (3,), directions given
    as columns ``dx, dy, dz`` (N,): each face's offset from the source is computed once,
    and the faces are the outer loop so that the ray loop has no branch (selects only; a
    ray parallel to a face divides by zero harmlessly, ``error_model="numpy"``) and
    vectorises: 2.5x faster than a loop per ray. The same clipping; compared with
    :func:`convex_chords` in tests."""
    n = dx.shape[0]
    lo = np.zeros(n)
    hi = t_max.copy()
    for f in range(normals.shape[0]):
        nx, ny, nz = normals[f, 0], normals[f, 1], normals[f, 2]
        a = nx * source[0] + ny * source[1] + nz * source[2] - offsets[f]
        for i in range(n):
            b = nx * dx[i] + ny * dy[i] + nz * dz[i]
            t = -a / b
            h = hi[i]
            hi[i] = min(h, t) if b > 0.0 else (-1.0 if (b == 0.0 and a > 0.0) else h)
            lo[i] = max(lo[i], t) if b < 0.0 else lo[i]
    out = np.empty(n)
    for i in range(n):
        out[i] = hi[i] - lo[i] if hi[i] > lo[i] else 0.0
    return out


@njit(cache=True)
def restart_points(o, d, centre, live, t0):
    """float32 ``o[live] - centre + t0[:, None] * d[live]`` without temporaries (the same
    float64 arithmetic as the numpy expression, cast once): the start points of the rays
    restarted just beyond their last hit, from their original origins."""
    out = np.empty((live.shape[0], 3), dtype=np.float32)
    for k in range(live.shape[0]):
        i = live[k]
        for c in range(3):
            out[k, c] = (o[i, c] - centre[c]) + t0[k] * d[i, c]
    return out


@njit(cache=True)
def crossing_senses(normals, face, d, ray):
    """``sign(normals[face] . d[ray])`` per crossing (+1 exit, -1 entry, 0 grazing)."""
    out = np.empty(face.shape[0])
    for k in range(face.shape[0]):
        f, r = face[k], ray[k]
        s = normals[f, 0] * d[r, 0] + normals[f, 1] * d[r, 1] + normals[f, 2] * d[r, 2]
        out[k] = 1.0 if s > 0.0 else (-1.0 if s < 0.0 else 0.0)
    return out
