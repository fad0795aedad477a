"""The fluoroscope's imaging chain after the line integrals: from primary transmission to video.

Every stage and its magnitude is documented in ``docs/error-model.md``. The order follows the
physics of an image-intensifier (II) fluoroscope:

1. primary transmission ``T = exp(-integral mu)`` per pixel (computed by the ray casting);
2. focal-spot blur: the finite focal spot throws a penumbra whose width at the input plane is
   ``focal_spot_mm * (M - 1)``, ``M`` the magnification of the imaged body
   (:func:`focal_spot_sigma_px`); one Gaussian per image at the magnification of the bone;
3. scatter: a broad, low-frequency component ``S = spr * lowpass(P)`` added to the primary
   ``P`` (:func:`add_scatter`), emitted where the rays crossed matter (primary transmission
   below ``SCATTERER_TRANSMISSION``); behind a uniform body ``S / P`` equals ``spr`` exactly;
4. quantum noise: Poisson counts at fluoroscopic photon numbers (:func:`quantum_noise`; a
   moment-matched normal law above 30 expected quanta, exact below), the
   tube output set by automatic brightness control (:func:`abc_photons`) or given directly;
5. intensifier and video blur: a Gaussian MTF with 50 % modulation at ``mtf50_lp_per_mm``
   (input-plane frequency; :func:`mtf_sigma_px`), applied after the quanta are counted so the
   noise is correlated as in a real II;
6. veiling glare and vignetting (the fluoroscope's existing fields);
7. video: a logarithmic amplifier between a black and a white level (gain and offset), camera
   noise in grey levels, 8-bit quantisation (:func:`video_u8`).

Images are ``(H, W)`` float arrays indexed ``[row, col]``, relative to the unattenuated beam;
``fov`` is the ``(H, W)`` bool mask of the circular field of view (outside it the image is 0).
:func:`form_image` computes on the field's bounding box (:func:`field_box`) and pastes the
result into the frame: every stage's input is 0 outside the field, so nothing changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

__all__ = [
    "FWHM_TO_SIGMA",
    "SCATTERER_TRANSMISSION",
    "focal_spot_sigma_px",
    "mtf_sigma_px",
    "gaussian_mtf",
    "blur",
    "wide_blur",
    "wide_blur_reference",
    "add_scatter",
    "abc_photons",
    "quantum_noise",
    "video_u8",
    "field_box",
    "form_image",
]

SCATTERER_TRANSMISSION = 0.95
"""A pixel's ray crossed a scattering medium when its primary transmission is below this."""
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # sigma of a Gaussian per FWHM


def focal_spot_sigma_px(focal_spot_mm: float, magnification: float, pixel_mm: float) -> float:
    """Gaussian sigma (px, input plane) of the focal-spot penumbra of a body at ``magnification``.

    The nominal focal spot is taken as the FWHM of a Gaussian source; a body at magnification
    ``M = SID / source-to-body`` is blurred at the input plane by ``focal_spot_mm * (M - 1)``
    (FWHM, mm), i.e. sigma ``= focal_spot_mm * (M - 1) / 2.355 / pixel_mm`` px.
    """
    if focal_spot_mm < 0 or not np.isfinite(focal_spot_mm):
        raise ValueError(f"focal_spot_mm must be finite and >= 0, got {focal_spot_mm}")
    if not magnification >= 1.0:
        raise ValueError(f"magnification must be >= 1 (the body lies between source and "
                         f"detector), got {magnification}")
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be > 0, got {pixel_mm}")
    return focal_spot_mm * (magnification - 1.0) * FWHM_TO_SIGMA / pixel_mm


def mtf_sigma_px(mtf50_lp_per_mm: float, pixel_mm: float) -> float:
    """Gaussian sigma (px) of a blur whose MTF is 0.5 at ``mtf50_lp_per_mm`` (input plane).

    A Gaussian line spread of sigma ``s`` mm has ``MTF(f) = exp(-2 pi^2 s^2 f^2)``; solving
    ``MTF(f50) = 0.5`` gives ``s = sqrt(ln 2 / 2) / (pi f50)``. ``mtf50_lp_per_mm = 0`` means
    no blur (sigma 0).
    """
    if mtf50_lp_per_mm < 0 or not np.isfinite(mtf50_lp_per_mm):
        raise ValueError(f"mtf50_lp_per_mm must be finite and >= 0, got {mtf50_lp_per_mm}")
    if mtf50_lp_per_mm == 0:
        return 0.0
    return math.sqrt(math.log(2.0) / 2.0) / (math.pi * mtf50_lp_per_mm) / pixel_mm


def gaussian_mtf(freq_lp_per_mm, sigma_mm: float) -> np.ndarray:
    """MTF of a Gaussian line spread of ``sigma_mm`` at frequencies ``freq_lp_per_mm``."""
    f = np.asarray(freq_lp_per_mm, dtype=np.float64)
    return np.exp(-2.0 * math.pi**2 * sigma_mm**2 * f**2)


def _gaussian(img: np.ndarray, sigma_px: float, border: int) -> np.ndarray:
    """OpenCV's separable Gaussian with scipy.ndimage's kernel (radius ``int(4 sigma +
    0.5)``): equal to ``gaussian_filter(img, sigma_px, mode=...)`` to rounding (``nearest``
    is BORDER_REPLICATE, ``constant`` BORDER_CONSTANT), 2-10x faster; compared in
    ``tests/testbed/test_detector.py``."""
    r = int(4.0 * sigma_px + 0.5)
    return cv2.GaussianBlur(img, (2 * r + 1, 2 * r + 1), sigmaX=sigma_px, sigmaY=sigma_px,
                            borderType=border)


def blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of ``img`` (H, W) with ``sigma_px``; 0 returns a copy.

    The image continues at its edge value (``mode="nearest"``); the caller zeroes what lies
    outside the field of view afterwards. ``scipy.ndimage.gaussian_filter(img, sigma_px,
    mode="nearest")`` is the reference.
    """
    img = np.asarray(img, dtype=np.float64)
    if sigma_px <= 0:
        return img.copy()
    return _gaussian(img, sigma_px, cv2.BORDER_REPLICATE)


def _coarsening(sigma_px: float) -> int:
    """The factor of the coarse grid of a wide blur: ``sigma / 8``, between 1 and 4."""
    return int(np.clip(sigma_px // 8, 1, 4))


def _block_mean(img: np.ndarray, f: int, *, fast: bool = False) -> np.ndarray:
    """Means of ``f`` x ``f`` blocks of ``img`` (H, W), zero-padded to whole blocks.
    ``fast``: OpenCV's area resize, which for a whole factor is the block mean (to rounding;
    the numpy reshape is the reference)."""
    H, W = img.shape
    h, w = -(-H // f), -(-W // f)
    if (h * f, w * f) == (H, W):
        pad = np.ascontiguousarray(img, dtype=np.float64)
    else:
        pad = np.zeros((h * f, w * f))
        pad[:H, :W] = img
    if fast:
        return cv2.resize(pad, (w, h), interpolation=cv2.INTER_AREA)
    return pad.reshape(h, f, w, f).mean(axis=(1, 3))


_BAND_MATRICES: dict = {}


def _gaussian_matrix(n: int, sigma_px: float) -> np.ndarray:
    """``(n, n)`` matrix of a 1-D Gaussian of ``sigma_px`` over ``n`` samples, zero beyond the
    ends: OpenCV's kernel (radius ``int(4 sigma + 0.5)``, normalised over its taps) in each
    band; remembered for the last few sizes, read-only."""
    key = (n, float(sigma_px))
    if key not in _BAND_MATRICES:
        if len(_BAND_MATRICES) >= 16:
            _BAND_MATRICES.pop(next(iter(_BAND_MATRICES)))
        r = int(4.0 * sigma_px + 0.5)
        taps = cv2.getGaussianKernel(2 * r + 1, sigma_px, cv2.CV_64F).ravel()
        offset = np.arange(n)[None, :] - np.arange(n)[:, None]      # column - row
        m = np.where(np.abs(offset) <= r, taps[np.clip(offset + r, 0, 2 * r)], 0.0)
        m.flags.writeable = False
        _BAND_MATRICES[key] = m
    return _BAND_MATRICES[key]


def _gaussian_small(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """``_gaussian(img, sigma_px, cv2.BORDER_CONSTANT)`` of a small image with a wide kernel
    as two products with banded matrices (BLAS): equal to it to ~1e-15 relative and 3-6x
    faster where the kernel spans much of the image (OpenCV's double-precision filter
    has no vector path); compared in ``tests/testbed/test_detector.py``."""
    h, w = img.shape
    return _gaussian_matrix(h, sigma_px) @ img @ _gaussian_matrix(w, sigma_px).T


def wide_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur (zero outside the image) of a wide kernel, computed on a grid coarser by
    ``sigma / 8`` (at most 4x) and interpolated back (the result is smooth at that scale).

    ``scipy.ndimage.gaussian_filter(img, sigma_px, mode="constant")`` is the reference;
    :func:`wide_blur_reference` is this function's arithmetic in scipy (compared in tests).
    """
    img = np.asarray(img, dtype=np.float64)
    f = _coarsening(sigma_px)
    if f == 1:
        return _gaussian(img, sigma_px, cv2.BORDER_CONSTANT)
    H, W = img.shape
    return _wide_blur_of_blocks(_block_mean(img, f, fast=True), sigma_px, f, (H, W))


def _wide_blur_of_blocks(blocks: np.ndarray, sigma_px: float, f: int, shape) -> np.ndarray:
    """:func:`wide_blur`'s steps after its block mean ``blocks`` (``f > 1``) of an image of
    ``shape``: the coarse blur and the interpolation back."""
    H, W = shape
    small = _gaussian_small(blocks, sigma_px / f)
    h, w = small.shape
    # back to full resolution: small pixel (i, j) is centred at full (f i + (f-1)/2, ...),
    # OpenCV's pixel-centre convention for a resize by f; bilinear, edges held
    return cv2.resize(small, (w * f, h * f), interpolation=cv2.INTER_LINEAR)[:H, :W]


_MTF_REPLICA_OK: dict = {}


def _mtf_taps(sigma_px: float) -> np.ndarray | None:
    """The 5 taps of :func:`blur`'s kernel (OpenCV's), or None for another kernel size."""
    if not sigma_px > 0 or int(4.0 * sigma_px + 0.5) != 2:
        return None
    return cv2.getGaussianKernel(5, sigma_px, cv2.CV_64F).ravel()


