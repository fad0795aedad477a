"""The surgical robot in pybullet, its calibration rod, and the robot's imperfections.

The robot is a 5-DOF SCARA-like arm (after ROBODOC): base yaw, elbow yaw, a vertical slide,
wrist yaw and wrist pitch. Its tool is the calibration rod: a radiolucent ULTEM cylinder with
steel beads on its axis and a metallic tip. Five joints place a *line* (a point on the rod
and the rod's direction); the roll of the rod about its own axis is not controlled and does
not matter, because the beads lie on the axis.

Frames (DESIGN.md): ``robot`` is the robot base (z up, the frame of calibration); ``rod`` has
its origin at the centre of bead 0 and its +x axis along the rod towards the tip; the beads
sit at ``x = RodSpec.bead_positions_mm()`` on that axis.

Imperfection, as a real robot has it (magnitudes and references: ``docs/error-model.md``).
The controller knows only the *nominal* kinematic model; the *true* arm differs from it by
small kinematic offsets (joint origins moved by
``kinematic_offset_mm`` and turned by ``kinematic_offset_deg``, drawn once per robot from its
``rng``). After a move, the servo stops where the encoders read the commanded angles, but the
encoders err by ``encoder_noise_deg`` / ``encoder_noise_mm`` (a fresh draw per move), so the
true joints differ from the read ones. The robot *reports* the nominal model at the read
joints (:attr:`Robot.reported_rod2robot`); the world holds the true model at the true joints
(:attr:`Robot.true_rod2robot`). Beads are rendered at the true pose; the calibration only
ever sees the reported one. The rod itself is mounted with a small error
(``rod_mount_error_mm``/``_deg``, after the tip calibration), its beads sit off their nominal
places (``RodSpec.bead_along_error_mm``/``bead_across_error_mm``, drawn once per robot), and it
sags under gravity as a cantilever (``RodSpec.sag``); only the true beads see these.

pybullet works in metres inside this module (its collision margins are tuned for metres);
everything that leaves the module is in mm.
"""

from __future__ import annotations

import functools
import os
import tempfile
from typing import Annotated, Literal

import numpy as np
import pybullet
import trimesh
from pydantic import Field, model_validator
from scipy.spatial.transform import Rotation

from reglib.geometry import RigidTransform
from testbed.bodies import Body
from testbed.spec import MILLIMETRES, Positive, Spec, TurnDeg

__all__ = [
    "JOINT_NAMES",
    "RodSpec",
    "SweepSpec",
    "RobotSpec",
    "Robot",
    "robot_urdf",
    "rod_bodies",
]

JOINT_NAMES = ("yaw", "elbow", "slide", "wrist", "pitch")
_PRISMATIC = (False, False, True, False, False)
_M = 1e-3  # metres per mm


# --------------------------------------------------------------------------- scene sections
#: the least difference (largest over a run's three gap ratios, each gap over the run's
#: length) between the gaps of two runs of 4 consecutive beads of a rod, one of them maybe
#: reversed; the default rod's closest pair differs by 0.035
MIN_RUN_CONTRAST = 0.02


def _alike_runs(gaps) -> str | None:
    """Two runs of 4 consecutive beads (3 gaps) that an image could not tell apart, either
    read forwards or backwards, named; None when every pair differs by
    :data:`MIN_RUN_CONTRAST`."""
    g = np.asarray(gaps, dtype=np.float64)
    runs = [g[i:i + 3] / g[i:i + 3].sum() for i in range(len(g) - 2)]
    for i, a in enumerate(runs):
        for j in range(i, len(runs)):
            for turned in (False, True):
                if i == j and not turned:
                    continue
                b = runs[j][::-1] if turned else runs[j]
                if np.abs(a - b).max() < MIN_RUN_CONTRAST:
                    what = (f"beads {i}-{i + 3} read backwards look like themselves" if i == j
                            else f"beads {i}-{i + 3} look like beads {j}-{j + 3}"
                            + (" read backwards" if turned else ""))
                    return what
    return None


#: the longest marker rod a scene may give (mm, from the wrist to the tip's end)
MAX_ROD_LENGTH_MM = 1000.0


