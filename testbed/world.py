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


TABLE_LENGTH_MM = 2000.0
"""An OR table top is about 2 m long and 0.5 m wide [memory: operating-table specifications,
e.g. 2050 x 540 mm for common general-surgery tables]: fixed, whatever the femur's length."""
TABLE_WIDTH_MM = 500.0
TABLE_BEYOND_DISTAL_MM = 600.0
"""Table beyond the knee (the femur's distal end): the lower leg and foot (knee height is
about 0.28 of stature [memory: Drillis & Contini 1966 segment proportions], 490 mm at
1.75 m)."""


def table_bodies(patient_bodies, proximal_robot=(0.0, -1.0, 0.0)) -> list[Body]:
    """Foam block under the outermost patient meshes and the OR table top under it (robot
    frame, z up).

    ``proximal_robot`` (3,): the femur's proximal direction in the robot frame (the ct
    frame's +z); the table's long axis is its horizontal part (the robot's y if the femur
    stands upright). The foam is the limb's size; the table is :data:`TABLE_LENGTH_MM` long
    whatever the limb's, ending :data:`TABLE_BEYOND_DISTAL_MM` beyond the knee (the femur's
    distal end), the rest of a patient's body lying on the proximal part.
    """
    outer = [b.mesh for b in patient_bodies if b.mesh is not None and b.inside is None]
    if not outer:
        return []
    bone = [b.mesh for b in patient_bodies if b.name == "femur" and b.mesh is not None]
    along = np.array([proximal_robot[0], proximal_robot[1], 0.0], dtype=float)
    if np.linalg.norm(along) < 1e-6:
        along = np.array([0.0, -1.0, 0.0])
    along /= np.linalg.norm(along)
    across = np.cross((0.0, 0.0, 1.0), along)
    R = np.column_stack([across, along, (0.0, 0.0, 1.0)])   # box frame -> robot
    v = np.vstack([m.vertices for m in outer]) @ R          # (across, along, up)
    lo, hi = v.min(axis=0), v.max(axis=0)
    mid = 0.5 * (lo + hi)

    def box(extents, centre_box):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, R @ np.asarray(centre_box, dtype=float)
        return trimesh.creation.box(extents=extents, transform=T)

    foam_z = lo[2] - 0.5 * FOAM_THICKNESS_MM - 0.5
    foam = box((hi[0] - lo[0] + 40.0, hi[1] - lo[1] + 200.0, FOAM_THICKNESS_MM),
               (mid[0], mid[1], foam_z))
    # from the knee (the femur's distal end; the limb's without a femur body)
    knee = (np.vstack([m.vertices for m in bone]) @ R)[:, 1].min() if bone else lo[1]
    table_start = knee - TABLE_BEYOND_DISTAL_MM   # along the proximal direction
    table = box((TABLE_WIDTH_MM, TABLE_LENGTH_MM, TABLE_THICKNESS_MM),
                (mid[0], table_start + 0.5 * TABLE_LENGTH_MM,
                 lo[2] - FOAM_THICKNESS_MM - 0.5 * TABLE_THICKNESS_MM - 1.0))
    return [Body("foam", "foam", foam), Body("table", "table", table)]


def build_world(scene, rng=None) -> World:
    """The world of an operating-room scene; ``rng`` draws the phantom's shape variation."""
    from testbed.instruments import scene_instruments
    from testbed.phantom import make_phantom

    rng = np.random.default_rng(rng)
    phantom = make_phantom(scene.phantom, rng)
    ct2robot = scene.patient.ct2robot()
    patient = [b.transformed(ct2robot) for b in phantom.bodies()]
    table = (table_bodies(patient, proximal_robot=ct2robot.R[:, 2])
             if scene.patient.on_table else [])
    instruments = list(scene_instruments(scene))
    _check_instruments_outside_bone(instruments, patient)
    return World(phantom, ct2robot, patient, table, instruments)


#: surface points of an instrument tested against the femur (seeded: the same every run)
INSTRUMENT_SAMPLES = 2000


def _check_instruments_outside_bone(instruments: list[Body], patient: list[Body]) -> None:
    """``ValueError`` naming an instrument that passes through the femur (a held-out review
    placed one inside the bone and the run went on). Instruments rest on the thigh or beside
    the bone, and may enter the soft tissue; the bone they cannot enter."""
    femur = next((b.mesh for b in patient if b.name == "femur" and b.mesh is not None), None)
    if femur is None:
        return
    for k, ins in enumerate(instruments):
        if ins.mesh is None:
            continue
        pts, _ = trimesh.sample.sample_surface(ins.mesh, INSTRUMENT_SAMPLES, seed=0)
        lo, hi = femur.bounds
        near = np.all((pts >= lo) & (pts <= hi), axis=1)
        inside = int(femur.contains(pts[near]).sum()) if near.any() else 0
        if inside:
            raise ValueError(
                f"instruments[{k}] ({ins.name!r}): passes through the femur ({inside} of "
                f"{INSTRUMENT_SAMPLES} points of its surface lie inside the bone); an "
                "instrument rests on the thigh or beside the bone: move its position_mm or "
                "turn it (rotation_deg)")


def world_bodies(scene, rng=None) -> list[Body]:
    """All bodies of the scene's world in the robot frame (used by ``testbed render``)."""
    return build_world(scene, rng).bodies
