"""Calibration of a fluoroscopic view in robot coordinates: markers, two-plane TPS, X-ray paths.

The robot moves a radiolucent rod with steel beads along a *near* and a *far* plane between
source and intensifier; a frame is taken after every move (Guéziec et al. 1998, Section II).

1. :func:`detect_markers` finds the beads that appeared between two consecutive frames (the
   rod's new position) as blobs of the difference of the log images, with sub-pixel,
   background-subtracted intensity-weighted centroids.
2. :func:`identify_row` says which bead of the rod each blob is: the beads' unequal spacing
   along the rod is matched to the blobs' positions along the imaged row by a 1-D affine map
   (consensus over all 2-point hypotheses), so beads outside the field or hidden are simply
   missing and stray blobs are rejected.
3. :class:`ThinPlateSpline` maps pixel ``(x, y)`` to the 3-D robot-frame point of a plane
   (``scipy.interpolate.RBFInterpolator``, thin-plate kernel, degree 1); :func:`tps_fit_svd`
   / :func:`tps_evaluate` are the paper's direct solve of ``[[K + lam I, P], [P^T, 0]]`` by
   SVD, kept as the reference.
4. :class:`Calibration` maps any pixel to its X-ray path in the robot frame: the line through
   its near-plane and far-plane points. :meth:`Calibration.center_of_perspective` is the
   point closest to a bundle of paths.

Conventions: pixel coordinates ``(x, y) = (col, row)``, the centre of the top-left pixel at
(0, 0); images ``(H, W)`` indexed ``[row, col]``; robot frame in mm.

Smoothing is given in the units of the paper's kernel ``k = r^2 log(r^2) / (16 pi)`` with
``r`` in pixels (the paper used ``lam = 0.01``); scipy's thin-plate kernel is ``r^2 log r``,
``8 pi`` times larger, so ``RBFInterpolator`` receives ``smoothing = 8 pi lam``.

Planes are fitted directly to 3-D points (three TPS sharing one kernel matrix). For markers
that lie exactly in a plane this equals the paper's ``u(x, y), v(x, y)`` in-plane coordinates
mapped to 3-D (the fit is linear in the values and reproduces affine functions).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.interpolate import RBFInterpolator

from reglib.geometry import closest_point_to_lines, point_line_distances

__all__ = [
    "PLANE_NAMES",
    "SweepData",
    "Markers",
    "ThinPlateSpline",
    "Calibration",
    "detect_markers",
    "identify_row",
    "find_markers",
    "calibrate",
    "tps_fit_svd",
    "tps_evaluate",
    "tps_kernel",
]

PLANE_NAMES = {-1: "reference", 0: "near", 1: "far", 2: "validation"}
_EIGHT_PI = 8.0 * np.pi


def _as_xy(xy, name="xy_px") -> np.ndarray:
    a = np.asarray(xy, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of pixel (x, y), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or inf")
    return a


# --------------------------------------------------------------------------- TPS reference
def tps_kernel(r2) -> np.ndarray:
    """The paper's thin-plate kernel ``r^2 log(r^2) / (16 pi)`` of squared distances (px^2)."""
    r2 = np.asarray(r2, dtype=np.float64)
    out = np.zeros_like(r2)
    pos = r2 > 0
    out[pos] = r2[pos] * np.log(r2[pos]) / (16.0 * np.pi)
    return out


