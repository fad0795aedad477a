"""The compiled passes of the fast marker detector (reglib._markers_numba) against their numpy
and scipy.ndimage references, on random cases; the detector as a whole, and identify_row's
compiled hypotheses and candidates, against their references are in test_calibration.py."""

import numpy as np
import pytest
from scipy import ndimage

from reglib import _markers_numba as mk
from reglib import markers as M


def _noise_args():
    T, S = M.NOISE_TILE_PX, M.NOISE_STEP_PX
    return (T, S, (T // S) ** 2 // 4, M.NOISE_START_STEP, M.NOISE_CLIP, M.NOISE_PASSES,
            M.NOISE_SCALE)


def _random_band(rng, shape):
    """Blurred random differences as the detector's Gaussians give them (float32), with
    blob-like outliers and a field mask."""
    d = rng.normal(0, rng.uniform(0.5, 3.0), shape)
    hot = rng.random(shape) < 0.01
    d[hot] += rng.uniform(5, 40, hot.sum())
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    mask = np.hypot(yy - shape[0] / 2, xx - shape[1] / 2) < rng.uniform(5, 1.2 * max(shape))
    d = np.where(mask, d, 0.0)
    g1 = ndimage.gaussian_filter(d, 1.0).astype(np.float32)
    g2 = ndimage.gaussian_filter(d, 4.0).astype(np.float32)
    return g1, g2, mask


def test_small_median_equals_numpy_median():
    """The branchless quickselect median of the block noise against np.median: odd and even
    counts, ties, runs of equal values, sorted and reversed input, one element; the input
    is left as it was."""
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 5, 8, 15, 16, 63, 64, 65, 256):
        work, tmp = np.empty(n), np.empty(n)
        for trial in range(60):
            x = rng.normal(size=n)
            if trial % 4 == 1:
                x = np.round(x * 2) / 2                 # few distinct values
            elif trial % 4 == 2 and n > 1:
                x[rng.random(n) < 0.6] = 0.25            # most values equal
            elif trial % 4 == 3:
                x = np.sort(x)[:: rng.choice([-1, 1])]
            before = x.copy()
            assert mk.small_median(x, n, work, tmp) == np.median(x), (n, trial)
            np.testing.assert_array_equal(x, before)
        assert mk.small_median(np.full(n, 3.0), n, work, tmp) == 3.0


def test_band_noise_equals_band_and_tile_noise():
    """The one-pass band-pass and block noise against the two separate passes (the same
    values, bit for bit), and the band against numpy's rim test, on random sizes (blocks cut
    by the edges) and masks; the block noise against its numpy reference per block."""
    rng = np.random.default_rng(5)
    args = _noise_args()
    for _ in range(15):
        shape = tuple(int(v) for v in rng.integers(20, 170, 2))
        g1, g2, mask = _random_band(rng, shape)
        ds, tiles = mk.band_noise(g1, g2, mask, *args)
        ds_np = g1 - g2
        np.testing.assert_array_equal(ds, np.where(g1 > 0.5 * ds_np, ds_np, np.float32(0.0)))
        np.testing.assert_array_equal(ds, mk.band(g1, g2))
        np.testing.assert_array_equal(tiles, mk.tile_noise(g1, g2, mask, *args))
        T, S, min_count = args[:3]
        v = g1.astype(np.float64) - g2
        for by in range(tiles.shape[0]):
            for bx in range(tiles.shape[1]):
                sl = (slice(by * T, (by + 1) * T, S), slice(bx * T, (bx + 1) * T, S))
                x = v[sl][mask[sl]]
                if len(x) < min_count:
                    assert np.isnan(tiles[by, bx])
                else:
                    assert tiles[by, bx] == pytest.approx(M._clipped_std(x), rel=1e-9)