class RodSpec(Spec):
    """``[robot.rod]``: the calibration rod (a radiolucent cylinder with steel beads).

    ``bead_spacings_mm``: the gaps between consecutive beads, from bead 0 (nearest the robot's
    wrist) towards the tip. Unequal gaps make every bead identifiable from 4 visible ones
    (the default pattern was chosen so that no shifted or reversed run of 4 beads, with at
    most one missing, has gap ratios within 0.034 of another's).
    """

    diameter_mm: Positive = 10.0
    material: str = "ultem"
    bead_diameter_mm: Positive = 2.0
    bead_material: str = "steel"
    bead_spacings_mm: tuple[float, ...] = (14.0, 27.0, 16.0, 12.0, 30.0, 21.0, 24.0)
    mount_mm: Positive = 120.0          # from the wrist pitch axis to bead 0, along the rod
    tip_gap_mm: Positive = 25.0         # from the last bead to the start of the tip
    tip_length_mm: Positive = 12.0
    tip_diameter_mm: Positive = 4.0
    tip_material: str = "steel"
    bead_along_error_mm: Annotated[float, Field(ge=0, le=2.0)] = 0.1
    """Bead placement error along the rod (mm, sigma per bead); docs/error-model.md "bead
    placement". Ideal: 0."""
    bead_across_error_mm: Annotated[float, Field(ge=0, le=1.0)] = 0.05
    """Bead placement error across the rod (mm, sigma per bead and axis); docs/error-model.md.
    Ideal: 0."""
    sag: bool = True
    """Rod sag under gravity (a cantilever from the holder); docs/error-model.md "rod sag".
    Ideal: false."""
    youngs_modulus_gpa: Annotated[float, Field(ge=0.5, le=450)] = 3.0
    """Young's modulus of the rod material (GPa; ULTEM/PEI, docs/error-model.md "rod sag")."""
    density_g_cm3: Annotated[float, Field(ge=0.5, le=23)] = 1.27
    """Density of the rod material (g/cm3; ULTEM 1000); the steel tip adds 7.9 g/cm3."""

    @model_validator(mode="after")
    def _check(self):
        for name in ("material", "bead_material", "tip_material"):
            if getattr(self, name) == "air":   # (a review: an invisible rod was swept)
                raise ValueError(f"{name} = 'air': the rod's parts must show on the X-ray "
                                 "frames (the default: an ULTEM rod, steel beads and tip)")
        if len(self.bead_spacings_mm) < 3:
            raise ValueError("bead_spacings_mm: at least 3 gaps (4 beads) are needed")
        small = [float(g) for g in self.bead_spacings_mm if g <= 3 * self.bead_diameter_mm]
        if small:   # (a review: a negative gap was refused without being named)
            raise ValueError(f"bead_spacings_mm: every gap must exceed 3 bead diameters "
                             f"({3 * self.bead_diameter_mm:g} mm with bead_diameter_mm = "
                             f"{self.bead_diameter_mm:g}); got {small} mm")
        if self.bead_diameter_mm >= self.diameter_mm:
            raise ValueError("bead_diameter_mm must be smaller than the rod diameter_mm")
        length = (self.mount_mm + sum(self.bead_spacings_mm) + self.tip_gap_mm
                  + self.tip_length_mm)
        if length > MAX_ROD_LENGTH_MM:
            raise ValueError(
                f"the rod would be {length:g} mm long (mount_mm + bead_spacings_mm + tip_gap_mm "
                f"+ tip_length_mm); at most {MAX_ROD_LENGTH_MM:g} mm, a rod a robot can sweep "
                "through a C-arm (the default is 301 mm)")
        if self.diameter_mm > 50.0:
            raise ValueError(f"diameter_mm = {self.diameter_mm:g}: at most 50 mm for a rod "
                             "(the default is 10 mm)")
        clash = _alike_runs(self.bead_spacings_mm)
        if clash is not None:
            raise ValueError(
                f"bead_spacings_mm: {clash}; the gaps must be unequal so that any 4 "
                "consecutive beads in an image tell where on the rod they are, and which way "
                "it points (every two runs' gap ratios must differ by at least "
                f"{MIN_RUN_CONTRAST:g}, as the default rod's (14, 27, 16, 12, 30, 21, 24) do)")
        from testbed.materials import material

        for key in ("material", "bead_material", "tip_material"):
            try:
                material(getattr(self, key))
            except ValueError as exc:
                raise ValueError(f"{key}: {exc}") from None
        return self

    def bead_positions_mm(self) -> np.ndarray:
        """Bead centres along the rod axis, ``(n_beads,)`` mm from bead 0 (rod frame x)."""
        return np.concatenate([[0.0], np.cumsum(self.bead_spacings_mm)])

    def sag_mm(self, x_mm, gravity_across: float = 1.0) -> np.ndarray:
        """Deflection (mm) under gravity of rod-frame points at ``x_mm`` (n,), the rod held as
        a cantilever at the wrist's pitch axis (``x = -mount_mm``).

        Euler-Bernoulli beam of the rod's circular section with its own weight (uniform load)
        and the steel tip as a point load at the free end:
        ``w(s) = q s^2 (6 L^2 - 4 L s + s^2) / (24 E I) + P s^2 (3 L - s) / (6 E I)``, ``s``
        from the holder, ``L`` to the end of the tip. ``gravity_across`` is the component of
        gravity across the rod (1 for a horizontal rod, 0 for a vertical one). Zero when
        ``sag`` is off.
        """
        x = np.asarray(x_mm, dtype=np.float64)
        if not self.sag:
            return np.zeros_like(x)
        g = 9.81 * float(gravity_across)
        s_m = (x + self.mount_mm) * _M
        L = (self.mount_mm + self.bead_positions_mm()[-1] + self.tip_gap_mm
             + self.tip_length_mm) * _M
        E = self.youngs_modulus_gpa * 1e9
        r = 0.5 * self.diameter_mm * _M
        inertia = np.pi * r**4 / 4.0
        q = self.density_g_cm3 * 1e3 * np.pi * r**2 * g             # N/m
        r_tip = 0.5 * self.tip_diameter_mm * _M
        P = 7.9e3 * np.pi * r_tip**2 * self.tip_length_mm * _M * g  # N
        w = (q * s_m**2 * (6 * L**2 - 4 * L * s_m + s_m**2) / (24 * E * inertia)
             + P * s_m**2 * (3 * L - s_m) / (6 * E * inertia))
        return w / _M

    @property
    def n_beads(self) -> int:
        return len(self.bead_spacings_mm) + 1


#: the least gap between the calibration planes, as a fraction of the source-to-image
#: distance (50 mm at 1 m; the clinic scenes' planes are 0.12 apart)
MIN_PLANE_GAP = 0.05
#: the least distance of the validation row's plane from either calibration plane, as a
#: fraction of their gap (the clinic scenes' row lies half the gap off both)
MIN_VALIDATION_OFFSET = 0.2


