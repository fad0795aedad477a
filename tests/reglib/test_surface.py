"""Tiling and surfaces: known contours -> tile -> manifold, oriented, exact vertices; DP vs
brute force; simplification within its tolerance."""

import numpy as np
import pytest
import trimesh

from reglib.surface import (
    Surface,
    check_manifold,
    simplify_surface,
    surface_distances,
    surface_distances_fast,
    surface_from_contours,
    tile_pair,
)


def _ellipse(cx, cy, a, b, z, n, phase=0.0, clockwise=False):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False) + phase
    if clockwise:
        t = t[::-1]
    return np.column_stack([cx + a * np.cos(t), cy + b * np.sin(t), np.full(n, z)])


def _outward_fraction(vertices, faces, centre_of):
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(axis=1)
    radial = c[:, :2] - centre_of(c)
    return np.mean(np.einsum("ij,ij->i", n[:, :2], radial) > 0)


def test_tiling_two_circles_gives_an_oriented_strip_on_the_contour_vertices():
    a = _ellipse(0, 0, 10, 10, 0.0, 24)
    b = _ellipse(0.5, 0, 9, 9, 2.0, 17, phase=0.4, clockwise=True)
    faces, cost = tile_pair(a, b)
    assert faces.shape == (24 + 17, 3)
    v = np.vstack([a, b])
    # Every vertex of both contours is used, and only those.
    assert set(np.unique(faces)) == set(range(41))
    info = check_manifold(v, faces)
    assert info["manifold"] and info["max_faces_per_edge"] == 2
    # A strip: the boundary is exactly the two contours' edges.
    assert info["boundary_edges"] == 24 + 17
    m = trimesh.Trimesh(v, faces, process=False)
    assert m.is_winding_consistent
    assert _outward_fraction(v, faces, lambda c: np.zeros((len(c), 2))) == 1.0
    assert cost == pytest.approx(m.area, rel=1e-9)


