"""Per-body path lengths along X-ray paths: ray casting of closed meshes and exact spheres.

A ray is the segment ``origin + t * direction`` for ``0 <= t <= t_max`` (mm, unit
direction), from the X-ray source to the intensifier's input plane. For a closed,
consistently oriented mesh, every crossing of the surface is an entry (the face normal points
against the ray) or an exit (it points along it), so the length inside the mesh is

    chord = sum over crossings of sign(n . d) * min(t, t_max)

(exits count +t, entries -t), provided the origin lies outside the mesh. Crossings found
twice (a ray through an edge or a vertex hits two or more faces at the same ``t``) are merged
first. A ray whose entries and exits do not balance after that has met the surface in a way
the fast path could not resolve (a crack between float32 triangles, a ray grazing an edge);
it is cast again with the exact double-precision reference, so the result is exact or an
error is raised.

Three engines share this code:

``"embree"``   The fast path, :class:`RayScene`. Rays from one point (an X-ray frame) are a
               fan: the closed meshes are rasterised on an image plane in float64, every
               ray's chord the signed sum of its distances to the triangles that cover it
               (:class:`FanRays`, :mod:`testbed._fan_numba`; ~15 ms for the 11 bodies of a
               640 x 480 patient frame, 2e-10 mm from the numpy reference). Other rays go to
               Intel Embree through ``embreex`` (float32, each mesh in its own scene
               centred on it): all hits along each ray, each pass restarting the rays that
               hit 2e-4 mm beyond their last hit, on the rays that meet the mesh's bounding
               sphere only (exact, conservative culling).
``"trimesh"``  trimesh's ``ray_pyembree.RayMeshIntersector`` (the same Embree, trimesh's
               multi-hit loop): a second implementation, compared in tests.
``"numpy"``    trimesh's pure-numpy ``ray_triangle.RayMeshIntersector``: the brute-force
               reference kept for tests and for the rays the fast paths could not resolve.

Spheres (steel beads) have an analytic chord.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import trimesh
from trimesh.ray import ray_triangle

from testbed.bodies import Body
from testbed.materials import material

__all__ = [
    "Engine",
    "FanRays",
    "RayScene",
    "attenuation_weights",
    "body_path_lengths",
    "mesh_chords",
    "ray_box_hits",
    "sphere_chords",
]

Engine = Literal["embree", "trimesh", "numpy"]

# a restarted ray begins this far (mm) beyond its last hit; surfaces closer than this along a
# ray would be merged (none of the world's are)
_STEP_MM = 2e-4

# two crossings of one ray closer than this (mm) with the same sense are one crossing
_MERGE_TOL_MM = 1e-5


def _check_rays(origins, directions, t_max):
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(
            f"origins and directions: expected two (N, 3) arrays, got {o.shape} and {d.shape}"
        )
    n = np.linalg.norm(d, axis=1)
    if np.any(np.abs(n - 1.0) > 1e-6):
        raise ValueError("directions: expected unit vectors")
    tm = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (len(o),))
    if np.any(~np.isfinite(tm)) or np.any(tm < 0):
        raise ValueError("t_max: expected finite, non-negative ray lengths (mm)")
    return o, d, np.ascontiguousarray(tm)


def ray_box_hits(origins, directions, t_max, lo, hi) -> np.ndarray:
    """Which segments ``origin + t d, 0 <= t <= t_max`` meet the box ``[lo, hi]`` (slab test).

    Returns a boolean ``(N,)``. Exact up to rounding; a margin of 1e-6 of the box size is
    added so that rays grazing the box are kept.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    pad = 1e-6 * max(float(np.max(hi - lo)), 1.0)
    lo, hi = lo - pad, hi + pad
    # a zero direction component becomes a tiny one: the slab bounds become +-inf-like with
    # the right signs (inside the slab: (-big, +big); outside: both of one sign)
    dd = np.where(directions == 0.0, 1e-300, directions)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv = 1.0 / dd
        t1 = (lo - origins) * inv
        t2 = (hi - origins) * inv
    enter = np.max(np.minimum(t1, t2), axis=1)
    leave = np.min(np.maximum(t1, t2), axis=1)
    return (enter <= leave) & (leave >= 0.0) & (enter <= t_max)


