"""Workspace checks: can the views and sweeps be taken around robot, C-arm, table and patient?

The paper names the workspace as an open problem: with a patient on the table, not every
C-arm pose leaves room for the robot to sweep the rod. :class:`Workspace` puts simple
collision shapes into the robot's pybullet client (the true arm and its rod are already
there): the C-arm of a view as boxes and cylinders (source housing, intensifier, the C),
the OR table as a box, the patient as the convex hulls of its outer bodies (or a box).
:func:`check_sweep` places the arm at every pose of a planned sweep and reports which
bodies collide, and which poses cannot be reached at all.

Frames and units: robot frame, mm (pybullet gets metres inside).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
import pybullet
from pydantic import Field

from reglib.geometry import RigidTransform
from testbed.spec import MILLIMETRES, Spec
from testbed.sweep import WorkspaceError

__all__ = ["Contact", "PoseCheck", "WorkspaceReport", "Workspace", "WorkspaceError",
           "WorkspaceSpec", "check_scene_workspace", "check_sweep", "require_feasible"]

_M = 1e-3


@dataclass(frozen=True)
class Contact:
    """Two bodies closer than the margin: names ``a``, ``b``; ``distance_mm`` (< 0: they
    overlap by that much)."""

    a: str
    b: str
    distance_mm: float


@dataclass(frozen=True)
class PoseCheck:
    """One pose of a sweep: its index, plane code, the contacts, or why it is unreachable."""

    index: int
    plane: int
    contacts: tuple[Contact, ...] = ()
    unreachable: str | None = None

    @property
    def ok(self) -> bool:
        return not self.contacts and self.unreachable is None


@dataclass
class WorkspaceReport:
    """The workspace check of one view: the C-arm's own contacts and every sweep pose."""

    view: str
    carm_contacts: list[Contact] = field(default_factory=list)
    poses: list[PoseCheck] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.carm_contacts and all(p.ok for p in self.poses)

    def colliding_pairs(self) -> set[tuple[str, str]]:
        pairs = {(c.a, c.b) for c in self.carm_contacts}
        for p in self.poses:
            pairs |= {(c.a, c.b) for c in p.contacts}
        return pairs

    def summary(self) -> str:
        """One line: ``view X: ok`` or what collides and which poses are unreachable."""
        if self.ok:
            return f"view {self.view}: ok ({len(self.poses)} poses)"
        parts = []
        pairs = sorted(self.colliding_pairs())
        if pairs:
            parts.append("collisions " + ", ".join(f"{a}-{b}" for a, b in pairs))
        bad = [p.index for p in self.poses if p.unreachable]
        if bad:
            parts.append(f"unreachable poses {bad}")
        hit = [p.index for p in self.poses if p.contacts]
        if hit:
            parts.append(f"colliding poses {hit}")
        return f"view {self.view}: cannot be taken: " + "; ".join(parts)


