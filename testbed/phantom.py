"""The simulated patient: a procedural femur with pins and a soft-tissue envelope.

The ``ct`` frame is the phantom's own frame (mm), the frame the CT scanner images:

- ``z`` along the femur's long axis, proximal positive: the lowest point of the condyles at
  z = 0, the top of the femoral head at z = ``length_mm`` (about 450 mm);
- ``x`` toward the patient's right: lateral for a right femur (the femoral head lies at
  negative x), medial for a left femur (the mirror image, head at positive x);
- ``y`` anterior. (x, y, z) is right-handed (RAS).

The femur is built with robust booleans (manifold3d): the union of convex lofts between
elliptic cross-sections along an anteriorly bowed shaft (with metaphyseal flares), a sphere
for the head, a loft for the neck (neck-shaft angle, anteversion), ellipsoids for the greater
and lesser trochanters and the two condyles (with the intercondylar notch between them; the
medial one lower, the knee's joint line tilted to the shaft by the anatomical lateral distal
femoral angle) and a trochlear bridge joining the condyles anteriorly. The same construction
with every part inset by the end-cortex thickness gives the cancellous bone at the two ends; a
tapered loft inside the shaft gives the medullary canal. Every mesh is watertight and manifold.

Pins: small steel cylinders in cancellous bone, one in the greater trochanter
(``proximal``) and one in each condyle (``distal_1`` medial, ``distal_2`` lateral); their
centre is the ground-truth target point.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import manifold3d as mf
import numpy as np
import trimesh
from pydantic import Field, model_validator

from testbed.bodies import Body
from testbed.spec import Positive, Spec, Vec3

__all__ = ["Phantom", "PhantomSpec", "PIN_NAMES", "make_phantom"]

PIN_NAMES = ("proximal", "distal_1", "distal_2")


#: the fields that only the procedural femur reads (a user mesh replaces them)
PROCEDURAL_FIELDS = (
    "length_mm", "head_radius_mm", "neck_length_mm", "neck_radius_mm", "neck_shaft_angle_deg",
    "anteversion_deg", "shaft_diameter_mm", "cortical_thickness_mm", "end_cortex_mm",
    "shaft_bow_mm", "condyle_width_mm", "notch_width_mm", "condyle_depth_mm",
    "distal_joint_angle_deg", "thigh_radius_mm", "knee_radius_mm", "shape_variation",
    "surface_detail_mm", "surface_detail_wavelength_mm")


#: the thickest cortex of the procedural femur's shaft, as a share of its diameter: a canal
#: of at least 30 % of the diameter stays (the capture-range study draws within it too)
MAX_CORTEX_SHARE = 0.35


class PhantomSpec(Spec):
    """``[phantom]``: the femur phantom (procedural, or a user mesh), its pins and the thigh.

    Dimensions (mm, deg) default to an adult femur; ``shape_variation`` (0: the mean femur,
    1: about one population standard deviation per dimension) draws a plausible femur from
    ``shape_seed`` mixed with the case's seed (``testbed.simulate``): every case of a study
    has its own femur, ``testbed run --seed S`` simulates the femur of case seed S and
    ``testbed render --seed S`` shows that one. The drawn dimensions stay within the bounds
    of their fields.
    """

    side: Literal["left", "right"] = "right"
    length_mm: Annotated[float, Field(ge=300, le=600)] = 450.0
    head_radius_mm: Annotated[float, Field(ge=15, le=35)] = 23.0
    neck_length_mm: Annotated[float, Field(ge=30, le=80)] = 50.0
    neck_radius_mm: Annotated[float, Field(ge=8, le=25)] = 15.0
    neck_shaft_angle_deg: Annotated[float, Field(ge=110, le=150)] = 127.0
    anteversion_deg: Annotated[float, Field(ge=-10, le=40)] = 12.0
    shaft_diameter_mm: Annotated[float, Field(ge=18, le=40)] = 28.0
    cortical_thickness_mm: Annotated[float, Field(ge=2, le=10)] = 6.5
    end_cortex_mm: Annotated[float, Field(ge=1, le=5)] = 2.5
    shaft_bow_mm: Annotated[float, Field(ge=0, le=25)] = 8.0
    condyle_width_mm: Annotated[float, Field(ge=60, le=100)] = 80.0
    notch_width_mm: Annotated[float, Field(ge=10, le=30)] = 18.0
    condyle_depth_mm: Annotated[float, Field(ge=45, le=80)] = 60.0
    distal_joint_angle_deg: Annotated[float, Field(ge=75, le=90)] = 81.0
    """Anatomical lateral distal femoral angle (aLDFA, deg): between the shaft's axis and the
    knee's joint line, on the lateral side. Normal 81 (79-83; Paley & Tetsworth, Clin.
    Orthop. 280, 1992 [memory]): with the shaft along z the medial condyle reaches lower
    than the lateral one, so the lowest CT slices cut one condyle only. 90: level condyles
    (the phantom before this field)."""
    thigh_radius_mm: Annotated[float, Field(ge=50, le=200)] = 85.0
    knee_radius_mm: Annotated[float, Field(ge=45, le=120)] = 60.0
    leg_mm: Annotated[float, Field(ge=0, le=600)] = 250.0
    """Soft tissue of the lower leg beyond the thigh's knee end (mm along the femur, knee's
    radius): a patient's leg goes on past the knee, so a distal view never sees air there
    (0: the thigh ends 40 mm past the condyles, a bare limb)."""
    hip_mm: Annotated[float, Field(ge=0, le=600)] = 250.0
    """Soft tissue of the hip and pelvis beyond the thigh's hip end (mm along the femur,
    thigh's radius; the pelvic bones are not modelled): the body goes on past the femoral
    head, so a proximal view of a short femur never sees air there (0: the thigh ends 30 mm
    past the head). Without it, the air beside a limb that ends inside a view saturates the
    video, and the sweep frames' differences fail (a review: 18-81 blobs for 8 beads)."""
    pin_diameter_mm: Annotated[float, Field(ge=1, le=8)] = 4.0
    """The implanted pins' diameter (mm): from a K-wire's 1 mm (a thinner pin is neither
    implanted as a landmark nor located by touch; 0.1 mm was accepted before, a held-out
    review) to 8 mm."""
    pin_length_mm: Annotated[float, Field(ge=2, le=20)] = 8.0
    segments: Annotated[int, Field(ge=16, le=256)] = 64
    shape_variation: Annotated[float, Field(ge=0, le=3)] = 0.0
    """Population standard deviations per dimension (0-3; beyond 3 the drawn femur is no
    femur: negative radii)."""
    shape_seed: Annotated[int, Field(ge=0)] = 0
    surface_detail_mm: Annotated[float, Field(ge=0, le=1.0)] = 0.0
    """Surface detail of a real femur that the smooth procedural one lacks (mm RMS along the
    normals; 0: none, both profiles): a smooth random field of 24 plane waves of
    ``surface_detail_wavelength_mm`` (0.6-1.6 times it), drawn from ``shape_seed``, moves the
    outer bone surface (subdivided to a sixth of the wavelength). An optional source, not a
    default: docs/error-model.md gives its measured effect and why no default is set."""
    surface_detail_wavelength_mm: Annotated[float, Field(ge=5, le=100)] = 20.0
    mesh_path: str | None = None
    mesh_pins_mm: dict[str, Vec3] | None = None
    mesh_margin_mm: Positive = 40.0

    @model_validator(mode="after")
    def _check(self):
        if self.mesh_path is not None and not self.mesh_path.strip():
            raise ValueError("mesh_path is empty; give the femur mesh's file, or leave "
                             "mesh_path out for the procedural femur")
        fields = type(self).model_fields
        moved = [k for k in (PROCEDURAL_FIELDS if self.mesh_path is not None
                             else ("mesh_margin_mm",))
                 if getattr(self, k) != fields[k].default]
        if moved and self.mesh_path is not None:
            raise ValueError(f"{', '.join(moved)}: field(s) of the procedural femur, which the "
                             f"user mesh (mesh_path) replaces, so they would be ignored; "
                             "remove them (around a user mesh the thigh is its bounding box "
                             "widened by mesh_margin_mm)")
        if moved:
            raise ValueError("mesh_margin_mm is only used around a user mesh (mesh_path); the "
                             "procedural femur's thigh is set by thigh_radius_mm and "
                             "knee_radius_mm")
        if self.notch_width_mm >= self.condyle_width_mm / 2:
            raise ValueError("notch_width_mm must be below half of condyle_width_mm")
        if self.cortical_thickness_mm >= MAX_CORTEX_SHARE * self.shaft_diameter_mm:
            # a review: 9 mm in an 18 mm shaft (no canal) stopped the CT scan with a
            # TypeError; 10 mm (a canal of -1 mm radius) was simulated as one of +1 mm
            raise ValueError(
                f"cortical_thickness_mm ({self.cortical_thickness_mm:g}) must be below "
                f"{MAX_CORTEX_SHARE:g} x shaft_diameter_mm ({self.shaft_diameter_mm:g}) = "
                f"{MAX_CORTEX_SHARE * self.shaft_diameter_mm:.3g} mm, which leaves the shaft "
                "a marrow canal of at least 30 % of its diameter")
        if self.mesh_pins_mm is not None:
            if self.mesh_path is None:
                raise ValueError("mesh_pins_mm is given without mesh_path: the pins of a user "
                                 "mesh need the mesh (the procedural femur places its own)")
            missing = set(PIN_NAMES) - set(self.mesh_pins_mm)
            if missing:
                raise ValueError(f"mesh_pins_mm lacks the pins {sorted(missing)}")
            extra = set(self.mesh_pins_mm) - set(PIN_NAMES)
            if extra:
                raise ValueError(f"mesh_pins_mm: unknown pin(s) {sorted(extra)}; the pins are "
                                 f"{list(PIN_NAMES)}")
            # two pins where one is (a review: distal_1 = distal_2 was run, accepted and
            # scored with the pin counted twice): their steel would overlap. All three within
            # a few cm: pins (and mesh) in metres or cm, not a misplaced pin (a review's
            # femur in metres was told to "place each pin where it is")
            for i, a in enumerate(PIN_NAMES):
                for b in PIN_NAMES[i + 1:]:
                    gap = float(np.linalg.norm(np.subtract(self.mesh_pins_mm[a],
                                                           self.mesh_pins_mm[b])))
                    if gap < self.pin_length_mm:
                        raise ValueError(
                            f"mesh_pins_mm: pins {a!r} and {b!r} lie {gap:.3g} mm apart, "
                            f"closer than a pin is long (pin_length_mm = "
                            f"{self.pin_length_mm:g}): place each pin where it is"
                            f"{self._pin_units_hint()}")
        return self

    def _pin_units_hint(self) -> str:
        """``""``, or, when all three ``mesh_pins_mm`` lie within 50 mm, a clause saying
        they look like metres or centimetres (a femur's proximal and distal pins lie
        hundreds of mm apart)."""
        pins = np.array([self.mesh_pins_mm[n] for n in PIN_NAMES], dtype=np.float64)
        span = float(np.max(np.linalg.norm(pins[:, None] - pins[None], axis=-1)))
        if span >= 50.0:
            return ""
        return (f"; all three lie within {span:.3g} mm, where a femur's proximal and distal "
                "pins lie hundreds of mm apart: mesh_pins_mm and the mesh are in millimetres "
                "(pins in metres or centimetres need scaling)")