def _cull(bounds, o, d, tm) -> np.ndarray:
    """Indices of the segments that may meet the box ``bounds`` (2, 3): those that meet its
    circumscribed sphere (one dot product per ray). Conservative (never drops a segment that
    meets the box), so the result stays exact; a tighter slab test (:func:`ray_box_hits`)
    cost more than the Embree misses it saved on the default scene."""
    lo, hi = np.asarray(bounds[0], dtype=np.float64), np.asarray(bounds[1], dtype=np.float64)
    c = 0.5 * (lo + hi)
    r2 = 0.25 * float(np.sum((hi - lo) ** 2)) * (1.0 + 1e-9) + 1e-12
    w = c - o
    b = np.einsum("ij,ij->i", w, d)
    perp2 = np.einsum("ij,ij->i", w, w) - b * b
    h = np.sqrt(np.maximum(r2 - perp2, 0.0))
    return np.flatnonzero((perp2 < r2) & (b + h >= 0.0) & (b - h <= tm))


def _crossings(mesh, origins, directions, engine: Engine, prepared=None):
    """All crossings of the rays with the mesh: ray index, distance t (mm), sense (+1 exit)."""
    if engine == "embree":
        em = _EmbreeMesh(mesh) if prepared is None else prepared
        return em.crossings(origins, directions)
    if engine == "trimesh":
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        inter = RayMeshIntersector(mesh, scale_to_box=False)
    elif engine == "numpy":
        inter = ray_triangle.RayMeshIntersector(mesh)
    else:
        raise ValueError(f"engine: expected 'embree', 'trimesh' or 'numpy', got {engine!r}")
    tri, ray, loc = inter.intersects_id(
        origins, directions, multiple_hits=True, return_locations=True
    )
    tri = np.asarray(tri, dtype=np.int64)
    ray = np.asarray(ray, dtype=np.int64)
    if len(ray) == 0:
        return ray, np.zeros(0), np.zeros(0)
    t = np.einsum("ij,ij->i", np.asarray(loc, dtype=np.float64) - origins[ray], directions[ray])
    sense = np.sign(np.einsum("ij,ij->i", mesh.face_normals[tri], directions[ray]))
    keep = sense != 0  # a ray in the plane of a face does not cross it
    return ray[keep], t[keep], sense[keep]


def _merge(ray, t, sense):
    """Merge crossings of one ray found on several faces at the same t with the same sense."""
    if len(ray) == 0:
        return ray, t, sense
    order = np.lexsort((t, ray))
    ray, t, sense = ray[order], t[order], sense[order]
    dup = np.zeros(len(ray), dtype=bool)
    dup[1:] = (ray[1:] == ray[:-1]) & (np.abs(t[1:] - t[:-1]) < _MERGE_TOL_MM) & (
        sense[1:] == sense[:-1]
    )
    # a coincident entry-exit pair (a ray touching an edge from outside) cancels exactly in
    # the signed sum, so it needs no special case
    keep = ~dup
    return ray[keep], t[keep], sense[keep]


def _signed_sums(n, ray, t, sense, t_max):
    chord = np.zeros(n)
    balance = np.zeros(n)
    np.add.at(chord, ray, sense * np.minimum(np.maximum(t, 0.0), t_max[ray]))
    np.add.at(balance, ray, sense)
    return chord, balance