@pytest.mark.parametrize("quality", ["area", "compactness"])
def test_dynamic_programming_finds_the_brute_force_optimum(quality):
    rng = np.random.default_rng(42)
    for _ in range(8):
        m, n = rng.integers(3, 10, size=2)
        a = _ellipse(0, 0, 10, 7, 0.0, m) + np.r_[rng.normal(0, 1.0, (m, 2)).T, [np.zeros(m)]].T
        b = _ellipse(1, 0, 8, 9, 3.0, n) + np.r_[rng.normal(0, 1.0, (n, 2)).T, [np.zeros(n)]].T
        f_dp, c_dp = tile_pair(a, b, quality=quality)
        f_bf, c_bf = tile_pair(a, b, quality=quality, method="brute_force")
        assert c_dp == pytest.approx(c_bf, abs=1e-9)
        # Start at other pairs too: still the optimum for that start.
        s = (int(rng.integers(m)), int(rng.integers(n)))
        assert tile_pair(a, b, quality=quality, start=s)[1] == pytest.approx(
            tile_pair(a, b, quality=quality, start=s, method="brute_force")[1], abs=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_dp_equals_the_numpy_recursion(seed):
    """The compiled tiling DP against the numpy one on random cost tables of contour
    sizes the CT gives (up to 300 x 300 vertices): the same path, the same total."""
    from reglib.surface import _dp, _dp_numpy

    rng = np.random.default_rng(seed)
    for _ in range(5):
        m, n = (int(x) for x in rng.integers(1, 300, 2))
        ci, cj = rng.uniform(0, 1, (m, n + 1)), rng.uniform(0, 1, (m + 1, n))
        c1, s1 = _dp(ci, cj)
        c2, s2 = _dp_numpy(ci, cj)
        assert c1 == pytest.approx(c2, rel=1e-12) and np.array_equal(s1, s2)
        assert s1.sum() == n and len(s1) == m + n


def test_ellipse_into_two_circles_branching_is_manifold_and_oriented():
    slices = [
        [_ellipse(-12, 0, 6, 6, 0.0, 30), _ellipse(12, 0, 6, 6, 0.0, 30)],
        [_ellipse(-12, 0, 6.5, 6.5, 1.0, 32), _ellipse(12, 0, 6.5, 6.5, 1.0, 32)],
        [_ellipse(0, 0, 20, 8, 2.0, 70)],
        [_ellipse(0, 0, 19, 8, 3.0, 66, phase=0.2, clockwise=True)],
    ]
    s = surface_from_contours(slices)
    # The vertices are exactly the contour vertices, in order.
    np.testing.assert_array_equal(s.vertices, np.vstack([c for sl in slices for c in sl]))
    assert set(np.unique(s.faces)) == set(range(len(s.vertices)))
    info = check_manifold(s.vertices, s.faces)
    assert info["manifold"], info
    # Open at both ends: the boundary is the lowest two circles and the highest ellipse.
    assert info["boundary_edges"] == 30 + 30 + 66
    assert trimesh.Trimesh(s.vertices, s.faces, process=False).is_winding_consistent

    def centre(c):
        out = np.zeros((len(c), 2))
        low = c[:, 2] < 1.0
        out[low, 0] = np.sign(c[low, 0]) * 12
        return out

    # Normals point outward: everywhere on the two branches, and on all but the crotch
    # between them (where "outward from the axis" is not defined) above.
    low = s.vertices[s.faces].mean(axis=1)[:, 2] < 1.0
    assert _outward_fraction(s.vertices, s.faces[low], centre) == 1.0
    assert _outward_fraction(s.vertices, s.faces[~low], centre) > 0.9
    # two slices of which no contour overlaps one of the other: nothing to join
    with pytest.raises(ValueError, match="none of one slice overlaps"):
        surface_from_contours([slices[0], [_ellipse(0, 0, 3, 3, 5.0, 10)] * 3])


@pytest.mark.parametrize("name", ["one into three", "a new island", "islands end",
                                  "a notch in one slice", "two into two across"])
def test_any_counts_of_contours_tile_by_overlap_into_an_oriented_manifold(name):
    """Three cross-sections in a slice (a ridge or an osteophyte of a real femur): the
    contours that overlap across two slices are bridged into one loop per slice and tiled,
    a contour overlapping none is left out of that strip; every strip manifold, the
    winding consistent, and the boundary exactly the end slices' edges."""
    e = _ellipse
    slices, open_ends, unused = {
        "one into three": (
            [[e(0, 0, 25, 8, 0, 80)], [e(0, 0, 24, 8, 1, 78)],
             [e(-15, 0, 6, 6, 2, 30), e(0, 0, 5, 5, 2, 28), e(15, 0, 6, 6, 2, 30)],
             [e(-15, 0, 5.5, 6, 3, 30), e(0, 0, 5, 5, 3, 28), e(15, 0, 6, 5.5, 3, 30)]],
            80 + 30 + 28 + 30, 0),
        "a new island": (    # 2 -> 3 -> 2: the island is tiled with nothing
            [[e(-12, 0, 6, 6, 0, 30), e(12, 0, 6, 6, 0, 30)],
             [e(-12, 0, 6, 6, 1, 30), e(12, 0, 6, 6, 1, 30), e(0, 20, 2, 2, 1, 12)],
             [e(-12, 0, 6, 6, 2, 30), e(12, 0, 6, 6, 2, 30)]],
            4 * 30, 12),
        "islands end": (     # 3 -> 1: two small contours beside the bone end there
            [[e(0, 0, 10, 10, 0, 40), e(30, 0, 2, 2, 0, 10), e(-30, 0, 2, 2, 0, 10)],
             [e(0, 0, 10, 10, 1, 40)]],
            40 + 40, 20),
        "a notch in one slice": (   # 1 -> 2 -> 1: bridged for both strips, not twice
            [[e(0, 0, 20, 8, 0, 70)],    # at the same vertices (an edge of 4 triangles)
             [e(-10, 0, 8, 6, 1, 40), e(10, 0, 8, 6, 1, 40)],
             [e(0, 0, 20, 8, 2, 70)]],
            70 + 70, 0),
        "two into two across": (   # each lower contour overlaps both upper ones
            [[e(-6, 0, 5, 5, 0, 30), e(6, 0, 5, 5, 0, 30)],
             [e(0, -5, 7, 4, 1, 30), e(0, 5, 7, 4, 1, 30)]],
            4 * 30, 0),
    }[name]
    s = surface_from_contours(slices)
    np.testing.assert_array_equal(s.vertices, np.vstack([c for sl in slices for c in sl]))
    info = check_manifold(s.vertices, s.faces)
    assert info["manifold"] and info["max_faces_per_edge"] == 2, info
    assert trimesh.Trimesh(s.vertices, s.faces, process=False).is_winding_consistent
    # an island that overlaps nothing in either neighbour has no triangle
    assert len(s.vertices) - len(np.unique(s.faces)) == unused
    # the boundary: the lowest and the highest slice's contours (a bridge's two sides
    # each get one triangle of the strip, so it is no boundary)
    assert info["boundary_edges"] == open_ends


def test_surface_of_a_cylinder_is_exact_and_simplifies_within_tolerance():
    rng = np.random.default_rng(0)
    slices = [[_ellipse(0, 0, 15, 12, z, 90, phase=rng.uniform())] for z in np.arange(0, 30.0, 1)]
    s = surface_from_contours(slices, quality="compactness")
    assert check_manifold(s.vertices, s.faces)["manifold"]
    simp = simplify_surface(s, 0.2)
    assert simp.n_triangles < 0.5 * s.n_triangles
    assert check_manifold(simp.vertices, simp.faces)["manifold"]
    # The verified bound holds, both ways (exact distances, recomputed here).
    assert simp.info["hausdorff_mm"] <= 0.2
    assert surface_distances(s.vertices, simp.vertices, simp.faces).max() <= 0.2 + 1e-9
    assert surface_distances(simp.vertices, s.vertices, s.faces).max() <= 0.2 + 1e-9
    assert simplify_surface(s, 0.0) is s
    # Contour-level simplification (the default): a manifold on a subset of the vertices.
    sc = surface_from_contours(slices, quality="compactness", simplify_tol_mm=0.2)
    assert sc.n_triangles < 0.6 * s.n_triangles
    assert check_manifold(sc.vertices, sc.faces)["manifold"]
    assert {tuple(p) for p in sc.vertices} <= {tuple(p) for p in s.vertices}
    assert surface_distances(s.vertices, sc.vertices, sc.faces).max() <= 0.2 + 1e-9
    with pytest.raises(ValueError, match="tolerance"):
        simplify_surface(s, -1.0)


def test_surface_distances_match_brute_force():
    rng = np.random.default_rng(5)
    s = surface_from_contours([[_ellipse(0, 0, 5, 4, z, 12)] for z in (0.0, 2.0, 4.0)])
    pts = rng.uniform(-8, 8, (50, 3))
    got = surface_distances(pts, s.vertices, s.faces)
    # Brute force: dense barycentric sampling of every triangle.
    w = np.array([(i, j) for i in range(41) for j in range(41 - i)]) / 40.0
    tri = s.vertices[s.faces]
    dense = (tri[:, None, 0] + w[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0])
             + w[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0])).reshape(-1, 3)
    ref = np.min(np.linalg.norm(pts[:, None] - dense[None], axis=2), axis=1)
    assert np.all(got <= ref + 1e-9) and np.all(ref - got < 0.1)


