"""Thin-plate splines from pixels to values: the calibration planes' maps (NOTES.md s1).

:class:`ThinPlateSpline` maps pixel ``(x, y)`` to values (e.g. the 3-D robot-frame point of a
calibration plane): ``scipy.interpolate.RBFInterpolator`` (thin-plate kernel, degree 1) is
kept as the reference beside a direct solve; :func:`tps_fit_svd` / :func:`tps_evaluate` are the
paper's solve of ``[[K + lam I, P], [P^T, 0]]`` by SVD.

Smoothing is given in the units of the paper's kernel ``k = r^2 log(r^2) / (16 pi)`` with
``r`` in pixels (the paper used ``lam = 0.01``); scipy's thin-plate kernel is ``r^2 log r``,
``8 pi`` times larger, so ``RBFInterpolator`` receives ``smoothing = 8 pi lam``.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RBFInterpolator

__all__ = ["ThinPlateSpline", "tps_evaluate", "tps_fit_svd", "tps_kernel"]


_EIGHT_PI = 8.0 * np.pi


def _as_xy(xy, name="xy_px") -> np.ndarray:
    """``xy`` as a finite (N, 2) float64 array of pixel (x, y), or ValueError naming it."""
    a = np.asarray(xy, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array of pixel (x, y), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or inf")
    return a


# --------------------------------------------------------------------------- TPS reference
def _check_fit(xy_px, values, smoothing, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The centres (n, 2) and values (n, m) of a fit, or ``ValueError``: fewer than 3
    centres, centres on one line (no affine part), values not one finite row per centre, a
    smoothing that is no finite number >= 0, or a centre given twice without smoothing (the
    interpolation then has no solution)."""
    xy = _as_xy(xy_px)
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"values: expected an (n, m) array of numbers, got "
                         f"{type(values).__name__}") from None
    v = v[:, None] if v.ndim == 1 else v
    if v.ndim != 2 or v.shape[0] != len(xy):
        raise ValueError(f"values: expected {len(xy)} rows (one per centre), got shape "
                         f"{v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("values: contains NaN or inf")
    if (isinstance(smoothing, bool) or not isinstance(smoothing, numbers.Real)
            or not np.isfinite(smoothing) or smoothing < 0):
        raise ValueError(f"smoothing: expected a finite number >= 0, got {smoothing!r}")
    if len(xy) < 3:
        raise ValueError(f"{what}: at least 3 markers are needed, got {len(xy)}")
    centred = xy - xy.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[-1] < 1e-6 * max(sv[0], 1e-300):
        raise ValueError(f"{what}: the markers are collinear in the image")
    if smoothing == 0:
        _, first, counts = np.unique(xy, axis=0, return_index=True, return_counts=True)
        if np.any(counts > 1):
            raise ValueError(f"{what}: {int(np.sum(counts > 1))} centre(s) given more than "
                             "once (e.g. row "
                             f"{int(first[np.argmax(counts > 1)])}); interpolating them needs "
                             "smoothing > 0")
    return xy, v


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
    xy, v = _check_fit(xy_px, values, smoothing, "tps_fit_svd")
    n = len(xy)
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
        xy, v = _check_fit(xy_px, values, smoothing, "thin-plate spline")
        shift = xy.mean(axis=0)
        centred = xy - shift
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


