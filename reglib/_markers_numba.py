"""Compiled passes of the fast marker detector (:func:`reglib.markers.detect_markers`).

Each computes what the numpy steps of the detector compute (the same values, in one pass
over the field's bounding box instead of several whole-array temporaries); the reference
detector (``detect_markers(reference=True)``, scipy.ndimage alone) is compared with the
fast one in tests/reglib/test_calibration.py.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


@njit(cache=True)
def centred_difference(a, b, mask, sign, max_abs):
    """``d = sign * (a - b)`` less its median over ``mask`` (integer frames: the median by
    counting, the two middle values' mean for an even count), 0 outside ``mask``. Returns
    ``(d float32, pixels in mask)``: ``d`` is a multiple of 0.5 below ``2 max_abs + 1`` in
    magnitude, exact in float32 for frames of at most 16 bits (``np.float64(d)`` is the
    float64 difference); ``max_abs`` bounds ``|a - b|`` (255 for 8-bit frames). The arrays
    may be views (a crop of a frame)."""
    H, W = a.shape
    # four histograms, a pixel's by its column: runs of equal values (the noise's few
    # levels) do not wait on one counter
    counts4 = np.zeros((4, 2 * max_abs + 1), dtype=np.int64)
    for r in range(H):
        ar, br, mr = a[r], b[r], mask[r]
        for c in range(W):
            if mr[c]:
                counts4[c & 3, sign * (np.int64(ar[c]) - np.int64(br[c])) + max_abs] += 1
    counts = np.zeros(2 * max_abs + 1, dtype=np.int64)
    n = 0
    for v in range(counts.shape[0]):
        counts[v] = counts4[0, v] + counts4[1, v] + counts4[2, v] + counts4[3, v]
        n += counts[v]
    med = 0.0
    if n > 0:
        hi_rank = n // 2
        lo_rank = hi_rank - 1 if n % 2 == 0 else hi_rank
        cum = 0
        lo_v = 0
        hi_v = 0
        found_lo = False
        for v in range(counts.shape[0]):
            cum += counts[v]
            if not found_lo and cum > lo_rank:
                lo_v = v
                found_lo = True
            if cum > hi_rank:
                hi_v = v
                break
        med = ((lo_v - max_abs) + (hi_v - max_abs)) / 2.0
    d = np.empty((H, W), dtype=np.float32)
    # in float32, exactly: the frames' values (at most 16 bits), their difference and the
    # half-integer median are exact there, and so is the result (at most 19 of its 24 bits)
    med32 = np.float32(med)
    sign32 = np.float32(sign)
    for r in range(H):
        for c in range(W):
            v = sign32 * (np.float32(a[r, c]) - np.float32(b[r, c])) - med32
            d[r, c] = v if mask[r, c] else np.float32(0.0)
    return d, n


@njit(cache=True)
def band(g1, g2):
    """``ds = g1 - g2`` (float32) where ``g1 > 0.5 ds``, 0 elsewhere (the rim test; as
    ``2 g1 > ds``, exact in float32), in one vectorised pass (its maximum is numpy's: a
    maximum does not vectorise here)."""
    H, W = g1.shape
    ds = np.empty((H, W), dtype=np.float32)
    for r in range(H):
        for c in range(W):
            v = g1[r, c] - g2[r, c]
            ds[r, c] = v if g1[r, c] + g1[r, c] > v else np.float32(0.0)
    return ds


# ------------------------------------------------------------- the two Gaussians at once
# OpenCV's GaussianBlur of a float32 image with BORDER_REFLECT (reglib.markers._gaussian),
# replicated operation by operation as this machine's build computes it (found by experiment,
# as testbed._detector_numba's MTF blur): the row filter a multiply by the first tap then
# fused multiply-adds in tap order on the columns of its vector blocks (all but the last
# W % 4), plain multiply-adds on the rest; the column filter (symmetric) the centre row
# times the centre tap, then per tap pair a fused multiply-add of the pair's sum (the row
# below plus the row above), plain multiply-adds on the last W % 8 columns.
# reglib.markers checks the replica against cv2 once per shape and falls back to cv2 when
# they differ.

@intrinsic
def _fma32(typingctx, a, b, c):
    """``a * b + c`` in float32 rounded once (LLVM's fma)."""
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        from numba.core import cgutils

        f = ir.FloatType()
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f, [f, f, f]),
                                            "llvm.fma.f32")
        return builder.call(fn, args)

    return sig, codegen


@njit(inline="always")
def _reflect(j, n):
    """Index ``j`` of a sequence of ``n`` reflected at its ends as OpenCV's BORDER_REFLECT
    (``fedcba|abcdef|fedcba``), for ``-n <= j < 2 n``."""
    return -j - 1 if j < 0 else (2 * n - j - 1 if j >= n else j)