class SweepSpec(Spec):
    """``[robot.sweep]``: the calibration sweep per C-arm view (``testbed.sweep``).

    Two planes between source and intensifier at ``near_fraction`` and ``far_fraction`` of
    the source-to-image distance, perpendicular to the beam unless ``tilt_deg`` turns them
    about the rod's direction. The rod lies in the plane along ``rod_angle_deg`` (from the
    C-arm's x axis) and is stepped ``rows_per_plane`` times across it so the beads cover
    ``coverage`` of the field. The sweep starts with a frame with the rod parked outside the
    beam (a reference for the first difference); with ``reference_frames = "each"`` the far
    plane and the validation row get one too (otherwise their first frame is compared with
    the previous plane's last row, which lies at the other side of the image). A validation
    row follows, in a plane at ``validation_fraction`` turned by ``validation_angle_deg``.

    The default planes (76 % and 94 % of the SID) lie between the patient (about the
    isocenter, 65 %) and the intensifier, so the rod clears a patient on the table; planes
    through the patient's space (e.g. 60 % / 80 %) are reported by ``testbed.workspace``.
    """

    near_fraction: Annotated[float, Field(gt=0.05, lt=0.99)] = 0.76
    far_fraction: Annotated[float, Field(gt=0.05, lt=0.99)] = 0.94
    tilt_deg: Annotated[float, Field(ge=-45, le=45)] = 0.0
    rod_angle_deg: TurnDeg = 0.0
    rows_per_plane: Annotated[int, Field(ge=3, le=50)] = 9
    coverage: Annotated[float, Field(ge=0.25, le=1.2)] = 0.9
    reference_frames: Literal["first", "each"] = "first"
    validation_fraction: Annotated[float, Field(gt=0.05, lt=0.99)] = 0.85
    validation_angle_deg: TurnDeg = 30.0
    validation_offset_mm: Annotated[float, Field(ge=-100.0, le=100.0)] = 5.0
    """The validation row's centre from the beam's axis, across it (mm): inside the field
    (a 9-inch field is 97 mm in radius at 0.85 of the SID)."""
    move_time_s: Annotated[float, Field(ge=0.04, le=60.0)] = 1.0
    """Time of one rod move and its frame (s): at least one video frame (0.04 s at 25 Hz);
    the paper's about 1 s."""
    dose_rate_mrem_per_min: Positive = 45.0

    @model_validator(mode="after")
    def _check(self):
        if not self.near_fraction < self.far_fraction:
            raise ValueError("near_fraction must be smaller than far_fraction")
        gap = self.far_fraction - self.near_fraction
        if gap < MIN_PLANE_GAP:
            raise ValueError(
                f"far_fraction - near_fraction = {gap:.4g}: the two calibration planes must "
                f"lie at least {MIN_PLANE_GAP:g} of the source-to-image distance apart (a "
                "path is the line through its points on the two planes: planes close "
                "together leave its direction undetermined)")
        off = min(abs(self.validation_fraction - self.near_fraction),
                  abs(self.validation_fraction - self.far_fraction))
        if off < MIN_VALIDATION_OFFSET * gap:
            raise ValueError(
                f"validation_fraction = {self.validation_fraction:g} lies {off:.3g} from a "
                f"calibration plane (near_fraction {self.near_fraction:g}, far_fraction "
                f"{self.far_fraction:g}): the validation row must lie at least "
                f"{MIN_VALIDATION_OFFSET:g} of the planes' gap off both, or it cannot test "
                "the paths between them")
        return self


#: the farthest end of the robot's linear slide from its base (mm, either way): a slide
#: beside an OR table (the default -900 to 300 mm)
MAX_SLIDE_MM = 5000.0


#: the range of a surgical arm's link lengths (mm) that ``[robot]`` accepts: the builtin
#: arm's are 60-550 mm; below 10 mm a length was given in metres (a review)
MIN_LINK_MM = 10.0
MAX_LINK_MM = 3000.0


class RobotSpec(Spec):
    """``[robot]``: the robot, its rod, its sweeps and its imperfections.

    Geometry (mm): the base yaw axis is the robot frame's z axis; link 1 (``link1_mm``) and
    link 2 (``link2_mm``) are horizontal at ``base_height_mm``; the slide moves the quill
    within ``slide_range_mm``; the wrist sits ``quill_mm`` below link 2 and the pitch axis
    ``pitch_drop_mm`` below the wrist. ``urdf``: ``"builtin"`` (generated from these fields)
    or a path to a URDF with the same five joint names.
    """

    urdf: str = "builtin"
    base_height_mm: float = 850.0
    link1_mm: Positive = 550.0
    link2_mm: Positive = 450.0
    slide_range_mm: tuple[float, float] = (-900.0, 300.0)
    quill_mm: Positive = 250.0
    pitch_drop_mm: Positive = 60.0
    elbow_limit_deg: Annotated[float, Field(gt=0, le=180)] = 160.0
    pitch_limit_deg: Annotated[float, Field(gt=0, le=180)] = 120.0
    encoder_noise_deg: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0005
    encoder_noise_mm: Annotated[float, Field(ge=0.0, le=5.0)] = 0.002
    kinematic_offset_mm: Annotated[float, Field(ge=0, le=5.0)] = 0.075
    """Kinematic-parameter errors, translation of each joint origin (mm, sigma per axis):
    the robot's absolute accuracy; docs/error-model.md "robot absolute accuracy".
    Ideal (today's repeatability-level robot): 0.02."""
    kinematic_offset_deg: Annotated[float, Field(ge=0, le=1.0)] = 0.0075
    """Kinematic-parameter errors, rotation of each joint origin (deg, sigma per axis);
    docs/error-model.md. Ideal: 0.002."""
    rod_mount_error_mm: Annotated[float, Field(ge=0, le=5.0)] = 0.1
    """Rod mounting error after the tip calibration, translation (mm, sigma per axis);
    docs/error-model.md "rod mounting". Ideal: 0."""
    rod_mount_error_deg: Annotated[float, Field(ge=0, le=2.0)] = 0.05
    """Rod mounting error, rotation (deg, sigma per axis); docs/error-model.md. Ideal: 0.

    The imperfections' upper bounds (kinematic offsets 5 mm / 1 deg, mounting 5 mm / 2 deg,
    bead placement 2 mm along / 1 mm across) lie 10-70 times above the clinic defaults:
    beyond them the rod's beads would leave the rod or the sweep poses the field, and the
    run would fail far from the field that caused it."""
    ik_tolerance_mm: Annotated[float, Field(ge=1e-4, le=1.0)] = 1e-3
    rod: RodSpec = RodSpec()
    sweep: SweepSpec = SweepSpec()

    @model_validator(mode="after")
    def _check(self):
        # lengths in metres where millimetres are read: the robot shrinks to a few mm and
        # the first sweep pose was "unreachable ... move the view" (a review, h93)
        for name in ("link1_mm", "link2_mm", "quill_mm"):   # (a wrist's pitch_drop_mm may
            # be a few mm: a compact wrist, h94)
            v = getattr(self, name)
            if not MIN_LINK_MM <= v <= MAX_LINK_MM:
                raise ValueError(
                    f"{name}: expected a surgical arm's length, {MIN_LINK_MM:g}-{MAX_LINK_MM:g} "
                    f"mm, got {v:g}" + (f"; given in metres? {MILLIMETRES}"
                                        if v < MIN_LINK_MM else ""))
        if not abs(self.base_height_mm) <= MAX_LINK_MM:
            raise ValueError(f"base_height_mm: expected at most {MAX_LINK_MM:g} mm either way "
                             f"(the links' height above the robot frame), got "
                             f"{self.base_height_mm:g}")
        lo, hi = self.slide_range_mm
        if not lo < hi:
            raise ValueError("slide_range_mm: expected (low, high) with low < high")
        if hi - lo < MIN_LINK_MM:
            raise ValueError(f"slide_range_mm: ({lo:g}, {hi:g}) spans {hi - lo:g} mm, less than "
                             f"{MIN_LINK_MM:g} mm; given in metres? {MILLIMETRES}")
        if max(abs(lo), abs(hi)) > MAX_SLIDE_MM:   # (+-1e9 mm was taken, a review)
            raise ValueError(f"slide_range_mm: expected ends within +-{MAX_SLIDE_MM:g} mm of "
                             f"the robot's base (a slide beside an OR table), got ({lo:g}, "
                             f"{hi:g})")
        return self

    def ideal(self) -> RobotSpec:
        """The ideal profile of docs/error-model.md: repeatability-level kinematic offsets
        (0.02 mm, 0.002 deg), no rod mounting or bead placement error, no sag; encoder noise
        kept."""
        rod = self.rod.model_copy(update=dict(bead_along_error_mm=0.0,
                                              bead_across_error_mm=0.0, sag=False))
        return self.model_copy(update=dict(kinematic_offset_mm=0.02, kinematic_offset_deg=0.002,
                                           rod_mount_error_mm=0.0, rod_mount_error_deg=0.0,
                                           rod=rod))

    def without_errors(self) -> RobotSpec:
        """The same robot with no encoder noise, kinematic offsets, rod mounting or bead errors
        and no sag (a perfect robot and rod)."""
        rod = self.rod.model_copy(update=dict(bead_along_error_mm=0.0,
                                              bead_across_error_mm=0.0, sag=False))
        return self.model_copy(update=dict(encoder_noise_deg=0.0, encoder_noise_mm=0.0,
                                           kinematic_offset_mm=0.0, kinematic_offset_deg=0.0,
                                           rod_mount_error_mm=0.0, rod_mount_error_deg=0.0,
                                           rod=rod))


