"""Calibration of a fluoroscopic view in robot coordinates: two-plane TPS, X-ray paths.

The robot moves a radiolucent rod with steel beads along a *near* and a *far* plane between
source and intensifier; a frame is taken after every move (Guéziec et al. 1998, Section II).
The markers (the beads' images, identified) come from :mod:`reglib.markers`.

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

import re
from dataclasses import dataclass

import numpy as np

from reglib.geometry import closest_point_to_lines, point_line_distances
from reglib.markers import FAR, NEAR, PLANE_NAMES, Markers
from reglib.tps import ThinPlateSpline, _as_xy, tps_evaluate, tps_fit_svd, tps_kernel

__all__ = [
    "ThinPlateSpline",
    "Calibration",
    "calibrate",
    "summarise_problems",
    "tps_fit_svd",
    "tps_evaluate",
    "tps_kernel",
]

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


def summarise_problems(problems, limit: int = 8) -> str:
    """The problems met while finding a view's markers, one entry per kind: messages that
    differ only in their numbers (the frame, blob counts) are merged, each number shown as
    its range over them, with how many there were (``"8 x view v, near plane, frame 1-8:
    row dropped (identify_row: 43-81 blobs ...)"``). At most ``limit`` kinds, then how many
    more; "no problems were recorded" for none."""
    groups: dict[tuple, list] = {}
    for msg in problems:
        parts = re.split(r"(\d+(?:\.\d+)?)", str(msg))
        groups.setdefault(tuple(parts[0::2]), []).append(parts[1::2])
    out = []
    for text, numbers in list(groups.items())[:limit]:
        pieces = [text[0]]
        for k, rest in enumerate(text[1:]):
            vals = [v[k] for v in numbers]
            lo, hi = min(vals, key=float), max(vals, key=float)
            pieces.append((lo if lo == hi else f"{lo}-{hi}") + rest)
        out.append((f"{len(numbers)} x " if len(numbers) > 1 else "") + "".join(pieces))
    more = len(groups) - limit
    if more > 0:
        out.append(f"and {more} other kind(s) of problem")
    return "; ".join(out) or "no problems were recorded"


def calibrate(markers: Markers, *, smoothing: float = 0.01, min_markers: int = 12,
              min_rows: int = 3) -> Calibration:
    """Two-plane TPS calibration of one view from its identified markers.

    Uses the near (0) and far (1) plane markers. A plane with fewer than ``min_markers``
    markers or fewer than ``min_rows`` rows (frames) cannot be calibrated soundly:
    ``ValueError`` names the view and plane and lists the problems met while finding the
    markers. Otherwise the problems are kept in ``Calibration.problems``.
    """
    tps = {}
    for p in (NEAR, FAR):
        m = markers.plane == p
        n_rows = len(np.unique(markers.frame[m]))
        if m.sum() < min_markers or n_rows < min_rows:
            detail = summarise_problems(markers.problems)
            raise ValueError(
                f"view {markers.view}: {PLANE_NAMES[p]} plane has {int(m.sum())} markers in "
                f"{n_rows} rows (need {min_markers} in {min_rows}); cannot calibrate. "
                f"Problems: {detail}")
        try:
            tps[p] = ThinPlateSpline.fit(markers.xy_px[m], markers.robot[m], smoothing=smoothing)
        except ValueError as exc:
            raise ValueError(f"view {markers.view}: {PLANE_NAMES[p]} plane: {exc}") from None
    return Calibration(markers.view, tps[0], tps[1], tuple(markers.problems))
