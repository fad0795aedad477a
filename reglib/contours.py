"""2-D contours from a few user clicks: a two-stage snake, and its use on CT slices.

The deformable model of Kass, Witkin and Terzopoulos as the paper uses it (NOTES.md s2):
stretching and bending energies plus a potential, the smoothed norm of the image gradient.
The clicks are joined into a polygon and resampled; a first snake runs on a heavily smoothed,
down-sampled potential (long range), a second one on the full-resolution potential; each
vertex is finally moved along the contour normal to the sub-pixel maximum of the gradient
norm (parabola through the three samples around the maximum).

The solver is the iteration of :func:`skimage.segmentation.active_contour` (:func:`_snake_steps`,
with a compiled gradient of the potential's spline; skimage's function is its reference),
given our potential as its "line" image (``w_line=1, w_edge=0``), so the snake climbs the
gradient-norm ridge. skimage works in
(row, col); everything here takes and returns pixel coordinates ``(x, y) = (col, row)`` with
the centre of the top-left pixel at (0, 0).

Clicks are input: in the testbed they are simulated by the studies from the truth plus
seeded noise, never made here.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from types import MappingProxyType

import numpy as np
from scipy import ndimage

from reglib.geometry import arc_length, polygon_distances

__all__ = [
    "SliceContours",
    "contours_from_ct",
    "gradient_potential",
    "refine_subpixel",
    "cubic_coefficients",
    "resample_polygon",
    "snake_contour",
    "snake_scale",
    "snake_upsampling",
    "positive_number",
    "resampling",
    "untangle_contour",
    "REFERENCE_CT_PIXEL_MM",
]


# --------------------------------------------------------------------------- helpers
def _check_image(image) -> np.ndarray:
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be a 2-D array (H, W), got shape {img.shape}")
    if min(img.shape) < 8:
        raise ValueError(f"image is too small for a snake: shape {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError("image contains NaN or infinite values")
    return img


def _check_clicks(clicks_xy, shape, *, closed: bool) -> np.ndarray:
    pts = np.asarray(clicks_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"clicks_xy must have shape (K, 2) as (x, y) px, got {pts.shape}")
    need = 3 if closed else 2
    if len(pts) < need:
        kind = "closed" if closed else "open"
        raise ValueError(f"a {kind} contour needs at least {need} clicks, got {len(pts)}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("clicks_xy contains NaN or infinite values")
    h, w = shape
    out = (pts[:, 0] < -0.5) | (pts[:, 0] > w - 0.5) | (pts[:, 1] < -0.5) | (pts[:, 1] > h - 0.5)
    if np.any(out):
        k = int(np.flatnonzero(out)[0])
        raise ValueError(
            f"click {k} at (x, y) = ({pts[k, 0]:.1f}, {pts[k, 1]:.1f}) px lies outside the "
            f"image of {w} x {h} px (x in [-0.5, {w - 0.5}], y in [-0.5, {h - 0.5}])"
        )
    return pts


def resample_polygon(points_xy, spacing: float, *, closed: bool = True,
                     min_points: int = 8, max_points: int = 600) -> np.ndarray:
    """Points evenly spaced by arc length along a polygon.

    Parameters
    ----------
    points_xy : (K, 2) array, polygon vertices (any unit; px here).
    spacing : target distance between consecutive output points, same unit.
    closed : the polygon closes back on its first vertex (the output does not repeat it).

    Returns
    -------
    (M, 2) array, ``min_points <= M <= max_points``.
    """
    spacing = positive_number(spacing, "resample_polygon: spacing", unit="px")
    p, s = arc_length(points_xy, closed=closed)
    total = s[-1]
    if not np.isfinite(total):    # a review: "cannot convert float NaN to integer"
        raise ValueError("resample_polygon: points_xy: the polygon holds NaN or infinite "
                         "coordinates")
    if total <= 0:
        raise ValueError("polygon has zero length (all points coincide)")
    m = int(np.clip(round(total / spacing), min_points, max_points))
    t = np.arange(m) * (total / m) if closed else np.linspace(0.0, total, m)
    x = np.interp(t, s, p[:, 0])
    y = np.interp(t, s, p[:, 1])
    return np.column_stack([x, y])


def gradient_potential(image, sigma_px: float, *, clip_percentile: float = 98.0) -> np.ndarray:
    """The snake's potential: Gaussian-smoothed gradient norm, scaled to about [0, 1].

    Parameters
    ----------
    image : (H, W) array (any intensity unit, e.g. HU).
    sigma_px : standard deviation of the Gaussian derivative filter, px.
    clip_percentile : the gradient norm is divided by this percentile and clipped at 1, so
        that one very strong edge (a metal pin) does not flatten all the others.

    Returns
    -------
    (H, W) float64 array.
    """
    img = np.asarray(image, np.float64)
    if img.ndim != 2 or img.size == 0:
        raise ValueError(f"image must be a non-empty 2-D array (H, W), got shape {img.shape}")
    if not 0 < clip_percentile <= 100:
        raise ValueError(f"clip_percentile must lie in (0, 100], got {clip_percentile!r}")
    if not np.all(np.isfinite(img)):      # a review: an all-NaN potential, unsaid
        raise ValueError("gradient_potential: image holds NaN or infinite values")
    g = ndimage.gaussian_gradient_magnitude(img, positive_number(sigma_px, "sigma_px", unit="px"))
    q = _percentile_linear(g, clip_percentile)
    if q <= 0:
        q = float(g.max()) or 1.0
    return np.minimum(g / q, 1.0)


def _percentile_linear(a, q: float, *, reference: bool = False) -> float:
    """``float(np.percentile(a, q))`` (the default "linear" method, q in [0, 100]) of a
    finite array, the same number: the two order statistics about the virtual index
    ``(n - 1) q / 100`` by one partition and numpy's own interpolation (its ``_lerp``),
    without numpy's general machinery (50 us a call against 100 us on 100 x 100 px; a
    run of experiment2 makes 220 snake potentials). ``reference=True`` calls numpy."""
    if reference:
        return float(np.percentile(a, q))
    flat = np.asarray(a, dtype=np.float64).ravel()
    n = flat.size
    v = (n - 1) * (q / 100)
    lo = hi = -1                         # numpy's indices at the top: the largest value
    if v < n - 1:
        lo = int(np.floor(v))
        hi = lo + 1
    # numpy's own selection (its kth: the ends too), so that even the sign of a zero
    # picked among equal values is numpy's
    part = np.partition(flat, sorted({0, -1, lo, hi}))
    below, above = float(part[lo]), float(part[hi])
    t = v - lo
    diff = above - below
    return above - diff * (1 - t) if t >= 0.5 else below + diff * t


def _normals(c: np.ndarray, closed: bool) -> np.ndarray:
    """Unit normals (x, y) of a polyline from central differences."""
    if closed:
        d = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
    else:
        d = np.gradient(c, axis=0)
    n = np.column_stack([d[:, 1], -d[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


def _outward(c: np.ndarray, n: np.ndarray, closed: bool) -> np.ndarray:
    """Flip normals of a closed contour so that they point away from its inside."""
    if not closed:
        return n
    x, y = c[:, 0], c[:, 1]
    area2 = np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    # _normals gives (dy, -dx): outward for a contour with positive signed area in (x, y).
    return n if area2 > 0 else -n


SNAKE_INVERSES_KEPT = 32
"""How many of :func:`_snake_inverse`'s matrices are kept (at most 600 x 600 each)."""

SPLINE_PAD_PX = 12
"""Edge padding before the cubic B-spline prefilter: what ``ndimage.map_coordinates`` pads
for ``mode="nearest"``, so that :func:`cubic_coefficients` and :func:`_sample_cubic` give
its values."""


