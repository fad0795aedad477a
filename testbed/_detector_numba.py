"""Compiled (numba) per-pixel stages of the imaging chain: quantum counts and 8-bit video.

numba draws from a numpy ``Generator`` inside compiled code with numpy's own algorithms and
bit generator, so a loop that draws one normal per pixel of the field, in row-major order,
consumes the stream exactly as ``rng.standard_normal(n)`` does and gives the same numbers
(3.5x faster here: numpy's sampler calls its bit generator through a pointer per draw). The
arithmetic follows :func:`testbed.detector.quantum_noise` and :func:`testbed.detector.video_u8`
operation by operation, so the frames equal theirs (``tests/testbed/test_detector.py``
compares them on random images; a logarithm's last bit may differ between numpy's and the
C library's, which moves a grey level only when it lies on a rounding boundary). The
normals of numpy's default bit generator (PCG64) are drawn inline, 20 % faster (the section
below), and :func:`glare_vignetting_video` computes the video's logarithm without the C
library, taking numpy's only for the pixels whose grey level it cannot settle.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic, overload
from numba.np.random._constants import (
    fi_double,
    ki_double,
    wi_double,
    ziggurat_nor_inv_r,
    ziggurat_nor_r,
)

# ----------------------------------------------------------------- normal draws, inline
# numba's ``Generator.standard_normal()`` calls the bit generator through a pointer per draw
# (0.61 ms of the 172,820 draws of a sweep frame's stream). For numpy's default bit
# generator, PCG64, the kernels can instead step its 128-bit state inline (0.49 ms): a
# kernel given ``state``, a uint64 array (state high, low, increment high, low;
# pcg_state() and set_pcg_state() move it from and back to the Generator), threads the
# state through locals (``hi, lo = _rng_begin(state)``, ``z, hi, lo = _draw_normal(state,
# hi, lo)``, ``_rng_end(state, hi, lo)``) and draws the same numbers as
# ``rng.standard_normal()`` (numpy's ziggurat, as numba's own, with numba's tables); given
# the Generator itself, the same code is numba's own call. Every kernel below draws this
# way and compiles for either.

@intrinsic
def _mul128(typingctx, a_hi, a_lo, b_hi, b_lo):
    """``(a * b) mod 2**128`` of two uint64 pairs (high, low), as (high, low)."""
    sig = types.UniTuple(types.uint64, 2)(types.uint64, types.uint64, types.uint64,
                                          types.uint64)

    def codegen(context, builder, signature, args):
        i128 = ir.IntType(128)
        sixty_four = ir.Constant(i128, 64)

        def join(hi, lo):
            return builder.or_(builder.shl(builder.zext(hi, i128), sixty_four),
                               builder.zext(lo, i128))

        prod = builder.mul(join(args[0], args[1]), join(args[2], args[3]))
        lo = builder.trunc(prod, ir.IntType(64))
        hi = builder.trunc(builder.lshr(prod, sixty_four), ir.IntType(64))
        return context.make_tuple(builder, signature.return_type, (hi, lo))

    return sig, codegen


_PCG_MUL_HI = np.uint64(2549297995355413924)      # PCG64's 128-bit multiplier
_PCG_MUL_LO = np.uint64(4865540595714422341)


@njit(inline="always")
def _pcg_next64(hi, lo, inc_hi, inc_lo):
    """PCG64's next 64-bit output (XSL-RR of the stepped state) and the stepped state
    ``(hi, lo)``: the state is threaded through locals (registers), 25 % faster than
    through an array."""
    h, low = _mul128(hi, lo, _PCG_MUL_HI, _PCG_MUL_LO)
    lo2 = low + inc_lo
    hi2 = h + inc_hi + (np.uint64(1) if lo2 < low else np.uint64(0))
    x = hi2 ^ lo2
    rot = hi2 >> np.uint64(58)
    return (x >> rot) | (x << ((np.uint64(64) - rot) & np.uint64(63))), hi2, lo2


@njit(inline="always")
def _pcg_next_double(hi, lo, inc_hi, inc_lo):
    r, hi, lo = _pcg_next64(hi, lo, inc_hi, inc_lo)
    return (r >> np.uint64(11)) * (1.0 / 9007199254740992.0), hi, lo


@njit
def _pcg_normal_tail(idx, rabs, x, hi, lo, inc_hi, inc_lo):
    """The ziggurat's rare branches (about 1 draw in 100): (accepted, value, hi, lo)."""
    if idx == 0:
        while True:
            u, hi, lo = _pcg_next_double(hi, lo, inc_hi, inc_lo)
            xx = -ziggurat_nor_inv_r * np.log1p(-u)
            u, hi, lo = _pcg_next_double(hi, lo, inc_hi, inc_lo)
            yy = -np.log1p(-u)
            if yy + yy > xx * xx:
                if (rabs >> np.uint64(8)) & np.uint64(0x1):
                    return True, -(ziggurat_nor_r + xx), hi, lo
                return True, ziggurat_nor_r + xx, hi, lo
    u, hi, lo = _pcg_next_double(hi, lo, inc_hi, inc_lo)
    if (fi_double[idx - 1] - fi_double[idx]) * u + fi_double[idx] < np.exp(-0.5 * x * x):
        return True, x, hi, lo
    return False, x, hi, lo


