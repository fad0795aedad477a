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
   point, a rotation about that point only (:func:`solve_increment`);
4. stop when the step is below ``tol_step_mm``, the residual below ``tol_residual_mm``, or
   after ``max_iterations``; fail (``converged=False`` with a ``reason``) on an empty view, a
   view without apparent contour, a pose solve that breaks down, too few inliers, or a pose
   that runs away from the start (divergence).

Frames: surfaces in ``ct`` (mm); views (centers and paths) in ``robot`` (mm); the result is
``ct2robot`` (``x_robot = R x_ct + t``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from reglib.apparent import SurfaceTopology, apparent_contours, prepare_surface
from reglib.closest import ContourSet, closest_points, select_contours
from reglib.geometry import RigidTransform, as_lines, skew
from reglib.pose import solve_pose, tukey_weights

__all__ = [
    "IterationRecord",
    "RegistrationResult",
    "View",
    "match_view",
    "register",
    "solve_increment",
]


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
        ext = (np.ones(len(o), dtype=bool) if self.external is None
               else np.asarray(self.external, dtype=bool).reshape(-1))
        if ext.shape != (len(o),):
            raise ValueError(f"{label}: external must have shape ({len(o)},), got {ext.shape}")
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


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """Outcome of :func:`register`. Falsy when it did not converge; ``reason`` says why.

    Attributes
    ----------
    ct2robot : RigidTransform, the final pose (the start pose if it failed before a solve).
    converged : bool.
    reason : str, why it stopped (converged: which test; failed: what went wrong).
    iterations : int.
    history : tuple of IterationRecord.
    residuals : (M,) float64, mm, point-path distances of the last matches at the final pose.
    weights : (M,) float64, the solver's final weights of those matches (0 = rejected).
    view_index : (M,) int64, the view of each match.
    inlier_fraction_per_view : (V,) float64.
    time_s : float, total wall time.
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

    def __bool__(self) -> bool:
        return bool(self.converged)

    @property
    def inlier_fraction(self) -> float:
        return float(np.mean(self.weights > 0)) if self.weights.size else 0.0


# --------------------------------------------------------------------------- own solver
def solve_increment(points, origins, directions, *, normals=None, fixed_point=None,
                    robust: bool = True, tukey_a: float = 2.0, max_iterations: int = 20,
                    tol: float = 1e-10):
    """Rigid update that puts ``points`` on their lines: robust Gauss-Newton (IRLS).

    The paper's linearised robust solver, written for the two cases ``solve_pose`` does not
    cover: a rotation about a fixed point (experiment 1) and a residual measured only along
    a given normal of each line (the "normal" residual of :func:`register`). The update is
    linearised as ``x' = x + w x (x - m) + tau`` about the (weighted) centroid ``m`` of the
    points, or about ``fixed_point`` (then ``tau = 0``), and each step is applied exactly
    (rotation vector ``w``). Weights: Tukey's biweight, ``a = tukey_a``, scale
    ``median(|r|) / 0.6745``.

    Parameters
    ----------
    points : (N, 3) mm, the matched points with the current pose applied (lines' frame).
    origins, directions : (N, 3) mm and unit, the lines.
    normals : (N, 3) unit vectors orthogonal to the directions, or None. With normals the
        residual is the scalar ``n . (x - o)`` (distance to the plane through the line with
        normal n); without, the 3-vector ``(I - d d^T)(x - o)`` (distance to the line).
    fixed_point : (3,) mm or None; when given only a rotation about it is solved.

    Returns
    -------
    (update: RigidTransform in the lines' frame, residuals (N,) mm at the end,
     weights (N,), ok: bool, message: str)
    """
    x = np.array(points, dtype=np.float64)
    o, d = as_lines(origins, directions)
    if x.shape != o.shape:
        raise ValueError(f"points {x.shape} and lines {o.shape} must have the same shape")
    dof = 3 if fixed_point is not None else 6
    need = 2 if fixed_point is not None else 3
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != x.shape:
            raise ValueError(f"normals {nrm.shape} must have the shape of points {x.shape}")
        need = dof
    if len(x) < need:
        raise ValueError(f"solve_increment needs at least {need} matches, got {len(x)}")
    M = None if normals is not None else np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    f = None if fixed_point is None else np.asarray(fixed_point, dtype=np.float64).reshape(3)
    scale = float(np.sqrt(np.mean(np.sum((x - x.mean(0)) ** 2, axis=1)))) or 1.0
    R_tot, t_tot = np.eye(3), np.zeros(3)
    w = np.ones(len(x))

    def residuals(x):
        if M is None:
            r = np.einsum("ij,ij->i", nrm, x - o)
            return r[:, None], np.abs(r)
        r = np.einsum("nij,nj->ni", M, x - o)
        return r, np.linalg.norm(r, axis=1)

    ok, message = True, ""
    for _ in range(max_iterations):
        r, dist = residuals(x)
        if robust:
            s = max(float(np.median(dist)) / 0.6745, 1e-12 * scale)
            w = tukey_weights(dist / s, tukey_a)
            if np.count_nonzero(w) < need:
                return (RigidTransform(R_tot, t_tot), dist, w, False,
                        f"fewer than {need} matches kept by the biweight")
        m = f if f is not None else (w @ x) / w.sum()
        y = x - m
        if M is None:
            J = np.concatenate([np.cross(y, nrm), nrm], axis=1)[:, None, :dof]
        else:
            J = np.concatenate([-np.einsum("nij,njk->nik", M, skew(y)), M], axis=2)
            J = J[:, :, :dof]
        J2 = J.reshape(-1, dof)                     # one row per residual component
        wr = np.repeat(w, J.shape[1])
        A = J2.T @ (wr[:, None] * J2)
        b = -J2.T @ (wr * r.reshape(-1))
        sv = np.linalg.svd(A, compute_uv=False)
        if sv[-1] <= 1e-12 * max(sv[0], 1e-300):
            return (RigidTransform(R_tot, t_tot), dist, w, False,
                    "the update is undetermined by the matches (degenerate geometry)")
        delta = np.linalg.solve(A, b)
        Q = Rotation.from_rotvec(delta[:3]).as_matrix()
        tau = delta[3:] if dof == 6 else np.zeros(3)
        x = y @ Q.T + m + tau
        R_tot, t_tot = Q @ R_tot, Q @ (t_tot - m) + m + tau
        if delta[:3] @ delta[:3] < tol * tol and tau @ tau < (tol * scale) ** 2:
            break
    _, dist = residuals(x)
    if robust:
        s = max(float(np.median(dist)) / 0.6745, 1e-12 * scale)
        w = tukey_weights(dist / s, tukey_a)
    return RigidTransform(R_tot, t_tot), dist, w, ok, message


# --------------------------------------------------------------------------- one view
def match_view(surfaces, view: View, ct2robot: RigidTransform, *, closest: str = "blocks",
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
    robot2ct = ct2robot.inverse()
    c_ct = robot2ct.apply(view.center)
    o_ct, d_ct = robot2ct.apply_lines(view.origins, view.directions)
    conts, owner = [], []
    for k, top in enumerate(surfaces):
        cs = apparent_contours(top, c_ct)
        conts += cs
        owner += [k] * len(cs)
    if not conts:
        return None, None, ContourSet.from_polylines([], []), np.zeros(0, dtype=np.int64)
    cset = ContourSet.from_contours(conts)
    within = None
    if closest == "blocks":
        # Step B only looks at the nearest contour and the stabbed ones within the limit
        within = 0.0 if selection == "closest" else float(max_stab_distance_mm)
        within = None if not np.isfinite(within) else within
    cp = closest_points(cset, o_ct, d_ct, method=closest, within_mm=within)
    ext = view.external if selection == "paper" else np.zeros(view.n_paths, dtype=bool)
    sel = select_contours(cp, cset, d_ct, ext, max_stab_distance_mm=max_stab_distance_mm)
    rows = np.arange(len(sel))
    pts = cp.p[rows, sel]
    tangents = cset.tangents(cp.segment[rows, sel], pts)
    return pts, tangents, cset, np.asarray(owner, dtype=np.int64)


# --------------------------------------------------------------------------- the loop
def _corners(surfaces) -> np.ndarray:
    v = np.vstack([s.vertices for s in surfaces])
    lo, hi = v.min(axis=0), v.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                     for z in (lo[2], hi[2])])


def _motion(a: RigidTransform, b: RigidTransform, corners) -> tuple[float, float]:
    mm = float(np.max(np.linalg.norm(a.apply(corners) - b.apply(corners), axis=1)))
    return mm, float(np.degrees((a @ b.inverse()).angle_rad))


def _as_topologies(surfaces):
    out = []
    if isinstance(surfaces, SurfaceTopology):
        surfaces = [surfaces]
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


def register(surfaces, views, initial: RigidTransform, *,
             method: Literal["robust", "lm", "linear", "ransac"] = "robust",
             closest: Literal["blocks", "dense", "hierarchy", "reference"] = "blocks",
             selection: Literal["paper", "closest"] = "paper",
             max_stab_distance_mm: float = 10.0,
             residual: Literal["line", "normal"] = "normal",
             fixed_point_ct=None, tukey_a: float = 4.685, max_iterations: int = 50,
             tol_step_mm: float = 1e-4, tol_residual_mm: float = 0.0,
             stall_window: int = 5, tol_stall_mm: float = 0.1, max_motion_mm: float = 150.0,
             max_rotation_deg: float = 45.0, min_inlier_fraction: float = 0.2,
             solver_iterations: int = 20, solver_options: dict | None = None
             ) -> RegistrationResult:
    """Register CT surfaces to the X-ray paths of several views (the paper's loop).

    Parameters
    ----------
    surfaces : list of SurfaceTopology (or ``(vertices, faces)`` pairs), CT frame, mm.
    views : list of View (robot frame).
    initial : RigidTransform ``ct2robot``, the start pose.
    method : pose solver of :func:`reglib.pose.solve_pose` (default "robust", the paper's),
        used with ``residual="line"``. With ``residual="normal"`` or ``fixed_point_ct`` the
        loop's own IRLS solver (:func:`solve_increment`) is used instead: robust (Tukey)
        unless ``method="linear"``; "lm" and "ransac" then also mean robust.
    closest : Step A method of :func:`reglib.closest.closest_points` (default "blocks",
        restricted to the contours Step B can select; all methods give the same matches).
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
        point-to-plane ICP). "normal" and ``fixed_point_ct`` use :func:`solve_increment`.
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
    max_motion_mm, max_rotation_deg : divergence limits on the distance from ``initial``
        (bounding-box corner displacement, rotation angle).
    min_inlier_fraction : fail when the solver keeps a smaller share of the matches.
    solver_iterations : inner iterations of the pose solver per loop iteration (the matches
        change at every iteration anyway).
    solver_options : extra keyword arguments for ``solve_pose``.

    Returns
    -------
    RegistrationResult; ``converged=False`` with a ``reason`` on failure, never a silent
    wrong pose.
    """
    t_start = time.perf_counter()
    tops = _as_topologies(surfaces)
    views = list(views)
    if not views:
        raise ValueError("views: at least one view is needed")
    for i, v in enumerate(views):
        if not isinstance(v, View):
            raise ValueError(f"views[{i}]: expected a View, got {type(v).__name__}")
    if not isinstance(initial, RigidTransform):
        raise ValueError(f"initial: expected a RigidTransform ct2robot, got {type(initial)}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations: expected >= 1, got {max_iterations}")
    fixed_robot = None
    if fixed_point_ct is not None:
        fp = np.asarray(fixed_point_ct, dtype=np.float64).reshape(-1)
        if fp.shape != (3,) or not np.all(np.isfinite(fp)):
            raise ValueError(f"fixed_point_ct: expected a finite (3,) point, got {fp!r}")
        fixed_robot = initial.apply(fp)
    if residual not in ("line", "normal"):
        raise ValueError(f"residual: expected 'line' or 'normal', got {residual!r}")
    if selection not in ("paper", "closest"):
        raise ValueError(f"selection: expected 'paper' or 'closest', got {selection!r}")
    opts = dict(solver_options or {})
    opts.setdefault("max_iterations", solver_iterations)
    opts.setdefault("tukey_a", tukey_a)
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
    T = initial
    history: list[IterationRecord] = []
    last = None
    reason = ""
    converged = False
    it = 0
    for it in range(1, max_iterations + 1):
        t0 = time.perf_counter()
        pts, tans = [], []
        for i, v in enumerate(views):
            p_ct, e_ct, _, _ = match_view(tops, v, T, closest=closest, selection=selection,
                                          max_stab_distance_mm=max_stab_distance_mm)
            if p_ct is None:
                return fail(f"view {i} ({v.name!r}): the surfaces show no apparent contour "
                            f"from its center at iteration {it} (degenerate geometry or "
                            "surfaces outside the view)", T=T, it=it, history=history)
            pts.append(p_ct)
            tans.append(e_ct)
        p_ct = np.vstack(pts)
        if residual == "normal" or fixed_robot is not None:
            normals = None
            if residual == "normal":
                normals = np.cross(d_r, T.apply_vectors(np.vstack(tans)))
                nn = np.linalg.norm(normals, axis=1, keepdims=True)
                normals = normals / np.where(nn > 0, nn, 1.0)
            try:
                U, dist, w, ok, msg = solve_increment(
                    T.apply(p_ct), o_r, d_r, normals=normals, fixed_point=fixed_robot,
                    robust=method != "linear", tukey_a=tukey_a,
                    max_iterations=solver_iterations)
            except ValueError as err:
                return fail(f"pose solve refused the matches at iteration {it}: {err}", T=T,
                            it=it, history=history)
            if not ok:
                return fail(f"pose solve failed at iteration {it}: {msg}", T=T, it=it,
                            history=history)
            T_new = U @ T
        else:
            try:
                res = solve_pose(p_ct, o_r, d_r, method=method, initial=T, **opts)
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
        last = (dist, w)
        T = T_new
        moved_mm, moved_deg = _motion(T, initial, corners)
        if moved_mm > max_motion_mm or moved_deg > max_rotation_deg:
            reason = (f"diverged at iteration {it}: the pose moved {moved_mm:.1f} mm / "
                      f"{moved_deg:.1f} deg from the start (limits {max_motion_mm} mm, "
                      f"{max_rotation_deg} deg)")
            break
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
        if len(window) == stall_window and max(window) < tol_stall_mm and \
                window[-1] > 0.5 * window[0]:
            converged = True
            reason = (f"the last {stall_window} steps were all below tol_stall_mm="
                      f"{tol_stall_mm} (largest {max(window):.3g} mm) and no longer shrink: "
                      "the matches only alternate between neighbouring contour points")
            break
    else:
        reason = (f"no convergence after {max_iterations} iterations (last step "
                  f"{history[-1].step_mm:.3g} mm)")
    dist, w = last
    per_view = np.array([float(np.mean(w[view_index == i] > 0)) for i in range(len(views))])
    return RegistrationResult(
        ct2robot=T, converged=converged, reason=reason, iterations=it, history=tuple(history),
        residuals=dist, weights=w, view_index=view_index.astype(np.int64),
        inlier_fraction_per_view=per_view, time_s=time.perf_counter() - t_start,
    )