@dataclass(frozen=True)
class Phantom:
    """The phantom in the ct frame (mm).

    ``femur``: outer bone surface (cortical bone); ``canal``: medullary canal (marrow), inside
    the femur; ``cancellous``: cancellous bone at both ends, inside the femur (a user mesh's
    within its cortex, :func:`_user_interior`, or None); ``soft_tissue``: thigh envelope
    around the femur; ``pins``: name -> (3,) centre; ``pin_meshes``: name -> steel
    cylinder; ``landmarks``: name -> (3,) anatomical points (``head_center``,
    ``neck_base``, ``lesser_trochanter``, ``greater_trochanter``, ``medial_condyle``,
    ``lateral_condyle``); ``spec``: the resolved dimensions.
    """

    femur: trimesh.Trimesh
    canal: trimesh.Trimesh | None
    cancellous: trimesh.Trimesh | None
    soft_tissue: trimesh.Trimesh
    pins: dict[str, np.ndarray]
    pin_meshes: dict[str, trimesh.Trimesh]
    pin_inside: dict[str, str]
    side: str
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    spec: PhantomSpec | None = None

    def bodies(self) -> list[Body]:
        """The phantom as world bodies in the ct frame, outermost first, nesting set."""
        out = [Body("soft_tissue", "soft_tissue", self.soft_tissue, inside=None),
               Body("femur", "cortical_bone", self.femur, inside="soft_tissue")]
        if self.cancellous is not None:
            out.append(Body("cancellous", "cancellous_bone", self.cancellous, inside="femur"))
        if self.canal is not None:
            out.append(Body("canal", "marrow", self.canal, inside="femur"))
        for name in PIN_NAMES:
            out.append(Body(f"pin_{name}", "steel", self.pin_meshes[name],
                            inside=self.pin_inside[name]))
        return out

    def z_range_mm(self) -> tuple[float, float]:
        """Lowest and highest z of the femur, mm."""
        return float(self.femur.bounds[0, 2]), float(self.femur.bounds[1, 2])


# --------------------------------------------------------------------------- geometry
def _to_trimesh(m: mf.Manifold) -> trimesh.Trimesh:
    mesh = m.to_mesh()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    f = np.asarray(mesh.tri_verts, dtype=np.int64)
    return trimesh.Trimesh(v, f, process=True)


def _ring(center, e1, e2, a, b, n) -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return (np.asarray(center)[None, :] + np.outer(a * np.cos(t), e1)
            + np.outer(b * np.sin(t), e2))


def _ellipsoid(center, axes, n) -> mf.Manifold:
    return mf.Manifold.sphere(1.0, n).scale(tuple(float(a) for a in axes)).translate(
        tuple(float(c) for c in center))


def _loft(rings) -> list[mf.Manifold]:
    return [mf.Manifold.hull_points(np.vstack([r0, r1])) for r0, r1 in zip(rings, rings[1:],
                                                                              strict=False)]


@dataclass
class _Dims:
    """Resolved dimensions (after shape variation), right femur."""

    L: float
    head_r: float
    neck_len: float
    neck_r: float
    nsa: float
    antev: float
    shaft_r: float
    cortex: float
    end_cortex: float
    bow: float
    condyle_w: float
    notch_w: float
    condyle_d: float
    n: int
    aldfa: float = 90.0
    width_scale: float = 1.0    # the draw's common scale of the widths (s_wid)


def field_bounds(name: str) -> tuple[float, float]:
    """(lower, upper) of a numeric PhantomSpec field (from its pydantic constraints; -inf /
    inf where it has none)."""
    lo, hi = -np.inf, np.inf
    for m in PhantomSpec.model_fields[name].metadata:
        lo = getattr(m, "ge", None) if getattr(m, "ge", None) is not None else lo
        hi = getattr(m, "le", None) if getattr(m, "le", None) is not None else hi
    return float(lo), float(hi)


