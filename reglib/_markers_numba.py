"""Compiled passes of the fast marker detector (:func:`reglib.markers.detect_markers`).

Each computes what the numpy steps of the detector compute (the same values, in one pass
over the field's bounding box instead of several whole-array temporaries); the reference
detector (``detect_markers(reference=True)``, scipy.ndimage alone) is compared with the
fast one in tests/reglib/test_calibration.py.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def centred_difference(a, b, mask, sign, max_abs):
    """``d = sign * (a - b)`` less its median over ``mask`` (integer frames: the median by
    counting, the two middle values' mean for an even count), 0 outside ``mask``. Returns
    ``(d float64, d float32, pixels in mask)``; ``max_abs`` bounds ``|a - b|`` (255 for 8-bit
    frames). The arrays may be views (a crop of a frame)."""
    H, W = a.shape
    counts = np.zeros(2 * max_abs + 1, dtype=np.int64)
    n = 0
    for r in range(H):
        for c in range(W):
            if mask[r, c]:
                counts[sign * (np.int64(a[r, c]) - np.int64(b[r, c])) + max_abs] += 1
                n += 1
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
    d = np.zeros((H, W))
    d32 = np.zeros((H, W), dtype=np.float32)
    for r in range(H):
        for c in range(W):
            if mask[r, c]:
                v = sign * (np.float64(a[r, c]) - np.float64(b[r, c])) - med
                d[r, c] = v
                d32[r, c] = v
    return d, d32, n


@njit(cache=True)
def band(g1, g2, mask, n):
    """``ds = g1 - g2`` (float32); its values in ``mask`` (``n`` pixels; all of them if
    ``n`` is 0), row-major; then ``ds`` where ``g1 > 0.5 ds`` and 0 elsewhere, and its
    maximum. Returns ``(ds after the rim test, the masked values before it, the maximum)``."""
    H, W = g1.shape
    use_all = n == 0
    vals = np.empty(H * W if use_all else n, dtype=np.float32)
    ds = np.empty((H, W), dtype=np.float32)
    peak = -np.inf
    j = 0
    for r in range(H):
        for c in range(W):
            v = g1[r, c] - g2[r, c]
            if use_all or mask[r, c]:
                vals[j] = v
                j += 1
            v = v if g1[r, c] > 0.5 * v else np.float32(0.0)
            ds[r, c] = v
            peak = max(peak, v)
    return ds, vals, peak


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
    reference: :func:`reglib.markers._clipped_std`)."""
    H, W = g1.shape
    ny = (H + tile - 1) // tile
    nx = (W + tile - 1) // tile
    out = np.full((ny, nx), np.nan)
    buf = np.empty(tile * tile)
    sub = np.empty(tile * tile)
    for by in range(ny):
        for bx in range(nx):
            m = 0
            for r in range(by * tile, min((by + 1) * tile, H), step):
                for c in range(bx * tile, min((bx + 1) * tile, W), step):
                    if mask[r, c]:
                        buf[m] = np.float64(g1[r, c]) - np.float64(g2[r, c])
                        m += 1
            if m < min_count:
                continue
            k = 0
            for j in range(0, m, start_step):
                sub[k] = buf[j]
                k += 1
            mean = np.median(sub[:k])
            for j in range(k):
                sub[j] = abs(sub[j] - mean)
            sd = 1.4826 * np.median(sub[:k])
            if not sd > 0:   # most values equal (clipped video): the plain deviation
                s1 = 0.0
                for j in range(m):
                    s1 += buf[j]
                mean = s1 / m
                s2 = 0.0
                for j in range(m):
                    s2 += (buf[j] - mean) ** 2
                sd = np.sqrt(s2 / m)
            for _ in range(passes):
                lo = mean - clip * sd
                hi = mean + clip * sd
                n = 0
                s1 = 0.0
                for j in range(m):
                    if buf[j] >= lo and buf[j] <= hi:
                        s1 += buf[j]
                        n += 1
                if n == 0:
                    break
                mean = s1 / n
                s2 = 0.0
                for j in range(m):
                    if buf[j] >= lo and buf[j] <= hi:
                        s2 += (buf[j] - mean) ** 2
                sd = np.sqrt(s2 / n)
            out[by, bx] = scale * sd
    return out


@njit(cache=True, inline="always")
def _low(tiles, tile, r, c, n_sigma, low_floor):
    """The noise threshold of pixel (r, c): ``max(n_sigma * its block's figure,
    low_floor)``, the numpy reference's ``np.maximum(n_sigma * noise_map, 0.02 * peak)``."""
    return max(n_sigma * tiles[r // tile, c // tile], low_floor)


@njit(cache=True)
def above_noise(ds, tiles, tile, n_sigma, low_floor):
    """``ds > low`` per pixel (uint8, for the labelling), ``low`` from the blocks' figures
    ``tiles`` (:func:`_low`)."""
    H, W = ds.shape
    out = np.zeros((H, W), dtype=np.uint8)
    for r in range(H):
        for c in range(W):
            if ds[r, c] > _low(tiles, tile, r, c, n_sigma, low_floor):
                out[r, c] = 1
    return out


@njit(cache=True)
def above_region_thresholds(regions, n_regions, ds, tiles, tile, n_sigma, low_floor,
                            base_floor, rel):
    """The pixels of a labelled region above ``max(base, rel * the region's peak of ds)``,
    ``base = max(low, base_floor)`` per pixel (:func:`_low`)."""
    H, W = ds.shape
    peak = np.zeros(n_regions + 1)
    for r in range(H):
        for c in range(W):
            k = regions[r, c]
            if k > 0 and ds[r, c] > peak[k]:
                peak[k] = ds[r, c]
    out = np.zeros((H, W), dtype=np.bool_)
    for r in range(H):
        for c in range(W):
            k = regions[r, c]
            if k > 0:
                base = max(_low(tiles, tile, r, c, n_sigma, low_floor), base_floor)
                t = max(base, rel * peak[k])
                out[r, c] = ds[r, c] > t
    return out


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
def blob_centroid(d, labels, k, r0, r1, c0, c1, area, max_elongation, centroid_floor):
    """The sub-pixel centroid of blob ``k`` (its pixels: ``labels == k`` within rows
    ``r0:r1`` and columns ``c0:c1``), as the detector's Python loop computes it: rejected
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
            if labels[r, c] == k:
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
    for _ in range(3):
        x0 = int(max(cx - r_in - 4, 0))
        x1 = int(min(cx + r_in + 5, W))
        y0 = int(max(cy - r_in - 4, 0))
        y1 = int(min(cy + r_in + 5, H))
        m = 0
        top = -np.inf
        any_inner = False
        for r in range(y0, y1):
            for c in range(x0, x1):
                rr = np.hypot(c - cx, r - cy)
                if rr > r_in and rr <= r_in + 3:
                    if m == ring.shape[0]:
                        bigger = np.empty(2 * m)
                        for j in range(m):  # not a slice copy: see testbed._distortion_numba
                            bigger[j] = ring[j]
                        ring = bigger
                    ring[m] = d[r, c]
                    m += 1
                if rr <= r_in:
                    any_inner = True
                    if d[r, c] > top:
                        top = d[r, c]
        bg = np.median(ring[:m]) if m > 0 else 0.0
        floor = bg + centroid_floor * (top - bg) if any_inner else bg
        sw = 0.0
        swx = 0.0
        swy = 0.0
        for r in range(y0, y1):
            for c in range(x0, x1):
                if np.hypot(c - cx, r - cy) <= r_in:
                    w = max(d[r, c] - floor, 0.0)
                    sw += w
                    swx += w * c
                    swy += w * r
        if sw <= 0:
            break
        cx = swx / sw
        cy = swy / sw
    return True, cx, cy, x0, x1, y0, y1


@njit(cache=True)
def row_hypotheses(t, s, tolerance):
    """The spacing hypotheses of :func:`reglib.markers.identify_row`: for every blob pair
    ``i < j`` (in ``itertools.combinations`` order) and bead pair ``p != q`` (``p``-major),
    the affine map ``t = a s + b`` through them, each blob's nearest predicted bead ``jb``,
    its distance ``e`` (px), and whether it is within ``tolerance`` times the smallest
    predicted gap. Returns ``(jb (B, K), e (B, K), inl (B, K), count (B,))``."""
    K = t.shape[0]
    n = s.shape[0]
    min_gap = np.inf
    for m in range(n - 1):
        min_gap = min(min_gap, s[m + 1] - s[m])
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
                    a = (t[j] - t[i]) / (s[q] - s[p])
                    b = t[i] - a * s[p]
                    lim = tolerance * (abs(a) * min_gap)
                    for k in range(K):
                        best = np.inf
                        arg = 0
                        for m in range(n):
                            v = abs(t[k] - (a * s[m] + b))
                            if v < best:
                                best = v
                                arg = m
                        jb[h, k] = arg
                        e[h, k] = best
                        inside = best < lim
                        inl[h, k] = inside
                        if inside:
                            count[h] += 1
                    h += 1
    return jb, e, inl, count
