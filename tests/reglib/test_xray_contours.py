"""X-ray contours from clicks: simulate a rendered bone cylinder, trace it, compare with its
true apparent contour (computed from the cylinder and the C-arm geometry)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from reglib.xray_contours import (
    XrayContour,
    _agreement_band,
    _frame_agreement_direct,
    _near_mask,
    field_of_view_mask,
    field_scale,
    frame_agreement,
    frame_noise_sd,
    pixel_scale,
    refine_edge_profile,
    xray_contour,
    xray_contours,
)
from testbed.bodies import Body
from testbed.fluoroscope import FluoroscopeSpec, ViewSpec, make_carm, render

R_MM = 14.0


def _shaft_scene():
    """A cortical tube (marrow inside) in a soft-tissue cylinder, tilted in the image."""
    turn = (trimesh.transformations.rotation_matrix(0.3, (0, 0, 1))
            @ trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    meshes = []
    for radius, sections in ((70.0, 128), (R_MM, 256), (8.0, 128)):
        m = trimesh.creation.cylinder(radius=radius, height=600.0, sections=sections)
        m.apply_transform(turn)
        meshes.append(m)
    meshes[0].apply_translation((8.0, 0.0, 0.0))
    bodies = [Body("tissue", "soft_tissue", meshes[0]),
              Body("bone", "cortical_bone", meshes[1], inside="tissue"),
              Body("canal", "marrow", meshes[2], inside="bone")]
    return bodies, turn[:3, :3] @ np.array([0.0, 0.0, 1.0])


def _true_edges(carm, axis):
    """The two silhouette generators of the bone cylinder, projected: (2, N, 2) px."""
    s = carm.source_robot
    w = s - (s @ axis) * axis
    d = np.linalg.norm(w)
    u, v = w / d, np.cross(axis, w / d)
    c, sn = R_MM / d, np.sqrt(1 - (R_MM / d) ** 2)
    t = np.linspace(-150.0, 150.0, 3001)
    return [carm.project(R_MM * (c * u + k * sn * v) + t[:, None] * axis) for k in (1, -1)]


@pytest.fixture(scope="module")
def frames():
    bodies, axis = _shaft_scene()
    fluoro = FluoroscopeSpec().ideal()  # the snake on the chain it was measured with
    carm = make_carm(fluoro, ViewSpec(orbital_deg=5.0))
    clean = render(carm, bodies, fluoro=fluoro, noise=False)
    noisy = render(carm, bodies, fluoro=fluoro, rng=np.random.default_rng(3))
    return carm, axis, clean, noisy


def _trace(frame, edge, rng):
    clicks = edge[[900, 1300, 1700, 2100]] + rng.normal(0.0, 1.5, (4, 2))
    return xray_contour(frame.image_u8, clicks, label="external")


@pytest.mark.slow
def test_snake_finds_the_true_apparent_contour(frames):
    carm, axis, clean, noisy = frames
    rng = np.random.default_rng(0)
    for edge in _true_edges(carm, axis):
        tree = cKDTree(edge)
        # noise off: every vertex within 0.3 px of the true contour
        c = _trace(clean, edge, rng)
        assert c.label == "external" and not c.closed and len(c.points_xy) > 100
        dist, idx = tree.query(c.points_xy)
        assert dist.max() < 0.3, np.percentile(dist, [50, 90, 100])
        assert idx.max() - idx.min() > 1000  # it follows the edge, not a piece of it
        # the plain gradient maximum is biased inwards: the profile fit matters
        plain = xray_contour(clean.image_u8, c.points_xy[::20], profile_fit=False)
        assert np.median(tree.query(plain.points_xy)[0]) > 0.5
        # with quantum noise: the typical vertex still within 0.3 px
        c = _trace(noisy, edge, rng)
        dist, _ = tree.query(c.points_xy)
        assert np.median(dist) < 0.3 and np.percentile(dist, 90) < 0.7


def test_field_of_view_and_bad_input(frames):
    carm, axis, clean, _ = frames
    mask = field_of_view_mask(clean.image_u8)
    # the estimated field lies inside the true one and covers nearly all of it
    assert not (mask & ~clean.fov).any()
    assert mask.sum() > 0.97 * clean.fov.sum()
    edge = _true_edges(carm, axis)[0]
    with pytest.raises(ValueError, match="outside the image's field of view"):
        xray_contour(clean.image_u8, [[2.0, 2.0], [50.0, 50.0], edge[1500]])
    with pytest.raises(ValueError, match="label"):
        xray_contour(clean.image_u8, edge[[1000, 1500, 2000]], label="outer")
    # the label given is the label returned (a mutation audit, h101: with every contour
    # labelled external, no test failed)
    for label in ("internal", "external"):
        c = xray_contour(clean.image_u8, edge[[900, 1300, 1700, 2100]], label=label)
        assert c.label == label and len(c.points_xy) > 100
    with pytest.raises(ValueError, match=r"traces\[0\]: missing 'clicks_xy'"):
        xray_contours(clean.image_u8, [{"label": "internal"}])
    with pytest.raises(ValueError, match="2-D"):
        xray_contour(np.zeros((3, 4, 5)), edge[[1000, 1500]])
    with pytest.raises(ValueError, match="label"):
        XrayContour(np.zeros((3, 2)), "middle", False)
    # a review: a constant image gave 60 contour points and no problem, a 1e300 one a
    # message about converting NaN to an integer, a mask of text a mask of True
    flat = np.where(clean.fov, 120, 0).astype(np.uint8)
    H, W = mask.shape
    ij = np.rint(edge[:, ::-1]).astype(int)
    seen = (ij[:, 0] >= 0) & (ij[:, 0] < H) & (ij[:, 1] >= 0) & (ij[:, 1] < W)
    inner = edge[seen][mask[ij[seen, 0], ij[seen, 1]]]
    clicks = inner[np.linspace(0, len(inner) - 1, 6).astype(int)]
    with pytest.raises(ValueError, match="uniform inside the field of view"):
        xray_contour(flat, clicks)
    with pytest.raises(ValueError, match=r"values must be finite and within \+-1e\+12"):
        xray_contour(clean.image_u8 * 1e300, clicks)
    with pytest.raises(ValueError, match="fov_mask: expected booleans"):
        xray_contour(clean.image_u8, clicks, fov_mask=np.where(clean.fov, "yes", "no"))
    spot = flat.copy()                     # flat where the clicks are, one bright spot
    r, c = np.argwhere(clean.fov)[len(np.argwhere(clean.fov)) // 2]
    spot[r - 2:r + 3, c - 2:c + 3] = 250
    with pytest.raises(ValueError, match="no edge along the traced outline"):
        xray_contour(spot, clicks)
    # the true image's outline passes
    assert len(xray_contour(clean.image_u8, clicks).points_xy) > 10


def test_a_frame_of_noise_alone_has_no_outline(frames):
    """A review: a frame replaced by flat grey plus noise was traced (the snake follows the
    noise, which changes by more than 1 % of the field's range across it) and the estimate
    accepted at mTRE 1.5 mm. The signed change across the trace must stand above the
    frame's noise: it does on the noisy render of the bone, not on grey plus noise of any
    level, whose trace the snake still makes."""
    carm, axis, _, noisy = frames
    img = noisy.image_u8.astype(float)
    mask = field_of_view_mask(img)
    edge = _true_edges(carm, axis)[0]
    H, W = mask.shape
    ij = np.rint(edge[:, ::-1]).astype(int)
    seen = (ij[:, 0] >= 0) & (ij[:, 0] < H) & (ij[:, 1] >= 0) & (ij[:, 1] < W)
    inner = edge[seen][mask[ij[seen, 0], ij[seen, 1]]]
    clicks = inner[np.linspace(0, len(inner) - 1, 6).astype(int)]
    assert len(xray_contour(noisy.image_u8, clicks).points_xy) > 10
    rng = np.random.default_rng(8)
    for sd in (1.0, 3.0, 8.0):
        grey = np.where(mask, img[mask].mean() + rng.normal(0.0, sd, img.shape), img)
        grey = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
        with pytest.raises(ValueError, match="above the frame's noise"):
            xray_contour(grey, clicks)
        # the trace itself is made: only the edge test refuses it
        assert len(xray_contour(grey, clicks, noise_sd=0.0).points_xy) > 10


def test_frame_noise_sd_against_the_noise_added():
    """The robust noise figure against the standard deviation of the Gaussian noise added to
    random smooth frames with a few steps (edges barely move it), within 5 %; an unmasked
    pixel does not count, a noiseless 8-bit ramp gives 0."""
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:240, 0:320]
    for _ in range(6):
        sd = rng.uniform(0.5, 10.0)
        base = 60 + 0.2 * xx + 30 * np.sin(yy / rng.uniform(20, 60))
        base += 40.0 * (np.hypot(xx - rng.uniform(80, 240), yy - 120) < rng.uniform(30, 80))
        mask = np.hypot(xx - 160, yy - 120) < 110
        img = np.where(mask, base + rng.normal(0.0, sd, base.shape), 1e6)
        assert frame_noise_sd(img, mask) == pytest.approx(sd, rel=0.05)
    ramp = np.rint(50 + 0.2 * xx).astype(np.uint8)
    assert frame_noise_sd(ramp, np.ones(ramp.shape, bool)) == 0.0


def test_click_window_check_equals_the_dilated_mask():
    """The per-click window lookup against ndimage.binary_dilation of the mask (4 steps),
    on random masks with clicks everywhere, beyond the image's edges included."""
    from scipy import ndimage

    rng = np.random.default_rng(4)
    for _ in range(5):
        mask = ndimage.binary_opening(rng.uniform(0, 1, (40, 60)) > 0.7)
        rows, cols = rng.integers(-6, 46, 400), rng.integers(-6, 66, 400)
        ref = np.zeros(len(rows), dtype=bool)
        ok = (rows >= 0) & (rows < 40) & (cols >= 0) & (cols < 60)
        ref[ok] = ndimage.binary_dilation(mask, iterations=4)[rows[ok], cols[ok]]
        np.testing.assert_array_equal(_near_mask(mask, rows, cols, 4), ref)


def test_edge_profile_on_the_samples_box_equals_the_whole_image():
    """The profile fit smoothing only the box of its samples against smoothing the whole
    image: the same vertices, bit for bit, contours near and beyond the image's edges
    included."""
    rng = np.random.default_rng(8)
    yy, xx = np.mgrid[0:120, 0:160]
    img = 100 + 80 * np.sqrt(np.clip(35.0**2 - (xx - 70.0) ** 2 - (yy - 60.0) ** 2, 0, None))
    img += rng.normal(0, 2, img.shape)
    t = np.linspace(0.3, 2.6, 40)
    for centre, r in (((70.0, 60.0), 35.0), ((5.0, 60.0), 30.0), ((150.0, 115.0), 40.0)):
        c = np.column_stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)])
        c += rng.normal(0, 0.5, c.shape)
        got = refine_edge_profile(img, c)
        ref = refine_edge_profile(img, c, whole_image=True)
        np.testing.assert_array_equal(got, ref)


