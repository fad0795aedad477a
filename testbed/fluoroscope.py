"""The C-arm fluoroscope with an image intensifier: geometry, distortion, X-ray image formation.

Frames and conventions (DESIGN.md):

- ``carm`` frame of one C-arm pose: the X-ray source (focal spot) at the origin, ``+z`` the
  beam axis towards the intensifier, ``+x`` along image columns, ``+y`` along image rows
  (down the image). The intensifier's input plane is ``z_carm = sid_mm``.
- Pinhole: the undistorted pixel of a carm point ``P`` is
  ``x_u = cx + sid * P_x / (P_z * pixel_mm)``, ``y_u = cy + sid * P_y / (P_z * pixel_mm)``,
  ``(cx, cy)`` the principal point (where the beam axis meets the image). Pixel ``(x, y) =
  (col, row)``, centre of the top-left pixel at (0, 0).
- The intensifier distorts: a point whose pinhole (undistorted) pixel is ``u`` appears at the
  distorted pixel ``distort(u)`` (:class:`Distortion`): pincushion (radial,
  ``1 + k1 rho^2 + k2 rho^4`` about a centre) then S-distortion (a rotation growing with the
  radius, ``theta = theta_edge * rho^2``, plus a shift), where ``rho`` is the radius over the
  radius of the field of view. The S-distortion comes from the Earth's magnetic field acting
  on the electrons in the tube: the field component along the beam axis turns the image, the
  transverse component shifts it; both depend on the C-arm's orientation, so the distortion
  changes with the pose.
- Rendering: each distorted pixel takes the X-ray path of its undistorted point (the inverse
  of ``distort``, solved to 1e-10 px), so the image is exact, with no resampling; the
  pixel -> ray map is kept as truth (:meth:`CArm.pixel_ray_map`).
- X-ray formation: per-body path lengths by ray casting (``testbed.raycast``),
  Beer-Lambert with per-material coefficients (nested bodies count
  ``mu(body) - mu(enclosing body)``); then the imaging chain of ``testbed.detector``:
  focal-spot blur, scatter, Poisson quantum noise (with automatic brightness control),
  intensifier and video blur (an MTF), veiling glare (a wide Gaussian blur of a fraction of
  the light), vignetting, and an 8-bit video frame with a logarithmic video amplifier and
  camera noise. Outside the circular field of view the image is dark (0). Magnitudes and
  references: ``docs/error-model.md``.
- The distortion has a local, higher-order part (the intensifier's own, the same at every
  pose) and a drift between the calibration sweep and the acquisition of the patient frame
  (``make_carm(..., stage=)``).

Pose of the C-arm (``ViewSpec``), robot frame with ``+z`` up: with both rotations zero the
beam points up (source under the table) and the image axes ``x, y`` are the robot's ``x, y``.
``carm2robot.R = Ry(angular) @ Rx(orbital) @ Rz(roll)``; the source lies
``source_to_isocenter_mm`` before the isocenter along the beam.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator
from scipy.spatial.transform import Rotation

from reglib.geometry import RigidTransform
from testbed import detector
from testbed.bodies import Body
from testbed.detector import form_image
from testbed.materials import material
from testbed.raycast import (
    _CUBE_CORNERS,
    FanRays,
    RayScene,
    attenuation_weights,
    body_path_lengths,
)
from testbed.spec import NAME_MAX, Positive, RoomVec3, Spec, Vec2

__all__ = [
    "IDEAL_FLUOROSCOPE",
    "CArm",
    "Distortion",
    "FluoroscopeSpec",
    "Frame",
    "SweepRenderer",
    "ViewSpec",
    "make_carm",
    "make_distortion",
    "sinusoid_terms",
    "render",
    "render_view",
]

BONE_MATERIALS = ("cortical_bone", "cancellous_bone")


# --------------------------------------------------------------------------- scene sections
IDEAL_FLUOROSCOPE = dict(focal_spot_mm=0.0, mtf50_lp_per_mm=0.0, scatter_to_primary=0.0,
                         abc_photons_per_pixel=0.0, video_noise_u8=0.0,
                         distortion_local_mm=0.0, distortion_drift_mm=0.0)
"""Field values of the ideal profile (docs/error-model.md): the clinic sources off."""


#: a component of the magnetic field at the intensifier (uT)
_Field_uT = Annotated[float, Field(ge=-200.0, le=200.0)]


#: the most rays a frame may cast (width x height x oversample^2): 2**24, a 2048 x 2048
#: image with oversample 2 (the default frame casts 307,200)
MAX_RAYS_PER_FRAME = 2**24


class FluoroscopeSpec(Spec):
    """``[fluoroscope]``: the C-arm and its image intensifier (defaults: a 9-inch mobile C-arm).

    Geometry: ``sid_mm`` source to intensifier input plane (1000); ``fov_diameter_mm`` the
    circular field of view at the input plane (228.6 = 9 inch); ``width_px`` x ``height_px``
    the video frame (640 x 480); ``pixel_mm`` pixel spacing at the input plane (0.5: the
    field of view is a circle of 457 px diameter); ``principal_offset_px`` where the beam axis
    meets the image, from the image centre (0, 0).

    Distortion (``distortion`` switches it): ``pincushion_k1`` (0.02) and ``pincushion_k2``
    (0.005), radial gain ``1 + k1 rho^2 + k2 rho^4`` with ``rho`` the radius over the field of
    view's radius (about 6 px at the edge); ``distortion_center_px`` the centre of the
    pincushion from the principal point ((4, -3) px); ``earth_field_uT`` the Earth's field in
    the robot frame ((0, 20, -44) uT: north along +y, pointing down);
    ``s_rotation_deg_per_uT`` image rotation at the edge of the field per uT of field along
    the beam (0.03 deg/uT: about 1.3 deg, 5 px at the edge, for a vertical beam);
    ``s_shift_mm_per_uT`` image shift per uT of transverse field (0.04 mm/uT: about 1.6 px
    for a vertical beam).

    Image formation (``noise`` switches the quantum noise): ``photons_per_pixel`` detected
    quanta per pixel of the unattenuated beam (5000); ``glare_fraction`` (0.12) of the light
    spread by veiling glare with a Gaussian of ``glare_sigma_px`` (30 px); ``vignetting``
    relative brightness lost at the edge of the field (0.25, ``1 - v rho^2``);
    ``display_range`` natural-log units of intensity spread over the video range (6.0);
    ``black_u8`` and ``white_u8`` the video levels of the darkest and of the unattenuated
    intensity (8, 240): the video's offset and gain; ``oversample`` rays per pixel side (1: one
    ray through each pixel centre; 2: four rays per pixel, averaged as the detector
    integrates).

    Clinic error sources (``testbed.detector``; each default is the clinical magnitude, with
    its figure and reference in ``docs/error-model.md``; the value in brackets switches it
    off, as in ``scenes/experiment2-ideal.toml``):
    ``focal_spot_mm`` nominal focal spot (0.6 mm [0]), blurring a body at magnification ``M``
    by ``focal_spot_mm (M - 1)`` FWHM at the input plane; ``mtf50_lp_per_mm`` frequency at the
    input plane where the intensifier + video chain passes 50 % modulation (0.65 [0 = no
    blur]); ``scatter_to_primary`` scatter-to-primary ratio behind a uniform region (0.5, with
    the intensifier's grid [0]) spread by a Gaussian of ``scatter_sigma_mm`` (40 mm at the
    input plane); ``abc_photons_per_pixel`` the median detected quanta per pixel and frame that
    the automatic brightness control holds in the field (150 [0 = off: then
    ``photons_per_pixel`` quanta of the unattenuated beam]); ``video_noise_u8`` camera noise in
    grey levels (0.8 [0]); ``distortion_local_mm`` RMS of the local, higher-order distortion
    left after the pincushion and S terms (0.3 mm at the input plane [0]);
    ``distortion_drift_mm`` RMS change of the distortion between the calibration sweep and the
    acquisition (0.2 mm [0]); ``distortion_seed`` draws the intensifier's local field and, per
    view, its drift.
    """

    sid_mm: Annotated[float, Field(ge=300.0, le=2000.0)] = 1000.0
    """Source to intensifier (mm): C-arms have about 900-1200."""
    fov_diameter_mm: Annotated[float, Field(ge=100.0, le=450.0)] = 228.6
    """Field of view at the input plane (mm): intensifiers of 4 to 16 inches, 102-406 mm."""
    width_px: Annotated[int, Field(ge=8, le=4096)] = 640
    height_px: Annotated[int, Field(ge=8, le=4096)] = 480
    pixel_mm: Annotated[float, Field(ge=0.05, le=5.0)] = 0.5
    principal_offset_px: Vec2 = (0.0, 0.0)
    distortion: bool = True
    pincushion_k1: Annotated[float, Field(ge=-0.2, le=0.2)] = 0.02
    pincushion_k2: Annotated[float, Field(ge=-0.2, le=0.2)] = 0.005
    distortion_center_px: Vec2 = (4.0, -3.0)
    earth_field_uT: tuple[_Field_uT, _Field_uT, _Field_uT] = (0.0, 20.0, -44.0)
    """The magnetic field at the intensifier (uT per axis; the Earth's is 25-65 uT)."""
    s_rotation_deg_per_uT: Annotated[float, Field(ge=-1, le=1)] = 0.03
    s_shift_mm_per_uT: Annotated[float, Field(ge=-1, le=1)] = 0.04
    noise: bool = True
    photons_per_pixel: Annotated[float, Field(ge=1.0, le=1e7)] = 5000.0
    """Detected quanta per pixel of the unattenuated beam, used only without automatic
    brightness control (``abc_photons_per_pixel = 0``, the ideal profile); under it (the
    clinic default) ``abc_photons_per_pixel`` sets the quanta and this field has no effect
    (a review changed it tenfold in experiment2 and saw nothing)."""
    glare_fraction: Annotated[float, Field(ge=0, lt=1)] = 0.12
    glare_sigma_px: Annotated[float, Field(gt=0, le=500)] = 30.0
    vignetting: Annotated[float, Field(ge=0, lt=1)] = 0.25
    display_range: Annotated[float, Field(ge=1.0, le=20.0)] = 6.0
    black_u8: Annotated[int, Field(ge=0, le=255)] = 8
    white_u8: Annotated[int, Field(ge=1, le=255)] = 240
    oversample: Annotated[int, Field(ge=1, le=8)] = 1
    focal_spot_mm: Annotated[float, Field(ge=0, le=3)] = 0.6
    """Nominal focal spot (mm, FWHM); docs/error-model.md "focal spot". Ideal: 0."""
    mtf50_lp_per_mm: Annotated[float, Field(ge=0, le=20)] = 0.65
    """Intensifier + video MTF50 at the input plane (lp/mm); docs/error-model.md "MTF".
    Ideal: 0 (no blur)."""
    scatter_to_primary: Annotated[float, Field(ge=0, le=20)] = 0.5
    """Scatter-to-primary ratio (unitless); docs/error-model.md "scatter". Ideal: 0."""
    scatter_sigma_mm: Annotated[float, Field(gt=0, le=500)] = 40.0
    """Width (Gaussian sigma, mm at the input plane) of the scatter; docs/error-model.md."""
    abc_photons_per_pixel: Annotated[float, Field(ge=0, le=1e7)] = 150.0
    """Median detected quanta per pixel held by the brightness control (photons);
    docs/error-model.md "quantum noise". Ideal: 0 (off: ``photons_per_pixel`` applies)."""
    video_noise_u8: Annotated[float, Field(ge=0, le=50)] = 0.8
    """Camera noise (grey levels, sigma); docs/error-model.md "video". Ideal: 0."""
    distortion_local_mm: Annotated[float, Field(ge=0, le=5)] = 0.3
    """RMS local, higher-order distortion (mm, input plane); docs/error-model.md. Ideal: 0."""
    distortion_drift_mm: Annotated[float, Field(ge=0, le=5)] = 0.2
    """RMS distortion change between sweep and acquisition (mm, input plane);
    docs/error-model.md "drift". Ideal: 0."""
    distortion_seed: Annotated[int, Field(ge=0)] = 0
    """Seed of the intensifier's local distortion field and of each view's drift."""
    quantum_sampler: Literal["fast", "exact"] = "fast"
    """How quantum counts are drawn (``testbed.detector.quantum_noise``): "fast", the Poisson
    law's moment-matched normal approximation above 30 expected quanta (0.08 % from it in
    total variation there, less above) and exact below; "exact", numpy's Poisson sampler for
    every pixel, which gives the frames a seed gave before the fast sampler existed (the
    ideal profile keeps it, so that its regression case stays the same images)."""

    def ideal(self) -> FluoroscopeSpec:
        """The same fluoroscope with the clinic error sources of issue 11 off (the ideal
        profile of docs/error-model.md: no focal-spot, MTF or scatter blur, no brightness
        control or camera noise, no local distortion or drift); other fields kept."""
        return self.model_copy(update=IDEAL_FLUOROSCOPE)

    @model_validator(mode="after")
    def _check(self):
        if self.white_u8 <= self.black_u8:
            raise ValueError(f"white_u8 ({self.white_u8}) must exceed black_u8 ({self.black_u8})")
        radius_px = 0.5 * self.fov_diameter_mm / self.pixel_mm
        if radius_px < 4:
            raise ValueError(
                f"fov_diameter_mm / pixel_mm = {2 * radius_px:.1f} px: the field of view must "
                "span at least 8 pixels"
            )
        rays = self.width_px * self.height_px * self.oversample ** 2
        if rays > MAX_RAYS_PER_FRAME:
            raise ValueError(
                f"width_px x height_px x oversample^2 = {self.width_px} x {self.height_px} x "
                f"{self.oversample}^2 = {rays:,} rays per frame; at most {MAX_RAYS_PER_FRAME:,} "
                "(a 2048 x 2048 image with oversample 2): a frame would take minutes and a "
                "sweep hours")
        size = max(self.width_px, self.height_px)
        for name in ("principal_offset_px", "distortion_center_px"):
            v = getattr(self, name)
            if max(abs(v[0]), abs(v[1])) > size:
                raise ValueError(f"{name} = {tuple(v)}: at most the image's size ({size} px) "
                                 "from the image centre")
        return self


class ViewSpec(Spec):
    """``[[views]]``: one C-arm pose.

    ``name``; ``region`` the part of the femur it images ("proximal" or "distal");
    ``isocenter_mm`` the point on the beam axis the C-arm turns about (robot frame, mm);
    ``orbital_deg`` rotation about the robot x axis, ``angular_deg`` about the robot y axis,
    ``roll_deg`` of the whole C-arm about its beam (source, intensifier and the C's arc turn
    together, and the image with them: a roll moves the arc in the workspace check, and the
    intensifier's orientation in the earth's field; ``c_side_deg`` moves the arc alone; see
    the module docstring for the order);
    ``source_to_isocenter_mm`` (650) distance from the source to the isocenter, less than the
    fluoroscope's ``sid_mm``; ``c_side_deg`` where the C's arc stands off the beam, as an
    angle in the image plane from the carm's ``+x`` towards ``+y`` (0, the default: ``+x``,
    which with zero rotations is the robot's ``+x``, the side of the table opposite the
    robot: a mobile C-arm rolled in from the side of the table; 90 or 270 put the C along
    the table, where it meets the table top unless the view lies beyond the table's end, and
    the workspace check refuses it; 180 puts it on the robot's side). It changes only what
    the workspace check sees.
    """

    name: str = "view"
    region: Literal["proximal", "distal"] = "proximal"
    isocenter_mm: RoomVec3 = (0.0, 0.0, 0.0)

    @field_validator("name")
    @classmethod
    def _a_file_name(cls, v: str) -> str:
        # a view's name names dataset entries and files (xray_<name>.png): nothing a file
        # system or a dataset key would change
        if not (v and (v[0].isascii() and (v[0].isalnum() or v[0] == "_"))
                and all(c.isascii() and (c.isalnum() or c in "_.-") for c in v)):
            raise ValueError("a view name is ASCII letters, digits, '_', '.' or '-', "
                             "starting with a letter, a digit or '_'")
        if len(v) > NAME_MAX:  # file names such as a dataset's images/sweep_<name>/
            raise ValueError(f"a view name has at most {NAME_MAX} characters, got {len(v)}")
        return v
    orbital_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0
    angular_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0
    roll_deg: Annotated[float, Field(ge=-180, le=180)] = 0.0
    source_to_isocenter_mm: Positive = 650.0
    c_side_deg: Annotated[float, Field(ge=-360, le=360)] = 0.0


# --------------------------------------------------------------------------- distortion
@dataclass(frozen=True)
class Distortion:
    """The intensifier's distortion at one pose: undistorted pixel -> distorted pixel.

    ``center_px`` (2,) pincushion centre (x, y) in px; ``radius_px`` the radius of the field
    of view (px) that normalises ``rho``; ``k1, k2`` pincushion coefficients;
    ``rotation_edge_rad`` the S-rotation at ``rho = 1``; ``shift_px`` (2,) the shift.

    ``distort(u) = c + Rot(theta_edge * rho^2) (u - c) (1 + k1 rho^2 + k2 rho^4) + shift
    + sum_k a_k sin(2 pi f_k . (u - c) + phi_k)``, ``rho = |u - c| / radius_px``.

    ``local``: the local, higher-order part (docs/error-model.md, "local distortion" and
    "drift"): terms ``(a_x px, a_y px, f_x 1/px, f_y 1/px, phi rad)``, plane waves of the
    displacement (:func:`sinusoid_terms`); empty for none.
    """

    center_px: tuple[float, float]
    radius_px: float
    k1: float
    k2: float
    rotation_edge_rad: float
    shift_px: tuple[float, float]
    local: tuple[tuple[float, float, float, float, float], ...] = ()

    def _local_arrays(self):
        t = np.asarray(self.local, dtype=np.float64).reshape(-1, 5)
        return t[:, :2], t[:, 2:4], t[:, 4]

    def local_displacement(self, xy_px) -> np.ndarray:
        """The local part of the displacement ``(N, 2)`` px at undistorted pixels ``(N, 2)``."""
        u = np.asarray(xy_px, dtype=np.float64)
        if not self.local:
            return np.zeros_like(u)
        a, f, ph = self._local_arrays()
        arg = 2.0 * np.pi * ((u - np.asarray(self.center_px)) @ f.T) + ph  # (..., K)
        return np.sin(arg) @ a

    def distort(self, xy_px) -> np.ndarray:
        """Distorted pixels ``(N, 2)`` of undistorted (pinhole) pixels ``(N, 2)`` (x, y)."""
        u = np.asarray(xy_px, dtype=np.float64)
        c = np.asarray(self.center_px)
        p = u - c
        rho2 = np.sum(p * p, axis=-1, keepdims=True) / self.radius_px**2
        p = p * (1.0 + self.k1 * rho2 + self.k2 * rho2 * rho2)
        th = self.rotation_edge_rad * rho2[..., 0]
        cs, sn = np.cos(th), np.sin(th)
        q = np.stack([cs * p[..., 0] - sn * p[..., 1], sn * p[..., 0] + cs * p[..., 1]], -1)
        out = c + q + np.asarray(self.shift_px)
        if self.local:
            out = out + self.local_displacement(u)
        return out

    def jacobian(self, xy_px) -> np.ndarray:
        """``d distort / d u`` at undistorted pixels ``(N, 2)``: ``(N, 2, 2)`` (analytic)."""
        u = np.asarray(xy_px, dtype=np.float64)
        p = u - np.asarray(self.center_px)
        r0 = self.radius_px**2
        rho2 = np.sum(p * p, axis=-1) / r0
        g = 1.0 + self.k1 * rho2 + self.k2 * rho2 * rho2
        th = self.rotation_edge_rad * rho2
        q = p * g[..., None]
        jq = np.stack([-q[..., 1], q[..., 0]], -1)  # d Rot(theta) q / d theta, before Rot
        dg = (2.0 / r0) * (self.k1 + 2.0 * self.k2 * rho2)
        dth = (2.0 / r0) * self.rotation_edge_rad
        inner = (g[..., None, None] * np.eye(2)
                 + dg[..., None, None] * p[..., :, None] * p[..., None, :]
                 + dth * jq[..., :, None] * p[..., None, :])
        cs, sn = np.cos(th), np.sin(th)
        rot = np.stack([np.stack([cs, -sn], -1), np.stack([sn, cs], -1)], -2)
        J = rot @ inner
        if self.local:
            a, f, ph = self._local_arrays()
            arg = 2.0 * np.pi * (p @ f.T) + ph  # (..., K)
            # sum_k cos(arg_k) a_k (2 pi f_k)^T as one matrix product over the K terms
            m = (a[:, :, None] * (2.0 * np.pi * f)[:, None, :]).reshape(len(a), 4)
            J = J + (np.cos(arg) @ m).reshape(J.shape)
        return J

    def curvature_bound(self, radius_px: float) -> float:
        """An upper bound (1/px) of ``|D2 distort(u)[v, v]|`` over unit ``v`` and every
        undistorted ``u`` within ``radius_px`` of the centre: a Newton step ``s`` then leaves
        a residual of at most ``bound / 2 * |s|^2`` (Taylor's theorem), anywhere in that disc.

        With ``t = |p|^2 / R^2`` (``p = u - c``, ``R = radius_px`` of the field), ``g = 1 + k1 t
        + k2 t^2``, ``theta = rot t`` and ``h = g p``, ``D2 (Rot(theta) h) = Rot''(theta) h
        Dtheta^2 + Rot'(theta) (h D2theta + 2 Dh Dtheta) + Rot(theta) D2h``, each rotation of
        norm 1, bounded term by term with ``|g| <= 1 + |k1| T + |k2| T^2``, ``|g'| <= |k1| +
        2 |k2| T`` (``T`` the largest ``t``), ``|Dh| <= |g| + 2 |g'| T``, ``|D2h| <= 6 |g'| P /
        R^2 + 8 |k2| P^3 / R^4``, ``|Dtheta| <= 2 |rot| P / R^2``, ``|D2theta| <= 2 |rot| /
        R^2`` (``P = radius_px``); each local term adds ``|a_k| (2 pi |f_k|)^2``.
        """
        P = float(radius_px)
        R2 = float(self.radius_px) ** 2
        T = P * P / R2
        k1, k2, rot = abs(self.k1), abs(self.k2), abs(self.rotation_edge_rad)
        g = 1.0 + k1 * T + k2 * T * T
        dg = k1 + 2.0 * k2 * T
        h, dh = g * P, g + 2.0 * dg * T
        d2h = 6.0 * dg * P / R2 + 8.0 * k2 * P**3 / R2**2
        dth, d2th = 2.0 * rot * P / R2, 2.0 * rot / R2
        bound = h * dth * dth + h * d2th + 2.0 * dh * dth + d2h
        if self.local:
            a, f, _ = self._local_arrays()
            bound += float(np.sum(np.linalg.norm(a, axis=1)
                                  * (2.0 * np.pi * np.linalg.norm(f, axis=1)) ** 2))
        return bound

    def displacement_bound(self, center_xy, radius_px: float) -> float:
        """An upper bound (px) of ``|distort(u) - u|`` over undistorted ``u`` within
        ``radius_px`` of ``center_xy`` (x, y) px.

        With ``p = u - c`` (``|p| <= P``, ``P`` the disc's reach from the centre ``c``),
        ``distort(u) - u = (Rot(theta) g - I) p + shift + sum_k a_k sin(...)`` and
        ``|Rot(theta) g - I| <= |g| |theta| + |g - 1|``, ``|g - 1| <= |k1| T + |k2| T^2``,
        ``|theta| <= |rot| T`` (``T = P^2 / R^2``).
        """
        P = float(np.hypot(center_xy[0] - self.center_px[0],
                           center_xy[1] - self.center_px[1])) + float(radius_px)
        T = P * P / float(self.radius_px) ** 2
        g1 = abs(self.k1) * T + abs(self.k2) * T * T          # bounds |g - 1|
        bound = ((1.0 + g1) * abs(self.rotation_edge_rad) * T + g1) * P
        bound += float(np.hypot(*self.shift_px))
        if self.local:
            bound += float(np.sum(np.linalg.norm(self._local_arrays()[0], axis=1)))
        return bound

    def undistort(self, xy_px, *, tol_px: float = 1e-10, max_iter: int = 50,
                  reference: bool = False, failed: str = "raise") -> np.ndarray:
        """Undistorted pixels ``(N, 2)`` of distorted pixels ``(N, 2)``: ``distort``'s inverse.

        Newton iterations with the analytic Jacobian; raises ``ValueError`` if they do not
        converge to ``tol_px`` (the distortion must stay one-to-one there), or with
        ``failed="nan"`` gives those points NaN (pixels beyond the field, where the
        polynomial may fold). Compiled per point (:mod:`testbed._distortion_numba`);
        ``reference=True`` runs the same iterations in numpy (compared in tests).
        """
        d = np.asarray(xy_px, dtype=np.float64)
        shape = d.shape
        d = d.reshape(-1, 2)
        if not reference:
            from testbed._distortion_numba import undistort

            a, f, ph = self._local_arrays()
            # the disc where a step may be accepted by the curvature bound (beyond it, the
            # residual is evaluated): the inputs' reach and room for the displacement
            reach = 1.25 * float(np.max(np.hypot(d[:, 0] - self.center_px[0],
                                                 d[:, 1] - self.center_px[1]),
                                        initial=0.0)) + 20.0
            u, ok = undistort(np.ascontiguousarray(d), float(self.center_px[0]),
                              float(self.center_px[1]), float(self.radius_px), float(self.k1),
                              float(self.k2), float(self.rotation_edge_rad),
                              float(self.shift_px[0]), float(self.shift_px[1]),
                              np.ascontiguousarray(a), np.ascontiguousarray(f),
                              np.ascontiguousarray(ph), float(tol_px), int(max_iter),
                              0.5 * self.curvature_bound(reach), reach)
            if ok.all():
                return u.reshape(shape)
            if failed == "nan":
                u[~ok] = np.nan
                return u.reshape(shape)
            raise ValueError(_not_invertible(tol_px, max_iter, d[~ok]))
        # start from the displacement evaluated at the distorted point (first order), and
        # iterate only the points not yet within tol_px (most converge in 2 steps)
        u = 2.0 * d - self.distort(d)
        active = np.arange(len(d))
        for _ in range(max_iter):
            r = self.distort(u[active]) - d[active]
            done = np.max(np.abs(r), axis=1) < tol_px
            active, r = active[~done], r[~done]
            if not len(active):
                return u.reshape(shape)
            J = self.jacobian(u[active])
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            du0 = (J[..., 1, 1] * r[..., 0] - J[..., 0, 1] * r[..., 1]) / det
            du1 = (-J[..., 1, 0] * r[..., 0] + J[..., 0, 0] * r[..., 1]) / det
            u[active] -= np.stack([du0, du1], -1)
        if failed == "nan":
            u[active] = np.nan
            return u.reshape(shape)
        raise ValueError(_not_invertible(tol_px, max_iter, d[active]))


def _not_invertible(tol_px: float, max_iter: int, where_px: np.ndarray) -> str:
    """The message of a distortion that :meth:`Distortion.undistort` cannot invert, naming
    the scene fields that make it."""
    return (f"fluoroscope: the intensifier's distortion folds the image over itself, or nearly "
            f"(it cannot be inverted to {tol_px} px in {max_iter} iterations at "
            f"{len(where_px)} pixel(s), e.g. {np.round(where_px[0], 1).tolist()} px): weaken "
            "pincushion_k1 / pincushion_k2 (|k| up to about 0.05; negative values fold the "
            "edge), distortion_local_mm, or the S-distortion (s_rotation_deg_per_uT, "
            "s_shift_mm_per_uT, earth_field_uT)")


def sinusoid_terms(rms_px: float, radius_px: float, rng, *, n_terms: int = 12,
                   periods: tuple[float, float] = (0.25, 0.8)) -> tuple:
    """Random plane-wave terms of a smooth displacement field for :class:`Distortion`.

    ``n_terms`` waves with uniform random directions, periods uniform in ``periods`` (in units
    of ``radius_px``), Gaussian amplitude vectors and uniform phases, scaled so that the RMS
    displacement over the plane (expected over phases) is ``rms_px``:
    ``sqrt(sum_k |a_k|^2 / 2) = rms_px``. Returns a tuple of ``(a_x, a_y, f_x, f_y, phi)``;
    empty when ``rms_px == 0``.
    """
    if rms_px <= 0:
        return ()
    rng = np.random.default_rng(rng)
    ang = rng.uniform(0.0, 2.0 * np.pi, n_terms)
    per = rng.uniform(periods[0], periods[1], n_terms) * radius_px
    f = np.stack([np.cos(ang), np.sin(ang)], 1) / per[:, None]
    a = rng.normal(0.0, 1.0, (n_terms, 2))
    a *= rms_px / math.sqrt(np.sum(a * a) / 2.0)
    ph = rng.uniform(0.0, 2.0 * np.pi, n_terms)
    return tuple(tuple(float(v) for v in row) for row in np.column_stack([a, f, ph]))


def _view_key(view_name: str) -> int:
    return zlib.crc32(view_name.encode("utf-8"))


def make_distortion(fluoro: FluoroscopeSpec, carm2robot: RigidTransform,
                    principal_px, *, view_name: str = "view",
                    stage: Literal["calibration", "acquisition"] = "acquisition") -> Distortion:
    """The distortion of the intensifier at the pose ``carm2robot`` (see FluoroscopeSpec).

    The local field (``distortion_local_mm``) belongs to the intensifier: drawn from
    ``distortion_seed`` alone, the same at every pose. The drift (``distortion_drift_mm``) is
    what changed between the calibration sweep and the acquisition of the patient frame: drawn
    from ``distortion_seed`` and ``view_name``, added only at ``stage="acquisition"``.
    """
    if stage not in ("calibration", "acquisition"):
        raise ValueError(f"stage must be 'calibration' or 'acquisition', got {stage!r}")
    b_carm = carm2robot.R.T @ np.asarray(fluoro.earth_field_uT, dtype=np.float64)
    # electrons travel along +z; the Lorentz force v x B deflects them along z x B
    shift_mm = fluoro.s_shift_mm_per_uT * np.array([-b_carm[1], b_carm[0]])
    radius_px = 0.5 * fluoro.fov_diameter_mm / fluoro.pixel_mm
    local = sinusoid_terms(fluoro.distortion_local_mm / fluoro.pixel_mm, radius_px,
                           np.random.default_rng([fluoro.distortion_seed, 1]))
    if stage == "acquisition":
        local = local + sinusoid_terms(
            fluoro.distortion_drift_mm / fluoro.pixel_mm, radius_px,
            np.random.default_rng([fluoro.distortion_seed, 2, _view_key(view_name)]),
            n_terms=8, periods=(0.8, 3.0))
    return Distortion(
        center_px=tuple(np.asarray(principal_px) + np.asarray(fluoro.distortion_center_px)),
        radius_px=radius_px,
        k1=fluoro.pincushion_k1,
        k2=fluoro.pincushion_k2,
        rotation_edge_rad=math.radians(fluoro.s_rotation_deg_per_uT * b_carm[2]),
        shift_px=tuple(shift_mm / fluoro.pixel_mm),
        local=local,
    )


# --------------------------------------------------------------------------- C-arm
@dataclass(frozen=True)
class CArm:
    """One C-arm pose with its true projection (distortion included).

    ``carm2robot``: the carm frame (source at the origin, +z the beam) in the robot frame;
    ``sid_mm``: the input plane is ``z_carm = sid_mm``; ``pixel_mm``: pixel spacing at the
    input plane; ``principal_px`` (x, y): where the beam axis meets the image;
    ``fov_radius_mm``: radius of the circular field of view at the input plane;
    ``distortion``: the intensifier's distortion, or None (an ideal pinhole camera);
    ``c_side_deg``: the side of the beam the C's arc stands on (deg in the image plane from
    the carm's ``+x`` towards ``+y``; used by the workspace check only).
    """

    carm2robot: RigidTransform
    sid_mm: float
    width_px: int
    height_px: int
    pixel_mm: float = 0.5
    principal_px: tuple[float, float] = (319.5, 239.5)
    fov_radius_mm: float = 114.3
    distortion: Distortion | None = None
    name: str = "view"
    c_side_deg: float = 0.0
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def source_robot(self) -> np.ndarray:
        """The X-ray source (focal spot), robot frame, (3,) mm."""
        return np.array(self.carm2robot.t)

    @property
    def axis_robot(self) -> np.ndarray:
        """The beam axis (unit, from source to intensifier), robot frame, (3,)."""
        return np.array(self.carm2robot.R[:, 2])

    def undistorted(self) -> CArm:
        """The same pose seen by an ideal pinhole camera (no distortion)."""
        return replace(self, distortion=None, _cache={})

    # pinhole
    def _plane_points(self, xy_u) -> np.ndarray:
        """Carm-frame points (N, 3) mm on the input plane of undistorted pixels (N, 2)."""
        xy_u = np.asarray(xy_u, dtype=np.float64)
        p = np.empty(xy_u.shape[:-1] + (3,))
        p[..., 0] = (xy_u[..., 0] - self.principal_px[0]) * self.pixel_mm
        p[..., 1] = (xy_u[..., 1] - self.principal_px[1]) * self.pixel_mm
        p[..., 2] = self.sid_mm
        return p

    def undistort_px(self, xy_px) -> np.ndarray:
        """Undistorted (pinhole) pixels (N, 2) of distorted pixels (N, 2)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        return xy if self.distortion is None else self.distortion.undistort(xy)

    def distort_px(self, xy_u) -> np.ndarray:
        """Distorted pixels (N, 2) of undistorted (pinhole) pixels (N, 2)."""
        xy = np.asarray(xy_u, dtype=np.float64)
        return xy if self.distortion is None else self.distortion.distort(xy)

    def true_rays(self, xy_px) -> tuple[np.ndarray, np.ndarray]:
        """The true X-ray paths reaching distorted pixels ``xy_px`` (N, 2) (x, y) px.

        Returns ``origins (N, 3)`` (the source, mm) and unit ``directions (N, 3)``, both in
        the robot frame.
        """
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy_px: expected an (N, 2) array of pixels, got {xy.shape}")
        return self.rays_of_undistorted(self.undistort_px(xy))

    def rays_of_undistorted(self, xy_u) -> tuple[np.ndarray, np.ndarray]:
        """The X-ray paths through undistorted (pinhole) pixels ``xy_u`` (N, 2): origins
        (the source) and unit directions (N, 3), robot frame."""
        p = self._plane_points(xy_u)
        d = p / np.linalg.norm(p, axis=1, keepdims=True)
        d = self.carm2robot.apply_vectors(d)
        return np.broadcast_to(self.source_robot, d.shape).copy(), d

    def project(self, points_robot) -> np.ndarray:
        """Distorted pixels ``(N, 2)`` (x, y) where robot-frame points ``(N, 3)`` mm appear.

        The exact inverse of :meth:`true_rays`. Points at or behind the source raise
        ``ValueError``.
        """
        return self.distort_px(self.project_undistorted(points_robot))

    def project_undistorted(self, points_robot) -> np.ndarray:
        """Undistorted (pinhole) pixels ``(N, 2)`` of robot-frame points ``(N, 3)`` mm: the
        central projection from the source onto the input plane. Points at or behind the
        source raise ``ValueError``."""
        p = np.asarray(points_robot, dtype=np.float64).reshape(-1, 3)
        q = self.carm2robot.inverse().apply(p)
        if np.any(q[:, 2] <= 1e-9):
            raise ValueError(f"view {self.name!r}: points at or behind the X-ray source")
        return np.stack([
            self.principal_px[0] + self.sid_mm * q[:, 0] / (q[:, 2] * self.pixel_mm),
            self.principal_px[1] + self.sid_mm * q[:, 1] / (q[:, 2] * self.pixel_mm),
        ], 1)

    def pixel_grid(self) -> np.ndarray:
        """Pixel centres ``(H, W, 2)`` (x, y)."""
        x, y = np.meshgrid(np.arange(self.width_px, dtype=np.float64),
                           np.arange(self.height_px, dtype=np.float64))
        return np.stack([x, y], -1)

    def _undistorted_grid(self) -> np.ndarray:
        """Undistorted pixel ``(H, W, 2)`` of every pixel centre (computed once per C-arm;
        where :meth:`_field` has inverted a pixel already, its value is taken, so that the
        truth and the rendered rays agree to the bit). Pixels beyond the field's reach
        (never imaged) where the distortion cannot be inverted are NaN: with 2 mm pixels the
        frame reaches far past the intensifier, where its polynomial folds, and
        ``testbed generate`` refused the scene blaming the distortion (a review, h93)."""
        if "undist" not in self._cache:
            g = self.pixel_grid()
            if "candidates" not in self._cache and self.distortion is not None:
                self._field()                   # inverts the pixels that can be in the field
            if "candidates" in self._cache:
                cand, uv_c = self._cache["candidates"]
                full = np.empty_like(g)
                full[cand] = uv_c
                if self.distortion is not None:
                    full[~cand] = self.distortion.undistort(g[~cand], failed="nan")
                else:
                    full[~cand] = g[~cand]
            else:
                full = self.undistort_px(g.reshape(-1, 2)).reshape(g.shape)
            self._cache["undist"] = full
        return self._cache["undist"]

    def _field(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The field of view without inverting the distortion at pixels that cannot be in
        it: ``(fov (H, W) bool, undistorted pixels of the field (M, 2) row-major, rho (H, W)
        exact in the field and inf beyond the pixels examined)``, read-only, kept.

        A pixel can be in the field only within the field's radius plus the distortion's
        largest displacement there (:meth:`Distortion.displacement_bound`) of the principal
        point; only those are inverted (57 % of a 640 x 480 frame for experiment2)."""
        if "field" not in self._cache:
            if "undist" in self._cache:
                rho = self.rho_map()
                fov = rho <= 1.0
                uv = self._cache["undist"][fov]
            else:
                reach = self.fov_radius_mm / self.pixel_mm + 1.0
                if self.distortion is not None:
                    reach += self.distortion.displacement_bound(self.principal_px,
                                                                reach - 1.0)
                cand, pts = self._candidate_pixels(reach)
                uv_c = self.undistort_px(pts)
                self._cache["candidates"] = (cand, uv_c)
                rho_c = self._rho_of_undistorted(uv_c)
                inside = rho_c <= 1.0
                fov = np.zeros(cand.shape, dtype=bool)
                fov[cand] = inside
                rho = np.full(cand.shape, np.inf)
                rho[cand] = rho_c
                uv = np.compress(inside, uv_c, axis=0)     # uv_c[inside], 10x faster
            for a in (fov, uv, rho):
                a.flags.writeable = False
            self._cache["field"] = (fov, uv, rho)
        return self._cache["field"]

    def _candidate_pixels(self, reach: float, *, reference: bool = False
                          ) -> tuple[np.ndarray, np.ndarray]:
        """The pixels whose centre lies within ``reach`` px of the principal point:
        ``(mask (H, W) bool, their centres (M, 2) (x, y) row-major)``. The distances are
        those of :meth:`pixel_grid`'s centres (the same differences, broadcast from a row
        and a column) and the centres are made from the mask's indices, without the
        (H, W, 2) grid (1 ms against 9 ms for 640 x 480 px; 8 fields a run);
        ``reference=True`` takes them from :meth:`pixel_grid` (compared in tests)."""
        if reference:
            g = self.pixel_grid()
            cand = np.hypot(g[..., 0] - self.principal_px[0],
                            g[..., 1] - self.principal_px[1]) <= reach
            return cand, g[cand]
        x = np.arange(self.width_px, dtype=np.float64) - self.principal_px[0]
        y = np.arange(self.height_px, dtype=np.float64) - self.principal_px[1]
        cand = np.hypot(x[None, :], y[:, None]) <= reach
        rows, cols = np.nonzero(cand)
        pts = np.empty((len(rows), 2))
        pts[:, 0] = cols
        pts[:, 1] = rows
        return cand, pts

    def pixel_ray_map(self) -> tuple[np.ndarray, np.ndarray]:
        """The truth: the X-ray path of every pixel, ``origins (H, W, 3)`` and unit
        ``directions (H, W, 3)`` in the robot frame (mm)."""
        o, d = self._ray_map()
        return o.copy(), d.copy()

    def _ray_map(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`pixel_ray_map`'s arrays as cached (read-only; origins a broadcast view)."""
        if "rays" not in self._cache:
            p = self._plane_points(self._undistorted_grid().reshape(-1, 2))
            d = p / np.linalg.norm(p, axis=1, keepdims=True)
            d = np.einsum("ij,nj->ni", self.carm2robot.R, d)
            shape = (self.height_px, self.width_px, 3)
            o = np.broadcast_to(self.source_robot, d.shape)
            d = d.reshape(shape)
            d.flags.writeable = False
            self._cache["rays"] = (o.reshape(shape), d)
        return self._cache["rays"]

    def fov_rho(self, xy_px) -> np.ndarray:
        """Radius on the input plane over the field-of-view radius, for distorted pixels
        ``(N, 2)``; the field of view is ``rho <= 1``. Returns ``(N,)``."""
        return self._rho_of_undistorted(self.undistort_px(np.asarray(xy_px, dtype=np.float64)))

    def point_rho(self, points_robot) -> np.ndarray:
        """:meth:`fov_rho` of robot-frame points ``(N, 3)`` mm as seen from the source (the
        central projection, without the distortion's round trip). Returns ``(N,)``."""
        return self._rho_of_undistorted(self.project_undistorted(points_robot))

    def _rho_of_undistorted(self, xy_u) -> np.ndarray:
        p = self._plane_points(xy_u)
        return np.hypot(p[..., 0], p[..., 1]) / self.fov_radius_mm

    def rho_map(self) -> np.ndarray:
        """``fov_rho`` of every pixel centre, ``(H, W)``."""
        if "rho" not in self._cache:
            self._cache["rho"] = self._rho_of_undistorted(self._undistorted_grid())
        return self._cache["rho"]

    def fov_mask(self) -> np.ndarray:
        """Pixels inside the circular field of view, ``(H, W)`` bool (``rho_map() <= 1``)."""
        return self._field()[0].copy()

    def displacement_field(self) -> np.ndarray:
        """Distorted minus undistorted position ``(H, W, 2)`` px at every distorted pixel."""
        return self.pixel_grid() - self._undistorted_grid()


def view_pose(view: ViewSpec) -> RigidTransform:
    """``carm2robot`` of a view (see the module docstring)."""
    R = (Rotation.from_euler("y", view.angular_deg, degrees=True)
         * Rotation.from_euler("x", view.orbital_deg, degrees=True)
         * Rotation.from_euler("z", view.roll_deg, degrees=True)).as_matrix()
    source = np.asarray(view.isocenter_mm) - view.source_to_isocenter_mm * R[:, 2]
    return RigidTransform(R, source)


def make_carm(fluoro: FluoroscopeSpec, view: ViewSpec, *, distortion: bool | None = None,
              view_index: int | None = None,
              stage: Literal["calibration", "acquisition"] = "acquisition") -> CArm:
    """The C-arm of ``view`` with the intensifier of ``fluoro``.

    ``distortion``: None follows ``fluoro.distortion``; True/False forces it.
    ``stage``: ``"calibration"`` for the sweep frames, ``"acquisition"`` (default) for the
    patient frame and its true rays; they differ by the drift ``distortion_drift_mm``
    (:func:`make_distortion`).
    Raises ``ValueError`` naming the field if the isocenter lies beyond the input plane.
    """
    where = f"views[{view_index}]" if view_index is not None else f"view {view.name!r}"
    if view.source_to_isocenter_mm >= fluoro.sid_mm:
        raise ValueError(
            f"{where}.source_to_isocenter_mm = {view.source_to_isocenter_mm} mm: must be less "
            f"than fluoroscope.sid_mm = {fluoro.sid_mm} mm (the isocenter lies between the "
            "source and the intensifier)"
        )
    carm2robot = view_pose(view)
    principal = (
        (fluoro.width_px - 1) / 2.0 + fluoro.principal_offset_px[0],
        (fluoro.height_px - 1) / 2.0 + fluoro.principal_offset_px[1],
    )
    use = fluoro.distortion if distortion is None else bool(distortion)
    dist = (make_distortion(fluoro, carm2robot, principal, view_name=view.name, stage=stage)
            if use else None)
    return CArm(
        carm2robot=carm2robot,
        sid_mm=float(fluoro.sid_mm),
        width_px=int(fluoro.width_px),
        height_px=int(fluoro.height_px),
        pixel_mm=float(fluoro.pixel_mm),
        principal_px=principal,
        fov_radius_mm=0.5 * float(fluoro.fov_diameter_mm),
        distortion=dist,
        name=view.name,
        c_side_deg=float(view.c_side_deg),
    )


# --------------------------------------------------------------------------- image formation
class PathImages(Mapping):
    """Body name -> (H, W) float32 path length (mm) through that body, made on first access
    from the field's ``(M, B)`` lengths (most frames are looked at for one or two bodies)."""

    def __init__(self, names: list[str], lengths: np.ndarray, fov: np.ndarray):
        self._index = {n: j for j, n in enumerate(names)}
        self._lengths, self._fov, self._images = lengths, fov, {}

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._images:
            img = np.zeros(self._fov.shape, dtype=np.float32)
            img[self._fov] = self._lengths[:, self._index[name]]
            self._images[name] = img
        return self._images[name]

    def __iter__(self):
        return iter(self._index)

    def __len__(self) -> int:
        return len(self._index)


@dataclass(frozen=True)
class Frame:
    """One rendered fluoroscopic frame and its truth.

    ``image_u8`` (H, W) uint8: the 8-bit video frame (what the clinic has).
    ``image`` (H, W) float32: detected intensity, linear, relative to the unattenuated beam
    at the centre (blur, scatter, quantum noise, glare and vignetting included), before the
    video's logarithmic amplifier, its camera noise and the 8-bit quantisation.
    ``attenuation`` (H, W) float32: the line integral of mu along each pixel's X-ray path
    (dimensionless; mean over the sub-rays when oversampling).
    ``path_mm``: body name -> (H, W) float32 path length through that body (mm).
    ``materials``: body name -> material name. ``fov`` (H, W) bool: the field of view.
    ``carm``: the C-arm (its ``pixel_ray_map()`` is the true pixel -> ray map).
    """

    image_u8: np.ndarray
    image: np.ndarray
    attenuation: np.ndarray
    path_mm: dict
    materials: dict
    fov: np.ndarray
    carm: CArm

    def mask(self, materials=BONE_MATERIALS) -> np.ndarray:
        """Pixels whose X-ray path crosses a body of one of ``materials``, (H, W) bool."""
        out = np.zeros(self.fov.shape, dtype=bool)
        for name, mat in self.materials.items():
            if mat in materials:
                out |= self.path_mm[name] > 0
        return out & self.fov

    @property
    def bone_mask(self) -> np.ndarray:
        return self.mask(BONE_MATERIALS)


def _check_source_outside(carm: CArm, bodies: list[Body]) -> None:
    src = carm.source_robot
    for b in bodies:
        if b.mesh is not None:
            lo, hi = b.mesh.bounds
            if np.all(src >= lo) and np.all(src <= hi) and b.mesh.contains(src[None])[0]:
                raise ValueError(
                    f"view {carm.name!r}: the X-ray source at {np.round(src, 1).tolist()} mm "
                    f"lies inside body {b.name!r}; move the view's isocenter_mm or change "
                    "source_to_isocenter_mm / orbital_deg / angular_deg"
                )
        else:
            dist = np.linalg.norm(b.sphere_centers - src, axis=1)
            if np.any(dist <= b.sphere_radii):
                raise ValueError(
                    f"view {carm.name!r}: the X-ray source lies inside a sphere of body "
                    f"{b.name!r}"
                )


def _magnification(carm: CArm, bodies: list[Body]) -> float:
    """SID over the source-to-bone distance along the beam: the magnification of the focal-
    spot blur (one value per image, at the centre of the bone bodies' bounds; the isocenter's
    650 mm when no bone is in the scene). See docs/error-model.md, "focal spot"."""
    centres = []
    for b in bodies:
        if b.material in BONE_MATERIALS and b.mesh is not None:
            centres.append(np.mean(b.mesh.bounds, axis=0))
    depth = 650.0
    if centres:
        depth = float((np.mean(centres, axis=0) - carm.source_robot) @ carm.axis_robot)
    depth = float(np.clip(depth, 1e-3 * carm.sid_mm, carm.sid_mm))
    return carm.sid_mm / depth


def _sub_offsets(n: int) -> np.ndarray:
    s = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(s, s)
    return np.stack([x.ravel(), y.ravel()], 1)


def _field_rays(carm: CArm, n_sub: int) -> list[tuple]:
    """Per sub-pixel offset of an ``n_sub`` x ``n_sub`` oversampling, the X-ray paths of
    the pixels of the C-arm's field of view: ``(origins, directions, t_max, undistorted
    pixels)``, t_max (mm) reaching the input plane. One sample per pixel takes the C-arm's
    ray map. Kept in the C-arm's cache (a pose's rays never change), read-only."""
    key = ("field_rays", n_sub)
    if key not in carm._cache:
        fov = carm.fov_mask()
        grid = carm.pixel_grid()[fov] if n_sub > 1 else None
        rays = []
        for off in _sub_offsets(n_sub):
            if n_sub == 1 and "rays" in carm._cache:
                o, d = carm._ray_map()
                o, d = o[fov], d[fov]
                uv = carm._field()[1]
            elif n_sub == 1:    # the ray map's arithmetic, on the field's pixels only
                uv = carm._field()[1]
                p = carm._plane_points(uv)
                d = np.einsum("ij,nj->ni", carm.carm2robot.R,
                              p / np.linalg.norm(p, axis=1, keepdims=True))
                o = np.broadcast_to(carm.source_robot, d.shape).copy()
            else:
                uv = carm.undistort_px(grid + off)
                o, d = carm.rays_of_undistorted(uv)
            ray = (o, d, carm.sid_mm / (d @ carm.axis_robot), uv)
            for a in ray:
                a.flags.writeable = False
            rays.append(ray)
        carm._cache[key] = rays
    return carm._cache[key]


def _field_fans(carm: CArm, n_sub: int) -> list[FanRays]:
    """The rays of :func:`_field_rays` over the C-arm's field of view, as one binned
    :class:`testbed.raycast.FanRays` per sub-pixel offset, kept in the C-arm's cache (the
    rays of a pose never change; every frame of the pose reuses the binning)."""
    key = ("fans", n_sub)
    if key not in carm._cache:
        fans = []
        for _o, d, tm, _ in _field_rays(carm, n_sub):
            if len(d) == 0:   # (FanRays.of would average no rays and call the field wide)
                raise ValueError(
                    f"view {carm.name!r}: no pixel of the {carm.width_px} x {carm.height_px} "
                    "image lies in the intensifier's field of view; the field is centred "
                    "where [fluoroscope] principal_offset_px puts the beam axis (and "
                    "distorted about distortion_center_px): bring it into the image")
            fan = FanRays.of(carm.source_robot, np.ascontiguousarray(d), tm)
            if fan is None:  # a field wider than 160 degrees: not a fluoroscope
                raise ValueError(f"view {carm.name!r}: the field of view is too wide to "
                                 "rasterise")
            fans.append(fan)
        carm._cache[key] = fans
    return carm._cache[key]


def render(carm: CArm, bodies: list[Body], *, fluoro: FluoroscopeSpec, rng=None,
           noise: bool | None = None, distortion: bool | None = None,
           engine: str = "embree", ray_scene: RayScene | None = None) -> Frame:
    """Render one fluoroscopic frame of ``bodies`` (robot frame) seen by ``carm``.

    Parameters
    ----------
    carm : CArm
        The pose and projection (from :func:`make_carm`).
    bodies : list of Body
        Closed meshes and spheres in the robot frame, nesting by ``inside``.
    fluoro : FluoroscopeSpec
        Image-formation parameters (noise, glare, vignetting, video levels, oversampling).
    rng : numpy Generator or int or None
        For the quantum noise.
    noise : bool or None
        None follows ``fluoro.noise``.
    distortion : bool or None
        None renders ``carm`` as it is; False renders its undistorted twin; True requires
        ``carm`` to have a distortion.
    engine : "embree", "trimesh" or "numpy"
        ``testbed.raycast``'s engines: "embree" is the fast path (:class:`RayScene`: the
        field's rays binned once per C-arm and the meshes rasterised, Embree for a mesh
        reaching behind the source), the others the exact references.
    ray_scene : testbed.raycast.RayScene or None
        The same ``bodies`` prepared once for many frames (engine "embree" only).

    Raises ``ValueError`` if the source lies inside a body, or for unknown materials or
    nesting.
    """
    if distortion is False:
        carm = carm.undistorted()
    elif distortion is True and carm.distortion is None:
        raise ValueError("render: distortion=True but the C-arm was made without distortion")
    use_noise = fluoro.noise if noise is None else bool(noise)
    for b in bodies:
        material(b.material)
    weights = attenuation_weights(bodies)
    _check_source_outside(carm, bodies)
    if ray_scene is not None and [b.name for b in ray_scene.bodies] != [b.name for b in bodies]:
        raise ValueError("render: ray_scene was prepared for other bodies")
    if ray_scene is None and engine == "embree":
        ray_scene = RayScene(bodies)

    H, W = carm.height_px, carm.width_px
    fov = carm.fov_mask()
    n_sub = fluoro.oversample
    M = int(np.count_nonzero(fov))
    att = np.zeros(M)
    trans = np.zeros(M)
    lengths = np.zeros((M, len(bodies))) if n_sub > 1 else None
    if engine == "embree":
        per_offset = (ray_scene.fan_path_lengths(fan) for fan in _field_fans(carm, n_sub))
    else:
        per_offset = (body_path_lengths(bodies, o, d, t_max, engine=engine)
                      for o, d, t_max, _ in _field_rays(carm, n_sub))
    for L in per_offset:
        a = L @ weights
        if n_sub == 1:
            att, trans, lengths = a, np.exp(-a), L
            break
        att += a / n_sub**2
        trans += np.exp(-a) / n_sub**2
        lengths += L / n_sub**2

    full = np.zeros((H, W))
    full[fov] = trans
    full, video = form_image(full, fov, carm._field()[2], fluoro,
                             magnification=_magnification(carm, bodies),
                             noise=use_noise, rng=np.random.default_rng(rng))

    att_img = np.zeros((H, W), dtype=np.float32)
    att_img[fov] = att
    return Frame(
        image_u8=video,
        image=full.astype(np.float32),
        attenuation=att_img,
        # float32 as the images it makes (the same numbers; half the memory a frame keeps)
        path_mm=PathImages([b.name for b in bodies], np.asarray(lengths, dtype=np.float32),
                           fov),
        materials={b.name: b.material for b in bodies},
        fov=fov,
        carm=carm,
    )


class SweepRenderer:
    """The frames of one view's calibration sweep, fast: the static bodies are cast once.

    A sweep frame differs from the view's empty-rod frame only where the rod is. The line
    integrals of the static bodies (patient, table, instruments; they do not move during a
    sweep) are computed once per view; per frame only the rays that can meet the rod are
    cast against the rod's bodies, and line integrals add. Which rays can meet the rod: the
    rod's bodies seen from the source, on the undistorted (pinhole) image plane, lie inside
    the convex hull of the central projections of their vertices (of the bounding cubes'
    corners for the beads), central projection mapping lines to lines; a ray is kept when
    its undistorted pixel lies within ``HULL_MARGIN_PX`` of that hull, so the culling is
    conservative and the frame is that of :func:`render` with all bodies (the reference,
    compared in ``tests/testbed/test_sweep.py``) up to the order of floating-point sums.
    The image chain (:func:`testbed.detector.form_image`) runs on the field's box, as in
    :func:`render`, with the same generator draws; the culling skips whole blocks of
    ``CULL_BLOCK`` rays (consecutive in row-major order) whose undistorted pixels' bounding
    box misses the hull's.

    Parameters
    ----------
    carm : CArm (the calibration-stage C-arm of the view).
    fluoro : FluoroscopeSpec.
    bodies : the static bodies (robot frame).
    """

    HULL_MARGIN_PX = 0.5
    FLAT_HULL_PX2 = 1e-6   # a hull of this area (px^2) or less is flat: its box is used
    CULL_BLOCK = 64      # rays per block of the culling's bounding boxes

    def __init__(self, carm: CArm, fluoro: FluoroscopeSpec, bodies: list[Body]):
        self.carm, self.fluoro, self.bodies = carm, fluoro, list(bodies)
        for b in self.bodies:
            material(b.material)
        _check_source_outside(carm, self.bodies)
        self._source = carm.source_robot
        self._robot2carm = carm.carm2robot.inverse()
        self._by_name = {b.name: b for b in self.bodies}
        self.fov = carm.fov_mask()
        from testbed._fan_numba import block_boxes

        self._rays, self._uv, self._blocks, self._planes, static = [], [], [], [], []
        weights = attenuation_weights(self.bodies)
        scene = RayScene(self.bodies) if self.bodies else None
        fans = _field_fans(carm, fluoro.oversample)
        for fan, (o, d, tm, uv) in zip(fans, _field_rays(carm, fluoro.oversample)):
            a = (scene.fan_path_lengths(fan) @ weights if self.bodies else np.zeros(len(o)))
            self._rays.append((np.ascontiguousarray(o), np.ascontiguousarray(d), tm))
            self._uv.append(np.ascontiguousarray(uv))      # undistorted pixel of each ray
            self._blocks.append((*block_boxes(self._uv[-1], self.CULL_BLOCK),
                                 self.CULL_BLOCK))
            self._planes.append((fan.axis, fan.e1, fan.e2))   # the field fan's image plane
            static.append(a)
        self._static = static
        self._static_exp = [np.exp(-a) for a in static]
        # the image chain computes on the field's box: the frames are built there
        field = detector._field(self.fov, carm._field()[2], fluoro.vignetting)
        self._box, self._fov_box = field.box, field.fov
        self._field_px = np.flatnonzero(self._fov_box)  # the box's flat pixel of each ray
        self._static_box = np.zeros(self._fov_box.shape)  # the frame without the rod (k = 1)
        self._static_box[self._fov_box] = self._static_exp[0]
        self._magnification = _magnification(carm, self.bodies)
        # with scatter, the stages before its wide blur are redone only near the rod (each
        # pixel depends on the transmission within the focal spot's kernel radius): the
        # chain's field then, else None (the whole chain per frame)
        self._local = None
        if fluoro.scatter_to_primary > 0 and len(self._static) == 1:
            self._local = field
            self._sources0 = detector._sources(self._static_box, self._fov_box, fluoro,
                                               self._magnification)
            for a in self._sources0:
                a.flags.writeable = False
            # what each frame changes near the rod, restored after it (no copy per frame)
            self._work = tuple(a.copy() for a in self._sources0)
            # the scatter's wide blur, redone per frame only for the rod's window
            self._scatter_blur = detector.WideBlurUpdate(
                self._sources0[1], fluoro.scatter_sigma_mm / float(fluoro.pixel_mm))
            self._focal_r = detector._focal_radius_px(fluoro, self._magnification)

    def _hull_px(self, rod: list[Body]) -> np.ndarray:
        """Undistorted pixels (K, 2) of the rod's vertices (bead cubes' corners)."""
        return self.carm.project_undistorted(self._rod_points(rod)[0])

    def _rod_points(self, rod: list[Body]):
        """The rod's vertices and bead cubes' corners ``(K, 3)`` (robot frame, in the rod's
        order), the rows ``(start, stop)`` of each mesh's vertices among them ``(M, 2)``,
        and the beads' centres ``(C, 3)`` and radii ``(C,)``."""
        pts, seg, centres, radii = [], [], [], []
        k = 0
        for b in rod:
            if b.mesh is not None:
                v = np.asarray(b.mesh.vertices)
                seg.append((k, k + len(v)))
            else:
                v = (b.sphere_centers[:, None, :] + b.sphere_radii[:, None, None]
                     * _CUBE_CORNERS[None]).reshape(-1, 3)
                centres.append(b.sphere_centers)
                radii.append(np.broadcast_to(b.sphere_radii, (len(b.sphere_centers),)))
            pts.append(v)
            k += len(v)
        seg = np.array(seg, dtype=np.int64).reshape(-1, 2)
        centres = (np.vstack(centres).astype(np.float64) if centres else np.zeros((0, 3)))
        radii = np.concatenate(radii).astype(np.float64) if radii else np.zeros(0)
        return np.vstack(pts), seg, centres, radii

    def _rod_hull(self, rod: list[Body]):
        """``(pts, lo, hi, equations)``: :meth:`_hull_px` of the rod (the same pixels: the
        same product by the inverse pose, then the pinhole expressions compiled), the bounds
        and half-planes :meth:`_inside_hull` derives from them (one compiled call,
        :func:`testbed._fan_numba.projected_hull`); before them the source's check of
        :func:`_check_source_outside` (run only when
        :func:`testbed._fan_numba.source_near_bodies` cannot rule the rod out)."""
        from testbed._fan_numba import projected_hull, source_near_bodies

        p, seg, centres, radii = self._rod_points(rod)
        if source_near_bodies(p, seg, centres, radii, self._source):
            _check_source_outside(self.carm, rod)
        inv = self._robot2carm
        q = p @ inv.R.T + inv.t            # as RigidTransform.apply
        carm = self.carm
        ok, pts, lo, hi, equations = projected_hull(
            q, float(carm.principal_px[0]), float(carm.principal_px[1]), float(carm.sid_mm),
            float(carm.pixel_mm), float(self.HULL_MARGIN_PX), float(self.FLAT_HULL_PX2))
        if not ok:
            raise ValueError(f"view {carm.name!r}: points at or behind the X-ray source")
        return pts, lo, hi, equations

    @classmethod
    def _inside_hull(cls, uv, pts: np.ndarray, *, reference: bool = False,
                     blocks=None, hull=None) -> np.ndarray:
        """Indices (ascending) of the points ``uv`` (M, 2) within the margin of the convex
        hull of ``pts`` (K, 2); compiled (the hull by :func:`testbed._fan_numba.hull_equations`,
        the points by :func:`testbed._fan_numba.points_in_hull`; ``blocks``: ``(block_lo,
        block_hi, block)`` of ``uv`` from :func:`testbed._fan_numba.block_boxes`, so that
        blocks outside the hull's box are skipped; ``hull``: ``(lo, hi, equations)`` of
        ``pts`` when the caller has them, :meth:`_rod_hull`'s). ``reference=True``: scipy's
        convex hull and the same tests in numpy (compared in tests)."""
        m = cls.HULL_MARGIN_PX
        if hull is not None and not reference:
            from testbed._fan_numba import points_in_hull, points_in_hull_blocks

            lo, hi, equations = hull
            if blocks is not None:
                return points_in_hull_blocks(uv, *blocks, lo, hi, equations, m)
            return points_in_hull(uv, lo, hi, equations, m)
        lo, hi = pts.min(axis=0) - m, pts.max(axis=0) + m
        if not reference:
            from testbed._fan_numba import hull_equations, points_in_hull, points_in_hull_blocks

            # rows (nx, ny, offset), outward unit normals; inside: n.x + off <= 0; none when
            # flat (a rod seen end-on): its bounding box is conservative
            order = np.lexsort((pts[:, 1], pts[:, 0]))
            equations = hull_equations(np.ascontiguousarray(pts[order], dtype=np.float64),
                                       cls.FLAT_HULL_PX2)
            if blocks is not None:
                return points_in_hull_blocks(uv, *blocks, lo, hi,
                                             np.ascontiguousarray(equations), m)
            return points_in_hull(uv, lo, hi, np.ascontiguousarray(equations), m)
        from scipy.spatial import ConvexHull, QhullError

        try:
            equations = ConvexHull(pts).equations
        except QhullError:
            equations = np.zeros((0, 3))
        x, y = uv[:, 0], uv[:, 1]
        cand = np.flatnonzero((x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]))
        # one edge at a time on the survivors: most candidates fall at the first few edges
        x, y = uv[cand, 0], uv[cand, 1]
        for nx, ny, off in equations:
            keep = nx * x + ny * y + off <= m
            cand, x, y = cand[keep], x[keep], y[keep]
        return cand

    def _with_rod(self, fan: int, rod: list[Body], hull, weights: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The rays of fan ``fan`` the rod can meet (indices) and their transmission with the
        static bodies and the rod (``hull``: :meth:`_rod_hull`'s)."""
        (o, d, tm), a_static = self._rays[fan], self._static[fan]
        idx = self._inside_hull(self._uv[fan], hull[0], blocks=self._blocks[fan],
                                hull=hull[1:])
        if not len(idx):
            return idx, np.zeros(0)
        # what body_path_lengths does for rays from one point (without checking that they
        # are), binned on the field fan's image plane (a subset of its rays: within its angle)
        # in cells shaped like the rays' extent (the rod's long thin faces cross fewer
        # cells; the chords are the same)
        from testbed._fan_numba import gather_rays

        # d[idx], tm[idx], a_static[idx] in one compiled gather (the same arrays)
        d_idx, tm_idx, a_idx = gather_rays(d, tm, a_static, idx)
        rays = (FanRays(o[0], d_idx, tm_idx, *self._planes[fan], elongation="auto")
                if len(idx) >= FanRays.MIN_RAYS else None)
        scene = RayScene(list(rod))
        lengths = (scene.fan_path_lengths(rays) if rays is not None
                   else scene.path_lengths(o[idx], d_idx, tm_idx))
        a = a_idx + lengths @ weights
        return idx, np.exp(-a)

    def transmission(self, rod: list[Body]) -> np.ndarray:
        """Primary transmission (H, W) with ``rod`` (robot frame) in the beam."""
        full = np.zeros(self.fov.shape)
        full[self._box] = self._transmission_box(rod)[0]
        return full

    def _transmission_box(self, rod: list[Body]) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`transmission` on the image chain's box (``self._box``), and the box's flat
        indices of the pixels that differ from the static frame (None with oversampling)."""
        k = len(self._static)
        if k == 1:    # the static frame, changed at the rays the rod can meet
            px, e = self._rod_rays(rod)
            box = self._static_box.copy()
            box.flat[px] = e
            return box, px
        weights, hull = self._rod_setup(rod)
        trans = np.zeros(len(self._static[0]))
        for fan in range(k):
            e = self._static_exp[fan].copy()
            idx, e_rod = self._with_rod(fan, rod, hull, weights)
            e[idx] = e_rod
            trans += e / k
        box = np.zeros(self._fov_box.shape)
        box[self._fov_box] = trans
        return box, None

    def _rod_setup(self, rod: list[Body]):
        """The rod's attenuation weights and its culling hull (:meth:`_rod_hull`)."""
        rod = list(rod)
        return self._rod_weights(rod), self._rod_hull(rod)

    def _rod_weights(self, rod: list[Body]) -> np.ndarray:
        """``attenuation_weights(self.bodies + rod)[len(self.bodies):]`` (the same numbers
        and refusals), with the static bodies' names looked up once (``enclosing``)."""
        return attenuation_weights(rod, enclosing=self._by_name)

    def _rod_rays(self, rod: list[Body]) -> tuple[np.ndarray, np.ndarray]:
        """Without oversampling: the box's flat indices of the rays the rod can meet, and
        their transmission (the static frame holds everywhere else)."""
        weights, hull = self._rod_setup(rod)
        idx, e = self._with_rod(0, rod, hull, weights)
        return self._field_px[idx], e

    def _local_sources(self, px: np.ndarray, e: np.ndarray):
        """The chain's scatter sources (:func:`testbed.detector._sources`) of the static
        frame changed to the transmission ``e`` at the box's flat pixels ``px``: the static
        frame's, redone on those pixels' box grown by the focal kernel's radius (computed on
        it grown by twice the radius, so that the kept part never sees the window's edge).
        Written into the renderer's working copies of the static sources, which are
        returned with the window written (None when ``px`` is empty): the caller restores
        it (:meth:`_restore`) once the frame is made."""
        p, src = self._work
        if not len(px):
            return p, src, None
        r = self._focal_r
        H, W = self._fov_box.shape
        rows, cols = np.divmod(px, W)
        lo = np.array([rows.min(), cols.min()])
        hi = np.array([rows.max(), cols.max()]) + 1
        o_lo, o_hi = np.maximum(lo - 2 * r, 0), np.minimum(hi + 2 * r, (H, W))
        i_lo, i_hi = np.maximum(lo - r, 0), np.minimum(hi + r, (H, W))
        outer = (slice(o_lo[0], o_hi[0]), slice(o_lo[1], o_hi[1]))
        window = self._static_box[outer].copy()
        window[rows - o_lo[0], cols - o_lo[1]] = e
        ps, ss = detector._sources(window, self._fov_box[outer], self.fluoro,
                                   self._magnification)
        inner = (slice(i_lo[0], i_hi[0]), slice(i_lo[1], i_hi[1]))
        sub = (slice(i_lo[0] - o_lo[0], i_hi[0] - o_lo[0]),
               slice(i_lo[1] - o_lo[1], i_hi[1] - o_lo[1]))
        p[inner] = ps[sub]
        src[inner] = ss[sub]
        return p, src, inner

    def _restore(self, inner) -> None:
        """The working copies of the static sources back to them in the window ``inner``."""
        if inner is not None:
            for work, static in zip(self._work, self._sources0, strict=True):
                work[inner] = static[inner]

    def render(self, rod: list[Body], *, rng=None, noise: bool | None = None) -> np.ndarray:
        """The 8-bit video frame (H, W) uint8 with ``rod`` in the beam; ``rng`` as in
        :func:`render` (the same draws)."""
        use_noise = self.fluoro.noise if noise is None else bool(noise)
        rng = np.random.default_rng(rng)
        if self._local is None:
            trans, _ = self._transmission_box(rod)
            _, video = form_image(trans, self.fov, self.carm._field()[2], self.fluoro,
                                  magnification=self._magnification, noise=use_noise,
                                  rng=rng, intensity=False)
            return video
        p, src, inner = self._local_sources(*self._rod_rays(rod))
        try:
            _, video_box = detector._after_sources(p, src, self._local, self.fluoro,
                                                   noise=use_noise, rng=rng,
                                                   low=self._scatter_blur.blur(src, inner))
        finally:
            self._restore(inner)
        video = np.zeros(self.fov.shape, dtype=np.uint8)
        video[self._box] = video_box
        return video


# --------------------------------------------------------------------------- scene wiring
def render_view(scene, view: int, *, seed: int | None = None, bodies=None,
                distortion: bool | None = None, noise: bool | None = None) -> Frame:
    """Render view number ``view`` (0-based) of an operating-room scene.

    Raises ``ValueError`` naming the scene field when the view index is out of range, the
    source lies inside a body, or the field of view shows no bone.
    """
    n = len(scene.views)
    if n == 0:
        raise ValueError(
            f"scene {scene.scene.name!r} (kind {scene.scene.kind!r}) has no [[views]] to "
            "render; give an operating-room scene, e.g. experiment2"
        )
    if not 0 <= view < n:
        raise ValueError(f"--view {view}: the scene has {n} [[views]] (0 to {n - 1})")
    seed = scene.scene.seed if seed is None else seed
    ss = np.random.SeedSequence(seed)
    world_ss, noise_ss = ss.spawn(2)
    if bodies is None:
        from testbed.world import world_bodies

        bodies = world_bodies(scene, np.random.default_rng(world_ss))
    vspec = scene.views[view]
    carm = make_carm(scene.fluoroscope, vspec, distortion=distortion, view_index=view)
    try:
        frame = render(carm, bodies, fluoro=scene.fluoroscope,
                       rng=np.random.default_rng(noise_ss), noise=noise)
    except ValueError as exc:
        raise ValueError(f"views[{view}] ({vspec.name!r}): {exc}") from None
    has_bone = any(mat in BONE_MATERIALS for mat in frame.materials.values())
    if has_bone and not frame.bone_mask.any():
        raise ValueError(
            f"views[{view}] ({vspec.name!r}): the field of view misses the anatomy (no bone "
            f"in the image); check views[{view}].isocenter_mm = {list(vspec.isocenter_mm)} "
            "and the orbital/angular angles against patient.position_mm"
        )
    return frame
