"""Bodies of the simulated world: closed meshes (and exact spheres) with a material.

The contract between the world's parts: the phantom, the robot's rod and the OR instruments
each give a list of :class:`Body`; the CT scanner samples them and the fluoroscope ray-casts
them. Nesting is explicit: a body lies inside the body named by ``inside`` (or in air), so
along a ray the attenuation is ``sum_b length_b * (mu(b) - mu(inside(b)))`` and a CT voxel
takes the material of the innermost body that contains it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from reglib.geometry import RigidTransform
from testbed.materials import material

__all__ = ["Body", "transform_bodies"]


@dataclass(frozen=True)
class Body:
    """A closed mesh or a set of exact spheres made of one material, in a stated frame (mm).

    ``mesh``: a watertight ``trimesh.Trimesh`` or None. ``sphere_centers`` (K, 3) and
    ``sphere_radii`` (K,) describe exact spheres (steel beads) when ``mesh`` is None.
    ``inside``: the name of the body that encloses this one (None: air).
    """

    name: str
    material: str
    mesh: trimesh.Trimesh | None = None
    sphere_centers: np.ndarray | None = None
    sphere_radii: np.ndarray | None = None
    inside: str | None = None

    def __post_init__(self):
        material(self.material)  # raises ValueError naming the unknown material
        if (self.mesh is None) == (self.sphere_centers is None):
            raise ValueError(f"body {self.name!r}: give either a mesh or sphere centers")
        if self.sphere_centers is not None:
            c = np.asarray(self.sphere_centers, dtype=np.float64).reshape(-1, 3)
            r = np.broadcast_to(np.asarray(self.sphere_radii, dtype=np.float64), (len(c),))
            object.__setattr__(self, "sphere_centers", c)
            object.__setattr__(self, "sphere_radii", np.array(r))

    def transformed(self, a2b: RigidTransform) -> Body:
        """The same body in another frame."""
        mesh = None
        if self.mesh is not None:
            mesh = self.mesh.copy()
            mesh.apply_transform(a2b.as_matrix())
        centers = None if self.sphere_centers is None else a2b.apply(self.sphere_centers)
        return Body(self.name, self.material, mesh, centers, self.sphere_radii, self.inside)


def transform_bodies(bodies, a2b: RigidTransform) -> list[Body]:
    return [b.transformed(a2b) for b in bodies]
