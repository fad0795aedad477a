"""Closest points between lines and contours: the three fast methods against the plain
brute force on random polylines and lines (1e-9 mm), the reference against first-order
optimality, the paper's radius r, the stabbing test and the selection rule, bad input."""

import numpy as np
import pytest
import trimesh

from reglib.apparent import apparent_contours, prepare_surface
from reglib.closest import (
    ContourSet,
    closest_points,
    match_contours,
    select_contours,
    stabbing,
)


def random_case(rng, n_lines=120, n_contours=5):
    polys, closed = [], []
    for _ in range(n_contours):
        k = int(rng.integers(2, 120))
        steps = rng.normal(size=(k, 3)) * rng.uniform(0.5, 6.0)
        polys.append(np.cumsum(steps, axis=0) + rng.normal(size=3) * 40.0)
        closed.append(bool(rng.integers(0, 2)) and k >= 3)
    cs = ContourSet.from_polylines(polys, closed)
    # lines from near a common center (like X-ray paths), plus some random ones
    c = np.array([0.0, 0.0, -600.0]) + rng.normal(size=3) * 5
    tgt = rng.normal(size=(n_lines, 3)) * 40.0
    o = c + rng.normal(size=(n_lines, 3))
    o[: n_lines // 4] = rng.normal(size=(n_lines // 4, 3)) * 100
    d = tgt - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # origins anywhere along the lines
    o = o + rng.uniform(-300, 300, size=(n_lines, 1)) * d
    return cs, o, d


@pytest.mark.parametrize("method", ["dense", "blocks", "hierarchy", "compiled"])
def test_fast_methods_agree_with_brute_force(method):
    rng = np.random.default_rng(10)
    for _ in range(6):
        cs, o, d = random_case(rng)
        ref = closest_points(cs, o, d, method="reference")
        got = closest_points(cs, o, d, method=method)
        assert got.distance.shape == (len(o), cs.n_contours)
        np.testing.assert_allclose(got.distance, ref.distance, atol=1e-9, rtol=0)
        np.testing.assert_allclose(got.p, ref.p, atol=1e-9, rtol=0)
        np.testing.assert_allclose(got.q, ref.q, atol=1e-9, rtol=0)
        # the segment holds p, and belongs to the right contour
        sc = cs.segment_contour[got.segment]
        assert np.array_equal(sc, np.broadcast_to(np.arange(cs.n_contours), sc.shape))


@pytest.mark.parametrize("method", ["blocks", "compiled"])
@pytest.mark.parametrize("within", [0.0, 5.0, 20.0])
def test_within_is_exact_where_step_b_looks(within, method):
    """With ``within_mm`` the nearest contour and all contours within the limit are exact;
    the others are either exact too or reported at infinity (never a wrong finite value)."""
    rng = np.random.default_rng(13)
    for _ in range(4):
        cs, o, d = random_case(rng)
        ref = closest_points(cs, o, d, method="reference")
        got = closest_points(cs, o, d, method=method, within_mm=within)
        need = ref.distance <= np.maximum(ref.distance.min(axis=1, keepdims=True), within)
        np.testing.assert_allclose(got.distance[need], ref.distance[need], atol=1e-9, rtol=0)
        np.testing.assert_allclose(got.p[need], ref.p[need], atol=1e-9, rtol=0)
        other = ~need
        finite = np.isfinite(got.distance[other])
        np.testing.assert_allclose(got.distance[other][finite], ref.distance[other][finite],
                                   atol=1e-9, rtol=0)
        assert np.all(got.segment[other][~finite] == -1)
        # Step B gives the same selection as with all contours computed
        lim = within
        np.testing.assert_array_equal(
            select_contours(got, cs, d, None, max_stab_distance_mm=lim),
            select_contours(ref, cs, d, None, max_stab_distance_mm=lim))
    with pytest.raises(ValueError, match="within_mm"):
        closest_points(cs, o, d, method="dense", within_mm=1.0)


def test_reference_is_the_minimum():
    """Independent check of the reference: p on its segment, q on the line, q - p orthogonal
    to the line, and no sampled contour point closer to the line."""
    rng = np.random.default_rng(11)
    cs, o, d = random_case(rng, n_lines=40, n_contours=3)
    cp = closest_points(cs, o, d, method="reference")
    a, b = cs.starts[cp.segment], cs.ends[cp.segment]
    # p on segment [a, b]
    e = b - a
    s = np.einsum("ncj,ncj->nc", cp.p - a, e) / np.einsum("ncj,ncj->nc", e, e)
    assert np.all((s > -1e-9) & (s < 1 + 1e-9))
    np.testing.assert_allclose(a + s[..., None] * e, cp.p, atol=1e-9)
    # q - p orthogonal to the line direction
    assert np.max(np.abs(np.einsum("ncj,nj->nc", cp.q - cp.p, d))) < 1e-9
    # dense sampling of every segment is never closer
    t = np.linspace(0, 1, 101)
    samples = cs.starts[:, None, :] + t[None, :, None] * (cs.ends - cs.starts)[:, None, :]
    samples = samples.reshape(-1, 3)
    owner = np.repeat(cs.segment_contour, len(t))
    w = samples[None] - o[:, None]
    perp = w - np.einsum("nsj,nj->ns", w, d)[..., None] * d[:, None]
    dist = np.linalg.norm(perp, axis=2)
    for c in range(cs.n_contours):
        assert np.all(cp.distance[:, c] <= dist[:, owner == c].min(axis=1) + 1e-9)


def test_hierarchy_radius_and_sorted_lines():
    """Neighbouring lines (sorted along a curve) give the same answer, and the paper's r
    is non-negative and equals (d2 - eps2 - d1) / 2 >= 0 by construction."""
    rng = np.random.default_rng(12)
    theta = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    ring = np.c_[30 * np.cos(theta), 20 * np.sin(theta), 5 * np.sin(3 * theta)]
    cs = ContourSet.from_polylines([ring, ring[::3] * 1.5 + [0, 0, 10]], [True, True])
    c = np.array([0.0, 0.0, -600.0])
    tgt = np.c_[31 * np.cos(theta), 21 * np.sin(theta), np.zeros_like(theta)]
    tgt += rng.normal(size=tgt.shape) * 0.5
    d = tgt - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.repeat(c[None], len(d), axis=0)
    ref = closest_points(cs, o, d, method="reference")
    got = closest_points(cs, o, d, method="hierarchy")
    np.testing.assert_allclose(got.distance, ref.distance, atol=1e-9, rtol=0)
    assert got.reuse_radius is not None
    assert np.all(got.reuse_radius >= -1e-12)


def circle_contour_and_lines():
    """The apparent contour of a sphere seen from c, and lines from c inside / outside it."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    top = prepare_surface(m.vertices, m.faces)
    c = np.array([0.0, 0.0, -500.0])
    conts = apparent_contours(top, c)
    cs = ContourSet.from_contours(conts)
    ang = np.linspace(0, 2 * np.pi, 17)[:-1]
    half = np.arcsin(50.0 / 500.0)
    dirs = []
    for f in (0.8, 1.2):   # inside, then outside the silhouette cone
        a = f * half
        dirs.append(np.c_[np.sin(a) * np.cos(ang), np.sin(a) * np.sin(ang), np.full(16, np.cos(a))])
    d = np.vstack(dirs)
    o = np.repeat(c[None], len(d), axis=0)
    return cs, o, d


def test_stabbing_means_passing_inside_the_silhouette():
    cs, o, d = circle_contour_and_lines()
    cp = closest_points(cs, o, d)
    st = stabbing(cp, cs, d)
    assert st.shape == (32, 1)
    assert np.all(st[:16, 0]) and not np.any(st[16:, 0])


def test_selection_rule():
    cs1, o, d = circle_contour_and_lines()
    # a second, larger concentric contour: every inside line stabs both
    big = cs1.path[:-1] * [1.5, 1.5, 1.0]
    cs = ContourSet.from_polylines([cs1.path[:-1], big], [True, True])
    cp = closest_points(cs, o, d)
    st = stabbing(cp, cs, d)
    inside = np.arange(16)
    assert np.all(st[inside])
    # external lines that stab: the farthest stabbed contour (the big one)
    sel = select_contours(cp, cs, d, np.ones(32, dtype=bool))
    assert np.all(sel[inside] == np.argmax(cp.distance[inside], axis=1))
    # internal lines: the closest contour
    sel_int = select_contours(cp, cs, d, np.zeros(32, dtype=bool))
    assert np.array_equal(sel_int, np.argmin(cp.distance, axis=1))
    # lines outside both stab the big one only if inside it; those outside both: closest
    outside = ~st.any(axis=1)
    assert np.array_equal(sel[outside], np.argmin(cp.distance[outside], axis=1))
    # a stab distance limit smaller than the far contour falls back to the nearer one
    sel_lim = select_contours(cp, cs, d, None,
                              max_stab_distance_mm=float(cp.distance[inside].min(axis=1).max()))
    assert np.all(sel_lim[inside] == np.argmin(cp.distance[inside], axis=1))


def test_bad_input():
    cs = ContourSet.from_polylines([np.eye(3)], [False])
    o = np.zeros((2, 3))
    with pytest.raises(ValueError, match="unit"):
        closest_points(cs, o, np.ones((2, 3)))
    with pytest.raises(ValueError, match="method"):
        closest_points(cs, o, np.tile([1.0, 0, 0], (2, 1)), method="fast")
    with pytest.raises(ValueError, match="same shape"):
        closest_points(cs, o, np.tile([1.0, 0, 0], (3, 1)))
    with pytest.raises(ValueError, match="at least 2 vertices"):
        ContourSet.from_polylines([np.zeros((1, 3))], [False])
    with pytest.raises(ValueError, match="ContourSet"):
        closest_points([np.eye(3)], o, np.tile([1.0, 0, 0], (2, 1)))
    empty = closest_points(ContourSet.from_polylines([], []), o, np.tile([1.0, 0, 0], (2, 1)))
    assert empty.distance.shape == (2, 0)


@pytest.mark.parametrize("seed", range(4))
def test_compiled_tangents_equal_the_numpy_reference(seed):
    """ContourSet.tangents compiled vs numpy: points inside segments, exactly at vertices
    (the two segments' mean), at the free ends of open contours (two-vertex open contours
    included: their one segment both starts and ends there), invalid entries (NaN), and an
    (N, C)-shaped input as stabbing passes it."""
    rng = np.random.default_rng(seed)
    cs, o, d = random_case(rng)
    extra = ContourSet.from_polylines([rng.normal(size=(2, 3)) * 30.0], [False])
    cs = ContourSet.from_polylines(
        [cs.path[cs.offsets[c] + c: cs.offsets[c + 1] + c + 1][:-1] if cs.closed[c]
         else cs.path[cs.offsets[c] + c: cs.offsets[c + 1] + c + 1]
         for c in range(cs.n_contours)] + [extra.path],
        list(cs.closed) + [False])
    s = cs.n_segments
    seg = rng.integers(0, s, 600)
    w = rng.uniform(0.0, 1.0, (600, 1))
    w[:150] = 0.0                                           # at a segment's start
    w[150:300] = 1.0                                        # at its end
    p = cs.starts[seg] + w * (cs.ends[seg] - cs.starts[seg])
    seg[::37] = -1
    got = cs.tangents(seg, p)
    ref = cs.tangents(seg, p, reference=True)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    np.testing.assert_allclose(got[seg >= 0], ref[seg >= 0], atol=1e-12)
    cp = closest_points(cs, o, d, method="compiled")
    got = cs.tangents(cp.segment, cp.p)
    assert got.shape == cp.p.shape
    np.testing.assert_allclose(got, cs.tangents(cp.segment, cp.p, reference=True), atol=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_block_capsules_equal_the_numpy_ones(seed):
    """The compiled capsules of the "compiled" method against reglib.closest's numpy
    _block_capsules (the "blocks" method's), for several block sizes; contours shorter
    than a block and degenerate (repeated-vertex) axes included."""
    from reglib._closest_numba import block_capsules
    from reglib.closest import _block_capsules

    rng = np.random.default_rng(seed)
    cs, _, _ = random_case(rng)
    loop = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.0, 5.0, 0.0], [0.0, 0.0, 0.0]])
    cs = ContourSet.from_polylines(
        [cs.path[cs.offsets[c] + c: cs.offsets[c + 1] + c + 1] for c in range(cs.n_contours)]
        + [loop], [False] * cs.n_contours + [False])
    for size in (1, 3, 8, 64):
        bc, j0, _, a, b, eps, first = _block_capsules(cs, size)
        ga, gb, geps, seg0, cb0 = block_capsules(cs.path, cs.offsets, size)
        assert np.array_equal(ga, a) and np.array_equal(gb, b)
        np.testing.assert_allclose(geps, eps, rtol=1e-12, atol=1e-12)
        assert np.array_equal(seg0, np.r_[cs.offsets[bc] + j0, cs.n_segments])
        assert np.array_equal(cb0, np.r_[first, len(bc)])


def test_compiled_exact_pairs_equal_the_numpy_exact_points():
    """reglib._closest_numba.exact_pairs against reglib.closest._exact on random pairs
    (degenerate zero-length segments included), and its threshold masking against the
    numpy expression it replaced."""
    from reglib._closest_numba import exact_pairs
    from reglib.closest import _exact

    rng = np.random.default_rng(6)
    cs, o, d = random_case(rng)
    n, c = len(o), 7
    seg = rng.integers(-1, cs.n_segments, (n, c))
    starts, ends = cs.starts.copy(), cs.ends.copy()
    ends[::11] = starts[::11]                                 # zero-length segments
    dist_in = rng.uniform(0.0, 30.0, (n, c))
    for within in (-1.0, 0.0, 8.0):
        s = seg.copy()
        dist, p, q = exact_pairs(o, d, starts, ends, dist_in, s, within)
        want = seg.copy()
        if within >= 0:
            thr = np.maximum(within, dist_in.min(axis=1))
            want[dist_in > (thr + 1e-7 * (1.0 + thr))[:, None]] = -1
        assert np.array_equal(s, want)
        li, ci = np.nonzero(want >= 0)
        rd, rp, rq = _exact(o[li], d[li], starts[want[li, ci]], ends[want[li, ci]])
        np.testing.assert_allclose(dist[li, ci], rd, rtol=0, atol=1e-12)
        np.testing.assert_allclose(p[li, ci], rp, rtol=0, atol=1e-12)
        np.testing.assert_allclose(q[li, ci], rq, rtol=0, atol=1e-12)
        assert np.all(np.isinf(dist[want < 0])) and np.all(np.isnan(p[want < 0]))


def _steps_a_b(cs, o, d, ext, within, max_stab, method):
    """The numpy chain match_contours fuses: Step A, Step B, the tangent at the choice."""
    cp = closest_points(cs, o, d, method=method,
                        within_mm=within if method in ("blocks", "compiled") else None)
    sel = select_contours(cp, cs, d, ext, max_stab_distance_mm=max_stab)
    rows = np.arange(len(sel))
    return sel, cp.p[rows, sel], cs.tangents(cp.segment[rows, sel], cp.p[rows, sel])


@pytest.mark.parametrize("seed", range(4))
def test_match_contours_equals_steps_a_and_b(seed):
    """The fused, warm-started, compiled Steps A and B (the registration's path) against
    the chain they replace: identical to the unfused compiled search; against the brute
    force, the same closest points and tangents (1e-9) and the same choices wherever the
    choice is not a tie."""
    rng = np.random.default_rng(40 + seed)
    for _ in range(4):
        cs, o, d = random_case(rng, n_lines=150, n_contours=int(rng.integers(1, 9)))
        ext = rng.random(len(o)) < 0.7
        max_stab = float(rng.choice([5.0, 15.0, np.inf]))
        # as the registration asks: Step A exact where Step B looks
        within = max_stab if np.isfinite(max_stab) else None
        sel, seg, pts, tg = match_contours(cs, o, d, ext, within_mm=within,
                                           max_stab_distance_mm=max_stab)
        s1, p1, t1 = _steps_a_b(cs, o, d, ext, within, max_stab, "compiled")
        assert np.array_equal(sel, s1)
        assert np.array_equal(pts, p1, equal_nan=True)
        assert np.array_equal(tg, t1, equal_nan=True)
        assert np.all(cs.segment_contour[seg] == sel)
        s0, p0, t0 = _steps_a_b(cs, o, d, ext, within, max_stab, "reference")
        same = s0 == sel
        assert same.mean() > 0.99
        np.testing.assert_allclose(pts[same], p0[same], atol=1e-9, rtol=0)
        np.testing.assert_allclose(tg[same], t0[same], atol=1e-9, rtol=0)
    # no threshold, no external line, one line, no contour
    cs, o, d = random_case(rng)
    sel, _, pts, _ = match_contours(cs, o, d, np.zeros(len(o), dtype=bool))
    cp = closest_points(cs, o, d, method="reference")
    assert np.array_equal(sel, np.argmin(cp.distance, axis=1))
    assert match_contours(cs, o[:1], d[:1])[0].shape == (1,)
    empty = match_contours(ContourSet.from_polylines([], []), o, d)
    assert np.all(empty[0] == -1) and np.all(np.isnan(empty[2]))
    with pytest.raises(ValueError, match="external"):
        match_contours(cs, o, d, np.ones(3, dtype=bool))


@pytest.mark.parametrize("seed", range(3))
def test_match_contours_honours_max_stab_without_a_step_a_threshold(seed):
    """match_contours with ``within_mm=None`` keeps max_stab_distance_mm, as select_contours
    does (a mutation audit: the compiled test dropped passed every test, which always gave
    within_mm equal to max_stab; agreement with the reference 1.00 against 0.04)."""
    rng = np.random.default_rng(100 + seed)
    n_diff_inf = 0
    for _ in range(4):
        cs, o, d = random_case(rng, n_lines=150, n_contours=6)
        ext = np.ones(len(o), dtype=bool)
        for max_stab in (2.0, 5.0):
            sel, _, _, _ = match_contours(cs, o, d, ext, within_mm=None,
                                          max_stab_distance_mm=max_stab)
            cp = closest_points(cs, o, d, method="reference")
            want = select_contours(cp, cs, d, ext, max_stab_distance_mm=max_stab)
            n_diff_inf += int(np.sum(want != select_contours(cp, cs, d, ext)))
            assert np.mean(sel == want) > 0.99, (max_stab, np.mean(sel == want))
    assert n_diff_inf > 10   # the limit matters on these cases
