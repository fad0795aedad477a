"""Compiled (numba) per-pixel stages of the imaging chain: quantum counts and 8-bit video.

numba draws from a numpy ``Generator`` inside compiled code with numpy's own algorithms and
bit generator, so a loop that draws one normal per pixel of the field, in row-major order,
consumes the stream exactly as ``rng.standard_normal(n)`` does and gives the same numbers
(3.5x faster here: numpy's sampler calls its bit generator through a pointer per draw). The
arithmetic follows :func:`testbed.detector.quantum_noise` and :func:`testbed.detector.video_u8`
operation by operation, so the frames equal theirs (``tests/testbed/test_detector.py``
compares them on random images; a logarithm's last bit may differ between numpy's and the
C library's, which moves a grey level only when it lies on a rounding boundary).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def quantum_counts(img, fov, photons, exact_below, rng):
    """In place on ``img (H, W)``: inside ``fov`` the fluence becomes quantum counts of
    ``photons * fluence`` (the moment-matched normal law of
    :func:`testbed.detector.quantum_noise`) over ``photons``; one normal drawn per field
    pixel in row-major order. Returns the flat indices of the field pixels expecting fewer
    than ``exact_below`` quanta and their expectations, in that order: the caller draws
    their counts from the Poisson law (after every normal, as the reference does)."""
    H, W = img.shape
    low_idx = np.empty(H * W, np.int64)     # untouched beyond n_low: no cost
    low_lam = np.empty(H * W)
    n_low = 0
    sixth = 1.0 / 6.0
    for r in range(H):
        for c in range(W):
            if not fov[r, c]:
                continue
            lam = max(img[r, c], 0.0) * photons
            z = rng.standard_normal()
            k = np.sqrt(lam) * z
            k += lam
            k += (z * z - 1.0) * sixth
            k = max(np.rint(k), 0.0)
            if lam < exact_below:
                low_idx[n_low] = r * W + c
                low_lam[n_low] = lam
                n_low += 1
            img[r, c] = k / photons
    return low_idx[:n_low], low_lam[:n_low]


@njit(cache=True)
def video(log_img, fov, black_u8, white_u8, display_range, noise_u8, rng):
    """The 8-bit frame of :func:`testbed.detector.video_u8` from ``log_img``, the natural
    logarithm of the intensity floored at 1e-12 (numpy's vectorised logarithm, the
    reference's, 5x faster than a scalar one here): logarithmic level between the black and
    white levels, camera noise (one normal per field pixel, row-major, when
    ``noise_u8 > 0``), rounded and clipped; 0 outside ``fov``."""
    H, W = log_img.shape
    out = np.zeros((H, W), np.uint8)
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    for r in range(H):
        for c in range(W):
            if not fov[r, c]:
                continue
            level = 1.0 + log_img[r, c] / display_range
            v = black + gain * min(max(level, 0.0), 1.0)
            if noise_u8 > 0:
                v += rng.standard_normal() * noise_u8
            out[r, c] = np.uint8(min(max(np.rint(v), 0.0), 255.0))
    return out


@njit(cache=True)
def scatter_source(primary, fov, scatterer):
    """For :func:`testbed.detector.add_scatter`: the primary in the field (0 outside) and the
    scatter source (the primary where ``scatterer``, 0 elsewhere), ``(H, W)`` each."""
    H, W = primary.shape
    p = np.zeros((H, W))
    src = np.zeros((H, W))
    for r in range(H):
        for c in range(W):
            if fov[r, c]:
                v = primary[r, c]
                p[r, c] = v
                if scatterer[r, c]:
                    src[r, c] = v
    return p, src


@njit(cache=True)
def add_scatter_field(low, den, spr, p, fov, n_field):
    """In place on ``low`` (the blurred scatter source): ``low / den * spr + p`` in the field,
    0 outside (the rounding of the reference's numpy steps). Returns the field's ``n_field``
    values in row-major order (for the brightness control's median)."""
    H, W = low.shape
    values = np.empty(n_field)
    n = 0
    for r in range(H):
        for c in range(W):
            if fov[r, c]:
                v = low[r, c] / den[r, c]
                v *= spr
                v += p[r, c]
                low[r, c] = v
                values[n] = v
                n += 1
            else:
                low[r, c] = 0.0
    return values


@njit(cache=True)
def masked_transmission(trans, fov, threshold):
    """The first step of :func:`testbed.detector.form_image` in one pass: the transmission in
    ``fov`` (0 outside) and the scatterers (``fov`` and transmission below ``threshold``)."""
    H, W = trans.shape
    img = np.zeros((H, W))
    scatterer = np.zeros((H, W), np.bool_)
    for r in range(H):
        for c in range(W):
            if fov[r, c]:
                v = trans[r, c]
                img[r, c] = v
                scatterer[r, c] = v < threshold
    return img, scatterer


@njit(cache=True)
def glare_vignetting(img, glare, g, vignetting, floor):
    """In place on ``img``: ``(img (1 - g) + g glare) vignetting`` (the reference's roundings;
    ``g = 0``: ``img vignetting``); returns the result floored at ``floor`` (a new array,
    the logarithm's input)."""
    H, W = img.shape
    out = np.empty((H, W))
    keep = 1.0 - g
    for r in range(H):
        for c in range(W):
            v = img[r, c]
            if g > 0:
                v *= keep
                v += glare[r, c] * g
            v *= vignetting[r, c]
            img[r, c] = v
            out[r, c] = max(v, floor)
    return out


@njit(cache=True)
def band_of(values, lo, hi):
    """One pass over ``values``: the count below ``lo``, the values within ``[lo, hi]`` (in
    their order) and the count of NaNs (a NaN is neither below nor within)."""
    n = values.shape[0]
    band = np.empty(n)
    below = 0
    nb = 0
    nans = 0
    for i in range(n):
        v = values[i]
        if v < lo:
            below += 1
        elif v <= hi:
            band[nb] = v
            nb += 1
        elif v != v:
            nans += 1
    return below, band[:nb].copy(), nans