def test_fast_distances_agree_with_exact_where_it_matters():
    rng = np.random.default_rng(8)
    slices = [[_ellipse(0, 0, 12, 9, z, 40, phase=rng.uniform())] for z in (0.0, 3.0, 9.0)]
    s = surface_from_contours(slices)
    pts = s.vertices[s.faces].mean(axis=1) + rng.normal(0, 0.5, (len(s.faces), 3))
    exact = surface_distances(pts, s.vertices, s.faces)
    for tol in (0.1, 0.4):
        fast = surface_distances_fast(pts, s.vertices, s.faces, tol_mm=tol, k=3)
        assert np.all(fast >= exact - 1e-9)                 # an upper bound everywhere
        np.testing.assert_allclose(fast[fast > tol], exact[fast > tol], atol=1e-9)
        np.testing.assert_array_equal(fast <= tol, exact <= tol)


def test_bad_contours_raise():
    with pytest.raises(ValueError, match="at least 3 points"):
        tile_pair(_ellipse(0, 0, 5, 5, 0, 2), _ellipse(0, 0, 5, 5, 1, 8))
    with pytest.raises(ValueError, match="shape"):
        tile_pair(np.zeros((5, 2)), _ellipse(0, 0, 5, 5, 1, 8))
    with pytest.raises(ValueError, match="increasing z"):
        surface_from_contours([[_ellipse(0, 0, 5, 5, 1, 8)], [_ellipse(0, 0, 5, 5, 0, 8)]])
    with pytest.raises(ValueError, match="at least 2 slices"):
        surface_from_contours([[_ellipse(0, 0, 5, 5, 1, 8)]])
    assert isinstance(Surface(np.zeros((3, 3)), np.array([[0, 1, 2]])).n_triangles, int)