def test_edge_profile_fit_with_long_lengths_finds_the_edge():
    """The profile model is tabulated to a reach; with lengths of several times the
    defaults (finer video) the model must not flatten at the table's end. A disc's line
    integral (a square root at its outline), blurred by 3 px, traced from 2 px off with the
    lengths tripled: every vertex within 0.1 px of the outline (the table's fixed 12 px
    reach left them up to 7.4 px off)."""
    from scipy import ndimage
    yy, xx = np.mgrid[0:400, 0:400]
    r_true = 120.0
    chord = np.sqrt(np.clip(r_true**2 - (xx - 200.0) ** 2 - (yy - 200.0) ** 2, 0, None))
    img = ndimage.gaussian_filter(60.0 + 1.5 * chord, 3.0)
    t = np.linspace(0.2, 2.8, 60)
    c = np.column_stack([200.0 + (r_true - 2.0) * np.cos(t), 200.0 + (r_true - 2.0) * np.sin(t)])
    m = 3
    out = refine_edge_profile(img, c, half_width_px=4.0 * m, sample_px=0.25 * m,
                              search_px=2.0 * m, pre_sigma_px=0.7 * m,
                              sigmas_px=tuple(v * m for v in (0.6, 0.8, 1.0, 1.2, 1.5)))
    r = np.linalg.norm(out - 200.0, axis=1)
    assert np.abs(r - r_true).max() < 0.1, np.abs(r - r_true).max()