@pytest.mark.parametrize("seed", range(3))
def test_gaussian_pair_equals_opencv(seed):
    """Both Gaussians of the detector in one compiled pass (gaussian_pair, a replica of
    OpenCV's float32 arithmetic) against OpenCV's GaussianBlur (the fast path's reference,
    _gaussian) on the detector's field box and widths of every remainder by 8 and values of
    widely different scales, and the detector's half-integer differences with a zero border
    (which the replica does not compute) and -0.0 in the field: where the once-per-shape
    check accepts the replica, bit for bit equal; _gaussians equals OpenCV's two calls
    either way, also on shapes too small for the replica (the check refuses them)."""
    rng = np.random.default_rng(seed)
    ka, kb = M._gaussian_taps(M.BLOB_SIGMA_PX), M._gaussian_taps(M.BACKGROUND_SIGMA_PX)
    accepted = 0
    shapes = [(480, 505), (20, 60), (60, 33), (61, 77)] + [
        (int(rng.integers(34, 140)), 34 + 9 * i) for i in range(8)]
    for shape in shapes:
        if seed == 0:
            img = rng.uniform(-2, 2, shape) * 10.0 ** rng.uniform(-3, 3, shape)
        else:     # as the detector's d: half-integers, 0 outside a disc
            yy, xx = np.mgrid[:shape[0], :shape[1]]
            disc = np.hypot(yy - shape[0] / 2, xx - shape[1] / 2) < 0.45 * max(shape)
            img = np.where(disc, rng.integers(-60, 60, shape) * 0.5, 0.0)
            if seed == 2:   # -0.0 inside (polarity "bright"): computed as any other value
                img[disc & (img == 0)] = -0.0
        img = img.astype(np.float32)
        ref = (M._gaussian(img, M.BLOB_SIGMA_PX, False),
               M._gaussian(img, M.BACKGROUND_SIGMA_PX, False))
        got = M._gaussians(img, False)
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_array_equal(g.view(np.int32), r.view(np.int32))
        ok = M._gaussian_replica_check(shape)
        if min(shape) <= len(kb) - 1:
            assert not ok
        if ok:
            accepted += 1
            for g, r in zip(mk.gaussian_pair(img, ka, kb), ref, strict=True):
                np.testing.assert_array_equal(g.view(np.int32), r.view(np.int32))
            # other radii (R 6 and 10: the column filter's rows one at a time; 8 and 12)
            sa, sb = (1.5, 2.5) if seed % 2 else (2.0, 3.0)
            got = mk.gaussian_pair(img, M._gaussian_taps(sa), M._gaussian_taps(sb))
            for g, sigma in zip(got, (sa, sb), strict=True):
                r = M._gaussian(img, sigma, False)
                np.testing.assert_array_equal(g.view(np.int32), r.view(np.int32))
    print(f"replica accepted for {accepted} of {len(shapes)} shapes")


def test_spread_tiles_equals_the_maximum_filter():
    """The neighbours' maximum of the block figures and the need of the field's figure
    against scipy.ndimage.maximum_filter and the numpy test of _noise_tiles."""
    rng = np.random.default_rng(6)
    T = M.NOISE_TILE_PX
    for _ in range(40):
        ny, nx = (int(v) for v in rng.integers(1, 9, 2))
        tiles = rng.uniform(0.1, 3.0, (ny, nx))
        tiles[rng.random((ny, nx)) < rng.uniform(0, 0.9)] = np.nan
        H, W = ny * T - int(rng.integers(0, T)), nx * T - int(rng.integers(0, T))
        inside = np.zeros((H, W), bool)
        ds = np.zeros((H, W), np.float32)
        if rng.random() < 0.5:
            inside[rng.integers(0, H), rng.integers(0, W)] = True
        if rng.random() < 0.5:
            ds[rng.integers(0, H), rng.integers(0, W)] = 1.0
        ref = ndimage.maximum_filter(np.where(np.isfinite(tiles), tiles, -np.inf), size=3,
                                     mode="constant", cval=-np.inf)
        none = ~np.isfinite(ref)
        need = any(inside[by * T:(by + 1) * T, bx * T:(bx + 1) * T].any()
                   or (ds[by * T:(by + 1) * T, bx * T:(bx + 1) * T] != 0).any()
                   for by, bx in zip(*np.nonzero(none), strict=True))
        got, got_need = mk.spread_tiles(tiles, inside, ds, T)
        np.testing.assert_array_equal(got, ref)
        assert got_need == need