@pytest.mark.parametrize("seed", range(4))
def test_compiled_douglas_peucker_keeps_what_scikit_image_keeps(seed):
    """_decimate's compiled Douglas-Peucker against skimage's approximate_polygon (the
    reference): the same vertices of noisy closed contours, at several tolerances."""
    from reglib.surface import _decimate

    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0, 2 * np.pi, 300))
    r = 20 + 3 * np.sin(5 * t) + rng.normal(0, 0.3, t.size)
    c = np.column_stack([r * np.cos(t), r * np.sin(t), np.full(t.size, 7.0)])
    for tol in (0.0, 0.05, 0.3, 1.0, 5.0, 50.0):
        fast = _decimate(c, tol)
        ref = _decimate(c, tol, reference=True)
        np.testing.assert_array_equal(fast, ref)
        if 0.0 < tol < 1.0:
            assert 3 <= len(fast) < len(c)


def test_points_in_polygon_equals_matplotlibs_path_on_random_polygons():
    from matplotlib.path import Path

    from reglib.surface import points_in_polygon

    rng = np.random.default_rng(3)
    for _ in range(20):
        k = int(rng.integers(3, 40))
        t = np.sort(rng.uniform(0, 2 * np.pi, k))
        r = rng.uniform(2, 10, k)
        poly = np.column_stack([r * np.cos(t), r * np.sin(t)])  # star-shaped, often concave
        if rng.uniform() < 0.5:
            poly = poly[::-1]
        pts = rng.uniform(-11, 11, (500, 2))
        np.testing.assert_array_equal(points_in_polygon(pts, poly),
                                      Path(poly).contains_points(pts))


def test_a_slice_cutting_one_condyle_below_two_continues_that_one_only():
    """The lowest slice of a real femur cuts one condyle, the next ones both: the lone
    contour is tiled with the condyle it lies under, and the other condyle's lowest contour
    is an open end (bridging the lone contour to both gave edges of four triangles)."""
    slices = [
        [_ellipse(12, 0, 4, 4, 0.0, 24)],                       # the lower condyle's tip
        [_ellipse(-12, 0, 5, 5, 1.0, 26), _ellipse(12, 0, 6, 6, 1.0, 30)],
        [_ellipse(-12, 0, 6, 6, 2.0, 30), _ellipse(12, 0, 6.5, 6.5, 2.0, 32)],
        [_ellipse(0, 0, 20, 8, 3.0, 70)],                       # the condyles merged
    ]
    s = surface_from_contours(slices)
    info = check_manifold(s.vertices, s.faces)
    assert info["manifold"] and info["max_faces_per_edge"] == 2, info
    # Open ends: the tip's contour, the other condyle's lowest contour, the top ellipse.
    assert info["boundary_edges"] == 24 + 26 + 70
    assert trimesh.Trimesh(s.vertices, s.faces, process=False).is_winding_consistent
    # The tip is joined to the condyle above it, not to the other one.
    tip = np.arange(24)
    other_low = np.arange(24, 24 + 26)
    tip_faces = s.faces[np.isin(s.faces, tip).any(axis=1)]
    assert not np.isin(tip_faces, other_low).any()
    # The same from above: a lone contour over one of two below.
    flipped = [[c * np.array([1, 1, -1]) for c in sl] for sl in slices[::-1]]
    flipped = [[c[::-1] for c in sl] for sl in flipped]
    info = check_manifold(*_tiled(flipped))
    assert info["manifold"] and info["max_faces_per_edge"] == 2, info


def _tiled(slices):
    s = surface_from_contours(slices)
    return s.vertices, s.faces