def mesh_chords(mesh: trimesh.Trimesh, origins, directions, t_max, *,
                engine: Engine = "embree", name: str = "mesh",
                _shift_mm: float = 1e-6, _prepared=None) -> np.ndarray:
    """Length (mm) of each segment ``origin + t d, 0 <= t <= t_max`` inside a closed mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Watertight, consistently oriented (outward normals), same frame as the rays.
    origins, directions : (N, 3) float64
        Ray origins (mm) and unit directions, outside the mesh.
    t_max : float or (N,) float64
        Segment lengths (mm).
    engine : "embree", "trimesh" or "numpy"
        The fast path, trimesh's Embree loop, or the brute-force reference (module docstring).
    name : str
        Used in error messages.

    Returns
    -------
    (N,) float64 chord lengths in mm.
    """
    if _prepared is None:
        o, d, tm = _check_rays(origins, directions, t_max)
    else:  # called by RayScene, which checked the rays once
        o, d, tm = origins, directions, t_max
    out = np.zeros(len(o))
    sel = _cull(mesh.bounds, o, d, tm)
    if sel.size == 0:
        return out
    ray, t, sense = _crossings(mesh, o[sel], d[sel], engine, _prepared)
    if engine != "embree":  # the restarted embree loop reports each crossing once
        ray, t, sense = _merge(ray, t, sense)
    chord, balance = _signed_sums(len(sel), ray, t, sense, tm[sel])
    bad = np.flatnonzero(balance != 0)
    if bad.size and engine in ("embree", "trimesh"):
        # the float32 fast path missed or doubled a crossing: redo those rays exactly
        chord[bad] = mesh_chords(mesh, o[sel[bad]], d[sel[bad]], tm[sel[bad]],
                                 engine="numpy", name=name)
        bad = np.zeros(0, dtype=np.int64)
    if bad.size and _shift_mm > 0:
        # a ray exactly through an edge or a vertex where it only touches the surface
        # (one face reported, the other not): the length inside is continuous there, so
        # take the mean over parallel rays shifted by 1e-6 of the mesh's size
        rng = np.random.default_rng(0)
        shift = _shift_mm * max(float(mesh.scale), 1.0)
        acc = np.zeros(bad.size)
        for _ in range(2):
            v = np.cross(d[sel[bad]], rng.normal(size=(bad.size, 3)))
            v *= shift / np.linalg.norm(v, axis=1, keepdims=True)
            acc += mesh_chords(mesh, o[sel[bad]] + v, d[sel[bad]], tm[sel[bad]],
                               engine="numpy", name=name, _shift_mm=0.0)
        chord[bad] = acc / 2
        bad = np.zeros(0, dtype=np.int64)
    if bad.size:
        first = sel[bad[0]]
        raise ValueError(
            f"body {name!r}: {bad.size} ray(s) enter and leave the mesh an unequal number of "
            f"times (first: ray {first}, origin {np.round(o[first], 3).tolist()} mm): the "
            "ray origin lies inside the mesh, or the mesh is not closed"
        )
    out[sel] = np.maximum(chord, 0.0)
    return out


def sphere_chords(centers, radii, origins, directions, t_max) -> np.ndarray:
    """Length (mm) of each segment inside each sphere, analytic.

    Parameters
    ----------
    centers : (K, 3) float64, radii : (K,) float64
        Spheres (mm), same frame as the rays.
    origins, directions : (N, 3) float64
        Ray origins (mm) and unit directions.
    t_max : float or (N,) float64
        Segment lengths (mm).

    Returns
    -------
    (N, K) float64 chord lengths in mm (clipped to the segment).
    """
    o, d, tm = _check_rays(origins, directions, t_max)
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(c),))
    out = np.zeros((len(o), len(c)))
    for k in range(len(c)):
        w = c[k] - o
        b = np.einsum("ij,ij->i", w, d)  # t of closest approach
        # cull: rays whose closest approach is farther than the radius
        perp2 = np.einsum("ij,ij->i", w, w) - b * b
        hit = np.flatnonzero(perp2 < r[k] * r[k])
        if hit.size == 0:
            continue
        h = np.sqrt(r[k] * r[k] - perp2[hit])
        t0 = np.clip(b[hit] - h, 0.0, tm[hit])
        t1 = np.clip(b[hit] + h, 0.0, tm[hit])
        out[hit, k] = t1 - t0
    return out


