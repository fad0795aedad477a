"""The iterative 2-D/3-D registration loop: CT surfaces to the X-ray paths of several views.

Paper: Guezic et al. 1998, Section IV (``paper/NOTES.md`` s3). One iteration, all views at
once:

1. for each view, its center of perspective is brought into the CT frame with the current
   pose (``ct2robot``), and the apparent contours of every surface are computed from it
   (:mod:`reglib.apparent`) -- moving the center instead of the surfaces is the same thing;
2. for each X-ray path of the view, the closest point on every contour (Step A) and the
   selection of one contour (Step B, :mod:`reglib.closest`) give a CT point matched to the
   path;
3. the pose is solved from all matched points (CT frame) and paths (robot frame), starting at
   the current pose (:func:`reglib.pose.solve_pose`, robust by default), or, with a fixed
   point, a rotation about that point only (``solve_pose`` with ``fixed_point``);
4. stop when the step is below ``tol_step_mm``, the residual below ``tol_residual_mm``, or
   after ``max_iterations``; fail (``converged=False`` with a ``reason``) on an empty view, a
   view without apparent contour, a pose solve that breaks down, too few inliers, a pose
   that runs away from the start (divergence), or a final pose that puts kept surface
   points behind a view's centre of perspective (cheirality: a mirror pose).

Frames: surfaces in ``ct`` (mm); views (centers and paths) in ``robot`` (mm); the result is
``ct2robot`` (``x_robot = R x_ct + t``).
"""

from __future__ import annotations

import functools
import inspect
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from reglib.apparent import SurfaceTopology, prepare_surface
from reglib.closest import ContourSet, _match_contours, closest_points, select_contours
from reglib.geometry import (
    RigidTransform,
    as_flags,
    as_lines,
    as_rigid_transform,
    point_line_distances,
    skew,
)
from reglib.pose import _check_options as _check_pose_options
from reglib.pose import solve_pose, tukey_weights

__all__ = [
    "IterationRecord",
    "RegistrationResult",
    "View",
    "match_view",
    "register",
]


#: the largest median distance (mm) of a view's paths from its center of perspective:
#: calibrated views of the testbed pass at 0.8-1.2 mm (at most 2.7-5.1 mm) from theirs
CENTER_TOLERANCE_MM = 10.0


@dataclass(frozen=True, eq=False)
class View:
    """One calibrated view: its center of perspective and its X-ray paths (robot frame).

    Attributes
    ----------
    center : (3,) float64, mm, robot frame; the center of perspective (e.g.
        :func:`reglib.geometry.closest_point_to_lines` of all the view's paths).
    origins, directions : (N, 3) float64, mm and unit, robot frame; the X-ray paths of the
        view's contour pixels, preferably in order along the image contour.
    external : (N,) bool; True for paths of external bone-contour pixels (the paper's
        selection rule), False for internal ones (closest contour). Default all True.
    name : label used in messages.
    """

    center: np.ndarray
    origins: np.ndarray
    directions: np.ndarray
    external: np.ndarray | None = None
    name: str = ""

    def __post_init__(self):
        c = np.asarray(self.center, dtype=np.float64).reshape(-1)
        label = f"view {self.name!r}"
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"{label}: center must be a finite (3,) point in mm, got {c!r}")
        o = np.asarray(self.origins, dtype=np.float64)
        d = np.asarray(self.directions, dtype=np.float64)
        if o.size == 0 and d.size == 0:
            o = d = np.zeros((0, 3))
        else:
            try:
                o, d = as_lines(o, d)
            except ValueError as err:
                raise ValueError(f"{label}: {err}") from None
        try:
            ext = (np.ones(len(o), dtype=bool) if self.external is None
                   else as_flags(self.external, "external").reshape(-1))
        except ValueError as err:
            raise ValueError(f"{label}: {err}") from None
        if ext.shape != (len(o),):
            raise ValueError(f"{label}: external must have shape ({len(o)},), got {ext.shape}")
        if len(o) >= 3:
            # the paths leave one focal spot: a center given elsewhere (a review's +100 mm)
            # turns the external-contour rule and the apparent contours to the wrong
            # viewpoint, and the registration degrades without a word
            off = point_line_distances(np.broadcast_to(c, o.shape), o, d)
            if np.median(off) > CENTER_TOLERANCE_MM:
                raise ValueError(
                    f"{label}: center {np.round(c, 1).tolist()} mm is not where the view's "
                    f"paths meet: they pass at a median {np.median(off):.1f} mm from it "
                    f"(at most {CENTER_TOLERANCE_MM:g} mm expected; a calibrated view's "
                    "pass within about 1 mm of its center of perspective, "
                    "reglib.geometry.closest_point_to_lines of the paths)")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "origins", o)
        object.__setattr__(self, "directions", d)
        object.__setattr__(self, "external", ext)

    @property
    def n_paths(self) -> int:
        return int(len(self.origins))


@dataclass(frozen=True)
class IterationRecord:
    """One iteration of the loop.

    ``residual_mm``: RMS point-path distance of the inliers at the pose after the solve;
    ``median_mm``: median distance of all matches after the solve; ``step_mm``: largest
    displacement of the surfaces' bounding-box corners by this iteration's update;
    ``step_deg``: its rotation angle; ``inlier_fraction``: share of matches the solver kept;
    ``n_matches``: matched paths; ``time_s``: wall time of the iteration.
    """

    iteration: int
    residual_mm: float
    median_mm: float
    step_mm: float
    step_deg: float
    inlier_fraction: float
    n_matches: int
    time_s: float


