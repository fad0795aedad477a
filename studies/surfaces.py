"""Study ``surfaces``: CT bone surfaces from snake contours, scored against the true femur.

The chain of the paper (NOTES.md s2) on the simulated CT of each case, at the scene's slice
protocol: the simulated operator's clicks (``testbed.operator``: a few points near the bone's
outline on the slice, with a seeded error, reused on the next slices), two-stage snakes,
tiling by dynamic programming, simplification within a tolerance. The reconstructed proximal
and distal surfaces are compared with the true femur surface both ways (``surface_distance``:
from the reconstruction to the truth; ``truth_distance``: from the truth between the first
and last slice outlined to the reconstruction; mm), beside marching cubes on the same volume
(``skimage.measure.marching_cubes`` with the slices' true z positions). Each trial is one
case (world and CT of case ``i`` of the study seed, as :func:`testbed.simulate.simulate_ct`
makes them); the figure shows case 0.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd
import trimesh
from scipy import ndimage

from reglib.pipeline import SURFACE_SIMPLIFY_TOL_MM
from reglib.surface import Surface, surface_from_ct
from studies.common import markdown_table
from testbed.ct import CTScan
from testbed.materials import material
from testbed.phantom import Phantom

TITLE = "CT surfaces from snake contours (tiling, simplification) vs marching cubes, vs truth"
DEFAULT_SCENE = "experiment2"
CASES = 3
QUICK_CASES = 1

__all__ = ["TITLE", "DEFAULT_SCENE", "run", "reconstruct_surfaces", "distances_to_truth",
           "distances_from_truth", "marching_cubes_surface"]


def reconstruct_surfaces(ct: CTScan, clicks: dict, *,
                         simplify_tol_mm: float = SURFACE_SIMPLIFY_TOL_MM,
                         quality: str = "area", timings: dict | None = None) -> dict:
    """Surfaces from the CT and the operator's clicks (region -> ``CtClicks``): region ->
    ``(Surface, list of SliceContours)``; ``timings`` (if given) receives s per region."""
    out = {}
    for region, cc in sorted(clicks.items()):
        t0 = time.perf_counter()
        out[region] = surface_from_ct(ct.volume_hu, ct.slice2ct, [int(k) for k in cc.slices],
                                      cc.clicks, quality=quality,
                                      simplify_tol_mm=simplify_tol_mm)
        if timings is not None:
            timings[f"surface_{region}"] = time.perf_counter() - t0
    return out


def _case_scene(scene, quick: bool):
    """The scene as the study simulates it: its own operator (until 2026-11-28 the study
    made the operator click again every 6 mm, where the scene's, and every run's, reuses
    its clicks over 10 mm by default: the study measured surfaces no run registers, a
    review, h80); ``quick``: coarser meshes and sampling."""
    update = {}
    if quick:  # a smaller version for smoke tests: coarser meshes and sampling
        update["phantom"] = scene.phantom.model_copy(
            update={"segments": min(scene.phantom.segments, 32)})
        update["ct"] = scene.ct.model_copy(update={"supersample": 1})
    return scene.model_copy(update=update)


def _case(tr, quick):
    from testbed.scene import load_scene
    from testbed.simulate import simulate_ct

    t0 = time.perf_counter()
    ctc = simulate_ct(_case_scene(load_scene(tr.scene), quick), tr.seed_sequence)
    timings = {"world+ct": time.perf_counter() - t0}
    recon = reconstruct_surfaces(ctc.ct, ctc.clicks, timings=timings)
    return ctc, recon, timings


def _surface_samples(vertices, faces, n_samples: int, rng) -> np.ndarray:
    """(n_samples, 3) points drawn uniformly by area on a triangle mesh (its frame, mm)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(f), n_samples, p=area / area.sum())
    r = rng.uniform(size=(n_samples, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    t = tri[pick]
    return t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])


def distances_to_truth(phantom: Phantom, vertices, faces, *, n_samples: int = 20000,
                       rng=None) -> np.ndarray:
    """Distances (mm) from points of a surface (its vertices and area-weighted samples) to
    the true femur surface."""
    rng = np.random.default_rng(rng)
    pts = np.vstack([np.asarray(vertices, np.float64),
                     _surface_samples(vertices, faces, n_samples, rng)])
    _, d, _ = trimesh.proximity.closest_point(phantom.femur, pts)
    return d


