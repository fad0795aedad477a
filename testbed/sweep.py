"""Calibration sweeps: the robot moves the rod across a near and a far plane of a C-arm view.

For each view (``testbed.fluoroscope.CArm``) :func:`plan_sweep` lays out the rod poses:

- a *near* and a *far* plane between source and intensifier, at ``near_fraction`` and
  ``far_fraction`` of the source-to-image distance from the source, perpendicular to the beam
  unless ``tilt_deg`` turns them about the rod's direction (the rod then stays parallel to
  the image plane);
- in each plane, the rod lies along the C-arm's x axis turned by ``rod_angle_deg`` and is
  stepped ``rows_per_plane`` times across the plane, its beads centred, so that the rows
  cover ``coverage`` of the field's diameter at that depth;
- the sweep starts with a *reference* frame, the rod parked outside the beam (its first
  difference then shows only the first row); both planes are swept in the same direction,
  so the far plane's first row lies at the other side of the image from the near plane's
  last (``reference_frames = "each"`` adds a reference frame before every plane);
- a validation row at another depth (``validation_fraction``) and in-plane angle
  (``validation_angle_deg``), also after a reference frame.

:func:`run_sweep` moves the robot through the plan, renders a frame after every move (X-rays
on continuously, ``move_time_s`` per move) and records the robot-reported bead positions (what
the calibration receives), the true ones (truth), the simulated time and the dose
(``dose_rate_mrem_per_min``; the paper: 40-50 mrem/min, 12-18 s per view).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reglib.geometry import RigidTransform
from testbed.robot import Robot, RobotSpec, SweepSpec


class WorkspaceError(ValueError):
    """A scene whose acquisition is physically impossible; the message names the view, the
    pose and the colliding pair (or the pose the robot cannot reach). Raised by
    :func:`testbed.workspace.require_feasible` before any simulation, and by
    :func:`run_sweep` for a pose out of the robot's reach when the check was skipped."""


#: the sweep poses' planes by their number (``SweepPose.plane``): -1 is the frame without
#: the rod
PLANE_NAMES = {-1: "reference frame", 0: "near plane", 1: "far plane", 2: "validation row"}

__all__ = ["SweepPose", "Sweep", "plan_sweep", "run_sweep", "PLANE_CODES"]

PLANE_CODES = {"reference": -1, "near": 0, "far": 1, "validation": 2}


@dataclass(frozen=True)
class SweepPose:
    """One commanded rod pose: bead 0 at ``point_robot`` (3,) mm, rod along the unit
    ``direction_robot`` (3,); ``plane`` as in :data:`PLANE_CODES`; ``row`` its index."""

    plane: int
    row: int
    point_robot: np.ndarray
    direction_robot: np.ndarray


@dataclass
class Sweep:
    """A recorded sweep of one view.

    Attributes
    ----------
    view : the view's name.
    frames : (F, H, W) uint8 video frames, one after each move.
    plane : (F,) int, :data:`PLANE_CODES` of each frame.
    beads_reported : (F, n, 3) mm robot frame, the robot-reported bead centres (NaN on
        reference frames: the rod is parked, its beads are outside the beam).
    beads_true : (F, n, 3) mm, the true bead centres (truth).
    joints : (F, 5) commanded joints (rad, rad, mm, rad, rad).
    time_s : (F,) simulated time at each frame (s, from the start of the sweep).
    duration_s : total fluoroscopy time (X-rays on from the first move to the last frame).
    dose_mrem : the dose for ``duration_s`` at the sweep's dose rate.
    bead_positions_mm : (n,) bead positions along the rod.
    fov : (H, W) bool, the field of view.
    """

    view: str
    frames: np.ndarray
    plane: np.ndarray
    beads_reported: np.ndarray
    beads_true: np.ndarray
    joints: np.ndarray
    time_s: np.ndarray
    duration_s: float
    dose_mrem: float
    bead_positions_mm: np.ndarray
    fov: np.ndarray
    poses: list

    def for_calibration(self) -> dict:
        """The fields a clinic has, as keyword arguments of ``reglib.markers.SweepData``
        (no truth)."""
        return dict(view=self.view, frames=self.frames, plane=self.plane,
                    beads_robot=self.beads_reported, bead_positions_mm=self.bead_positions_mm,
                    mask=self.fov)