#: how the ``reason`` of a registration that moved beyond its limits begins
DIVERGED = "diverged"


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """Outcome of :func:`register`. Falsy when it did not converge; ``reason`` says why.

    Attributes
    ----------
    ct2robot : RigidTransform, the final pose (the start pose if it failed before a solve;
        when it diverged, the last pose within the divergence limits).
    converged : bool.
    reason : str, why it stopped (converged: which test; failed: what went wrong).
    iterations : int.
    history : tuple of IterationRecord.
    residuals : (M,) float64, mm, point-path distances of the last matches at the final pose.
    weights : (M,) float64, the solver's final weights of those matches (0 = rejected).
    view_index : (M,) int64, the view of each match.
    inlier_fraction_per_view : (V,) float64.
    time_s : float, total wall time.
    sensitivity : (6,) float64 (3, about a fixed point), ascending, unitless: how strongly
        the final matches hold the pose (:func:`pose_sensitivity`); ``sensitivity[0]``, the
        weakest, is the RMS change of the across-contour distances per mm of RMS
        displacement of the surfaces along their least constrained motion. Empty when the
        loop did not solve.
    weakest_motion : (6,) float64, that motion (rotation rad, translation mm about the
        surfaces' centre or the fixed point; scaled to 1 mm RMS displacement).
    pivot_gain, pivot_gain_max : float, with a fixed point only (NaN otherwise): how far an
        error of the fixed point's robot position moves the registered bone
        (:func:`fixed_point_gain`): mm of RMS displacement of the surfaces, and mm at their
        farthest vertex, per mm of the point's error in its worst direction;
        ``pivot_response`` (3, 3) rad per mm, the rotation the matches answer that error with
        (``A`` of :func:`fixed_point_gain`; empty without a fixed point).
    """

    ct2robot: RigidTransform
    converged: bool
    reason: str
    iterations: int
    history: tuple = ()
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    view_index: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    inlier_fraction_per_view: np.ndarray = field(default_factory=lambda: np.zeros(0))
    time_s: float = 0.0
    sensitivity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    weakest_motion: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pivot_gain: float = float("nan")
    pivot_gain_max: float = float("nan")
    pivot_response: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __bool__(self) -> bool:
        return bool(self.converged)

    @property
    def inlier_fraction(self) -> float:
        return float(np.mean(self.weights > 0)) if self.weights.size else 0.0


# --------------------------------------------------------------------------- one view
def match_view(surfaces, view: View, ct2robot: RigidTransform, *, closest: str = "compiled",
               selection: Literal["paper", "closest"] = "paper",
               max_stab_distance_mm: float = np.inf):
    """Matched CT points for the paths of one view at the pose ``ct2robot``.

    Returns
    -------
    points_ct : (N, 3) mm, the selected closest contour point of each path (CT frame), or
        None when the surfaces show no apparent contour from this view.
    tangents_ct : (N, 3), unit oriented contour direction at each point (CT frame; the mean
        of the two segments' directions at a contour vertex).
    contours : ContourSet of the apparent contours in the CT frame.
    surface_of_contour : (C,) int64, which surface each contour belongs to.
    """
    if not isinstance(ct2robot, RigidTransform):
        raise ValueError(f"ct2robot: expected a RigidTransform (RigidTransform.from_matrix "
                         f"makes one of a (4, 4) matrix), got {type(ct2robot).__name__}")
    if not isinstance(view, View):
        raise ValueError(f"view: expected a View, got {type(view).__name__}")
    robot2ct = ct2robot.inverse()
    c_ct = robot2ct.apply(view.center)
    o_ct, d_ct = robot2ct.apply_lines(view.origins, view.directions)
    cset, owner = ContourSet.from_surfaces(surfaces, c_ct)
    if cset.n_contours == 0:
        return None, None, ContourSet.from_polylines([], []), np.zeros(0, dtype=np.int64)
    within = None
    if closest in ("blocks", "compiled"):
        # Step B only looks at the nearest contour and the stabbed ones within the limit
        within = 0.0 if selection == "closest" else float(max_stab_distance_mm)
        within = None if not np.isfinite(within) else within
    ext = view.external if selection == "paper" else np.zeros(view.n_paths, dtype=bool)
    if closest == "compiled":  # Steps A and B in one compiled pass; the rest: the reference
        # the view's lines were checked when it was made, and a rigid motion keeps them so
        _, _, pts, tangents = _match_contours(cset, o_ct, d_ct, ext, within,
                                              float(max_stab_distance_mm))
        return pts, tangents, cset, owner
    cp = closest_points(cset, o_ct, d_ct, method=closest, within_mm=within)
    sel = select_contours(cp, cset, d_ct, ext, max_stab_distance_mm=max_stab_distance_mm)
    rows = np.arange(len(sel))
    pts = cp.p[rows, sel]
    tangents = cset.tangents(cp.segment[rows, sel], pts)
    return pts, tangents, cset, owner