def distances_from_truth(phantom: Phantom, vertices, faces, z_range_mm, *,
                         n_samples: int = 20000, rng=None) -> np.ndarray:
    """Distances (mm) from area-weighted points of the true femur surface between the
    heights ``z_range_mm`` (ct mm: the slices a surface was made from) to the surface
    ``vertices``/``faces``.

    The other direction of :func:`distances_to_truth`: a surface can lie on the truth
    everywhere and still miss what lies between coarse slices (a condyle's curve, the lesser
    trochanter); only this direction sees it (a held-out review: 12 mm slices met the
    study's goal read one way)."""
    rng = np.random.default_rng(rng)
    femur = phantom.femur
    lo, hi = float(z_range_mm[0]), float(z_range_mm[1])
    zf = femur.vertices[femur.faces][:, :, 2]
    near = (zf.max(axis=1) >= lo) & (zf.min(axis=1) <= hi)
    if not near.any():
        return np.zeros(0)
    pts = _surface_samples(femur.vertices, femur.faces[near], 2 * n_samples, rng)
    pts = pts[(pts[:, 2] >= lo) & (pts[:, 2] <= hi)][:n_samples]
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                           process=False)
    _, d, _ = trimesh.proximity.closest_point(mesh, pts)
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


#: the study's goal: the contour surfaces' mean distance to the truth (mm), both ways
GOAL_MEAN_MM = 0.5
#: a contour surface's largest distance to the truth (mm) beyond which the report says so:
#: more than a slice's snake misses by its noise and the tiling by its chords (the distal
#: surfaces 2.3-2.5 mm at most over 3 cases, 2026-11-29; the proximal 3.6-5.8 mm, where the
#: snake cut a lobe off on streaked slices)
FAR_MM = 5.0


def worst_case_max(df: pd.DataFrame) -> dict:
    """(surface, way) -> ``(largest distance over the cases, its case)`` of the contour
    surfaces, ``way`` "to" (from the surface to the truth) or "from" (from the truth to the
    surface: what the surface leaves out)."""
    out = {}
    for metric, way in (("surface_distance", "to"), ("truth_distance", "from")):
        d = df[(df.metric == metric) & (df.method == "contours") & (df.statistic == "max")]
        for surface, g in d.groupby("surface"):
            i = g["value"].idxmax()
            out[surface, way] = (float(g.loc[i, "value"]), int(g.loc[i, "trial"]))
    return out