class Workspace:
    """Obstacles in the pybullet client of a :class:`testbed.robot.Robot`.

    Collisions are checked between the true arm (its links and the rod) and every obstacle,
    and between the C-arm's parts and the other obstacles (table, patient).
    """

    def __init__(self, robot):
        self.robot = robot
        self.client = robot.client
        self.obstacles: dict[str, int] = {}
        self.kind: dict[str, str] = {}
        n = pybullet.getNumJoints(robot.true_id, physicsClientId=self.client)
        self.link_names = {-1: "robot_base"}
        for j in range(n):
            name = pybullet.getJointInfo(robot.true_id, j, physicsClientId=self.client)[12]
            name = name.decode()
            self.link_names[j] = "rod" if name == "rod_mount" else f"robot_{name}"

    # -- adding obstacles
    def _add(self, name, kind, shape, pose: RigidTransform):
        if name in self.obstacles:
            raise ValueError(f"workspace: an obstacle named {name!r} exists already")
        q = pose.as_rotation().as_quat()
        body = pybullet.createMultiBody(baseMass=0, baseCollisionShapeIndex=shape,
                                        basePosition=list(pose.t * _M),
                                        baseOrientation=list(q), physicsClientId=self.client)
        self.obstacles[name] = body
        self.kind[name] = kind

    def add_box(self, name: str, half_extents_mm, pose: RigidTransform, *,
                kind: str = "obstacle") -> None:
        """A box of half extents (3,) mm at ``pose`` (box2robot)."""
        h = np.asarray(half_extents_mm, dtype=float)
        if h.shape != (3,) or np.any(h <= 0):
            raise ValueError(f"workspace box {name!r}: half_extents_mm must be 3 positive mm")
        shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=list(h * _M),
                                              physicsClientId=self.client)
        self._add(name, kind, shape, pose)

    def add_cylinder(self, name: str, radius_mm: float, length_mm: float,
                     pose: RigidTransform, *, kind: str = "obstacle") -> None:
        """A cylinder along the z axis of ``pose`` (cylinder2robot), centred at its origin."""
        shape = pybullet.createCollisionShape(pybullet.GEOM_CYLINDER, radius=radius_mm * _M,
                                              height=length_mm * _M,
                                              physicsClientId=self.client)
        self._add(name, kind, shape, pose)

    def add_mesh_hull(self, name: str, vertices_mm, *, kind: str = "patient") -> None:
        """The convex hull of a mesh's vertices (N, 3) mm, robot frame."""
        v = np.asarray(vertices_mm, dtype=float).reshape(-1, 3)
        if len(v) < 4:
            raise ValueError(f"workspace mesh {name!r}: at least 4 vertices are needed")
        c = v.mean(axis=0)
        import trimesh

        hull = trimesh.convex.convex_hull(v)
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_MESH, vertices=((hull.vertices - c) * _M).tolist(),
            physicsClientId=self.client)
        self._add(name, kind, shape, RigidTransform(np.eye(3), c))

    def add_bodies(self, bodies, *, kind: str = "patient") -> None:
        """World bodies (``testbed.bodies.Body``, robot frame): the convex hull of each
        outermost body (``inside`` None); nested bodies lie within their parents."""
        for b in bodies:
            if b.inside is not None:
                continue
            if b.mesh is not None:
                self.add_mesh_hull(b.name, b.mesh.vertices, kind=kind)
            else:
                for i, (c, r) in enumerate(zip(b.sphere_centers, b.sphere_radii)):
                    shape = pybullet.createCollisionShape(pybullet.GEOM_SPHERE,
                                                          radius=float(r) * _M,
                                                          physicsClientId=self.client)
                    self._add(f"{b.name}[{i}]", kind, shape, RigidTransform(np.eye(3), c))

    def add_table(self, top_center_mm, *, size_mm=(2000.0, 500.0, 60.0)) -> None:
        """The OR table top: a box whose top face is centred at ``top_center_mm`` (3,), long
        side along the robot's x axis."""
        sx, sy, sz = size_mm
        c = np.asarray(top_center_mm, dtype=float) - np.r_[0.0, 0.0, sz / 2]
        self.add_box("table", (sx / 2, sy / 2, sz / 2), RigidTransform(np.eye(3), c),
                     kind="table")

    def add_carm(self, carm, *, housing_radius_mm: float = 110.0,
                 c_depth_mm: float = 700.0, name: str = "carm") -> None:
        """The C-arm of a view: the source housing (a cylinder behind the source), the
        intensifier (a cylinder from the input plane on), and the C (three boxes joining them
        round the side given by ``carm.c_side_deg``: the carm's ``+x`` by default)."""
        R, src, sid = carm.carm2robot.R, carm.source_robot, carm.sid_mm
        ax = carm.axis_robot
        ii_r = carm.fov_radius_mm + 40.0
        pose = RigidTransform(R, src - 120.0 * ax)
        self.add_cylinder(f"{name}_source", housing_radius_mm, 200.0, pose, kind="carm")
        pose = RigidTransform(R, src + (sid + 100.0) * ax)
        self.add_cylinder(f"{name}_intensifier", ii_r, 200.0, pose, kind="carm")
        a = np.radians(carm.c_side_deg)
        y = np.cos(a) * R[:, 0] + np.sin(a) * R[:, 1]   # from the beam towards the arc
        Rc = np.column_stack([np.cross(y, ax), y, ax])   # the C's frame: y to the arc, z beam
        t = 40.0
        arm_len = c_depth_mm
        for label, depth in (("c_low", -220.0), ("c_high", sid + 200.0)):
            centre = src + depth * ax + y * arm_len / 2
            self.add_box(f"{name}_{label}", (t, arm_len / 2, t),
                         RigidTransform(Rc, centre), kind="carm")
        centre = src + (sid / 2) * ax + y * arm_len
        self.add_box(f"{name}_c_arc", (t, t, (sid + 420.0) / 2), RigidTransform(Rc, centre),
                     kind="carm")

    def remove(self, prefix: str) -> None:
        """Remove every obstacle whose name starts with ``prefix``."""
        for name in [n for n in self.obstacles if n.startswith(prefix)]:
            pybullet.removeBody(self.obstacles.pop(name), physicsClientId=self.client)
            self.kind.pop(name)

    # -- checks
    def robot_contacts(self, *, margin_mm: float = 0.0) -> list[Contact]:
        """Contacts between the true arm (at its current joints) and every obstacle."""
        out = []
        arm = self.robot.true_id
        for name, body in self.obstacles.items():
            pts = pybullet.getClosestPoints(arm, body, distance=margin_mm * _M,
                                            physicsClientId=self.client)
            seen = {}
            for p in pts:
                link = self.link_names.get(p[3], f"robot_link{p[3]}")
                seen[link] = min(seen.get(link, np.inf), p[8] / _M)
            out += [Contact(link, name, float(d)) for link, d in sorted(seen.items())]
        return out

    def carm_contacts(self, *, margin_mm: float = 0.0) -> list[Contact]:
        """Contacts between C-arm parts and the non-C-arm obstacles (table, patient)."""
        out = []
        carm = [n for n, k in self.kind.items() if k == "carm"]
        other = [n for n, k in self.kind.items() if k != "carm"]
        for a in carm:
            for b in other:
                pts = pybullet.getClosestPoints(self.obstacles[a], self.obstacles[b],
                                                distance=margin_mm * _M,
                                                physicsClientId=self.client)
                if pts:
                    out.append(Contact(a, b, float(min(p[8] for p in pts) / _M)))
        return out


