"""Study ``surfaces``: CT bone surfaces from snake contours, scored against the true femur.

The chain of the paper (NOTES.md s2) on the simulated CT of the scene's phantom, at the
scene's slice protocol (the clinical one by default): simulated user clicks (a few points on
the true cross-section plus seeded noise, given on some slices and reused on the next ones),
two-stage snakes, tiling by dynamic programming, simplification within a tolerance. The
reconstructed proximal and distal surfaces are compared with the true femur surface
(distances from the reconstruction to the truth, mm), beside marching cubes on the same
volume (``skimage.measure.marching_cubes`` with the slices' true z positions).

The helpers :func:`simulated_clicks` and :func:`reconstruct_surfaces` are reused by the
registration studies: they are the simulated user, the only place where the truth (the true
cross-sections) touches the CT contours.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
import trimesh
from scipy import ndimage

from reglib.surface import Surface, surface_from_ct
from studies.common import markdown_table
from testbed.ct import CTScan, CTSpec, scan
from testbed.materials import material
from testbed.phantom import Phantom, make_phantom

TITLE = "CT surfaces from snake contours (tiling, simplification) vs marching cubes, vs truth"
DEFAULT_SCENE = "experiment2"

__all__ = ["TITLE", "DEFAULT_SCENE", "run", "true_sections", "simulated_clicks",
           "reconstruct_surfaces", "distances_to_truth", "marching_cubes_surface"]


# --------------------------------------------------------------------------- the simulated user
def true_sections(phantom: Phantom, z_mm: float, *, min_area_mm2: float = 20.0) -> list:
    """The true femur cross-section at z: a list of (K, 2) polygons (x, y) in ct mm."""
    sec = phantom.femur.section(plane_origin=[0.0, 0.0, z_mm], plane_normal=[0.0, 0.0, 1.0])
    if sec is None:
        return []
    out = []
    for d in sec.discrete:
        p = np.asarray(d, dtype=np.float64)[:, :2]
        x, y = p[:, 0], p[:, 1]
        if 0.5 * abs(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) >= min_area_mm2:
            out.append(p)
    return out


def simulated_clicks(polygon_px, n_clicks: int, noise_px: float, rng) -> np.ndarray:
    """A user's clicks along a true contour: ``n_clicks`` points evenly spaced by arc length
    (random phase) plus Gaussian noise of ``noise_px``; returns (n_clicks, 2) (x, y) px."""
    rng = np.random.default_rng(rng)
    p = np.asarray(polygon_px, dtype=np.float64)
    closed = np.vstack([p, p[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    t = (rng.uniform() + np.arange(n_clicks)) / n_clicks * s[-1]
    pts = np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])
    return pts + rng.normal(0.0, noise_px, pts.shape)


def _region_plan(phantom: Phantom, ct: CTScan, region: str, click_every_mm: float):
    """Slices to contour in a region, and which of them the user clicks on."""
    head = phantom.landmarks.get("head_center")
    slices, polys = [], []
    for k in ct.regions[region]:
        z = float(ct.slice_z_mm[k])
        sec = true_sections(phantom, z)
        if not sec:
            continue
        if region == "proximal" and len(sec) > 1:
            # The femoral head has separated from the neck and trochanter: stop (the head is
            # left out, as in the paper).
            break
        if region == "proximal" and head is not None and z > head[2]:
            break
        slices.append(int(k))
        polys.append(sec)
    clicked, last_z, last_n = [], -np.inf, -1
    for k, sec in zip(slices, polys, strict=True):
        z = float(ct.slice_z_mm[k])
        if len(sec) != last_n or z - last_z >= click_every_mm:
            clicked.append(k)
            last_z, last_n = z, len(sec)
    return slices, dict(zip(slices, polys, strict=True)), clicked


def reconstruct_surfaces(phantom: Phantom, ct: CTScan, *, rng=None, n_clicks: int = 10,
                         click_noise_px: float = 1.0, click_every_mm: float = 0.0,
                         simplify_tol_mm: float = 0.3, quality: str = "area",
                         regions=("proximal", "distal"), timings: dict | None = None) -> dict:
    """Proximal and distal surfaces from the CT, the user simulated from the truth.

    Returns region name -> (Surface, list of SliceContours). ``click_every_mm``: the user
    clicks again after this distance in z (and whenever the number of contours changes); 0:
    on every slice. ``timings`` (if given) receives seconds per stage.
    """
    rng = np.random.default_rng(rng)
    out = {}
    for region in regions:
        slices, polys, clicked = _region_plan(phantom, ct, region, click_every_mm)
        if len(slices) < 2:
            raise ValueError(f"region {region!r}: fewer than 2 slices cross the femur")
        clicks = {}
        for k in clicked:
            secs = sorted(polys[k], key=lambda p: float(np.mean(p[:, 0])))
            clicks[k] = [simulated_clicks(ct.ct_to_pixel(np.column_stack([p, np.zeros(len(p))])),
                                          n_clicks, click_noise_px, rng) for p in secs]
        t0 = time.perf_counter()
        surf, contours = surface_from_ct(ct.volume_hu, ct.slice2ct, slices, clicks,
                                         quality=quality, simplify_tol_mm=simplify_tol_mm)
        if timings is not None:
            timings[f"surface_{region}"] = time.perf_counter() - t0
        out[region] = (surf, contours)
    return out


# --------------------------------------------------------------------------- scoring
def distances_to_truth(phantom: Phantom, vertices, faces, *, n_samples: int = 20000,
                       rng=None) -> np.ndarray:
    """Distances (mm) from points of a surface (its vertices and area-weighted samples) to
    the true femur surface."""
    rng = np.random.default_rng(rng)
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(f), n_samples, p=area / area.sum())
    r = rng.uniform(size=(n_samples, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    t = tri[pick]
    pts = t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])
    pts = np.vstack([v, pts])
    _, d, _ = trimesh.proximity.closest_point(phantom.femur, pts)
    return d


def marching_cubes_surface(ct: CTScan, region: str, z_range_mm=None) -> Surface:
    """Marching cubes on one region of the volume at the bone/soft-tissue mid level.

    Vertex z comes from the slice positions (interpolated at fractional slice index); only
    the inside of the bone is first filled slice by slice (so that the inner surfaces of the
    cortex do not appear), the largest connected component kept, cut to ``z_range_mm``.
    """
    from skimage.measure import marching_cubes

    idx = np.asarray(ct.regions[region])
    level = 0.5 * (material("soft_tissue").hu + material("cortical_bone").hu)
    vol = np.array(ct.volume_hu[idx], dtype=np.float32)
    # Fill the bone slice by slice (holes of the thresholded section: marrow, cancellous
    # bone) with the cortical value, so that only the outer bone surface crosses the level.
    bone = vol > level
    for k in range(len(vol)):
        inner = ndimage.binary_fill_holes(bone[k]) & ~bone[k]
        vol[k][inner] = material("cortical_bone").hu
    verts, faces, _, _ = marching_cubes(vol, level=level)
    # verts are (slice, row, col) fractional indices.
    z = np.interp(verts[:, 0], np.arange(len(idx)), ct.slice_z_mm[idx])
    xy = ct.origin_xy_mm + verts[:, [2, 1]] * ct.pixel_mm
    v = np.column_stack([xy, z])
    m = trimesh.Trimesh(v, faces, process=True)
    parts = m.split(only_watertight=False)
    m = max(parts, key=lambda p: p.area)
    if z_range_mm is not None:
        zc = m.triangles_center[:, 2]
        keep = (zc >= z_range_mm[0]) & (zc <= z_range_mm[1])
        m = trimesh.Trimesh(m.vertices, m.faces[keep], process=True)
    # Marching cubes orients faces toward lower values; flip so normals point out of bone.
    return Surface(np.asarray(m.vertices), np.asarray(m.faces)[:, ::-1].copy(), {})


def _stats(d: np.ndarray) -> dict:
    return {"mean": float(np.mean(d)), "p95": float(np.percentile(d, 95)),
            "max": float(np.max(d))}


def _figure(path, phantom, items):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(12, 10))
    vmax = max(np.percentile(d, 99) for *_, d in items)
    for i, (title, surf, d) in enumerate(items):
        ax = fig.add_subplot(2, 2, i + 1, projection="3d")
        tri = surf.vertices[surf.faces]
        fd = d[surf.faces].mean(axis=1)
        cols = plt.cm.viridis(np.clip(fd / vmax, 0, 1))
        ax.add_collection3d(Poly3DCollection(tri, facecolors=cols, edgecolor="none"))
        lo, hi = surf.vertices.min(axis=0), surf.vertices.max(axis=0)
        c, r = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set_xlim(c[0] - r, c[0] + r)
        ax.set_ylim(c[1] - r, c[1] + r)
        ax.set_zlim(c[2] - r, c[2] + r)
        ax.view_init(elev=15, azim=-60)
        ax.set_title(f"{title}: {surf.n_triangles} triangles, vertex mean {d.mean():.2f} mm",
                     fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, vmax))
    fig.colorbar(sm, ax=fig.axes, shrink=0.6, label="distance to the true femur (mm)")
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- the study
def run(ctx) -> pd.DataFrame:
    scene = ctx.scene
    rng = np.random.default_rng(ctx.seed)
    t0 = time.perf_counter()
    ph_spec = scene.phantom
    ct_spec: CTSpec = scene.ct
    if ctx.quick:  # a smaller version for smoke tests: coarser meshes and sampling
        ph_spec = ph_spec.model_copy(update={"segments": min(ph_spec.segments, 32)})
        ct_spec = ct_spec.model_copy(update={"supersample": 1})
    phantom = make_phantom(ph_spec)
    t_ph = time.perf_counter() - t0
    t0 = time.perf_counter()
    ct = scan(phantom, ct_spec, rng=rng)
    t_ct = time.perf_counter() - t0
    timings = {"phantom": t_ph, "ct": t_ct}
    recon = reconstruct_surfaces(phantom, ct, rng=rng, timings=timings, click_every_mm=6.0)
    rows = []
    items = []
    for region, (surf, contours) in recon.items():
        zr = (min(c.z_mm for c in contours), max(c.z_mm for c in contours))
        mc = marching_cubes_surface(ct, region, zr)
        for method, s in (("contours", surf), ("marching_cubes", mc)):
            d = distances_to_truth(phantom, s.vertices, s.faces, rng=rng,
                                   n_samples=2000 if ctx.quick else 20000)
            for stat, val in _stats(d).items():
                rows.append(dict(trial=0, metric="surface_distance", value=val, unit="mm",
                                 surface=region, statistic=stat, method=method))
            rows.append(dict(trial=0, metric="triangles", value=float(s.n_triangles),
                             unit="count", surface=region, statistic="", method=method))
            items.append((f"{region}, {method}", s, d[:len(s.vertices)]))
        rows.append(dict(trial=0, metric="slices", value=float(len(contours)), unit="count",
                         surface=region, statistic="", method="contours"))
        rows.append(dict(trial=0, metric="simplification_bound", unit="mm",
                         value=float(surf.info.get("hausdorff_mm", 0.0)), surface=region,
                         statistic="max", method="contours"))
    for stage, sec in timings.items():
        rows.append(dict(trial=0, metric="time", value=float(sec), unit="s", surface="",
                         statistic=stage, method=""))
    df = pd.DataFrame(rows)
    fig = ctx.figure("surfaces_distance.png",
                     "Reconstructed surfaces coloured by their distance to the true femur (mm)")
    _figure(fig, phantom, items)
    tab = df[df.metric == "surface_distance"].pivot_table(
        index=["surface", "method"], columns="statistic", values="value").reset_index()
    tri = df[df.metric == "triangles"][["surface", "method", "value"]].rename(
        columns={"value": "triangles"})
    tab = tab.merge(tri, on=["surface", "method"])[["surface", "method", "mean", "p95", "max",
                                                      "triangles"]]
    tab["triangles"] = tab["triangles"].astype(int)
    ctx.report("Distance to the true femur surface (mm)",
               markdown_table(tab) + "\n\nCT: " + f"{len(ct.slice_z_mm)} slices, "
               f"{ct.pixel_mm} mm pixels; the paper's surfaces had 1664 (proximal) and 3913 "
               "(distal) triangles; goal: mean <= 0.5 mm.")
    ctx.report("Time per stage (s)", markdown_table(pd.DataFrame(
        {"stage": list(timings), "seconds": list(timings.values())})))
    return df