_BOUNDS = {k: field_bounds(k) for k in (
    "length_mm", "head_radius_mm", "neck_length_mm", "neck_radius_mm", "shaft_diameter_mm",
    "cortical_thickness_mm", "condyle_width_mm", "notch_width_mm", "condyle_depth_mm",
    "neck_shaft_angle_deg", "anteversion_deg", "shaft_bow_mm", "distal_joint_angle_deg")}


def _resolve(spec: PhantomSpec) -> _Dims:
    v = float(spec.shape_variation)
    rng = np.random.default_rng(spec.shape_seed)
    # the 13th draw (the joint angle) came later: the first 12 stay what they were per seed
    z = np.clip(rng.standard_normal(13), -2.5, 2.5) * v
    s_len = 1 + 0.05 * z[0]
    s_wid = 1 + 0.06 * z[1]
    def within(name, value, scale=1.0):  # a drawn dimension stays within its field's bounds
        lo, hi = _BOUNDS[name]
        return float(np.clip(value, scale * lo, scale * hi))

    shaft_r = within("shaft_diameter_mm", spec.shaft_diameter_mm / 2 * s_wid * (1 + 0.05 * z[7]),
                     0.5)
    # a drawn cortex leaves a canal as a given one must (MAX_CORTEX_SHARE of the diameter)
    cortex = min(within("cortical_thickness_mm", spec.cortical_thickness_mm * (1 + 0.08 * z[8])),
                 MAX_CORTEX_SHARE * 2.0 * shaft_r)
    return _Dims(
        L=within("length_mm", spec.length_mm * s_len),
        head_r=within("head_radius_mm", spec.head_radius_mm * s_wid * (1 + 0.04 * z[2])),
        neck_len=within("neck_length_mm", spec.neck_length_mm * s_wid * (1 + 0.06 * z[3])),
        neck_r=within("neck_radius_mm", spec.neck_radius_mm * s_wid * (1 + 0.05 * z[4])),
        nsa=within("neck_shaft_angle_deg", spec.neck_shaft_angle_deg + 4.5 * z[5]),
        antev=within("anteversion_deg", spec.anteversion_deg + 6.0 * z[6]),
        shaft_r=shaft_r,
        cortex=cortex,
        end_cortex=spec.end_cortex_mm,
        bow=within("shaft_bow_mm", spec.shaft_bow_mm * (1 + 0.3 * z[9])),
        condyle_w=within("condyle_width_mm", spec.condyle_width_mm * s_wid * (1 + 0.04 * z[10])),
        notch_w=within("notch_width_mm", spec.notch_width_mm * s_wid * (1 + 0.08 * z[11])),
        condyle_d=within("condyle_depth_mm", spec.condyle_depth_mm * s_wid),
        n=int(spec.segments),
        aldfa=within("distal_joint_angle_deg", spec.distal_joint_angle_deg + 2.0 * z[12]),
        width_scale=float(s_wid),
    )


def _geometry(d: _Dims) -> dict:
    """Anatomical frame points and part sizes of a right femur (mm)."""
    L, n = d.L, d.n
    theta = np.radians(180.0 - d.nsa)          # neck axis from +z
    ante = np.radians(d.antev)
    neck_dir = np.array([-np.sin(theta) * np.cos(ante), np.sin(theta) * np.sin(ante),
                         np.cos(theta)])
    # The neck leaves the shaft axis; the head's top is at z = L.
    neck_base = np.array([0.0, 0.0, L - d.head_r - d.neck_len * neck_dir[2]])
    head_c = neck_base + d.neck_len * neck_dir
    r = d.shaft_r
    cw = d.condyle_w / 2
    cond_ax = (cw - d.notch_w / 2) / 2                # ML semi-axis of one condyle
    cond_x = d.notch_w / 2 + cond_ax
    cond_h = 0.40 * d.condyle_d                       # SI semi-axis
    # the medial condyle (-x, the head's side) lowest; the lateral one raised by the joint
    # line's tilt across the condyles' centres
    lat_dz = 2 * cond_x * np.tan(np.radians(90.0 - d.aldfa))
    cond = dict(ax=(cond_ax, d.condyle_d / 2, cond_h), y=-0.12 * d.condyle_d, z=cond_h,
                lat_dz=lat_dz)
    z_shaft0 = 2.4 * cond_h                           # shaft sections start above condyles
    z_shaft1 = neck_base[2] - 0.3 * r
    # (z, ML semi-axis, AP semi-axis, y offset) knots of the shaft sections.
    knots = np.array([
        [0.75 * cond_h, 0.95 * cw, 0.40 * d.condyle_d, 0.05 * d.condyle_d],
        [1.5 * cond_h, 0.85 * cw, 0.42 * d.condyle_d, 0.0],
        [z_shaft0, 1.6 * r, 1.25 * r, 0.0],
        [z_shaft0 + 0.12 * L, 1.05 * r, r, 0.0],
        [0.5 * L, r, 0.95 * r, 0.0],
        [z_shaft1 - 0.15 * L, 1.05 * r, r, 0.0],
        [z_shaft1 - 0.05 * L, 1.25 * r, 1.1 * r, 0.0],
        [z_shaft1, 1.55 * r, 1.2 * r, 0.0],
    ])
    gt = dict(c=np.array([0.9 * r + 4, -0.35 * r, neck_base[2] + 0.5 * d.neck_r]),
              ax=(0.55 * r + 4, 0.75 * r + 2, 1.1 * d.neck_r + 10))
    lt = dict(c=np.array([-0.85 * r, -0.55 * r, neck_base[2] - 2.6 * d.neck_r]),
              ax=(0.45 * r, 0.4 * r, 0.7 * d.neck_r))
    trochlea = dict(c=np.array([0.0, 0.22 * d.condyle_d, 1.55 * cond_h]),
                    ax=(0.85 * cw, 0.22 * d.condyle_d, 0.7 * cond_h))
    return dict(L=L, n=n, neck_dir=neck_dir, head_c=head_c, neck_base=neck_base, knots=knots,
                cond=cond, cond_x=cond_x, gt=gt, lt=lt, trochlea=trochlea,
                z_shaft0=z_shaft0, z_shaft1=z_shaft1)


def _bow_y(z, d: _Dims, g) -> np.ndarray:
    z0, z1 = g["z_shaft0"], g["z_shaft1"]
    t = np.clip((np.asarray(z) - z0) / (z1 - z0), 0.0, 1.0)
    return d.bow * np.sin(np.pi * t)


