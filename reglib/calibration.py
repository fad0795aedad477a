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
        for name, v in (("width_px", width_px), ("height_px", height_px)):
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or not 1 <= v <= 65536:
                raise ValueError(f"path_map: {name} must be an integer in [1, 65536] px, got "
                                 f"{v!r}")
        yy, xx = np.mgrid[0:height_px, 0:width_px].astype(np.float64)
        return self.paths(xx, yy)

    def distances(self, xy_px, points_robot) -> np.ndarray:
        """Distance (mm) from each 3-D point (N, 3) to the path of its pixel (N, 2)."""
        xy = _as_xy(xy_px)
        p = np.asarray(points_robot, dtype=np.float64)
        if p.shape != (len(xy), 3):
            raise ValueError(f"distances: points_robot must be ({len(xy)}, 3), one per pixel "
                             f"of xy_px, got {p.shape}")
        o, d = self.paths(xy)
        return point_line_distances(p, o, d)

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
    _check_markers(markers)
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
        spread = _plane_spread_mm(markers.robot[m])
        if spread < MIN_PLANE_SPREAD_MM:
            raise ValueError(
                f"view {markers.view}: {PLANE_NAMES[p]} plane: the robot reported its markers "
                f"within {spread:.3g} mm of one line (need a plane at least "
                f"{MIN_PLANE_SPREAD_MM:g} mm wide across the rod); cannot calibrate")
        try:
            tps[p] = ThinPlateSpline.fit(markers.xy_px[m], markers.robot[m], smoothing=smoothing)
        except ValueError as exc:
            raise ValueError(f"view {markers.view}: {PLANE_NAMES[p]} plane: {exc}") from None
    cal = Calibration(markers.view, tps[0], tps[1], tuple(markers.problems))
    xy = markers.xy_px[np.isin(markers.plane, (NEAR, FAR))]
    gap = np.linalg.norm(cal.far(xy) - cal.near(xy), axis=1)
    if not np.all(gap >= MIN_PATH_LENGTH_MM):
        raise ValueError(
            f"view {markers.view}: the near and far planes' fits meet (their points "
            f"{np.nanmin(gap):.3g} mm apart at a marker's pixel, need {MIN_PATH_LENGTH_MM:g}): "
            "the paths have no direction; cannot calibrate")
    return cal


#: a calibration plane's markers, as the robot reported them, must spread this far across
#: their best line (mm): a row of beads alone, or beads reported at one point, fit no plane
MIN_PLANE_SPREAD_MM = 5.0
#: ...and the near and far planes' fits must lie this far apart at every marker's pixel (mm)
MIN_PATH_LENGTH_MM = 1.0


def _plane_spread_mm(points: np.ndarray) -> float:
    """The extent (mm) of ``points`` (N, 3) along their second principal direction: 0 for
    points on one line or at one point."""
    if len(points) < 3:
        return 0.0
    c = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    along = c @ vt[1]
    return float(along.max() - along.min())


def _check_markers(markers) -> None:
    """``ValueError`` naming the field of a :class:`Markers` that calibrate cannot read."""
    if not isinstance(markers, Markers):
        raise ValueError(f"markers: expected a reglib.markers.Markers, got "
                         f"{type(markers).__name__}")
    try:
        n = len(markers.frame)
        fields = {"frame": np.asarray(markers.frame), "plane": np.asarray(markers.plane),
                  "xy_px": np.asarray(markers.xy_px, dtype=np.float64),
                  "robot": np.asarray(markers.robot, dtype=np.float64)}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"markers of view {markers.view}: frame, plane, xy_px and robot must "
                         f"be arrays of numbers ({exc})") from None
    want = {"frame": (n,), "plane": (n,), "xy_px": (n, 2), "robot": (n, 3)}
    for name, shape in want.items():
        if fields[name].shape != shape:
            raise ValueError(f"markers of view {markers.view}: {name} must be {shape} (one "
                             f"row per marker), got {fields[name].shape}")
    for name in ("xy_px", "robot"):
        if not np.all(np.isfinite(fields[name])):
            raise ValueError(f"markers of view {markers.view}: {name} holds NaN or inf")