class _EmbreeMesh:
    """One closed mesh in its own Embree scene (float32, vertices centred on the mesh)."""

    def __init__(self, mesh: trimesh.Trimesh):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.bounds = np.array(mesh.bounds, dtype=np.float64)
        self.centre = 0.5 * (self.bounds[0] + self.bounds[1])
        self.normals = np.asarray(mesh.face_normals, dtype=np.float64)
        # a line crosses a convex surface at most twice: no pass is needed after the second
        self.max_crossings = 2 if mesh.is_convex else None
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(self.scene, (mesh.vertices - self.centre).astype(np.float32),
                     np.ascontiguousarray(mesh.faces, dtype=np.int32))

    def crossings(self, o, d, max_hits: int = 1000):
        """All crossings: ray index, t (mm), sense (+1 exit, -1 entry). Each pass restarts
        the rays that hit just beyond their last hit (restart points and senses compiled:
        :mod:`testbed._raycast_numba`; the numpy expressions they replace are in their
        docstrings, and the engine is compared with the numpy reference in tests)."""
        from testbed._raycast_numba import crossing_senses, restart_points

        o = np.ascontiguousarray(o, dtype=np.float64)
        d = np.ascontiguousarray(d, dtype=np.float64)
        # the live rays are kept compact (start point, direction, distance so far)
        live = np.arange(len(o))
        start = (o - self.centre).astype(np.float32)
        dirs = d.astype(np.float32)
        t0 = np.zeros(len(o))
        rays, faces, ts = [], [], []
        passes = max_hits if self.max_crossings is None else self.max_crossings
        for _ in range(passes):
            if live.size == 0:
                break
            res = self.scene.run(start, dirs, output=1)
            hit = np.flatnonzero(res["primID"] != -1)
            if hit.size == 0:
                break
            t = t0[hit] + res["tfar"][hit]
            live = live[hit]
            rays.append(live)
            faces.append(res["primID"][hit])
            ts.append(t)
            t0 = t + _STEP_MM
            # restart in float64 from the original origin, so that errors do not accumulate
            start = restart_points(o, d, self.centre, live, t0)
            dirs = dirs[hit]
        else:
            if self.max_crossings is None:
                raise RuntimeError(f"more than {max_hits} hits along a ray")
        if not rays:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        ray, t = np.concatenate(rays), np.concatenate(ts)
        face = np.concatenate(faces).astype(np.int64)
        sense = crossing_senses(self.normals, face, d, ray)
        keep = sense != 0
        return ray[keep], t[keep], sense[keep]