# --------------------------------------------------------------------------- URDF
def _joint_origins(spec: RobotSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """Nominal (xyz mm, rpy rad) of each joint origin in its parent link, in URDF order."""
    L = [np.array(v, dtype=float) for v in (
        (0.0, 0.0, spec.base_height_mm),      # yaw, on the base
        (spec.link1_mm, 0.0, 0.0),            # elbow, at the end of link 1
        (spec.link2_mm, 0.0, 0.0),            # slide, at the end of link 2
        (0.0, 0.0, -spec.quill_mm),           # wrist, at the foot of the quill
        (0.0, 0.0, -spec.pitch_drop_mm),      # pitch, below the wrist
    )]
    return [(xyz, np.zeros(3)) for xyz in L]


def _check_urdf_text(path: str, text: str) -> None:
    """``ValueError`` in one line for a file that is no URDF at all (not XML, or its root is
    not ``<robot>``), before Bullet's parser prints its own lines about it."""
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f"robot.urdf: {path!r} is not a URDF (not XML: {exc})") from None
    if root.tag != "robot":
        raise ValueError(f"robot.urdf: {path!r} is not a URDF (its XML root is <{root.tag}>, "
                         "expected <robot>)")


def robot_urdf(spec: RobotSpec, *, offsets=None) -> str:
    """URDF text of the robot and its rod (lengths in metres, as pybullet expects).

    Parameters
    ----------
    spec : RobotSpec
    offsets : (5, 6) array or None
        Per joint, a translation (mm, 3) and a rotation (rad, roll-pitch-yaw, 3) added to the
        nominal joint origin: the true arm's kinematic errors. None: the nominal arm.
    """
    origins = _joint_origins(spec)
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=float).reshape(5, 6)
        origins = [(xyz + off[:3], rpy + off[3:]) for (xyz, rpy), off in zip(origins, offsets)]
    rod = spec.rod
    s = rod.bead_positions_mm()
    r_rod = rod.diameter_mm / 2 * _M
    rod_len = (rod.mount_mm + s[-1] + rod.tip_gap_mm) * _M
    lo, hi = spec.slide_range_mm
    el = np.radians(spec.elbow_limit_deg)
    pl = np.radians(spec.pitch_limit_deg)

    def box(size_m, xyz_m):
        return (f'<collision><origin xyz="{xyz_m[0]:.9g} {xyz_m[1]:.9g} {xyz_m[2]:.9g}"/>'
                f'<geometry><box size="{size_m[0]:.9g} {size_m[1]:.9g} {size_m[2]:.9g}"/>'
                f'</geometry></collision>')

    def inertial():
        return ('<inertial><mass value="1"/>'
                '<inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>')

    def link(name, body=""):
        return f'<link name="{name}">{inertial()}{body}</link>'

    def joint(name, kind, parent, child, xyz_mm, rpy, axis="0 0 1", limit=None):
        x = np.asarray(xyz_mm) * _M
        lim = ""
        if limit is not None:
            lim = (f'<limit lower="{limit[0]:.12g}" upper="{limit[1]:.12g}" effort="100" '
                   f'velocity="1"/>')
        return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/>'
                f'<child link="{child}"/><origin xyz="{x[0]:.12g} {x[1]:.12g} {x[2]:.12g}" '
                f'rpy="{rpy[0]:.12g} {rpy[1]:.12g} {rpy[2]:.12g}"/><axis xyz="{axis}"/>{lim}'
                f'</joint>')

    h = spec.base_height_mm * _M
    l1, l2 = spec.link1_mm * _M, spec.link2_mm * _M
    q = spec.quill_mm * _M
    parts = [
        '<?xml version="1.0"?>', '<robot name="scara5">',
        link("base", box((0.3, 0.3, max(h, 0.05)), (0, 0, h / 2))),
        link("link1", box((l1, 0.12, 0.1), (l1 / 2, 0, 0.06))),
        link("link2", box((l2, 0.1, 0.08), (l2 / 2, 0, 0.06))),
        link("quill", box((0.06, 0.06, q), (0, 0, -q / 2))),     # from link 2 to the wrist
        link("wrist", box((0.07, 0.07, spec.pitch_drop_mm * _M),
                          (0, 0, spec.pitch_drop_mm * _M / 2))),
        # the rod holder: the rod runs along +x from the pitch axis
        link("rod_mount", box((rod_len, 2 * r_rod, 2 * r_rod), (rod_len / 2, 0, 0))),
        link("bead0"),
        link("rod_end"),
    ]
    names = ["base", "link1", "link2", "quill", "wrist", "rod_mount"]
    kinds = ["revolute", "revolute", "prismatic", "revolute", "revolute"]
    axes = ["0 0 1", "0 0 1", "0 0 1", "0 0 1", "0 1 0"]
    limits = [(-np.radians(175), np.radians(175)), (-el, el), (lo * _M, hi * _M),
              (-np.pi, np.pi), (-pl, pl)]
    for i, jn in enumerate(JOINT_NAMES):
        xyz, rpy = origins[i]
        parts.append(joint(jn, kinds[i], names[i], names[i + 1], xyz, rpy, axes[i], limits[i]))
    parts.append(joint("bead0_fixed", "fixed", "rod_mount", "bead0",
                       (rod.mount_mm, 0, 0), (0, 0, 0)))
    parts.append(joint("rod_end_fixed", "fixed", "bead0", "rod_end", (s[-1], 0, 0), (0, 0, 0)))
    parts.append("</robot>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- rod bodies
@functools.lru_cache(maxsize=32)
def _cylinder_arrays(radius_mm: float, height_mm: float, sections: int):
    """Vertices and faces of ``trimesh.creation.cylinder`` (along z, centred), made once per
    size (read-only): a sweep places the same rod 20 times a view."""
    m = trimesh.creation.cylinder(radius=radius_mm, height=height_mm, sections=sections)
    v, f = np.array(m.vertices, dtype=np.float64), np.array(m.faces, dtype=np.int64)
    v.flags.writeable = f.flags.writeable = False
    return v, f


def _placed_cylinder(radius_mm: float, height_mm: float, sections: int,
                     matrix) -> trimesh.Trimesh:
    """``trimesh.creation.cylinder(...)`` moved by the rigid 4x4 ``matrix``: the same
    vertices as its ``apply_transform`` (the same ``transform_points``), without making the
    cylinder again (1.1 ms a cylinder, two a sweep frame; this 0.03 ms)."""
    from trimesh import transformations

    v, f = _cylinder_arrays(float(radius_mm), float(height_mm), int(sections))
    return trimesh.Trimesh(transformations.transform_points(v, np.asarray(matrix, dtype=float)),
                           f.copy(), process=False)


def rod_bodies(rod: RodSpec, rod2robot: RigidTransform, *, name: str = "rod",
               beads_robot=None) -> list[Body]:
    """The rod as world bodies (robot frame, mm): ULTEM cylinder, steel beads, steel tip.

    The beads are exact spheres nested in the cylinder, at ``beads_robot`` (n_beads, 3) mm
    when given (the true, misplaced and sagging beads), else on the nominal axis; the tip is a
    steel cylinder beyond the rod's far end (in air).
    """
    s = rod.bead_positions_mm()
    start = -rod.mount_mm + 10.0  # the cylinder starts just past the holder
    end = s[-1] + rod.tip_gap_mm
    # trimesh cylinders run along z, centred; lay it along rod x
    to_x = RigidTransform.from_rotvec([0.0, np.pi / 2, 0.0], [(start + end) / 2, 0.0, 0.0])
    cyl = _placed_cylinder(rod.diameter_mm / 2, end - start, 48,
                           (rod2robot @ to_x).as_matrix())
    to_tip = RigidTransform.from_rotvec([0.0, np.pi / 2, 0.0],
                                        [end + rod.tip_length_mm / 2, 0.0, 0.0])
    tip = _placed_cylinder(rod.tip_diameter_mm / 2, rod.tip_length_mm, 32,
                           (rod2robot @ to_tip).as_matrix())
    if beads_robot is None:
        beads = rod2robot.apply(np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]))
    else:
        beads = np.asarray(beads_robot, dtype=np.float64).reshape(len(s), 3)
    return [
        Body(name, rod.material, mesh=cyl),
        Body(f"{name}_beads", rod.bead_material, sphere_centers=beads,
             sphere_radii=np.full(len(s), rod.bead_diameter_mm / 2), inside=name),
        Body(f"{name}_tip", rod.tip_material, mesh=tip),
    ]