def _mtf_blur_in_field(img: np.ndarray, sigma_px: float, spans: np.ndarray, f: int
                       ) -> tuple[np.ndarray, np.ndarray | None]:
    """``blur(img, sigma_px)`` times the field (one run per row, ``spans``), and for ``f >=
    2`` its ``_block_mean(.., f, fast=True)`` (else None): one compiled pass
    (:func:`testbed._detector_numba.mtf_blur_runs`, a replica of OpenCV's arithmetic) when
    the replica equals OpenCV for this shape, kernel and factor in this process (checked
    once on random values); else OpenCV's calls, the reference."""
    from testbed._detector_numba import mtf_blur_runs, zero_outside_runs

    taps = _mtf_taps(sigma_px)
    key = (img.shape, float(sigma_px), int(f))
    if taps is not None and key not in _MTF_REPLICA_OK:
        if len(_MTF_REPLICA_OK) >= 64:
            _MTF_REPLICA_OK.pop(next(iter(_MTF_REPLICA_OK)))
        _MTF_REPLICA_OK[key] = _mtf_replica_check(img.shape, sigma_px, spans, f, taps)
    if taps is not None and _MTF_REPLICA_OK[key]:
        out, blocks = mtf_blur_runs(np.ascontiguousarray(img, dtype=np.float64), taps,
                                    spans, int(f))
        return out, (blocks if f >= 2 else None)
    out = blur(img, sigma_px)
    zero_outside_runs(out, spans)
    return out, (_block_mean(out, f, fast=True) if f >= 2 else None)


def _mtf_replica_check(shape, sigma_px: float, spans: np.ndarray, f: int,
                       taps: np.ndarray) -> bool:
    """Whether :func:`testbed._detector_numba.mtf_blur_runs` equals OpenCV's blur and area
    resize bit for bit on random values of ``shape`` (values of widely different scales)."""
    from testbed._detector_numba import mtf_blur_runs, zero_outside_runs

    rng = np.random.default_rng(20261127)
    img = rng.uniform(0.0, 2.0, shape) * 10.0 ** rng.uniform(-3.0, 3.0, shape)
    ref = blur(img, sigma_px)
    zero_outside_runs(ref, spans)
    out, blocks = mtf_blur_runs(img, taps, spans, int(f))
    ok = np.array_equal(out, ref)
    if f >= 2:
        ok = ok and np.array_equal(blocks, _block_mean(ref, f, fast=True))
    return bool(ok)


class WideBlurUpdate:
    """:func:`wide_blur` of images that differ from a fixed ``base`` (H, W) only in a window:
    the blur is linear, so its coarse grid is the base's plus the coarse blur of the
    window's change (two small matrix products), and only the interpolation back to full
    resolution is redone. Equal to :func:`wide_blur` of the whole image to rounding (~1e-16
    relative; compared in tests). A sweep frame's rod changes a few blocks of the scatter
    source, whose 80 px blur otherwise costs a block mean and two products over the whole
    field per frame."""

    def __init__(self, base: np.ndarray, sigma_px: float):
        self.base = np.array(base, dtype=np.float64)
        self.sigma = float(sigma_px)
        self.f = f = _coarsening(self.sigma)
        H, W = self.base.shape
        self.shape = (H, W)
        if f > 1:
            small_in = _block_mean(self.base, f, fast=True)
            h, w = small_in.shape
            self._gh = _gaussian_matrix(h, self.sigma / f)
            self._gw = _gaussian_matrix(w, self.sigma / f)
            self._small0 = self._gh @ small_in @ self._gw.T

    def blur(self, img: np.ndarray, window: tuple[slice, slice] | None) -> np.ndarray:
        """:func:`wide_blur` of ``img``, which equals ``base`` outside ``window`` (None: it
        equals ``base``)."""
        f = self.f
        if f == 1:
            return wide_blur(img, self.sigma)
        H, W = self.shape
        small = self._small0
        if window is not None:
            r0, r1 = window[0].start // f, -(-window[0].stop // f)     # whole blocks
            c0, c1 = window[1].start // f, -(-window[1].stop // f)
            rows = slice(r0 * f, min(r1 * f, H))
            cols = slice(c0 * f, min(c1 * f, W))
            change = np.zeros(((r1 - r0) * f, (c1 - c0) * f))
            d = img[rows, cols] - self.base[rows, cols]
            change[:d.shape[0], :d.shape[1]] = d
            coarse = change.reshape(r1 - r0, f, c1 - c0, f).mean(axis=(1, 3))
            small = small + self._gh[:, r0:r1] @ coarse @ self._gw[:, c0:c1].T
        h, w = small.shape
        return cv2.resize(small, (w * f, h * f), interpolation=cv2.INTER_LINEAR)[:H, :W]