def tps_fit_svd(xy_px, values, smoothing: float = 0.01) -> np.ndarray:
    """Coefficients of a smoothing thin-plate spline by the paper's direct SVD solve.

    Solves ``[[K + lam I, P], [P^T, 0]] [a; c] = [values; 0]`` with ``K_ij = k(|p_i - p_j|)``
    (see :func:`tps_kernel`) and ``P = [1, x_i, y_i]``, through the SVD (pseudo-inverse).

    Parameters
    ----------
    xy_px : (n, 2) centres, px.
    values : (n,) or (n, m) values at the centres.
    smoothing : lam >= 0.

    Returns
    -------
    coef : (n + 3, m) array: ``a`` (n rows) then the affine part ``c`` (constant, x, y).
    """
    xy = _as_xy(xy_px)
    v = np.asarray(values, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    n = len(xy)
    if v.shape[0] != n:
        raise ValueError(f"values: expected {n} rows (one per centre), got {v.shape[0]}")
    if n < 3:
        raise ValueError(f"tps_fit_svd: at least 3 centres are needed, got {n}")
    d2 = np.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=-1)
    A = np.zeros((n + 3, n + 3))
    A[:n, :n] = tps_kernel(d2) + smoothing * np.eye(n)
    P = np.column_stack([np.ones(n), xy])
    A[:n, n:] = P
    A[n:, :n] = P.T
    b = np.zeros((n + 3, v.shape[1]))
    b[:n] = v
    U, s, Vt = np.linalg.svd(A)
    keep = s > s[0] * 1e-13
    return (Vt[keep].T / s[keep]) @ (U[:, keep].T @ b)


def tps_evaluate(coef, centres_px, xy_px) -> np.ndarray:
    """Evaluate a spline of :func:`tps_fit_svd` at ``xy_px`` (N, 2); returns (N, m)."""
    c = _as_xy(centres_px, "centres_px")
    xy = _as_xy(xy_px)
    n = len(c)
    d2 = np.sum((xy[:, None, :] - c[None, :, :]) ** 2, axis=-1)
    return tps_kernel(d2) @ coef[:n] + np.column_stack([np.ones(len(xy)), xy]) @ coef[n:]


# --------------------------------------------------------------------------- TPS
@dataclass(frozen=True)
class ThinPlateSpline:
    """A smoothing thin-plate spline from pixels ``(x, y)`` to values (e.g. a 3-D point, mm).

    Built by :meth:`fit`; call it with ``(N, 2)`` pixel coordinates to get ``(N, m)``.
    Calls use a vectorised evaluation (kernel matrix by one matrix product per chunk of
    pixels) of coefficients solved directly from the same system as scipy's; the library's
    ``RBFInterpolator`` (``interpolator``, :meth:`reference`) is kept as the reference.
    """

    centres_px: np.ndarray
    values: np.ndarray
    smoothing: float
    interpolator: RBFInterpolator = field(repr=False)
    coef: np.ndarray = field(repr=False)          # (n + 3, m): kernel weights, then affine
    shift_px: np.ndarray = field(repr=False)      # (2,) the centres' mean (conditioning)

    @classmethod
    def fit(cls, xy_px, values, *, smoothing: float = 0.01) -> ThinPlateSpline:
        """Fit to ``xy_px`` (n, 2) px and ``values`` (n, m); ``smoothing`` in paper units.

        Raises ``ValueError`` with fewer than 3 centres, collinear centres (no affine part
        can be fitted), or a negative smoothing.
        """
        xy = _as_xy(xy_px)
        v = np.asarray(values, dtype=np.float64)
        v = v[:, None] if v.ndim == 1 else v
        if v.shape[0] != len(xy):
            raise ValueError(f"values: expected {len(xy)} rows, got {v.shape[0]}")
        if smoothing < 0:
            raise ValueError(f"smoothing must be >= 0, got {smoothing}")
        if len(xy) < 3:
            raise ValueError(f"thin-plate spline: at least 3 markers are needed, got {len(xy)}")
        shift = xy.mean(axis=0)
        centred = xy - shift
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[-1] < 1e-6 * max(sv[0], 1e-300):
            raise ValueError("thin-plate spline: the markers are collinear in the image")
        interp = RBFInterpolator(xy, v, kernel="thin_plate_spline", degree=1,
                                 smoothing=_EIGHT_PI * smoothing)
        n = len(xy)
        A = np.zeros((n + 3, n + 3))
        A[:n, :n] = _phi(_sq_dist(centred, centred)) + _EIGHT_PI * smoothing * np.eye(n)
        P = np.column_stack([np.ones(n), centred])
        A[:n, n:] = P
        A[n:, :n] = P.T
        rhs = np.zeros((n + 3, v.shape[1]))
        rhs[:n] = v
        coef = np.linalg.solve(A, rhs)
        return cls(xy, v, float(smoothing), interp, coef, shift)

    def __call__(self, xy_px) -> np.ndarray:
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy_px: expected (N, 2), got {xy.shape}")
        c = self.centres_px - self.shift_px
        n = len(c)
        out = np.empty((len(xy), self.values.shape[1]))
        step = 32768  # bounded memory on whole images
        for i in range(0, len(xy), step):
            q = xy[i:i + step] - self.shift_px
            out[i:i + step] = (_phi(_sq_dist(q, c)) @ self.coef[:n] + self.coef[n]
                               + q @ self.coef[n + 1:])
        return out

    def reference(self, xy_px) -> np.ndarray:
        """The same spline evaluated by ``scipy.interpolate.RBFInterpolator``, (N, m)."""
        return self.interpolator(np.asarray(xy_px, dtype=np.float64))

    def residuals(self) -> np.ndarray:
        """Distance between the spline and the marker values at the markers, ``(n,)``."""
        return np.linalg.norm(self(self.centres_px) - self.values, axis=1)


