"""Mutation audit 3: surface_from_contours' simplification check measures the full
surface's vertices against the SIMPLIFIED surface and reports that distance as
info["hausdorff_mm"]. Measuring the other way (the simplified vertices, a subset of the
full ones, against the full surface: always 0) passed every test."""
import numpy as np

from reglib.surface import surface_distances, surface_from_contours


def _ellipse(a, b, z, n, phase):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) + phase
    return np.column_stack([a * np.cos(t), b * np.sin(t), np.full(n, z)])


def test_reported_hausdorff_is_the_full_surfaces_distance_to_the_simplified_one():
    rng = np.random.default_rng(0)
    slices = [[_ellipse(15, 12, z, 90, rng.uniform())] for z in np.arange(0, 30.0, 1)]
    full = surface_from_contours(slices, quality="compactness")
    sc = surface_from_contours(slices, quality="compactness", simplify_tol_mm=0.2)
    assert sc.n_triangles < 0.6 * full.n_triangles
    h = float(surface_distances(full.vertices, sc.vertices, sc.faces).max())
    assert 0.02 < h <= 0.2 + 1e-9
    assert abs(sc.info["hausdorff_mm"] - h) < 1e-6, (sc.info["hausdorff_mm"], h)
