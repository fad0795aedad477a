"""The judge's true inputs: what reglib's stages would give if they were perfect.

For the error budget and the cheap studies, each estimated input of the registration can be
replaced by its truth (:data:`ORACLES`):

- ``"calibration"``: the true pixel -> X-ray path map of each C-arm (distortion included)
  and the true source as the centre of perspective;
- ``"surfaces"``: the phantom's femur cut to the z range of each reconstructed surface;
- ``"contours"``: the femur's exact apparent contour from the true source, projected through
  the true C-arm, on the frame's field, flagged external where it lies on the outline of the
  femur's shadow.

These live in the judge (``studies``), never in reglib: they use the simulator's truth.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion, distance_transform_edt

from reglib.pipeline import Stages, ViewCalibration, ViewContours, prepare

__all__ = ["ORACLES", "TrueCalibration", "oracle_stages", "silhouette_points",
           "true_calibrations", "true_contours", "true_surfaces"]

ORACLES = ("calibration", "surfaces", "contours")


class TrueCalibration:
    """The true calibration of a C-arm: ``paths`` and ``center_of_perspective`` as
    :class:`reglib.calibration.Calibration` has them (robot frame, mm)."""

    def __init__(self, carm):
        self.carm = carm

    def paths(self, xy_px):
        xy = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
        if len(xy) == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        return self.carm.true_rays(xy)

    def center_of_perspective(self, xy_px=None):
        return np.asarray(self.carm.source_robot, dtype=np.float64)


def silhouette_points(mesh, source, *, step_mm: float = 1.0) -> np.ndarray:
    """Points (N, 3) on the apparent contour of a closed mesh seen from ``source`` (mm):
    edges between a face turned towards the source and one turned away, sampled every
    ``step_mm``. Independent of ``reglib.apparent`` (this is the truth)."""
    normals = mesh.face_normals
    front = np.einsum("ij,ij->i", normals, mesh.triangles_center - source) < 0
    adj = mesh.face_adjacency
    edges = mesh.face_adjacency_edges[front[adj[:, 0]] != front[adj[:, 1]]]
    a, b = mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]]
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / step_mm)).astype(int)
    pts = [a[i] + (b[i] - a[i]) * (np.arange(n[i])[:, None] / n[i]) for i in range(len(a))]
    return np.vstack(pts) if pts else np.zeros((0, 3))


def true_calibrations(sim) -> dict:
    """View -> ViewCalibration with the true pixel -> path map (a ``testbed.simulate``
    :class:`~testbed.simulate.Simulation`)."""
    return {v: ViewCalibration(v, TrueCalibration(c)) for v, c in sim.carms.items()}


def _region_cut(vertices, faces, z_lo, z_hi):
    cz = vertices[faces].mean(axis=1)[:, 2]
    f = faces[(cz >= z_lo) & (cz <= z_hi)]
    used, inv = np.unique(f, return_inverse=True)
    return vertices[used], inv.reshape(-1, 3)


def true_surfaces(sim, estimated: dict) -> dict:
    """Region -> the true femur (ct frame) over the z range of the estimated surface."""
    femur = sim.world.phantom.femur
    v, f = np.asarray(femur.vertices, float), np.asarray(femur.faces, np.int64)
    return {r: _region_cut(v, f, float(ev[:, 2].min()), float(ev[:, 2].max()))
            for r, (ev, _) in estimated.items()}


def true_contours(sim) -> dict:
    """View -> ViewContours of the femur's exact apparent contour (px), external flags from
    the outline of the femur's shadow in the frame."""
    from testbed.instruments import file_key

    out = {}
    for v, carm in sim.carms.items():
        frame = sim.frames[v]
        # the femur where the view saw it ([patient] motion_mm / motion_deg move it between
        # views; a review found the oracle drawing it where the pins were digitised)
        pose = sim.truth.transforms.get(f"ct2robot_{file_key(v)}", sim.world.ct2robot)
        femur = sim.world.phantom.femur.copy()
        femur.apply_transform(pose.as_matrix())
        sil = silhouette_points(femur, carm.source_robot)
        xy = carm.project(sil) if len(sil) else np.zeros((0, 2))
        H, W = frame.fov.shape
        xy = xy[(xy[:, 0] >= 0) & (xy[:, 0] <= W - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= H - 1)]
        if len(xy):
            xy = xy[carm.fov_rho(xy) < 0.95]
        mask = frame.path_mm["femur"] > 0
        edge = distance_transform_edt(~(mask & ~binary_erosion(mask)))
        r = np.clip(np.rint(xy[:, 1]).astype(int), 0, H - 1)
        c = np.clip(np.rint(xy[:, 0]).astype(int), 0, W - 1)
        out[v] = ViewContours(v, xy, edge[r, c] <= 1.5)
    return out


def oracle_stages(sim, base: Stages, oracle=(), *, options=None) -> Stages:
    """``base`` (the estimated stages of ``sim``'s observation) with the inputs named in
    ``oracle`` (some of :data:`ORACLES`) replaced by the truth."""
    oracle = set(oracle)
    unknown = oracle - set(ORACLES)
    if unknown:
        raise ValueError(f"oracle: unknown {sorted(unknown)}; expected some of {ORACLES}")
    if not oracle:
        return base
    return prepare(
        sim.observation, options=options,
        calibrations=true_calibrations(sim) if "calibration" in oracle else base.calibrations,
        surfaces=true_surfaces(sim, base.surfaces) if "surfaces" in oracle else base.surfaces,
        contours=true_contours(sim) if "contours" in oracle else base.contours)