def _sq_dist(a, b) -> np.ndarray:
    """Squared distances (N, n) between rows of a (N, 2) and b (n, 2), by a matrix product."""
    d2 = (a * a).sum(axis=1)[:, None] + (b * b).sum(axis=1)[None, :] - 2.0 * (a @ b.T)
    return np.maximum(d2, 0.0)


def _phi(d2) -> np.ndarray:
    """scipy's thin-plate kernel ``r^2 log r`` of squared distances: ``d2 log(d2) / 2``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 0.5 * d2 * np.log(d2)
    out[d2 <= 0] = 0.0
    return out


# --------------------------------------------------------------------------- detection
def _log_image(img, response: str) -> np.ndarray:
    """The frame in log-intensity units (up to scale): as it is for a logarithmic video
    amplifier, else its logarithm."""
    a = np.asarray(img, dtype=np.float64)
    if response == "log":
        return a
    lo = 0.5 if np.issubdtype(np.asarray(img).dtype, np.integer) else 1e-6 * max(a.max(), 1e-12)
    return np.log(np.maximum(a, lo))


def detect_markers(previous, current, *, polarity: str = "dark", response: str = "log",
                   rel_threshold: float = 0.35,
                   n_sigma: float = 6.0, min_area_px: int = 4, max_area_px: int = 2000,
                   max_elongation: float = 2.0, centroid_floor: float = 0.25,
                   mask=None) -> tuple[np.ndarray, np.ndarray]:
    """Blobs that appeared in ``current`` and not in ``previous`` (the rod's new beads).

    Works on ``d = log(previous) - log(current)`` (for dark markers: the added attenuation,
    independent of what lies behind; with ``response="log"`` the frames already are log
    intensities, as from a logarithmic video amplifier, and are differenced as they are,
    with ``"linear"`` their logarithm is taken); blobs are the connected regions of the
    smoothed ``d`` above ``rel_threshold`` times the peak of the region (above the noise,
    ``n_sigma`` robust standard deviations) they lie in, and above half ``rel_threshold``
    times the frame's peak. Each centroid is the
    mean over a disc about the blob weighted by ``d`` above a floor (the median of a ring
    around the disc, the background, plus ``centroid_floor`` times the blob's height above
    it: this drops the rod's faint band under the bead), iterated with the disc re-centred.

    Parameters
    ----------
    previous, current : (H, W) images (any dtype; intensities, larger = more X-rays).
    polarity : "dark" (markers absorb: darker in ``current``) or "bright".
    mask : (H, W) bool, optional; where to look (e.g. the intensifier's circular field).
        A blob whose centroid window reaches outside it is dropped (cut by the field's edge,
        its centroid would be biased).

    Returns
    -------
    xy_px : (K, 2) sub-pixel centroids (x, y).
    strength : (K,) peak of ``d`` of each blob (log units).
    """
    a, b = np.asarray(previous), np.asarray(current)
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(f"detect_markers: frames must be two (H, W) images of the same shape, "
                         f"got {a.shape} and {b.shape}")
    if polarity not in ("dark", "bright"):
        raise ValueError(f"polarity: expected 'dark' or 'bright', got {polarity!r}")
    if response not in ("log", "linear"):
        raise ValueError(f"response: expected 'log' or 'linear', got {response!r}")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != a.shape:
            raise ValueError(f"mask: expected shape {a.shape}, got {mask.shape}")
    d = _log_image(a, response) - _log_image(b, response)
    if polarity == "bright":
        d = -d
    if mask is not None:
        d = np.where(mask, d, 0.0)
    ds = ndimage.gaussian_filter(d, 1.0)
    noise = 1.4826 * np.median(np.abs(ds - np.median(ds)))
    peak = ds.max()
    if peak <= 0:
        return np.zeros((0, 2)), np.zeros(0)
    # relative threshold per region: each connected region above the noise gets
    # rel_threshold times its own peak (a bright newcomer elsewhere, e.g. an instrument
    # moved into the field, does not raise the threshold for the beads)
    low = max(n_sigma * noise, 0.02 * peak)
    regions, n_regions = ndimage.label(ds > low)
    region_peak = np.zeros(n_regions + 1)
    region_peak[1:] = ndimage.maximum(ds, regions, np.arange(1, n_regions + 1))
    # never below half the global relative threshold: noise specks are regions of their own
    thr = np.maximum(max(low, 0.5 * rel_threshold * peak), rel_threshold * region_peak[regions])
    labels, n = ndimage.label((ds > thr) & (regions > 0))
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0)
    idx = np.arange(1, n + 1)
    areas = ndimage.sum_labels(np.ones_like(ds), labels, idx)
    H, W = d.shape
    yy, xx = np.mgrid[0:H, 0:W]
    out, strength = [], []
    slices = ndimage.find_objects(labels)
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
            px, py, pd = xx[y0:y1, x0:x1], yy[y0:y1, x0:x1], d[y0:y1, x0:x1]
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
    return np.asarray(out, dtype=np.float64), np.asarray(strength)


# --------------------------------------------------------------------------- identification
def identify_row(xy_px, bead_positions_mm, *, tolerance: float = 0.15,
                 min_matched: int = 4) -> tuple[np.ndarray, float]:
    """Which bead of the rod each blob of one row is.

    The rod lies parallel to the image plane in a sweep, so along the imaged row the bead
    positions ``s`` (mm along the rod) map to the blobs' coordinate ``t`` (px, on the row's
    principal line) by an affine map ``t = a s + b`` (up to the intensifier's distortion).
    Every hypothesis "blobs i < j are beads p and q" (both orientations of the rod) fixes the
    map; the one that places most blobs within ``tolerance`` times the smallest predicted gap
    of a bead wins, ties broken by the RMS of a least-squares refit on its blobs. The beads'
    unequal gaps make the answer unique; beads outside the field or hidden are simply
    missing, stray blobs are left unmatched.

    Parameters
    ----------
    xy_px : (K, 2) blob centroids of one row.
    bead_positions_mm : (n,) bead positions along the rod, increasing, unequal gaps.

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
    K, n = len(xy), len(s)
    if K < min_matched:
        raise ValueError(f"identify_row: {K} blobs; at least {min_matched} are needed")
    if K > 3 * n:
        raise ValueError(f"identify_row: {K} blobs for a rod of {n} beads; too many to match")
    c = xy.mean(axis=0)
    u = np.linalg.svd(xy - c)[2][0]
    t = (xy - c) @ u
    # hypotheses: blob pair (i, j), bead pair (p, q) with p != q (order gives the orientation)
    bi, bj = np.array(list(itertools.combinations(range(K), 2))).T
    bp, bq = np.array([(p, q) for p in range(n) for q in range(n) if p != q]).T
    I, P = np.repeat(bi, len(bp)), np.tile(bp, len(bi))
    J, Q = np.repeat(bj, len(bq)), np.tile(bq, len(bj))
    a = (t[J] - t[I]) / (s[Q] - s[P])
    b = t[I] - a * s[P]
    pred = a[:, None] * s[None, :] + b[:, None]                       # (B, n) px
    gap = np.abs(a) * np.min(np.diff(s))                               # (B,)
    err = np.abs(t[None, :, None] - pred[:, None, :])                  # (B, K, n)
    j = np.argmin(err, axis=2)
    e = np.take_along_axis(err, j[..., None], axis=2)[..., 0]          # (B, K)
    inl = e < tolerance * gap[:, None]
    count = inl.sum(axis=1)
    if count.max() < min_matched:
        raise ValueError(f"identify_row: the spacing pattern matches at most {count.max()} "
                         f"of {K} blobs (need {min_matched})")
    # distinct assignments of the two best counts, refitted; a candidate's score is its count
    # minus its refit RMS in units of (tolerance * gap / 5): a stray blob that happens to fall
    # near a bead cannot outvote a tight fit of fewer blobs
    top = np.flatnonzero(count >= max(min_matched, count.max() - 1))
    assign = np.where(inl[top], j[top], -1)
    _, first = np.unique(assign, axis=0, return_index=True)
    scored = []
    for k in top[first]:
        m = inl[k].copy()
        for bead_idx in np.unique(j[k][m]):  # two blobs on one bead: keep the closer
            claim = np.flatnonzero(m & (j[k] == bead_idx))
            m[claim[np.argsort(e[k][claim])[1:]]] = False
        inl[k] = m
        sk, tk = s[j[k][m]], t[m]
        A = np.column_stack([sk, np.ones_like(sk)])
        coef = np.linalg.lstsq(A, tk, rcond=None)[0]
        rms = float(np.sqrt(np.mean((tk - A @ coef) ** 2)))
        unit = 0.2 * tolerance * abs(coef[0]) * np.min(np.diff(s))
        scored.append((m.sum() - rms / unit, rms, k))
    scored.sort(reverse=True)
    score, rms, k = scored[0]
    if len(scored) > 1 and scored[1][0] > score - 0.5:
        raise ValueError(f"identify_row: ambiguous (two bead assignments fit {K} blobs about "
                         f"as well: RMS {rms:.2f} and {scored[1][1]:.2f} px)")
    return np.where(inl[k], j[k], -1), rms


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
    rows = {k: [] for k in ("frame", "plane", "bead", "xy", "robot")}
    problems: list[str] = []
    weak = []  # rows too short to identify on their own: (frame, name, blobs, message index)
    expected = 0

    def add(f, bead, xy):
        rows["frame"].append(np.full(len(bead), f))
        rows["plane"].append(np.full(len(bead), int(plane[f])))
        rows["bead"].append(bead)
        rows["xy"].append(xy)
        rows["robot"].append(beads[f][bead])

    for f in range(1, F):
        if plane[f] < 0:
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
                raise ValueError("no blobs")
            bead, _rms = identify_row(xy, s, min_matched=min_matched)
        except ValueError as exc:
            problems.append(f"{name}: row dropped ({exc}; {len(xy)} blobs found)")
            if len(xy):
                weak.append((f, name, xy, len(problems) - 1))
            continue
        ok = bead >= 0
        missing = sorted(set(range(len(s))) - set(bead[ok].tolist()))
        if missing:
            problems.append(f"{name}: beads {missing} not found (outside the field or hidden)")
        if (~ok).any():
            problems.append(f"{name}: {int((~ok).sum())} stray blob(s) at "
                            f"{np.round(xy[~ok], 1).tolist()} px ignored")
        add(f, bead[ok], xy[ok])

    # rows with too few blobs (at the edge of the field): predict where their beads appear
    # from the identified rows of the same plane (a TPS from in-plane mm to pixels) and take
    # the blobs that fall on a prediction
    for f, name, xy, k in weak:
        p = int(plane[f])
        have = [i for i, fr in enumerate(rows["frame"]) if plane[fr[0]] == p]
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
        dist = np.linalg.norm(xy[:, None, :] - pred[None], axis=2)
        j = np.argmin(dist, axis=1)
        good = dist[np.arange(len(xy)), j] < 0.2 * gap
        good &= np.array([np.sum(j[good] == jj) == 1 for jj in j])
        if good.any():
            add(f, j[good], xy[good])
            missing = sorted(set(range(len(s))) - set(j[good].tolist()))
            problems[k] = (f"{name}: {int(good.sum())} blob(s) identified from the plane's other "
                           f"rows; beads {missing} not found (outside the field or hidden)")

    def cat(key, shape):
        return np.concatenate(rows[key]) if rows[key] else np.zeros(shape)

    order = np.argsort(cat("frame", (0,)), kind="stable")
    return Markers(sweep.view, cat("frame", (0,)).astype(int)[order],
                   cat("plane", (0,)).astype(int)[order], cat("bead", (0,)).astype(int)[order],
                   cat("xy", (0, 2))[order], cat("robot", (0, 3))[order], problems, expected)


# --------------------------------------------------------------------------- calibration
@dataclass(frozen=True)
class Calibration:
    """A calibrated view: every pixel's X-ray path in the robot frame.

    ``near`` and ``far`` map pixels (N, 2) to points (N, 3) mm of the near and far
    calibration planes; the path of a pixel is the line through its two points, directed
    from near to far (from the source towards the intensifier).
    """

    view: str
    near: ThinPlateSpline
    far: ThinPlateSpline
    problems: tuple[str, ...] = ()

    def paths(self, x, y=None) -> tuple[np.ndarray, np.ndarray]:
        """X-ray paths of pixels.

        Parameters
        ----------
        x, y : arrays of the same shape (any, e.g. a whole (H, W) image grid), px; or ``x``
            an (N, 2) array and ``y`` None.

        Returns
        -------
        origins : (..., 3) mm, the near-plane point of each pixel (robot frame).
        directions : (..., 3) unit vectors from near to far plane.
        """
        if y is None:
            xy = _as_xy(x)
            shape = (len(xy),)
        else:
            x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
            if x.shape != y.shape:
                raise ValueError(f"paths: x {x.shape} and y {y.shape} must have one shape")
            shape = x.shape
            xy = np.column_stack([x.ravel(), y.ravel()])
        a = self.near(xy)
        b = self.far(xy)
        d = b - a
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return a.reshape(shape + (3,)), d.reshape(shape + (3,))

    def path_map(self, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray]:
        """Paths of every pixel of a ``(height_px, width_px)`` image: ``(H, W, 3)`` each."""
        yy, xx = np.mgrid[0:height_px, 0:width_px].astype(np.float64)
        return self.paths(xx, yy)

    def distances(self, xy_px, points_robot) -> np.ndarray:
        """Distance (mm) from each 3-D point (N, 3) to the path of its pixel (N, 2)."""
        o, d = self.paths(_as_xy(xy_px))
        return point_line_distances(np.asarray(points_robot, dtype=np.float64), o, d)

    def center_of_perspective(self, xy_px=None) -> np.ndarray:
        """The point (3,) mm closest in least squares to the paths of ``xy_px`` (default: the
        calibration markers of the near plane), i.e. the X-ray source as calibrated."""
        xy = self.near.centres_px if xy_px is None else _as_xy(xy_px)
        o, d = self.paths(xy)
        return closest_point_to_lines(o, d)


def calibrate(markers: Markers, *, smoothing: float = 0.01, min_markers: int = 12,
              min_rows: int = 3) -> Calibration:
    """Two-plane TPS calibration of one view from its identified markers.

    Uses the near (0) and far (1) plane markers. A plane with fewer than ``min_markers``
    markers or fewer than ``min_rows`` rows (frames) cannot be calibrated soundly:
    ``ValueError`` names the view and plane and lists the problems met while finding the
    markers. Otherwise the problems are kept in ``Calibration.problems``.
    """
    tps = {}
    for p in (0, 1):
        m = markers.plane == p
        n_rows = len(np.unique(markers.frame[m]))
        if m.sum() < min_markers or n_rows < min_rows:
            detail = "; ".join(markers.problems[:8]) or "no problems were recorded"
            raise ValueError(
                f"view {markers.view}: {PLANE_NAMES[p]} plane has {int(m.sum())} markers in "
                f"{n_rows} rows (need {min_markers} in {min_rows}); cannot calibrate. "
                f"Problems: {detail}")
        try:
            tps[p] = ThinPlateSpline.fit(markers.xy_px[m], markers.robot[m], smoothing=smoothing)
        except ValueError as exc:
            raise ValueError(f"view {markers.view}: {PLANE_NAMES[p]} plane: {exc}") from None
    return Calibration(markers.view, tps[0], tps[1], tuple(markers.problems))