@njit(inline="always")
def _pcg_normal(hi, lo, inc_hi, inc_lo):
    """numpy's ``random_standard_normal`` (ziggurat) on the PCG64 state: (value, hi, lo)."""
    while True:
        r, hi, lo = _pcg_next64(hi, lo, inc_hi, inc_lo)
        idx = r & np.uint64(0xFF)
        r >>= np.uint64(8)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = rabs * wi_double[idx]
        if r & np.uint64(1):
            x = -x
        if rabs < ki_double[idx]:
            return x, hi, lo
        ok, x, hi, lo = _pcg_normal_tail(idx, rabs, x, hi, lo, inc_hi, inc_lo)
        if ok:
            return x, hi, lo


def _rng_begin(source):
    """The state a kernel threads through its draws: ``(hi, lo)`` of a PCG64 state array,
    (0, 0) for a Generator."""
    raise NotImplementedError     # compiled only (overloads below)


def _draw_normal(source, hi, lo):
    """One standard normal from ``source`` (a PCG64 state array, whose state is ``hi, lo``,
    or a Generator): ``(value, hi, lo)``."""
    raise NotImplementedError


def _rng_end(source, hi, lo):
    """The threaded state back into ``source`` (a PCG64 state array; nothing for a
    Generator)."""
    raise NotImplementedError


@overload(_rng_begin, inline="always")
def _rng_begin_impl(source):
    if isinstance(source, types.Array):
        return lambda source: (source[0], source[1])
    return lambda source: (np.uint64(0), np.uint64(0))


@overload(_draw_normal)
def _draw_normal_impl(source, hi, lo):
    if isinstance(source, types.Array):
        return lambda source, hi, lo: _pcg_normal(hi, lo, source[2], source[3])
    return lambda source, hi, lo: (source.standard_normal(), hi, lo)


@overload(_rng_end, inline="always")
def _rng_end_impl(source, hi, lo):
    if isinstance(source, types.Array):
        def impl(source, hi, lo):
            source[0] = hi
            source[1] = lo
        return impl
    return lambda source, hi, lo: None


@njit(cache=True)
def draw_normals(n, source):
    """``n`` standard normals from ``source`` (a PCG64 state array or a Generator): for
    tests and the once-a-process check of the inline generator."""
    out = np.empty(n)
    hi, lo = _rng_begin(source)
    for i in range(n):
        out[i], hi, lo = _draw_normal(source, hi, lo)
    _rng_end(source, hi, lo)
    return out


