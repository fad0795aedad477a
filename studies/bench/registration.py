"""Benchmark of the 2-D/3-D registration loop (``reglib.register``) and its Step A methods.

Instance (made here, no testbed needed): a bone-like closed mesh (shaft capsule, head and
neck, trochanter, two condyles, unioned with manifold3d) cut into a proximal and a distal open
surface, simplified to the paper's sizes (1664 and 3913 triangles, quadric decimation); a
true pose ``ct2robot``; four views (two proximal, two distal) with centers of perspective
600 mm from the bone; the true X-ray paths: lines from each center through points sampled
every 1.5 mm along the apparent contours of the true surfaces, kept where they lie on the
external silhouette (a ray 0.2 mm outside the contour misses both surfaces; trimesh ray
casting). Starts: the true pose rotated by 7 deg about the pin centroid and shifted by
20 mm, random directions, seeded.

Timed, per Step A method (``blocks`` = default, ``dense``, ``reference`` = brute force;
``hierarchy`` = the paper's pure-Python capsule queue, on the first iteration only as it is
slow in CPython):

- one registration: total wall time, CPU time of this process (less sensitive to other
  jobs on a shared machine; numpy is single-threaded here), iterations, time per
  iteration;
- per iteration, its parts: apparent contours of both surfaces from the four centers,
  Step A + B for the four views, the pose solve.

Validator: the largest pin error (mm) after registration, against the truth.

Run: ``python -m studies.bench.registration [--starts 3] [--out CSV]``. The scene helpers
(:func:`make_scene`, :func:`perturbed`, :func:`pin_errors`) are also the test world of
``tests/reglib/test_register.py``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial.transform import Rotation

from reglib.apparent import SurfaceTopology, apparent_contours, prepare_surface
from reglib.closest import ContourSet, closest_points, select_contours
from reglib.geometry import RigidTransform, arc_length
from reglib.register import View, register
from studies.scoring import perturbed_start
from studies.scoring import pin_errors as _pin_errors
from testbed.phantom import PIN_NAMES

PINS_CT = np.array([[28.0, 0.0, 128.0], [14.0, 6.0, -122.0], [-13.0, 5.0, -120.0]])
PAPER_FACES = (1664, 3913)


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """Surfaces (CT frame), views (robot frame), the true ``ct2robot`` and the mesh used for
    ray casting (both surfaces, CT frame)."""

    surfaces: list[SurfaceTopology]
    views: dict[str, View]
    true: RigidTransform
    mesh_ct: trimesh.Trimesh


def bone_mesh(*, fine: bool = False) -> trimesh.Trimesh:
    """A closed bone-like mesh, mm, CT frame: shaft along z, head up at +z (~5k triangles,
    or ~18k with ``fine``)."""
    k = 2 if fine else 1
    shaft = trimesh.creation.capsule(height=240.0, radius=12.0, count=[24 * k, 24 * k])
    head = trimesh.creation.icosphere(subdivisions=2 + k, radius=22.0)
    head.apply_translation(PINS_CT[0])
    neck = trimesh.creation.cylinder(radius=9.0, segment=[[0, 0, 105.0], [24.0, 0, 125.0]],
                                     sections=24 * k)
    troch = trimesh.creation.icosphere(subdivisions=1 + k, radius=10.0)
    troch.apply_translation([-10.0, 4.0, 100.0])
    c1 = trimesh.creation.icosphere(subdivisions=2 + k, radius=17.0)
    c1.apply_translation(PINS_CT[1])
    c2 = trimesh.creation.icosphere(subdivisions=2 + k, radius=16.0)
    c2.apply_translation(PINS_CT[2])
    return trimesh.boolean.union([shaft, head, neck, troch, c1, c2], engine="manifold")


def cut(mesh: trimesh.Trimesh, keep, faces: int | None = None):
    """The open surface of the triangles whose centroid passes ``keep``; optionally
    simplified to ``faces`` triangles. Returns ``(vertices (V, 3) mm, faces (F, 3))``."""
    sub = mesh.submesh([np.flatnonzero(keep(mesh.triangles_center))], append=True)
    if faces is not None:
        sub = sub.simplify_quadric_decimation(face_count=faces)
    return np.asarray(sub.vertices, dtype=np.float64), np.asarray(sub.faces, dtype=np.int64)


def sample_polyline(points, closed: bool, step: float):
    """Points every ``step`` mm along a polyline and the segment each lies on."""
    P, s = arc_length(points, closed=closed)
    if s[-1] < step:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    t = np.arange(step / 2, s[-1], step)
    seg = np.clip(np.searchsorted(s, t, side="right") - 1, 0, len(P) - 2)
    return np.column_stack([np.interp(t, s, P[:, k]) for k in range(3)]), seg


def true_view(surfaces, mesh_ct, ct2robot: RigidTransform, center_robot, *,
              step: float = 1.5, probe_mm: float = 0.2, name: str = "") -> View:
    """True X-ray paths of the external silhouette seen from ``center_robot`` (mm)."""
    center_robot = np.asarray(center_robot, dtype=np.float64)
    c_ct = ct2robot.inverse().apply(center_robot)
    pts = []
    for top in surfaces:
        for k in apparent_contours(top, c_ct):
            s, seg = sample_polyline(k.points, k.closed, step)
            if len(s) == 0:
                continue
            a, b = k.segments
            dirs = s - c_ct
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            out = np.cross(dirs, (b - a)[seg])     # away from where the surface projects
            out /= np.linalg.norm(out, axis=1, keepdims=True)
            probe = s + probe_mm * out - c_ct
            probe /= np.linalg.norm(probe, axis=1, keepdims=True)
            hit = mesh_ct.ray.intersects_any(np.repeat(c_ct[None], len(s), 0), probe)
            pts.append(s[~hit])
    p_r = ct2robot.apply(np.vstack(pts))
    d = p_r - center_robot
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return View(center=center_robot, origins=np.repeat(center_robot[None], len(d), 0),
                directions=d, name=name)


def make_scene(*, paper_sizes: bool = False, seed: int = 1) -> SyntheticScene:
    """The four-view synthetic scene. ``paper_sizes``: surfaces of 1664 and 3913 triangles
    (from the fine mesh); otherwise the coarse cut (~2.3k and ~2.6k triangles)."""
    m = bone_mesh(fine=paper_sizes)
    nf = PAPER_FACES if paper_sizes else (None, None)
    prox = cut(m, lambda c: c[:, 2] > 40.0, nf[0])
    dist = cut(m, lambda c: c[:, 2] < -40.0, nf[1])
    surfaces = [prepare_surface(*prox), prepare_surface(*dist)]
    mesh_ct = trimesh.Trimesh(np.vstack([prox[0], dist[0]]),
                              np.vstack([prox[1], dist[1] + len(prox[0])]), process=False)
    true = RigidTransform.from_rotvec(Rotation.random(random_state=seed).as_rotvec(),
                                      [400.0, 50.0, 300.0])

    def center(target_ct, direction_ct):
        u = np.asarray(direction_ct, float) / np.linalg.norm(direction_ct)
        return true.apply(np.asarray(target_ct, float)) + 600.0 * true.apply_vectors(u[None])[0]

    centers = {
        "proximal_ap": center([0, 0, 100], [0, -1, 0.1]),
        "proximal_oblique": center([0, 0, 100], [1, -0.7, 0]),
        "distal_ap": center([0, 0, -100], [0, -1, -0.1]),
        "distal_oblique": center([0, 0, -100], [0.8, -1, 0]),
    }
    views = {k: true_view(surfaces, mesh_ct, true, c, name=k) for k, c in centers.items()}
    return SyntheticScene(surfaces, views, true, mesh_ct)


def perturbed(true: RigidTransform, deg: float, mm: float, rng) -> RigidTransform:
    """``true`` rotated by ``deg`` about the pin centroid (:func:`studies.scoring.
    perturbed_start`) and shifted by ``mm`` (random directions from ``rng``, a seed or
    Generator: the axis first, then the shift)."""
    rng = np.random.default_rng(rng)
    rot = perturbed_start(true, dict(zip(PIN_NAMES, PINS_CT, strict=True)), deg, rng)
    tdir = rng.normal(size=3)
    tdir /= np.linalg.norm(tdir)
    return RigidTransform(np.eye(3), mm * tdir) @ rot


def pin_errors(ct2robot: RigidTransform, true: RigidTransform) -> np.ndarray:
    """Distances (mm) between the pins mapped by the estimate and by the truth, (3,)."""
    e = _pin_errors(ct2robot, true, dict(zip(PIN_NAMES, PINS_CT, strict=True)))
    return np.array([e[k] for k in PIN_NAMES])


def _time_parts(scene: SyntheticScene, T: RigidTransform, closest: str) -> dict:
    """Wall time of the parts of one iteration at pose ``T`` (s)."""
    views = list(scene.views.values())
    t0 = time.perf_counter()
    conts = []
    for v in views:
        c_ct = T.inverse().apply(v.center)
        conts.append([k for s in scene.surfaces for k in apparent_contours(s, c_ct)])
    t1 = time.perf_counter()
    for v, cs in zip(views, conts):
        cset = ContourSet.from_contours(cs)
        o, d = T.inverse().apply_lines(v.origins, v.directions)
        within = 10.0 if closest in ("blocks", "compiled") else None
        cp = closest_points(cset, o, d, method=closest, within_mm=within)
        select_contours(cp, cset, d, v.external, max_stab_distance_mm=10.0)
    t2 = time.perf_counter()
    return {"apparent": t1 - t0, "closest": t2 - t1,
            "segments": sum(ContourSet.from_contours(c).n_segments for c in conts)}


def run_benchmark(starts: int = 3, methods=("compiled", "blocks", "dense", "reference"),
                  seed: int = 0) -> pd.DataFrame:
    """Long-format rows: ``trial, method, metric, value, unit``."""
    scene = make_scene(paper_sizes=True)
    rows = []
    views = list(scene.views.values())
    n_paths = sum(v.n_paths for v in views)
    rngs = np.random.SeedSequence(seed).spawn(starts)
    for i, ss in enumerate(rngs):
        init = perturbed(scene.true, 7.0, 20.0, np.random.default_rng(ss))
        for method in methods:
            cpu0 = time.process_time()
            res = register(scene.surfaces, views, init, closest=method)
            cpu = time.process_time() - cpu0
            err = pin_errors(res.ct2robot, scene.true)
            parts = _time_parts(scene, init, method)
            its = max(res.iterations, 1)
            common = {"trial": i, "method": method}
            rows += [
                {**common, "metric": "time", "value": res.time_s, "unit": "s"},
                {**common, "metric": "cpu_time", "value": cpu, "unit": "s"},
                {**common, "metric": "time_per_iteration", "value": res.time_s / its,
                 "unit": "s"},
                {**common, "metric": "iterations", "value": res.iterations, "unit": ""},
                {**common, "metric": "converged", "value": float(res.converged), "unit": ""},
                {**common, "metric": "max_pin_error", "value": float(err.max()), "unit": "mm"},
                {**common, "metric": "time_apparent", "value": parts["apparent"], "unit": "s"},
                {**common, "metric": "time_closest", "value": parts["closest"], "unit": "s"},
                {**common, "metric": "contour_segments", "value": parts["segments"],
                 "unit": ""},
                {**common, "metric": "paths", "value": n_paths, "unit": ""},
            ]
        # the paper's hierarchy: Step A + B of one iteration only (pure Python, slow)
        parts = _time_parts(scene, init, "hierarchy")
        rows.append({"trial": i, "method": "hierarchy", "metric": "time_closest",
                     "value": parts["closest"], "unit": "s"})
    return pd.DataFrame(rows)


def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Median over starts, one row per method."""
    return df.pivot_table(index="method", columns="metric", values="value", aggfunc="median")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="write the long-format rows to this CSV")
    args = ap.parse_args(argv)
    df = run_benchmark(starts=args.starts, seed=args.seed)
    if args.out:
        df.to_csv(args.out, index=False)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(summary(df).round(4))


if __name__ == "__main__":
    main()