@njit(inline="always")
def _row_filter(xe, k, W, acc):
    """OpenCV's row filter of taps ``k`` (float32, odd count) into ``acc`` (W,): ``xe`` is
    the row extended by the border (``acc[c]`` from ``xe[c:c + len(k)]``). Nine taps, then
    eight at a time, per pass over the columns (the running sums in ``acc``)."""
    n = k.shape[0]
    nv = W - W % 4
    j = 1
    if n >= 9:
        a0, a1, a2, a3, a4 = k[0], k[1], k[2], k[3], k[4]
        a5, a6, a7, a8 = k[5], k[6], k[7], k[8]
        for c in range(nv):
            s = xe[c] * a0
            s = _fma32(xe[c + 1], a1, s)
            s = _fma32(xe[c + 2], a2, s)
            s = _fma32(xe[c + 3], a3, s)
            s = _fma32(xe[c + 4], a4, s)
            s = _fma32(xe[c + 5], a5, s)
            s = _fma32(xe[c + 6], a6, s)
            s = _fma32(xe[c + 7], a7, s)
            acc[c] = _fma32(xe[c + 8], a8, s)
        j = 9
    else:
        a0 = k[0]
        for c in range(nv):
            acc[c] = xe[c] * a0
    while j + 8 <= n:
        a0, a1, a2, a3 = k[j], k[j + 1], k[j + 2], k[j + 3]
        a4, a5, a6, a7 = k[j + 4], k[j + 5], k[j + 6], k[j + 7]
        for c in range(nv):
            s = acc[c]
            s = _fma32(xe[c + j], a0, s)
            s = _fma32(xe[c + j + 1], a1, s)
            s = _fma32(xe[c + j + 2], a2, s)
            s = _fma32(xe[c + j + 3], a3, s)
            s = _fma32(xe[c + j + 4], a4, s)
            s = _fma32(xe[c + j + 5], a5, s)
            s = _fma32(xe[c + j + 6], a6, s)
            acc[c] = _fma32(xe[c + j + 7], a7, s)
        j += 8
    while j < n:
        a0 = k[j]
        for c in range(nv):
            acc[c] = _fma32(xe[c + j], a0, acc[c])
        j += 1
    for c in range(nv, W):
        s = xe[c] * k[0]
        for t in range(1, n):
            s = s + xe[c + t] * k[t]
        acc[c] = s


@njit(inline="always")
def _col_filter(ring, L, k, R, r, H, out):
    """OpenCV's (symmetric) column filter of taps ``k`` (``2 R + 1``) at row ``r`` of ``H``
    into ``out`` (W,): row ``i`` of the row-filtered image is ``ring[i % L]``. The centre
    and four tap pairs, then four pairs at a time, per pass over the columns."""
    W = out.shape[0]
    nv = W - W % 8
    kc = k[R]
    t = ring[r % L]
    j = 1
    if R >= 4:
        u1, d1 = ring[_reflect(r - 1, H) % L], ring[_reflect(r + 1, H) % L]
        u2, d2 = ring[_reflect(r - 2, H) % L], ring[_reflect(r + 2, H) % L]
        u3, d3 = ring[_reflect(r - 3, H) % L], ring[_reflect(r + 3, H) % L]
        u4, d4 = ring[_reflect(r - 4, H) % L], ring[_reflect(r + 4, H) % L]
        b1, b2, b3, b4 = k[R + 1], k[R + 2], k[R + 3], k[R + 4]
        for c in range(nv):
            s = t[c] * kc
            s = _fma32(d1[c] + u1[c], b1, s)
            s = _fma32(d2[c] + u2[c], b2, s)
            s = _fma32(d3[c] + u3[c], b3, s)
            out[c] = _fma32(d4[c] + u4[c], b4, s)
        j = 5
    else:
        for c in range(nv):
            out[c] = t[c] * kc
    while j + 4 <= R + 1:
        u1, d1 = ring[_reflect(r - j, H) % L], ring[_reflect(r + j, H) % L]
        u2, d2 = ring[_reflect(r - j - 1, H) % L], ring[_reflect(r + j + 1, H) % L]
        u3, d3 = ring[_reflect(r - j - 2, H) % L], ring[_reflect(r + j + 2, H) % L]
        u4, d4 = ring[_reflect(r - j - 3, H) % L], ring[_reflect(r + j + 3, H) % L]
        b1, b2, b3, b4 = k[R + j], k[R + j + 1], k[R + j + 2], k[R + j + 3]
        for c in range(nv):
            s = out[c]
            s = _fma32(d1[c] + u1[c], b1, s)
            s = _fma32(d2[c] + u2[c], b2, s)
            s = _fma32(d3[c] + u3[c], b3, s)
            out[c] = _fma32(d4[c] + u4[c], b4, s)
        j += 4
    while j <= R:
        u1, d1 = ring[_reflect(r - j, H) % L], ring[_reflect(r + j, H) % L]
        b1 = k[R + j]
        for c in range(nv):
            out[c] = _fma32(d1[c] + u1[c], b1, out[c])
        j += 1
    for c in range(nv, W):
        s = t[c] * kc
        for i in range(1, R + 1):
            s = s + (ring[_reflect(r + i, H) % L, c] + ring[_reflect(r - i, H) % L, c]) * k[R + i]
        out[c] = s