def _femur_manifold(d: _Dims, g: dict, inset: float) -> mf.Manifold:
    """Union of the femur's parts, every part shrunk by ``inset`` mm."""
    n = g["n"]
    ex, ey, ez = np.eye(3)
    parts = []
    # Shaft and metaphyses: lofts between elliptic sections, dense along z.
    k = g["knots"]
    zs = np.concatenate([np.linspace(k[i, 0], k[i + 1, 0], 4, endpoint=False)
                         for i in range(len(k) - 1)] + [[k[-1, 0]]])
    zs[0] += inset      # the inset loft's flat ends stay off the outer loft's ends
    zs[-1] -= inset
    a = np.interp(zs, k[:, 0], k[:, 1]) - inset
    b = np.interp(zs, k[:, 0], k[:, 2]) - inset
    yoff = np.interp(zs, k[:, 0], k[:, 3]) + _bow_y(zs, d, g)
    rings = [_ring((0.0, yo, z), ex, ey, aa, bb, n)
             for z, aa, bb, yo in zip(zs, a, b, yoff, strict=True)]
    parts += _loft(rings)
    # Neck: from inside the proximal shaft to the head, slightly narrowing.
    nd = g["neck_dir"]
    e1 = np.cross(nd, ey)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nd, e1)
    nb = g["neck_base"]
    top = rings[-1]
    neck0 = _ring(nb, e1, e2, 1.25 * d.neck_r - inset, 1.0 * d.neck_r - inset, n)
    neck1 = _ring(nb + 0.75 * d.neck_len * nd, e1, e2, 0.95 * d.neck_r - inset,
                  0.85 * d.neck_r - inset, n)
    parts.append(mf.Manifold.hull_points(np.vstack([top, neck0])))
    parts.append(mf.Manifold.hull_points(np.vstack([neck0, neck1])))
    parts.append(mf.Manifold.sphere(d.head_r - inset, n).translate(tuple(g["head_c"])))
    # Trochanters.
    for t in (g["gt"], g["lt"]):
        parts.append(_ellipsoid(t["c"], np.asarray(t["ax"]) - inset, n))
    gt_base = _ring(g["gt"]["c"] - np.array([0, 0, 0.6 * g["gt"]["ax"][2]]), ex, ey,
                    0.8 * g["gt"]["ax"][0] - inset, 0.8 * g["gt"]["ax"][1] - inset, n)
    parts.append(mf.Manifold.hull_points(np.vstack([rings[-4], gt_base])))
    # Condyles and the trochlear bridge.
    c = g["cond"]
    for sx in (-1.0, 1.0):
        z = c["z"] + (c["lat_dz"] if sx > 0 else 0.0)
        parts.append(_ellipsoid((sx * g["cond_x"], c["y"], z), np.asarray(c["ax"]) - inset, n))
    parts.append(_ellipsoid(g["trochlea"]["c"], np.asarray(g["trochlea"]["ax"]) - inset, n))
    return mf.Manifold.batch_boolean(parts, mf.OpType.Add)


def _canal_manifold(d: _Dims, g: dict) -> mf.Manifold:
    n = g["n"]
    ex, ey, _ = np.eye(3)
    r_in = d.shaft_r - d.cortex
    z0 = g["z_shaft0"] + 0.08 * d.L
    z1 = g["z_shaft1"] - 0.12 * d.L
    zs = np.linspace(z0, z1, 24)
    t = (zs - z0) / (z1 - z0)
    # Full radius in the middle, rounded off over the last 12 % at each end.
    taper = np.sqrt(np.clip(1 - (np.maximum(0, np.abs(t - 0.5) - 0.38) / 0.12) ** 2, 0.05, 1))
    rings = [_ring((0.0, _bow_y(z, d, g), z), ex, ey, 1.05 * r_in * s, r_in * s, n)
             for z, s in zip(zs, taper, strict=True)]
    return mf.Manifold.batch_boolean(_loft(rings), mf.OpType.Add)


#: the step (mm) by which a pin that reaches out of the procedural femur is moved along its
#: axis into the bone (:func:`_seat_pin`)
PIN_SEAT_STEP_MM = 0.5


def _seat_pin(name: str, center, axis, femur: trimesh.Trimesh, spec: PhantomSpec, n: int):
    """``(center, mesh)`` of a procedural femur's pin, moved along its axis until the whole
    pin lies in the femur (as a surgeon implants it), or where it was when it already does.
    A held-out review (2026-11-27) found a 20 mm pin reaching 2.4 mm out of a small femur's
    trochanter, its outer part attenuated as if it were bone. Raises ``ValueError`` naming
    the pin's fields when no place along the axis holds it."""
    c0 = np.asarray(center, dtype=np.float64)
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    mesh = _pin_mesh(c0, a, spec.pin_diameter_mm, spec.pin_length_mm, n)
    steps = int(np.ceil(spec.pin_length_mm / PIN_SEAT_STEP_MM))
    for k in [0, *(s * j for j in range(1, steps + 1) for s in (-1, 1))]:
        shift = k * PIN_SEAT_STEP_MM * a
        if femur.contains(mesh.vertices + shift).all():
            mesh.apply_translation(shift)
            return c0 + shift, mesh
    raise ValueError(
        f"the {name} pin ({spec.pin_diameter_mm:g} mm x {spec.pin_length_mm:g} mm) does not "
        "fit inside the femur anywhere along its axis; make pin_diameter_mm or pin_length_mm "
        "smaller, or the femur larger")


def _pin_mesh(center, axis, diameter, length, n) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=diameter / 2, height=length, sections=max(16, n // 2))
    z = np.array([0.0, 0.0, 1.0])
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    T = trimesh.geometry.align_vectors(z, a)
    T[:3, 3] = center
    m.apply_transform(T)
    return m


def _soft_tissue(bounds_lo, bounds_hi, spec: PhantomSpec, g: dict | None, n: int,
                 scales: tuple[float, float] = (1.0, 1.0)):
    """A thigh: lofts of ellipses from below the knee to above the hip, around the bone;
    ``scales``: factors (at least 1) of the knee's and the thigh's radii, by which a femur
    drawn wider than the spec's (``shape_variation``) widens them (:func:`_tissue_scales`;
    in the default thigh such a femur reached out of it)."""
    ex, ey, _ = np.eye(3)
    zlo, zhi = bounds_lo[2] - 40.0, bounds_hi[2] + 30.0
    if g is None:
        c = (bounds_lo + bounds_hi) / 2
        half = (bounds_hi - bounds_lo) / 2 + spec.mesh_margin_mm
        rings = [_ring((c[0], c[1], z), ex, ey, half[0], half[1], n) for z in (zlo, zhi)]
    else:
        zs = np.linspace(zlo, zhi, 8)
        t = (zs - zlo) / (zhi - zlo)
        head_x = g["head_c"][0]
        cx = 0.55 * head_x * t ** 1.5
        knee, thigh = spec.knee_radius_mm * scales[0], spec.thigh_radius_mm * scales[1]
        ra = knee + (thigh - knee) * t
        rb = 0.9 * ra
        rings = [_ring((x, 0.0, z), ex, ey, a, b, n)
                 for x, z, a, b in zip(cx, zs, ra, rb, strict=True)]
    # the lower leg and the hip go on beyond the thigh's ends, as wide as its end rings
    if spec.leg_mm > 0:
        rings.insert(0, rings[0] - [0.0, 0.0, spec.leg_mm])
    if spec.hip_mm > 0:
        rings.append(rings[-1] + [0.0, 0.0, spec.hip_mm])
    return mf.Manifold.batch_boolean(_loft(rings), mf.OpType.Add)


def _tissue_scales(spec: PhantomSpec, d: _Dims) -> tuple[float, float]:
    """How much wider than the spec's the drawn femur is at the knee (its condyles) and at
    the hip (its widths' common scale), at least 1 each: the soft tissue's scales."""
    knee = max(1.0, d.condyle_w / spec.condyle_width_mm, d.condyle_d / spec.condyle_depth_mm)
    return knee, max(1.0, d.width_scale)


def _check_closed(mesh: trimesh.Trimesh, what: str) -> None:
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume):
        if not mesh.is_watertight:
            mend = ("; its edges are not each shared by two faces: close its holes "
                    "(trimesh.repair.fill_holes, or a mesh editor)")
        elif not mesh.is_winding_consistent:
            mend = ("; its faces' winding disagrees: trimesh.repair.fix_winding(mesh) and "
                    "fix_normals(mesh) mend that, if it is otherwise closed")
        else:
            mend = ""
        raise ValueError(
            f"{what} is not a closed manifold solid (watertight={mesh.is_watertight}, "
            f"winding consistent={mesh.is_winding_consistent}, volume={mesh.is_volume})"
            f"{mend}")