_MASK64 = (1 << 64) - 1


def pcg_state(rng):
    """The inline draws' state of ``rng`` (a numpy Generator): a uint64 array (4,) when its
    bit generator is PCG64 and the inline generator checks out in this process
    (:func:`inline_pcg_ok`), else None (the kernels then draw from ``rng`` itself). Give it
    back with :func:`set_pcg_state` before ``rng`` draws again."""
    bg = rng.bit_generator
    if type(bg) is not np.random.PCG64 or not inline_pcg_ok():
        return None
    st = bg.state["state"]
    s, inc = st["state"], st["inc"]
    return np.array([s >> 64, s & _MASK64, inc >> 64, inc & _MASK64], dtype=np.uint64)


def set_pcg_state(rng, state) -> None:
    """``rng``'s PCG64 state after the inline draws of ``state`` (from :func:`pcg_state`)."""
    st = rng.bit_generator.state
    st["state"]["state"] = (int(state[0]) << 64) | int(state[1])
    rng.bit_generator.state = st


_INLINE_PCG_OK = []


def inline_pcg_ok() -> bool:
    """Whether the inline PCG64 draws equal numpy's in this process (checked once: 50,000
    normals from a fixed seed, and the generator's next draw after the state is given
    back)."""
    if not _INLINE_PCG_OK:
        ref_rng = np.random.Generator(np.random.PCG64(20261127))
        rng = np.random.Generator(np.random.PCG64(20261127))
        st = rng.bit_generator.state["state"]
        s, inc = st["state"], st["inc"]
        state = np.array([s >> 64, s & _MASK64, inc >> 64, inc & _MASK64], dtype=np.uint64)
        got = draw_normals(50_000, state)
        set_pcg_state(rng, state)
        ok = (np.array_equal(got, ref_rng.standard_normal(50_000))
              and rng.standard_normal() == ref_rng.standard_normal())
        _INLINE_PCG_OK.append(bool(ok))
    return _INLINE_PCG_OK[0]


@njit(cache=True)
def quantum_counts(img, fov, photons, exact_below, rng):
    """In place on ``img (H, W)``: inside ``fov`` the fluence becomes quantum counts of
    ``photons * fluence`` (the moment-matched normal law of
    :func:`testbed.detector.quantum_noise`) over ``photons``; one normal drawn per field
    pixel in row-major order. Returns the flat indices of the field pixels expecting fewer
    than ``exact_below`` quanta and their expectations, in that order: the caller draws
    their counts from the Poisson law (after every normal, as the reference does). ``rng``:
    a Generator or its PCG64 state (:func:`pcg_state`), as for every kernel here."""
    H, W = img.shape
    low_idx = np.empty(H * W, np.int64)     # untouched beyond n_low: no cost
    low_lam = np.empty(H * W)
    n_low = 0
    sixth = 1.0 / 6.0
    hi, lo = _rng_begin(rng)
    for r in range(H):
        for c in range(W):
            if not fov[r, c]:
                continue
            lam = max(img[r, c], 0.0) * photons
            z, hi, lo = _draw_normal(rng, hi, lo)
            k = np.sqrt(lam) * z
            k += lam
            k += (z * z - 1.0) * sixth
            k = max(np.rint(k), 0.0)
            if lam < exact_below:
                low_idx[n_low] = r * W + c
                low_lam[n_low] = lam
                n_low += 1
            img[r, c] = k / photons
    _rng_end(rng, hi, lo)
    return low_idx[:n_low], low_lam[:n_low]