def cubic_coefficients(image) -> np.ndarray:
    """Cubic B-spline coefficients of ``image`` (H, W) for :func:`refine_subpixel`'s
    ``spline``: the prefilter ``ndimage.map_coordinates(..., order=3, mode="nearest")``
    runs on every call, done once for several calls on one image."""
    padded = np.pad(np.asarray(image, dtype=np.float64), SPLINE_PAD_PX, mode="edge")
    return ndimage.spline_filter(padded, 3, output=np.float64, mode="nearest")


def _sample_cubic(coefficients: np.ndarray, rows, cols) -> np.ndarray:
    """``ndimage.map_coordinates(image, [rows, cols], order=3, mode="nearest")`` from
    :func:`cubic_coefficients` of ``image`` (compared in tests)."""
    return ndimage.map_coordinates(coefficients, [rows + SPLINE_PAD_PX, cols + SPLINE_PAD_PX],
                                   order=3, mode="nearest", prefilter=False)


def _nanmedian_rows(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=1)`` (the same numbers; NaN for a row without a finite
    value, without the warning) by one sort of the rows: NaN sorts last."""
    s = np.sort(a, axis=1)
    n = np.count_nonzero(~np.isnan(a), axis=1)
    rows = np.arange(len(a))
    hi = s[rows, np.minimum(n // 2, a.shape[1] - 1)]
    lo = s[rows, np.maximum((n - 1) // 2, 0)]
    return np.where(n == 0, np.nan, np.where(n % 2 == 1, hi, (lo + hi) / 2.0))


def refine_subpixel(image, contour_xy, *, search_px: float = 2.5, step_px: float = 0.25,
                    closed: bool = True, polarity: str | None = None,
                    max_jump_px: float = 1.0, normal_sigma: float = 0.0,
                    neighbour_edges: bool = False, spline=None) -> np.ndarray:
    """Move each vertex along its normal to the sub-pixel position of the edge.

    ``image`` is sampled (bicubic) at ``step_px`` intervals within ``+-search_px`` along the
    normal. Without ``polarity`` it is taken as a gradient norm and its maximum is sought;
    with ``polarity="bright_inside"`` (or ``"dark_inside"``) it is taken as a smoothed
    intensity image and the edge is the maximum of its decrease (increase) outward, so that
    an inner edge of the opposite sense (the inner side of a cortical shell) is ignored.
    A parabola through the best sample and its two neighbours gives the offset.

    A vertex whose best sample lies at the end of the search range, or whose edge point
    disagrees by more than ``max_jump_px`` with its neighbours', takes the median offset of
    its 7 neighbours. Agreement is judged on the offsets (against that median: a jump to
    another edge while the contour is still off) and, with ``neighbour_edges``, also on
    the positions: the vertex is kept when its edge point lies within ``max_jump_px`` of
    the edge points of the next vertex on either side, measured along its normal. Without
    that second test a vertex the snake left off the edge (a tooth of 1-3 px whose
    neighbours are already on the edge) is held where it is, its offset differing from
    theirs: on CT slices of the distal femur single vertices stayed 1-2.5 mm inside the
    bone, dents of the tiled surface that made dozens of spurious apparent contours and
    pulled the registration 6 mm off (``tests/reglib/test_distal_mechanism.py``).
    ``normal_sigma`` > 0 takes the normals of the contour smoothed over that many vertices,
    so that a tooth does not turn its own normal along the edge.

    Parameters
    ----------
    image : (H, W) array (gradient norm, or smoothed intensity with ``polarity``).
    contour_xy : (K, 2) array, (x, y) px.
    normal_sigma : Gaussian smoothing (in vertices) of the contour whose normals are used
        (0: the contour's own central differences).
    neighbour_edges : also accept an edge point that lies on the neighbours' edge curve
        (see above; :func:`contours_from_ct` turns it on).
    spline : :func:`cubic_coefficients` of ``image`` (computed when None), for several calls
        on one image.

    Returns
    -------
    (K, 2) array, (x, y) px.
    """
    c = np.asarray(contour_xy, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 2 or not np.all(np.isfinite(c)):
        # a review: NaN vertices came back NaN without a word
        raise ValueError(f"refine_subpixel: contour_xy: expected (K, 2) finite px, got "
                         f"shape {c.shape}" + (" with NaN or inf" if c.size else ""))
    if normal_sigma < 0:
        raise ValueError(f"normal_sigma: expected >= 0 vertices, got {normal_sigma}")
    shape = (c if normal_sigma == 0 else
             ndimage.gaussian_filter1d(c, normal_sigma, axis=0,
                                       mode="wrap" if closed else "nearest"))
    n = _outward(c, _normals(shape, closed), closed)
    t = np.arange(-search_px, search_px + step_px / 2, step_px)
    px = c[:, None, 0] + t[None, :] * n[:, None, 0]
    py = c[:, None, 1] + t[None, :] * n[:, None, 1]
    if spline is None:
        spline = cubic_coefficients(image)
    vals = _sample_cubic(spline, py.ravel(), px.ravel()).reshape(px.shape)
    if polarity is not None:
        if polarity not in ("bright_inside", "dark_inside"):
            raise ValueError(f"polarity must be None, 'bright_inside' or 'dark_inside', "
                             f"got {polarity!r}")
        d = np.gradient(vals, step_px, axis=1)
        vals = -d if polarity == "bright_inside" else d
    k = np.argmax(vals, axis=1)
    ok = (k > 0) & (k < len(t) - 1)
    kk = np.clip(k, 1, len(t) - 2)
    rows = np.arange(len(c))
    f0, f1, f2 = vals[rows, kk - 1], vals[rows, kk], vals[rows, kk + 1]
    den = f0 - 2 * f1 + f2
    frac = np.where(den < 0, 0.5 * (f0 - f2) / np.where(den < 0, den, -1.0), 0.0)
    off = np.where(ok, t[kk] + np.clip(frac, -0.5, 0.5) * step_px, np.nan)
    # Robustness: an offset far from the median of its neighbours (a jump to another edge,
    # noise) is replaced by that median, so the contour keeps no spikes or loops.
    w = 3
    idx = np.arange(-w, w + 1)[None, :] + np.arange(len(c))[:, None]
    idx = idx % len(c) if closed else np.clip(idx, 0, len(c) - 1)
    med = _nanmedian_rows(off[idx])
    med = np.where(np.isfinite(med), med, 0.0)
    # the edge points of the next vertex on either side, along this vertex's normal
    edge = c + off[:, None] * n                      # NaN where no edge was found
    side = np.arange(len(c))[:, None] + np.array([-1, 1])[None, :]
    side = side % len(c) if closed else np.clip(side, 0, len(c) - 1)
    along = np.einsum("ijk,ik->ij", edge[side] - c[:, None, :], n)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # both neighbours without an edge
        beside = np.nanmean(along, axis=1)
    on_their_curve = (np.abs(off - beside) <= max_jump_px) & neighbour_edges  # NaN: False
    bad = ~np.isfinite(off) | ((np.abs(off - med) > max_jump_px) & ~on_their_curve)
    off = np.where(bad, med, off)
    return c + off[:, None] * n


def _run_snake(potential, init_xy, *, alpha, beta, gamma, max_iter, closed, boundary,
               reference: bool = False):
    """The snake on ``potential`` from ``init_xy`` (n, 2) px; ``reference=True`` runs
    scikit-image's ``active_contour``, the default :func:`_snake_steps`, the same
    iteration with a compiled evaluation of the image's spline (equal to rounding)."""
    bc = "periodic" if closed else boundary
    if not reference and np.asarray(potential).dtype == np.float64:
        return _snake_steps(potential, init_xy, alpha=alpha, beta=beta, gamma=gamma,
                            max_iter=max_iter, boundary=bc)
    from skimage.segmentation import active_contour

    rc = np.ascontiguousarray(init_xy[:, ::-1])
    out = active_contour(
        potential, rc, alpha=alpha, beta=beta, gamma=gamma, w_line=1.0, w_edge=0.0,
        max_px_move=1.0, max_num_iter=max_iter, convergence=0.05, boundary_condition=bc,
    )
    return np.asarray(out, dtype=np.float64)[:, ::-1]


def _snake_steps(img, init_xy, *, alpha, beta, gamma, max_iter, boundary,
                 max_px_move=1.0, convergence=0.05, convergence_order=10):
    """scikit-image's ``active_contour`` (0.2x) with ``w_line=1, w_edge=0`` on a float64
    ``img``, step for step: the semi-implicit Euler iteration of Kass et al. with the
    image's quadratic interpolating spline (the same FITPACK fit), its gradient evaluated
    by :func:`reglib._snake_numba.spline_gradient` instead of two FITPACK calls per step
    (about 18 us each: 0.45 s of a capture-range trial), the steps compiled
    (:func:`reglib._snake_numba.snake_loop`; numpy's per-step overhead was 30 us).
    Returns (n, 2) px ``(x, y)``."""
    from scipy.interpolate import RectBivariateSpline

    from reglib._snake_numba import snake_loop

    intp = RectBivariateSpline(np.arange(img.shape[1]), np.arange(img.shape[0]), img.T,
                               kx=2, ky=2, s=0)
    tx, ty, c = (np.ascontiguousarray(v, dtype=np.float64) for v in intp.tck)
    x = np.array(init_xy[:, 0], dtype=np.float64)
    y = np.array(init_xy[:, 1], dtype=np.float64)
    inv, (sfixed, efixed, sfree, efree) = _snake_inverse(len(x), alpha, beta, gamma, boundary)
    snake_loop(inv, x, y, tx, ty, c, float(gamma), float(max_px_move), float(convergence),
               int(convergence_order), int(max_iter), sfixed, efixed, sfree, efree)
    return np.column_stack([x, y])


@functools.lru_cache(maxsize=SNAKE_INVERSES_KEPT)
def _snake_inverse(n: int, alpha, beta, gamma, boundary: str):
    """The inverse of the snake's implicit step, ``(A + gamma I)^-1`` (n, n), and its
    boundary flags ``(sfixed, efixed, sfree, efree)``, as scikit-image's ``active_contour``
    builds them; kept for the last :data:`SNAKE_INVERSES_KEPT` sizes and weights (a CT's
    snakes repeat their sizes: 220 snakes of experiment2 have 96 of them, and the matrix
    and its inverse were 0.14 s of a run). The array is shared: read it only
    (:func:`reglib._snake_numba.snake_loop` does)."""
    eye = np.eye(n)
    a = np.roll(eye, -1, axis=0) + np.roll(eye, -1, axis=1) - 2 * eye
    b = (np.roll(eye, -2, axis=0) + np.roll(eye, -2, axis=1) - 4 * np.roll(eye, -1, axis=0)
         - 4 * np.roll(eye, -1, axis=1) + 6 * eye)
    A = -alpha * a + beta * b
    sfixed = efixed = sfree = efree = False
    if boundary.startswith("fixed"):
        A[0, :] = 0
        A[1, :] = 0
        A[1, :3] = [1, -2, 1]
        sfixed = True
    if boundary.endswith("fixed"):
        A[-1, :] = 0
        A[-2, :] = 0
        A[-2, -3:] = [1, -2, 1]
        efixed = True
    if boundary.startswith("free"):
        A[0, :] = 0
        A[0, :3] = [1, -2, 1]
        A[1, :] = 0
        A[1, :4] = [-1, 3, -3, 1]
        sfree = True
    if boundary.endswith("free"):
        A[-1, :] = 0
        A[-1, -3:] = [1, -2, 1]
        A[-2, :] = 0
        A[-2, -4:] = [-1, 3, -3, 1]
        efree = True
    inv = np.linalg.inv(A + gamma * eye)
    return inv, (sfixed, efixed, sfree, efree)


# --------------------------------------------------------------------------- the snake
def snake_contour(
    image,
    clicks_xy,
    *,
    alpha: float = 0.01,
    beta: float = 0.1,
    gamma: float = 0.05,
    coarse_factor: int = 2,
    coarse_sigma_px: float = 3.0,
    fine_sigma_px: float = 1.0,
    spacing_px: float = 2.0,
    coarse_iterations: int = 200,
    fine_iterations: int = 80,
    subpixel: bool = True,
    polarity: str | None = None,
    search_px: float = 2.5,
    margin_px: float = 20.0,
    closed: bool = True,
    boundary_condition: str = "free",
    normal_sigma: float = 0.0,
    neighbour_edges: bool = False,
    scale: int = 1,
    upsample: int = 1,
) -> np.ndarray:
    """A contour from a few clicks: a snake on a coarse, then on a fine potential.

    Parameters
    ----------
    image : (H, W) array indexed [row, col] (any intensity unit: HU, grey levels).
    clicks_xy : (K, 2) array of (x, y) px near the structure, in order along it; K >= 3
        for a closed contour (K >= 2 for an open one). Joined into a polygon and resampled.
    alpha, beta : stretching and bending weights of the snake (skimage's meaning, for a
        potential scaled to [0, 1]).
    gamma : time step of the explicit image-force update.
    coarse_factor : down-sampling factor of the first stage (1: none).
    coarse_sigma_px, fine_sigma_px : Gaussian smoothing of the two potentials, in px of the
        full-resolution image.
    spacing_px : vertex spacing of the snake, px.
    coarse_iterations, fine_iterations : iteration caps of the two stages.
    subpixel : finish with :func:`refine_subpixel` (three passes of +-``search_px``).
    polarity : None (any edge: the gradient norm's ridge), ``"bright_inside"`` or
        ``"dark_inside"``: the sub-pixel step then seeks the edge of that sense only (bone
        is bright inside on CT).
    normal_sigma, neighbour_edges : of the sub-pixel step (:func:`refine_subpixel`);
        :func:`contours_from_ct` turns both on (1 vertex, True).
    margin_px : the work is done on a crop of the image around the clicks, this much larger.
    closed : a closed contour (periodic snake) or an open one (``boundary_condition`` of
        skimage, default "free").
    scale : a number >= 1: the image's pixels per pixel of the image the lengths above
        (given in px) were set for. With ``scale > 1`` both snakes run on the image's means
        over blocks of ``scale x scale`` pixels (whole ones for a whole number, else
        OpenCV's area resampling), with the options as given (so that they keep
        their meaning in mm and the snake its dynamics: its steps, tension and capture range
        are all in pixels); only the sub-pixel step uses the full resolution, with
        ``search_px``, ``spacing_px``, ``fine_sigma_px`` and its jump limit times ``scale``.
        :func:`contours_from_ct` sets it from the slices' pixel size.
    upsample : a number >= 1, for coarser images than the lengths were set for: the
        snake runs, with the options as given, on the image interpolated (cubic) to about
        ``upsample`` times as many pixels in each direction, and its contour is mapped back.
        At most one of ``scale`` and ``upsample`` may exceed 1.

    Returns
    -------
    (M, 2) float64 array of (x, y) px along the contour (closed: the first point is not
    repeated).

    Raises
    ------
    ValueError : the image is not 2-D and finite, fewer than 3 clicks (2 if open), a click
        outside the image.
    """
    img = _check_image(image)
    pts = _check_clicks(clicks_xy, img.shape, closed=closed)
    if coarse_factor < 1:
        raise ValueError(f"coarse_factor must be >= 1, got {coarse_factor}")
    for name, v in (("spacing_px", spacing_px), ("coarse_sigma_px", coarse_sigma_px),
                    ("fine_sigma_px", fine_sigma_px), ("search_px", search_px),
                    ("gamma", gamma)):
        positive_number(v, name, unit="px" if name.endswith("_px") else "")
    for name, v in (("margin_px", margin_px), ("alpha", alpha), ("beta", beta)):
        positive_number(v, name, unit="px" if name.endswith("_px") else "", zero=True)
    if np.ptp(img) == 0:
        raise ValueError("image: uniform (every pixel equal); there is no edge to follow")
    for name, v in (("scale", scale), ("upsample", upsample)):
        real = isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)
        if not (real and 1 <= v <= MAX_RESAMPLING):
            raise ValueError(f"{name} must be a number in [1, {MAX_RESAMPLING:g}], got {v!r}")
    if scale > 1 and upsample > 1:
        raise ValueError(f"scale ({scale}) and upsample ({upsample}): at most one may "
                         "exceed 1")
    options = dict(alpha=alpha, beta=beta, gamma=gamma, coarse_factor=coarse_factor,
                   coarse_sigma_px=coarse_sigma_px, fine_sigma_px=fine_sigma_px,
                   spacing_px=spacing_px, coarse_iterations=coarse_iterations,
                   fine_iterations=fine_iterations, polarity=polarity, search_px=search_px,
                   margin_px=margin_px, closed=closed, boundary_condition=boundary_condition,
                   normal_sigma=normal_sigma, neighbour_edges=neighbour_edges)
    if scale > 1:
        return _snake_scaled(img, pts, float(scale), subpixel=subpixel, **options)
    if upsample > 1:
        return _snake_upsampled(img, pts, float(upsample), subpixel=subpixel, **options)

    # Work on a crop around the clicks.
    h, w = img.shape
    pad = margin_px + 3 * coarse_sigma_px
    x0 = int(max(0, np.floor(pts[:, 0].min() - pad)))
    x1 = int(min(w, np.ceil(pts[:, 0].max() + pad) + 1))
    y0 = int(max(0, np.floor(pts[:, 1].min() - pad)))
    y1 = int(min(h, np.ceil(pts[:, 1].max() + pad) + 1))
    crop = img[y0:y1, x0:x1]
    off = np.array([x0, y0], dtype=np.float64)
    init = resample_polygon(pts - off, spacing_px, closed=closed)
    # Keep the snake inside the crop.
    lim = np.array([crop.shape[1] - 1, crop.shape[0] - 1], dtype=np.float64)

    # Stage 1: smoothed, down-sampled potential (long range).
    f = int(coarse_factor)
    if f > 1 and min(crop.shape) >= 8 * f:
        hh, ww = (crop.shape[0] // f) * f, (crop.shape[1] // f) * f
        small = crop[:hh, :ww].reshape(hh // f, f, ww // f, f).mean(axis=(1, 3))
        pot = gradient_potential(small, max(coarse_sigma_px / f, 0.5))
        shift = (f - 1) / 2.0  # centre of a small pixel in full-resolution px
        c0 = (resample_polygon(init, spacing_px * f, closed=closed) - shift) / f
        c0 = np.clip(c0, 0, np.array([small.shape[1] - 1, small.shape[0] - 1]))
        c = _run_snake(pot, c0, alpha=alpha, beta=beta, gamma=gamma, max_iter=coarse_iterations,
                       closed=closed, boundary=boundary_condition)
        c = c * f + shift
    else:
        pot = gradient_potential(crop, coarse_sigma_px)
        c = _run_snake(pot, init, alpha=alpha, beta=beta, gamma=gamma, max_iter=coarse_iterations,
                       closed=closed, boundary=boundary_condition)
    c = resample_polygon(np.clip(c, 0, lim), spacing_px, closed=closed)

    # Stage 2: full-resolution potential.
    if polarity is None:
        edge_img = ndimage.gaussian_gradient_magnitude(crop, fine_sigma_px)
    else:
        edge_img = ndimage.gaussian_filter(crop, fine_sigma_px)
    pot = gradient_potential(crop, fine_sigma_px)
    c = _run_snake(pot, c, alpha=alpha, beta=beta, gamma=gamma, max_iter=fine_iterations,
                   closed=closed, boundary=boundary_condition)
    c = np.clip(c, 0, lim)
    if subpixel:
        spline = cubic_coefficients(edge_img)
        for _ in range(2):
            c = refine_subpixel(edge_img, c, closed=closed, polarity=polarity,
                                search_px=search_px, normal_sigma=normal_sigma,
                                neighbour_edges=neighbour_edges, spline=spline)
            c = resample_polygon(np.clip(c, 0, lim), spacing_px, closed=closed,
                                 min_points=len(c) // 2)
        c = refine_subpixel(edge_img, c, closed=closed, polarity=polarity, search_px=search_px,
                            normal_sigma=normal_sigma, neighbour_edges=neighbour_edges,
                            spline=spline)
    return c + off


def _snake_scaled(img: np.ndarray, pts: np.ndarray, m: float, *, subpixel: bool,
                  **options) -> np.ndarray:
    """:func:`snake_contour` with ``scale = m > 1`` (``img`` and ``pts`` checked)."""
    h, w = img.shape
    pad = m * (options["margin_px"] + 3 * options["coarse_sigma_px"])
    x0 = int(max(0, np.floor(pts[:, 0].min() - pad)))
    y0 = int(max(0, np.floor(pts[:, 1].min() - pad)))
    x1 = int(min(w, np.ceil(pts[:, 0].max() + pad) + 1))
    y1 = int(min(h, np.ceil(pts[:, 1].max() + pad) + 1))
    whole = float(m).is_integer()
    if whole:   # whole blocks of m x m pixels (the crop grown, else shrunk, to a multiple)
        k = int(m)
        x1 = min(w, x0 + -(-(x1 - x0) // k) * k)
        y1 = min(h, y0 + -(-(y1 - y0) // k) * k)
        hh, ww = ((y1 - y0) // k) * k, ((x1 - x0) // k) * k
    else:
        hh, ww = y1 - y0, x1 - x0
    if min(hh, ww) < 8 * m:
        raise ValueError(f"image is too small for a snake at scale {m:g}: shape {img.shape}")
    crop = img[y0:y0 + hh, x0:x0 + ww]
    if whole:
        small = crop.reshape(hh // k, k, ww // k, k).mean(axis=(1, 3))
    else:
        import cv2

        size = (max(8, int(round(ww / m))), max(8, int(round(hh / m))))
        small = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
    f = np.array([ww / small.shape[1], hh / small.shape[0]])   # px per small pixel (x, y)
    off = np.array([x0, y0], dtype=np.float64)
    lim_small = np.array([small.shape[1] - 1, small.shape[0] - 1], dtype=np.float64)
    # pixel centres: small pixel j covers [j f - 0.5, (j + 1) f - 0.5] of the crop's
    clicks = np.clip((pts - off + 0.5) / f - 0.5, 0.0, lim_small)
    c = (snake_contour(small, clicks, subpixel=False, **options) + 0.5) * f - 0.5
    lim = np.array([ww - 1, hh - 1], dtype=np.float64)
    c = np.clip(c, 0, lim)
    if not subpixel:
        return c + off
    closed, polarity = options["closed"], options["polarity"]
    sigma = options["fine_sigma_px"] * m
    edge_img = (ndimage.gaussian_gradient_magnitude(crop, sigma) if polarity is None
                else ndimage.gaussian_filter(crop, sigma))
    spline = cubic_coefficients(edge_img)
    refine = dict(closed=closed, polarity=polarity, search_px=options["search_px"] * m,
                  step_px=0.25 * m, max_jump_px=1.0 * m, normal_sigma=options["normal_sigma"],
                  neighbour_edges=options["neighbour_edges"], spline=spline)
    spacing = options["spacing_px"] * m
    c = resample_polygon(c, spacing, closed=closed)
    for _ in range(2):
        c = refine_subpixel(edge_img, c, **refine)
        c = resample_polygon(np.clip(c, 0, lim), spacing, closed=closed,
                             min_points=len(c) // 2)
    return refine_subpixel(edge_img, c, **refine) + off


def _snake_upsampled(img: np.ndarray, pts: np.ndarray, u: float, *, subpixel: bool,
                     **options) -> np.ndarray:
    """:func:`snake_contour` with ``upsample = u > 1`` (``img`` and ``pts`` checked): on a
    crop around the clicks interpolated to about ``u`` times the pixels (the crop's pixel
    edges kept: for a whole ``u`` the centre of pixel ``i`` at ``u i + (u - 1) / 2``),
    mapped back."""
    h, w = img.shape
    pad = (options["margin_px"] + 3 * options["coarse_sigma_px"]) / u + 2
    x0 = int(max(0, np.floor(pts[:, 0].min() - pad)))
    y0 = int(max(0, np.floor(pts[:, 1].min() - pad)))
    x1 = int(min(w, np.ceil(pts[:, 0].max() + pad) + 1))
    y1 = int(min(h, np.ceil(pts[:, 1].max() + pad) + 1))
    crop = img[y0:y1, x0:x1]
    size = np.array([int(round(crop.shape[0] * u)), int(round(crop.shape[1] * u))])
    if size.prod() > MAX_RESAMPLED_PIXELS:
        raise ValueError(f"upsample {u:g}: the snake's window would hold {size.prod():,} "
                         f"pixels (at most {MAX_RESAMPLED_PIXELS:,})")
    big = ndimage.zoom(crop, size / np.array(crop.shape), order=3, mode="nearest",
                       grid_mode=True)
    f = np.array([big.shape[1] / crop.shape[1], big.shape[0] / crop.shape[0]])  # (x, y)
    off = np.array([x0, y0], dtype=np.float64)
    lim = np.array([big.shape[1] - 1, big.shape[0] - 1], dtype=np.float64)
    clicks = np.clip((pts - off + 0.5) * f - 0.5, 0.0, lim)
    c = snake_contour(big, clicks, subpixel=subpixel, **options)
    return (c + 0.5) / f - 0.5 + off


# --------------------------------------------------------------------------- CT slices
@dataclass(frozen=True)
class SliceContours:
    """The contours drawn on one CT slice.

    ``contours_px``: tuple of (K, 2) arrays of (x, y) px in the slice image;
    ``contours_ct``: the same points as (K, 3) arrays in ct mm; ``z_mm`` the slice position
    (mean z of its points in the ct frame); ``reseeded``: the contours were drawn again from
    a neighbour's because the clicked ones disagreed with both neighbours
    (:func:`contours_from_ct`'s ``consistency_mm``); ``disagreement_mm``: how far the kept
    contours stray from both neighbours' (:func:`slice_disagreement_mm`; NaN: not checked).
    """

    slice_index: int
    z_mm: float
    contours_px: tuple
    contours_ct: tuple
    reseeded: bool = False
    disagreement_mm: float = float("nan")


def _slice_affine(slice2ct: np.ndarray, k: int) -> tuple[np.ndarray, float]:
    """(4, 4) map of (col, row, 0, 1) for slice ``k`` (from a stack or one voxel affine)."""
    if slice2ct.ndim == 3:
        return slice2ct[k], 0.0
    return slice2ct, float(k)


def _to_ct(slice2ct: np.ndarray, k: int, xy: np.ndarray) -> np.ndarray:
    a, kk = _slice_affine(slice2ct, k)
    hom = np.column_stack([xy, np.full(len(xy), kk), np.ones(len(xy))])
    return (hom @ a.T)[:, :3]


def _first_crossing(p: np.ndarray):
    """The first pair (i, j), i < j (in that order), of non-adjacent edges of the closed
    polygon ``p`` (K, 2) that cross (edge i joins p[i] and p[i + 1]), with the crossing
    point; None if simple. The crossing test runs only on the pairs whose bounding boxes
    meet (a simple contour has few besides its neighbours);
    :func:`_first_crossing_loop`, one edge against all later ones at a time, is the
    reference."""
    n = len(p)
    if n < 4:
        return None
    b = np.roll(p, -1, axis=0)
    d = b - p
    lo, hi = np.minimum(p, b), np.maximum(p, b)
    near = ((lo[:, None, 0] <= hi[None, :, 0]) & (lo[None, :, 0] <= hi[:, None, 0])
            & (lo[:, None, 1] <= hi[None, :, 1]) & (lo[None, :, 1] <= hi[:, None, 1]))
    near = np.triu(near, 2)          # j >= i + 2: not the same or the next edge
    near[0, n - 1] = False           # edges n - 1 and 0 are neighbours too
    i, j = np.nonzero(near)          # in order of i, then j
    if not len(i):
        return None
    r, sj, q = d[i], d[j], p[j] - p[i]
    den = r[:, 0] * sj[:, 1] - r[:, 1] * sj[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (q[:, 0] * sj[:, 1] - q[:, 1] * sj[:, 0]) / den
        u = (q[:, 0] * r[:, 1] - q[:, 1] * r[:, 0]) / den
    hit = np.flatnonzero((den != 0) & (t > 0) & (t < 1) & (u > 0) & (u < 1))
    if not len(hit):
        return None
    k = hit[0]
    return int(i[k]), int(j[k]), p[i[k]] + t[k] * d[i[k]]


def _first_crossing_loop(p: np.ndarray):
    """Reference of :func:`_first_crossing`: one edge against the later ones at a time."""
    a = p
    d = np.roll(p, -1, axis=0) - p
    n = len(p)
    for i in range(n - 2):
        j = np.arange(i + 2, n if i else n - 1)
        if not len(j):
            continue
        r, sj, q = d[i], d[j], a[j] - a[i]
        den = r[0] * sj[:, 1] - r[1] * sj[:, 0]
        ok = den != 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (q[:, 0] * sj[:, 1] - q[:, 1] * sj[:, 0]) / den
            u = (q[:, 0] * r[1] - q[:, 1] * r[0]) / den
        hit = np.flatnonzero(ok & (t > 0) & (t < 1) & (u > 0) & (u < 1))
        if len(hit):
            jj = int(j[hit[0]])
            return i, jj, a[i] + t[hit[0]] * r
    return None


def untangle_contour(xy) -> np.ndarray:
    """A closed contour (K, 2) px without self-crossings: where two of its edges cross, it
    is cut there into two loops and the one enclosing the larger area is kept, until none
    cross (a snake whose vertices crossed over, as on the tip of a condyle that a CT slice
    grazes, leaves a twisted loop that tiles into a folded surface). Returns the contour
    itself when it is simple; the kept loop's vertices are a subset of the contour's plus
    the crossing points."""
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"untangle_contour: expected a (K, 2) contour (x, y) px, got shape "
                         f"{p.shape}")
    for _ in range(len(p)):
        hit = _first_crossing(p) if len(p) >= 4 else None
        if hit is None:
            return p
        i, j, x = hit
        inner = np.vstack([x, p[i + 1:j + 1]])           # x, p[i+1] .. p[j]
        outer = np.vstack([p[j + 1:], p[:i + 1], x])     # p[j+1] .. p[i], x
        p = max((inner, outer), key=lambda c: abs(_polygon_area(c)) if len(c) >= 3 else -1.0)
    return p


def _polygon_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


#: the largest ``scale`` or ``upsample`` of :func:`snake_contour`
MAX_RESAMPLING = 16.0
#: the most pixels of an upsampled snake window
MAX_RESAMPLED_PIXELS = 2**24
#: pixels within this ratio of :data:`REFERENCE_CT_PIXEL_MM` (either way) are taken as they
#: are: the snake's lengths keep their meaning within it
RESAMPLE_FROM = 1.2

#: the CT pixel size (mm) for which the snake's lengths in px (:func:`snake_contour`'s
#: defaults and :func:`contours_from_ct`'s) were set: the testbed's default CT, and within
#: the 0.6-0.9 mm of a clinical hip or knee field of view
REFERENCE_CT_PIXEL_MM = 0.8


def snake_upsampling(pixel_mm: float) -> float:
    """:func:`snake_contour`'s ``upsample`` for CT pixels of ``pixel_mm``: ``pixel_mm`` over
    :data:`REFERENCE_CT_PIXEL_MM` from :data:`RESAMPLE_FROM` up (at most
    :data:`MAX_RESAMPLING`), else 1, so that on coarser slices the snake's reach and
    smoothing keep their meaning in mm. With
    its lengths in px, 1.5 mm pixels gave it twice its reach: on ``experiment2`` (seed 2)
    contours near the distal pins leaked 20 mm out to the knee's skin and the registration
    ended 1.6 mm off (1.97 mm with 10 mm coarse slices), accepted."""
    return resampling(positive_number(pixel_mm) / REFERENCE_CT_PIXEL_MM)


def positive_number(value, what: str = "CT pixel size", *, unit: str = "mm",
                    zero: bool = False) -> float:
    """``value`` as a float if it is a positive (``zero``: or zero), finite number (of
    ``unit``), else a ``ValueError`` naming ``what`` (text, booleans and None are refused,
    not converted)."""
    number = isinstance(value, int | float | np.integer | np.floating)
    p = float(value) if number and not isinstance(value, bool) else float("nan")
    if not (np.isfinite(p) and (p > 0 or (zero and p == 0))):
        of = f" of {unit}" if unit else ""
        raise ValueError(f"{what} must be a {'non-negative' if zero else 'positive'} number"
                         f"{of}, got {value!r}")
    return p


def resampling(ratio: float) -> float:
    """:func:`snake_contour`'s ``scale`` or ``upsample`` for a ratio of pixel sizes: the
    ratio from :data:`RESAMPLE_FROM` up (at most :data:`MAX_RESAMPLING`), else 1."""
    return float(min(ratio, MAX_RESAMPLING)) if ratio >= RESAMPLE_FROM else 1.0


def snake_scale(pixel_mm: float) -> float:
    """:func:`snake_contour`'s ``scale`` for CT pixels of ``pixel_mm``:
    :data:`REFERENCE_CT_PIXEL_MM` over ``pixel_mm`` from :data:`RESAMPLE_FROM` up (at most
    :data:`MAX_RESAMPLING`), else 1 (whole numbers until a held-out review found the
    rounding's edge: 0.54 mm pixels, rounded to scale 1, gave a snake of two thirds its
    reach and two runs refused 1.7-1.8 mm off; 0.53 mm, scale 2, 0.36 mm). On finer slices
    the snake then keeps its capture range and smoothing in mm. With its lengths in px,
    the surfaces of ``experiment2`` with 0.5 mm pixels lay 3.2 / 2.8 mm (distal / proximal)
    from the true bone at their 95th percentile, and a registration ended 1.9 mm off,
    accepted; at this scale 1.1 / 0.2 mm (0.3 mm pixels: 4.7 / 4.6 -> 0.4 / 0.2 mm).
    Coarser pixels keep scale 1 (:func:`snake_upsampling` is theirs)."""
    return resampling(REFERENCE_CT_PIXEL_MM / positive_number(pixel_mm))


def _pixel_mm(slice2ct: np.ndarray) -> float:
    """The mean in-plane pixel size (mm) of a (4, 4) or (K, 4, 4) slice affine."""
    a = slice2ct.reshape(-1, 4, 4)
    return float(np.mean(np.linalg.norm(a[:, :3, :2], axis=1)))


#: slices whose neighbours on both sides lie within this distance (mm) along the stack are
#: checked against them by :func:`contours_from_ct` (the paper's finest spacing, 1 mm near
#: the pins, and the 2 mm of the schedules around it; a bone section moves by a fraction of a
#: millimetre between such slices except where the slice grazes a condyle's tip or a lobe
#: begins: where the contour count changes there the slice is left alone; where it does not,
#: the check can flag a good slice, and draw it again without the lobe's first part)
NEIGHBOUR_GAP_MM = 2.0
#: a checked slice disagrees with its neighbours when a point of its contours lies farther
#: than this (mm, in-plane) from the contours of both (measured on the clinic profile's
#: `surfaces` cases, 2026-11-29: snakes that cut a lobe off the proximal section on slices
#: crossed by a pin's streaks scored 3.75-8.2 mm; every other contour under the same
#: conditions 3 mm or less)
DISAGREEMENT_MM = 3.0


def _click_source(keys: np.ndarray, clicks_xy: Mapping, k: int) -> int:
    """The clicked slice whose clicks seed slice ``k`` (``keys``: the clicked slices,
    sorted): the nearest (ties: the lower), but between two clicked slices whose contour
    counts differ, the lower one. The operator clicks again where the cross-sections change
    (the condyles part), so the slices before that click still show what the previous
    clicks outlined (the nearest clicks, until 2026-11-26, gave them the new count: the
    shipped clinic scene outlined four slices below the parting with one contour); elsewhere
    the nearer clicks follow the shape better (the neck and trochanters change quickly
    along the femur)."""
    i = int(np.searchsorted(keys, k, side="right"))   # keys[i - 1] <= k < keys[i]
    if i == 0:
        return int(keys[0])
    below = int(keys[i - 1])
    if below == k or i == len(keys):
        return below
    above = int(keys[i])
    if len(clicks_xy[below]) != len(clicks_xy[above]):
        return below
    return above if above - k < k - below else below


#: the CT snakes' edge options (:func:`snake_contour`; :func:`contours_from_ct` adds the
#: scale and upsampling of the slices' pixels): bone brighter inside, the edge searched 5 px
#: along the normals of the contour smoothed over one vertex, and each vertex's edge
#: compared with its neighbours' (a tooth a vertex or two wide, 1-2.5 px inside the bone,
#: is brought back to the edge)
CT_SNAKE_OPTIONS = MappingProxyType({"polarity": "bright_inside", "search_px": 5.0,
                                     "normal_sigma": 1.0, "neighbour_edges": True})


def contours_from_ct(
    volume_hu,
    slice2ct,
    slice_indices: Sequence[int],
    clicks_xy: Mapping[int, Sequence[np.ndarray]],
    *,
    consistency_mm: float | None = DISAGREEMENT_MM,
    **snake_options,
) -> list[SliceContours]:
    """Snake contours on a set of CT slices, clicks reused from slice to slice.

    Parameters
    ----------
    volume_hu : (n_slices, rows, cols) array, CT numbers (HU).
    slice2ct : either (n_slices, 4, 4), one affine per slice mapping (col, row, 0, 1) of that
        slice to ct mm (unequal slice spacing), or one (4, 4) voxel affine mapping
        (col, row, slice, 1) to ct mm.
    slice_indices : the slices to contour.
    clicks_xy : slice index -> list of click polygons ((K, 2) arrays, (x, y) px), one per
        contour on that slice (one for the femur, two at the condyles). A slice without clicks
        reuses those of the nearest clicked slice (by index; ties go to the lower index),
        except where the number of contours changes: between clicked slices of different
        counts, the slices take the lower one's (an operator clicks anew where the
        cross-sections part or join, going up the slices).
    snake_options : keyword options of :func:`snake_contour`; ``polarity`` defaults to
        ``"bright_inside"`` (bone on CT), ``search_px`` to 5 (beyond a cortical shell),
        ``normal_sigma`` to 1 and ``neighbour_edges`` to True (no vertex left off the edge:
        see :func:`refine_subpixel`), ``scale`` and ``upsample`` to :func:`snake_scale` and
        :func:`snake_upsampling` of the slices' pixel size (the options' lengths in px are
        meant for pixels of :data:`REFERENCE_CT_PIXEL_MM`).
    consistency_mm : a slice whose neighbours on both sides lie within
        :data:`NEIGHBOUR_GAP_MM` and carry as many contours, and whose contours stray more
        than this (mm) from both (:func:`slice_disagreement_mm`), is contoured again with
        the snake seeded from a neighbour's contours; the new contours are kept if they agree
        within it and sit on the slice's edges no worse (``SliceContours.reseeded``; the
        rules, and what the check does not catch, in :func:`_reseed_disagreeing`). None: no
        check. The default, :data:`DISAGREEMENT_MM`.

    Returns
    -------
    list of :class:`SliceContours`, in the order of ``slice_indices``.
    """
    vol = np.asarray(volume_hu)
    if vol.ndim != 3:
        raise ValueError(f"volume_hu must have shape (n_slices, rows, cols), got {vol.shape}")
    aff = np.asarray(slice2ct, dtype=np.float64)
    if not (aff.shape == (4, 4) or aff.shape == (vol.shape[0], 4, 4)):
        raise ValueError(
            f"slice2ct must be (4, 4) or (n_slices={vol.shape[0]}, 4, 4), got {aff.shape}"
        )
    if not clicks_xy:
        raise ValueError("clicks_xy is empty: give the clicks of at least one slice")
    snake_options = {**CT_SNAKE_OPTIONS, "scale": snake_scale(_pixel_mm(aff)),
                     "upsample": snake_upsampling(_pixel_mm(aff)), **snake_options}
    keys = np.array(sorted(int(k) for k in clicks_xy))
    outside = [int(k) for k in keys if not 0 <= k < vol.shape[0]]
    if outside:
        raise ValueError(f"clicks on slice(s) {outside[:5]} outside the volume "
                         f"(0..{vol.shape[0] - 1})")
    out = []
    for k in slice_indices:
        k = int(k)
        if not 0 <= k < vol.shape[0]:
            raise ValueError(f"slice index {k} outside the volume (0..{vol.shape[0] - 1})")
        src = _click_source(keys, clicks_xy, k)
        polys = clicks_xy[src]
        if len(polys) == 0:
            raise ValueError(f"clicks_xy[{src}] holds no click polygon")
        px, ct = [], []
        for j, clicks in enumerate(polys):
            try:
                c = snake_contour(vol[k], clicks, **snake_options)
            except ValueError as exc:
                raise ValueError(f"slice {k} (clicks of slice {src}), contour {j}: {exc}") from None
            c = untangle_contour(c)
            px.append(c)
            ct.append(_to_ct(aff, k, c))
        z = float(np.mean(np.concatenate([p[:, 2] for p in ct])))
        out.append(SliceContours(k, z, tuple(px), tuple(ct)))
    if consistency_mm is not None:
        out = _reseed_disagreeing(vol, aff, out, snake_options,
                                  positive_number(consistency_mm, "consistency_mm"))
    return out



def _plane_axes(normal) -> np.ndarray:
    """(3, 2): two orthonormal axes across ``normal`` (3,); for the ct z axis, x and y."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    if abs(n[2]) >= 1.0 - 1e-12:
        return np.eye(3)[:, :2]
    u = np.cross([0.0, 0.0, 1.0], n)
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(n, u)])


def slice_disagreement_mm(contours_ct, below_ct, above_ct, *, normal=(0.0, 0.0, 1.0)) -> float:
    """How far (mm) a slice's contours stray from its two neighbours': the largest, over
    the points of ``contours_ct`` (list of (K, 3) ct mm), of the in-plane distance to the
    nearer of the contours of the slice below and of the slice above (each a list of (K, 3)
    ct mm), all seen along the slices' ``normal`` (the ct z axis for axial slices; a tilted
    gantry's slices tilt it). A point near either neighbour agrees, so a section that grows
    or shrinks steadily along the bone scores its one-slice change; a lobe the snake cut off
    (or a leak out along a streak) scores the lobe's width."""
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0:
        raise ValueError(f"slice_disagreement_mm: normal must be a finite, non-zero (3,) "
                         f"vector, got {normal!r}")
    axes = _plane_axes(n)

    def seen(cs):
        out = [np.asarray(c, dtype=np.float64)[:, :3] @ axes for c in cs]
        if not out or any(len(c) == 0 or not np.all(np.isfinite(c)) for c in out):
            raise ValueError("slice_disagreement_mm: every slice needs at least one contour "
                             "of finite points")
        return out

    below, above = seen(below_ct), seen(above_ct)
    worst = 0.0
    for xy in seen(contours_ct):
        d = np.minimum(polygon_distances(xy, below), polygon_distances(xy, above))
        worst = max(worst, float(d.max()))
    return worst


def _slice_frame(aff: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slice ``k``'s plane: its in-plane axes (3, 2) mm per px, its origin (3,) ct mm (pixel
    (0, 0)) and its normal (3,) (the axes' cross product, not normalised)."""
    a, kk = _slice_affine(aff, k)
    return a[:3, :2], a[:3, 3] + kk * a[:3, 2], np.cross(a[:3, 0], a[:3, 1])


def _ct_to_px(aff: np.ndarray, k: int, points_ct: np.ndarray) -> np.ndarray:
    """Points (K, 3) ct mm projected along the slice normal onto slice ``k``: (K, 2) px."""
    axes, origin, _ = _slice_frame(aff, k)
    xy, *_ = np.linalg.lstsq(axes, (np.asarray(points_ct)[:, :3] - origin).T, rcond=None)
    return xy.T


def _plane_positions(aff: np.ndarray, out: list[SliceContours]) -> np.ndarray:
    """Each slice's plane position (mm) along the stack's normal (that of its first slice):
    where the slice lies, whatever its contours hold (their mean z moves with what they
    outline on a tilted stack)."""
    if not out:
        return np.zeros(0)
    n = _slice_frame(aff, out[0].slice_index)[2]
    n = n / np.linalg.norm(n)
    return np.array([float(_slice_frame(aff, c.slice_index)[1] @ n) for c in out])


def _checked_neighbours(out: list[SliceContours], aff: np.ndarray
                        ) -> list[tuple[int, int, int]]:
    """(slice, below, above) positions in ``out`` of the slices to check: both neighbours
    (by the slice planes' positions along the stack, :func:`_plane_positions`) within
    :data:`NEIGHBOUR_GAP_MM`, and the same number of contours on all three."""
    pos = _plane_positions(aff, out)
    order = sorted(range(len(out)), key=lambda i: pos[i])
    triples = []
    for b, i, a in zip(order, order[1:], order[2:], strict=False):
        if max(pos[i] - pos[b], pos[a] - pos[i]) > NEIGHBOUR_GAP_MM + 1e-6:
            continue
        if len(out[b].contours_ct) == len(out[i].contours_ct) == len(out[a].contours_ct):
            triples.append((i, b, a))
    return triples


#: the share of a slice's contour vertices allowed on weak edges when contours are compared
#: by how well they sit on the image's edges (:func:`_edge_support`)
EDGE_SUPPORT_QUANTILE = 0.1


def _edge_support(gradient: np.ndarray, contours_px) -> float:
    """How well contours sit on edges: the :data:`EDGE_SUPPORT_QUANTILE` quantile, over
    their vertices, of the gradient norm ``gradient`` (H, W) sampled there (bilinear). A
    contour that cuts across a bone's section or hangs in soft tissue has a run of vertices
    where the gradient is weak."""
    xy = np.vstack([np.asarray(c, dtype=np.float64) for c in contours_px])
    g = ndimage.map_coordinates(gradient, [xy[:, 1], xy[:, 0]], order=1, mode="nearest")
    return float(np.quantile(g, EDGE_SUPPORT_QUANTILE))


#: a contour drawn again may leave out at most this area (mm^2) of the region its slice's
#: contours held when that part looks like bone (:func:`_left_out_bone_mm2`). Measured on
#: the clinic profile (experiment2 seeds 2, 4 and 5, 3 cases each, 2026-11-29): at the
#: greater trochanter's onset the clicked contour holds a bony island (the true section's
#: own, about 10 mm wide) and the snake seeded from the slice below left 80-95 mm^2 of it
#: out, mean 896-990 HU against 589-605 HU inside the new contour (the true section then up
#: to 10 mm from it, 3.4-3.8 mm before); the 24 real fixes left out 0-3.2 mm^2
MAX_LEFT_OUT_BONE_MM2 = 20.0
#: the ring (px) around the old and new contours whose intensities stand for what
#: surrounds the bone
_RING_PX = 3
#: bone-bright parts narrower than this (mm) do not count as bone left out: the bright
#: band of a metal streak along which a snake had leaked, and which the redraw leaves out
#: (a harder scene's 1000 HU streaks, 2026-11-29: redraws from 15-56 mm off the bone to
#: 0.2-1.1 mm left out such parts, 2.3-4.8 mm wide, as bright as the bone's inside; the
#: islands left out were 8-12.5 mm wide, the largest disc inside them). The opening's
#: element is an ellipse this wide across, in whole pixels per axis (7 px at 0.8 mm)
MIN_BONE_WIDTH_MM = 6.0


def _fill(shape, contours_px) -> np.ndarray:
    """(H, W) bool: the pixels inside any of ``contours_px`` ((K, 2) x, y px each)."""
    from skimage.draw import polygon

    m = np.zeros(shape, dtype=bool)
    for c in contours_px:
        c = np.asarray(c, dtype=np.float64)
        rr, cc = polygon(c[:, 1], c[:, 0], shape)
        m[rr, cc] = True
    return m


def _left_out_bone_mm2(image, old_px, new_px, axes_mm) -> float:
    """The area (mm^2) of the pixels inside the contours ``old_px`` and outside ``new_px``
    (slice ``image``, px) whose intensity is nearer the mean inside ``new_px`` than the mean
    of a ring of :data:`_RING_PX` around both (what surrounds the bone), in parts at least
    :data:`MIN_BONE_WIDTH_MM` wide (a morphological opening): the part of the bone the new
    contours leave out. ``axes_mm`` (3, 2): the slice's column and row steps (mm per px),
    for the pixels' area and the opening's element. A leak into soft tissue taken back
    counts nothing, nor the soft tissue a contour bridged to reach an island, nor a streak's
    narrow bright band; the island does. New contours holding nothing leave all the old
    inside out."""
    img = np.asarray(image, dtype=np.float64)
    axes = np.asarray(axes_mm, dtype=np.float64)
    px_area = float(np.linalg.norm(np.cross(axes[:, 0], axes[:, 1])))
    old, new = _fill(img.shape, old_px), _fill(img.shape, new_px)
    out = old & ~new
    if not out.any():
        return 0.0
    if not new.any():
        return float(np.count_nonzero(out) * px_area)
    both = old | new
    ring = ndimage.binary_dilation(both, iterations=_RING_PX) & ~both
    if not ring.any():                       # the contours fill the image: no surroundings
        return float(np.count_nonzero(out) * px_area)
    inside, around = img[new].mean(), img[ring].mean()
    bone = out & (np.abs(img - inside) < np.abs(img - around))
    # the element's half-widths (px) per axis: a width of MIN_BONE_WIDTH_MM in whole pixels
    rx, ry = (max(1, int(round(0.5 * (MIN_BONE_WIDTH_MM / float(np.linalg.norm(axes[:, j]))
                                      - 1.0)))) for j in (0, 1))
    yy, xx = np.mgrid[-ry:ry + 1, -rx:rx + 1]
    bone = ndimage.binary_opening(bone, structure=(xx / rx) ** 2 + (yy / ry) ** 2 <= 1.0)
    return float(np.count_nonzero(bone) * px_area)


def _reseed_disagreeing(vol, aff, out: list[SliceContours], snake_options: dict,
                        limit_mm: float) -> list[SliceContours]:
    """``out`` with the contours of each checked slice (:func:`_checked_neighbours`) that
    disagree with their neighbours by more than ``limit_mm`` (:func:`slice_disagreement_mm`)
    drawn again, the worst first: the snake seeded from each neighbour's contours in turn
    (only from a neighbour that is checked and agrees), the result kept if it agrees within
    ``limit_mm``, sits on the slice's edges no worse than the contours it replaces
    (:func:`_edge_support`; the better of the two) and leaves out no more than
    :data:`MAX_LEFT_OUT_BONE_MM2` of them that looks like bone (:func:`_left_out_bone_mm2`:
    where a lobe or an island begins, the slice below has none and a snake seeded from it
    leaves it out). After each slice drawn again its
    neighbours are judged again, so that a good slice beside a bad one is not drawn from
    the wrong neighbour; each slice is tried once. Where the bone itself changes that fast,
    a snake seeded elsewhere finds the same edges, or leaves some off them, and the slice
    keeps its contours. A slice drawn again gets its own contours back if they agree with
    its neighbours' as they end. Every checked slice's ``disagreement_mm`` is set (that of
    the contours it keeps, against its neighbours' as they end).

    Not caught: two neighbouring slices with the same wrong contours agree with each
    other; the slices at either end of a run of checked ones are never checked, nor used
    as seeds (a run of three cannot have its middle drawn again).

    Why: on a slice crossed by a pin's streaks, the operator's fresh clicks can start the
    snake where the streaks pull it across a lobe of the section (clinic profile, the
    trochanter: contours up to 11.7 mm off the bone on a slice between two good ones)."""
    near = {i: (b, a) for i, b, a in _checked_neighbours(out, aff)}
    cur = list(out)

    def normal(i):
        return _slice_frame(aff, cur[i].slice_index)[2]

    def judge(i):
        b, a = near[i]
        return slice_disagreement_mm(cur[i].contours_ct, cur[b].contours_ct,
                                     cur[a].contours_ct, normal=normal(i))

    score = {i: judge(i) for i in near}
    tried = set()
    h, w = vol.shape[1:]
    sigma = float(snake_options.get("fine_sigma_px", 1.0)) * max(
        float(snake_options.get("scale", 1.0)), 1.0)
    while True:
        todo = [i for i in near if i not in tried and score[i] > limit_mm]
        if not todo:
            break
        i = max(todo, key=lambda j: score[j])
        tried.add(i)
        b, a = near[i]
        k = cur[i].slice_index
        grad = ndimage.gaussian_gradient_magnitude(np.asarray(vol[k], np.float64), sigma)
        support = _edge_support(grad, cur[i].contours_px)
        axes = _slice_frame(aff, k)[0]
        best = None
        for j in (b, a):
            if not score.get(j, np.inf) <= limit_mm:   # seeds from a slice that agrees
                continue
            px = []
            try:
                for c in cur[j].contours_ct:
                    seeds = _ct_to_px(aff, k, c)
                    seeds = np.column_stack([np.clip(seeds[:, 0], -0.5, w - 0.5),
                                             np.clip(seeds[:, 1], -0.5, h - 0.5)])
                    px.append(untangle_contour(snake_contour(vol[k], seeds, **snake_options)))
            except ValueError:
                continue
            ct = [_to_ct(aff, k, c) for c in px]
            s = slice_disagreement_mm(ct, cur[b].contours_ct, cur[a].contours_ct,
                                      normal=normal(i))
            if s <= limit_mm and _edge_support(grad, px) >= support \
                    and (best is None or s < best[0]) and _left_out_bone_mm2(
                        vol[k], cur[i].contours_px, px, axes) <= MAX_LEFT_OUT_BONE_MM2:
                best = (s, px, ct)
        if best is None:
            continue
        cur[i] = replace(cur[i], contours_px=tuple(best[1]), contours_ct=tuple(best[2]),
                         reseeded=True)
        for j in (i, b, a):
            if j in near:
                score[j] = judge(j)
    # a slice drawn again before its bad neighbour was: its own contours, if they agree
    # with the neighbours as they end (at a lobe's onset, between a slice without the lobe
    # and a bad one that had cut it off, the snake seeded from below cut it off too)
    restored = set()
    for i in near:
        if cur[i].reseeded:
            b, a = near[i]
            if slice_disagreement_mm(out[i].contours_ct, cur[b].contours_ct,
                                     cur[a].contours_ct, normal=normal(i)) <= limit_mm:
                cur[i] = out[i]
                restored.update((i, b, a))
    # the scores are those of the contours kept: judged again only where a restore moved
    # a slice or a neighbour (the loop kept every other score current)
    for j in restored & near.keys():
        score[j] = judge(j)
    return [replace(c, disagreement_mm=score[i]) if i in near else c
            for i, c in enumerate(cur)]