def _rotate(v, axis, angle_rad):
    """Rotate vector ``v`` (3,) about unit ``axis`` by ``angle_rad`` (Rodrigues)."""
    return RigidTransform.from_rotvec(np.asarray(axis) * angle_rad).apply_vectors(v)


def plan_sweep(carm, spec: RobotSpec) -> list[SweepPose]:
    """Rod poses of a calibration sweep of ``carm`` (see the module docstring).

    The rod points away from the robot's base (bead 0 nearest the robot) so that the arm
    holds it from outside the beam. Returns the poses in the order they are taken.
    """
    sw: SweepSpec = spec.sweep
    s = spec.rod.bead_positions_mm()
    span = s[-1]
    R = carm.carm2robot.R
    src = carm.source_robot
    axis = carm.axis_robot
    a = np.radians(sw.rod_angle_deg)

    def frame(angle):
        e1 = R @ np.array([np.cos(angle), np.sin(angle), 0.0])
        e2 = R @ np.array([-np.sin(angle), np.cos(angle), 0.0])
        return e1, e2

    def orient(e1, centre):
        # bead 0 towards the robot's base axis (the robot frame's z axis)
        base = np.array([0.0, 0.0, centre[2]])
        return e1 if np.linalg.norm(centre - span / 2 * e1 - base) <= np.linalg.norm(
            centre + span / 2 * e1 - base) else -e1

    poses: list[SweepPose] = []
    for code, f in ((0, sw.near_fraction), (1, sw.far_fraction)):
        e1, e2 = frame(a)
        e2 = _rotate(e2, e1, np.radians(sw.tilt_deg))
        centre = src + f * carm.sid_mm * axis
        d = orient(e1, centre)
        radius = f * carm.fov_radius_mm  # the field's radius at this depth
        offsets = np.linspace(-1.0, 1.0, sw.rows_per_plane) * sw.coverage * radius
        park = centre - (radius + spec.rod.diameter_mm + 30.0) * e2
        if code == 0 or sw.reference_frames == "each":
            poses.append(SweepPose(-1, -1, park - span / 2 * d, d))
        for k, y in enumerate(offsets):
            c = centre + y * e2
            poses.append(SweepPose(code, k, c - span / 2 * d, d))
    e1, e2 = frame(a + np.radians(sw.validation_angle_deg))
    centre = src + sw.validation_fraction * carm.sid_mm * axis + sw.validation_offset_mm * e2
    d = orient(e1, centre)
    radius = sw.validation_fraction * carm.fov_radius_mm
    park = centre - (radius + spec.rod.diameter_mm + 30.0) * e2
    if sw.reference_frames == "each":
        poses.append(SweepPose(-1, -1, park - span / 2 * d, d))
    poses.append(SweepPose(2, 0, centre - span / 2 * d, d))
    # the validation row must show enough beads to be identified (identify_row needs 4):
    # those within 0.9 of the field's radius at their depth (nearer the rim, the detector's
    # window is cut). A review's 90 mm offset left 2 of 8 in a 9-inch field, and the views
    # failed as "0 validation markers", naming no field
    def beads_inside(row_centre) -> int:
        rho = carm.point_rho(row_centre - span / 2 * d + s[:, None] * d)
        return int(np.count_nonzero(rho <= VALIDATION_FIELD_SHARE))

    inside = beads_inside(centre)
    if inside < MIN_VALIDATION_BEADS:
        inside0 = beads_inside(src + sw.validation_fraction * carm.sid_mm * axis)
        if inside0 < MIN_VALIDATION_BEADS:
            # no offset can help: the rod's beads are too far apart for the field (a review
            # blamed the default offset of a rod of 432 mm)
            raise ValueError(
                f"robot.rod.bead_spacings_mm: the rod's {len(s)} beads span {span:.0f} mm, and "
                f"only {inside0} of them fall within {VALIDATION_FIELD_SHARE:g} of the field's "
                f"radius even on the beam's axis at the validation row (the field there is "
                f"{2 * radius:.0f} mm across; need {MIN_VALIDATION_BEADS}): space the beads "
                "more closely")
        raise ValueError(
            f"robot.sweep.validation_offset_mm = {sw.validation_offset_mm:g}: only {inside} of "
            f"the validation row's {len(s)} beads fall within the field of view (need "
            f"{MIN_VALIDATION_BEADS}, within {VALIDATION_FIELD_SHARE:g} of its radius); move "
            "the row towards the beam's axis, or check validation_fraction and "
            "validation_angle_deg")
    return poses