@njit(cache=True, error_model="numpy")
def quantum_counts_runs(img, spans, n_field, photons, exact_below, rng):
    """:func:`quantum_counts` for a field that is one run of columns per row (``spans``,
    :func:`row_spans`, holding every field pixel and no other; ``n_field`` of them): the
    normals drawn first into a buffer (a tight loop), then each row's counts in one
    vectorised loop with the same arithmetic; the same numbers and returns."""
    H, W = img.shape
    z = np.empty(n_field)
    hi, lo = _rng_begin(rng)
    for i in range(n_field):
        z[i], hi, lo = _draw_normal(rng, hi, lo)
    _rng_end(rng, hi, lo)
    sixth = 1.0 / 6.0
    n_low_row = np.zeros(H, np.int64)
    n = 0
    for r in range(H):
        c0, c1 = spans[r, 0], spans[r, 1]
        m = c1 - c0
        row, zr = img[r, c0:c1], z[n:n + m]
        n_low = 0
        for k in range(m):
            lam = max(row[k], 0.0) * photons
            zz = zr[k]
            q = np.sqrt(lam) * zz
            q += lam
            q += (zz * zz - 1.0) * sixth
            q = max(np.rint(q), 0.0)
            row[k] = q / photons
            zr[k] = lam                 # the draw is used: its place keeps the expectation
            n_low += lam < exact_below
        n_low_row[r] = n_low
        n += m
    total = n_low_row.sum()
    low_idx = np.empty(total, np.int64)
    low_lam = np.empty(total)
    i = 0
    n = 0
    for r in range(H):
        c0, c1 = spans[r, 0], spans[r, 1]
        if n_low_row[r]:
            for k in range(c1 - c0):
                lam = z[n + k]
                if lam < exact_below:
                    low_idx[i] = r * W + c0 + k
                    low_lam[i] = lam
                    i += 1
        n += c1 - c0
    return low_idx, low_lam


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
    hi, lo = _rng_begin(rng)
    for r in range(H):
        for c in range(W):
            if not fov[r, c]:
                continue
            level = 1.0 + log_img[r, c] / display_range
            v = black + gain * min(max(level, 0.0), 1.0)
            if noise_u8 > 0:
                z, hi, lo = _draw_normal(rng, hi, lo)
                v += z * noise_u8
            out[r, c] = np.uint8(min(max(np.rint(v), 0.0), 255.0))
    _rng_end(rng, hi, lo)
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


@njit(cache=True, error_model="numpy")
def add_scatter_spans(low, den, spr, p, spans, n_field):
    """:func:`add_scatter_field` for a field that is exactly one run of columns per row,
    ``spans`` (:func:`row_spans`; the caller checks that they hold every field pixel and
    no other): the same numbers, each row's run in one vectorised loop."""
    H, W = low.shape
    values = np.empty(n_field)
    n = 0
    for r in range(H):
        c0, c1 = spans[r, 0], spans[r, 1]
        row = low[r]
        for c in range(c0):
            row[c] = 0.0
        for c in range(c1, W):
            row[c] = 0.0
        m = c1 - c0
        seg, d, q, out = low[r, c0:c1], den[r, c0:c1], p[r, c0:c1], values[n:n + m]
        for k in range(m):
            v = seg[k] / d[k]
            v *= spr
            v += q[k]
            seg[k] = v
            out[k] = v
        n += m
    return values


@njit(cache=True)
def zero_outside_runs(img, spans):
    """``img *= inside`` (the field as 1.0 / 0.0) in place for a field that is one run of
    columns per row (``spans``, :func:`row_spans`): only the pixels outside the runs are
    multiplied (by 0.0: the same numbers, a NaN stays NaN); inside, a product by 1.0
    changes nothing."""
    H, W = img.shape
    for r in range(H):
        row = img[r]
        for c in range(spans[r, 0]):
            row[c] *= 0.0
        for c in range(spans[r, 1], W):
            row[c] *= 0.0


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


@njit(inline="always", error_model="numpy")
def _floored_log(v, floor):
    """``max(v, floor)`` and its :func:`_fast_log` (NaN unless it is a positive finite
    normal number)."""
    x = max(v, floor)
    ok = 2.2250738585072014e-308 <= x <= 1.7976931348623157e308
    return x, (_fast_log(x) if ok else np.nan)


