"""OR instruments that occlude the anatomy in fluoroscopic views: steel bodies.

Each instrument is one closed mesh (its parts united with manifold3d), built in its own frame
and placed in the robot frame by ``position_mm`` (mm) and ``rotation_deg`` (extrinsic x-y-z
Euler angles, deg). Kinds:

``"retractor"``  a Hohmann-type retractor: a 20 mm wide, 2 mm thick blade, 90 mm long, with a
                 bent tip and a 100 mm handle, along the instrument's +x axis.
``"clamp"``      a surgical clamp: two crossed 4 mm jaws 110 mm long and two finger rings,
                 along +x.
"""

from __future__ import annotations

import re
from typing import Literal

import numpy as np
import trimesh
from pydantic import field_validator
from scipy.spatial.transform import Rotation

from reglib.geometry import RigidTransform
from testbed.bodies import Body
from testbed.materials import material
from testbed.spec import NAME_MAX, Angles3, Spec, Vec3

__all__ = ["InstrumentSpec", "instrument_mesh", "make_instrument", "scene_instruments"]


#: names of the bodies the world builds itself (testbed.world): an instrument cannot take them
RESERVED_NAMES = frozenset({"soft_tissue", "femur", "cancellous", "canal", "pin_proximal",
                            "pin_distal_1", "pin_distal_2", "foam", "table"})


def file_key(name: str) -> str:
    """A body's name as a dataset's file names carry it (``meshes/robot_<key>.ply``): every
    character but ASCII letters, digits, ``_``, ``.`` and ``-`` replaced by ``_``. Two names
    whose keys differ only in case name one file on a case-insensitive disk."""
    return re.sub(r"[^A-Za-z0-9_.\-]", "_", name)


class InstrumentSpec(Spec):
    """``[[instruments]]``: one OR instrument (robot frame).

    ``name`` (unique among bodies); ``kind`` "retractor" or "clamp"; ``position_mm`` where
    the instrument's origin lies (robot frame); ``rotation_deg`` its orientation (extrinsic
    x-y-z Euler angles); ``material`` ("steel").
    """

    name: str = "retractor"
    kind: Literal["retractor", "clamp"] = "retractor"
    position_mm: Vec3 = (0.0, 0.0, 0.0)
    rotation_deg: Angles3 = (0.0, 0.0, 0.0)
    material: str = "steel"

    @field_validator("material")
    @classmethod
    def _known_material(cls, v: str) -> str:
        material(v)  # ValueError naming the unknown material and the known ones
        return v

    @field_validator("name")
    @classmethod
    def _not_reserved(cls, v: str) -> str:
        if v in RESERVED_NAMES:
            raise ValueError(f"{v!r} names one of the world's own bodies "
                             f"({', '.join(sorted(RESERVED_NAMES))}); choose another name")
        if not v.strip() or len(v) > NAME_MAX:
            raise ValueError(f"an instrument's name has 1 to {NAME_MAX} characters, not all "
                             "spaces")
        return v

    def instrument2robot(self) -> RigidTransform:
        rot = Rotation.from_euler("xyz", self.rotation_deg, degrees=True)
        return RigidTransform.from_rotation(rot, self.position_mm)


def _box(extents, center, rot_deg_y: float = 0.0) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("y", rot_deg_y, degrees=True).as_matrix()
    T[:3, 3] = center
    return trimesh.creation.box(extents=extents, transform=T)


def _union(parts) -> trimesh.Trimesh:
    mesh = trimesh.boolean.union(parts, engine="manifold")
    if not mesh.is_watertight:
        raise RuntimeError("instrument mesh is not watertight after the union")
    return mesh


def instrument_mesh(kind: str) -> trimesh.Trimesh:
    """The closed mesh of an instrument kind in its own frame (mm)."""
    if kind == "retractor":
        blade = _box((90.0, 20.0, 2.0), (45.0, 0.0, 0.0))
        tip = _box((25.0, 14.0, 2.0), (95.0, 0.0, -8.0), rot_deg_y=40.0)
        handle = _box((100.0, 14.0, 4.0), (-49.0, 0.0, 0.0))
        return _union([blade, tip, handle])
    if kind == "clamp":
        jaw1 = _box((110.0, 4.0, 3.0), (55.0, 0.0, 0.0))
        jaw1.apply_transform(trimesh.transformations.rotation_matrix(np.radians(4), (0, 0, 1)))
        jaw2 = _box((110.0, 4.0, 3.0), (55.0, 0.0, 0.0))
        jaw2.apply_transform(trimesh.transformations.rotation_matrix(np.radians(-4), (0, 0, 1)))
        rings = []
        for sign in (1.0, -1.0):
            ring = trimesh.creation.torus(major_radius=9.0, minor_radius=2.0,
                                          major_sections=32, minor_sections=12)
            ring.apply_translation((-9.0, sign * 10.0, 0.0))
            rings.append(ring)
        return _union([jaw1, jaw2, *rings])
    raise ValueError(f"instrument kind: expected 'retractor' or 'clamp', got {kind!r}")


def make_instrument(spec: InstrumentSpec) -> Body:
    """The instrument as a Body in the robot frame (in air: ``inside`` None)."""
    mesh = instrument_mesh(spec.kind)
    mesh.apply_transform(spec.instrument2robot().as_matrix())
    return Body(spec.name, spec.material, mesh=mesh)


def scene_instruments(scene) -> list[Body]:
    """Bodies of the scene's ``[[instruments]]`` (none if the scene has no such section)."""
    specs = getattr(scene, "instruments", None) or ()
    names = [s.name for s in specs]
    if len(set(names)) != len(names):
        raise ValueError(f"instruments: names must be unique, got {names}")
    return [make_instrument(s) for s in specs]