#: the validation row's beads that must lie within this share of the field's radius...
VALIDATION_FIELD_SHARE = 0.9
#: ...at least this many (reglib.markers.identify_row identifies a row from 4)
MIN_VALIDATION_BEADS = 4


def run_sweep(robot: Robot, carm, fluoro, *, bodies=(), rng=None, noise: bool | None = None,
              poses: list[SweepPose] | None = None, progress=None) -> Sweep:
    """Move the rod through a sweep of ``carm`` and render a frame after every move.

    Parameters
    ----------
    robot : Robot
    carm : testbed.fluoroscope.CArm
    fluoro : testbed.fluoroscope.FluoroscopeSpec
    bodies : static world bodies (robot frame) seen with the rod (patient, instruments).
    rng : numpy Generator, int or None (image noise).
    noise : None follows ``fluoro.noise``.
    poses : the plan (default :func:`plan_sweep`).

    The frames are rendered by :class:`testbed.fluoroscope.SweepRenderer` (the static
    bodies cast once per view, per frame only the rays that can meet the rod), whose
    frames are those of :func:`testbed.fluoroscope.render` with every body.

    Raises ``ValueError`` naming the view and pose when a pose is unreachable.
    """
    from testbed.fluoroscope import SweepRenderer

    rng = np.random.default_rng(rng)
    spec = robot.spec
    plan = plan_sweep(carm, spec) if poses is None else poses
    n = spec.rod.n_beads
    F = len(plan)
    frames = np.zeros((F, carm.height_px, carm.width_px), dtype=np.uint8)
    rep = np.full((F, n, 3), np.nan)
    tru = np.full((F, n, 3), np.nan)
    joints = np.zeros((F, 5))
    renderer = SweepRenderer(carm, fluoro, list(bodies))
    for i, pose in enumerate(plan):
        try:
            joints[i] = robot.place_rod(pose.point_robot, pose.direction_robot)
        except ValueError as exc:
            # (a review: "plane -1, row -1" for the reference frame, and no scene file named,
            # with [workspace] check = false, which skips the check that names it first)
            where = PLANE_NAMES.get(pose.plane, f"plane {pose.plane}")
            if pose.plane >= 0 and pose.row >= 0:
                where += f", row {pose.row}"
            raise WorkspaceError(
                f"view {carm.name!r}: sweep pose {i} ({where}): {exc}; the robot cannot hold "
                "the rod there: move the view (views[].isocenter_mm, orbital_deg, angular_deg) "
                "within the robot's reach, or change [robot] (base, links, joint limits) or "
                "the rod's planes ([robot.sweep])") from None
        if pose.plane >= 0:
            rep[i] = robot.bead_positions()
            tru[i] = robot.bead_positions(true=True)
        frames[i] = renderer.render(robot.rod_bodies(), rng=rng, noise=noise)
        if progress is not None:
            progress(i, F)
    sw = spec.sweep
    time_s = (np.arange(F) + 1) * sw.move_time_s
    duration = float(F * sw.move_time_s)
    return Sweep(view=carm.name, frames=frames, plane=np.array([p.plane for p in plan]),
                 beads_reported=rep, beads_true=tru, joints=joints, time_s=time_s,
                 duration_s=duration, dose_mrem=duration / 60.0 * sw.dose_rate_mrem_per_min,
                 bead_positions_mm=spec.rod.bead_positions_mm(), fov=renderer.fov, poses=plan)