@njit(inline="always")
def _col_filter2(ring, L, k, R, r, H, out0, out1):
    """:func:`_col_filter` at rows ``r`` and ``r + 1`` at once (``R`` a multiple of 4): each
    group of four tap pairs loads the ten rows the two rows' sums take once (the same
    operations on each row as :func:`_col_filter`)."""
    W = out0.shape[0]
    nv = W - W % 8
    kc = k[R]
    t0 = ring[r % L]
    t1 = ring[_reflect(r + 1, H) % L]
    for c in range(nv):
        out0[c] = t0[c] * kc
        out1[c] = t1[c] * kc
    j = 1
    while j + 4 <= R + 1:
        # row r's pair i (i = j...j+3) is rows r + i and r - i, row r + 1's rows r + 1 + i
        # and r + 1 - i: rows r - j + 1 ... r - j - 3 and r + j ... r + j + 4
        a0 = ring[_reflect(r - j + 1, H) % L]
        a1 = ring[_reflect(r - j, H) % L]
        a2 = ring[_reflect(r - j - 1, H) % L]
        a3 = ring[_reflect(r - j - 2, H) % L]
        a4 = ring[_reflect(r - j - 3, H) % L]
        e0 = ring[_reflect(r + j, H) % L]
        e1 = ring[_reflect(r + j + 1, H) % L]
        e2 = ring[_reflect(r + j + 2, H) % L]
        e3 = ring[_reflect(r + j + 3, H) % L]
        e4 = ring[_reflect(r + j + 4, H) % L]
        b1, b2, b3, b4 = k[R + j], k[R + j + 1], k[R + j + 2], k[R + j + 3]
        for c in range(nv):
            x0, x1, x2, x3, x4 = e0[c], e1[c], e2[c], e3[c], e4[c]
            y0, y1, y2, y3, y4 = a0[c], a1[c], a2[c], a3[c], a4[c]
            s = out0[c]
            s = _fma32(x0 + y1, b1, s)
            s = _fma32(x1 + y2, b2, s)
            s = _fma32(x2 + y3, b3, s)
            out0[c] = _fma32(x3 + y4, b4, s)
            s = out1[c]
            s = _fma32(x1 + y0, b1, s)
            s = _fma32(x2 + y1, b2, s)
            s = _fma32(x3 + y2, b3, s)
            out1[c] = _fma32(x4 + y3, b4, s)
        j += 4
    for c in range(nv, W):     # the last W % 8 columns: plain multiply-adds
        s = t0[c] * kc
        for i in range(1, R + 1):
            s = s + (ring[_reflect(r + i, H) % L, c] + ring[_reflect(r - i, H) % L, c]) * k[R + i]
        out0[c] = s
        s = t1[c] * kc
        for i in range(1, R + 1):
            s = s + (ring[_reflect(r + 1 + i, H) % L, c]
                     + ring[_reflect(r + 1 - i, H) % L, c]) * k[R + i]
        out1[c] = s


@njit(inline="always")
def _col_filter_rows(ring, L, k, R, r, H, g):
    """Rows ``r`` and ``r + 1`` (``r`` alone if it is the last) of the column filter into
    ``g``: :func:`_col_filter2` when ``R`` is a multiple of 4, else :func:`_col_filter`
    twice."""
    if r + 1 >= H:
        _col_filter(ring, L, k, R, r, H, g[r])
    elif R >= 4 and R % 4 == 0:
        _col_filter2(ring, L, k, R, r, H, g[r], g[r + 1])
    else:
        _col_filter(ring, L, k, R, r, H, g[r])
        _col_filter(ring, L, k, R, r + 1, H, g[r + 1])


@njit(cache=True)
def gaussian_pair(d, ka, kb):
    """OpenCV's GaussianBlur of ``d`` (H, W) float32 (BORDER_REFLECT) with the taps ``ka``
    and with the taps ``kb`` (float32, ``2 R + 1`` each: ``cv2.getGaussianKernel``), in one
    pass over the rows (each row's border extension shared, the row-filtered rows in a
    ring per kernel, the column filter two rows at a time), replicating OpenCV's arithmetic
    (above). Needs ``H, W > 2 R`` for the larger ``R``; found equal for 9 to 33 taps in
    steps of 4 (with 7 and 11 taps OpenCV's last ``W % 4`` columns differ in rare values,
    with 5 or fewer it filters otherwise). Returns ``(blurred by ka, blurred by kb)``."""
    H, W = d.shape
    Ra = (ka.shape[0] - 1) // 2
    Rb = (kb.shape[0] - 1) // 2
    R = max(Ra, Rb)
    xe = np.empty(W + 2 * R, dtype=np.float32)
    # each ring holds the rows from the oldest its next two output rows need to the newest
    La, Lb = R + Ra + 2, R + Rb + 2
    ring_a = np.empty((La, W), dtype=np.float32)
    ring_b = np.empty((Lb, W), dtype=np.float32)
    ga = np.empty((H, W), dtype=np.float32)
    gb = np.empty((H, W), dtype=np.float32)
    done = -1                      # the last row filtered into the rings
    for r in range(0, H, 2):
        while done < min(r + 1 + R, H - 1):
            done += 1
            src = d[done]
            for c in range(W):
                xe[R + c] = src[c]
            for j in range(R):
                xe[R - 1 - j] = src[j]
                xe[R + W + j] = src[W - 1 - j]
            _row_filter(xe[R - Ra:], ka, W, ring_a[done % La])
            _row_filter(xe[R - Rb:], kb, W, ring_b[done % Lb])
        _col_filter_rows(ring_a, La, ka, Ra, r, H, ga)
        _col_filter_rows(ring_b, Lb, kb, Rb, r, H, gb)
    return ga, gb


