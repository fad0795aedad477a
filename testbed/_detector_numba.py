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
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


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


@intrinsic
def _f64_bits(typingctx, x):
    """The bits of a float64 as an int64 (a bit cast)."""
    sig = types.int64(types.float64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))

    return sig, codegen


@intrinsic
def _bits_f64(typingctx, x):
    """The float64 of an int64's bits (a bit cast)."""
    sig = types.float64(types.int64)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())

    return sig, codegen


_LN2_HI = 6.93147180369123816490e-01      # ln 2's first 32 bits
_LN2_LO = 1.90821492927058770002e-10      # and the rest
#: the bound the fast logarithm's error is kept below (absolute, natural log units): it is
#: within 2.3e-16 relative of numpy's (about 1e-13 absolute at most, tested), so the margin
#: is wide; a grey level is taken from it only when both ends of this interval give it
LOG_TOLERANCE = 4e-10


@njit(inline="always", error_model="numpy")
def _fast_log(x):
    """ln(x) of a positive, finite, normal float64 to about one ulp, in vectorisable
    arithmetic (no C library call): ``x = 2^e m``, ``m`` in [sqrt(1/2), sqrt(2)),
    ``ln m = 2 atanh(s)``, ``s = (m - 1) / (m + 1)``, the series to ``s^23``."""
    b = _f64_bits(x)
    eb = (b + (0x3FF0000000000000 - 0x3FE6A09E667F3BCD)) >> 52      # e + 1023
    m = _bits_f64(b - ((eb - 1023) << 52))
    f = m - 1.0
    s = f / (2.0 + f)
    z = s * s
    p = 2.0 / 23.0
    p = p * z + 2.0 / 21.0
    p = p * z + 2.0 / 19.0
    p = p * z + 2.0 / 17.0
    p = p * z + 2.0 / 15.0
    p = p * z + 2.0 / 13.0
    p = p * z + 2.0 / 11.0
    p = p * z + 2.0 / 9.0
    p = p * z + 2.0 / 7.0
    p = p * z + 2.0 / 5.0
    p = p * z + 2.0 / 3.0
    e = float(np.int32(eb) - np.int32(1023))       # int32: a vector conversion on AVX2
    return e * _LN2_HI + ((f - s * f) + (s * z * p + e * _LN2_LO))   # 2s = f - s f


@njit(cache=True, error_model="numpy")
def fast_log(x):
    """:func:`_fast_log` of every value of ``x`` (1-D; NaN where a value is not a positive
    finite normal number), for tests."""
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        v = x[i]
        out[i] = _fast_log(v) if 2.2250738585072014e-308 <= v <= 1.7976931348623157e308 else np.nan
    return out


@njit(inline="always")
def _video_level(log_v, z, black, gain, display_range, noise_u8):
    """The grey level of :func:`video` before its rounding, from the logarithm ``log_v`` and
    the normal draw ``z`` (unused when ``noise_u8 <= 0``)."""
    level = 1.0 + log_v / display_range
    v = black + gain * min(max(level, 0.0), 1.0)
    if noise_u8 > 0:
        v += z * noise_u8
    return v


@njit(cache=True)
def row_spans(fov):
    """Per row of ``fov`` (H, W) the first field column and one past the last ((H, 2); 0, 0
    for a row without field)."""
    H, W = fov.shape
    spans = np.zeros((H, 2), np.int64)
    for r in range(H):
        c0 = 0
        while c0 < W and not fov[r, c0]:
            c0 += 1
        if c0 == W:
            continue
        c1 = W
        while not fov[r, c1 - 1]:
            c1 -= 1
        spans[r, 0] = c0
        spans[r, 1] = c1
    return spans


@njit(cache=True, error_model="numpy")
def glare_vignetting_video(img, glare, g, vignetting, floor, fov, spans, black_u8, white_u8,
                           display_range, noise_u8, rng):
    """:func:`glare_vignetting` (in place on ``img``), the logarithm and :func:`video` in
    two passes, the logarithm without the C library (``spans``: :func:`row_spans` of
    ``fov``). The first pass (vectorised) takes :func:`_fast_log` of the floored intensity
    within the spans; the second draws the camera noise per field pixel (row-major, as
    :func:`video`) and rounds the level. The level is computed by the same monotone steps
    from a logarithm within ``LOG_TOLERANCE`` of the exact one, so it lies within
    ``|gain| / display_range * LOG_TOLERANCE`` (plus a few of its ulps) of the exact level:
    where it lies farther than that from a rounding boundary, the exact logarithm gives the
    same grey level. Elsewhere (about never, or an intensity that is not a positive finite
    number) the pixel is left to the caller: returns ``(video, idx, x, z)``, the box's flat
    indices of those pixels in row-major order, their floored intensities and their draws,
    for :func:`video_finish` with numpy's logarithm of ``x`` (the reference's own)."""
    H, W = img.shape
    keep = 1.0 - g
    lg = np.empty((H, W))
    for r in range(H):
        if g > 0:
            for c in range(W):
                v = img[r, c] * keep
                v += glare[r, c] * g
                img[r, c] = v * vignetting[r, c]
        else:
            for c in range(W):
                img[r, c] = img[r, c] * vignetting[r, c]
        c0, c1 = spans[r, 0], spans[r, 1]
        x_row, lg_row = img[r, c0:c1], lg[r, c0:c1]     # views: no negative-index checks
        for k in range(c1 - c0):
            x = max(x_row[k], floor)
            ok = 2.2250738585072014e-308 <= x <= 1.7976931348623157e308
            lg_row[k] = _fast_log(x) if ok else np.nan
    out = np.zeros((H, W), np.uint8)
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    # how far the level of the fast logarithm may lie from the exact one's (grey levels)
    margin = abs(gain) / display_range * LOG_TOLERANCE * 1.001 + 1e-9
    pend = np.empty(H * W, np.int64)       # untouched beyond n_pend: no cost
    pend_z = np.empty(H * W)
    n_pend = 0
    for r in range(H):
        c0, c1 = spans[r, 0], spans[r, 1]
        fov_row, lg_row, out_row = fov[r, c0:c1], lg[r, c0:c1], out[r, c0:c1]
        for k in range(c1 - c0):
            if not fov_row[k]:
                continue
            z = rng.standard_normal() if noise_u8 > 0 else 0.0
            v = _video_level(lg_row[k], z, black, gain, display_range, noise_u8)
            vr = np.rint(v)
            if abs(v - vr) < 0.5 - margin:     # False for NaN
                out_row[k] = np.uint8(min(max(vr, 0.0), 255.0))
            else:
                pend[n_pend] = r * W + c0 + k
                pend_z[n_pend] = z
                n_pend += 1
    idx = pend[:n_pend].copy()
    x = np.empty(n_pend)
    for i in range(n_pend):
        x[i] = max(img.flat[idx[i]], floor)
    return out, idx, x, pend_z[:n_pend].copy()


@njit(cache=True)
def video_finish(out, idx, log_x, z, black_u8, white_u8, display_range, noise_u8):
    """The pixels :func:`glare_vignetting_video` left: ``out.flat[idx]`` from their
    logarithms and draws, as :func:`video` computes them."""
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    for i in range(idx.shape[0]):
        v = _video_level(log_x[i], z[i], black, gain, display_range, noise_u8)
        out.flat[idx[i]] = np.uint8(min(max(np.rint(v), 0.0), 255.0))