def test_fine_video_keeps_the_contour_on_the_outline():
    """A bone shaft on the clinic chain with 2048 x 1536 video of 0.156 mm pixels (the same
    9-inch field): xray_contour scales its lengths by the field's size in pixels (3.27
    here; 3.2 from the nominal pixel) and lands within 0.15 mm of the true outline
    (median; measured 0.09-0.11 mm, 90th percentile 0.19-0.20, at most 0.53); with the
    lengths of 640 x 480 video (scale 1), 0.18-0.21 mm, 90th percentile 0.62-0.63, up to
    1.1 mm."""
    bodies, axis = _shaft_scene()
    p = 0.15625
    fluoro = FluoroscopeSpec(width_px=2048, height_px=1536, pixel_mm=p)
    carm = make_carm(fluoro, ViewSpec(orbital_deg=5.0))
    frame = render(carm, bodies, fluoro=fluoro, rng=np.random.default_rng(3))
    mask = field_of_view_mask(frame.image_u8)
    assert field_scale(mask) == pytest.approx(3.2, abs=0.1)      # the 3-px eroded field
    rng = np.random.default_rng(0)
    for edge in _true_edges(carm, axis):
        tree = cKDTree(edge)
        n = len(edge)
        clicks = (edge[[int(n * 0.3), int(n * 0.43), int(n * 0.57), int(n * 0.7)]]
                  + rng.normal(0.0, 1.5 * 0.5 / p, (4, 2)))    # 1.5 px of 640 x 480 video
        d = tree.query(xray_contour(frame.image_u8, clicks, fov_mask=mask).points_xy)[0] * p
        assert np.median(d) < 0.15 and np.percentile(d, 90) < 0.3 and d.max() < 0.7, (
            np.median(d), np.percentile(d, 90), d.max())
        d1 = tree.query(xray_contour(frame.image_u8, clicks, fov_mask=mask,
                                     scale=1).points_xy)[0] * p
        assert np.percentile(d1, 90) > 2 * np.percentile(d, 90)
        # the nominal pixel, when the observation states it (scale 3.2 here)
        dp = tree.query(xray_contour(frame.image_u8, clicks, fov_mask=mask,
                                     pixel_mm=p).points_xy)[0] * p
        assert np.median(dp) < 0.15 and np.percentile(dp, 90) < 0.3 and dp.max() < 0.7, (
            np.median(dp), np.percentile(dp, 90), dp.max())