def test_contours_too_small_to_tile_are_left_out_with_their_empty_slices():
    """A snake on a condyle's tip that the slice grazes can shrink to a segment (seen on a
    clinic case with the anatomical knee: 'a contour needs at least 3 points, got 2'); such
    contours, and a slice left without a contour, are not tiled."""
    from reglib.surface import MIN_CONTOUR_AREA_MM2, tileable_contours

    segment = np.array([[10.0, 0.0, 0.0], [11.0, 0.0, 0.0]])
    sliver = _ellipse(12, 0, 1.0, 0.5, 1.0, 12)          # 1.6 mm^2
    assert np.pi * 1.0 * 0.5 < MIN_CONTOUR_AREA_MM2
    slices = [
        [_ellipse(-12, 0, 5, 5, 0.0, 26), segment],
        [sliver],
        [_ellipse(-12, 0, 6, 6, 2.0, 30), _ellipse(12, 0, 6, 6, 2.0, 30)],
        [_ellipse(0, 0, 20, 8, 3.0, 70)],
    ]
    kept = tileable_contours(slices)
    assert [len(s) for s in kept] == [1, 2, 1]
    np.testing.assert_array_equal(kept[0][0], slices[0][0])
    s = surface_from_contours(kept)
    info = check_manifold(s.vertices, s.faces)
    assert info["manifold"] and info["boundary_edges"] == 26 + 30 + 70, info


#: two contours of a grazed condyle's tip on neighbouring slices (a clinic case with the
#: anatomical knee, rounded to 0.1 mm): the upper one crosses itself, and the strip from
#: their closest pair ran along one contour from the start and back over the same vertices
#: at the end (an edge of four triangles)
_TIP_LOW = [[17.8, -12.5], [18.2, -14.1], [18.7, -15.6], [19.4, -17.1], [20.2, -18.4],
            [21.2, -19.7], [22.5, -20.6], [24.0, -21.2], [25.6, -21.0], [27.0, -20.2],
            [28.2, -19.1], [29.2, -17.9], [29.9, -16.4], [30.5, -14.9], [31.1, -13.4],
            [29.7, -13.2], [28.2, -13.5], [26.7, -13.5], [25.4, -11.8], [23.7, -13.0],
            [22.1, -11.3], [20.7, -13.3], [19.1, -12.9]]
_TIP_HIGH = [[25.3, -0.6], [21.4, -2.6], [20.2, -4.7], [21.6, -7.5], [23.1, -7.8],
             [24.4, -8.0], [25.1, -8.6], [25.5, -8.9], [26.0, -7.9], [25.2, -7.6],
             [24.0, -7.7], [23.3, -8.2], [23.9, -9.3], [24.2, -8.9], [25.0, -8.4],
             [27.2, -8.7], [25.9, -6.9], [27.6, -5.3], [27.5, -3.8]]


def test_a_strip_that_would_fold_onto_itself_is_tiled_from_another_start():
    from reglib.surface import _ccw, _strip_is_manifold, _tile_indices

    a = np.column_stack([_TIP_LOW, np.full(len(_TIP_LOW), 10.6)])
    b = np.column_stack([_TIP_HIGH, np.full(len(_TIP_HIGH), 11.6)])
    v = np.vstack([a, b])
    la, lb = _ccw(np.arange(len(a)), v), _ccw(np.arange(len(b)) + len(a), v)
    # the closest pair's strip is the defect this guards against
    assert not _strip_is_manifold(_tile_indices(la, lb, v, "area", "dp", None)[0])
    slices = [[_ellipse(-24, 0, 16, 10, 10.6, 60), a],
              [_ellipse(-24, 0, 16.5, 10, 11.6, 62), b],
              [_ellipse(0, -5, 30, 14, 12.6, 90)]]
    for tol in (None, 0.3):
        s = surface_from_contours(slices, simplify_tol_mm=tol)
        info = check_manifold(s.vertices, s.faces)
        assert info["manifold"] and info["max_faces_per_edge"] == 2, (tol, info)


def test_strip_check_equals_counting_edges_with_numpy_unique():
    from reglib.surface import _strip_is_manifold

    rng = np.random.default_rng(8)
    seen = set()
    for _ in range(300):
        f = rng.integers(0, 12, size=(int(rng.integers(2, 20)), 3))
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        if not len(f):
            continue
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ref = np.unique(e, axis=0, return_counts=True)[1].max() <= 2
        assert _strip_is_manifold(f) == ref
        seen.add(bool(ref))
    assert seen == {True, False}