@njit(cache=True, error_model="numpy")
def glare_vignetting_video(img, glare, g, vignetting, floor, fov, spans, runs, n_field,
                           black_u8, white_u8, display_range, noise_u8, rng):
    """:func:`glare_vignetting` (in place on ``img``), the logarithm and :func:`video`,
    the logarithm without the C library (``spans``: :func:`row_spans` of ``fov``; ``runs``:
    every row's field fills its span; ``n_field``: the field's pixel count). First the
    camera noise, one normal per field pixel in row-major order (as :func:`video`), into a
    buffer; then row by row (vectorised where ``runs``) the glare and vignetting, the
    floored intensity's :func:`_fast_log` and the grey level. The level is computed by the
    same monotone steps from a logarithm within ``LOG_TOLERANCE`` of the exact one, so it
    lies within ``|gain| / display_range * LOG_TOLERANCE`` (plus a few of its ulps) of the
    exact level: where it lies farther than that from a rounding boundary, the exact
    logarithm gives the same grey level. Elsewhere (about never, or an intensity that is
    not a positive finite number) the pixel is left to the caller: returns ``(video, idx,
    x, z)``, the box's flat indices of those pixels in row-major order, their floored
    intensities and their draws, for :func:`video_finish` with numpy's logarithm of ``x``
    (the reference's own)."""
    H, W = img.shape
    keep = 1.0 - g
    zb = np.empty(n_field) if noise_u8 > 0 else np.zeros(n_field)
    if noise_u8 > 0:
        hi, lo = _rng_begin(rng)
        if runs:
            for i in range(n_field):
                zb[i], hi, lo = _draw_normal(rng, hi, lo)
        else:
            n = 0
            for r in range(H):
                for c in range(spans[r, 0], spans[r, 1]):
                    if fov[r, c]:
                        zb[n], hi, lo = _draw_normal(rng, hi, lo)
                        n += 1
        _rng_end(rng, hi, lo)
    out = np.zeros((H, W), np.uint8)
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    # how far the level of the fast logarithm may lie from the exact one's (grey levels)
    limit = 0.5 - (abs(gain) / display_range * LOG_TOLERANCE * 1.001 + 1e-9)
    undecided = np.zeros(H, np.int64)
    n = 0
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
        m = c1 - c0
        # views: no negative-index checks in the vectorised loop
        x_row, fov_row, out_row = img[r, c0:c1], fov[r, c0:c1], out[r, c0:c1]
        bad = 0
        if runs:
            z_row = zb[n:n + m]
            for k in range(m):
                _, a = _floored_log(x_row[k], floor)
                v = _video_level(a, z_row[k], black, gain, display_range, noise_u8)
                vr = np.rint(v)
                out_row[k] = np.uint8(min(max(vr, 0.0), 255.0))
                bad += not abs(v - vr) < limit          # True for NaN
            n += m
        else:
            for k in range(m):
                if fov_row[k]:
                    _, a = _floored_log(x_row[k], floor)
                    v = _video_level(a, zb[n], black, gain, display_range, noise_u8)
                    vr = np.rint(v)
                    out_row[k] = np.uint8(min(max(vr, 0.0), 255.0))
                    bad += not abs(v - vr) < limit
                    n += 1
        undecided[r] = bad
    n_pend = undecided.sum()
    idx = np.empty(n_pend, np.int64)
    x = np.empty(n_pend)
    z = np.empty(n_pend)
    i = 0
    n = 0
    for r in range(H):
        c0, c1 = spans[r, 0], spans[r, 1]
        if undecided[r] == 0:
            n += c1 - c0 if runs else fov[r, c0:c1].sum()
            continue
        for c in range(c0, c1):
            if not fov[r, c]:
                continue
            xf, a = _floored_log(img[r, c], floor)
            v = _video_level(a, zb[n], black, gain, display_range, noise_u8)
            if not abs(v - np.rint(v)) < limit:
                idx[i] = r * W + c
                x[i] = xf
                z[i] = zb[n]
                i += 1
            n += 1
    return out, idx, x, z