#: a user mesh whose surface moves by less than this (mm RMS) under some turn of 30-330 deg
#: about its long axis is refused (:func:`_axial_symmetry`: a 32-sided cylinder or a capsule
#: 0; the procedural femur and four random ones 4.1-5.6 mm, their head and condyles off the
#: shaft's axis)
MIN_AXIAL_ASYMMETRY_MM = 1.0
#: how far (mm) a user mesh's lowest point may lie from z = 0, where the ct frame's
#: convention puts the condyles' lowest point (a mesh in a scanner's coordinates, 1000 mm
#: up, was refused only at its first view, as a femur outside the field), and its bounding
#: box's centre from the z axis (one 100 mm off in x ran with warnings to re-aim the views)
MAX_MESH_BASE_MM = 50.0
#: :func:`_axial_symmetry` of the user meshes read, by (file, modification time, size)
_SYMMETRY: dict = {}


def _axial_symmetry(mesh: trimesh.Trimesh, n_points: int = 300, least_deg: float = 30.0,
                    step_deg: float = 10.0) -> tuple[float, float]:
    """The turn (deg) about the mesh's long axis (its axis of least inertia, through its
    centre of mass) that moves its surface least, and by how much: the RMS distance (mm) of
    ``n_points`` surface points, turned, to the surface; turns from ``least_deg`` to
    ``360 - least_deg`` in steps of ``step_deg`` (a femur turned by 10 deg moves only 1.7 mm
    RMS, most of it shaft; by 30 deg and more, several mm). Seeded: the same mesh gives the
    same figures."""
    pts, _ = trimesh.sample.sample_surface(mesh, n_points, seed=0)
    vals, vecs = np.linalg.eigh(mesh.moment_inertia)
    axis = vecs[:, int(np.argmin(vals))]        # least inertia: the long axis
    c = mesh.center_mass
    q = trimesh.proximity.ProximityQuery(mesh)
    best = (0.0, np.inf)
    for deg in np.arange(least_deg, 360.0 - least_deg + step_deg / 2, step_deg):
        R = trimesh.transformations.rotation_matrix(np.radians(deg), axis, c)
        turned = pts @ R[:3, :3].T + R[:3, 3]
        rms = float(np.sqrt(np.mean(q.signed_distance(turned) ** 2)))
        if rms < best[1]:
            best = (float(deg), rms)
    return best


#: the most triangles a user mesh may have: a femur's 60,000 mm^2 of surface in 500,000
#: triangles has edges of about 0.5 mm, finer than a CT's voxels resolve; a held-out review's
#: mesh of 3.67 million hung a run (over 300 s, 2.1 GB, in the symmetry test's decimation,
#: deaf to Ctrl-C) and one of 0.96 million took 84 s against 6
MAX_USER_FACES = 500_000

#: a user mesh of more faces is tested for symmetry on a copy decimated to this many
#: (:func:`_symmetry_proxy`)
SYMMETRY_MAX_FACES = 20_000