def test_bad_faces_methods_and_counts_are_named():
    """A review's inputs that failed deep inside (numpy's remainder on text faces, trimesh's
    IndexError) or passed (indices out of range called manifold; an unknown tiling method
    named as brute force's size limit)."""
    from reglib.apparent import prepare_surface
    from reglib.pose import p3l_solutions
    from reglib.surface import check_manifold, surface_distances, surface_distances_fast

    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    for bad, message in ((f.astype(str), "expected integer vertex indices, got an array of <U"),
                         (f + 0j, "expected integer vertex indices, got an array of complex"),
                         (f + 10, r"vertex indices must be in \[0, 3\], got \[10, 13\]"),
                         ([[0, 1, 2], [0, 1]], "expected an \\(F, 3\\) array of vertex indices"),
                         (f + 0.5, "expected integer vertex indices$")):
        with pytest.raises(ValueError, match="faces: " + message):
            prepare_surface(v, bad)
    with pytest.raises(ValueError, match=r"faces: vertex indices must be in \[0, 3\]"):
        check_manifold(v, f + 10)
    with pytest.raises(ValueError, match=r"faces: vertex indices must be in \[0, 3\]"):
        surface_distances(np.zeros((2, 3)), v, f + 10)
    with pytest.raises(ValueError, match="k: expected an integer >= 1"):
        surface_distances_fast(np.zeros((2, 3)), v, f, tol_mm=0.1, k=0)
    with pytest.raises(ValueError, match="tol_mm: expected a finite distance"):
        surface_distances_fast(np.zeros((2, 3)), v, f, tol_mm=float("nan"))
    assert check_manifold(v, f)["manifold"]
    ring = np.column_stack([np.cos(np.linspace(0, 6, 8)), np.sin(np.linspace(0, 6, 8)),
                            np.zeros(8)])
    with pytest.raises(ValueError, match="tile_pair: method must be 'dp' or 'brute_force', got "
                                         "'greedy'"):
        tile_pair(ring, ring + [0, 0, 1], method="greedy")
    with pytest.raises(ValueError, match=r"tile_pair: start \(9, 0\) is outside"):
        tile_pair(ring, ring + [0, 0, 1], start=(9, 0))
    d = np.tile([0.0, 0.0, 1.0], (2, 1))
    with pytest.raises(ValueError, match=r"p3l_solutions: expected three points and three "
                                         r"lines"):
        p3l_solutions(v[:2], np.zeros((2, 3)), d)


def test_slices_closer_than_a_millimetre_are_grouped_into_slabs():
    """reglib.surface.slice_slabs: from the lowest slice up, each slab the slices within
    MIN_SLICE_GAP_MM (1 mm, or a pixel if larger) of its lowest; slices 1 mm apart or more
    are a slab each."""
    from reglib.surface import slice_slabs

    def affines(z, px=0.8):
        a = np.tile(np.eye(4), (len(z), 1, 1))
        a[:, 0, 0] = a[:, 1, 1] = px
        a[:, 2, 3] = z
        return a

    z = np.round(np.arange(0.0, 3.01, 0.2), 6)
    slabs = slice_slabs(affines(z), range(len(z)))
    assert [[float(z[k]) for k in s] for s in slabs] == [
        [0.0, 0.2, 0.4, 0.6, 0.8], [1.0, 1.2, 1.4, 1.6, 1.8], [2.0, 2.2, 2.4, 2.6, 2.8], [3.0]]
    coarse = np.array([0.0, 1.0, 2.0, 8.0, 14.0])      # the clinical schedule's kind
    assert slice_slabs(affines(coarse), range(5)) == [[0], [1], [2], [3], [4]]
    assert slice_slabs(affines(coarse, px=1.5), range(5)) == [[0, 1], [2], [3], [4]]
    # indices outside the volume are left for contours_from_ct to refuse, naming them
    assert slice_slabs(affines(z), [0, 1, 99]) == [[0], [1], [99]]
    assert slice_slabs(affines(z), [-1, 0, 1]) == [[-1], [0], [1]]


