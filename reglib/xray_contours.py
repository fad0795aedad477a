"""Bone contours on fluoroscopic (X-ray) images from a few user clicks.

On a fluoroscopic frame the femur shows *external* contours (the outline of the bone: the
edges of the shaft, the head, the condyles) and *internal* ones (edges seen through the bone:
the medullary canal, the far condyle, the lesser trochanter). Both kinds are 2-D projections
of apparent contours and both can be used for registration (X-rays see through bone); the
label says which kind the user traced, as the registration treats them differently
(NOTES.md s3, step B).

Each contour is found by the two-stage snake of :func:`reglib.contours.snake_contour`, on an
image prepared for X-ray video:

- the dark surround of the circular field of view is replaced by the nearest pixel inside it,
  so that the edge of the field (the strongest edge of the frame) does not attract the snake;
- the 8-bit video is used as it is (a logarithmic video amplifier makes its grey levels
  proportional to the line integral of attenuation, and bone edges steps in it);

then every vertex is moved along its normal to the edge found by fitting the intensity
profile across it (:func:`refine_edge_profile`). The gradient maximum alone is biased
inwards on X-ray images: near an apparent contour of a smooth body, the path length through
the body grows as the square root of the distance to the contour, so the blurred edge has its
steepest point a fraction of the blur inside the body (about 0.6 px here). The fit uses that
generic shape (``a + b * sqrt(max(+-(s - s0), 0))``, blurred by a Gaussian of unknown width)
and returns ``s0``, the contour itself. Curves are open by default (the edges of a shaft end
at the border of the field); closed curves (the femoral head) are asked for with
``closed=True``.

Pixel coordinates ``(x, y) = (col, row)``, the centre of the top-left pixel at (0, 0);
images ``(H, W)`` indexed ``[row, col]``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import ndimage

from reglib.contours import positive_number, resampling, snake_contour
from reglib.geometry import as_flags

__all__ = ["REFERENCE_FIELD_PX", "REFERENCE_PIXEL_MM", "XrayContour", "field_of_view_mask",
           "field_scale", "pixel_scale", "prepare_xray", "refine_edge_profile", "xray_contour",
           "xray_contours"]

Label = Literal["external", "internal"]


@dataclass(frozen=True)
class XrayContour:
    """One bone contour on an X-ray image.

    ``points_xy`` (K, 2) float64 (x, y) px along the contour; ``label`` "external" or
    "internal"; ``closed`` whether the last point joins the first.
    """

    points_xy: np.ndarray
    label: Label
    closed: bool

    def __post_init__(self):
        if self.label not in ("external", "internal"):
            raise ValueError(f"label: expected 'external' or 'internal', got {self.label!r}")


def field_of_view_mask(image, *, dark_level: float = 2.0, erode_px: int = 3,
                       reference: bool = False) -> np.ndarray:
    """The image's field of view: the largest bright connected region, eroded, ``(H, W)``.

    Video frames of an image intensifier are dark (near 0) outside a circular field. Pixels
    above ``dark_level`` belong to it; the largest connected part is kept and eroded by
    ``erode_px`` so that the blurred rim is excluded. Computed with OpenCV's labelling and
    erosion (5x faster); ``reference=True``: scipy.ndimage's, the same mask (compared in
    tests).
    """
    img = np.asarray(image, dtype=np.float64)
    lit = img > dark_level
    if reference:
        lab, n = ndimage.label(lit)
        if n == 0:
            raise ValueError(_NO_FIELD)
        sizes = ndimage.sum(lit, lab, index=np.arange(1, n + 1))
        mask = lab == (1 + int(np.argmax(sizes)))
        mask = ndimage.binary_fill_holes(mask)  # black objects (metal) stay in the field
        if erode_px > 0:
            mask = ndimage.binary_erosion(mask, iterations=erode_px)
        return mask
    import cv2

    from reglib.markers import _label

    lab, n = _label(lit, reference=False)       # scipy's labels, in the same order
    if n == 0:
        raise ValueError(_NO_FIELD)
    sizes = np.bincount(lab.ravel(), minlength=n + 1)[1:]
    mask = lab == (1 + int(np.argmax(sizes)))
    # holes: the parts of the rest (4-connected, as scipy's filling) that touch no border
    rest, _ = _label(~mask, reference=False)
    edge = np.unique(np.concatenate([rest[0], rest[-1], rest[:, 0], rest[:, -1]]))
    mask |= (rest > 0) & ~np.isin(rest, edge)
    if erode_px > 0:   # scipy's cross, outside the image counted as background
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        mask = cv2.erode(mask.view(np.uint8), cross, iterations=int(erode_px),
                         borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
    return mask


_NO_FIELD = "image: no pixel above the dark level; is this an X-ray frame?"


def prepare_xray(image, *, fov_mask=None) -> np.ndarray:
    """The image as float64 with the outside of the field filled by the nearest inside pixel."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D (H, W) array, got shape {img.shape}")
    mask = field_of_view_mask(img) if fov_mask is None else np.asarray(fov_mask, dtype=bool)
    if mask.shape != img.shape:
        raise ValueError(f"fov_mask: shape {mask.shape} differs from the image's {img.shape}")
    if not mask.any():
        raise ValueError("fov_mask: empty field of view")
    _, (rows, cols) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return img[rows, cols]