# --------------------------------------------------------------------------- the robot
class Robot:
    """A pybullet robot (DIRECT mode, its own client) holding the calibration rod.

    Use as a context manager or call :meth:`close`. Two arms live in the client: the
    *nominal* model (what the controller knows; used for inverse kinematics and for the
    reported pose) and the *true* arm (nominal plus kinematic offsets; used for the world's
    rod, the rendered beads and collision checks). Collisions between the two are disabled.

    Parameters
    ----------
    spec : RobotSpec
    rng : numpy Generator, int seed or None
        Draws the kinematic offsets now and the encoder errors at every move.
    """

    def __init__(self, spec: RobotSpec | None = None, *, rng=None):
        self.spec = spec or RobotSpec()
        self.rng = np.random.default_rng(rng)
        self.client = pybullet.connect(pybullet.DIRECT)
        self._closed = False
        sp = self.spec
        # each error source draws from a stream of its own (children of the seed; ``self.rng``
        # keeps the encoders' per-move noise), so that switching one off leaves the others'
        # draws as they were (the error budget compares configurations one source apart)
        kin_rng, mount_rng, along_rng, across_rng = self.rng.spawn(4)
        off = np.zeros((5, 6))
        off[:, :3] = kin_rng.normal(0.0, sp.kinematic_offset_mm, (5, 3))
        off[:, 3:] = np.radians(kin_rng.normal(0.0, sp.kinematic_offset_deg, (5, 3)))
        self.kinematic_offsets = off
        # the rod as mounted and as made
        self.rod_mount_error = RigidTransform(np.eye(3), np.zeros(3))
        if sp.rod_mount_error_mm > 0 or sp.rod_mount_error_deg > 0:
            t = mount_rng.normal(0.0, sp.rod_mount_error_mm, 3)
            rv = np.radians(mount_rng.normal(0.0, sp.rod_mount_error_deg, 3))
            self.rod_mount_error = RigidTransform.from_rotvec(rv, t)
        n_b = sp.rod.n_beads
        self.bead_errors_mm = np.zeros((n_b, 3))
        if sp.rod.bead_along_error_mm > 0:
            self.bead_errors_mm[:, 0] = along_rng.normal(0.0, sp.rod.bead_along_error_mm, n_b)
        if sp.rod.bead_across_error_mm > 0:
            self.bead_errors_mm[:, 1:] = across_rng.normal(0.0, sp.rod.bead_across_error_mm,
                                                           (n_b, 2))
        self._dir = tempfile.TemporaryDirectory(prefix="testbed_robot_")
        if sp.urdf == "builtin":
            nominal_text, true_text = robot_urdf(sp), robot_urdf(sp, offsets=off)
        else:
            try:
                nominal_text = true_text = open(sp.urdf).read()
            except (OSError, UnicodeDecodeError) as exc:
                raise ValueError(f"robot.urdf: cannot read {sp.urdf!r} ({exc})") from None
            _check_urdf_text(sp.urdf, nominal_text)
        self.nominal_id = self._load(nominal_text, "nominal.urdf")
        self.true_id = self._load(true_text, "true.urdf")
        self._index = self._joint_index(self.nominal_id)
        self.movable = [self._index[n] for n in JOINT_NAMES]
        self.bead0_link = self._index["bead0_fixed"]
        self.end_link = self._index["rod_end_fixed"]
        info = [pybullet.getJointInfo(self.nominal_id, j, physicsClientId=self.client)
                for j in self.movable]
        self.lower = np.array([i[8] for i in info])
        self.upper = np.array([i[9] for i in info])
        # never let the two arms collide with each other
        n = pybullet.getNumJoints(self.nominal_id, physicsClientId=self.client)
        for a in range(-1, n):
            for b in range(-1, n):
                pybullet.setCollisionFilterPair(self.nominal_id, self.true_id, a, b, 0,
                                                physicsClientId=self.client)
        self.q_commanded = np.zeros(5)   # joint values (rad, rad, m, rad, rad)
        self.q_read = np.zeros(5)
        self.q_true = np.zeros(5)
        self._set(self.nominal_id, self.q_read)
        self._set(self.true_id, self.q_true)

    # -- lifetime
    def _load(self, text, fname):
        path = os.path.join(self._dir.name, fname)
        with open(path, "w") as f:
            f.write(text)
        if self.spec.urdf == "builtin":
            return pybullet.loadURDF(path, useFixedBase=True, physicsClientId=self.client)
        # a user's URDF: Bullet prints its parser's errors and warnings (without a final
        # newline) on the C stdout and stderr, where they would spoil a --json output and a
        # one-line error; they are caught in a file, and the last one goes into the error
        import sys
        import tempfile

        sys.stdout.flush()
        sys.stderr.flush()
        saved = [os.dup(1), os.dup(2)]
        with tempfile.TemporaryFile() as log:
            try:
                os.dup2(log.fileno(), 1)
                os.dup2(log.fileno(), 2)
                return pybullet.loadURDF(path, useFixedBase=True, physicsClientId=self.client)
            except pybullet.error as exc:
                log.seek(0)
                said = [ln.strip() for ln in log.read().decode(errors="replace").splitlines()
                        if ln.strip()]
                last = f"; its parser said: {said[-1][:200]}" if said else ""
                raise ValueError(f"robot.urdf: {self.spec.urdf!r} cannot be loaded as a URDF "
                                 f"(pybullet: {exc}{last})") from None
            finally:
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
                for fd in saved:
                    os.close(fd)

    def close(self) -> None:
        if not self._closed:
            pybullet.disconnect(physicsClientId=self.client)
            self._dir.cleanup()
            self._closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass

    def _joint_index(self, body):
        n = pybullet.getNumJoints(body, physicsClientId=self.client)
        out = {}
        for j in range(n):
            out[pybullet.getJointInfo(body, j, physicsClientId=self.client)[1].decode()] = j
        missing = [k for k in (*JOINT_NAMES, "bead0_fixed", "rod_end_fixed") if k not in out]
        if missing:
            raise ValueError(f"robot.urdf: the URDF lacks the joints {missing}")
        return out

    # -- kinematics (joint units: rad, and m for the slide)
    def _set(self, body, q):
        for j, v in zip(self.movable, q):
            pybullet.resetJointState(body, j, float(v), physicsClientId=self.client)

    def _link_pose(self, body, link) -> RigidTransform:
        st = pybullet.getLinkState(body, link, computeForwardKinematics=True,
                                   physicsClientId=self.client)
        R = Rotation.from_quat(st[5]).as_matrix()
        return RigidTransform(R, np.asarray(st[4]) / _M)

    def forward(self, q, *, true: bool = False) -> RigidTransform:
        """``rod2robot`` of the nominal (or true) arm at joints ``q`` (rad, rad, mm, rad, rad).

        Leaves that arm at ``q`` (the other arm is not moved; the poses reported after a move
        are recomputed from the stored joints, so this does not change them).
        """
        q = self._to_internal(q)
        body = self.true_id if true else self.nominal_id
        self._set(body, q)
        return self._link_pose(body, self.bead0_link)

    @staticmethod
    def _to_internal(q_user):
        q = np.array(q_user, dtype=float).reshape(5)
        q[2] *= _M
        return q

    @staticmethod
    def _to_user(q):
        q = np.array(q, dtype=float).reshape(5)
        q[2] /= _M
        return q

    def _link_position_mm(self, body, link) -> np.ndarray:
        """The link frame's origin (3,) mm (what ``_link_pose(...).t`` gives, without the
        rotation: the inverse kinematics' residual needs only positions)."""
        st = pybullet.getLinkState(body, link, computeForwardKinematics=True,
                                   physicsClientId=self.client)
        return np.asarray(st[4]) / _M

    def _targets_mm(self, q):
        self._set(self.nominal_id, q)
        a = self._link_position_mm(self.nominal_id, self.bead0_link)
        b = self._link_position_mm(self.nominal_id, self.end_link)
        return a, b

    def _jacobian(self, q) -> np.ndarray:
        """``d(bead 0, last bead) / dq`` (6, 5), mm per internal joint unit, of the nominal
        arm at joints ``q`` (internal units): pybullet's analytic Jacobian of the two link
        frames' origins (their inertial frames coincide with them in our URDF)."""
        self._set(self.nominal_id, q)
        zeros = [0.0] * len(self.movable)
        rows = []
        for link in (self.bead0_link, self.end_link):
            lin, _ = pybullet.calculateJacobian(self.nominal_id, link, [0.0, 0.0, 0.0],
                                                [float(v) for v in q], zeros, zeros,
                                                physicsClientId=self.client)
            rows.append(np.asarray(lin, dtype=float) / _M)
        return np.vstack(rows)

    def _jacobian_reference(self, q, h: float = 1e-3) -> np.ndarray:
        """:meth:`_jacobian` by central differences of the forward kinematics (the reference
        in tests; pybullet's link poses are single precision, hence the large step)."""
        J = np.empty((6, 5))
        for k in range(5):
            e = np.zeros(5)
            e[k] = h
            plus = np.concatenate(self._targets_mm(q + e))
            minus = np.concatenate(self._targets_mm(q - e))
            J[:, k] = (plus - minus) / (2 * h)
        return J

    def _newton(self, q, goal_a, goal_b, *, iterations=12):
        """Gauss-Newton refinement of joints ``q`` (internal units) towards the two targets
        (analytic Jacobian); steps are clipped to the limits."""
        def resid(x):
            a, b = self._targets_mm(x)
            return np.r_[a - goal_a, b - goal_b]

        r = resid(q)
        for _ in range(iterations):
            J = self._jacobian(q)
            dq = np.linalg.lstsq(J, -r, rcond=1e-10)[0]
            q_new = np.clip(q + dq, self.lower, self.upper)
            r_new = resid(q_new)
            if np.linalg.norm(r_new) >= np.linalg.norm(r):
                break
            q, r = q_new, r_new
            if np.abs(r).max() < 1e-5:
                break
        return q

    def inverse(self, point_robot, direction_robot) -> np.ndarray:
        """Joints (rad, rad, mm, rad, rad) that put bead 0 at ``point_robot`` (3,) mm and the
        rod's axis along unit ``direction_robot`` (3,), by pybullet IK refined by Newton steps
        (Gauss-Newton on the two bead targets). Raises ``ValueError`` if the pose is unreachable,
        saying how far off the best solution stays.
        """
        p = np.asarray(point_robot, dtype=float).reshape(-1)
        d = np.asarray(direction_robot, dtype=float).reshape(-1)
        if p.shape != (3,) or d.shape != (3,) or not np.all(np.isfinite(np.r_[p, d])):
            raise ValueError("place_rod: point and direction must be finite (3,) vectors")
        nd = np.linalg.norm(d)
        if nd < 1e-9:
            raise ValueError("place_rod: direction has zero length")
        d = d / nd
        span = self.spec.rod.bead_positions_mm()[-1]
        goal_a, goal_b = p, p + span * d
        mid = 0.5 * (self.lower + self.upper)
        seeds = [self.q_commanded * np.r_[1, 1, _M, 1, 1], mid,
                 np.r_[0.7, 1.2, mid[2], 0.0, 0.0], np.r_[-0.7, -1.2, mid[2], 0.0, 0.0]]
        best, best_err = None, np.inf
        for seed in seeds:
            self._set(self.nominal_id, np.clip(seed, self.lower, self.upper))
            # pybullet's IK with two end effectors (bead 0 and the last bead); its null-space
            # options are not supported for several end effectors, so limits are applied after
            q = pybullet.calculateInverseKinematics2(
                self.nominal_id, [self.bead0_link, self.end_link],
                [list(goal_a * _M), list(goal_b * _M)],
                maxNumIterations=200, residualThreshold=1e-10, physicsClientId=self.client)
            q = np.asarray(q, dtype=float)
            q[[0, 1, 3, 4]] = (q[[0, 1, 3, 4]] + np.pi) % (2 * np.pi) - np.pi
            x = self._newton(np.clip(q, self.lower, self.upper), goal_a, goal_b)
            a, b = self._targets_mm(x)
            err = max(np.linalg.norm(a - goal_a), np.linalg.norm(b - goal_b))
            if err < best_err:
                best, best_err = x, err
            if best_err <= self.spec.ik_tolerance_mm:
                break
        if best_err > self.spec.ik_tolerance_mm:
            raise ValueError(
                f"place_rod: pose unreachable: point {np.round(p, 2).tolist()} mm, direction "
                f"{np.round(d, 4).tolist()}: the best joint solution leaves the rod "
                f"{best_err:.3f} mm off the commanded line (tolerance "
                f"{self.spec.ik_tolerance_mm} mm)")
        return self._to_user(best)

    def move_joints(self, q_user) -> None:
        """Command joints (rad, rad, mm, rad, rad); the true arm ends up with encoder error."""
        q = self._to_internal(q_user)
        if np.any(q < self.lower - 1e-12) or np.any(q > self.upper + 1e-12):
            raise ValueError(f"move_joints: joints {np.round(q_user, 4).tolist()} outside the "
                             f"limits {self.lower.tolist()} .. {self.upper.tolist()}")
        sp = self.spec
        sig = np.array([sp.encoder_noise_deg] * 5)
        sig = np.radians(sig)
        sig[2] = sp.encoder_noise_mm * _M
        self.q_commanded = q
        self.q_read = q.copy()                      # the servo stops at the commanded reading
        self.q_true = q + self.rng.normal(0.0, 1.0, 5) * sig
        self._set(self.nominal_id, self.q_read)
        self._set(self.true_id, self.q_true)

    def set_true_joints(self, q_user) -> None:
        """Put the true arm at joints (rad, rad, mm, rad, rad) without a move (no encoder
        draw): for collision checks of a planned pose. The next move overrides it."""
        self.q_true = self._to_internal(q_user)
        self._set(self.true_id, self.q_true)

    @property
    def true_joints(self) -> np.ndarray:
        """The true arm's joints (rad, rad, mm, rad, rad)."""
        return self._to_user(self.q_true)

    def place_rod(self, point_robot, direction_robot) -> np.ndarray:
        """Put bead 0 at ``point_robot`` (3,) mm with the rod along ``direction_robot`` (3,).

        Inverse kinematics on the nominal model, checked by its forward kinematics; then the
        move (encoder errors drawn). Returns the commanded joints (rad, rad, mm, rad, rad).
        Raises ``ValueError`` for an unreachable pose.
        """
        q = self.inverse(point_robot, direction_robot)
        self.move_joints(q)
        return q

    # -- poses after the last move
    @property
    def reported_rod2robot(self) -> RigidTransform:
        """The rod pose the robot reports: nominal model at the encoder readings."""
        self._set(self.nominal_id, self.q_read)
        return self._link_pose(self.nominal_id, self.bead0_link)

    @property
    def true_rod2robot(self) -> RigidTransform:
        """The rod's true pose: the true arm at the true joints, times the rod's mounting
        error (simulator only)."""
        self._set(self.true_id, self.q_true)
        return self._link_pose(self.true_id, self.bead0_link) @ self.rod_mount_error

    def true_bead_local(self, rod2robot_true: RigidTransform | None = None) -> np.ndarray:
        """True bead centres in the (true) rod frame, ``(n_beads, 3)`` mm: nominal positions
        plus placement errors plus the sag under gravity at the rod's current orientation."""
        pose = self.true_rod2robot if rod2robot_true is None else rod2robot_true
        rod = self.spec.rod
        s = rod.bead_positions_mm()
        local = np.column_stack([s, np.zeros_like(s), np.zeros_like(s)]) + self.bead_errors_mm
        if rod.sag:
            d = pose.R[:, 0]
            g = np.array([0.0, 0.0, -1.0])  # gravity, robot frame (z up)
            g_perp = g - (g @ d) * d
            mag = float(np.linalg.norm(g_perp))
            if mag > 1e-12:
                w = rod.sag_mm(s, gravity_across=mag)      # (n,) mm along g_perp
                local = local + np.outer(w, pose.R.T @ (g_perp / mag))
        return local

    def bead_positions(self, *, true: bool = False) -> np.ndarray:
        """Bead centres in the robot frame, ``(n_beads, 3)`` mm: reported (the nominal rod
        at the reported pose) or ``true`` (misplaced, sagging beads on the true rod)."""
        if true:
            pose = self.true_rod2robot
            return pose.apply(self.true_bead_local(pose))
        s = self.spec.rod.bead_positions_mm()
        local = np.column_stack([s, np.zeros_like(s), np.zeros_like(s)])
        return self.reported_rod2robot.apply(local)

    def digitize(self, point_robot) -> np.ndarray | None:
        """Where the robot reports a point that its rod's first bead touches (robot frame,
        (3,) mm), as when it locates an implanted pin; None where it cannot reach it.

        The controller moves its nominal model until the true bead stands at the point: it
        reports ``x`` with ``f(x) = p``, ``f`` the true bead (the arm's kinematic offsets,
        the rod's mounting, the bead's placement and sag) at the joints the nominal model
        puts at ``x``; to first order
        ``x = p - (f(p) - p)``, the robot's own absolute error at that configuration with
        its sign turned. The rod points from the robot's base towards the point (or, where
        that cannot be reached, along another horizontal or the vertical). Draws nothing from
        the robot's random stream; leaves the arms where the last move put them.
        """
        p = np.asarray(point_robot, dtype=np.float64).reshape(3)
        radial = np.array([p[0], p[1], 0.0])
        radial = radial / n if (n := np.linalg.norm(radial)) > 1e-9 else np.array([1.0, 0, 0])
        side = np.cross([0.0, 0.0, 1.0], radial)
        q = None
        for d in (radial, side, -side, np.array([0.0, 0.0, -1.0])):
            try:
                q = self.inverse(p, d)
                break
            except ValueError:
                continue
        if q is None:
            return None
        moved = self.q_true
        self.q_true = self._to_internal(q)              # the true arm at the touching joints
        try:
            true_p = self.bead_positions(true=True)[0]  # its placed, sagging bead 0
        finally:
            self.q_true = moved                         # the arms as the last move left them
            self._set(self.true_id, self.q_true)
            self._set(self.nominal_id, self.q_read)
        return p - (true_p - p)

    def rod_bodies(self) -> list[Body]:
        """The rod at its true pose, with its true beads, as world bodies (robot frame)."""
        pose = self.true_rod2robot
        return rod_bodies(self.spec.rod, pose, beads_robot=pose.apply(self.true_bead_local(pose)))