def test_thresholds_on_the_bounding_boxes_equal_the_whole_frame():
    """The pixels above the noise with their bounding box, and the pixels above their
    region's threshold labelled on that box, against the numpy steps of the reference
    detector on the whole frame (ndimage.label and ndimage.maximum): the same labels."""
    rng = np.random.default_rng(9)
    T = M.NOISE_TILE_PX
    for trial in range(30):
        shape = tuple(int(v) for v in rng.integers(30, 200, 2))
        g1, g2, mask = _random_band(rng, shape)
        ds = mk.band(g1, g2)
        if trial % 5 == 0:
            ds[:] = 0.0                               # nothing above the noise
        ny, nx = -(-shape[0] // T), -(-shape[1] // T)
        tiles = rng.uniform(0.2, 2.0, (ny, nx))
        peak = float(ds.max())
        n_sigma, rel = 4.5, 0.35
        low_floor, base_floor = 0.02 * peak, 0.5 * rel * peak
        noise_px = np.repeat(np.repeat(tiles, T, axis=0), T, axis=1)[:shape[0], :shape[1]]
        low = np.maximum(n_sigma * noise_px, low_floor)
        above, r0, r1, c0, c1 = mk.above_noise(ds, tiles, T, n_sigma, low_floor)
        np.testing.assert_array_equal(above.astype(bool), ds > low)
        if not (ds > low).any():
            assert r1 == 0
            continue
        rows, cols = np.nonzero(ds > low)
        assert (r0, r1, c0, c1) == (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
        regions_ref, n_ref = ndimage.label(ds > low)
        regions, n_regions = M._label(above[r0:r1, c0:c1], False)
        assert n_regions == n_ref
        np.testing.assert_array_equal(regions, regions_ref[r0:r1, c0:c1])
        base = np.maximum(low, base_floor)
        region_peak = np.zeros(n_ref + 1)
        region_peak[1:] = ndimage.maximum(ds, regions_ref, np.arange(1, n_ref + 1))
        thr = np.maximum(base, rel * region_peak[regions_ref])
        sel_ref = (ds > thr) & (regions_ref > 0)
        sel, s0, s1, t0, t1 = mk.above_region_thresholds(
            regions, n_regions, ds, tiles, T, n_sigma, low_floor, base_floor, rel, r0, c0)
        np.testing.assert_array_equal(sel.astype(bool), sel_ref[r0:r1, c0:c1])
        labels_ref, n_lab = ndimage.label(sel_ref)
        if s1 == 0:
            assert n_lab == 0
            continue
        labels, n = M._label(sel[s0:s1, t0:t1], False)
        assert n == n_lab
        np.testing.assert_array_equal(labels, labels_ref[r0 + s0:r0 + s1, c0 + t0:c0 + t1])


@pytest.mark.parametrize("seed", range(3))
def test_fast_detector_equals_the_reference_in_its_other_modes(seed):
    """Bright markers, the field's single noise figure, 16-bit frames and 32-bit ones (the
    numpy difference, then the compiled passes): the fast detector against its scipy.ndimage
    reference (the same blobs, centroids to 1e-6 px)."""
    rng = np.random.default_rng(40 + seed)
    shape = (150, 190)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    centres = rng.uniform(20, 130, (6, 2)) * [1.2, 1.0]
    bead = sum(np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 4.0) for cx, cy in centres)
    base = rng.uniform(100, 150)
    mask = np.hypot(xx - 95, yy - 75) < 80
    for dtype, scale, polarity, mode in ((np.uint8, 1, "dark", "field"),
                                         (np.uint8, 1, "bright", "block"),
                                         (np.uint16, 200, "dark", "block"),
                                         (np.int32, 1, "dark", "block")):   # numpy steps
        sign = 1 if polarity == "bright" else -1
        prev = base * scale + rng.normal(0, 1.0 * scale, shape)
        cur = (base + sign * 40 * bead) * scale + rng.normal(0, 1.0 * scale, shape)
        prev, cur = (np.clip(np.rint(v), 0, min(np.iinfo(dtype).max, 65535)).astype(dtype)
                     for v in (prev, cur))
        for m in (None, mask):
            kw = dict(polarity=polarity, noise_mode=mode, mask=m)
            fast = M.detect_markers(prev, cur, **kw)
            ref = M.detect_markers(prev, cur, reference=True, **kw)
            assert fast[0].shape == ref[0].shape and len(ref[0]) >= 3
            assert np.abs(fast[0] - ref[0]).max() < 1e-6
            assert np.abs(fast[1] - ref[1]).max() < 1e-6 * ref[1].max()



def test_whole_float_areas_are_read_as_integers():
    """``min_area_px=4.0`` is 4 (it was refused as not a whole number); 4.5, NaN and '4'
    are still refused, by name."""
    before = np.full((60, 60), 200, np.uint8)
    after = before.copy()
    after[20:25, 20:25] = 100
    after[40:42, 40:42] = 100                  # a blob of 10-14 px after the smoothing
    for area in (4, 15):
        a = M.detect_markers(before, after, min_area_px=area)
        b = M.detect_markers(before, after, min_area_px=float(area), max_area_px=2000.0)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert len(a[0]) == (2 if area == 4 else 1)
    for bad in (4.5, np.nan, "4"):
        with pytest.raises(ValueError, match="min_area_px and max_area_px: expected whole"):
            M.detect_markers(before, after, min_area_px=bad)


def test_row_counts_and_rows_at_equal_row_hypotheses():
    """identify_row's split hypotheses (row_counts, then row_hypotheses_at for some of
    them) against row_hypotheses (all rows at once) on random rows: 2-12 blobs, 2-9 beads
    of unequal gaps, blobs on whole and half pixels (ties in the distances) and repeated;
    the same counts, and the same labels, distances and inliers for any selection of
    hypotheses in any order."""
    rng = np.random.default_rng(11)
    for _ in range(300):
        n = int(rng.integers(2, 10))
        s = np.cumsum(rng.uniform(5, 20, n))
        K = int(rng.integers(2, 13))
        t = rng.uniform(-150, 150, K)
        if rng.random() < 0.5:
            t = np.round(2 * t) / 2
        if rng.random() < 0.3:
            t[rng.integers(K)] = t[0]
        tol = float(rng.uniform(0.05, 0.5))
        jb, e, inl, count = mk.row_hypotheses(t, s, tol)
        np.testing.assert_array_equal(mk.row_counts(t, s, tol), count)
        hyp = rng.permutation(len(count))[:int(rng.integers(0, len(count) + 1))]
        got = mk.row_hypotheses_at(t, s, tol, hyp.astype(np.int64))
        for g, r in zip(got, (jb, e, inl), strict=True):
            np.testing.assert_array_equal(g, r[hyp])