def _goal_lines(tab: pd.DataFrame, worst: dict | None = None) -> str:
    """Per contour surface, the goal met or missed, each way measured; and a note for a
    surface whose largest distance in some case, either way (``worst``,
    :func:`worst_case_max`), exceeds :data:`FAR_MM`."""
    lines = []
    for _, r in tab[tab.method == "contours"].iterrows():
        for col, way in (("mean", "to the truth"), ("truth's mean", "from the truth")):
            if col in r and np.isfinite(r[col]):
                word = "met" if r[col] <= GOAL_MEAN_MM else "**missed**"
                lines.append(f"- {word}: {r['surface']} surface, mean {r[col]:.2f} mm {way}")
    # a mean can meet the goal beside a slice outlined mm off the bone (a review, h87: a
    # 10.1 mm maximum went without a word; it was a condyle outlined as a sliver). The worst
    # case, not the mean of the cases' maxima (a review, h90: 3.6 / 3.9 / 5.8 mm averaged to
    # 4.4 and no note), and both ways: a lobe cut off shows from the truth's side
    for (surface, way), (mx, case) in sorted((worst or {}).items()):
        if mx > FAR_MM:
            what = ("reaches {:.1f} mm from the truth" if way == "to" else
                    "leaves the truth up to {:.1f} mm away").format(mx)
            lines.append(f"- **note**: the {surface} surface {what} in case {case}: a slice "
                         "outlined off the bone, which its mean hides; the figure shows case "
                         "0's surfaces")
    return "\n\n" + "\n".join(lines) if lines else ""


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
        # at the vertices alone, which the colours show: the table's mean adds points
        # spread over the triangles (a review, h87: both were called "mean")
        ax.set_title(f"{title}: {surf.n_triangles} triangles\nat its vertices mean "
                     f"{d.mean():.2f}, max {d.max():.2f} mm", fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
    sm = plt.cm.ScalarMappable(cmap="viridis", norm=plt.Normalize(0, vmax))
    top = max(float(d.max()) for *_, d in items)
    # the scale ends at the 99th percentile; say so where farther vertices share its colour
    label = "distance to the true femur (mm)" + (
        f"\nthe colour ends at {vmax:.2f} mm (99th percentile); farther: up to {top:.1f} mm"
        if top > vmax else "")
    fig.colorbar(sm, ax=fig.axes, shrink=0.6, label=label,
                 extend="max" if top > vmax else "neither")
    fig.savefig(path, dpi=90)
    plt.close(fig)


# --------------------------------------------------------------------------- the study
def trial(tr) -> list[dict]:
    quick = bool(tr.params["quick"])
    ctc, recon, timings = _case(tr, quick)
    phantom, ct = ctc.world.phantom, ctc.ct
    rng = tr.rng()
    rows = []
    for region, (surf, contours) in recon.items():
        zr = (min(c.z_mm for c in contours), max(c.z_mm for c in contours))
        mc = marching_cubes_surface(ct, region, zr)
        for method, srf in (("contours", surf), ("marching_cubes", mc)):
            n = 2000 if quick else 20000
            d = distances_to_truth(phantom, srf.vertices, srf.faces, rng=rng, n_samples=n)
            back = distances_from_truth(phantom, srf.vertices, srf.faces, zr, rng=rng,
                                        n_samples=n)
            for metric, dist in (("surface_distance", d), ("truth_distance", back)):
                for stat, val in (_stats(dist) if dist.size else {}).items():
                    rows.append(dict(metric=metric, value=val, unit="mm", surface=region,
                                     statistic=stat, method=method))
            rows.append(dict(metric="triangles", value=float(srf.n_triangles), unit="count",
                             surface=region, statistic="", method=method))
        rows.append(dict(metric="slices", value=float(len(contours)), unit="count",
                         surface=region, statistic="", method="contours"))
        rows.append(dict(metric="simplification_bound", unit="mm",
                         value=float(surf.info.get("hausdorff_mm", 0.0)), surface=region,
                         statistic="max", method="contours"))
    for stage, sec in timings.items():
        rows.append(dict(metric="time", value=float(sec), unit="s", surface="",
                         statistic=stage, method=""))
    return rows


def run(ctx) -> pd.DataFrame:
    from studies.runner import run_study_trials

    n = QUICK_CASES if ctx.quick else CASES
    df = run_study_trials(ctx, trial, [{"case": i, "quick": bool(ctx.quick)} for i in range(n)])
    ok = df[df.metric == "surface_distance"]
    if ok.empty:
        ctx.report("Distance to the true femur surface (mm)", "No case finished.")
        return df
    tab = ok.pivot_table(index=["surface", "method"], columns="statistic", values="value",
                         aggfunc="mean").reset_index()
    tri = df[df.metric == "triangles"].groupby(["surface", "method"])["value"].mean().rename(
        "triangles").reset_index()
    tab = tab.merge(tri, on=["surface", "method"])[["surface", "method", "mean", "p95", "max",
                                                      "triangles"]]
    tab["triangles"] = tab["triangles"].round().astype(int)
    back = df[df.metric == "truth_distance"]
    if len(back):     # results of before the truth's side was measured have none
        bt = back.pivot_table(index=["surface", "method"], columns="statistic",
                              values="value", aggfunc="mean").reset_index()
        bt = bt.rename(columns={k: f"truth's {k}" for k in ("mean", "p95", "max")})
        tab = tab.merge(bt[["surface", "method", "truth's mean", "truth's p95", "truth's max"]],
                        on=["surface", "method"], how="left")
    ctx.report("Distance to the true femur surface (mm)",
               markdown_table(tab) + f"\n\nMean over {ok['trial'].nunique()} case(s) of each "
               "case's statistic. `mean`, `p95`, `max`: from the reconstruction to the true "
               "femur"
               + (" (a surface on the truth wherever it is); `truth's ...`: from the true "
                  "femur, between the first and last slice outlined, to the reconstruction "
                  "(what it misses between slices, e.g. a condyle's curve)" if len(back)
                  else "")
               + ". The paper's surfaces had 1664 (proximal) and 3913 (distal) triangles; "
               f"goal: mean <= {GOAL_MEAN_MM} mm" + (" both ways" if len(back) else "") + "."
               + _goal_lines(tab, worst_case_max(df)))
    t = df[df.metric == "time"].groupby("statistic")["value"].median()
    ctx.report("Time per stage (s, median over the cases)", markdown_table(pd.DataFrame(
        {"stage": list(t.index), "seconds": list(t.values)})))
    # the figure: the first case that finished, again (same seed, same surfaces); a case
    # that failed would fail again here and lose the others' results
    from studies.runner import make_trials

    first = int(ok["trial"].min())
    tr0 = make_trials(str(ctx.scene_path), int(ctx.seed),
                      [{"case": i, "quick": ctx.quick} for i in range(first + 1)])[first]
    ctc, recon, _ = _case(tr0, bool(ctx.quick))
    items = []
    rng = np.random.default_rng(0)
    for region, (surf, contours) in recon.items():
        zr = (min(c.z_mm for c in contours), max(c.z_mm for c in contours))
        for method, srf in (("contours", surf),
                            ("marching_cubes", marching_cubes_surface(ctc.ct, region, zr))):
            d = distances_to_truth(ctc.world.phantom, srf.vertices, srf.faces, rng=rng,
                                   n_samples=1)
            items.append((f"{region}, {method}", srf, d[:len(srf.vertices)]))
    _figure(ctx.figure("surfaces_distance.png", f"Reconstructed surfaces of case {first} "
                       "coloured by their distance to the true femur (mm)"), ctc.world.phantom,
            items)
    return df