def wide_blur_reference(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """:func:`wide_blur` in scipy.ndimage (Gaussian filters and ``map_coordinates``)."""
    img = np.asarray(img, dtype=np.float64)
    f = _coarsening(sigma_px)
    if f == 1:
        return gaussian_filter(img, sigma_px, mode="constant")
    H, W = img.shape
    small = gaussian_filter(_block_mean(img, f), sigma_px / f, mode="constant")
    rows = (np.arange(H) - (f - 1) / 2) / f
    cols = (np.arange(W) - (f - 1) / 2) / f
    return map_coordinates(small, np.meshgrid(rows, cols, indexing="ij"), order=1,
                           mode="nearest")


_FOV_ENTRIES: dict = {}


def _fov_entry(fov: np.ndarray) -> dict:
    """What the chain derives from a field-of-view mask, remembered by the mask's content for
    the last 16 masks (every frame of a C-arm has the same field): ``"inside"``, the mask as
    1.0 / 0.0 (a product with it zeroes the outside, faster than indexing), and whatever
    :func:`_field_weight` and :func:`_field` add; arrays read-only."""
    fov = np.ascontiguousarray(fov, dtype=bool)
    key = (fov.shape, hash(fov.tobytes()))
    if key not in _FOV_ENTRIES:
        if len(_FOV_ENTRIES) >= 16:
            _FOV_ENTRIES.pop(next(iter(_FOV_ENTRIES)))
        inside = fov.astype(np.float64)
        inside.flags.writeable = False
        _FOV_ENTRIES[key] = {"inside": inside}
    return _FOV_ENTRIES[key]


def _derived(entry: dict, key, make):
    """``entry[key]``, made by ``make()`` when missing; an entry keeps its 16 newest derived
    items (a study's C-arms may share one mask, each with its own radius map)."""
    if key not in entry:
        if len(entry) > 16:
            entry.pop(next(k for k in entry if k != "inside"))
        entry[key] = make()
    return entry[key]


def _field_weight(fov: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """For :func:`add_scatter`: ``wide_blur(fov, sigma_px)`` with ``inf`` where it is at most
    1e-6 (so that a division by it gives exactly 0 there), and the field as 1.0 / 0.0."""
    entry = _fov_entry(fov)

    def make():
        den = wide_blur(entry["inside"], sigma_px)
        den[den <= 1e-6] = np.inf
        den.flags.writeable = False
        return den

    return _derived(entry, ("scatter", float(sigma_px)), make), entry["inside"]


#: the chain runs on the field's bounding box grown by this margin (at least one zero row and
#: column around the field for the edge-replicating blurs, and more than half a coarse block
#: for the wide blurs' interpolation back to full resolution) ...
CROP_PAD_PX = 8
#: ... with its first row and column on multiples of this (a multiple of every coarse-grid
#: factor of :func:`wide_blur`, 1 to 4), so that the block means fall on the full frame's grid
CROP_ALIGN_PX = 12


def _crop_box(fov: np.ndarray) -> tuple[slice, slice]:
    """The box (rows, columns) on which :func:`form_image` computes: every pixel of ``fov``,
    :data:`CROP_PAD_PX` around it, starts and lengths multiples of :data:`CROP_ALIGN_PX`,
    clipped to the frame. Outside the field every stage's input is 0 and stays 0 beyond the
    box, so each stage on the box equals the whole frame's there (compared in tests)."""
    H, W = fov.shape
    rows, cols = np.flatnonzero(fov.any(axis=1)), np.flatnonzero(fov.any(axis=0))
    if not len(rows):
        return slice(0, H), slice(0, W)

    def span(idx, n):     # whole coarse blocks where the frame allows (no padding copies)
        lo = max(int(idx[0]) - CROP_PAD_PX, 0) // CROP_ALIGN_PX * CROP_ALIGN_PX
        hi = int(idx[-1]) + 1 + CROP_PAD_PX
        return slice(lo, min(lo - (lo - hi) // CROP_ALIGN_PX * CROP_ALIGN_PX, n))

    return span(rows, H), span(cols, W)


@dataclass(frozen=True)
class _Field:
    """Per field of view (and vignetting), for :func:`form_image`, on the box the chain
    computes on (:func:`_crop_box`, or the whole frame): the mask, the mask as 1.0 / 0.0, the
    vignetting factor (0 outside), the field's pixel count, the scatter weights by sigma
    (:func:`_field_weight` of the box's mask), and the mask's row spans
    (:func:`testbed._detector_numba.row_spans`; ``runs``: each row's field pixels fill its
    span, as in a disc)."""

    box: tuple[slice, slice]
    whole: bool                # the box is the whole frame
    fov: np.ndarray
    inside: np.ndarray
    vignetting: np.ndarray
    n: int
    rho: np.ndarray            # held, so that its id (the cache key) stays its own
    weights: dict
    spans: np.ndarray          # per row, the field's first column and one past its last
    runs: bool                 # every row's field is the whole of its span

    def scatter_weight(self, sigma_px: float) -> np.ndarray:
        key = float(sigma_px)
        if key not in self.weights:
            self.weights[key] = _field_weight(self.fov, sigma_px)[0]
        return self.weights[key]


def _field(fov: np.ndarray, rho: np.ndarray, vignetting: float, *, crop: bool = True
           ) -> _Field:
    """The :class:`_Field` of ``fov`` and ``rho`` (the same arrays for every frame of a
    C-arm: kept with the mask's entry, by the radius map's identity)."""
    entry = _fov_entry(fov)

    def make():
        mask = np.asarray(fov, dtype=bool)
        H, W = mask.shape
        box = _crop_box(mask) if crop else (slice(0, H), slice(0, W))
        whole = (box[0].stop - box[0].start, box[1].stop - box[1].start) == (H, W)
        vig = np.zeros(mask.shape)
        vig[mask] = 1.0 - vignetting * np.asarray(rho, dtype=np.float64)[mask] ** 2
        if whole:
            sub, inside = mask, entry["inside"]
        else:
            sub, inside = np.ascontiguousarray(mask[box]), np.ascontiguousarray(
                entry["inside"][box])
            vig = np.ascontiguousarray(vig[box])
        from testbed._detector_numba import row_spans

        sub = np.ascontiguousarray(sub)
        spans = row_spans(sub)
        n = int(np.count_nonzero(sub))
        runs = n == int((spans[:, 1] - spans[:, 0]).sum())
        for a in (sub, inside, vig, spans):
            a.flags.writeable = False
        return _Field(box, whole, sub, inside, vig, n, rho, {}, spans, runs)

    return _derived(entry, ("vignetting", id(rho), float(vignetting), bool(crop)), make)


def add_scatter(primary: np.ndarray, fov: np.ndarray, *, spr: float, sigma_px: float,
                scatterer: np.ndarray | None = None) -> np.ndarray:
    """Primary plus scatter: ``P + spr * lowpass(P * scatterer)`` inside ``fov`` (H, W) bool.

    ``lowpass`` is a Gaussian of ``sigma_px`` normalised over the field of view
    (``G * (P m) / G * fov``, ``m`` the ``scatterer`` mask, default the whole field), so a
    uniform primary behind a scattering medium gets exactly ``spr * P`` of scatter, also near
    the field's edge (a convolution model of scatter, after Love and Kruger, Med. Phys. 14(2),
    1987). Behind a dense body ``S / P`` exceeds ``spr``, as measured; where nothing scatters
    (an empty beam) there is none. ``spr = 0`` returns the primary.
    """
    _check_spr(spr)
    if spr == 0:
        return np.where(fov, np.asarray(primary, dtype=np.float64), 0.0)
    den, inside = _field_weight(fov, sigma_px)
    p = np.array(primary, dtype=np.float64)
    p *= inside
    src = p if scatterer is None else np.where(scatterer, p, 0.0)
    low = wide_blur(src, sigma_px)
    # in place, with the same roundings as p + spr * (num / den) (0 where den <= 1e-6)
    np.divide(low, den, out=low)
    low *= spr
    low += p
    low *= inside
    return low


def _check_spr(spr: float) -> None:
    if spr < 0 or not np.isfinite(spr):
        raise ValueError(f"scatter_to_primary must be finite and >= 0, got {spr}")


def _median(values: np.ndarray) -> float:
    """``np.median(values)`` (the same number), partitioning one rank instead of two: for an
    even count the lower middle value is the largest below the upper one. Reorders
    ``values``. Of many values, only those in a band around a subsample's median are
    partitioned (:func:`_median_banded`; 4x faster on a frame's field)."""
    n = len(values)
    if n == 0:
        return float("nan")
    if n >= _BANDED_MEDIAN_FROM:
        med = _median_banded(values)
        if med is not None:
            return med
    k = n // 2
    values.partition(k)
    upper = values[k]
    if n % 2:
        return float(upper)
    return float((values[:k].max() + upper) / 2.0)


#: from this many values :func:`_median` first tries :func:`_median_banded`
_BANDED_MEDIAN_FROM = 4096
#: the subsample's stride, and the band's half width in standard errors of its median's rank
_BANDED_STRIDE = 16
_BANDED_Z = 6.0


def _median_banded(values: np.ndarray) -> float | None:
    """``np.median(values)`` from the values between two ranks of a strided subsample that
    bracket the median with a margin of :data:`_BANDED_Z` standard errors: one compiled pass
    counts those below the band and gathers those in it, and only the band is partitioned
    (the same ranks, so the same number). None when the band misses a middle rank (about
    never) or the values hold NaNs: the caller then partitions them all."""
    from testbed._detector_numba import band_of

    n = len(values)
    sample = values[::_BANDED_STRIDE].copy()
    m = len(sample)
    half = int(_BANDED_Z * 0.5 * np.sqrt(m)) + 2
    k_lo, k_hi = max(m // 2 - half, 0), min(m // 2 + half, m - 1)
    sample.partition((k_lo, k_hi))
    lo, hi = float(sample[k_lo]), float(sample[k_hi])
    below, band, nans = band_of(np.ascontiguousarray(values, dtype=np.float64), lo, hi)
    k = n // 2
    ranks = (k,) if n % 2 else (k - 1, k)
    if nans or below > ranks[0] or below + len(band) <= ranks[-1]:
        return None
    at = [r - below for r in ranks]
    band.partition(at)
    if n % 2:
        return float(band[at[0]])
    return float((band[at[0]] + band[at[1]]) / 2.0)


def abc_photons(fluence: np.ndarray, fov: np.ndarray, target_photons: float, *,
                field_values: np.ndarray | None = None) -> float:
    """Photons per pixel of the unattenuated beam that automatic brightness control sets so
    that the median detected count in ``fov`` equals ``target_photons``.

    ``fluence`` (H, W): detected fluence relative to the unattenuated beam;
    ``field_values``: ``fluence[fov]`` when the caller has them (reordered here).
    """
    values = fluence[fov] if field_values is None else field_values
    med = _median(values) if len(values) else 0.0
    if not med > 0:
        raise ValueError("automatic brightness control: no X-rays reach the field of view")
    return target_photons / med


#: a pixel expecting fewer quanta than this is counted exactly (numpy's Poisson sampler); above
#: it the count comes from the normal law corrected to the Poisson's first three moments (mean
#: and variance ``lam``, third central moment ``lam``: the Cornish-Fisher term
#: ``(z**2 - 1) / 6``), rounded: 3x faster than numpy's sampler, and 0.08 % from the Poisson's
#: probabilities in total variation at 30 quanta, 0.015 % at the clinic's median of 150 (the
#: plain normal law: 2.3 % and 1.0 %); tests/testbed/test_detector.py samples both laws
POISSON_EXACT_BELOW = 30.0


def quantum_noise(fluence: np.ndarray, photons: float, rng, *, exact: bool = False
                  ) -> np.ndarray:
    """Quantum counts of ``photons * fluence`` per pixel, back in units of the beam.

    ``exact=True`` draws every count from numpy's Poisson sampler (the reference); the
    default draws counts of at least :data:`POISSON_EXACT_BELOW` expected quanta from the
    moment-matched normal approximation and the rest exactly.
    """
    if not photons > 0:
        raise ValueError(f"photons per pixel must be > 0, got {photons}")
    rng = np.random.default_rng(rng)
    lam = np.maximum(fluence, 0.0)
    lam *= photons
    if exact:
        counts = rng.poisson(lam)
        return np.divide(counts, photons, out=lam)
    z = rng.standard_normal(lam.shape)
    k = np.sqrt(lam)
    k *= z
    k += lam
    z *= z                                # the skewness term (z^2 - 1) / 6
    z -= 1.0
    z *= 1.0 / 6.0
    k += z
    np.rint(k, out=k)
    np.maximum(k, 0.0, out=k)
    low = lam < POISSON_EXACT_BELOW
    if low.any():
        k[low] = rng.poisson(lam[low])
    k /= photons
    return k


def _with_pcg(rng, kernel, *args):
    """``kernel(*args, source)`` drawing its normals from the Generator ``rng``: inline from
    its PCG64 state when it has one (:func:`testbed._detector_numba.pcg_state`, the same
    numbers, 20 % faster), the state given back to ``rng`` after; else from ``rng``."""
    from testbed._detector_numba import pcg_state, set_pcg_state

    state = pcg_state(rng)
    if state is None:
        return kernel(*args, rng)
    out = kernel(*args, state)
    set_pcg_state(rng, state)
    return out


def _quantum_noise_in_field(img: np.ndarray, fov: np.ndarray, photons: float, rng, *,
                            field: _Field | None = None) -> None:
    """``img[fov] = quantum_noise(img[fov], photons, rng)`` in place, compiled
    (:func:`testbed._detector_numba.quantum_counts`, or ``quantum_counts_runs`` when
    ``field``, the :class:`_Field` of ``fov``, is one run per row): the same draws in the
    same order, the same numbers, without gathering the field's pixels."""
    from testbed._detector_numba import quantum_counts, quantum_counts_runs

    if not photons > 0:
        raise ValueError(f"photons per pixel must be > 0, got {photons}")
    rng = np.random.default_rng(rng)
    if field is not None and field.runs:        # one run of field pixels per row
        idx, lam = _with_pcg(rng, quantum_counts_runs, img, field.spans, field.n,
                             float(photons), POISSON_EXACT_BELOW)
    else:
        idx, lam = _with_pcg(rng, quantum_counts, img, np.ascontiguousarray(fov, dtype=bool),
                             float(photons), POISSON_EXACT_BELOW)
    if len(idx):
        img.flat[idx] = rng.poisson(lam) / photons


def video_u8(intensity: np.ndarray, fov: np.ndarray, *, black_u8: int, white_u8: int,
             display_range: float, noise_u8: float = 0.0, rng=None,
             reference: bool = False) -> np.ndarray:
    """8-bit video of ``intensity`` (relative to the unattenuated beam; (H, W)).

    Logarithmic amplifier: ``level = 1 + ln(I) / display_range`` clipped to [0, 1], mapped to
    ``black_u8 + (white_u8 - black_u8) * level`` (offset and gain), plus Gaussian camera noise
    of ``noise_u8`` grey levels, rounded and clipped to 0..255; 0 outside ``fov``. Compiled
    (:func:`testbed._detector_numba.video`, the same draws); ``reference=True`` runs the
    numpy code below (compared in tests).
    """
    if not reference:
        log_img = np.maximum(intensity, 1e-12, dtype=np.float64)
        np.log(log_img, out=log_img)
        return _video_of_log(log_img, fov, black_u8=black_u8, white_u8=white_u8,
                             display_range=display_range, noise_u8=noise_u8, rng=rng)
    fov = np.asarray(fov, dtype=bool)
    inside = np.asarray(intensity, dtype=np.float64)[fov]
    level = 1.0 + np.log(np.maximum(inside, 1e-12)) / display_range
    video = black_u8 + (white_u8 - black_u8) * np.clip(level, 0.0, 1.0)
    if noise_u8 > 0:   # one draw per pixel of the field
        noise = np.random.default_rng(rng).standard_normal(video.shape)
        noise *= noise_u8
        video += noise
    out = np.zeros(fov.shape, dtype=np.uint8)
    out[fov] = np.clip(np.rint(video), 0, 255)
    return out


def _video_of_log(log_img: np.ndarray, fov: np.ndarray, *, black_u8: int, white_u8: int,
                  display_range: float, noise_u8: float, rng) -> np.ndarray:
    """:func:`video_u8`'s compiled path from ``log_img``, the logarithm of the intensity
    floored at 1e-12 (:func:`testbed._detector_numba.video`)."""
    from testbed._detector_numba import video

    return _with_pcg(np.random.default_rng(rng), video, log_img,
                     np.ascontiguousarray(fov, dtype=bool), int(black_u8), int(white_u8),
                     float(display_range), float(noise_u8))


def field_box(fov: np.ndarray, rho: np.ndarray, vignetting: float) -> tuple[slice, slice]:
    """The box (rows, columns) of the frame on which :func:`form_image` computes for this
    field (``crop=True``); a transmission given on it is taken as such."""
    return _field(fov, rho, vignetting).box


def form_image(transmission: np.ndarray, fov: np.ndarray, rho: np.ndarray, fluoro, *,
               magnification: float, noise: bool, rng=None, exact_noise: bool = False,
               reference: bool = False, crop: bool = True, intensity: bool = True
               ) -> tuple[np.ndarray | None, np.ndarray]:
    """The whole chain from primary transmission to the 8-bit frame.

    Parameters
    ----------
    transmission : (H, W) float, or on the box of :func:`field_box` (with ``crop``)
        Primary transmission ``exp(-integral mu)`` per pixel (0 outside ``fov``).
    fov : (H, W) bool
        The circular field of view.
    rho : (H, W) float
        Radius on the input plane over the field's radius (for vignetting).
    fluoro : testbed.fluoroscope.FluoroscopeSpec
        The fields ``focal_spot_mm``, ``scatter_to_primary``, ``scatter_sigma_mm``,
        ``photons_per_pixel``, ``abc_photons_per_pixel``, ``mtf50_lp_per_mm``,
        ``glare_fraction``, ``glare_sigma_px``, ``vignetting``, ``display_range``,
        ``black_u8``, ``white_u8``, ``video_noise_u8``, ``pixel_mm``, ``quantum_sampler``.
    magnification : float
        SID over the source-to-bone distance (for the focal-spot blur).
    noise : bool
        Quantum and camera noise on or off.
    rng : numpy Generator, int or None
    exact_noise : bool
        Every quantum count from numpy's Poisson sampler (the reference of
        :func:`quantum_noise`'s fast sampler), as ``fluoro.quantum_sampler = "exact"``.
    reference : bool
        The per-pixel stages in numpy instead of compiled (the same draws and numbers; the
        compiled ones are compared with them in tests).
    crop : bool
        Compute on the field's bounding box (:func:`_crop_box`; outside the field every
        stage's input is 0, so the frame is the whole frame's, compared in tests);
        ``False``: on the whole frame.
    intensity : bool
        ``False``: the intensity is not returned (None; the frame's video only).

    Returns ``(intensity (H, W) float64, video (H, W) uint8)``.
    """
    rng = np.random.default_rng(rng)
    field = _field(fov, rho, fluoro.vignetting, crop=crop)
    trans = np.asarray(transmission, dtype=np.float64)
    if trans.shape != np.shape(fov):
        if trans.shape != field.inside.shape:
            raise ValueError(f"transmission: shape {trans.shape}, expected the frame's "
                             f"{np.shape(fov)} or the field's box {field.inside.shape}")
    else:
        trans = trans[field.box]
    img, video = _chain(trans, field, fluoro, magnification=magnification, noise=noise,
                        rng=rng, exact_noise=exact_noise, reference=reference)
    if field.whole:
        return (img if intensity else None), video
    full = None
    if intensity:
        full = np.zeros(np.shape(fov))
        full[field.box] = img
    full_video = np.zeros(np.shape(fov), dtype=np.uint8)
    full_video[field.box] = video
    return full, full_video


def _chain(trans: np.ndarray, field: _Field, fluoro, *, magnification: float, noise: bool,
           rng, exact_noise: bool, reference: bool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`form_image` on the box of ``field`` (``trans`` is the box's transmission)."""
    fov = field.fov
    if reference:
        img = np.array(trans, dtype=np.float64)
        img *= field.inside
        scatterer = fov & (img < SCATTERER_TRANSMISSION)
        img = blur(img, focal_spot_sigma_px(fluoro.focal_spot_mm, magnification,
                                            float(fluoro.pixel_mm)))
    elif fluoro.scatter_to_primary > 0:
        p, src = _sources(trans, fov, fluoro, magnification)
        return _after_sources(p, src, field, fluoro, noise=noise, rng=rng,
                              exact_noise=exact_noise)
    else:
        img, scatterer = _primary(trans, fov, fluoro, magnification)
    img = add_scatter(img, fov, spr=fluoro.scatter_to_primary,
                      sigma_px=fluoro.scatter_sigma_mm / float(fluoro.pixel_mm),
                      scatterer=scatterer)
    return _after_scatter(img, None, field, fluoro, noise=noise, rng=rng,
                          exact_noise=exact_noise, reference=reference)


def _focal_radius_px(fluoro, magnification: float) -> int:
    """The focal-spot blur's kernel radius (px; 0 without blur)."""
    sigma = focal_spot_sigma_px(fluoro.focal_spot_mm, magnification, float(fluoro.pixel_mm))
    return int(4.0 * sigma + 0.5) if sigma > 0 else 0


def _primary(trans: np.ndarray, fov: np.ndarray, fluoro, magnification: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """The compiled chain's first stages: the transmission masked to ``fov``, blurred by the
    focal spot, and the scatterers (``fov`` and the unblurred transmission below
    :data:`SCATTERER_TRANSMISSION`)."""
    from testbed._detector_numba import masked_transmission

    img, scatterer = masked_transmission(np.ascontiguousarray(trans),
                                         np.ascontiguousarray(fov), SCATTERER_TRANSMISSION)
    img = blur(img, focal_spot_sigma_px(fluoro.focal_spot_mm, magnification,
                                        float(fluoro.pixel_mm)))
    return img, scatterer


def _sources(trans: np.ndarray, fov: np.ndarray, fluoro, magnification: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """The compiled chain's stages before the scatter's wide blur, on the box ``fov`` covers
    (or on a window of it): :func:`_primary` split into ``(p, src)``, the primary in the
    field and the scatter source. Each pixel depends only on the transmission within
    :func:`_focal_radius_px` of it (what :class:`testbed.fluoroscope.SweepRenderer` uses to
    redo only the rod's neighbourhood)."""
    from testbed._detector_numba import scatter_source

    fov = np.ascontiguousarray(fov)
    img, scatterer = _primary(trans, fov, fluoro, magnification)
    return scatter_source(img, fov, scatterer)


def _after_sources(p: np.ndarray, src: np.ndarray, field: _Field, fluoro, *, noise: bool,
                   rng, exact_noise: bool = False, low: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The compiled chain from the scatter sources (:func:`_sources`, ``scatter_to_primary >
    0``) to ``(intensity, video)`` on the box; ``low``: the scatter source's wide blur when
    the caller has it (:class:`WideBlurUpdate`; written into)."""
    from testbed._detector_numba import add_scatter_field, add_scatter_spans

    _check_spr(fluoro.scatter_to_primary)
    sigma = fluoro.scatter_sigma_mm / float(fluoro.pixel_mm)
    if low is None:
        low = wide_blur(src, sigma)
    if field.runs:       # one run of field pixels per row: vectorised
        values = add_scatter_spans(low, field.scatter_weight(sigma),
                                   float(fluoro.scatter_to_primary), p, field.spans, field.n)
    else:
        values = add_scatter_field(low, field.scatter_weight(sigma),
                                   float(fluoro.scatter_to_primary), p, field.fov, field.n)
    return _after_scatter(low, values, field, fluoro, noise=noise, rng=rng,
                          exact_noise=exact_noise, reference=False)


def _after_scatter(img: np.ndarray, values, field: _Field, fluoro, *, noise: bool, rng,
                   exact_noise: bool, reference: bool) -> tuple[np.ndarray, np.ndarray]:
    """The chain from primary plus scatter (``img`` on the box; ``values``: its field values
    in row-major order, or None) to ``(intensity, video)``."""
    px = float(fluoro.pixel_mm)
    fov = field.fov
    # the quanta and the camera each draw from a stream of their own (children of ``rng``'s
    # seed, which is not drawn from): how many Poisson draws the quanta take depends on the
    # image, and a source that changes the image (scatter, blur, the photons) must not
    # redraw the camera's noise, nor the next frame's (the error budget compares
    # configurations that differ by one source only); a frame without noise draws nothing
    quanta_rng, camera_rng = _frame_streams(rng) if noise else (rng, rng)
    if noise:
        if fluoro.abc_photons_per_pixel > 0:
            n0 = abc_photons(img, fov, fluoro.abc_photons_per_pixel, field_values=values)
        else:
            n0 = fluoro.photons_per_pixel
        exact = exact_noise or getattr(fluoro, "quantum_sampler", "fast") == "exact"
        if exact or reference:
            img[fov] = quantum_noise(img[fov], n0, quanta_rng, exact=exact)
        else:
            _quantum_noise_in_field(img, fov, n0, quanta_rng, field=field)
    g = float(fluoro.glare_fraction)
    sigma = mtf_sigma_px(fluoro.mtf50_lp_per_mm, px)
    f = _coarsening(fluoro.glare_sigma_px) if g > 0 else 1
    blocks = None
    if field.runs and not reference and sigma > 0:
        # the MTF blur, the same product outside the runs only, and the glare's block mean
        # in one pass
        img, blocks = _mtf_blur_in_field(img, sigma, field.spans, f if f > 1 else 0)
    elif field.runs and not reference:
        from testbed._detector_numba import zero_outside_runs

        img = blur(img, sigma)
        zero_outside_runs(img, field.spans)
    else:
        img = blur(img, sigma)
        img *= field.inside
    noise_u8 = fluoro.video_noise_u8 if noise else 0.0
    if reference:
        if g > 0:
            glare = wide_blur(img, fluoro.glare_sigma_px)
            glare *= g
            img *= 1.0 - g
            img += glare
        img *= field.vignetting          # 1 - v rho^2 in the field, 0 outside
        video = video_u8(img, fov, black_u8=fluoro.black_u8, white_u8=fluoro.white_u8,
                         display_range=fluoro.display_range, noise_u8=noise_u8,
                         rng=camera_rng, reference=True)
        return img, video
    # glare, vignetting, the logarithm and the video in one compiled call (the logarithm
    # computed fast and checked against the grey levels' rounding: numpy's is taken for the
    # pixels it cannot settle)
    if g > 0:
        glare = (_wide_blur_of_blocks(blocks, fluoro.glare_sigma_px, f, img.shape)
                 if blocks is not None else wide_blur(img, fluoro.glare_sigma_px))
    else:
        glare = img
    video = _glare_vignetting_video(img, glare, g, field, fluoro, noise_u8, camera_rng)
    return img, video


def _frame_streams(rng) -> tuple[np.random.Generator, np.random.Generator]:
    """The quanta's and the camera's random streams of one frame: two children spawned from
    ``rng`` (a Generator, a seed or None); ``rng``'s own stream is not drawn from, so that
    every frame rendered with it (a sweep's) has streams of its own whatever the others
    drew."""
    quanta, camera = np.random.default_rng(rng).spawn(2)
    return quanta, camera


def _glare_vignetting_video(img: np.ndarray, glare: np.ndarray, g: float, field: _Field,
                            fluoro, noise_u8: float, rng) -> np.ndarray:
    """In place on ``img`` (on the box of ``field``): ``(img (1 - g) + g glare) vignetting``;
    returns the 8-bit video of it (:func:`video_u8`, the same draws and levels), compiled
    (:func:`testbed._detector_numba.glare_vignetting_video`, its logarithm's few undecided
    pixels finished with numpy's)."""
    from testbed._detector_numba import glare_vignetting_video, video_finish

    black, white = int(fluoro.black_u8), int(fluoro.white_u8)
    dr, noise_u8 = float(fluoro.display_range), float(noise_u8)
    video, idx, x, z = _with_pcg(
        np.random.default_rng(rng), glare_vignetting_video, img, glare, float(g),
        field.vignetting, 1e-12, field.fov, field.spans, field.runs, field.n, black, white,
        dr, noise_u8)
    if len(idx):
        video_finish(video, idx, np.log(x), z, black, white, dr, noise_u8)
    return video