def check_sweep(workspace: Workspace, carm, poses, *, margin_mm: float = 0.0,
                carm_name: str = "carm") -> WorkspaceReport:
    """Check a planned sweep of ``carm`` (``testbed.sweep.plan_sweep``) for collisions.

    Adds the C-arm to the workspace (removed again afterwards), then for every pose solves
    the robot's inverse kinematics and places the true arm there (no move, no encoder draw:
    the robot's state is restored). Returns a :class:`WorkspaceReport`.
    """
    robot = workspace.robot
    workspace.add_carm(carm, name=carm_name)
    report = WorkspaceReport(view=carm.name)
    q_true = robot.true_joints
    try:
        report.carm_contacts = workspace.carm_contacts(margin_mm=margin_mm)
        for i, pose in enumerate(poses):
            try:
                q = robot.inverse(pose.point_robot, pose.direction_robot)
            except ValueError as exc:
                report.poses.append(PoseCheck(i, pose.plane, (), str(exc)))
                continue
            robot.set_true_joints(q)
            contacts = tuple(workspace.robot_contacts(margin_mm=margin_mm))
            report.poses.append(PoseCheck(i, pose.plane, contacts))
    finally:
        robot.set_true_joints(q_true)
        workspace.remove(carm_name)
    return report


# --------------------------------------------------------------------------- scene check
class WorkspaceSpec(Spec):
    """``[workspace]``: the check that every view and sweep pose can be taken.

    ``check``: check the scene before any simulation (default true; false skips it and the
    reports say so in their first lines); ``margin_mm``: bodies closer than this count as
    colliding (0: touching or overlapping).
    """

    check: bool = True
    margin_mm: Annotated[float, Field(ge=0, le=100)] = 0.0


def check_scene_workspace(scene, world) -> list[WorkspaceReport]:
    """Check every view of ``scene`` and every pose of its calibration sweep.

    ``world`` is the scene's :class:`testbed.world.World` (robot frame): the patient's
    outermost bodies (as convex hulls), the table and foam, and the instruments are the
    obstacles, with the C-arm of each view (source housing, intensifier, the C). The robot's
    links, quill and rod are checked against all of them at every sweep pose, and the C-arm
    against the others.
    """
    from testbed.fluoroscope import make_carm
    from testbed.robot import Robot
    from testbed.sweep import plan_sweep

    reports = []
    with Robot(scene.robot, rng=0) as robot:
        ws = Workspace(robot)
        ws.add_bodies(world.patient_bodies, kind="patient")
        ws.add_bodies(world.table, kind="table")
        ws.add_bodies(world.instruments, kind="instrument")
        for i, vspec in enumerate(scene.views):
            carm = make_carm(scene.fluoroscope, vspec, view_index=i)
            reports.append(check_sweep(ws, carm, plan_sweep(carm, robot.spec),
                                       margin_mm=scene.workspace.margin_mm))
    return reports


def _first_problem(scene, report: WorkspaceReport, poses) -> str:
    name = scene.scene.name
    if report.carm_contacts:
        c = min(report.carm_contacts, key=lambda c: c.distance_mm)
        return (f"scene {name}: view {report.view}: the C-arm's {c.a} collides with {c.b} "
                f"({_gap(c)})")
    for p in report.poses:
        plane = _PLANES.get(p.plane, str(p.plane))
        if p.unreachable:
            return (f"scene {name}: view {report.view}, sweep pose {p.index} (plane {plane}): "
                    f"unreachable ({_clip(p.unreachable.splitlines()[0])})")
        if p.contacts:
            c = min(p.contacts, key=lambda c: c.distance_mm)
            return (f"scene {name}: view {report.view}, sweep pose {p.index} (plane {plane}): "
                    f"{c.a} collides with {c.b} ({_gap(c)}; {len(report.colliding_pairs())} "
                    f"colliding pair(s) in the view)")
    return f"scene {name}: view {report.view}: ok"