# --------------------------------------------------------------------------- conditioning
def pose_sensitivity(points, normals, weights, targets, *, centre=None, fixed_point=None):
    """How strongly matched points hold a rigid pose: generalised eigenvalues of the matches'
    information against the targets' displacement.

    A small motion of the bone, rotation ``w`` (rad) and translation ``v`` (mm) about
    ``centre``, moves a matched point ``p`` across its contour by ``n . (w x (p - c) + v)``
    (``n`` the unit normal of the match: across the contour, perpendicular to its X-ray path)
    and a target ``q`` by ``w x (q - c) + v``. With ``F`` the weighted mean of the first
    quadratic form over the matches and ``M`` the mean of the second over the targets, the
    square roots of the eigenvalues of ``F x = lambda M x`` are the RMS change of the
    across-contour distances per mm of RMS displacement of the targets, for each principal
    motion. The smallest one near 0 means the matches leave that motion of the bone free
    (e.g. two views, one per end of a long bone, hardly see the bone slide along either
    beam).

    Parameters
    ----------
    points, normals : (N, 3) mm and unit vectors, the matched points and their normals, in
        one frame.
    weights : (N,) >= 0 (0: left out).
    targets : (Q, 3) mm, points whose displacement counts (e.g. the surfaces' vertices).
    centre : (3,) mm, the motions' centre (default: the targets' mean); only a choice of
        coordinates, the eigenvalues do not depend on it.
    fixed_point : (3,) mm or None: only rotations about it are free (3 values).

    Returns
    -------
    ``(s, motion)``: ``s`` (6,) or (3,) ascending, unitless; ``motion`` (6,) the weakest
    principal motion (rotation rad then translation mm; zero translation with a fixed
    point), scaled to 1 mm RMS displacement of the targets.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    q = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if not (len(p) == len(n) == len(w)) or len(q) == 0:
        raise ValueError("pose_sensitivity: points, normals and weights must have one row per "
                         "match, and targets at least one point")
    rot_only = fixed_point is not None
    c = (np.asarray(fixed_point, dtype=np.float64) if rot_only
         else q.mean(axis=0) if centre is None else np.asarray(centre, dtype=np.float64))
    keep = (w > 0) & np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(n), axis=1)
    k = 3 if rot_only else 6
    if w[keep].sum() <= 0:
        return np.zeros(k), np.zeros(6)
    J = np.hstack([np.cross(p[keep] - c, n[keep]), n[keep]])[:, :k]
    F = (J * w[keep, None]).T @ J / w[keep].sum()
    # M = mean over targets of G^T G, G = [-skew(q - c) | I]: in closed form from the
    # targets' second moments
    d = q - c
    S = d.T @ d / len(d)
    m = d.mean(axis=0)
    skew_m = skew(m)
    M = np.zeros((6, 6))
    M[:3, :3] = np.trace(S) * np.eye(3) - S
    M[:3, 3:] = skew_m
    M[3:, :3] = skew_m.T
    M[3:, 3:] = np.eye(3)
    M = M[:k, :k]
    # F x = lambda M x with M symmetric positive definite: through M's Cholesky factor
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError:  # the targets do not span the motions (collinear)
        return np.full(k, np.nan), np.zeros(6)
    Li = np.linalg.inv(L)
    lam, y = np.linalg.eigh(Li @ F @ Li.T)
    x = Li.T @ y[:, 0]
    motion = np.zeros(6)
    motion[:k] = x / np.sqrt(x @ M @ x)
    return np.sqrt(np.clip(lam, 0.0, None)), motion


def fixed_point_gain(points, normals, weights, targets, fixed_point):
    """How an error of a fixed point moves a pose registered by rotation about it.

    With the rotation alone free about ``fixed_point`` ``p``, an error ``e`` of where the
    point lies moves the bone by ``e``; the matches then turn it by the rotation ``w = A e``
    that best restores their across-contour distances (the weighted least squares of
    ``n . (w x (x - p) + e)`` over the matches, linearised at the final pose), so that a
    target ``q`` moves by ``e + w x (q - p)``. Two views of a long bone hold its spin
    loosely, and a point at one end moved across the views turns the other end by several
    times the error (the paper's experiment 1).

    Parameters
    ----------
    points, normals, weights : the matches, as :func:`pose_sensitivity`.
    targets : (Q, 3) mm, points whose displacement counts (the surfaces' vertices).
    fixed_point : (3,) mm, in the frame of the points.

    Returns
    -------
    ``(rms, largest, A)``: mm of RMS displacement of the targets, and mm at the target that
    moves most, per mm of error in its worst direction; ``A`` (3, 3) rad per mm, the
    rotation the matches answer an error with. NaN and a NaN ``A`` when the kept matches
    do not hold the rotation (rank below 3).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    q = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(fixed_point, dtype=np.float64).reshape(3)
    if not (len(p) == len(n) == len(w)) or len(q) == 0:
        raise ValueError("fixed_point_gain: points, normals and weights must have one row per "
                         "match, and targets at least one point")
    nan = float("nan")
    keep = (w > 0) & np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(n), axis=1)
    Jr = np.cross(p[keep] - c, n[keep]) * np.sqrt(w[keep])[:, None]
    Jt = n[keep] * np.sqrt(w[keep])[:, None]
    H = Jr.T @ Jr
    ev = np.linalg.eigvalsh(H) if keep.any() else np.zeros(3)
    if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
        return nan, nan, np.full((3, 3), nan)
    A = -np.linalg.solve(H, Jr.T @ Jt)
    # each target's displacement per unit error: D_q = I - skew(q - c) A, (Q, 3, 3)
    d = q - c
    D = np.broadcast_to(np.eye(3), (len(d), 3, 3)) - np.einsum("qij,jk->qik", skew(d), A)
    G = np.einsum("qji,qjk->qik", D, D)        # D_q^T D_q: both figures read it
    rms = float(np.sqrt(np.linalg.eigvalsh(G.mean(axis=0))[-1]))
    largest = float(np.sqrt(np.linalg.eigvalsh(G)[:, -1].max()))
    return rms, largest, A


# --------------------------------------------------------------------------- the loop
def _across(directions, tangents) -> np.ndarray:
    """Unit vectors across the contour and perpendicular to the path (``d x t``), one per
    match: the direction of the "normal" residual and of a match's hold on the pose. A zero
    tangent gives a zero row (solve_pose ignores it)."""
    n = np.cross(directions, tangents)
    nn = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(nn > 0, nn, 1.0)


def _residuals_at(T: RigidTransform, p_ct, tans_ct, origins, directions, *, normal: bool,
                  robust: bool, tukey_a: float) -> tuple[np.ndarray, np.ndarray]:
    """Distances (mm) of matched CT points placed by ``T`` to their X-ray paths (robot
    frame), across the contour when ``normal`` (the "normal" residual) else to the line,
    and the weights a solve would give them there (Tukey's biweight at the robust scale
    ``median / 0.6745`` when ``robust``, else ones)."""
    p = T.apply(p_ct)
    if normal:
        dist = np.abs(np.sum((p - origins) * _across(directions, T.apply_vectors(tans_ct)),
                             axis=1))
    else:
        dist = point_line_distances(p, origins, directions)
    if not robust:
        return dist, np.ones_like(dist)
    s = float(np.median(dist)) / 0.6745
    return dist, (tukey_weights(dist / s, tukey_a) if s > 0 else np.ones_like(dist))


def _corners(surfaces) -> np.ndarray:
    v = np.vstack([s.vertices for s in surfaces])
    lo, hi = v.min(axis=0), v.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


def _motion(a: RigidTransform, b: RigidTransform, corners) -> tuple[float, float]:
    mm = float(np.max(np.linalg.norm(a.apply(corners) - b.apply(corners), axis=1)))
    return mm, float(np.degrees((a @ b.inverse()).angle_rad))


def _stacked(tops) -> tuple:
    """The surfaces' edge tables stacked for :func:`reglib._closest_numba.match_views`:
    ``(normals, normal_dot_centroid, twin (local), he_origin, he_dest (global vertex ids),
    vertices, face0, max_valence)``."""
    v0 = np.cumsum([0] + [len(t.vertices) for t in tops])
    face0 = np.cumsum([0] + [len(t.normals) for t in tops]).astype(np.int64)
    cat = np.concatenate
    return (np.ascontiguousarray(np.vstack([t.normals for t in tops]), dtype=np.float64),
            np.ascontiguousarray(cat([t.normal_dot_centroid for t in tops]), dtype=np.float64),
            np.ascontiguousarray(cat([t.twin for t in tops]), dtype=np.int64),
            np.ascontiguousarray(cat([t.he_origin + v0[k] for k, t in enumerate(tops)]),
                                 dtype=np.int64),
            np.ascontiguousarray(cat([t.he_dest + v0[k] for k, t in enumerate(tops)]),
                                 dtype=np.int64),
            np.ascontiguousarray(np.vstack([t.vertices for t in tops]), dtype=np.float64),
            face0, int(max(t.max_valence for t in tops)))


def _match_all(stack, views, T: RigidTransform, o_r, d_r, ext, view0, within, max_stab, *,
               every: bool = False):
    """Every view's matches at the pose ``T`` in one compiled call (``closest="compiled"``):
    ``(points_ct, tangents_ct, bad)``, ``bad`` the index of the first view whose surfaces
    show no apparent contour (None: none; the later views are matched only with ``every``,
    and that view's rows are NaN). The same matches as :func:`match_view` view by view (the
    reference, compared in tests)."""
    from reglib._apparent_numba import OK, TWICE
    from reglib._closest_numba import match_views
    from reglib.closest import COMPILED_BLOCK, COMPILED_SUPER

    robot2ct = T.inverse()
    centres = robot2ct.apply(np.vstack([v.center for v in views]))
    o_ct, d_ct = robot2ct.apply_lines(o_r, d_r)
    p, tan, bad, status = match_views(
        np.ascontiguousarray(o_ct), np.ascontiguousarray(d_ct), ext, view0,
        np.ascontiguousarray(centres), *stack, within, max_stab, COMPILED_BLOCK,
        COMPILED_SUPER, every)
    if status != OK:
        raise RuntimeError("apparent_contours: linking visited an edge twice" if status == TWICE
                           else "apparent_contours: a chain without a start did not close")
    return p, tan, (None if bad < 0 else int(bad))


def _as_topologies(surfaces):
    out = []
    if isinstance(surfaces, Mapping):     # region -> surface (Stages.surfaces): by region
        surfaces = [surfaces[k] for k in sorted(surfaces)]
    if isinstance(surfaces, SurfaceTopology) or (
            isinstance(surfaces, tuple | list) and len(surfaces) == 2
            and isinstance(surfaces[0], np.ndarray) and surfaces[0].ndim == 2):
        surfaces = [surfaces]             # one surface, not in a list
    try:
        surfaces = list(surfaces)
    except TypeError:
        raise ValueError(f"surfaces: expected a list of SurfaceTopology or (vertices, faces) "
                         f"pairs, got {type(surfaces).__name__}") from None
    for i, s in enumerate(surfaces):
        if isinstance(s, SurfaceTopology):
            out.append(s)
        else:
            try:
                v, f = s
            except (TypeError, ValueError):
                raise ValueError(
                    f"surfaces[{i}]: expected a SurfaceTopology or a (vertices, faces) pair"
                ) from None
            out.append(prepare_surface(v, f))
    if not out:
        raise ValueError("surfaces: at least one surface is needed")
    return out


#: solve_pose's checked options and their defaults
_POSE_DEFAULTS = {"max_iterations": 100, "tol": 1e-12, "r": 0.1, "tukey_a": 2.0,
                  "threshold": None, "max_trials": 2000, "confidence": 0.999,
                  "backend": "auto"}


def _check_solver_options(method, opts):
    """``solver_options`` holds only what ``solve_pose`` takes and register does not set."""
    params = set(inspect.signature(solve_pose).parameters)
    mine = {"points", "origins", "directions", "method", "initial", "normals", "fixed_point"}
    unknown = sorted(set(opts) - params)
    if unknown:
        raise ValueError(f"solver_options: unknown option(s) {unknown} of solve_pose")
    taken = sorted(set(opts) & mine)
    if taken:
        raise ValueError(f"solver_options: {taken} are set by register itself (use its "
                         "method, initial and fixed_point_ct arguments)")


#: register's default inner iterations of the pose solve per loop iteration. Fewer would do
#: less work thrown away (the matches change at the next iteration): at 5, a capture-range
#: trial ran 14.7 -> 17.0 /min with the same results on the ideal profile, but on the clinic
#: the loop's limit cycles, settled after 16-22 iterations at 20, no longer repeat exactly:
#: table2's case 15 ran 50 iterations unconverged from 2 of its 11 starts (steps 0.46-0.54
#: mm) and 12 restarts each, refused 1.0-1.4 mm off (2026-11-28). Only the coarse stage,
#: which hands over at 0.5 mm steps, takes fewer (reglib.pipeline.COARSE_STAGE).
SOLVER_ITERATIONS = 20
#: register's default Tukey constant (units of the robust scale ``median / 0.6745``): the
#: usual 95 %-efficiency value (see register's ``tukey_a``)
TUKEY_A = 4.685
#: register's default divergence limits: the pose may move this far from its start
#: (bounding-box corner displacement, mm; rotation, deg) before the loop is stopped
MAX_MOTION_MM = 150.0
MAX_ROTATION_DEG = 45.0

#: the limit cycles' periods the robust solvers' loop recognises as settled
CYCLE_PERIODS = (2, 3, 4, 5, 6, 7, 8)
#: a cycle whose steps reach this (mm, the surfaces' bounding-box motion) has not settled,
#: whatever its period: a review found "lm" called converged on a period-3 cycle of steps up
#: to 6.2 mm, 30 deg off; the robust solvers' cycles on clinic and held-out scenes have steps
#: of 0.23-1.94 mm (experiment1 seed 3: 0.67-1.23 mm, 0.70 mm from the truth)
MAX_CYCLE_STEP_MM = 3.0


def _limit_cycle(placed, tol_mm: float, periods) -> int:
    """The smallest period ``p`` of ``periods`` such that each of the last ``p + 1`` poses
    lies within ``tol_mm`` (bounding-box motion) of the pose ``p`` iterations before it
    (two whole cycles), else 0. ``placed``: per pose so far, the surfaces' bounding-box
    corners it places (8, 3) mm (the motion of :func:`_motion`, from corners placed once)."""
    for p in periods:
        if len(placed) >= 2 * p + 1 and all(
                np.sqrt(np.max(np.sum((placed[-1 - k] - placed[-1 - k - p]) ** 2, axis=1)))
                < tol_mm for k in range(p + 1)):
            return p
    return 0


def _settled_cycle(placed, history, tol_mm: float, periods) -> int:
    """:func:`_limit_cycle`'s period, or 0 when the steps of the cycle's last ``period``
    iterations (``history``, records with ``step_mm``) reach :data:`MAX_CYCLE_STEP_MM`: such
    a cycle has not settled."""
    p = _limit_cycle(placed, tol_mm, periods)
    if p and max(h.step_mm for h in history[-p:]) >= MAX_CYCLE_STEP_MM:
        return 0
    return p


#: register's whole-number options and their least values
_WHOLE = {"max_iterations": 1, "solver_iterations": 1, "stall_window": 0, "stale_window": 0}
#: ... and their largest (a review: max_iterations = 10**12 with the stop tests off ran on
#: for ever, its history growing by a record per iteration; solve_pose caps its own
#: iterations at reglib.pose.MAX_ITERATIONS)
MAX_LOOP_ITERATIONS = 10_000
_WHOLE_MAX = {"max_iterations": MAX_LOOP_ITERATIONS, "solver_iterations": None,
              "stall_window": MAX_LOOP_ITERATIONS, "stale_window": MAX_LOOP_ITERATIONS}
#: register's real-valued options: (test, the values in words); NaN never passes
_REAL = {
    "tukey_a": (lambda v: 0 < v < np.inf,
                "a finite number > 0 (the Tukey constant, in robust sigmas)"),
    "tol_step_mm": (lambda v: 0 <= v < np.inf, "a finite distance >= 0 mm"),
    "tol_residual_mm": (lambda v: 0 <= v < np.inf, "a finite distance >= 0 mm"),
    "tol_stall_mm": (lambda v: 0 <= v < np.inf, "a finite distance >= 0 mm"),
    "max_motion_mm": (lambda v: v > 0, "a distance > 0 mm"),
    "max_rotation_deg": (lambda v: v > 0, "an angle > 0 deg"),
    "min_inlier_fraction": (lambda v: 0 <= v <= 1, "a fraction in [0, 1]"),
    "max_stab_distance_mm": (lambda v: v > 0, "a distance > 0 mm (inf: the paper's rule)"),
}


def is_real(v) -> bool:
    """A real number (an int or a float, numpy's too; not a bool, not a string)."""
    return not isinstance(v, bool) and isinstance(v, int | float | np.integer | np.floating)


class OptionError(ValueError):
    """A keyword option of :func:`register` it cannot take: ``option`` names it (None for
    unknown names), ``why`` says what was expected."""

    def __init__(self, option: str | None, why: str, text: str | None = None):
        super().__init__(text or (f"{option}: {why}" if option else why))
        self.option, self.why = option, why


def _check_values(o: dict) -> None:
    """``ValueError`` naming the first of register's keyword options (``o``: all of them)
    that register cannot take: a value outside its ``Literal`` choices, a count that is no
    whole number or below its least, a real number that is NaN, not a number or out of its
    range, a fixed point that is no finite (3,) point, or a solver that the residual does
    not allow."""
    so = o.get("solver_options")
    if so is not None and not isinstance(so, Mapping):
        raise OptionError("solver_options", "expected a mapping of solve_pose's options "
                          f"(e.g. {{'tol': 1e-8}}), got {type(so).__name__}")
    for name, allowed in _keyword_spec()[1].items():
        if o[name] not in allowed:
            raise OptionError(name, f"expected one of {list(allowed)}, got {o[name]!r}")
    from reglib.pose import MAX_ITERATIONS

    for name, low in _WHOLE.items():
        v = o[name]
        high = _WHOLE_MAX[name] or MAX_ITERATIONS
        if isinstance(v, bool) or not isinstance(v, int | np.integer) or not low <= v <= high:
            raise OptionError(name, f"expected an integer in [{low}, {high}], got {v!r}")
    for name, (ok, what) in _REAL.items():
        v = o[name]
        if not (is_real(v) and not np.isnan(v) and ok(v)):
            raise OptionError(name, f"expected {what}, got {v!r}")
    if o["fixed_point_ct"] is not None:
        try:
            fp = np.asarray(o["fixed_point_ct"], dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            fp = np.full(1, np.nan)
        if fp.shape != (3,) or not np.all(np.isfinite(fp)):
            raise OptionError("fixed_point_ct", "expected a finite (3,) point, got "
                              f"{o['fixed_point_ct']!r}")
    if ((o["residual"] == "normal" or o["fixed_point_ct"] is not None)
            and o["method"] not in ("robust", "linear")):
        why = (f"{o['method']!r} cannot be used with residual='normal' or a fixed point "
               "(their solve is an IRLS); use 'robust' or 'linear'")
        raise OptionError("method", why, f"method {why}")
    _solver_options(o["method"], so or {}, o["solver_iterations"], o["tukey_a"])


def _solver_options(method, solver_options, solver_iterations, tukey_a) -> dict:
    """The keyword options register passes to ``solve_pose``: ``solver_options`` with
    register's ``solver_iterations`` and ``tukey_a`` as defaults; :class:`OptionError` for a
    key ``solve_pose`` does not take or register sets itself, or a value it cannot use."""
    opts = dict(solver_options)
    if "rng" in opts:      # a review: SeedSequence's own TypeError, naming no option
        try:
            np.random.default_rng(opts["rng"])
        except (TypeError, ValueError):
            raise OptionError("solver_options", "rng: expected a seed (int >= 0) or a numpy "
                              f"Generator, got {opts['rng']!r}") from None
    try:
        _check_solver_options(method, opts)
        opts.setdefault("max_iterations", solver_iterations)
        opts.setdefault("tukey_a", tukey_a)
        _check_pose_options(method, **{k: opts.get(k, v) for k, v in _POSE_DEFAULTS.items()})
    except ValueError as err:
        why = str(err).removeprefix("solver_options: ")
        raise OptionError("solver_options", why, f"solver_options: {why}") from None
    return opts


@functools.cache
def _keyword_spec() -> tuple[dict, dict]:
    """register's keyword options with their defaults, and the allowed values of those typed
    ``Literal`` (read once from its signature)."""
    import typing

    params = inspect.signature(register).parameters
    defaults = {k: p.default for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY}
    hints = typing.get_type_hints(register)
    choices = {k: typing.get_args(h) for k, h in hints.items()
               if k in defaults and typing.get_origin(h) is typing.Literal}
    return defaults, choices


def check_options(**options) -> None:
    """``ValueError`` naming the option for keyword options of :func:`register` that it would
    refuse (an unknown name, or a value :func:`register` cannot take, register's defaults
    standing for the others), before any work is done."""
    defaults = _keyword_spec()[0]
    unknown = sorted(set(options) - set(defaults))
    if unknown:
        raise OptionError(None, f"unknown option(s) {unknown} of reglib.register.register (it "
                                f"takes {sorted(defaults)})")
    _check_values({**defaults, **options})


def register(surfaces, views, initial: RigidTransform, *,
             method: Literal["robust", "lm", "linear", "ransac"] = "robust",
             closest: Literal["compiled", "blocks", "dense", "hierarchy", "reference"] = "compiled",
             selection: Literal["paper", "closest"] = "paper",
             max_stab_distance_mm: float = 10.0,
             residual: Literal["line", "normal"] = "normal",
             fixed_point_ct=None, tukey_a: float = TUKEY_A, max_iterations: int = 50,
             tol_step_mm: float = 1e-4, tol_residual_mm: float = 0.0,
             stall_window: int = 5, tol_stall_mm: float = 0.1,
             max_motion_mm: float = MAX_MOTION_MM, max_rotation_deg: float = MAX_ROTATION_DEG,
             min_inlier_fraction: float = 0.2,
             stale_window: int = 10,
             solver_iterations: int = SOLVER_ITERATIONS, solver_options: dict | None = None
             ) -> RegistrationResult:
    """Register CT surfaces to the X-ray paths of several views (the paper's loop).

    Parameters
    ----------
    surfaces : list of SurfaceTopology (or ``(vertices, faces)`` pairs), CT frame, mm.
    views : list of View (robot frame).
    initial : RigidTransform ``ct2robot``, the start pose (or its (4, 4) matrix).
    method : pose solver of :func:`reglib.pose.solve_pose` (default "robust", the paper's),
        used with ``residual="line"``. With ``residual="normal"`` or ``fixed_point_ct`` the
        solve is ``solve_pose``'s constrained IRLS (``normals``, ``fixed_point``): robust
        (Tukey) or ``"linear"``; "lm" and "ransac" are refused there (ValueError).
    closest : Step A method of :func:`reglib.closest.closest_points` (default "compiled",
        the capsule pruning in numba, restricted like "blocks" to the contours Step B can
        select; all methods give the same matches).
    selection : "paper" (Step B: external paths take the farthest stabbed contour, else the
        closest) or "closest" (every path takes its closest contour).
    max_stab_distance_mm : with "paper", stabbed contours farther than this do not count
        (the stabbing test is local to the closest point; a contour of another surface far
        away can pass it by chance, and taking it as "the farthest" throws the pose off by
        tens of degrees). ``inf`` is the paper's rule as written. Default 10 mm.
    residual : "line" (the paper: point-to-path distance, solved by ``solve_pose``) or
        "normal" (only the component across the apparent contour, i.e. the distance from
        the point to the plane through the path along the contour; the matched point may
        slide along the contour, which converges in far fewer iterations, like
        point-to-plane ICP). "normal" and ``fixed_point_ct`` use ``solve_pose``'s IRLS.
        Default "normal": on a 7 deg / 20 mm start it converges exactly in 4-20
        iterations, where "line" still moves by 0.02-0.1 mm per iteration after 60.
    fixed_point_ct : (3,) mm or None; a CT point whose robot position ``initial(point)`` is
        known and kept (e.g. a located pin, as in the paper's experiment 1): only the
        rotation about it is optimised.
    tukey_a : Tukey's constant (units of the robust scale ``median / 0.6745``) of the pose
        solves. Default 4.685, the usual 95 %-efficiency value, not the paper's 2: with
        a = 2 the biweight keeps only ~60 % of the matches, and in the tests 2 of 8 starts
        7 deg / 20 mm off settled on a wrong pose (15 deg about the bone's long axis, pins
        7-8 mm off) that fits those 60 % to 0.02 mm; with 4.685 all 8 reach the truth in
        4-5 iterations.
    max_iterations : iterations of the loop.
    tol_step_mm : converged when an update moves the surfaces' bounding box by less.
    tol_residual_mm : converged when the inlier RMS residual falls below (0: never).
    stall_window, tol_stall_mm : converged when each of the last ``stall_window`` updates
        moved the surfaces by less than ``tol_stall_mm`` and the last is not below half the
        first (the steps stopped shrinking; 0 disables). With real (noisy) paths the
        matches keep switching between neighbouring contour points and the pose jitters by
        a few hundredths of a mm forever, so ``tol_step_mm`` alone is never met (seen on the
        experiment2 scene: 0.05 mm steps after 50 iterations, pins at 0.2-0.3 mm).
    stale_window : with ``method="linear"`` (plain least squares: outlier matches are not
        rejected, and the loop can cycle for ever; seen on the test bone, a period-4 cycle
        of 0.5-2.2 mm steps from every 7 deg / 20 mm start), stop, not converged, when the
        median point-path distance has not improved on its best by 1 % for this many
        iterations (0 disables). The robust methods are not affected.
    max_motion_mm, max_rotation_deg : divergence limits on the distance from ``initial``
        (bounding-box corner displacement, rotation angle).
    min_inlier_fraction : fail when the solver keeps a smaller share of the matches.
    solver_iterations : inner iterations of the pose solver per loop iteration (the matches
        change at every iteration anyway).
    solver_options : extra keyword arguments for ``solve_pose``. With ``method="ransac"``
        its ``rng`` (a seed, default 0) seeds one generator used by every iteration, so
        that a call is reproducible.

    Returns
    -------
    RegistrationResult; ``converged=False`` with a ``reason`` on failure, never a silent
    wrong pose. A result whose kept surface points (the matches the last solve kept) lie
    behind their view's centre of perspective is never converged (reason "cheirality: ...").

    Raises
    ------
    ValueError naming the argument: an ``initial`` that is not a rigid transform (not a
    rotation, or NaN), an unknown ``method``, ``residual`` or ``selection``, "lm" or
    "ransac" with ``residual="normal"`` or a fixed point, and option values out of range
    (``tukey_a <= 0``, NaN or negative tolerances, ``stall_window < 0``, ...).
    """
    t_start = time.perf_counter()
    tops = _as_topologies(surfaces)
    if isinstance(views, View):
        views = [views]
    try:
        views = list(views)
    except TypeError:
        raise ValueError(f"views: expected a list of View, got {type(views).__name__}") from None
    if not views:
        raise ValueError("views: at least one view is needed")
    for i, v in enumerate(views):
        if not isinstance(v, View):
            raise ValueError(f"views[{i}]: expected a View, got {type(v).__name__}")
    initial = as_rigid_transform(initial, "initial")      # a (4, 4) ct2robot matrix too
    R0 = np.asarray(initial.R, dtype=np.float64)
    if (not np.all(np.isfinite(R0)) or not np.all(np.isfinite(initial.t))
            or not np.allclose(R0.T @ R0, np.eye(3), atol=1e-6) or np.linalg.det(R0) < 0):
        raise ValueError("initial: its 3x3 part is not a rotation (orthonormal, det +1) or it "
                         "holds NaN/inf; a rigid ct2robot is expected")
    _check_values(dict(method=method, closest=closest, selection=selection,
                       max_stab_distance_mm=max_stab_distance_mm, residual=residual,
                       fixed_point_ct=fixed_point_ct, tukey_a=tukey_a,
                       max_iterations=max_iterations, tol_step_mm=tol_step_mm,
                       tol_residual_mm=tol_residual_mm, stall_window=stall_window,
                       tol_stall_mm=tol_stall_mm, max_motion_mm=max_motion_mm,
                       max_rotation_deg=max_rotation_deg,
                       min_inlier_fraction=min_inlier_fraction, stale_window=stale_window,
                       solver_iterations=solver_iterations, solver_options=solver_options))
    fixed_robot = None
    if fixed_point_ct is not None:
        fixed_robot = initial.apply(np.asarray(fixed_point_ct, dtype=np.float64).reshape(3))
    opts = _solver_options(method, solver_options or {}, solver_iterations, tukey_a)
    if method == "ransac":
        # one generator for the whole loop: each iteration draws new samples, and the same
        # call gives the same result (seed ``solver_options["rng"]``, default 0)
        opts["rng"] = np.random.default_rng(opts.get("rng", 0))
    corners = _corners(tops)

    def fail(reason, T=initial, it=0, history=(), **kw):
        return RegistrationResult(ct2robot=T, converged=False, reason=reason, iterations=it,
                                  history=tuple(history), time_s=time.perf_counter() - t_start,
                                  **kw)

    empty = [f"{i} ({v.name!r})" if v.name else str(i)
             for i, v in enumerate(views) if v.n_paths == 0]
    if empty:
        return fail(f"view {', '.join(empty)} has no contour pixels (no X-ray paths)")

    view_index = np.concatenate([np.full(v.n_paths, i) for i, v in enumerate(views)])
    o_r = np.vstack([v.origins for v in views])
    d_r = np.vstack([v.directions for v in views])
    # each path's source: the view's centre of perspective, as the point of the path nearest
    # to it (the paths' own origins are on the near calibration plane, which may lie beyond
    # the bone); "in front" is measured from there
    c_r = np.vstack([v.center for v in views])[view_index]
    src_r = o_r + np.sum((c_r - o_r) * d_r, axis=1, keepdims=True) * d_r
    if closest == "compiled":  # every view's Steps A and B in one compiled call
        stack = _stacked(tops)
        view0 = np.cumsum([0] + [v.n_paths for v in views]).astype(np.int64)
        ext_all = (np.concatenate([v.external for v in views]) if selection == "paper"
                   else np.zeros(len(o_r), dtype=bool))
        within_all = 0.0 if selection == "closest" else float(max_stab_distance_mm)
        within_all = within_all if np.isfinite(within_all) else -1.0
    T = initial
    history: list[IterationRecord] = []
    placed: list[np.ndarray] = []        # the corners each pose places (_limit_cycle)
    last = None
    best_median, best_at = np.inf, 0
    reason = ""
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        t0 = time.perf_counter()
        if closest == "compiled":
            p_ct, tans_ct, bad = _match_all(stack, views, T, o_r, d_r, ext_all, view0,
                                            within_all, float(max_stab_distance_mm))
        else:
            pts, tans, bad = [], [], None
            for i, v in enumerate(views):
                p_ct, e_ct, _, _ = match_view(tops, v, T, closest=closest, selection=selection,
                                              max_stab_distance_mm=max_stab_distance_mm)
                if p_ct is None:
                    bad = i
                    break
                pts.append(p_ct)
                tans.append(e_ct)
            if bad is None:
                p_ct = np.vstack(pts)
                tans_ct = np.vstack(tans)
        if bad is not None:
            return fail(f"view {bad} ({views[bad].name!r}): the surfaces show no apparent "
                        f"contour from its center at iteration {it} (degenerate geometry or "
                        "surfaces outside the view)", T=T, it=it, history=history)
        if residual == "normal" or fixed_robot is not None:
            normals = _across(d_r, T.apply_vectors(tans_ct)) if residual == "normal" else None
            try:
                inc = solve_pose(T.apply(p_ct), o_r, d_r, method=method, normals=normals,
                                 fixed_point=fixed_robot, tukey_a=tukey_a,
                                 max_iterations=solver_iterations, tol=1e-10,
                                 cheirality=False)  # judged below, from the views' centres
            except ValueError as err:
                return fail(f"pose solve refused the matches at iteration {it}: {err}", T=T,
                            it=it, history=history)
            if not inc.converged:
                return fail(f"pose solve failed at iteration {it}: {inc.message}", T=T,
                            it=it, history=history)
            T_new = inc.transform @ T
            dist, w = inc.residuals, inc.weights
        else:
            try:
                # RANSAC's hypotheses are judged by cheirality from the sources; the
                # others' results below, from the views' centres
                # the input checks once: the lines stay those of the views, and later
                # iterations only move the matched points along the surfaces (a
                # degenerate set of them fails the solve's rank test)
                res = solve_pose(p_ct, src_r if method == "ransac" else o_r, d_r,
                                 method=method, initial=T,
                                 **{"cheirality": method == "ransac", "check": it == 1,
                                    # the final pose's cheirality is judged below
                                    "mirror_check": False, **opts})
            except ValueError as err:
                return fail(f"pose solve refused the matches at iteration {it}: {err}", T=T,
                            it=it, history=history)
            if not res.converged and res.iterations < opts["max_iterations"]:
                return fail(f"pose solve failed at iteration {it}: {res.message}", T=T,
                            it=it, history=history)
            T_new = RigidTransform(res.R, res.t)
            dist, w = res.residuals, res.weights
        step_mm, step_deg = _motion(T_new, T, corners)
        inl = w > 0
        frac = float(np.mean(inl))
        rms = float(np.sqrt(np.mean(dist[inl] ** 2))) if inl.any() else float("inf")
        history.append(IterationRecord(it, rms, float(np.median(dist)), step_mm, step_deg, frac,
                                       len(dist), time.perf_counter() - t0))
        moved_mm, moved_deg = _motion(T_new, initial, corners)
        if moved_mm > max_motion_mm or moved_deg > max_rotation_deg:
            # the result keeps the last pose within the limits (this iteration's, whose
            # matches were just found), with its own figures: a runaway pose (one view: 500
            # mm off) and figures measured there mislead whoever prints or averages them
            dist, w = _residuals_at(T, p_ct, tans_ct, o_r, d_r, normal=(
                residual == "normal" or fixed_robot is not None),
                robust=method != "linear", tukey_a=tukey_a)
            last = (dist, w, p_ct, tans_ct)
            reason = (f"{DIVERGED} at iteration {it}: the pose moved {moved_mm:.1f} mm / "
                      f"{moved_deg:.1f} deg from the start (limits {max_motion_mm} mm, "
                      f"{max_rotation_deg} deg); the result keeps "
                      + ("the start" if it == 1 else f"iteration {it - 1}'s pose")
                      + ", the last within them")
            break
        last = (dist, w, p_ct, tans_ct)
        placed.append(T_new.apply(corners))
        T = T_new
        if frac < min_inlier_fraction:
            reason = (f"too few inliers at iteration {it}: {frac:.0%} of the matches kept "
                      f"(minimum {min_inlier_fraction:.0%}); the start is probably too far off")
            break
        if step_mm < tol_step_mm:
            converged = True
            reason = f"step {step_mm:.2e} mm below tol_step_mm={tol_step_mm}"
            break
        if rms < tol_residual_mm:
            converged = True
            reason = f"inlier RMS residual {rms:.2e} mm below tol_residual_mm={tol_residual_mm}"
            break
        window = [h.step_mm for h in history[-stall_window:]] if stall_window > 0 else []
        if stall_window > 0 and len(window) == stall_window and max(window) < tol_stall_mm \
                and window[-1] > 0.5 * window[0]:
            converged = True
            reason = (f"the last {stall_window} steps were all below tol_stall_mm="
                      f"{tol_stall_mm} (largest {max(window):.3g} mm) and no longer shrink: "
                      "the matches only alternate between neighbouring contour points")
            break
        # a limit cycle: the matches cycle through a few sets and the pose through as many
        # poses (seen with noisy clinic contours: a constant 0.35 mm step for ever, period
        # 2; on a random femur 0.23 / 0.25 / 0.45 mm steps, period 3; on experiment1's two
        # views, seed 3, 0.67 / 0.75 / 1.04 / 1.23 / 1.18 / 0.92 mm, period 6, which was
        # called unconverged after 50 or 200 iterations and refused 0.70 mm off, a
        # review); it has settled when each of the last p + 1 poses is where it was p
        # iterations before (two whole cycles), with steps below MAX_CYCLE_STEP_MM. Periods
        # above 2 not for "linear": plain least squares cycles with period 4 on wrong poses
        # and stops by stale_window instead.
        period = _settled_cycle(placed, history, tol_stall_mm,
                                (2,) if method == "linear" else CYCLE_PERIODS) \
            if stall_window > 0 else 0
        if period:
            converged = True
            reason = (f"the pose cycles through {period} poses (steps up to "
                      f"{max(h.step_mm for h in history[-period:]):.3g} mm; each returns "
                      f"within tol_stall_mm={tol_stall_mm} mm every {period} iterations): "
                      "the matches cycle between sets of neighbouring contour points")
            break
        med = history[-1].median_mm
        if med < 0.99 * best_median:
            best_median, best_at = med, it
        if method == "linear" and stale_window > 0 and it - best_at >= stale_window:
            reason = (f"stopped improving: the median point-path distance has not improved "
                      f"on its best ({best_median:.3g} mm at iteration {best_at}) for "
                      f"{stale_window} iterations, the pose still moves by {step_mm:.3g} mm "
                      "per iteration (least squares cycling between match sets)")
            break
    else:
        reason = (f"no convergence after {max_iterations} iterations (last step "
                  f"{history[-1].step_mm:.3g} mm)")
    dist, w, p_ct, tans_ct = last
    if converged:
        # cheirality: the registered surface points the solve kept must lie in front of
        # their view's centre of perspective (a mirror pose puts them behind the source)
        depth = np.sum((T.apply(p_ct) - c_r) * d_r, axis=1)
        behind = (w > 0) & ~(depth > 0)
        if np.any(behind):
            names = sorted({views[i].name or str(i) for i in view_index[behind]})
            converged = False
            reason = (f"cheirality: {int(np.count_nonzero(behind))} of the "
                      f"{int(np.count_nonzero(w > 0))} kept surface points lie behind the "
                      f"centre of perspective of view(s) {', '.join(names)} (a mirror or "
                      f"runaway pose; the loop had stopped with: {reason})")
    per_view = np.array([float(np.mean(w[view_index == i] > 0)) for i in range(len(views))])
    points_r = T.apply(p_ct)
    normals_r = _across(d_r, T.apply_vectors(tans_ct))
    vertices_r = T.apply(np.vstack([s.vertices for s in tops]))
    sens, weakest = pose_sensitivity(points_r, normals_r, w, vertices_r,
                                     fixed_point=fixed_robot)
    gain = gain_max = float("nan")
    response = np.zeros(0)
    if fixed_robot is not None:
        gain, gain_max, response = fixed_point_gain(points_r, normals_r, w, vertices_r,
                                                    fixed_robot)
    return RegistrationResult(
        ct2robot=T, converged=converged, reason=reason, iterations=it, history=tuple(history),
        residuals=dist, weights=w, view_index=view_index.astype(np.int64),
        inlier_fraction_per_view=per_view, time_s=time.perf_counter() - t_start,
        sensitivity=sens, weakest_motion=weakest, pivot_gain=gain, pivot_gain_max=gain_max,
        pivot_response=response,
    )
