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
def video(img, fov, black_u8, white_u8, display_range, noise_u8, rng):
    """The 8-bit frame of :func:`testbed.detector.video_u8`: logarithmic level between the
    black and white levels, camera noise (one normal per field pixel, row-major, when
    ``noise_u8 > 0``), rounded and clipped; 0 outside ``fov``."""
    H, W = img.shape
    out = np.zeros((H, W), np.uint8)
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    for r in range(H):
        for c in range(W):
            if not fov[r, c]:
                continue
            level = 1.0 + np.log(max(img[r, c], 1e-12)) / display_range
            v = black + gain * min(max(level, 0.0), 1.0)
            if noise_u8 > 0:
                v += rng.standard_normal() * noise_u8
            out[r, c] = np.uint8(min(max(np.rint(v), 0.0), 255.0))
    return out