def test_the_scale_follows_the_pixel_not_the_field():
    """A 150 mm intensifier on 1024 x 768 video of 0.25 mm: its field is 600 px across,
    which field_scale reads as a 9-inch field (scale 1.31); the pixel asks for 2 (a
    held-out review: seeds 2 and 3 were accepted 1.50 and 1.69 mm off at scale 1, 0.79 at
    2)."""
    yy, xx = np.mgrid[0:768, 0:1024]
    field = (xx - 511.5) ** 2 + (yy - 383.5) ** 2 <= (75.0 / 0.25) ** 2
    assert field_scale(field) == pytest.approx(1.31, abs=0.01)
    np.testing.assert_allclose([pixel_scale(v) for v in (0.25, 0.15625, 0.2, 0.4, 0.45, 0.5,
                                                         0.667)],
                               [2.0, 3.2, 2.5, 1.25, 1.0, 1.0, 1.0])
    for bad in (0.0, -0.25, float("nan"), None, "0.25", [0.25]):
        with pytest.raises(ValueError, match="pixel_mm"):
            pixel_scale(bad)


def test_field_of_view_mask_equals_scipys_on_random_frames():
    """OpenCV's labelling, hole filling and erosion against scipy.ndimage's: the same mask
    on random fields with dark objects inside, bright specks outside and dark notches
    reaching the field's rim (which are not holes), and the same refusal of a dark frame."""
    rng = np.random.default_rng(31)
    yy, xx = np.mgrid[0:96, 0:128]
    for trial in range(12):
        img = np.where(np.hypot(xx - 64 + rng.uniform(-20, 20), yy - 48)
                       < rng.uniform(30, 70), rng.uniform(20, 200, xx.shape), 0.0)
        for _ in range(int(rng.integers(0, 6))):    # metal inside, specks and notches
            cx, cy, r = rng.uniform(0, 128), rng.uniform(0, 96), rng.uniform(1, 8)
            img[np.hypot(xx - cx, yy - cy) < r] = rng.choice([0.0, 150.0])
        for erode in (0, 1, 3):
            np.testing.assert_array_equal(
                field_of_view_mask(img, erode_px=erode),
                field_of_view_mask(img, erode_px=erode, reference=True), err_msg=str(trial))
    for ref in (False, True):
        with pytest.raises(ValueError, match="no pixel above the dark level"):
            field_of_view_mask(np.zeros((40, 40)), reference=ref)