def _symmetry_proxy(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh :func:`_axial_symmetry` is measured on: ``mesh`` itself up to
    :data:`SYMMETRY_MAX_FACES` faces, else a copy decimated to that many (quadric
    decimation, fast_simplification through trimesh), or the mesh where decimation
    fails. The closest-point queries grow with the faces: a femur of 222,000 faces (the
    procedural one subdivided twice, as fine as a CT segmentation's) took 11.9 s (3.5 s
    decimated, 1.4 s of it the decimation), its figure 4.83 mm RMS exact and 4.46 mm on
    the copy; a capsule of 131,000 faces 0.0003 mm on the copy. The test is a gate at
    :data:`MIN_AXIAL_ASYMMETRY_MM`, which those differences do not cross
    (tests/testbed/test_phantom.py compares the two on subdivided random femurs)."""
    if len(mesh.faces) <= SYMMETRY_MAX_FACES:
        return mesh
    try:
        proxy = mesh.simplify_quadric_decimation(face_count=SYMMETRY_MAX_FACES)
        # decimation leaves degenerate triangles, whose closest points are NaN
        proxy.update_faces(proxy.nondegenerate_faces())
        proxy.remove_unreferenced_vertices()
    except Exception:  # noqa: BLE001 - any failure of the library: measure the mesh itself
        return mesh
    return proxy if len(proxy.faces) else mesh


def _binary_stl_mismatch(path: Path) -> str:
    """For a binary STL whose header's triangle count disagrees with the file's size (a
    binary STL is an 80-byte header, a uint32 count and 50 bytes per triangle), what to
    add to the message; '' otherwise."""
    if path.suffix.lower() != ".stl":
        return ""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(84)
    if len(head) < 84 or head[:5].lower() == b"solid":
        return ""
    count = int.from_bytes(head[80:84], "little")
    if size == 84 + 50 * count:
        return ""
    return (f" (it looks like a binary STL whose header counts {count:,} triangles, where "
            f"its {size:,} bytes hold {max(size - 84, 0) / 50:,.1f} at 50 bytes each after an "
            "84-byte header: the file was cut short or its header's count is wrong)")


def _user_phantom(spec: PhantomSpec) -> Phantom:
    path = Path(spec.mesh_path)
    if not path.is_file():
        what = ("is a folder" if path.is_dir() else
                "is not a regular file (a device, pipe or socket)" if path.exists() else
                "no such file")
        raise ValueError(f"phantom.mesh_path: {str(path)!r} {what}; expected a mesh file "
                         "(STL, PLY, OBJ, ...)")
    why = _binary_stl_mismatch(path)
    if why:     # trimesh then parses it as ASCII (and needs charset_normalizer to say so)
        raise ValueError(f"phantom.mesh_path: cannot read {str(path)!r} as a mesh{why}")
    try:
        mesh = trimesh.load_mesh(path, process=False)   # NaN vertices seen, not dropped
    except Exception as exc:  # trimesh raises many kinds on unreadable files
        raise ValueError(
            f"phantom.mesh_path: cannot read {str(path)!r} as a mesh ({exc})"
        ) from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"phantom.mesh_path: {str(path)!r} holds no single triangle mesh")
    if len(mesh.faces) == 0:
        raise ValueError(f"phantom.mesh_path: {str(path)!r} holds no triangles (an empty file, "
                         "or points without faces); give a closed triangle surface")
    if len(mesh.faces) > MAX_USER_FACES:
        raise ValueError(
            f"phantom.mesh_path: the mesh in {str(path)!r} has {len(mesh.faces):,} triangles; "
            f"at most {MAX_USER_FACES:,} (finer than a CT's voxels resolve): decimate it "
            "first (e.g. trimesh's mesh.simplify_quadric_decimation(face_count=200_000))")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError(f"phantom.mesh_path: the mesh in {str(path)!r} has vertices with NaN "
                         "or infinite coordinates")
    mesh.process()                                      # merge the vertices (STL), as before
    shells = mesh.body_count
    if shells > 1:
        raise ValueError(f"phantom.mesh_path: the mesh in {str(path)!r} is {shells} separate "
                         "surfaces; a femur is one closed surface (join or remove the others)")
    if not mesh.is_watertight:
        raise ValueError(f"phantom.mesh_path: the mesh in {str(path)!r} is not watertight "
                         "(it has holes or open edges); give a closed surface")
    if mesh.is_winding_consistent and mesh.volume < 0:
        raise ValueError(f"phantom.mesh_path: the mesh in {str(path)!r} is inside out (its "
                         "triangles face inwards: negative volume); reverse their winding "
                         "(e.g. trimesh's mesh.invert())")
    _check_closed(mesh, f"phantom.mesh_path {str(path)!r}")
    ext = mesh.extents
    if ext.max() < 50.0:
        raise ValueError(
            f"phantom.mesh_path: the mesh in {str(path)!r} is {ext.max():.3g} units long; "
            "its units must be millimetres (an adult femur is 300-600 mm; a mesh in metres "
            "or centimetres needs scaling)")
    if ext[2] < max(ext[0], ext[1]):
        raise ValueError(
            f"phantom.mesh_path: the femur in {str(path)!r} must lie along the ct frame's z "
            "axis (proximal up, the lowest point of the condyles near z = 0, mm); its extents "
            f"are x {ext[0]:.0f}, y {ext[1]:.0f}, z {ext[2]:.0f} mm")
    centre_xy = 0.5 * (mesh.bounds[0, :2] + mesh.bounds[1, :2])
    z0 = float(mesh.bounds[0, 2])
    off_xy = float(np.hypot(*centre_xy)) > MAX_MESH_BASE_MM
    off_z = abs(z0) > MAX_MESH_BASE_MM
    if off_xy or off_z:   # the whole move in one message (a review: z came on the next run)
        dx, dy = -centre_xy if off_xy else (0.0, 0.0)
        where = [f"its bounding box's centre at x = {centre_xy[0]:.0f}, y = "
                 f"{centre_xy[1]:.0f} mm"] if off_xy else []
        where += [f"its lowest point at z = {z0:.0f} mm"] if off_z else []
        raise ValueError(
            f"phantom.mesh_path: the femur in {str(path)!r} has {' and '.join(where)}; the ct "
            f"frame puts the femur along its z axis (its bounding box's centre within "
            f"{MAX_MESH_BASE_MM:g} mm of it) with the condyles' lowest point near z = 0 (within "
            f"{MAX_MESH_BASE_MM:g} mm): the scene's views and [patient] position_mm place that "
            "frame, and a mesh in a CT scanner's coordinates is not in it: translate the mesh "
            f"and mesh_pins_mm by ({dx:.0f}, {dy:.0f}, {-z0 if off_z else 0.0:.0f}) mm")
    lo, hi = field_bounds("length_mm")
    if not lo <= ext[2] <= hi:
        raise ValueError(
            f"phantom.mesh_path: the femur in {str(path)!r} is {ext[2]:.0f} mm long along z; "
            f"an adult femur is {lo:.0f}-{hi:.0f} mm (the range of phantom.length_mm): is the "
            "mesh in millimetres, and is it a whole femur?")
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size)
    if key not in _SYMMETRY:          # ~1.5 s; a run reads its mesh up to three times
        _SYMMETRY[key] = _axial_symmetry(_symmetry_proxy(mesh))
    turn, moved = _SYMMETRY[key]
    if moved < MIN_AXIAL_ASYMMETRY_MM:
        raise ValueError(
            f"phantom.mesh_path: the mesh in {str(path)!r} is nearly symmetric about its long "
            f"axis (turned by {turn:.0f} deg about it, its surface moves by {moved:.2f} mm "
            f"RMS, under {MIN_AXIAL_ASYMMETRY_MM:g} mm): its X-ray outlines cannot fix that "
            "turn, so registering it tests nothing; a femur's head, neck, trochanters and "
            "condyles make it asymmetric")
    if spec.mesh_pins_mm is None:
        raise ValueError("phantom.mesh_pins_mm must give the pin centres (proximal, distal_1, "
                         "distal_2) for a user mesh")
    pins = {k: np.asarray(spec.mesh_pins_mm[k], dtype=np.float64) for k in PIN_NAMES}
    inside = mesh.contains(np.array([pins[k] for k in PIN_NAMES]))
    if not np.all(inside):
        bad = [k for k, ok in zip(PIN_NAMES, inside, strict=True) if not ok]
        raise ValueError(f"phantom.mesh_pins_mm: pins {bad} are not inside the user mesh")
    # the proximal pin in the upper half, the distal ones in the lower: a mesh turned head
    # down (with its pins) was registered with every label swapped and said nothing
    z_lo, z_hi = (float(v) for v in mesh.bounds[:, 2])
    mid = 0.5 * (z_lo + z_hi)
    wrong = [k for k in PIN_NAMES if (pins[k][2] < mid) == (k == "proximal")]
    if wrong:
        raise ValueError(
            f"phantom.mesh_pins_mm: pin(s) {wrong} lie in the wrong half of the femur (z "
            f"{z_lo:.0f} to {z_hi:.0f} mm; " + ", ".join(f"{k} at z = {pins[k][2]:.0f}"
                                                         for k in wrong)
            + "): the proximal pin goes in the upper half, the distal ones in the lower; is "
            "the mesh upside down (the ct frame puts the femoral head up), or are the pins' "
            "names swapped?")
    n = spec.segments
    pin_meshes = {k: _pin_mesh(p, (1.0, 0.0, 0.0), spec.pin_diameter_mm, spec.pin_length_mm, n)
                  for k, p in pins.items()}
    soft = _to_trimesh(_soft_tissue(mesh.bounds[0], mesh.bounds[1], spec, None, n))
    cancellous = _user_interior(mesh)
    pin_inside = {k: "femur" for k in PIN_NAMES}
    if cancellous is not None:
        # (until 2026-11-27 a crossing pin dropped the interior for the whole femur, without
        # a word: a review's wide femur with a pin 1.4 mm under its surface turned solid
        # cortical bone and lost its distal views' beads)
        nested = _nest_pins(cancellous, pin_meshes)
        cancellous, pin_inside = nested if nested is not None else (None, pin_inside)
    return Phantom(femur=mesh, canal=None, cancellous=cancellous, soft_tissue=soft, pins=pins,
                   pin_meshes=pin_meshes, pin_inside=pin_inside, side=spec.side,
                   landmarks={}, spec=spec)


def _nest_pins(cancellous: trimesh.Trimesh, pin_meshes: dict):
    """``(cancellous, pin_inside)``: each pin nested in the body it lies in, "cancellous"
    when the cancellous bone holds the whole pin, else "femur"; a pin across the cortex's
    inner surface is carved out of the cancellous bone, so that each part of it displaces
    the bone it lies in. None when the carving fails (the caller keeps its fallback)."""
    pin_inside, crossing = {}, []
    for k, pm in pin_meshes.items():
        held = cancellous.contains(np.asarray(pm.vertices))
        pin_inside[k] = "cancellous" if held.all() else "femur"
        if held.any() and not held.all():
            crossing.append(k)
    if not crossing:
        return cancellous, pin_inside
    carved = _carve(cancellous, [pin_meshes[k] for k in crossing])
    return None if carved is None else (carved, pin_inside)


def _carve(body: trimesh.Trimesh, tools: list[trimesh.Trimesh]) -> trimesh.Trimesh | None:
    """``body`` less the union of ``tools`` (manifold3d), or None when the result is not a
    closed mesh (the caller then drops the interior, as before)."""
    def to_mf(m):
        return mf.Manifold(mf.Mesh(vert_properties=np.asarray(m.vertices, dtype=np.float32),
                                   tri_verts=np.asarray(m.faces, dtype=np.uint32)))

    try:
        out = to_mf(body) - mf.Manifold.batch_boolean([to_mf(t) for t in tools],
                                                       mf.OpType.Add)
        mesh = _to_trimesh(out)
    except (ValueError, RuntimeError, TypeError):   # manifold3d cannot read a mesh
        return None
    return mesh if len(mesh.faces) and mesh.is_watertight and mesh.volume > 0 else None


#: a user femur's cortex (mm): the voxels deeper than this under its surface are cancellous
#: bone (:func:`_user_interior`); their surface lies about half a voxel out of them, so the
#: cortex measures 2.2 mm (median; 1.2-3.3 mm from the 5th to the 95th percentile, 0.4 mm
#: at least, on the procedural femur as a mesh), as the procedural femur's ends, 2.5 mm
#: (``end_cortex_mm``; its shaft 6.5 mm about a marrow canal, which a user mesh lacks)
USER_CORTEX_MM = 3.0
#: the voxel (mm) of the user femur's interior
USER_INTERIOR_PITCH_MM = 2.5


def _user_interior(mesh: trimesh.Trimesh) -> trimesh.Trimesh | None:
    """The cancellous bone of a user femur: the voxels (:data:`USER_INTERIOR_PITCH_MM`)
    more than :data:`USER_CORTEX_MM` inside its surface (deeper by half a voxel, then a
    voxel, where the first surface reaches out of the mesh), the mesh's voxels from the CT
    scanner's own section rasteriser (:class:`testbed.ct._MeshSlicer`, a voxel inside when
    more than half of its row is), their surface by marching cubes; None when no surface is
    closed and wholly inside the mesh (the femur is then solid cortical bone, as before
    2026-11-26). 0.1-0.4 s.

    A user mesh was solid cortical bone: a review's wide femurs (condyles of 89 mm)
    attenuated so much that their distal views' validation beads were lost and 7 of 8 such
    runs were refused, where the same shapes built procedurally, cancellous within a cortex,
    were not."""
    from scipy import ndimage
    from skimage import measure

    from testbed.ct import _MeshSlicer

    h = USER_INTERIOR_PITCH_MM
    lo, hi = mesh.bounds
    xs = np.arange(lo[0] + 0.5 * h, hi[0], h)
    ys = np.arange(lo[1] + 0.5 * h, hi[1], h)
    zs = np.arange(lo[2] + 0.5 * h, hi[2], h)
    if min(len(xs), len(ys), len(zs)) < 3:
        return None
    slicer = _MeshSlicer(mesh)
    solid = np.stack([slicer.coverage(float(z), ys, float(xs[0]), h, len(xs)).T > 0.5
                      for z in zs], axis=2)
    # depth below the surface (padded: the grid's border is outside the mesh); the voxels
    # and the marching cubes each place the surface within about half a voxel, so a deeper
    # cut is tried where the first reaches out of the mesh
    depth = ndimage.distance_transform_edt(np.pad(solid, 1), sampling=h)[1:-1, 1:-1, 1:-1]
    for cortex in (USER_CORTEX_MM, USER_CORTEX_MM + 0.5 * h, USER_CORTEX_MM + h):
        deep = depth > cortex
        if not deep.any():
            return None
        v, f, _, _ = measure.marching_cubes(np.pad(deep, 1).astype(np.float32), 0.5,
                                            spacing=(h, h, h))
        inner = trimesh.Trimesh(v - h + np.array([xs[0], ys[0], zs[0]]), f, process=True)
        if inner.volume < 0:
            inner.invert()
        if inner.is_watertight and inner.is_volume \
                and mesh.contains(np.asarray(inner.vertices)).all():
            return inner
    return None


def make_phantom(spec: PhantomSpec | None = None, rng=None) -> Phantom:
    """Build the phantom in the ct frame.

    Parameters
    ----------
    spec : the ``[phantom]`` section (default: the mean right femur).
    rng : unused by the procedural femur, whose variation is drawn from ``spec.shape_seed``
        (the simulator sets it per case, see :class:`PhantomSpec`) so that the spec fixes the
        patient; accepted for a uniform signature.

    Returns
    -------
    Phantom

    Raises
    ------
    ValueError : the user mesh is missing, unreadable, not watertight, or its pins are not
        inside it.
    """
    spec = PhantomSpec() if spec is None else spec
    if spec.mesh_path is not None:
        return _user_phantom(spec)
    key = _build_key(spec)
    if key not in _BUILT:
        if len(_BUILT) >= 4:
            _BUILT.pop(next(iter(_BUILT)))
        _BUILT[key] = _procedural_phantom(key)
    return _copied(_BUILT[key], spec)


#: the last few procedural phantoms by their geometry's spec (:func:`_build_key`; building
#: one takes 0.5-1 s of CSG on a 2-core machine; a study trial asks for its femur up to
#: three times), handed out as copies
_BUILT: dict = {}


def _build_key(spec: PhantomSpec) -> PhantomSpec:
    """The spec that fixes the procedural phantom's geometry: ``spec`` itself, with
    ``shape_seed`` set to 0 when neither ``shape_variation`` nor ``surface_detail_mm``
    draws from it (the capture-range study's random femurs have their variation 0, and the
    simulator gives every case its own seed, so their femur was built twice a trial). The
    surface detail is drawn from the seed: with detail the seed stays (it was set to 0 too,
    and every case and seed got the same detail)."""
    if spec.shape_variation == 0 and spec.surface_detail_mm == 0 and spec.shape_seed != 0:
        return spec.model_copy(update={"shape_seed": 0})
    return spec


def _copied(ph: Phantom, spec: PhantomSpec | None = None) -> Phantom:
    """``ph`` with its own copies of every mesh and array (callers may change them), and
    ``spec`` as its spec when given."""
    return replace(
        ph, spec=ph.spec if spec is None else spec, femur=ph.femur.copy(),
        soft_tissue=ph.soft_tissue.copy(),
        canal=None if ph.canal is None else ph.canal.copy(),
        cancellous=None if ph.cancellous is None else ph.cancellous.copy(),
        pins={k: v.copy() for k, v in ph.pins.items()},
        pin_meshes={k: m.copy() for k, m in ph.pin_meshes.items()},
        pin_inside=dict(ph.pin_inside),
        landmarks={k: v.copy() for k, v in ph.landmarks.items()})


def _check_soft_tissue_holds(femur: trimesh.Trimesh, soft: trimesh.Trimesh, spec, d) -> None:
    """ValueError naming the fields when the femur reaches outside its soft tissue (a
    thigh narrower than the bone: a held-out review's scene loaded, then failed in the
    CT's contouring with no field named)."""
    outside = ~soft.contains(femur.vertices)
    if not outside.any():
        return
    z = femur.vertices[outside, 2]
    raise ValueError(
        f"phantom: the femur reaches outside the thigh's soft tissue ({int(outside.sum())} of "
        f"{len(outside)} surface points, at z = {z.min():.0f} to {z.max():.0f} mm): "
        f"thigh_radius_mm ({spec.thigh_radius_mm:g}) and knee_radius_mm "
        f"({spec.knee_radius_mm:g}) must exceed the bone's half-widths (shaft "
        f"{d.shaft_r:.0f} mm, condyles {d.condyle_w / 2:.0f} x {d.condyle_d / 2:.0f} mm, head "
        f"{d.head_r:.0f} mm, after shape_variation)")


#: the salt of the surface detail's random stream (after the shape's draws of shape_seed)
_DETAIL_SALT = 7


def _with_detail(femur: trimesh.Trimesh, spec: PhantomSpec, d) -> trimesh.Trimesh:
    """The outer bone surface with ``spec.surface_detail_mm`` RMS of detail along its normals
    (see :class:`PhantomSpec`), or ``femur`` itself when it is 0. The displacement is clipped
    at 2.5 RMS, and inward also to 0.5 mm short of the ends' cortex, so that the surface
    stays outside the cancellous bone it holds."""
    amp = float(spec.surface_detail_mm)
    if amp <= 0:
        return femur
    lam = float(spec.surface_detail_wavelength_mm)
    v, f = trimesh.remesh.subdivide_to_size(femur.vertices, femur.faces, max_edge=lam / 6.0)
    mesh = trimesh.Trimesh(v, f, process=True)
    rng = np.random.default_rng([spec.shape_seed, _DETAIL_SALT])
    k = 24
    dirs = rng.normal(size=(k, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    wave = dirs * (2.0 * np.pi / (rng.uniform(0.6, 1.6, k) * lam))[:, None]
    phase = rng.uniform(0.0, 2.0 * np.pi, k)
    field = np.sin(mesh.vertices @ wave.T + phase).sum(axis=1)
    field *= amp / np.sqrt(np.mean(field ** 2))
    field = np.clip(field, -min(2.5 * amp, max(d.end_cortex - 0.5, 0.0)), 2.5 * amp)
    return trimesh.Trimesh(mesh.vertices + field[:, None] * mesh.vertex_normals, mesh.faces,
                           process=False)


def _csg_meshes(spec: PhantomSpec, d, g: dict, mirror: bool) -> tuple[trimesh.Trimesh, ...]:
    """The procedural femur's CSG: the outer bone (before any surface detail), the soft
    tissue, the canal and the cancellous bone, from the disk cache when it holds them
    (:func:`_cache_file`; the booleans take 0.5-0.6 s of CPU a phantom, the cached meshes
    about 15 ms to read) and built (:func:`_build_csg_meshes`) and stored otherwise."""
    import zipfile

    path = _cache_file(spec)
    if path is not None and path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                return tuple(trimesh.Trimesh(z[f"v{i}"], z[f"f{i}"], process=False)
                             for i in range(4))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            pass        # unreadable (e.g. a write cut short): built again and replaced
    meshes = _build_csg_meshes(spec, d, g, mirror)
    if path is not None:
        _cache_store(path, meshes)
    return meshes


def _build_csg_meshes(spec: PhantomSpec, d, g: dict, mirror: bool
                      ) -> tuple[trimesh.Trimesh, ...]:
    """The reference of :func:`_csg_meshes`: the booleans evaluated (manifold3d)."""
    femur_m = _femur_manifold(d, g, 0.0)
    inner = _femur_manifold(d, g, d.end_cortex)
    canal_m = _canal_manifold(d, g)
    lo_cut = g["z_shaft0"] + 0.12 * d.L
    hi_cut = g["z_shaft1"] - 0.17 * d.L
    big = 4 * d.L
    slab_lo = mf.Manifold.cube((big, big, lo_cut + big), True).translate(
        (0.0, 0.0, (lo_cut - big) / 2))
    slab_hi = mf.Manifold.cube((big, big, big), True).translate((0.0, 0.0, hi_cut + big / 2))
    canc_m = (inner ^ (slab_lo + slab_hi)) - canal_m
    bb = np.asarray(femur_m.bounding_box())
    soft_m = _soft_tissue(bb[:3], bb[3:], spec, g, d.n, _tissue_scales(spec, d))
    if mirror:
        femur_m, canc_m, canal_m, soft_m = (m.mirror((1.0, 0.0, 0.0))
                                            for m in (femur_m, canc_m, canal_m, soft_m))
    return tuple(_to_trimesh(m) for m in (femur_m, soft_m, canal_m, canc_m))


#: the environment variable naming the folder of the phantom cache; empty: no cache. Unset:
#: ``testbed/__pycache__/phantoms`` beside the code, as numba keeps its compiled kernels
CACHE_ENV = "TESTBED_CACHE_DIR"
#: the most phantoms the cache keeps (about 1.2 MB each; the oldest go first)
CACHE_MAX_FILES = 64
def _cache_file(spec: PhantomSpec) -> Path | None:
    """Where the CSG meshes of ``spec`` are cached: a file named by the SHA-256 of the spec
    (as :func:`_build_key` gives it), this module's source and the versions of manifold3d,
    trimesh and numpy; None when the cache is off."""
    import hashlib
    import os

    root = os.environ.get(CACHE_ENV)
    if root is None:
        root = str(Path(__file__).parent / "__pycache__" / "phantoms")
    if not root:
        return None
    key = hashlib.sha256((_cache_salt() + spec.model_dump_json()).encode()).hexdigest()
    return Path(root) / f"csg-{key[:32]}.npz"


@functools.cache
def _cache_salt() -> str:
    """What, besides the spec, fixes the meshes: this module's code and the versions of the
    libraries that evaluate and process them (a SHA-256, hex)."""
    import hashlib
    from importlib import metadata

    h = hashlib.sha256(Path(__file__).read_bytes())
    for lib in ("manifold3d", "trimesh", "numpy"):
        h.update(f"{lib} {metadata.version(lib)}".encode())
    return h.hexdigest()


def _cache_store(path: Path, meshes) -> None:
    """Write the meshes to ``path`` (a temporary file renamed into place: a reader never
    sees half a file) and keep the folder to :data:`CACHE_MAX_FILES`; a cache that cannot
    be written is no error."""
    import os
    import tempfile

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".csg-", suffix=".npz", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **{f"{k}{i}": a for i, m in enumerate(meshes)
                               for k, a in (("v", m.vertices), ("f", m.faces))})
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        kept = sorted(path.parent.glob("csg-*.npz"), key=lambda p: p.stat().st_mtime)
        for old in kept[:-CACHE_MAX_FILES]:
            old.unlink(missing_ok=True)
    except OSError:
        pass


def _procedural_phantom(spec: PhantomSpec) -> Phantom:
    d = _resolve(spec)
    g = _geometry(d)
    mirror = spec.side == "left"
    femur0, soft, canal, canc = _csg_meshes(spec, d, g, mirror)
    femur = _with_detail(femur0, spec, d)
    _check_soft_tissue_holds(femur, soft, spec, d)
    sx = -1.0 if mirror else 1.0
    flip = np.array([sx, 1.0, 1.0])
    c = g["cond"]
    gt = g["gt"]["c"]
    pins = {
        "proximal": np.array([gt[0] + 1.0, gt[1], gt[2] - 0.15 * g["gt"]["ax"][2]]) * flip,
        "distal_1": np.array([-g["cond_x"], c["y"] + 2.0, 0.9 * c["z"]]) * flip,
        "distal_2": np.array([g["cond_x"], c["y"] + 2.0, 0.9 * c["z"] + c["lat_dz"]]) * flip,
    }
    axes = {"proximal": (1.0, 0.0, 0.0), "distal_1": (0.0, 1.0, 0.0),
            "distal_2": (0.0, 1.0, 0.0)}
    pin_inside = {k: "cancellous" for k in PIN_NAMES}
    pin_meshes = {}
    for k in PIN_NAMES:
        pins[k], pin_meshes[k] = _seat_pin(k, pins[k], axes[k], femur, spec, d.n)
    # a wide or long pin, a thick end cortex: a pin across the cortex's inner surface
    nested = _nest_pins(canc, pin_meshes) if canc is not None else None
    if nested is not None:
        canc, pin_inside = nested
    gl = {"head_center": g["head_c"], "neck_base": g["neck_base"],
          "greater_trochanter": gt, "lesser_trochanter": g["lt"]["c"],
          "medial_condyle": np.array([-g["cond_x"], c["y"], c["z"]]),
          "lateral_condyle": np.array([g["cond_x"], c["y"], c["z"] + c["lat_dz"]])}
    landmarks = {k: np.asarray(v, dtype=np.float64) * flip for k, v in gl.items()}
    return Phantom(femur=femur, canal=canal, cancellous=canc, soft_tissue=soft, pins=pins,
                   pin_meshes=pin_meshes, pin_inside=pin_inside,
                   side=spec.side, landmarks=landmarks, spec=spec)