def test_a_cylinder_from_slices_much_closer_than_a_pixel_keeps_its_normals():
    """CT slices 0.2 mm apart with 0.8 mm pixels (a held-out scene): each snake contour lies
    a fraction of a pixel off the outline, and tiled 0.2 mm apart those errors tilted the
    wall's normals far out of the slice plane (the registration matches the surface's
    apparent contours, which follow the normals). Averaged into 1 mm slabs, a vertical
    wall's normals stay near the plane, and the contours lie on the outline."""
    from reglib.surface import surface_from_ct
    from tests.reglib.test_contours import _ellipse_image

    rng = np.random.default_rng(4)
    z = np.round(np.arange(0.0, 12.01, 0.2), 6)
    img = _ellipse_image((70, 70), 35.0, 35.0, 18.0, 14.0, 0.3, level=1200.0)
    vol = np.stack([img + rng.normal(0.0, 150.0, img.shape) for _ in z])
    s2c = np.tile(np.eye(4), (len(z), 1, 1))
    s2c[:, 0, 0] = s2c[:, 1, 1] = 0.8
    s2c[:, 2, 3] = z
    clicks = {0: [np.column_stack([35 + 17 * np.cos(t), 35 + 13 * np.sin(t)])
                  for t in [np.linspace(0.3, 0.3 + 2 * np.pi, 6, endpoint=False)]]}
    surf, contours = surface_from_ct(vol, s2c, range(len(z)), clicks, simplify_tol_mm=None)
    assert len(contours) == 13                     # 61 slices in slabs of 1 mm
    assert [c.slice_index for c in contours] == list(range(0, 61, 5))
    # the slabs' contours on the ellipse (semi-axes 18 x 14 px of 0.8 mm, turned 0.3 rad)
    c, sn = np.cos(0.3), np.sin(0.3)
    for sc in contours:
        p = sc.contours_ct[0][:, :2] / 0.8 - 35.0
        u, v = c * p[:, 0] + sn * p[:, 1], -sn * p[:, 0] + c * p[:, 1]
        r = np.sqrt((u / 18.0) ** 2 + (v / 14.0) ** 2)
        assert np.abs(r - 1.0).mean() < 0.02
    tri = surf.vertices[surf.faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # tilt out of the slice plane (every slice tiled: median 0.30, half the faces > 0.3)
    assert np.median(np.abs(n[:, 2])) < 0.12 and np.mean(np.abs(n[:, 2]) > 0.3) < 0.05


@pytest.mark.parametrize("seed", range(3))
def test_triangle_areas_from_coordinate_planes_equal_the_reference(seed):
    """The tiling's triangle areas made from the coordinates' planes against np.cross and
    np.linalg.norm, on the broadcast shapes of both cost tables: the same bits."""
    from reglib.surface import _tri_cost

    rng = np.random.default_rng(seed)
    for _ in range(40):
        m, n = (int(v) for v in rng.integers(3, 60, 2))
        a = rng.normal(0.0, 10.0 ** rng.uniform(-1, 3), (m, 3))
        b = rng.normal(0.0, 10.0 ** rng.uniform(-1, 3), (n, 3))
        for args in ((a[:-1, None], a[1:, None], b[None, :]),
                     (a[:, None], b[None, 1:], b[None, :-1])):
            got = _tri_cost(*args, "area")
            ref = _tri_cost(*args, "area", reference=True)
            assert got.shape == ref.shape
            np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("where", ["end", "middle"])
def test_a_slice_whose_contours_continue_no_neighbour_is_left_out_of_the_surface(where):
    """A review (2026-11-27) set the simulated operator's bone threshold to 150 HU: slices at
    the femur's end were outlined around something 20 mm off the bone, and the whole CT
    surface failed ("cannot be tiled"). Such slices are now left out, the largest run of
    slices that continue one another is tiled, and the surface says which z it left out."""
    zs = np.arange(0.0, 16.0, 2.0)
    # two condyles per slice; the stray slice holds two small blobs 40 mm away
    stack = [[_ellipse(-15, 0, 10, 8, z, 40), _ellipse(15, 0, 10, 8, z, 40)] for z in zs]
    k = 0 if where == "end" else 3
    stack[k] = [_ellipse(-15, 40, 3, 3, zs[k], 16), _ellipse(15, 40, 3, 3, zs[k], 16)]
    surf = surface_from_contours(stack)
    assert surf.info["left_out_z_mm"] == ((zs[0],) if where == "end" else tuple(zs[:4]))
    kept = len(zs) - len(surf.info["left_out_z_mm"])
    assert surf.info["n_slices"] == kept
    assert check_manifold(surf.vertices, surf.faces)["manifold"]
    # the surface is the condyles': nothing of the blobs, every kept slice's contour in it
    assert surf.vertices[:, 1].max() < 8.0 + 1e-9
    assert np.ptp(surf.vertices[:, 2]) == pytest.approx(zs[-1] - zs[len(zs) - kept])
    # a stack that continues throughout leaves nothing out
    whole = [[_ellipse(-15, 0, 10, 8, z, 40), _ellipse(15, 0, 10, 8, z, 40)] for z in zs]
    assert surface_from_contours(whole).info["left_out_z_mm"] == ()