def test_frame_agreement_by_fft_equals_the_direct_sum():
    """The FFT correlation of the edge bands against direct sums over the reference's
    window at every shift within reach, on random textured frames with a known shift and
    random fields (the band at half its widths, for small frames): the same peak, where
    the shift applied put it."""
    from scipy import ndimage

    rng = np.random.default_rng(12)
    yy, xx = np.mgrid[0:120, 0:160]
    for _ in range(5):
        base = ndimage.gaussian_filter(rng.normal(0.0, 40.0, (120, 160)), rng.uniform(1, 3))
        mask = np.hypot(xx - 80 + rng.uniform(-5, 5), yy - 60) < rng.uniform(52, 58)
        dx, dy = (int(v) for v in rng.integers(-6, 7, 2))
        ref = base + rng.normal(0.0, 0.5, base.shape)
        frame = np.roll(base, (dy, dx), (0, 1)) + rng.normal(0.0, 0.5, base.shape)
        ncc, shift = frame_agreement(frame, ref, mask, reach_px=8, scale=0.5)
        grid = [(a, b) for b in range(-8, 9) for a in range(-8, 9)]
        direct = _frame_agreement_direct(frame, ref, mask, grid, reach_px=8, scale=0.5)
        k = int(np.argmax(direct))
        assert grid[k] == shift == (dx, dy)
        assert direct[k] == pytest.approx(ncc, abs=1e-9) and 0.5 < ncc <= 1.0
        # the band's float32 Gaussians against scipy's in float64
        outer = np.ones(base.shape, bool)
        fast = _agreement_band(frame, outer, 0.5)
        exact = _agreement_band(frame, outer, 0.5, reference=True)
        assert np.abs(fast - exact).max() < 1e-5 * np.abs(exact).max()
    # straight parallel edges (stripes along y) leave a flat ridge along them: noise puts the
    # bare peak anywhere on it, but no shift explains the frames within AGREEMENT_TIE of it,
    # and no shift is reported (a review: a view was left out as 'moved by (+1, -7) px');
    # the same frames truly shifted by 3 px across the stripes are still found shifted
    stripes = np.sin(xx / 4.0) * 40.0 + np.sin(xx / 9.0 + 1.0) * 30.0
    mask = np.hypot(xx - 80, yy - 60) < 56
    for seed in range(4):
        r = np.random.default_rng(seed)
        ref = stripes + r.normal(0.0, 2.0, stripes.shape)
        same = stripes + r.normal(0.0, 2.0, stripes.shape)
        ncc, shift = frame_agreement(same, ref, mask, reach_px=8, scale=0.5)
        assert shift == (0, 0), (seed, shift)
        moved = np.roll(stripes, 3, 1) + r.normal(0.0, 2.0, stripes.shape)
        assert frame_agreement(moved, ref, mask, reach_px=8, scale=0.5)[1][0] == 3
    # a flat band or an empty window: no figure; frames of other shapes: named
    flat = np.full((120, 160), 50.0)
    assert np.isnan(frame_agreement(flat, flat, np.ones((120, 160), bool))[0])
    assert np.isnan(frame_agreement(base, base, np.zeros((120, 160), bool))[0])
    with pytest.raises(ValueError, match="shapes differ"):
        frame_agreement(flat, flat[:5], np.ones((120, 160), bool))