@njit(cache=True)
def _select(x, n, k, tmp):
    """The value of rank ``k`` (0-based) among ``x[:n]`` (no NaN): quickselect with the
    median of three as pivot, each step a branchless three-way partition into the other
    buffer (the less and the greater values; those equal to the pivot are not moved), so
    that no branch waits on a comparison of the data (2.5x faster than an in-place
    partition on fresh blocks). ``x`` and ``tmp`` (``n`` values each) are overwritten."""
    src = x
    dst = tmp
    off = 0
    m = n
    while m > 1:
        a = src[off]
        b = src[off + m // 2]
        c = src[off + m - 1]
        pivot = max(min(a, b), min(max(a, b), c))
        nl = 0
        ng = 0
        for j in range(m):
            v = src[off + j]
            dst[nl] = v           # kept if less, else overwritten
            nl += v < pivot
            dst[m - 1 - ng] = v   # kept if greater
            ng += v > pivot
        if k < nl:
            off = 0
            m = nl
        elif k >= m - ng:
            k -= m - ng
            off = m - ng
            m = ng
        else:
            return pivot
        src, dst = dst, src
    return src[off]


@njit(cache=True)
def small_median(x, n, work, tmp):
    """``np.median(x[:n])`` (``n >= 1``, no NaN): the middle value, or the two middle
    values' mean for an even ``n``; ``x`` unchanged, ``work`` and ``tmp`` (``n`` values each)
    scratch space."""
    for j in range(n):
        work[j] = x[j]
    k = n // 2
    hi_v = _select(work, n, k, tmp)
    if n % 2:
        return hi_v
    # the value of rank k - 1: hi_v itself when fewer than k values lie below it, else the
    # largest of those below it (two running maxima: shorter chains)
    less = 0
    m0 = -np.inf
    m1 = -np.inf
    for j in range(0, n - 1, 2):
        v0 = x[j]
        v1 = x[j + 1]
        less += (v0 < hi_v) + (v1 < hi_v)
        m0 = max(m0, v0 if v0 < hi_v else -np.inf)
        m1 = max(m1, v1 if v1 < hi_v else -np.inf)
    if less < k:
        return hi_v
    return (max(m0, m1) + hi_v) / 2.0


@njit(cache=True, fastmath={"reassoc", "nsz"})
def _clipped_sums(buf, m, centre, lo, hi):
    """Count, sum and sum of squares of ``buf[:m] - centre`` over the values within
    ``[lo, hi]``, in any order (vectorised)."""
    n = 0
    s1 = 0.0
    s2 = 0.0
    for j in range(m):
        x = buf[j]
        keep = (x >= lo) & (x <= hi)
        dx = x - centre if keep else 0.0
        n += 1 if keep else 0
        s1 += dx
        s2 += dx * dx
    return n, s1, s2


@njit(cache=True)
def _block_noise(buf, m, sub, start_step, clip, passes, scale):
    """The noise figure of one block from its ``m`` values ``buf[:m]`` (:func:`tile_noise`);
    ``sub`` is scratch space of ``3 m`` values at least."""
    k = 0
    for j in range(0, m, start_step):
        sub[k] = buf[j]
        k += 1
    work = sub[k:2 * k]
    tmp = sub[2 * k:3 * k]
    mean = small_median(sub, k, work, tmp)
    for j in range(k):
        sub[j] = abs(sub[j] - mean)
    sd = 1.4826 * small_median(sub, k, work, tmp)
    if not sd > 0:   # most values equal (clipped video): the plain deviation
        _, s1, _ = _clipped_sums(buf, m, 0.0, -np.inf, np.inf)
        mean = s1 / m
        _, _, s2 = _clipped_sums(buf, m, mean, -np.inf, np.inf)
        sd = np.sqrt(s2 / m)
    for _ in range(passes):
        n, s1, s2 = _clipped_sums(buf, m, mean, mean - clip * sd, mean + clip * sd)
        if n == 0:
            break
        shift = s1 / n
        mean = mean + shift
        sd = np.sqrt(max(s2 / n - shift * shift, 0.0))
    return scale * sd


@njit(cache=True)
def tile_noise(g1, g2, mask, tile, step, min_count, start_step, clip, passes, scale):
    """The noise of ``g1 - g2`` per ``tile`` x ``tile`` block (blocks from the top-left
    corner, the last ones cut by the edge), from its values in ``mask`` on every
    ``step``-th row and column of the block, in row-major order: the median and 1.4826
    times the median absolute deviation of every ``start_step``-th of them (their mean and
    standard deviation if that deviation is 0), then
    ``passes`` times the mean and standard deviation of the values within ``clip``
    deviations of the centre, times ``scale``; NaN for a block with fewer than
    ``min_count`` values. Returns ``(rows of blocks, columns of blocks)`` float64 (the
    reference: :func:`reglib.markers._clipped_std`, equal to rounding: the sums here are
    taken in one vectorised pass about the previous centre, not in order about the mean).
    Block by block; :func:`band_noise` computes the same in one pass with the band."""
    H, W = g1.shape
    ny = (H + tile - 1) // tile
    nx = (W + tile - 1) // tile
    out = np.full((ny, nx), np.nan)
    buf = np.empty(tile * tile)
    sub = np.empty(3 * tile * tile)
    for by in range(ny):
        for bx in range(nx):
            m = 0
            for r in range(by * tile, min((by + 1) * tile, H), step):
                for c in range(bx * tile, min((bx + 1) * tile, W), step):
                    if mask[r, c]:
                        buf[m] = np.float64(g1[r, c]) - np.float64(g2[r, c])
                        m += 1
            if m >= min_count:
                out[by, bx] = _block_noise(buf, m, sub, start_step, clip, passes, scale)
    return out


@njit(cache=True)
def band_noise(g1, g2, mask, tile, step, min_count, start_step, clip, passes, scale):
    """:func:`band` and :func:`tile_noise` in one pass over ``g1`` and ``g2`` (row by row:
    each row's samples go to its blocks' buffers, a row of blocks is measured when its last
    row is read), the same values. Returns ``(ds, tiles)``."""
    H, W = g1.shape
    ny = (H + tile - 1) // tile
    nx = (W + tile - 1) // tile
    ds = np.empty((H, W), dtype=np.float32)
    out = np.full((ny, nx), np.nan)
    bufs = np.empty((nx, tile * tile))
    count = np.zeros(nx, dtype=np.int64)
    sub = np.empty(3 * tile * tile)
    for r in range(H):
        for c in range(W):
            v = g1[r, c] - g2[r, c]
            ds[r, c] = v if g1[r, c] + g1[r, c] > v else np.float32(0.0)
        by = r // tile
        if (r - by * tile) % step == 0:
            for bx in range(nx):
                m = count[bx]
                for c in range(bx * tile, min((bx + 1) * tile, W), step):
                    if mask[r, c]:
                        bufs[bx, m] = np.float64(g1[r, c]) - np.float64(g2[r, c])
                        m += 1
                count[bx] = m
        if r == H - 1 or (r + 1) % tile == 0:     # the row of blocks is complete
            for bx in range(nx):
                if count[bx] >= min_count:
                    out[by, bx] = _block_noise(bufs[bx], count[bx], sub, start_step, clip,
                                               passes, scale)
                count[bx] = 0
    return ds, out


@njit(cache=True)
def spread_tiles(tiles, inside, ds, tile):
    """The largest figure of each block and its 8 neighbours (NaN blocks do not count; the
    numpy reference: ``ndimage.maximum_filter`` in :func:`reglib.markers._noise_tiles`);
    -inf where none has a figure. Returns ``(spread, need)``: ``need`` whether such a block
    holds a pixel in ``inside`` or with ``ds != 0`` (it then needs the field's figure)."""
    ny, nx = tiles.shape
    H, W = ds.shape
    out = np.full((ny, nx), -np.inf)
    need = False
    for by in range(ny):
        for bx in range(nx):
            v = -np.inf
            for y in range(max(by - 1, 0), min(by + 2, ny)):
                for x in range(max(bx - 1, 0), min(bx + 2, nx)):
                    t = tiles[y, x]
                    if np.isfinite(t) and t > v:
                        v = t
            out[by, bx] = v
            if v == -np.inf and not need:
                for r in range(by * tile, min((by + 1) * tile, H)):
                    for c in range(bx * tile, min((bx + 1) * tile, W)):
                        if inside[r, c] or ds[r, c] != 0:
                            need = True
    return out, need


@njit(cache=True, inline="always")
def _low(tiles, tile, r, c, n_sigma, low_floor):
    """The noise threshold of pixel (r, c): ``max(n_sigma * its block's figure,
    low_floor)``, the numpy reference's ``np.maximum(n_sigma * noise_map, 0.02 * peak)``."""
    return max(n_sigma * tiles[r // tile, c // tile], low_floor)


@njit(cache=True)
def above_noise(ds, tiles, tile, n_sigma, low_floor):
    """``ds > low`` per pixel (uint8, for the labelling), ``low`` from the blocks' figures
    ``tiles`` (:func:`_low`); and the bounding box of the pixels above it, rows ``[r0, r1)``
    and columns ``[c0, c1)`` (none: ``r1 == 0``)."""
    H, W = ds.shape
    out = np.empty((H, W), dtype=np.uint8)
    low = np.empty(W)   # float64: the comparison of the reference
    r0, r1, c0, c1 = H, 0, W, 0
    for r in range(H):
        if r % tile == 0:    # the row of blocks' thresholds, per column
            for c in range(W):
                low[c] = max(n_sigma * tiles[r // tile, c // tile], low_floor)
        row = ds[r]
        o = out[r]
        hits = 0
        for c in range(W):
            v = row[c] > low[c]
            o[c] = v
            hits += v
        if hits:
            r0, r1 = min(r0, r), r + 1
            for c in range(W):
                if o[c]:
                    c0 = min(c0, c)
                    break
            for c in range(W - 1, -1, -1):
                if o[c]:
                    c1 = max(c1, c + 1)
                    break
    if r1 == 0:
        return out, 0, 0, 0, 0
    return out, r0, r1, c0, c1


@njit(cache=True)
def above_region_thresholds(regions, n_regions, ds, tiles, tile, n_sigma, low_floor,
                            base_floor, rel, r_off, c_off):
    """The pixels of a labelled region above ``max(base, rel * the region's peak of ds)``,
    ``base = max(low, base_floor)`` per pixel (:func:`_low`). ``regions`` covers rows
    ``r_off...`` and columns ``c_off...`` of ``ds`` (the blocks' frame). Returns ``(uint8
    pixels, r0, r1, c0, c1)``: their bounding box in ``regions`` (as :func:`above_noise`)."""
    H, W = regions.shape
    peak = np.zeros(n_regions + 1)
    for r in range(H):
        for c in range(W):
            k = regions[r, c]
            if k > 0 and ds[r + r_off, c + c_off] > peak[k]:
                peak[k] = ds[r + r_off, c + c_off]
    out = np.zeros((H, W), dtype=np.uint8)
    r0, r1, c0, c1 = H, 0, W, 0
    for r in range(H):
        for c in range(W):
            k = regions[r, c]
            if k > 0:
                base = max(_low(tiles, tile, r + r_off, c + c_off, n_sigma, low_floor),
                           base_floor)
                t = max(base, rel * peak[k])
                if ds[r + r_off, c + c_off] > t:
                    out[r, c] = 1
                    r0, r1 = min(r0, r), max(r1, r + 1)
                    c0, c1 = min(c0, c), max(c1, c + 1)
    if r1 == 0:
        return out, 0, 0, 0, 0
    return out, r0, r1, c0, c1


@njit(cache=True)
def label_boxes(labels, n):
    """Pixel count and bounding box (rows ``[r0, r1)``, columns ``[c0, c1)``) of labels 1..n:
    ``(areas (n,), boxes (n, 4))``."""
    areas = np.zeros(n + 1)
    boxes = np.empty((n + 1, 4), dtype=np.int64)
    H, W = labels.shape
    for k in range(n + 1):    # element by element: slice assignments compile numba's
        boxes[k, 0] = H       # shape-checked copy with its message formatting (~1 s cold)
        boxes[k, 1] = -1
        boxes[k, 2] = W
        boxes[k, 3] = -1
    for r in range(H):
        for c in range(W):
            k = labels[r, c]
            if k > 0:             # most pixels are background: no chain of updates on [0]
                areas[k] += 1.0
                boxes[k, 0] = min(boxes[k, 0], r)
                boxes[k, 1] = max(boxes[k, 1], r)
                boxes[k, 2] = min(boxes[k, 2], c)
                boxes[k, 3] = max(boxes[k, 3], c)
    for k in range(n + 1):
        boxes[k, 1] += 1
        boxes[k, 3] += 1
    return areas[1:], boxes[1:]


@njit(cache=True)
def blob_centroid(d, labels, k, r0, r1, c0, c1, lr, lc, area, max_elongation,
                  centroid_floor):
    """The sub-pixel centroid of blob ``k`` (its pixels: ``labels == k`` within rows
    ``r0:r1`` and columns ``c0:c1`` of ``d``; ``labels`` covers ``d`` from row ``lr`` and
    column ``lc``), as the detector's Python loop computes it: rejected
    (``ok`` False) when not round (the 2x2 sample covariance of its pixels has a
    non-positive eigenvalue or an axis ratio above ``max_elongation``); else the mean over a
    disc about the blob of ``d`` above a floor (the median of a ring around the disc plus
    ``centroid_floor`` times the disc's height above it), the disc re-centred three times.
    Returns ``(ok, cx, cy, x0, x1, y0, y1)`` (the last window)."""
    H, W = d.shape
    # raw moments about the box's corner (small numbers: no cancellation to speak of)
    n = 0
    sx = sy = sxx = syy = sxy = 0.0
    for r in range(r0, r1):
        for c in range(c0, c1):
            if labels[r - lr, c - lc] == k:
                u = float(c - c0)
                v = float(r - r0)
                n += 1
                sx += u
                sy += v
                sxx += u * u
                syy += v * v
                sxy += u * v
    mx = sx / n
    my = sy / n
    cx = c0 + mx
    cy = r0 + my
    if n > 2:
        cxx = (sxx - n * mx * mx) / (n - 1)
        cyy = (syy - n * my * my) / (n - 1)
        cxy = (sxy - n * mx * my) / (n - 1)
        half = 0.5 * (cxx + cyy)
        rad = np.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
        ev0 = half - rad
        ev1 = half + rad
        if ev0 <= 0 or np.sqrt(ev1 / ev0) > max_elongation:
            return False, cx, cy, 0, 0, 0, 0
    r_in = np.sqrt(area / np.pi) * 1.6 + 1.5
    x0 = x1 = y0 = y1 = 0
    ring = np.empty(H * W if H * W < 4096 else 4096)
    # each window pixel's distance from the centre, from the first loop for the second
    side = int(2.0 * r_in + 10.0) + 1      # the window's side at most (rows and columns)
    dist = np.empty(side * side)
    for _ in range(3):
        x0 = int(max(cx - r_in - 4, 0))
        x1 = int(min(cx + r_in + 5, W))
        y0 = int(max(cy - r_in - 4, 0))
        y1 = int(min(cy + r_in + 5, H))
        ww = x1 - x0
        m = 0
        top = -np.inf
        any_inner = False
        for r in range(y0, y1):
            for c in range(x0, x1):
                rr = np.hypot(c - cx, r - cy)
                dist[(r - y0) * ww + (c - x0)] = rr
                if rr > r_in and rr <= r_in + 3:
                    if m == ring.shape[0]:
                        bigger = np.empty(2 * m)
                        for j in range(m):  # not a slice copy: see testbed._distortion_numba
                            bigger[j] = ring[j]
                        ring = bigger
                    ring[m] = np.float64(d[r, c])
                    m += 1
                if rr <= r_in:
                    any_inner = True
                    if d[r, c] > top:
                        top = np.float64(d[r, c])
        bg = np.median(ring[:m]) if m > 0 else 0.0
        floor = bg + centroid_floor * (top - bg) if any_inner else bg
        sw = 0.0
        swx = 0.0
        swy = 0.0
        for r in range(y0, y1):
            for c in range(x0, x1):
                if dist[(r - y0) * ww + (c - x0)] <= r_in:
                    w = max(np.float64(d[r, c]) - floor, 0.0)
                    sw += w
                    swx += w * c
                    swy += w * r
        if sw <= 0:
            break
        cx = swx / sw
        cy = swy / sw
    return True, cx, cy, x0, x1, y0, y1


@njit(cache=True)
def blob_centroids(d, labels, n, lr, lc, ds, mask, use_mask, min_area, max_area,
                   max_elongation, centroid_floor):
    """The detector's blob loop: each of the labels 1..n (``labels`` covers ``d`` from row
    ``lr`` and column ``lc``) of ``min_area..max_area`` pixels that :func:`blob_centroid`
    accepts, and (with ``use_mask``) whose last centroid window lies in ``mask``: its
    centroid (x, y) and the largest ``ds`` over its pixels, in label order. Returns
    ``(xy (K, 2), strength (K,))``."""
    areas, boxes = label_boxes(labels, n)
    xy = np.empty((n, 2))
    strength = np.empty(n)
    K = 0
    for k in range(n):
        if not (min_area <= areas[k] <= max_area):
            continue
        r0, r1 = boxes[k, 0] + lr, boxes[k, 1] + lr
        c0, c1 = boxes[k, 2] + lc, boxes[k, 3] + lc
        ok, cx, cy, x0, x1, y0, y1 = blob_centroid(d, labels, k + 1, r0, r1, c0, c1, lr, lc,
                                                   areas[k], max_elongation, centroid_floor)
        if not ok:
            continue
        if use_mask:
            cut = False
            for r in range(y0, y1):
                for c in range(x0, x1):
                    if not mask[r, c]:
                        cut = True
            if cut:
                continue     # cut by the edge of the field
        top = -np.inf
        for r in range(r0, r1):
            for c in range(c0, c1):
                if labels[r - lr, c - lc] == k + 1 and ds[r, c] > top:
                    top = np.float64(ds[r, c])
        xy[K, 0] = cx
        xy[K, 1] = cy
        strength[K] = top
        K += 1
    return xy[:K], strength[:K]


@njit(inline="always")
def _smallest_gap(s):
    """The smallest gap between consecutive values of ``s``."""
    min_gap = np.inf
    for m in range(s.shape[0] - 1):
        min_gap = min(min_gap, s[m + 1] - s[m])
    return min_gap


@njit(inline="always")
def _hypothesis_map(t, s, i, j, p, q, tolerance, min_gap):
    """The affine map ``t = a s + b`` of hypothesis "blobs i, j are beads p, q" and its
    tolerance (px): ``(a, b, lim)``."""
    a = (t[j] - t[i]) / (s[q] - s[p])
    b = t[i] - a * s[p]
    return a, b, tolerance * (abs(a) * min_gap)


@njit(inline="always")
def _nearest_bead(tk, a, b, s):
    """The bead whose predicted place ``a s + b`` is nearest to ``tk`` (the first of equals)
    and its distance (px)."""
    best = np.inf
    arg = 0
    for m in range(s.shape[0]):
        v = abs(tk - (a * s[m] + b))
        if v < best:
            best = v
            arg = m
    return arg, best


@njit(cache=True)
def row_hypotheses(t, s, tolerance):
    """The spacing hypotheses of :func:`reglib.markers.identify_row`: for every blob pair
    ``i < j`` (in ``itertools.combinations`` order) and bead pair ``p != q`` (``p``-major),
    the affine map ``t = a s + b`` through them, each blob's nearest predicted bead ``jb``,
    its distance ``e`` (px), and whether it is within ``tolerance`` times the smallest
    predicted gap. Returns ``(jb (B, K), e (B, K), inl (B, K), count (B,))``. The detector
    takes the counts alone (:func:`row_counts`), then these rows for the leading hypotheses
    (:func:`row_hypotheses_at`): the same values, without the (B, K) arrays of all."""
    K = t.shape[0]
    n = s.shape[0]
    min_gap = _smallest_gap(s)
    B = (K * (K - 1) // 2) * n * (n - 1)
    jb = np.empty((B, K), dtype=np.int64)
    e = np.empty((B, K))
    inl = np.empty((B, K), dtype=np.bool_)
    count = np.zeros(B, dtype=np.int64)
    h = 0
    for i in range(K):
        for j in range(i + 1, K):
            for p in range(n):
                for q in range(n):
                    if p == q:
                        continue
                    a, b, lim = _hypothesis_map(t, s, i, j, p, q, tolerance, min_gap)
                    for k in range(K):
                        arg, best = _nearest_bead(t[k], a, b, s)
                        jb[h, k] = arg
                        e[h, k] = best
                        inside = best < lim
                        inl[h, k] = inside
                        if inside:
                            count[h] += 1
                    h += 1
    return jb, e, inl, count


@njit(cache=True)
def row_counts(t, s, tolerance):
    """``count`` of :func:`row_hypotheses` (B,) alone: the same values (each blob's
    distance to its nearest predicted bead is the smallest of the same distances), 2.3x
    faster (0.037 against 0.085 ms on a row of 8 blobs and 8 beads)."""
    K = t.shape[0]
    n = s.shape[0]
    min_gap = _smallest_gap(s)
    count = np.zeros((K * (K - 1) // 2) * n * (n - 1), dtype=np.int64)
    h = 0
    for i in range(K):
        for j in range(i + 1, K):
            for p in range(n):
                for q in range(n):
                    if p == q:
                        continue
                    a, b, lim = _hypothesis_map(t, s, i, j, p, q, tolerance, min_gap)
                    c = 0
                    for k in range(K):
                        c += _nearest_bead(t[k], a, b, s)[1] < lim
                    count[h] = c
                    h += 1
    return count


@njit(cache=True)
def row_hypotheses_at(t, s, tolerance, hyp):
    """The rows ``hyp`` (hypothesis indices, as :func:`row_hypotheses` numbers them) of
    :func:`row_hypotheses`' ``jb``, ``e`` and ``inl``, in the order of ``hyp``: the same
    values. Returns ``(jb (len(hyp), K), e, inl)``."""
    K = t.shape[0]
    n = s.shape[0]
    min_gap = _smallest_gap(s)
    per_pair = n * (n - 1)
    H = hyp.shape[0]
    jb = np.empty((H, K), dtype=np.int64)
    e = np.empty((H, K))
    inl = np.empty((H, K), dtype=np.bool_)
    for r in range(H):
        h = hyp[r]
        pair, rest = h // per_pair, h % per_pair
        p, q = rest // (n - 1), rest % (n - 1)
        q += q >= p                 # q runs over the beads other than p
        i = 0                       # the blob pair of index ``pair`` in combinations order
        while pair >= K - 1 - i:
            pair -= K - 1 - i
            i += 1
        j = i + 1 + pair
        a, b, lim = _hypothesis_map(t, s, i, j, p, q, tolerance, min_gap)
        for k in range(K):
            arg, best = _nearest_bead(t[k], a, b, s)
            jb[r, k] = arg
            e[r, k] = best
            inl[r, k] = best < lim
    return jb, e, inl


@njit(cache=True, error_model="numpy")
def resolve_assignments(j, e, inl, top, s, t, tolerance):
    """The candidates of :func:`reglib.markers.identify_row` (hypotheses ``top`` of
    :func:`row_hypotheses`): the first hypothesis of each distinct assignment, that
    assignment with two blobs on one bead resolved (the closer keeps it, the lower index on
    a tie), the distinct results in order of first appearance, and an approximate score
    (its count less the RMS of a line fit of ``t`` on ``s`` in units of ``0.2 tolerance
    |slope|`` times the smallest gap; summed in order, not as numpy sums: the caller
    rescores the leaders with numpy). Returns
    ``(assignments (C, K), score (C,), hypothesis (C,))``."""
    K = j.shape[1]
    n = s.shape[0]
    min_gap = np.inf
    for q in range(n - 1):
        min_gap = min(min_gap, s[q + 1] - s[q])
    C = top.shape[0]
    finals = np.empty((C, K), dtype=np.int64)
    score = np.empty(C)
    which = np.empty(C, dtype=np.int64)
    nc = 0
    for ih in range(C):
        # the first hypothesis of each assignment before the doubles are resolved (the
        # reference's np.unique): a later one with the same assignment is not looked at
        h = top[ih]
        seen = False
        for ih2 in range(ih):
            h2 = top[ih2]
            same = True
            for i in range(K):
                if (inl[h, i] != inl[h2, i]) or (inl[h, i] and j[h, i] != j[h2, i]):
                    same = False
                    break
            if same:
                seen = True
                break
        if seen:
            continue
        for i in range(K):
            keep = inl[h, i]
            if keep:
                for i2 in range(K):
                    if (i2 != i and inl[h, i2] and j[h, i2] == j[h, i]
                            and (e[h, i2] < e[h, i] or (e[h, i2] == e[h, i] and i2 < i))):
                        keep = False
                        break
            finals[nc, i] = j[h, i] if keep else -1
        dup = False
        for q in range(nc):
            same = True
            for i in range(K):
                if finals[q, i] != finals[nc, i]:
                    same = False
                    break
            if same:
                dup = True
                break
        if dup:
            continue
        cnt = 0
        xm = 0.0
        ym = 0.0
        for i in range(K):
            if finals[nc, i] >= 0:
                cnt += 1
                xm += s[finals[nc, i]]
                ym += t[i]
        xm /= cnt
        ym /= cnt
        sxy = 0.0
        sxx = 0.0
        for i in range(K):
            if finals[nc, i] >= 0:
                dx = s[finals[nc, i]] - xm
                sxy += dx * (t[i] - ym)
                sxx += dx * dx
        slope = sxy / sxx
        icpt = ym - slope * xm
        r2 = 0.0
        for i in range(K):
            if finals[nc, i] >= 0:
                r = t[i] - (slope * s[finals[nc, i]] + icpt)
                r2 += r * r
        rms = np.sqrt(r2 / cnt)
        unit = 0.2 * tolerance * abs(slope) * min_gap
        score[nc] = cnt - rms / unit
        which[nc] = h
        nc += 1
    return finals[:nc], score[:nc], which[:nc]
