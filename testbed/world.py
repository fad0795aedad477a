"""The simulated operating room of a scene, assembled in the robot frame.

:func:`build_world` makes the patient (the phantom of ``[phantom]``, placed by
``[patient]`` as ``ct2robot``), the OR table and foam under the limb (``patient.on_table``)
and the instruments of ``[[instruments]]``. Everything here is truth: the method sees only
what the CT scanner, the fluoroscope and the robot make of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from reglib.geometry import RigidTransform
from testbed.bodies import Body

__all__ = ["World", "build_world", "world_bodies", "table_bodies"]

TABLE_THICKNESS_MM = 25.0
FOAM_THICKNESS_MM = 40.0


@dataclass(frozen=True)
class World:
    """The scene's world. ``phantom`` is in the ct frame; ``bodies`` in the robot frame."""

    phantom: object
    ct2robot: RigidTransform
    patient_bodies: list
    table: list
    instruments: list

    @property
    def bodies(self) -> list[Body]:
        """Everything the X-rays cross (robot frame), patient first."""
        return [*self.patient_bodies, *self.table, *self.instruments]

    @property
    def pins_robot(self) -> dict[str, np.ndarray]:
        """True pin centres (mm, robot frame), by name."""
        return {k: self.ct2robot.apply(v) for k, v in self.phantom.pins.items()}


def table_bodies(patient_bodies) -> list[Body]:
    """Foam block and table top under the outermost patient meshes (robot frame, z up)."""
    outer = [b.mesh for b in patient_bodies if b.mesh is not None and b.inside is None]
    if not outer:
        return []
    lo = np.min([m.bounds[0] for m in outer], axis=0)
    hi = np.max([m.bounds[1] for m in outer], axis=0)
    centre = 0.5 * (lo + hi)
    length_y = (hi[1] - lo[1]) + 200.0
    foam = trimesh.creation.box(
        extents=(hi[0] - lo[0] + 40.0, length_y, FOAM_THICKNESS_MM),
        transform=trimesh.transformations.translation_matrix(
            (centre[0], centre[1], lo[2] - 0.5 * FOAM_THICKNESS_MM - 0.5)))
    table = trimesh.creation.box(
        extents=(500.0, length_y + 200.0, TABLE_THICKNESS_MM),
        transform=trimesh.transformations.translation_matrix(
            (centre[0], centre[1], lo[2] - FOAM_THICKNESS_MM - 0.5 * TABLE_THICKNESS_MM - 1.0)))
    return [Body("foam", "foam", foam), Body("table", "table", table)]


def build_world(scene, rng=None) -> World:
    """The world of an operating-room scene; ``rng`` draws the phantom's shape variation."""
    from testbed.instruments import scene_instruments
    from testbed.phantom import make_phantom

    rng = np.random.default_rng(rng)
    phantom = make_phantom(scene.phantom, rng)
    ct2robot = scene.patient.ct2robot()
    patient = [b.transformed(ct2robot) for b in phantom.bodies()]
    table = table_bodies(patient) if scene.patient.on_table else []
    return World(phantom, ct2robot, patient, table, list(scene_instruments(scene)))


def world_bodies(scene, rng=None) -> list[Body]:
    """All bodies of the scene's world in the robot frame (used by ``testbed render``)."""
    return build_world(scene, rng).bodies