def _normals(c: np.ndarray, closed: bool) -> np.ndarray:
    d = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0) if closed else np.gradient(c, axis=0)
    n = np.column_stack([d[:, 1], -d[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(norm > 0, norm, 1.0)


#: the least reach (px) of :func:`_blurred_sqrt_table`: what the default lengths of
#: :func:`refine_edge_profile` need (4 + 2 px from the edge, and the blur's tail)
TABLE_REACH_PX = 12.0


@functools.lru_cache(maxsize=8)
def _blurred_sqrt_table(sigmas: tuple, step: float = 0.01, reach: float = TABLE_REACH_PX):
    """``H_sigma(x) = (G_sigma * sqrt(max(., 0)))(x)`` on a grid, one row per sigma of the
    tuple ``sigmas`` (remembered: every contour of a run asks for the same; read-only)."""
    x = np.arange(-reach, reach + step / 2, step)
    base = np.sqrt(np.maximum(x, 0.0))
    rows = np.array([ndimage.gaussian_filter1d(base, s / step, mode="nearest")
                     for s in sigmas])
    x.flags.writeable = False
    rows.flags.writeable = False
    return x, rows


def refine_edge_profile(image, contour_xy, *, closed: bool = False, half_width_px: float = 4.0,
                        sample_px: float = 0.25, search_px: float = 2.0,
                        pre_sigma_px: float = 0.7, sigmas_px=(0.6, 0.8, 1.0, 1.2, 1.5),
                        smooth_vertices: int = 5, whole_image: bool = False) -> np.ndarray:
    """Move each contour vertex along its normal to the edge of a fitted X-ray edge profile.

    The image, smoothed by ``pre_sigma_px``, is sampled (bilinear) every ``sample_px`` within
    ``+-half_width_px`` of the vertex along its normal; the profile is fitted in least squares
    by ``a + b * H_sigma(+-(s - s0))`` (``H_sigma`` a square root blurred by a Gaussian of
    width ``sigma``: the shape of the line integral across an apparent contour), over both
    signs, ``sigma`` in ``sigmas_px`` and ``s0`` within ``+-search_px`` (grid of 0.05 px, then
    a parabola through the best three). Vertices whose best ``s0`` lies at the end of the
    search range, or whose fit explains less than half the profile's variance, are failed
    fits; the offsets of the others are passed through a running median over
    ``smooth_vertices`` neighbours (1: none), which also fills the failed ones.

    Parameters
    ----------
    image : (H, W) array indexed [row, col].
    contour_xy : (K, 2) float64 (x, y) px.
    whole_image : smooth the whole image instead of the samples' box (the reference of that
        crop, compared in tests: the same numbers).

    Returns
    -------
    (K, 2) float64 (x, y) px.
    """
    for name, v in (("half_width_px", half_width_px), ("sample_px", sample_px),
                    ("search_px", search_px)):
        positive_number(v, f"refine_edge_profile: {name}", unit="px")
    positive_number(pre_sigma_px, "refine_edge_profile: pre_sigma_px", unit="px", zero=True)
    if not len(sigmas_px):
        raise ValueError("refine_edge_profile: sigmas_px must list at least one edge width (px)")
    shape = np.shape(contour_xy)
    if len(shape) != 2 or shape[1] != 2 or shape[0] < (3 if closed else 2):
        raise ValueError(f"refine_edge_profile: contour_xy must be (K, 2) (x, y) px with K >= "
                         f"{3 if closed else 2}, got shape {shape}")
    for v in sigmas_px:
        positive_number(v, "refine_edge_profile: sigmas_px", unit="px")
    image = np.asarray(image, dtype=np.float64)
    c = np.asarray(contour_xy, dtype=np.float64)
    n = _normals(c, closed)
    s = np.arange(-half_width_px, half_width_px + sample_px / 2, sample_px)  # (S,)
    px = c[:, None, 0] + s[None, :] * n[:, None, 0]
    py = c[:, None, 1] + s[None, :] * n[:, None, 1]
    # smooth only the samples' box, with a margin of the filter's reach (and the bilinear
    # neighbour) inside which the crop's values are the whole image's, bit for bit; a
    # coordinate minus the crop's whole-pixel origin keeps its fraction exactly
    pad = int(4.0 * pre_sigma_px + 0.5) + 2
    H, W = image.shape
    r0, r1, c0, c1 = 0, 0, 0, 0
    if px.size:
        r0, r1 = max(int(np.floor(py.min())) - pad, 0), min(int(np.ceil(py.max())) + pad + 1, H)
        c0, c1 = max(int(np.floor(px.min())) - pad, 0), min(int(np.ceil(px.max())) + pad + 1, W)
    if whole_image or r0 >= r1 or c0 >= c1:   # (no samples, or all beyond an edge)
        r0, r1, c0, c1 = 0, H, 0, W
    img = ndimage.gaussian_filter(image[r0:r1, c0:c1], pre_sigma_px)
    prof = ndimage.map_coordinates(img, [(py - r0).ravel(), (px - c0).ravel()], order=1,
                                   mode="nearest").reshape(px.shape)  # (K, S)
    eff = np.sqrt(np.asarray(sigmas_px, dtype=np.float64) ** 2 + pre_sigma_px**2)
    # the model is evaluated at up to half_width + search from its edge: the table reaches
    # that far and 3 of the widest blur's sigmas beyond, or its ends would flatten the
    # model there (the defaults need 11 px: the table of 12 px, as before)
    reach = max(TABLE_REACH_PX, half_width_px + search_px + 3.0 * float(eff.max()))
    xt, table = _blurred_sqrt_table(tuple(float(e) for e in eff), reach=float(reach))
    s0 = np.arange(-search_px, search_px + 1e-9, 0.05)  # (T,)
    best_res = np.full(len(c), np.inf)
    best_t = np.zeros(len(c), dtype=int)
    best_curve = np.zeros((len(c), len(s0)))
    pm = prof - prof.mean(axis=1, keepdims=True)
    total = np.sum(pm * pm, axis=1)
    for row in table:
        for sign in (1.0, -1.0):
            arg = sign * (s[None, :] - s0[:, None])  # (T, S)
            h = np.interp(arg, xt, row)
            hm = h - h.mean(axis=1, keepdims=True)  # (T, S)
            hh = np.sum(hm * hm, axis=1)  # (T,)
            ph = pm @ hm.T  # (K, T)
            res = total[:, None] - ph**2 / hh[None, :]  # residual after the best a, b
            k = np.argmin(res, axis=1)
            rk = res[np.arange(len(c)), k]
            better = rk < best_res
            best_res[better] = rk[better]
            best_t[better] = k[better]
            best_curve[better] = res[better]
    k = best_t
    ok = (k > 0) & (k < len(s0) - 1) & (best_res < 0.5 * total)
    kk = np.clip(k, 1, len(s0) - 2)
    rows = np.arange(len(c))
    f0, f1, f2 = best_curve[rows, kk - 1], best_curve[rows, kk], best_curve[rows, kk + 1]
    den = f0 - 2 * f1 + f2
    frac = np.where(den > 0, 0.5 * (f0 - f2) / np.where(den > 0, den, 1.0), 0.0)
    off = s0[kk] + np.clip(frac, -0.5, 0.5) * 0.05
    if smooth_vertices > 1 and ok.sum() >= smooth_vertices:
        # the edge is smooth along the contour: a running median of the offsets rejects
        # vertices fitted to noise or to a neighbouring edge; failed fits take it too
        idx = np.flatnonzero(ok)
        med = ndimage.median_filter(off[idx], size=smooth_vertices,
                                    mode="wrap" if closed else "nearest")
        off = np.interp(np.arange(len(c)), idx, med)
    else:
        off = np.where(ok, off, 0.0)
    return c + off[:, None] * n


LENIENT_PX = 4
"""A click within this many pixels (4-connected steps) of the field of view is accepted."""


def _near_mask(mask: np.ndarray, rows: np.ndarray, cols: np.ndarray, steps: int) -> np.ndarray:
    """For pixels ``(rows, cols)``: whether they lie in ``ndimage.binary_dilation(mask,
    iterations=steps)`` (a pixel of the mask within ``steps`` 4-connected steps, i.e. L1
    distance; a pixel outside the image is not), looked up in a window per pixel instead of
    dilating the whole mask (``tests/reglib/test_xray_contours.py`` compares them)."""
    H, W = mask.shape
    out = np.zeros(len(rows), dtype=bool)
    for i, (r, c) in enumerate(zip(rows, cols, strict=True)):
        if not (0 <= r < H and 0 <= c < W):
            continue
        r0, r1 = max(r - steps, 0), min(r + steps + 1, H)
        c0, c1 = max(c - steps, 0), min(c + steps + 1, W)
        dr = np.abs(np.arange(r0, r1) - r)[:, None]
        dc = np.abs(np.arange(c0, c1) - c)[None, :]
        out[i] = bool(np.any(mask[r0:r1, c0:c1] & (dr + dc <= steps)))
    return out


def xray_contour(
    image,
    clicks_xy,
    *,
    label: Label = "external",
    closed: bool = False,
    fov_mask=None,
    fine_sigma_px: float = 1.0,
    spacing_px: float = 2.0,
    profile_fit: bool = True,
    filled=None,
    scale: int | None = None,
    pixel_mm: float | None = None,
    noise_sd: float | None = None,
    **snake_options,
) -> XrayContour:
    """One bone contour from a few clicks on an X-ray image.

    Parameters
    ----------
    image : (H, W) array, the video frame (uint8 or float), indexed [row, col].
    clicks_xy : (K, 2) array of (x, y) px near the bone edge, in order along it (K >= 2 for
        an open contour, K >= 3 for a closed one).
    label : "external" (the bone outline) or "internal" (an edge seen through the bone).
    closed : a closed contour (e.g. the femoral head) or an open one (default).
    fov_mask : (H, W) bool, the field of view; estimated from the image when None.
    fine_sigma_px, spacing_px, snake_options : passed to
        :func:`reglib.contours.snake_contour`.
    profile_fit : finish with :func:`refine_edge_profile` (else the snake's gradient maximum).
    filled : the image as :func:`prepare_xray` gives it for ``fov_mask`` (computed when
        None); pass it when tracing several contours on one image.
    scale : the snake's and the profile fit's lengths in px (set for video of
        :data:`REFERENCE_PIXEL_MM` pixels at the intensifier's input) times this number
        (>= 1); None: :func:`pixel_scale` of ``pixel_mm`` when it is given, else
        :func:`field_scale` of the field of view.
    pixel_mm : the video's nominal pixel at the intensifier's input (mm), if known.
    noise_sd : the frame's pixel noise (grey levels; :func:`frame_noise_sd`, computed when
        None); the traced outline must stand :data:`MIN_EDGE_Z` standard errors above it.

    Returns
    -------
    XrayContour with ``points_xy`` (M, 2) (x, y) px, sub-pixel.

    Raises
    ------
    ValueError : bad label, image or clicks (too few, outside the image or the field).
    """
    if label not in ("external", "internal"):
        raise ValueError(f"label: expected 'external' or 'internal', got {label!r}")
    if np.iscomplexobj(image):
        raise ValueError("image: complex values; expected a real grey-level frame")
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image: expected a 2-D (H, W) array, got shape {img.shape}")
    if not np.all(np.isfinite(img)) or np.abs(img).max(initial=0.0) > MAX_IMAGE_VALUE:
        raise ValueError(f"image: values must be finite and within +-{MAX_IMAGE_VALUE:g} "
                         "(grey levels or counts), got up to "
                         f"{np.nanmax(np.abs(img)):.3g}")
    mask = field_of_view_mask(img) if fov_mask is None else as_flags(fov_mask, "fov_mask")
    pts = np.asarray(clicks_xy, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"clicks_xy: expected a (K, 2) array of (x, y) px, got {pts.shape}")
    if mask.shape == img.shape and mask.any() and np.ptp(img[mask]) == 0:
        raise ValueError("image: uniform inside the field of view; there is no edge to trace")
    # a click is accepted anywhere in the field, its blurred rim included (the snake works on
    # the filled image, so a click just outside the eroded mask does no harm)
    inside = _near_mask(mask, np.rint(pts[:, 1]).astype(int), np.rint(pts[:, 0]).astype(int),
                        LENIENT_PX)
    if not inside.all():
        bad = np.flatnonzero(~inside).tolist()
        raise ValueError(f"clicks_xy: clicks {bad} lie outside the image's field of view")
    if filled is None:
        filled = prepare_xray(img, fov_mask=mask)
    elif np.shape(filled) != img.shape:
        raise ValueError(f"filled: shape {np.shape(filled)} differs from the image's "
                         f"{img.shape}")
    if scale is not None:
        m = scale
    else:
        m = pixel_scale(pixel_mm) if pixel_mm is not None else field_scale(mask)
    pts_out = snake_contour(filled, pts, closed=closed, fine_sigma_px=fine_sigma_px,
                            spacing_px=spacing_px, scale=m, **snake_options)
    if profile_fit:
        pts_out = refine_edge_profile(filled, pts_out, closed=closed, **_profile_lengths(m))
    changes = _changes_across(filled, pts_out, closed)
    step, span = _edge_step(changes), float(np.ptp(filled[mask]))
    if not step >= MIN_EDGE_STEP * span:
        raise ValueError(f"no edge along the traced outline: the image changes by "
                         f"{step:.3g} across it (median over its points), under "
                         f"{MIN_EDGE_STEP:.0%} of the field's range {span:.3g}; "
                         "are the clicks near the bone's outline?")
    if noise_sd is None:
        noise_sd = frame_noise_sd(img, mask)
    z = _edge_z(changes, float(noise_sd))
    if not z >= MIN_EDGE_Z:
        raise ValueError(f"no edge along the traced outline above the frame's noise: the "
                         f"image's signed change across it is {z:.2g} standard errors of its "
                         f"noise ({float(noise_sd):.3g} grey levels) from none, under "
                         f"{MIN_EDGE_Z:g}; does the frame show the bone?")
    return XrayContour(points_xy=pts_out, label=label, closed=closed)


#: the video pixel (mm at the intensifier's input) for which the X-ray snake's and profile
#: fit's lengths in px were set: 640 x 480 video of a 9-inch (228.6 mm) intensifier
REFERENCE_PIXEL_MM = 0.5
#: ...and that video's field of view across (px)
REFERENCE_FIELD_PX = 457.0


def pixel_scale(pixel_mm: float) -> float:
    """:func:`reglib.contours.resampling` of :data:`REFERENCE_PIXEL_MM` over ``pixel_mm``
    (mm at the intensifier's input): on finer video the lengths in px of
    :func:`xray_contour` grow with it, so that the snake keeps its smoothing and reach, and
    the profile fit the blur widths it tries, in mm (an intensifier's blur is set in mm,
    not in pixels). Measured on ``experiment2`` with 2048 x 1536 video of 0.156 mm pixels
    (seed 1): with the reference's lengths the external contours lay 1.8-3.4 px from the
    true outline (median) and the registration ended 2.2 mm off, accepted."""
    p = positive_number(pixel_mm, "pixel_mm (the video's pixel at the intensifier's input)")
    return resampling(REFERENCE_PIXEL_MM / p)


def field_scale(fov_mask) -> float:
    """:func:`pixel_scale` when the pixel size is not known, from the field of view's area
    against :data:`REFERENCE_FIELD_PX` (a 9-inch field), as :func:`pixel_scale` takes its
    ratio. It takes the intensifier for a 9-inch one: on a 150 mm field of
    1024 x 768 video of 0.25 mm it gives 1 where the pixel asks for 2 (a held-out review:
    seeds 2 and 3 accepted 1.50 and 1.69 mm off; 0.79 mm at scale 2), and a field cut by
    the frame's edge counts short."""
    mask = np.asarray(fov_mask, dtype=bool)
    diameter = 2.0 * np.sqrt(np.count_nonzero(mask) / np.pi)
    return resampling(diameter / REFERENCE_FIELD_PX)


def _profile_lengths(m: float) -> dict:
    """:func:`refine_edge_profile`'s lengths in px at scale ``m``: its defaults times ``m``
    (none at 1)."""
    if m == 1:
        return {}
    import inspect

    defaults = {k: p.default for k, p in inspect.signature(refine_edge_profile).parameters.items()}
    out = {k: defaults[k] * m for k in ("half_width_px", "sample_px", "search_px",
                                        "pre_sigma_px")}
    out["sigmas_px"] = tuple(v * m for v in defaults["sigmas_px"])
    return out


#: an X-ray image's largest value (grey levels or counts): beyond it, gradients overflow
MAX_IMAGE_VALUE = 1e12
#: the least change of the image across a traced outline (median over its points, between
#: 3 px inside and 3 px outside), as a fraction of the field's range: a bone's outline in
#: a fluoroscopic frame changes by tens of grey levels of 255
MIN_EDGE_STEP = 0.01


#: the least signed change across a traced outline, in standard errors of its median under
#: the frame's noise alone (:func:`_edge_z`). The simulated operator's traces on the shipped
#: scenes (experiment1, experiment2 and experiment2-ideal, seeds 1-4; 2 to 334 points) give
#: 17-106, and 13 at 20 detected quanta per pixel; traces on a frame of flat grey plus
#: noise of 1, 3 or 8 grey levels 0.01-2.0, which the fraction of the range above let
#: through (a review: such a frame accepted at mTRE 1.5 mm, its view's fit passing)
MIN_EDGE_Z = 5.0


def _changes_across(filled, pts, closed: bool) -> np.ndarray:
    """The change of ``filled`` across the contour ``pts`` (N, 2) px, signed along its
    normals: the value 3 px to the normal's side minus the value 3 px to the other (bilinear),
    (N,); empty for fewer than 2 points."""
    if len(pts) < 2:
        return np.zeros(0)
    n = _normals(pts, closed)
    a, b = pts + 3.0 * n, pts - 3.0 * n
    va = ndimage.map_coordinates(filled, [a[:, 1], a[:, 0]], order=1, mode="nearest")
    vb = ndimage.map_coordinates(filled, [b[:, 1], b[:, 0]], order=1, mode="nearest")
    return va - vb


def _edge_step(changes: np.ndarray) -> float:
    """The median absolute change across a contour (:func:`_changes_across`); nan for
    none."""
    if not len(changes):
        return float("nan")
    return float(np.median(np.abs(changes)))


def _edge_z(changes: np.ndarray, noise_sd: float) -> float:
    """How far a contour is from lying on no edge, in standard errors: the median of the
    signed changes across it (:func:`_changes_across`; a bone's outline keeps one side the
    darker, noise does not) over the standard error of that median for a difference of two
    pixels of noise ``noise_sd`` each at every point (1.2533 * sqrt(2) * noise_sd /
    sqrt(N)). ``inf`` for a noiseless frame with a change, 0 with none, nan for no
    points."""
    if not len(changes):
        return float("nan")
    med = abs(float(np.median(changes)))
    se = 1.2533 * np.sqrt(2.0) * noise_sd / np.sqrt(len(changes))
    if se <= 0:
        return float("inf") if med > 0 else 0.0
    return med / se


def frame_noise_sd(image, fov_mask) -> float:
    """The frame's pixel noise (grey levels): a robust standard deviation (1.4826 times the
    median absolute deviation) of the differences of horizontal neighbours within the field,
    over sqrt(2). Edges are few among the field's pixels and barely move it; an 8-bit frame
    with less noise than its quantisation gives 0."""
    img = np.asarray(image, dtype=np.float64)
    m = np.asarray(fov_mask, dtype=bool)
    d = (img[:, 1:] - img[:, :-1])[m[:, 1:] & m[:, :-1]]
    if d.size < 2:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def xray_contours(image, traces: Sequence[dict], *, fov_mask=None) -> list[XrayContour]:
    """Several contours on one image.

    ``traces``: a sequence of dicts with ``clicks_xy`` and optionally ``label`` and
    ``closed`` (and snake options); the field of view is estimated and the image prepared
    once.
    """
    img = np.asarray(image, dtype=np.float64)
    mask = field_of_view_mask(img) if fov_mask is None else fov_mask
    filled = prepare_xray(img, fov_mask=mask) if len(traces) else None
    noise = frame_noise_sd(img, mask) if len(traces) else None
    out = []
    for i, tr in enumerate(traces):
        tr = dict(tr)
        if "clicks_xy" not in tr:
            raise ValueError(f"traces[{i}]: missing 'clicks_xy'")
        clicks = tr.pop("clicks_xy")
        try:
            out.append(xray_contour(img, clicks, fov_mask=mask, filled=filled,
                                    noise_sd=noise, **tr))
        except ValueError as exc:
            raise ValueError(f"traces[{i}]: {exc}") from None
    return out


#: the band in which an X-ray frame is compared with its sweep's reference frame: a
#: difference of Gaussians of these widths (px, for video of REFERENCE_PIXEL_MM pixels):
#: edges of the bone, the table and the instruments, without the noise's finest grain and
#: the glare's and vignetting's slow changes
AGREEMENT_SIGMAS_PX = (2.0, 6.0)
#: no shift is taken when its correlation lies within this share of the peak's: it explains
#: the frames as well. A review (2026-11-27): views whose fields showed mostly
#: straight, parallel edges (a turned patient under views not re-aimed) correlated 0.979 at
#: no shift against 0.980 at (+1, -7) px (ideal profile) and 0.647 against 0.672 (clinic,
#: 0.963 of it), and were left out as "moved after the sweep". On experiment2's four views a
#: true shift of 1 px leaves 0.967-0.986 of the peak at no shift, of 2 px (the first beyond
#: the pipeline's 1.5 px limit) 0.879-0.934: the share is about the band's own correlation
#: at a 1.5 px lag
AGREEMENT_TIE = 0.04


def _agreement_band(image, window, m: float, *, reference: bool = False) -> np.ndarray:
    """The image's edge band (:data:`AGREEMENT_SIGMAS_PX` times ``m``) inside ``window``,
    its mean there taken off, 0 outside: (H, W) float64. The Gaussians are OpenCV's in
    float32 (:func:`reglib.markers._gaussian`, 4x faster); a band below their rounding
    (1e-6 of the image's largest value) is flat, all 0. ``reference=True``: scipy's in
    float64 (compared in tests)."""
    from reglib.markers import _gaussian

    img = np.asarray(image, dtype=np.float64)
    s1, s2 = (m * s for s in AGREEMENT_SIGMAS_PX)
    b = (_gaussian(img, s1, reference).astype(np.float64)
         - _gaussian(img, s2, reference))
    b = np.where(window, b, 0.0)
    if not reference and np.abs(b).max(initial=0.0) <= 1e-6 * max(1.0, np.abs(img).max()):
        b[:] = 0.0
    b[window] -= b[window].mean()
    return b


def _agreement_windows(frame, reference, fov_mask, m: float, reach: int):
    """The frame's window (the field away from its rim by the band's reach, where the
    filters see only the field) and the reference's, ``reach`` px further in: every shift
    within ``reach`` then sees the whole reference window over the frame's."""
    mask = np.asarray(fov_mask, dtype=bool)
    if mask.shape != np.shape(frame) or np.shape(reference) != np.shape(frame):
        raise ValueError(f"frame_agreement: shapes differ: frame {np.shape(frame)}, reference "
                         f"{np.shape(reference)}, fov_mask {mask.shape}")
    depth = ndimage.distance_transform_cdt(mask, metric="chessboard")
    rim = int(np.ceil(3 * m * AGREEMENT_SIGMAS_PX[1]))
    return depth > rim, depth > rim + reach


def frame_agreement(frame, reference, fov_mask, *, reach_px: int = 32, scale: float = 1.0):
    """How well two frames of one C-arm pose agree: the normalised cross-correlation of
    their edge bands (:data:`AGREEMENT_SIGMAS_PX` times ``scale``) inside the field, at
    its peak over the shifts within ``reach_px``, and that shift.

    The reference's band is taken ``reach_px`` inside the frame's, so that each shift
    correlates the whole of it, normalised by the frame's energy under it at that shift
    (a window cut alike in both pulled the peak towards no shift). An X-ray frame and its
    sweep's reference frame (the rod parked, the patient in the beam) show the same scene
    from the same pose: the peak lies at no shift, 0.54-1.00 on the shipped scenes' views
    (at 20 quanta per pixel too). A frame shifted by ``s`` px peaks at ``s``; a frame of
    another view, mirrored or turned, peaks at 0.35 at most. No shift is reported when its
    correlation lies within :data:`AGREEMENT_TIE` (a share) of the peak's. Computed by FFT
    (:func:`_frame_agreement_direct` is the direct sum, compared in tests).

    Returns
    -------
    (ncc, (dx, dy)): the peak's correlation in [-1, 1] and its shift in px (the frame's
    content lies ``(dx, dy)`` from the reference's), or no shift when no shift's correlation
    is within :data:`AGREEMENT_TIE` of the peak's. ``(nan, (0, 0))`` where a window is empty
    or a band is flat.
    """
    R = int(reach_px)
    outer, inner = _agreement_windows(frame, reference, fov_mask, scale, R)
    if not inner.any():
        return float("nan"), (0, 0)
    a = _agreement_band(frame, outer, scale)
    b = _agreement_band(reference, inner, scale)
    H, W = a.shape
    shape = (H + R, W + R)

    def corr(u, v):  # out[dy, dx] = sum_y u[y + d] * v[y]; negative shifts wrap to the end
        c = np.fft.irfft2(np.fft.rfft2(u, s=shape) * np.conj(np.fft.rfft2(v, s=shape)),
                          s=shape)
        rows = np.r_[shape[0] - R:shape[0], 0:R + 1]
        cols = np.r_[shape[1] - R:shape[1], 0:R + 1]
        return c[np.ix_(rows, cols)]

    num = corr(a, b)
    energy = np.maximum(corr(a * a, inner.astype(np.float64)), 0.0) * np.sum(b * b)
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where(energy > 0, num / np.sqrt(energy), -np.inf)
    k = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    if not np.isfinite(ncc[k]):
        return float("nan"), (0, 0)
    # no shift when it explains the frames as well as the peak (AGREEMENT_TIE): a ridge
    # along straight edges is flat, and its argmax a shift that nothing made
    if ncc[R, R] >= ncc[k] - AGREEMENT_TIE * abs(ncc[k]):
        return float(ncc[k]), (0, 0)
    return float(ncc[k]), (int(k[1]) - R, int(k[0]) - R)


def _frame_agreement_direct(frame, reference, fov_mask, shifts, *, reach_px: int = 32,
                            scale: float = 1.0):
    """The correlation of :func:`frame_agreement` at each shift ``(dx, dy)`` of ``shifts``
    (each within ``reach_px``) by direct sums over the reference's window (its reference in
    tests)."""
    outer, inner = _agreement_windows(frame, reference, fov_mask, scale, int(reach_px))
    a = _agreement_band(frame, outer, scale)
    b = _agreement_band(reference, inner, scale)
    ys, xs = np.nonzero(inner)
    bb = b[ys, xs]
    out = []
    for dx, dy in shifts:
        aa = a[ys + dy, xs + dx]
        out.append(float(np.sum(aa * bb) / np.sqrt(np.sum(aa * aa) * np.sum(bb * bb))))
    return np.array(out)