@njit(cache=True)
def video_finish(out, idx, log_x, z, black_u8, white_u8, display_range, noise_u8):
    """The pixels :func:`glare_vignetting_video` left: ``out.flat[idx]`` from their
    logarithms and draws, as :func:`video` computes them."""
    gain = float(white_u8 - black_u8)
    black = float(black_u8)
    for i in range(idx.shape[0]):
        v = _video_level(log_x[i], z[i], black, gain, display_range, noise_u8)
        out.flat[idx[i]] = np.uint8(min(max(np.rint(v), 0.0), 255.0))


# ------------------------------------------- the MTF blur, the field mask, the block mean
# OpenCV's 5-tap GaussianBlur (CV_64F, BORDER_REPLICATE) and its area resize by a whole
# factor, replicated operation by operation as this machine's build computes them (found by
# experiment; testbed.detector checks the replica against cv2 once per shape and falls back
# to cv2 when they differ), so that the MTF blur, the field mask's product and the glare's
# block mean are one pass over the box.

@intrinsic
def _fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's fma)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        from numba.core import cgutils

        d = ir.DoubleType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]),
                                            "llvm.fma.f64")
        return builder.call(fn, args)

    return sig, codegen


@njit(inline="always")
def _row5_fma_at(src, c, W, k0, k1, k2, k3, k4):
    """:func:`_blur_row5`'s value at column ``c`` near an edge (taps clamped to the row):
    a multiply then fused multiply-adds in tap order."""
    x0, x1 = src[max(c - 2, 0)], src[max(c - 1, 0)]
    x2, x3, x4 = src[c], src[min(c + 1, W - 1)], src[min(c + 2, W - 1)]
    s = x0 * k0
    s = _fma(x1, k1, s)
    s = _fma(x2, k2, s)
    s = _fma(x3, k3, s)
    return _fma(x4, k4, s)


@njit(inline="always")
def _blur_row5(src, dst, k0, k1, k2, k3, k4):
    """OpenCV's row filter of a 5-tap kernel (edges replicated) of ``src`` (W,) into ``dst``:
    a multiply then fused multiply-adds in tap order, in 4-wide column blocks; the last
    ``W % 4`` columns by plain multiply-adds."""
    W = src.shape[0]
    nv = W - W % 4
    for c in range(min(2, nv)):
        dst[c] = _row5_fma_at(src, c, W, k0, k1, k2, k3, k4)
    hi = min(nv, W - 2)
    if hi > 2:
        a0, a1, a2, a3, a4 = src[0:hi - 2], src[1:hi - 1], src[2:hi], src[3:hi + 1], src[4:hi + 2]
        out = dst[2:hi]
        for c in range(hi - 2):
            s = a0[c] * k0
            s = _fma(a1[c], k1, s)
            s = _fma(a2[c], k2, s)
            s = _fma(a3[c], k3, s)
            out[c] = _fma(a4[c], k4, s)
    for c in range(max(hi, 2), nv):
        dst[c] = _row5_fma_at(src, c, W, k0, k1, k2, k3, k4)
    for c in range(nv, W):
        x0, x1 = src[max(c - 2, 0)], src[max(c - 1, 0)]
        x2, x3, x4 = src[c], src[min(c + 1, W - 1)], src[min(c + 2, W - 1)]
        s = x0 * k0
        s += x1 * k1
        s += x2 * k2
        s += x3 * k3
        s += x4 * k4
        dst[c] = s


