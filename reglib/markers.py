"""Calibration markers: the beads of the robot's rod, found and identified in sweep frames.

The robot moves a radiolucent rod with steel beads along a *near* and a *far* plane between
source and intensifier, and on a validation row; a frame is taken after every move
(Guéziec et al. 1998, Section II; NOTES.md s1). Between two frames only the rod moved:

1. :func:`detect_markers` finds the beads that appeared between two consecutive frames (the
   rod's new position) as blobs of the difference of the log images, with sub-pixel,
   background-subtracted intensity-weighted centroids.
2. :func:`identify_row` says which bead of the rod each blob is: the beads' unequal spacing
   along the rod is matched to the blobs' positions along the imaged row by a 1-D affine map
   (consensus over all 2-point hypotheses), so beads outside the field or hidden are simply
   missing and stray blobs are rejected.
3. :func:`find_markers` runs both over a whole sweep (:class:`SweepData`) and returns the
   identified :class:`Markers` with the robot-reported 3-D position of each, for
   :func:`reglib.calibration.calibrate`.

Conventions: pixel coordinates ``(x, y) = (col, row)``, the centre of the top-left pixel at
(0, 0); images ``(H, W)`` indexed ``[row, col]``; robot frame in mm.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from reglib.geometry import as_flags, as_whole
from reglib.tps import ThinPlateSpline, _as_xy

__all__ = [
    "PLANE_CODES",
    "PLANE_NAMES",
    "REFERENCE",
    "NEAR",
    "FAR",
    "VALIDATION",
    "SweepData",
    "Markers",
    "detect_markers",
    "identify_row",
    "find_markers",
    "check_planes",
    "identify_by_paths",
]

#: plane codes of a sweep's frames
REFERENCE, NEAR, FAR, VALIDATION = -1, 0, 1, 2
PLANE_NAMES = {REFERENCE: "reference", NEAR: "near", FAR: "far", VALIDATION: "validation"}
PLANE_CODES = {v: k for k, v in PLANE_NAMES.items()}
#: detection works on a difference of Gaussians of these widths (px): about a bead's radius
#: in the image, and a background wider than a bead and narrower than the rod's band
BLOB_SIGMA_PX = 1.0
BACKGROUND_SIGMA_PX = 4.0
#: the smallest blob (px above the threshold) taken for a bead: fewer pixels locate no
#: centroid to a fraction of a pixel
MIN_AREA_PX = 4
#: the noise is measured per block of this size (px): a patient frame's quanta, hence the
#: noise of its log difference, vary several-fold over the field (bone against air beside
#: the limb), and one figure for the field lets the noisiest part through as blobs
NOISE_TILE_PX = 32
#: ...on every second row and column of the block (the band-pass's noise is correlated over
#: about a blob's width: a quarter of the pixels lose little), as a standard deviation
#: clipped at 3 of them, 2 times (a bead or an edge in the block does not count), from a
#: start robust to a third of the block being signal (the median absolute deviation of every
#: 4th value), scaled to a Gaussian's (a unit normal cut at +-3 has a deviation of 0.9866)
NOISE_STEP_PX = 2
NOISE_START_STEP = 4
NOISE_CLIP, NOISE_PASSES, NOISE_SCALE = 3.0, 2, 1.0 / 0.9866


# --------------------------------------------------------------------------- detection
def _log_image(img, response: str) -> np.ndarray:
    """The frame in log-intensity units (up to scale): as it is for a logarithmic video
    amplifier, else its logarithm."""
    a = np.asarray(img, dtype=np.float64)
    if response == "log":
        return a
    lo = 0.5 if np.issubdtype(np.asarray(img).dtype, np.integer) else 1e-6 * max(a.max(), 1e-12)
    return np.log(np.maximum(a, lo))


def _median(v: np.ndarray, reference: bool) -> float:
    """``np.median`` of a non-empty 1-D float array without NaN. The fast path partitions at
    one rank and takes the largest value below it for an even count: numpy's median
    partitions at both middle ranks at once, 9x slower here (1.9 against 0.21 ms on a
    frame's 240,000 values); the same value (the two middle ones' mean, as numpy takes it)."""
    if reference:
        return float(np.median(v))
    n = len(v)
    k = n // 2
    p = np.partition(v, k)
    if n % 2:
        return float(p[k])
    return float((p[:k].max() + p[k]) / 2)


def _label(binary: np.ndarray, reference: bool) -> tuple[np.ndarray, int]:
    """``scipy.ndimage.label(binary)`` (4-connected, labels 1..n in raster order of each
    region's first pixel); the fast path is OpenCV's connectedComponents, the same labels
    (tests/reglib/test_calibration.py), 2.4x faster."""
    if reference:
        return ndimage.label(binary)
    import cv2

    n, labels = cv2.connectedComponents(np.ascontiguousarray(binary, dtype=np.uint8),
                                        connectivity=4, ltype=cv2.CV_32S)
    return labels, n - 1


def _gaussian(img, sigma_px: float, reference: bool) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter(img, sigma_px)`` (mode "reflect"); the fast path is
    OpenCV's separable filter with scipy's kernel (radius ``int(4 sigma + 0.5)``) and border
    (BORDER_REFLECT is scipy's "reflect") in float32: 1e-6 of the band-pass's range from the
    reference, 4x faster than in float64 (0.56 against 2.2 ms for sigma 4 on a frame)."""
    if reference:
        return ndimage.gaussian_filter(img, sigma_px)
    import cv2

    r = int(4.0 * sigma_px + 0.5)
    return cv2.GaussianBlur(np.ascontiguousarray(img, dtype=np.float32), (2 * r + 1, 2 * r + 1),
                            sigmaX=sigma_px, sigmaY=sigma_px, borderType=cv2.BORDER_REFLECT)


_GAUSSIAN_REPLICA_OK: dict = {}
_GAUSSIAN_TAPS: dict = {}


def _gaussian_taps(sigma_px: float) -> np.ndarray:
    """The float32 taps of :func:`_gaussian`'s fast path (OpenCV's kernel of radius
    ``int(4 sigma + 0.5)``), computed once per sigma (0.04 ms a call)."""
    taps = _GAUSSIAN_TAPS.get(float(sigma_px))
    if taps is None:
        import cv2

        r = int(4.0 * sigma_px + 0.5)
        taps = cv2.getGaussianKernel(2 * r + 1, sigma_px, cv2.CV_32F).ravel()
        _GAUSSIAN_TAPS[float(sigma_px)] = taps
    return taps


def _gaussians(d, reference: bool) -> tuple[np.ndarray, np.ndarray]:
    """``_gaussian(d, BLOB_SIGMA_PX)`` and ``_gaussian(d, BACKGROUND_SIGMA_PX)``. The fast
    path computes both in one compiled pass (:func:`reglib._markers_numba.gaussian_pair`, a
    replica of OpenCV's float32 arithmetic: the same bits, 1.3 against 0.9 ms for the pair
    on a 480 x 505 field) when the replica equals OpenCV for this shape in this process
    (checked once per shape on random values, :func:`_gaussian_replica_check`); else
    OpenCV's two calls."""
    if reference:
        return (_gaussian(d, BLOB_SIGMA_PX, True), _gaussian(d, BACKGROUND_SIGMA_PX, True))
    from reglib import _markers_numba as mk

    d = np.ascontiguousarray(d, dtype=np.float32)
    key = d.shape
    if key not in _GAUSSIAN_REPLICA_OK:
        if len(_GAUSSIAN_REPLICA_OK) >= 64:
            _GAUSSIAN_REPLICA_OK.pop(next(iter(_GAUSSIAN_REPLICA_OK)))
        _GAUSSIAN_REPLICA_OK[key] = _gaussian_replica_check(key)
    if _GAUSSIAN_REPLICA_OK[key]:
        return mk.gaussian_pair(d, _gaussian_taps(BLOB_SIGMA_PX),
                                _gaussian_taps(BACKGROUND_SIGMA_PX))
    return (_gaussian(d, BLOB_SIGMA_PX, False), _gaussian(d, BACKGROUND_SIGMA_PX, False))


def _gaussian_replica_check(shape) -> bool:
    """Whether :func:`reglib._markers_numba.gaussian_pair` equals :func:`_gaussian`'s fast
    path (OpenCV) bit for bit on random values of ``shape`` (of widely different scales);
    False for a shape too small for it (a side of at most twice the wider kernel's
    radius)."""
    from reglib import _markers_numba as mk

    ka, kb = _gaussian_taps(BLOB_SIGMA_PX), _gaussian_taps(BACKGROUND_SIGMA_PX)
    if min(shape) <= max(len(ka), len(kb)) - 1:
        return False
    rng = np.random.default_rng(20261128)
    # 2**-10...2**10 times uniform in (-2, 2) (ldexp: 3 ms for a 480 x 505 field, a power of
    # ten 6 ms)
    img = np.ldexp(rng.uniform(-2.0, 2.0, shape).astype(np.float32),
                   rng.integers(-10, 11, shape, dtype=np.int32))
    ga, gb = mk.gaussian_pair(img, ka, kb)
    return bool(np.array_equal(ga, _gaussian(img, BLOB_SIGMA_PX, False))
                and np.array_equal(gb, _gaussian(img, BACKGROUND_SIGMA_PX, False)))


def _clipped_std(x: np.ndarray) -> float:
    """The reference of the compiled block noise (``reglib._markers_numba.tile_noise``): a
    start from the median and the median absolute deviation of every
    :data:`NOISE_START_STEP`-th value of ``x`` (their mean and standard deviation if that
    deviation is 0: most values equal, as in clipped video), then :data:`NOISE_PASSES`
    times the mean and standard deviation of the values within :data:`NOISE_CLIP`
    deviations of the centre, times :data:`NOISE_SCALE`."""
    start = x[::NOISE_START_STEP]
    mean = np.median(start)
    sd = 1.4826 * np.median(np.abs(start - mean))
    if not sd > 0:   # most values equal (clipped video): the plain deviation
        mean, sd = x.mean(), np.sqrt(((x - x.mean()) ** 2).mean())
    for _ in range(NOISE_PASSES):
        keep = (x >= mean - NOISE_CLIP * sd) & (x <= mean + NOISE_CLIP * sd)
        if not keep.any():
            break
        mean = x[keep].mean()
        sd = np.sqrt(((x[keep] - mean) ** 2).mean())
    return float(NOISE_SCALE * sd)


def _noise_tiles(g1, g2, inside, field_noise, mode: str, reference: bool, ds=None,
                 raw=None) -> np.ndarray:
    """(ny, nx) the noise of the band-pass ``g1 - g2`` per block of :data:`NOISE_TILE_PX`
    px (the blocks from the frame's corner, the last ones cut by its edge): the clipped
    standard deviation (:func:`_clipped_std`) of the block's values within ``inside``, on
    every :data:`NOISE_STEP_PX`-th row and column; then the largest figure of the block and
    the 8 around it; a block with no figure there (less than a quarter of its sampled
    pixels inside, nor any neighbour's) takes the field's figure ``field_noise``.
    ``mode="field"``: ``field_noise`` everywhere.

    ``field_noise``: a number, or a function that computes it (1 ms per frame: two medians
    of the whole field), called only when a block needs it. With ``ds`` (the band-pass
    after the rim test) given, a block without a figure whose pixels are all outside
    ``inside`` with ``ds == 0`` does not need it (no pixel there can pass a positive
    threshold) and gets ``inf``, which gives the same detections. ``raw``: the blocks'
    figures before the neighbours' maximum, when the caller has them
    (``reglib._markers_numba.band_noise``)."""
    H, W = g1.shape
    T, S = NOISE_TILE_PX, NOISE_STEP_PX
    ny, nx = -(-H // T), -(-W // T)
    figure = field_noise if callable(field_noise) else (lambda: field_noise)
    min_count = (T // S) ** 2 // 4
    if mode == "field":
        return np.full((ny, nx), figure(), dtype=np.float64)
    if reference:
        v = np.asarray(g1, dtype=np.float64) - np.asarray(g2, dtype=np.float64)
        tiles = np.full((ny, nx), np.nan)
        for by in range(ny):
            for bx in range(nx):
                sl = (slice(by * T, (by + 1) * T, S), slice(bx * T, (bx + 1) * T, S))
                x = v[sl][inside[sl]]
                if len(x) >= min_count:
                    tiles[by, bx] = _clipped_std(x)
    else:
        from reglib import _markers_numba as mk

        tiles = raw if raw is not None else mk.tile_noise(
            g1, g2, inside, T, S, min_count, NOISE_START_STEP, NOISE_CLIP, NOISE_PASSES,
            NOISE_SCALE)
        if ds is not None:   # the steps below compiled (reglib._markers_numba.spread_tiles)
            tiles, need = mk.spread_tiles(tiles, inside, ds, T)
            none = ~np.isfinite(tiles)
            if none.any():
                tiles[none] = figure() if need else np.inf
            return tiles
    # the largest of the block and its 8 neighbours (blocks without a figure, outside the
    # field or beyond the frame, do not count): a block across the edge of the limb
    # measures its quiet part (the clipping takes the noisy part for outliers), and the
    # noisy pixels next to it would pass as blobs
    tiles = ndimage.maximum_filter(np.where(np.isfinite(tiles), tiles, -np.inf), size=3,
                                   mode="constant", cval=-np.inf)
    none = ~np.isfinite(tiles)
    if none.any():
        need = ds is None or any(
            inside[by * T:(by + 1) * T, bx * T:(bx + 1) * T].any()
            or (ds[by * T:(by + 1) * T, bx * T:(bx + 1) * T] != 0).any()
            for by, bx in zip(*np.nonzero(none), strict=True))
        tiles[none] = figure() if need else np.inf
    return tiles


def _noise_map(g1, g2, inside, field_noise, mode: str, reference: bool) -> np.ndarray:
    """(H, W) the noise of the band-pass at each pixel: its block's figure
    (:func:`_noise_tiles`)."""
    H, W = g1.shape
    T = NOISE_TILE_PX
    tiles = _noise_tiles(g1, g2, inside, field_noise, mode, reference)
    return np.repeat(np.repeat(tiles, T, axis=0), T, axis=1)[:H, :W]


def detect_markers(previous, current, *, polarity: str = "dark", response: str = "log",
                   rel_threshold: float = 0.35, noise_mode: str = "block",
                   n_sigma: float = 4.5, min_area_px: int = MIN_AREA_PX, max_area_px: int = 2000,
                   max_elongation: float = 2.0, centroid_floor: float = 0.25,
                   mask=None, reference: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Blobs that appeared in ``current`` and not in ``previous`` (the rod's new beads).

    Works on ``d = log(previous) - log(current)`` less its median over the field (for dark
    markers: the added attenuation, independent of what lies behind and of a change of the
    tube output between the frames; with ``response="log"`` the frames already are log
    intensities, as from a logarithmic video amplifier, and are differenced as they are,
    with ``"linear"`` their logarithm is taken); blobs are the connected regions of the
    smoothed ``d`` above ``rel_threshold`` times the peak of the region (above the noise,
    ``n_sigma`` robust standard deviations of the noise where it lies) they lie in, and
    above half ``rel_threshold`` times the frame's peak. Each centroid is the
    mean over a disc about the blob weighted by ``d`` above a floor (the median of a ring
    around the disc, the background, plus ``centroid_floor`` times the blob's height above
    it: this drops the rod's faint band under the bead), iterated with the disc re-centred.

    Parameters
    ----------
    previous, current : (H, W) images (any dtype; intensities, larger = more X-rays).
    polarity : "dark" (markers absorb: darker in ``current``) or "bright".
    noise_mode : "block" (the noise measured per block of the field, :func:`_noise_map`:
        behind bone, beside the limb in air and under a steel instrument the quanta and so
        the noise differ several-fold) or "field" (one robust figure for the whole field;
        with ``n_sigma=6.0``, the detector before 2026-11-25: a patient turned under the
        C-arm filled the noisy part with blobs, 34-84 per frame for a rod of 8 beads).
    mask : (H, W) bool, optional; where to look (e.g. the intensifier's circular field).
        A blob whose centroid window reaches outside it is dropped (cut by the field's edge,
        its centroid would be biased).
    reference : the same steps in numpy and scipy.ndimage alone (float64 Gaussian filters
        on the whole frame, per-label maxima and areas, numpy medians), kept as the
        reference of the fast path (the field's bounding box, float32 OpenCV Gaussians,
        OpenCV's connected components, the passes and the blob centroids compiled in
        :mod:`reglib._markers_numba`), which ``tests/reglib/test_calibration.py`` compares
        with it on random frames (the same blobs, centroids within 1e-6 px).

    Returns
    -------
    xy_px : (K, 2) sub-pixel centroids (x, y).
    strength : (K,) peak of ``d`` of each blob (log units).
    """
    a, b = np.asarray(previous), np.asarray(current)
    if a.shape != b.shape or a.ndim != 2 or min(a.shape) < 3:
        raise ValueError(f"detect_markers: frames must be two (H, W) images of the same shape, "
                         f"at least 3 x 3 px, got {a.shape} and {b.shape}")
    for name, x in (("previous", a), ("current", b)):
        if x.dtype.kind not in "biuf":
            raise ValueError(f"detect_markers: {name}: expected real intensities, got "
                             f"{x.dtype}")
        if x.dtype.kind == "f" and not np.isfinite(x).all():   # found no marker, unsaid
            raise ValueError(f"detect_markers: {name}: the frame holds NaN or infinite "
                             "values")
        if x.size and x.dtype.kind in "fiu" and x.dtype.itemsize > 4 \
                and np.abs(x).max() > 1e30:     # float32 would make them inf (a review)
            raise ValueError(f"detect_markers: {name}: values up to "
                             f"{float(np.abs(x).max()):.3g}; expected intensities (grey "
                             "levels), at most 1e30")
    if polarity not in ("dark", "bright"):
        raise ValueError(f"polarity: expected 'dark' or 'bright', got {polarity!r}")
    if response not in ("log", "linear"):
        raise ValueError(f"response: expected 'log' or 'linear', got {response!r}")
    if noise_mode not in ("block", "field"):
        raise ValueError(f"noise_mode: expected 'block' or 'field', got {noise_mode!r}")
    for name, v, low, high in (("rel_threshold", rel_threshold, 0.0, 1.0),
                               ("n_sigma", n_sigma, 0.0, 100.0),
                               ("max_elongation", max_elongation, 1.0, 100.0),
                               ("centroid_floor", centroid_floor, 0.0, 1.0)):
        if isinstance(v, bool) or not isinstance(v, int | float | np.number) \
                or not low <= float(v) <= high:
            raise ValueError(f"detect_markers: {name}: expected a number in [{low:g}, "
                             f"{high:g}], got {v!r}")
    try:    # whole numbers, 4.0 as 4 (geometry.as_whole; booleans and text refused)
        areas = [as_whole(v, "area") for v in (min_area_px, max_area_px)]
        if any(a.ndim for a in areas) or not 1 <= areas[0] <= areas[1]:
            raise ValueError
    except ValueError:
        raise ValueError(f"detect_markers: min_area_px and max_area_px: expected whole numbers "
                         f"1 <= min <= max, got {min_area_px!r} and {max_area_px!r}") from None
    min_area_px, max_area_px = int(areas[0]), int(areas[1])
    if mask is not None:
        mask = as_flags(mask, "mask")
        if mask.shape != a.shape:
            raise ValueError(f"mask: expected shape {a.shape}, got {mask.shape}")
    x_off = y_off = 0
    if mask is not None and not reference:
        # the work on the field's bounding box, widened by the wider Gaussian's radius: d is
        # 0 outside the field, so every value that can differ from 0 lies inside it
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if len(rows):
            m = int(4.0 * BACKGROUND_SIGMA_PX + 0.5) + 1
            # ...its corner on the noise blocks' grid, so that the blocks are the frame's
            y_off = max(rows[0] - m, 0) // NOISE_TILE_PX * NOISE_TILE_PX
            x_off = max(cols[0] - m, 0) // NOISE_TILE_PX * NOISE_TILE_PX
            y_end, x_end = min(rows[-1] + m + 1, a.shape[0]), min(cols[-1] + m + 1, a.shape[1])
            a, b = a[y_off:y_end, x_off:x_end], b[y_off:y_end, x_off:x_end]
            mask = mask[y_off:y_end, x_off:x_end]
    small_int = (np.issubdtype(a.dtype, np.integer) and np.issubdtype(b.dtype, np.integer)
                 and max(a.dtype.itemsize, b.dtype.itemsize) <= 2)
    inside = mask if mask is not None else np.ones(a.shape, dtype=bool)
    if not reference and response == "log" and small_int:
        # the same steps compiled, one pass each (reglib._markers_numba)
        from reglib import _markers_numba as mk

        top = max(int(np.iinfo(a.dtype).max) - min(int(np.iinfo(b.dtype).min), 0),
                  int(np.iinfo(b.dtype).max) - min(int(np.iinfo(a.dtype).min), 0))
        # d in float32 holds the float64 difference exactly (half-integers)
        d, n_in = mk.centred_difference(a, b, inside, -1 if polarity == "bright" else 1, top)
        g1, g2 = _gaussians(d, False)
        if noise_mode == "block":     # the band-pass and its blocks' noise in one pass
            ds, raw_tiles = mk.band_noise(g1, g2, inside, NOISE_TILE_PX, NOISE_STEP_PX,
                                          (NOISE_TILE_PX // NOISE_STEP_PX) ** 2 // 4,
                                          NOISE_START_STEP, NOISE_CLIP, NOISE_PASSES,
                                          NOISE_SCALE)
        else:
            ds, raw_tiles = mk.band(g1, g2), None
        peak = float(ds.max())

        def noise():     # the field's figure, computed only if a block needs it
            dsi = (g1 - g2)[inside] if n_in else (g1 - g2).ravel()
            return 1.4826 * _median(np.abs(dsi - _median(dsi, False)), False)
    else:
        raw_tiles = None
        d = _log_image(a, response) - _log_image(b, response)
        if polarity == "bright":
            d = -d
        # the automatic brightness control changes the tube output from frame to frame: a
        # uniform gain, i.e. a constant in log intensity, that would lift the whole field above
        # the threshold; it is the median difference (the beads cover a few hundred pixels)
        if inside.any():
            d = d - _median(d[inside], reference)
        if mask is not None:
            d = np.where(mask, d, 0.0)
        # a band-pass at the beads' scale (difference of Gaussians): the rod's band and the
        # broad steel tip fade, bead-sized blobs stay, so that a strong tip or a blurred frame
        # does not lift the threshold above the beads
        g1, g2 = _gaussians(d, reference)
        ds = g1 - g2
        dsi = ds[inside] if inside.any() else ds.ravel()  # the noise of the field, not the black
        noise = 1.4826 * _median(np.abs(dsi - _median(dsi, reference)), reference)
        # ...of attenuation that was added: the positive rim the band-pass leaves around a bead
        # that went away (or any dip) is no blob
        ds = np.where(g1 > 0.5 * ds, ds, 0.0)
        peak = ds.max()
    if peak <= 0:
        return np.zeros((0, 2)), np.zeros(0)
    # relative threshold per region: each connected region above the noise gets
    # rel_threshold times its own peak (a bright newcomer elsewhere, e.g. an instrument
    # moved into the field, does not raise the threshold for the beads)
    # never below half the global relative threshold: noise specks are regions of their own
    if reference:
        noise_px = _noise_map(g1, g2, inside, noise, noise_mode, reference)
        low = np.maximum(n_sigma * noise_px, 0.02 * peak)
        regions, n_regions = _label(ds > low, reference)
        base = np.maximum(low, 0.5 * rel_threshold * peak)
        region_peak = np.zeros(n_regions + 1)
        region_peak[1:] = ndimage.maximum(ds, regions, np.arange(1, n_regions + 1))
        thr = np.maximum(base, rel_threshold * region_peak[regions])
        labels, n = ndimage.label((ds > thr) & (regions > 0))
    else:  # the same thresholds from the blocks' figures, per pixel in compiled passes
        # (ndimage.maximum sorts all labels: 45 ms on a noisy frame)
        from reglib import _markers_numba as mk

        tiles = _noise_tiles(g1, g2, inside, noise, noise_mode, False, ds=ds, raw=raw_tiles)
        low_floor, base_floor = 0.02 * peak, 0.5 * rel_threshold * peak
        # each labelling on the bounding box of its pixels: the same labels (raster order)
        above, r0, r1, c0, c1 = mk.above_noise(ds, tiles, NOISE_TILE_PX, n_sigma, low_floor)
        if r1 == 0:
            return np.zeros((0, 2)), np.zeros(0)
        regions, n_regions = _label(above[r0:r1, c0:c1], False)
        sel, s0, s1, t0, t1 = mk.above_region_thresholds(
            regions, n_regions, ds, tiles, NOISE_TILE_PX, n_sigma, low_floor, base_floor,
            rel_threshold, r0, c0)
        if s1 == 0:
            return np.zeros((0, 2)), np.zeros(0)
        labels, n = _label(sel[s0:s1, t0:t1], False)
        xy, strength = mk.blob_centroids(
            d, labels, n, r0 + s0, c0 + t0, ds, inside, mask is not None, float(min_area_px),
            float(max_area_px), float(max_elongation), float(centroid_floor))
        return xy + [x_off, y_off], strength
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0)
    areas = ndimage.sum_labels(np.ones_like(ds), labels, np.arange(1, n + 1))
    slices = ndimage.find_objects(labels)
    H, W = d.shape
    out, strength = [], []
    for k, sl in enumerate(slices):
        if sl is None or not (min_area_px <= areas[k] <= max_area_px):
            continue
        sub = labels[sl] == k + 1
        ys, xs = np.nonzero(sub)
        ys = ys + sl[0].start
        xs = xs + sl[1].start
        cov = np.cov(np.vstack([xs, ys])) if len(xs) > 2 else np.eye(2)
        ev = np.linalg.eigvalsh(cov)
        if ev[0] <= 0 or np.sqrt(ev[1] / ev[0]) > max_elongation:
            continue  # not a round blob (the rod's tip, an instrument edge)
        cx, cy = xs.mean(), ys.mean()
        r_in = np.sqrt(areas[k] / np.pi) * 1.6 + 1.5
        for _ in range(3):
            x0, x1 = int(max(cx - r_in - 4, 0)), int(min(cx + r_in + 5, W))
            y0, y1 = int(max(cy - r_in - 4, 0)), int(min(cy + r_in + 5, H))
            px, py = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
            pd = d[y0:y1, x0:x1]
            rr = np.hypot(px - cx, py - cy)
            ring = pd[(rr > r_in) & (rr <= r_in + 3)]
            bg = np.median(ring) if ring.size else 0.0
            inner = rr <= r_in
            floor = bg + centroid_floor * (pd[inner].max() - bg) if inner.any() else bg
            w = np.where(inner, np.maximum(pd - floor, 0.0), 0.0)
            sw = w.sum()
            if sw <= 0:
                break
            cx, cy = (w * px).sum() / sw, (w * py).sum() / sw
        if mask is not None and not mask[y0:y1, x0:x1].all():
            continue  # cut by the edge of the field
        out.append((cx, cy))
        strength.append(float(ds[sl][sub].max()))
    if not out:
        return np.zeros((0, 2)), np.zeros(0)
    return np.asarray(out, dtype=np.float64) + [x_off, y_off], np.asarray(strength)


# --------------------------------------------------------------------------- identification
def increasing_positions(s: np.ndarray, min_count: int) -> bool:
    """Whether ``s`` is a 1-D array of at least ``min_count`` finite, strictly increasing
    values (the beads' positions along the rod, mm)."""
    return bool(s.ndim == 1 and len(s) >= min_count and np.all(np.isfinite(s))
                and np.all(np.diff(s) > 0))


def identify_row(xy_px, bead_positions_mm, *, tolerance: float = 0.15,
                 min_matched: int = 4, reference: bool = False) -> tuple[np.ndarray, float]:
    """Which bead of the rod each blob of one row is.

    The rod lies parallel to the image plane in a sweep, so along the imaged row the bead
    positions ``s`` (mm along the rod) map to the blobs' coordinate ``t`` (px, on the row's
    principal line) by an affine map ``t = a s + b`` (up to the intensifier's distortion).
    Every hypothesis "blobs i < j are beads p and q" (both orientations of the rod) fixes the
    map; the one that places most blobs within ``tolerance`` times the smallest predicted gap
    of a bead wins, ties broken by the RMS of a least-squares refit on its blobs. The beads'
    unequal gaps make the answer unique; beads outside the field or hidden are simply
    missing, stray blobs are left unmatched. A runner-up that labels no blob otherwise (the
    same labels, some blobs left out) is no rival; the blobs still unlabelled then take the
    labels of free beads at their places along the row (:func:`_label_the_rest`).

    Parameters
    ----------
    xy_px : (K, 2) blob centroids of one row.
    bead_positions_mm : (n,) bead positions along the rod, increasing, unequal gaps.
    reference : the hypotheses as numpy arrays (the reference of the compiled loops,
        compared in tests/reglib/test_calibration.py).

    Returns
    -------
    bead : (K,) int, the bead index of each blob, -1 for a blob that matches no bead.
    rms_px : float, RMS residual of the matched blobs along the row.

    Raises
    ------
    ValueError
        Fewer than ``min_matched`` blobs, too many blobs, or no hypothesis matching
        ``min_matched`` blobs unambiguously.
    """
    xy = _as_xy(xy_px)
    s = np.asarray(bead_positions_mm, dtype=np.float64)
    if not increasing_positions(s, 2):
        raise ValueError(f"identify_row: bead_positions_mm must be increasing finite positions "
                         f"(mm along the rod), got {s.tolist()!r:.80}")
    K, n = len(xy), len(s)
    if K < min_matched:
        raise ValueError(f"identify_row: {K} blobs; at least {min_matched} are needed")
    if K > 3 * n:
        raise ValueError(f"identify_row: {K} blobs for a rod of {n} beads; too many to match "
                         "(something besides the rod changed between the two frames: e.g. "
                         "an instrument moved, or a bright region such as air beside the limb "
                         "saturates the video while the tube output changed)")
    c = xy.mean(axis=0)
    u = np.linalg.svd(xy - c)[2][0]
    t = (xy - c) @ u
    # hypotheses: blob pair (i, j), bead pair (p, q) with p != q (order gives the orientation)
    if reference:
        bi, bj = np.array(list(itertools.combinations(range(K), 2))).T
        bp, bq = np.array([(p, q) for p in range(n) for q in range(n) if p != q]).T
        I, P = np.repeat(bi, len(bp)), np.tile(bp, len(bi))
        J, Q = np.repeat(bj, len(bq)), np.tile(bq, len(bj))
        a = (t[J] - t[I]) / (s[Q] - s[P])
        b = t[I] - a * s[P]
        pred = a[:, None] * s[None, :] + b[:, None]                   # (B, n) px
        gap = np.abs(a) * np.min(np.diff(s))                           # (B,)
        err = np.abs(t[None, :, None] - pred[:, None, :])              # (B, K, n)
        j = np.argmin(err, axis=2)
        e = np.take_along_axis(err, j[..., None], axis=2)[..., 0]      # (B, K)
        inl = e < tolerance * gap[:, None]
        count = inl.sum(axis=1)
    else:   # the same, compiled (reglib._markers_numba.row_counts): the counts first
        from reglib._markers_numba import row_counts

        count = row_counts(np.ascontiguousarray(t), np.ascontiguousarray(s), float(tolerance))
    if count.max() < min_matched:
        raise ValueError(f"identify_row: the spacing pattern matches at most {count.max()} "
                         f"of {K} blobs (need {min_matched})")
    # distinct assignments of the two best counts, refitted; a candidate's score is its count
    # minus its refit RMS in units of (tolerance * gap / 5): a stray blob that happens to fall
    # near a bead cannot outvote a tight fit of fewer blobs
    top = np.flatnonzero(count >= max(min_matched, count.max() - 1))
    if not reference:
        # ...then the labels, distances and inliers of these hypotheses alone
        # (reglib._markers_numba.row_hypotheses_at, row_hypotheses' rows), numbered 0.. in
        # the same order
        from reglib._markers_numba import row_hypotheses_at

        j, e, inl = row_hypotheses_at(np.ascontiguousarray(t), np.ascontiguousarray(s),
                                      float(tolerance), top)
        top = np.arange(len(top))
    scored = None
    if not reference:
        # the doubles resolved, the distinct assignments and their approximate scores
        # compiled (reglib._markers_numba.resolve_assignments); only those that can come
        # first or second (within 0.5 of the best, with a margin for the rounding of the
        # sums) are rescored as below: the same scores, winner and runner-up
        from reglib._markers_numba import resolve_assignments

        finals, approx, which = resolve_assignments(j, e, inl, top, s, t, float(tolerance))
        if np.all(np.isfinite(approx)):
            scored = []
            for a_k, h in zip(finals[approx >= approx.max() - 0.5 - 1e-6],
                              which[approx >= approx.max() - 0.5 - 1e-6], strict=True):
                m = a_k >= 0
                inl[h] = m
                slope, _, rms = _line_fit(s[a_k[m]], t[m])
                unit = 0.2 * tolerance * abs(slope) * np.min(np.diff(s))
                scored.append((m.sum() - rms / unit, rms, h, a_k))
    if scored is None:
        assign = np.where(inl[top], j[top], -1)
        _, first = np.unique(assign, axis=0, return_index=True)
        scored, seen = [], set()
        for k in top[first]:
            m = inl[k].copy()
            for bead_idx in np.unique(j[k][m]):  # two blobs on one bead: keep the closer
                claim = np.flatnonzero(m & (j[k] == bead_idx))
                m[claim[np.argsort(e[k][claim])[1:]]] = False
            inl[k] = m
            final = tuple(np.where(m, j[k], -1).tolist())
            if final in seen:  # the same assignment once the doubles are resolved
                continue
            seen.add(final)
            slope, _, rms = _line_fit(s[j[k][m]], t[m])
            unit = 0.2 * tolerance * abs(slope) * np.min(np.diff(s))
            scored.append((m.sum() - rms / unit, rms, k, np.array(final)))
    scored.sort(key=lambda c: c[:3], reverse=True)
    score, rms, k, best = scored[0]
    # a rival is an assignment that labels a blob otherwise: one that only leaves out some
    # of the best's blobs (the intensifier's distortion bends the row, and dropping its end
    # blob straightens the line fit) agrees with it and is no rival
    rival = next((c for c in scored[1:] if _conflicting(best, c[3])), None)
    if rival is not None and rival[0] > score - 0.5:
        raise ValueError(f"identify_row: ambiguous (two bead assignments fit {K} blobs about "
                         f"as well: RMS {rms:.2f} and {rival[1]:.2f} px)")
    bead = np.where(inl[k], j[k], -1)
    m = bead >= 0
    tol_px = tolerance * abs(_line_fit(s[bead[m]], t[m])[0]) * np.min(np.diff(s))
    w = (xy - c) @ np.array([-u[1], u[0]])
    keep = _on_row(t, w, m, ACROSS_ROW_TOLERANCES * tol_px)
    if (keep != m).any():
        # a blob beside the row took a bead's label: drop it, and give the label to an
        # unmatched blob on the row at that bead's place, if there is one
        bead[m & ~keep] = -1
        if keep.sum() < min_matched:
            raise ValueError(f"identify_row: {int((m & ~keep).sum())} of the blobs that fit "
                             "the spacing lie off the row's line; too few left")
    # an unmatched blob on the row at a free bead's place takes its label: a blob whose bead
    # a stray had taken, or an end blob that the intensifier's distortion moved beyond the
    # straight line's tolerance
    if _label_the_rest(bead, s, t, w, tol_px) or (keep != m).any():
        m = bead >= 0
        rms = _line_fit(s[bead[m]], t[m])[2]
    return bead, rms


def _label_the_rest(bead: np.ndarray, s: np.ndarray, t: np.ndarray, w: np.ndarray,
                    tol_px: float) -> bool:
    """Label, in place, the unmatched blobs of a row (``bead`` -1) that lie within
    ``tol_px`` along the row of a free bead's place and on the row across it, one at a time,
    the nearest first. The places come from a fit of the labelled blobs' ``t`` (px along
    the row) to their beads' ``s`` (mm): a line through four blobs, a parabola through
    five, a cubic through six or more (the intensifier's pincushion stretches the row
    towards the field's edge, as ``r (1 + k r^2)``: at the row's ends, where a blob lies
    beyond the fitted ones, a straight line missed it by 7-13 px against a tolerance of
    about 4 px); across the row, a line through the blobs' ``w`` (px) within
    ``ACROSS_ROW_TOLERANCES * tol_px``. Returns whether any blob was labelled."""
    added = False
    while np.any(bead < 0):
        m = bead >= 0
        deg = int(min(3, max(1, m.sum() - 3)))
        place = np.polyval(np.polyfit(s[bead[m]], t[m], deg), s)        # (n,) px
        w_slope, w_icpt, _ = _line_fit(t[m], w[m])
        free = np.setdiff1d(np.arange(len(s)), bead[m])
        if not free.size:
            break
        best = None
        for i in np.flatnonzero(~m):
            if abs(w[i] - (w_slope * t[i] + w_icpt)) >= ACROSS_ROW_TOLERANCES * tol_px:
                continue
            off = np.abs(place[free] - t[i])
            p = int(np.argmin(off))
            if off[p] < tol_px and (best is None or off[p] < best[0]):
                best = (off[p], i, int(free[p]))
        if best is None:
            break
        bead[best[1]] = best[2]
        added = True
    return added


def _conflicting(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two assignments of a row's blobs to beads (-1: none) contradict each other:
    a blob labelled by both with different beads, or one bead given to two blobs."""
    both = (a >= 0) & (b >= 0)
    if np.any(a[both] != b[both]):
        return True
    union = np.where(a >= 0, a, b)
    union = union[union >= 0]
    return len(np.unique(union)) < len(union)


def _line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares line ``y = slope x + intercept`` through ``(x, y)`` (at least two
    distinct ``x``) and its RMS residual."""
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    slope = float(np.dot(dx, y - ym) / np.dot(dx, dx))
    icpt = ym - slope * xm
    rms = float(np.sqrt(np.mean((y - (slope * x + icpt)) ** 2)))
    return slope, icpt, rms


def _on_row(t, w, matched, tol_px: float) -> np.ndarray:
    """Which of the ``matched`` blobs lie on the row's line (a bool mask).

    The spacing match uses the coordinate ``t`` along the row alone, so a stray blob beside
    the row (the rod's steel tip, an instrument's corner) can take a missing or a present
    bead's label. Each matched blob's offset ``w`` across the row is compared with the
    straight line through the others (leave one out, so that a far blob cannot pull the
    line towards itself); the farthest blob is dropped while it is more than ``tol_px``
    off, and the test repeated on the rest (four blobs at least)."""
    keep = matched.copy()
    while keep.sum() >= 4:
        idx = np.flatnonzero(keep)
        # leave-one-out residuals from one least-squares line: r_i / (1 - h_i), with the
        # line's leverages h_i = 1/n + (x_i - mean)^2 / Sxx
        x, y = t[idx], w[idx]
        slope, icpt, _ = _line_fit(x, y)
        dx = x - x.mean()
        h = 1.0 / len(idx) + dx * dx / max(float(np.sum(dx * dx)), 1e-300)
        res = np.abs(y - (slope * x + icpt)) / np.maximum(1.0 - h, 1e-12)
        worst = int(np.argmax(res))
        if res[worst] <= tol_px:
            break
        keep[idx[worst]] = False
    return keep


# --------------------------------------------------------------------------- sweep data
@dataclass(frozen=True)
class SweepData:
    """What a clinic records while the robot sweeps the rod through one view.

    Attributes
    ----------
    view : name of the view (for messages).
    frames : (F, H, W) images, one after each rod move (X-rays on continuously).
    plane : (F,) int; -1 a reference frame (rod parked outside the beam), 0 near plane,
        1 far plane, 2 validation row.
    beads_robot : (F, n, 3) robot-reported bead centres, mm, robot frame (NaN where plane
        is -1).
    bead_positions_mm : (n,) bead positions along the rod.
    mask : (H, W) bool or None; the image's field (where markers may be found).
    """

    view: str
    frames: np.ndarray
    plane: np.ndarray
    beads_robot: np.ndarray
    bead_positions_mm: np.ndarray
    mask: np.ndarray | None = None


@dataclass
class Markers:
    """Identified markers of one view: one row per marker.

    ``frame (M,)``, ``plane (M,)`` (0 near, 1 far, 2 validation), ``bead (M,)`` index along
    the rod, ``xy_px (M, 2)``, ``robot (M, 3)`` mm (reported). ``problems``: messages naming
    the view, frame and beads that were missing, stray or unidentifiable.
    """

    view: str
    frame: np.ndarray
    plane: np.ndarray
    bead: np.ndarray
    xy_px: np.ndarray
    robot: np.ndarray
    problems: list[str] = field(default_factory=list)
    expected: int = 0

    def select(self, plane: int) -> tuple[np.ndarray, np.ndarray]:
        """``(xy_px (k, 2), robot (k, 3))`` of the markers of one plane."""
        m = self.plane == plane
        return self.xy_px[m], self.robot[m]


#: a blob more than this many along-row tolerances (``tolerance`` of :func:`identify_row`
#: times the smallest bead gap, px) off the straight line through the row's other blobs is
#: a stray: correctly identified beads of the clinic sweeps (experiment2, seed 1996, four
#: views) lie 0.53 px (median), 2.4 px (99th percentile), 2.9 px (max) off it (the row bends
#: with the distortion), against an along-row tolerance of 3.8 px there
ACROSS_ROW_TOLERANCES = 3.0

#: a row's labels disagree with its plane when one of its markers lies this many bead gaps
#: (the smallest predicted spacing between the row's beads, px) from where the plane's other
#: rows place that bead: a wrong label is a whole gap or more off, a right one a pixel or less
RELABEL_GAPS = 0.4


#: the terms u^a v^b of the plane-to-image map: total degree <= 3, linear across the rows
_PLANE_TERMS = tuple((a, b) for a in range(4) for b in range(2) if a + b <= 3)


def _plane_design(robot_mm: np.ndarray, rod_mm: np.ndarray):
    """The design of a smooth map from robot points of one sweep plane to pixels: a
    polynomial in ``u`` (along the rod) and ``v`` (across it, in the plane), of total degree
    <= 3 and linear in ``v`` (:data:`_PLANE_TERMS`), in coordinates centred and scaled on
    ``robot_mm`` (the plane's markers). Returns ``design(points (..., 3)) -> (..., T)``, or
    None when the rod is normal to the plane."""
    c = robot_mm.mean(axis=0)
    normal = np.linalg.svd(robot_mm - c, full_matrices=False)[2][2]
    u = rod_mm - np.dot(rod_mm, normal) * normal
    if not np.linalg.norm(u) > 0:
        return None
    u /= np.linalg.norm(u)
    axes = np.stack([u, np.cross(normal, u)], axis=1)          # (3, 2)
    scale = np.maximum(np.abs((robot_mm - c) @ axes).max(axis=0), 1e-9)

    def design(points):
        w = ((np.asarray(points, dtype=np.float64) - c) @ axes) / scale
        return np.stack([w[..., 0] ** a * w[..., 1] ** b for a, b in _PLANE_TERMS], axis=-1)

    return design


def _match_predictions(xy: np.ndarray, pred: np.ndarray, within_px: float):
    """Each blob ``xy`` (K, 2) the bead whose predicted pixel ``pred`` (n, 2) is nearest to
    it: ``(bead (K,), good (K,))``, ``good`` where it is within ``within_px`` and no other
    good blob took the same bead."""
    dist = np.linalg.norm(xy[:, None, :] - pred[None], axis=2)
    j = np.argmin(dist, axis=1)
    good = dist[np.arange(len(xy)), j] < within_px
    good &= np.array([np.sum(j[good] == jj) == 1 for jj in j], dtype=bool)
    return j, good


def _relabel_rows(rows, blobs, names, beads, plane_of, problems) -> None:
    """Check the identified rows of the near and far planes against each other and relabel
    the rows that disagree with the plane's consensus (in place).

    :func:`identify_row` matches one row's blobs to the rod's bead spacing alone; with beads
    missing and a stray blob a shifted labelling can fit as well as the right one, and a
    wrong label moves a marker by a whole bead gap, which the thin-plate spline then bends
    the calibration to. Consensus over pairs of rows: each pair fixes a smooth map from the
    plane to the image (:func:`_plane_design`, linear across rows) and the rows whose every
    marker lies within ``RELABEL_GAPS`` bead gaps of it agree; the pair with most agreeing
    rows wins (a wrong row cannot bend it, as a least-squares fit over all rows would be
    bent). A row outside the consensus takes the labels of the consensus map's predictions
    (each blob the bead predicted nearest to it, within ``RELABEL_GAPS`` gaps and unique),
    or is dropped when no blob matches; both are named in ``problems``.
    """
    for p in (NEAR, FAR):
        _relabel_plane(rows, blobs, names, beads, plane_of, problems, p)


def _relabel_plane(rows, blobs, names, beads, plane_of, problems, p: int) -> None:
    """:func:`_relabel_rows` on plane ``p``."""
    idx = [i for i, f in enumerate(rows["frame"]) if len(f) and plane_of[f[0]] == p]
    if len(idx) < 3:
        return
    fr = [int(rows["frame"][i][0]) for i in idx]
    rod = np.mean([beads[f][-1] - beads[f][0] for f in fr], axis=0)
    design = _plane_design(np.concatenate([rows["robot"][i] for i in idx]), rod)
    if design is None:
        return
    D = design(np.stack([beads[f] for f in fr]))                    # (R, n, T)
    # every marker of the plane: its row (0..R-1), bead and pixel
    row_of = np.concatenate([np.full(len(rows["bead"][i]), r) for r, i in enumerate(idx)])
    bead_of = np.concatenate([rows["bead"][i] for i in idx])
    xy = np.concatenate([rows["xy"][i] for i in idx])
    A_all = D[row_of, bead_of]                                      # (M, T)
    R = len(idx)
    # each row's markers are one run of row_of (rows not empty): where each run starts
    starts = np.concatenate([[0], np.cumsum([len(rows["bead"][i]) for i in idx])[:-1]])

    def fit(use):
        # a pair of rows (the consensus loop, 0.04 ms a pair less than np.isin)
        sel = (row_of == use[0]) | (row_of == use[1]) if len(use) == 2 \
            else np.isin(row_of, use)
        if sel.sum() < len(_PLANE_TERMS) + 2:
            return None
        return np.linalg.lstsq(A_all[sel], xy[sel], rcond=None)[0]

    def scores(coef):
        pred = D @ coef                                             # (R, n, 2)
        gap = np.maximum(np.linalg.norm(np.diff(pred, axis=1), axis=2).min(axis=1), 1e-9)
        off = np.linalg.norm(xy - pred[row_of, bead_of], axis=1) / gap[row_of]
        # the worst marker of each row: np.maximum.at(zeros(R), row_of, off), over the runs
        worst = np.maximum(np.maximum.reduceat(off, starts), 0.0)
        return worst, pred, gap

    best = None
    for pair in itertools.combinations(range(R), 2):
        coef = fit(list(pair))
        if coef is None:
            continue
        worst = scores(coef)[0]
        agree = worst <= RELABEL_GAPS
        key = (int(agree.sum()), -float(worst[agree].sum()))
        if best is None or key > best[0]:
            best = (key, np.flatnonzero(agree))
    if best is None or len(best[1]) == R or len(best[1]) < 2:
        return          # all agree, or no consensus to judge by (validation decides)
    coef = fit(list(best[1]))
    if coef is None:
        return
    worst, pred_all, gap_all = scores(coef)
    for r in sorted(set(range(R)) - set(best[1].tolist())):
        i, f = idx[r], fr[r]
        pred, gap = pred_all[r], gap_all[r]
        xy_f = blobs[f]
        j, good = _match_predictions(xy_f, pred, RELABEL_GAPS * gap)
        before = rows["bead"][i].tolist()
        problems[:] = [m for m in problems if not m.startswith(names[f] + ":")]
        rows["bead"][i] = j[good]
        rows["xy"][i] = xy_f[good]
        rows["robot"][i] = beads[f][j[good]]
        rows["frame"][i] = np.full(int(good.sum()), f)
        rows["plane"][i] = np.full(int(good.sum()), p)
        problems.append(
            f"{names[f]}: labels {before} disagreed with the plane's other rows (a marker "
            f"{worst[r]:.1f} bead gaps from its prediction); "
            + (f"relabelled {j[good].tolist()} from them" if good.any()
               else "no blob matches them; row dropped")
            + (f"; {int((~good).sum())} blob(s) unmatched" if (~good).any() else ""))


def check_planes(view: str, plane, n_frames: int) -> np.ndarray:
    """``plane`` as (F,) integers, each a code of :data:`PLANE_NAMES`; else a ValueError
    naming the view."""
    plane = np.asarray(plane)
    if plane.shape != (n_frames,) or not np.issubdtype(plane.dtype, np.integer):
        raise ValueError(f"view {view}: sweep 'plane' must be ({n_frames},) integers (one per "
                         f"frame), got {plane.dtype} {plane.shape}")
    bad = sorted(set(plane.tolist()) - set(PLANE_NAMES))
    if bad:
        raise ValueError(f"view {view}: sweep 'plane' holds {bad}; expected codes "
                         f"{sorted(PLANE_NAMES)} ({', '.join(PLANE_NAMES.values())})")
    return plane


def find_markers(sweep: SweepData, *, polarity: str = "dark", min_matched: int = 4,
                 **detect_kw) -> Markers:
    """Detect and identify every marker of a sweep (see :func:`detect_markers`,
    :func:`identify_row`). A frame is compared with the frame before it. A row with too few
    blobs to identify alone (at the edge of the field) is matched to where its beads are
    predicted from the other rows of its plane; a row that still cannot be identified is
    dropped and named in ``problems``, as are missing beads (outside the field, hidden) and
    stray blobs.
    """
    frames = np.asarray(sweep.frames)
    plane = np.asarray(sweep.plane)
    beads = np.asarray(sweep.beads_robot, dtype=np.float64)
    s = np.asarray(sweep.bead_positions_mm, dtype=np.float64)
    F = len(frames)
    if frames.ndim != 3 or plane.shape != (F,) or beads.shape[:2] != (F, len(s)):
        raise ValueError(
            f"view {sweep.view}: frames {frames.shape}, plane {plane.shape} and beads_robot "
            f"{beads.shape} disagree (expected (F, H, W), (F,), (F, {len(s)}, 3))")
    plane = check_planes(sweep.view, plane, F)
    if np.isinf(beads).any():   # NaN marks a reading the robot did not make; inf is no reading
        f, b = np.argwhere(np.isinf(beads).any(axis=-1))[0]
        raise ValueError(f"view {sweep.view}: beads_reported holds infinite values (first at "
                         f"frame {f}, bead {b}); expected robot positions in mm, NaN where "
                         "the robot reported none")
    nan = np.isnan(beads)
    part = nan.any(axis=-1) & ~nan.all(axis=-1)
    if part.any():   # a review's NaN in one coordinate was read as a reading not made
        f, b = np.argwhere(part)[0]
        raise ValueError(f"view {sweep.view}: beads_reported at frame {f}, bead {b} is "
                         f"{beads[f, b].tolist()}: NaN in some coordinates only; NaN marks a "
                         "reading the robot did not make, in all three coordinates")
    rows = {k: [] for k in ("frame", "plane", "bead", "xy", "robot")}
    problems: list[str] = []
    weak = []  # rows too short to identify on their own: (frame, name, blobs, message)
    blobs: dict[int, np.ndarray] = {}   # every blob of an identified row, by frame
    names: dict[int, str] = {}
    expected = 0

    def add(f, bead, xy):
        rows["frame"].append(np.full(len(bead), f))
        rows["plane"].append(np.full(len(bead), int(plane[f])))
        rows["bead"].append(bead)
        rows["xy"].append(xy)
        rows["robot"].append(beads[f][bead])

    for f in range(1, F):
        if plane[f] == REFERENCE:
            continue
        expected += len(s)
        name = f"view {sweep.view}, {PLANE_NAMES.get(int(plane[f]), plane[f])} plane, frame {f}"
        if not np.all(np.isfinite(beads[f])):
            problems.append(f"{name}: robot positions missing; row dropped")
            continue
        xy, _ = detect_markers(frames[f - 1], frames[f], polarity=polarity, mask=sweep.mask,
                               **detect_kw)
        try:
            if not len(xy):
                raise ValueError(
                    "no bead-sized blob in the difference from the previous frame: are "
                    "the beads smaller than min_area_px = "
                    f"{detect_kw.get('min_area_px', MIN_AREA_PX)} px in the image, fainter "
                    "than the noise, or outside the field?")
            bead, _rms = identify_row(xy, s, min_matched=min_matched)
        except ValueError as exc:
            problems.append(f"{name}: row dropped ({exc}; {len(xy)} blobs found)")
            if len(xy):   # the message itself: the relabelling below rebuilds the list
                weak.append((f, name, xy, problems[-1]))
            continue
        ok = bead >= 0
        blobs[f], names[f] = xy, name
        missing = sorted(set(range(len(s))) - set(bead[ok].tolist()))
        if missing:
            problems.append(f"{name}: beads {missing} not found (outside the field, hidden, "
                            "or too faint)")
        if (~ok).any():
            problems.append(f"{name}: {int((~ok).sum())} stray blob(s) at "
                            f"{np.round(xy[~ok], 1).tolist()} px ignored")
        add(f, bead[ok], xy[ok])

    _relabel_rows(rows, blobs, names, beads, plane, problems)

    # rows with too few blobs (at the edge of the field): predict where their beads appear
    # from the identified rows of the same plane (a TPS from in-plane mm to pixels) and take
    # the blobs that fall on a prediction
    for f, name, xy, message in weak:
        p = int(plane[f])
        have = [i for i, fr in enumerate(rows["frame"]) if len(fr) and plane[fr[0]] == p]
        if len(have) < 2:
            continue
        P = np.concatenate([rows["robot"][i] for i in have])
        X = np.concatenate([rows["xy"][i] for i in have])
        c = P.mean(axis=0)
        basis = np.linalg.svd(P - c)[2][:2].T
        try:
            to_px = ThinPlateSpline.fit((P - c) @ basis, X, smoothing=0.0)
        except ValueError:
            continue
        pred = to_px((beads[f] - c) @ basis)
        gap = np.min(np.linalg.norm(np.diff(pred, axis=0), axis=1))
        j, good = _match_predictions(xy, pred, 0.2 * gap)
        if good.any():
            add(f, j[good], xy[good])
            missing = sorted(set(range(len(s))) - set(j[good].tolist()))
            found = (f"{name}: {int(good.sum())} blob(s) identified from the plane's other "
                     f"rows; beads {missing} not found (outside the field, hidden, or too "
                     "faint)")
            if message in problems:
                problems[problems.index(message)] = found
            else:
                problems.append(found)

    def cat(key, shape):
        return np.concatenate(rows[key]) if rows[key] else np.zeros(shape)

    order = np.argsort(cat("frame", (0,)), kind="stable")
    return Markers(sweep.view, cat("frame", (0,)).astype(int)[order],
                   cat("plane", (0,)).astype(int)[order], cat("bead", (0,)).astype(int)[order],
                   cat("xy", (0, 2))[order], cat("robot", (0, 3))[order], problems, expected)


def identify_by_paths(sweep: SweepData, distances, frames, *, tolerance: float = 0.3,
                      min_matched: int = 4, on_row_px: float = 3.0, polarity: str = "dark",
                      **detect_kw):
    """The beads of some frames of a sweep identified by a calibration's X-ray paths, for a
    row that its blobs alone cannot identify (two assignments that fit about equally; the
    validation plane has a single row, so no other row of its plane can predict it).

    Each blob that appeared in a frame (:func:`detect_markers` against the frame before)
    is the bead whose robot-reported position lies nearest its X-ray path, when nearer than
    ``tolerance`` times the rod's smallest bead gap (mm); one blob per bead, the nearest.
    With the default 0.3 of the default rod's 12 mm, 3.6 mm. A row is used only with the
    evidence :func:`identify_row` asks for, ``min_matched`` beads, and when no other blob
    lies on it (within ``on_row_px`` of the line through its identified blobs): a blob on
    the row that matches no bead is a bead the calibration misplaces by more than the
    tolerance (e.g. at one end of the field), and leaving it out would validate the
    calibration on the beads it already agrees with. A calibration off by less than the
    tolerance is measured (and failed above its validation limit); one off by more than
    the tolerance everywhere finds no bead, unless its error lies within that of a bead
    gap along the rod (then the blobs take the neighbouring beads, and their distances
    show the remainder).

    Parameters
    ----------
    sweep : SweepData.
    distances : callable ``(xy_px (K, 2), points_robot (K, 3)) -> (K,) mm``, the distance
        from each point to the X-ray path of its pixel (``Calibration.distances``).
    frames : indices of the frames to identify (each compared with the frame before).

    Returns
    -------
    frame (M,), bead (M,), xy_px (M, 2), robot (M, 3) mm, and a note per frame it looked
    at (none for frame 0).
    """
    frames_img = np.asarray(sweep.frames)
    beads = np.asarray(sweep.beads_robot, dtype=np.float64)
    s = np.sort(np.asarray(sweep.bead_positions_mm, dtype=np.float64))
    limit = tolerance * float(np.min(np.diff(s))) if len(s) > 1 else np.inf
    out_f, out_b, out_xy, notes = [], [], [], []
    for f in frames:
        f = int(f)
        if f < 1:
            continue
        plane_name = PLANE_NAMES.get(int(sweep.plane[f]), sweep.plane[f])
        name = f"view {sweep.view}, {plane_name} plane, frame {f}"
        have = np.flatnonzero(np.all(np.isfinite(beads[f]), axis=1))
        if not len(have):
            notes.append(f"{name}: robot positions missing; row not identified by the "
                         "calibration's paths")
            continue
        xy, _ = detect_markers(frames_img[f - 1], frames_img[f], polarity=polarity,
                               mask=sweep.mask, **detect_kw)
        K, n = len(xy), len(have)
        if K == 0:
            notes.append(f"{name}: no blobs to identify by the calibration's paths")
            continue
        d = distances(np.repeat(xy, n, axis=0), np.tile(beads[f][have], (K, 1))).reshape(K, n)
        d = np.where(np.isfinite(d), d, np.inf)
        best = np.argmin(d, axis=1)
        near = d[np.arange(K), best] < limit
        kept = []
        for b in np.unique(best[near]):
            k = np.flatnonzero(near & (best == b))
            kept.append(int(k[np.argmin(d[k, b])]))
        kept = np.array(sorted(kept, key=lambda k: best[k]), dtype=np.int64)
        head = (f"{name}: {len(kept)} of {K} blob(s) identify beads by the calibration's X-ray "
                f"paths (within {limit:.1f} mm)")
        if len(kept) < min_matched:
            notes.append(f"{head}, {min_matched} needed; row dropped")
            continue
        # the line through the identified blobs: a blob on it that matches no bead
        c = xy[kept].mean(axis=0)
        u = np.linalg.svd(xy[kept] - c)[2][0]
        rest = np.setdiff1d(np.arange(K), kept)
        across = np.abs((xy[rest] - c) @ np.array([-u[1], u[0]]))
        if np.any(across <= on_row_px):
            notes.append(f"{head}; {int(np.sum(across <= on_row_px))} other blob(s) on the row "
                         "match no bead (the calibration may misplace them); row dropped")
            continue
        out_f.append(np.full(len(kept), f))
        out_b.append(have[best[kept]])
        out_xy.append(xy[kept])
        notes.append(head)
    if not out_f:
        return (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, 2)),
                np.zeros((0, 3)), notes)
    f_all = np.concatenate(out_f).astype(np.int64)
    b_all = np.concatenate(out_b).astype(np.int64)
    return f_all, b_all, np.concatenate(out_xy), beads[f_all, b_all], notes