class _ConvexMesh:
    """A convex closed mesh as the intersection of its faces' half-spaces: chords by
    clipping (:mod:`testbed._raycast_numba`), no ray casting."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.bounds = np.array(mesh.bounds, dtype=np.float64)
        n = np.asarray(mesh.face_normals, dtype=np.float64)
        v = np.asarray(mesh.vertices, dtype=np.float64)[np.asarray(mesh.faces)[:, 0]]
        # coplanar faces (a box's two triangles per side) give one half-space
        planes = np.unique(np.round(np.column_stack([n, np.einsum("ij,ij->i", n, v)]), 9),
                           axis=0)
        self.normals = np.ascontiguousarray(planes[:, :3])
        self.offsets = np.ascontiguousarray(planes[:, 3])

    def chords(self, o, d, tm) -> np.ndarray:
        from testbed._raycast_numba import convex_chords

        return convex_chords(o, d, np.ascontiguousarray(tm), self.normals, self.offsets)

    def fan_chords(self, rays: FanRays) -> np.ndarray:
        """:meth:`chords` of a fan (rays from one point)."""
        from testbed._raycast_numba import convex_chords_fan

        return convex_chords_fan(rays.source, *rays.direction_columns, rays.t_max,
                                 self.normals, self.offsets)


#: a unit cube's corners (x slowest, z fastest)
_CUBE_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)],
                         dtype=np.float64)


class FanRays:
    """Rays from one point (an X-ray source), binned on an image plane for rasterising
    closed meshes: :mod:`testbed._fan_numba` explains the method and why it is exact.

    The image plane is normal to the rays' mean direction ``a``; every ray must make less
    than ``MAX_HALF_ANGLE_DEG`` with it (:meth:`of` returns None otherwise), and a mesh is
    rasterised only when all its vertices lie in front of the source
    (:meth:`can_rasterise`). Rays whose crossings do not balance (float rounding at a
    projected vertex) are recast with the exact reference, as in :func:`mesh_chords`.
    """

    MIN_RAYS = 64
    MAX_HALF_ANGLE_DEG = 80.0
    RAYS_PER_CELL = 2.0

    def __init__(self, source, directions, t_max, axis, e1, e2, *,
                 elongation: float | str = 1.0, rays_per_cell: float | None = None,
                 reference: bool = False):
        from testbed._fan_numba import bin_points, binned_fan, plane_coords

        self.source = np.asarray(source, dtype=np.float64)
        self.directions = directions
        self.t_max = t_max
        self.axis, self.e1, self.e2 = axis, e1, e2
        # the products by BLAS (as they were); the rest compiled (plane_coords,
        # binned_fan: the same numbers), or in numpy with ``reference`` (compared in tests)
        da = directions @ axis
        compiled = (not reference and len(da) > 0 and da.dtype == np.float64
                    and t_max.dtype == np.float64)
        if compiled:
            x, y, x0, y0, x1, y1 = plane_coords(da, directions @ e1, directions @ e2)
        else:
            x = (directions @ e1) / da
            y = (directions @ e2) / da
            x0, y0, x1, y1 = float(x.min()), float(y.min()), float(x.max()), float(y.max())
        wx, wy = x1 - x0, y1 - y0
        per_cell = self.RAYS_PER_CELL if rays_per_cell is None else float(rays_per_cell)
        if elongation == "auto":      # the rays' extent's own shape, within 1/32 to 32
            elongation = min(max(wy / max(wx, 1e-300), 1.0 / 32.0), 32.0)
            # a tall extent's cells taller still (the shape's square): the rasteriser scans
            # the cells row by row, and a long face across many rows of few cells each
            # paid each row's set-up for a few rays (a sweep's vertical rod: 18 % less
            # work; a wide extent's faces already span long rows)
            if elongation > 1.0:
                elongation *= elongation
        h = math.sqrt(max(wx * wy, 1e-24) * per_cell / len(x))
        h = max(h, 1e-12, max(wx, wy) / 4096)
        # cells of the same area, ``elongation`` times taller than wide (1: square): the
        # chords do not depend on the cells, only the work does
        hx = max(h / math.sqrt(elongation), 1e-12, wx / 4096)
        hy = max(h * math.sqrt(elongation), 1e-12, wy / 4096)
        self.grid = (x0, y0, hx, hy, int(wx / hx) + 1, int(wy / hy) + 1)
        # rays (N, 4) in bin order: the image point x, y, 1 / (d . a) and t_max (mm)
        if compiled:
            self.start, self.order, self.rays = binned_fan(x, y, da, t_max, *self.grid)
        else:
            start, order = bin_points(x, y, *self.grid)
            self.start, self.order = start, order
            self.rays = np.column_stack([x[order], y[order], 1.0 / da[order], t_max[order]])
        self._acc = None
        self._columns = None

    @property
    def direction_columns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The directions' x, y, z as three contiguous (N,) arrays (made once)."""
        if self._columns is None:
            self._columns = tuple(np.ascontiguousarray(self.directions[:, k])
                                  for k in range(3))
        return self._columns

    @classmethod
    def of(cls, source, directions, t_max) -> FanRays | None:
        """The fan of unit ``directions`` (N, 3) from ``source`` (3,) with lengths ``t_max``
        (N,) mm, or None when the rays spread too wide for one image plane."""
        from testbed._fan_numba import column_means

        d = np.ascontiguousarray(directions, dtype=np.float64)
        a = column_means(d)             # d.mean(axis=0), the same bits, compiled
        if not np.linalg.norm(a) > 0:
            return None
        a = a / np.linalg.norm(a)
        if float((d @ a).min()) <= math.cos(math.radians(cls.MAX_HALF_ANGLE_DEG)):
            return None
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]
        e1 = np.cross(a, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        return cls(source, d, np.ascontiguousarray(t_max, dtype=np.float64), a, e1, e2)

    def can_rasterise(self, mesh: trimesh.Trimesh) -> bool:
        """True when every vertex lies in front of the source (depth > 1e-6 of the mesh's
        distance)."""
        return self._in_front(*self._depths(mesh))

    def _depths(self, mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
        """The mesh's vertices relative to the source ``p (V, 3)`` and their depths ``z``."""
        p = np.asarray(mesh.vertices, dtype=np.float64) - self.source
        return p, p @ self.axis

    @staticmethod
    def _in_front(p: np.ndarray, z: np.ndarray) -> bool:
        return bool(z.min() > 1e-6 * max(float(np.abs(p).max()), 1.0))

    def sphere_chords(self, centres, radii, *, reference: bool = False) -> np.ndarray:
        """Length (mm) of every ray inside the spheres (summed over them), ``(N,)``, in the
        rays' order: :func:`sphere_chords` for the rays near each sphere's image only (the
        image boxes after the products compiled, :func:`testbed._fan_numba.
        sphere_image_boxes`; in numpy with ``reference``, compared in tests)."""
        from testbed._fan_numba import fan_sphere_chords, sphere_image_boxes

        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (len(c),))
        p = (c[:, None, :] + r[:, None, None] * _CUBE_CORNERS[None]) - self.source  # (K, 8, 3)
        z = p @ self.axis
        if not reference and len(c):
            ok, lo, hi = sphere_image_boxes(z, p @ self.e1, p @ self.e2)
        else:
            ok = np.all(z > 1e-9, axis=1)    # the bounding cube wholly in front of the source
            zs = np.where(z > 1e-9, z, 1.0)
            px, py = (p @ self.e1) / zs, (p @ self.e2) / zs
            lo = np.stack([px.min(axis=1), py.min(axis=1)], 1)
            hi = np.stack([px.max(axis=1), py.max(axis=1)], 1)
        out = np.zeros(len(self.rays))
        fan_sphere_chords(c, np.ascontiguousarray(r), lo, hi, ok, self.directions,
                          self.t_max, self.order, self.start, *self.grid, self.source, out)
        return out

    def chords(self, mesh: trimesh.Trimesh, *, name: str = "mesh",
               out: np.ndarray | None = None, depths=None) -> np.ndarray:
        """Length (mm) of every ray inside the closed ``mesh`` (N,), in the rays' order;
        written into ``out`` (N,) float64 when given (it must hold zeros). ``depths``:
        :meth:`_depths` of the mesh when the caller has them."""
        from testbed._fan_numba import fan_chords, finish

        p, z = self._depths(mesh) if depths is None else depths
        vx = (p @ self.e1) / z
        vy = (p @ self.e2) / z
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        n = len(self.rays)
        out = np.zeros(n) if out is None else out
        if self._acc is None:                # bin order: chord, balance; zeroed again by
            self._acc = np.zeros((n, 2))     # finish() after every mesh
        lo, hi = fan_chords(vx, vy, z, faces, self.rays, self.start, *self.grid, self._acc)
        bad = finish(self._acc, self.order, out, lo, hi)
        if bad.size:
            o = np.broadcast_to(self.source, (bad.size, 3))
            out[bad] = mesh_chords(mesh, o, self.directions[bad], self.t_max[bad],
                                   engine="numpy", name=name)
        return out


#: convex meshes of at most this many faces are clipped analytically (a box: 12); larger
#: convex meshes (a pin's 128-face cylinder) are cast, their rays being few after culling
CONVEX_CLIP_MAX_FACES = 64


class RayScene:
    """The bodies of a world prepared once for repeated casting.

    Fans of rays from one point (an X-ray frame: :class:`FanRays`) rasterise the closed
    meshes; other rays cast them with Embree, each mesh in its own Embree scene (meshes of a
    world may share surfaces, e.g. the canal and the cancellous bone; one scene for all
    would report only one of two coincident crossings), built on first use. Spheres are
    handled analytically, and so are small convex meshes (the table and its mattress:
    12-face boxes that every ray crosses, 90 ms each by casting with restarts, ~2 ms by
    half-space clipping).
    """

    def __init__(self, bodies: list[Body]):
        self.bodies = list(bodies)
        self._convex = {}
        self._embree = {}
        for j, b in enumerate(self.bodies):
            if b.mesh is not None and len(b.mesh.faces) <= CONVEX_CLIP_MAX_FACES \
                    and b.mesh.is_convex:
                self._convex[j] = _ConvexMesh(b.mesh)

    def _embree_mesh(self, j: int) -> _EmbreeMesh:
        if j not in self._embree:
            self._embree[j] = _EmbreeMesh(self.bodies[j].mesh)
        return self._embree[j]

    def path_lengths(self, origins, directions, t_max, *, fan: bool = True) -> np.ndarray:
        """Path length (mm) of every ray through every body, ``(N, B)`` float64.

        When every ray starts at the same point (an X-ray frame) and ``fan`` is true, the
        rays are binned once (:class:`FanRays`) and :meth:`fan_path_lengths` does the work;
        otherwise the meshes are cast with Embree.
        """
        o, d, tm = _check_rays(origins, directions, t_max)
        if fan and len(o) >= FanRays.MIN_RAYS and np.all(o == o[0]):
            rays = FanRays.of(o[0], d, tm)
            if rays is not None:
                return self.fan_path_lengths(rays)
        return self._lengths(np.ascontiguousarray(o), np.ascontiguousarray(d), tm, None)

    def fan_path_lengths(self, rays: FanRays) -> np.ndarray:
        """Path length (mm) of every ray of the fan through every body, ``(N, B)`` float64
        (a transposed view of a ``(B, N)`` array). Meshes that reach behind the source are
        cast with Embree instead of rasterised."""
        o = np.broadcast_to(rays.source, rays.directions.shape)
        return self._lengths(o, rays.directions, rays.t_max, rays)

    def _lengths(self, o, d, tm, fan: FanRays | None) -> np.ndarray:
        out = np.zeros((len(self.bodies), len(d)))
        for j, body in enumerate(self.bodies):
            if body.mesh is None:
                out[j] = (sphere_chords(body.sphere_centers, body.sphere_radii, o, d,
                                        tm).sum(1) if fan is None
                          else fan.sphere_chords(body.sphere_centers, body.sphere_radii))
            elif j in self._convex:
                out[j] = (self._convex[j].chords(o, d, tm) if fan is None
                          else self._convex[j].fan_chords(fan))
            else:
                depths = fan._depths(body.mesh) if fan is not None else None
                if depths is not None and fan._in_front(*depths):   # can_rasterise
                    fan.chords(body.mesh, name=body.name, out=out[j], depths=depths)
                else:
                    out[j] = mesh_chords(body.mesh, np.ascontiguousarray(o), d, tm,
                                         name=body.name, _prepared=self._embree_mesh(j))
        return out.T


def body_path_lengths(bodies: list[Body], origins, directions, t_max, *,
                      engine: Engine = "embree", scene: RayScene | None = None) -> np.ndarray:
    """Path length (mm) of every ray through every body.

    ``engine``: "embree" (the fast path; pass a :class:`RayScene` as ``scene`` to reuse the
    prepared meshes), "trimesh" (trimesh's Embree intersector) or "numpy" (trimesh's
    brute-force intersector, the reference).

    Returns ``(N, B)`` float64: column ``b`` is the length inside ``bodies[b]`` (for a set of
    spheres, the sum over its spheres).
    """
    if engine == "embree":
        scene = RayScene(bodies) if scene is None else scene
        return scene.path_lengths(origins, directions, t_max)
    o, d, tm = _check_rays(origins, directions, t_max)
    out = np.zeros((len(o), len(bodies)))
    for j, body in enumerate(bodies):
        if body.mesh is not None:
            out[:, j] = mesh_chords(body.mesh, o, d, tm, engine=engine, name=body.name)
        else:
            out[:, j] = sphere_chords(body.sphere_centers, body.sphere_radii, o, d, tm).sum(1)
    return out


def attenuation_weights(bodies: list[Body], *, enclosing: dict | None = None) -> np.ndarray:
    """``mu(body) - mu(enclosing body)`` (1/mm) for each body, shape ``(B,)``.

    The line integral of attenuation along a ray is ``path_lengths @ weights``. ``inside``
    must name another body of the list or of ``enclosing`` (name -> Body: bodies that are
    not weighed here, e.g. a sweep's static world around its rod; the list's names must not
    repeat theirs), or be None: air; otherwise ``ValueError``.
    """
    others = {} if enclosing is None else enclosing
    names = [b.name for b in bodies]
    if len(set(names)) != len(names) or any(n in others for n in names):
        every = [*others, *names]
        dup = sorted({n for n in every if every.count(n) > 1})
        raise ValueError(f"bodies: names must be unique, repeated: {dup}")
    by_name = {**others, **{b.name: b for b in bodies}}
    w = np.zeros(len(bodies))
    for j, b in enumerate(bodies):
        outer = 0.0
        if b.inside is not None:
            if b.inside not in by_name:
                raise ValueError(
                    f"body {b.name!r}: inside={b.inside!r} names no body of the world "
                    f"(bodies: {list(by_name)})"
                )
            outer = material(by_name[b.inside].material).mu_per_mm
        w[j] = material(b.material).mu_per_mm - outer
    return w