@njit(inline="always")
def _block_row(prow, dst, f, scale):
    """One row of cv2's area resize by ``f`` (2, 3 or 4) of the rows ``prow`` (f, w f):
    each block's values in row-major order summed 4 at a time into a running sum from 0,
    times ``scale``."""
    w = dst.shape[0]
    if f == 2:
        a, b = prow[0], prow[1]
        for j in range(w):
            c = 2 * j
            s = 0.0
            s += ((a[c] + a[c + 1]) + b[c]) + b[c + 1]
            dst[j] = s * scale
    elif f == 3:
        a, b, d = prow[0], prow[1], prow[2]
        for j in range(w):
            c = 3 * j
            s = 0.0
            s += ((a[c] + a[c + 1]) + a[c + 2]) + b[c]
            s += ((b[c + 1] + b[c + 2]) + d[c]) + d[c + 1]
            s += d[c + 2]
            dst[j] = s * scale
    else:
        a, b, d, e = prow[0], prow[1], prow[2], prow[3]
        for j in range(w):
            c = 4 * j
            s = 0.0
            s += ((a[c] + a[c + 1]) + a[c + 2]) + a[c + 3]
            s += ((b[c] + b[c + 1]) + b[c + 2]) + b[c + 3]
            s += ((d[c] + d[c + 1]) + d[c + 2]) + d[c + 3]
            s += ((e[c] + e[c + 1]) + e[c + 2]) + e[c + 3]
            dst[j] = s * scale


@njit(cache=True, error_model="numpy")
def mtf_blur_runs(img, taps, spans, f):
    """``detector.blur(img, sigma)`` for a 5-tap kernel ``taps`` (cv2's GaussianBlur, edges
    replicated), times the field as 1.0 / 0.0 (:func:`zero_outside_runs` of ``spans``), and,
    for ``f >= 2``, the means of its ``f`` x ``f`` blocks zero-padded to whole blocks
    (``detector._block_mean(.., fast=True)``, cv2's area resize: each block's values in
    row-major order summed 4 at a time into a running sum, times ``float32(1 / f**2)``), in
    one pass over the rows (the row filter's rows in a ring of 5). Returns ``(blurred,
    block_means)`` (``block_means`` (0, 0) when ``f < 2``). Equal to OpenCV's on the builds
    the caller's check accepts (``detector._mtf_replica_ok``)."""
    H, W = img.shape
    k0, k1, k2, k3, k4 = taps[0], taps[1], taps[2], taps[3], taps[4]
    out = np.empty((H, W))
    ring = np.empty((5, W))
    done = -1                          # the last source row filtered into the ring
    fb = f if f >= 2 else 1
    h, w = -(-H // fb), -(-W // fb)
    small = np.zeros((h, w)) if f >= 2 else np.zeros((0, 0))
    scale = float(np.float32(1.0) / np.float32(fb * fb))
    prow = np.zeros((fb, w * fb))
    for r in range(H):
        need = min(r + 2, H - 1)
        while done < need:
            done += 1
            _blur_row5(img[done], ring[done % 5], k0, k1, k2, k3, k4)
        t0, t1 = ring[max(r - 2, 0) % 5], ring[max(r - 1, 0) % 5]
        t2 = ring[r % 5]
        t3, t4 = ring[min(r + 1, H - 1) % 5], ring[min(r + 2, H - 1) % 5]
        row = out[r]
        for c in range(W):
            s = t2[c] * k2
            s = s + k3 * (t1[c] + t3[c])
            row[c] = s + k4 * (t0[c] + t4[c])
        for c in range(spans[r, 0]):
            row[c] *= 0.0
        for c in range(spans[r, 1], W):
            row[c] *= 0.0
        if f >= 2 and (r % f == f - 1 or r == H - 1):
            bi = r // f
            if (bi + 1) * f <= H and w * f == W:
                _block_row(out[bi * f:(bi + 1) * f], small[bi], f, scale)
            else:
                for dy in range(f):           # the block row, zero-padded to whole blocks
                    if bi * f + dy < H:
                        prow[dy, :W] = out[bi * f + dy]
                    else:
                        prow[dy, :W] = 0.0
                _block_row(prow, small[bi], f, scale)
    return out, small