_PLANES = {-1: "reference", 0: "near", 1: "far", 2: "validation"}
# every field that moves the C-arm, and every field that moves or turns the rod's planes
# (reviews: a view refused for its source_to_isocenter_mm was told to change the others;
# the sweep's angles were not named)
_VIEW = ("move the view (views[].isocenter_mm, orbital_deg, angular_deg, c_side_deg, "
         "source_to_isocenter_mm)")
_SWEEP = ("move the rod's planes ([robot.sweep] near_fraction, validation_fraction, "
          "far_fraction: fractions of the source-intensifier distance; or turn them: "
          "rod_angle_deg, tilt_deg, validation_angle_deg)")


def _units_hint(scene, report: WorkspaceReport) -> str:
    """For an unreachable pose of a robot whose base height is a few millimetres: that it
    may be given in metres (a review, h93: ``base_height_mm = 0.85`` was read as 0.85 mm
    and the message named only the view)."""
    from testbed.robot import MIN_LINK_MM

    h = float(scene.robot.base_height_mm)
    if 0.0 < abs(h) < MIN_LINK_MM and any(p.unreachable for p in report.poses):
        return f" (robot.base_height_mm = {h:g}: given in metres? {MILLIMETRES})"
    return ""


def _remedy(report: WorkspaceReport) -> str:
    """What to change for the first problem of ``report``, by the bodies involved."""
    if report.carm_contacts:
        return _VIEW
    for p in report.poses:
        if p.unreachable:
            return f"{_VIEW} within the robot's reach, or change [robot]"
        if p.contacts:
            c = min(p.contacts, key=lambda c: c.distance_mm)
            mine, other = (c.a, c.b) if c.a.startswith(("robot", "rod")) else (c.b, c.a)
            if other.startswith("carm_intensifier"):
                if mine.startswith("rod"):
                    return f"{_SWEEP} further from the intensifier, or {_VIEW}"
                # the arm reaching past the intensifier's rim: moving the planes along the
                # beam does not clear it, nor does sweeping less of the field (a review of a
                # 12-inch intensifier: 8.6 mm became 5.5 / 4.8 mm, and 0.8-3.6 mm at a
                # coverage of 0.75-0.5); a rod held further from the wrist does (mount_mm
                # 180 mm instead of 120: feasible, and accepted at 0.34 mm)
                return ("the robot's arm reaches past the intensifier's rim: hold the rod "
                        "further from the wrist ([robot.rod] mount_mm, e.g. 180 mm for a "
                        f"12-inch intensifier), or {_VIEW}")
            if other.startswith("carm"):
                return f"{_VIEW}, or {_SWEEP}"
            base = other.split("[")[0]
            where = ("[patient] position_mm: the patient and the table" if base in (
                "table", "foam", "soft_tissue", "femur", "cancellous", "canal")
                or base.startswith(("pin_", "leg", "hip", "table"))
                else "its [[instruments]] position_mm")
            return f"{_SWEEP}, or move the {other} ({where}), or {_VIEW}"
    return _VIEW


def _clip(text: str, limit: int = 200) -> str:
    """``text`` cut at a word boundary to at most ``limit`` characters."""
    if len(text) <= limit:
        return text
    return text[:limit].rsplit(" ", 1)[0] + " ..."


def _gap(c: Contact) -> str:
    if c.distance_mm < 0:     # "overlap 0.0 mm" read as no collision (a review)
        return (f"overlap {-c.distance_mm:.1f} mm" if c.distance_mm <= -0.05
                else "overlap under 0.05 mm")
    return f"{c.distance_mm:.1f} mm apart, within the margin"


def require_feasible(scene, world) -> list[WorkspaceReport]:
    """:func:`check_scene_workspace`, raising :class:`WorkspaceError` (one line: view, pose,
    colliding pair) for the first view that cannot be taken. Skipped (returns []) when the
    scene says ``[workspace] check = false``."""
    if not scene.workspace.check:
        return []
    reports = check_scene_workspace(scene, world)
    for r in reports:
        if not r.ok:
            # opting out helps a scene that knowingly collides, never a pose the robot
            # cannot reach: the sweep then fails all the same (a review)
            first = next((p for p in r.poses if p.unreachable or p.contacts), None)
            out_of_reach = not r.carm_contacts and first is not None and bool(first.unreachable)
            raise WorkspaceError(_first_problem(scene, r, None) + "; " + _remedy(r)
                                 + _units_hint(scene, r)
                                 + ("" if out_of_reach else ", or set [workspace] check = false"))
    return reports
