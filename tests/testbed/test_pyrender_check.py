"""An independent check of the projection geometry: pyrender (OpenGL rasterisation, EGL)
renders the same meshes from the same pinhole; its silhouette must agree with the
ray caster's mask (distortion off)."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import pytest
import trimesh

from testbed.bodies import Body
from testbed.fluoroscope import FluoroscopeSpec, ViewSpec, make_carm, render

pyrender = pytest.importorskip("pyrender")


def _pyrender_silhouette(carm, meshes):
    """Silhouette (H, W) bool of ``meshes`` (robot frame) from the C-arm's ideal pinhole.

    pyrender renders with 4x multisampling (hard-coded); its depth read-back keeps one sample,
    away from the pixel centre, so the silhouette is taken from the resolved colour instead:
    a white flat-shaded mesh on black, a pixel inside when at least half of it is covered.
    """
    scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[1.0, 1.0, 1.0])
    white = pyrender.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0])
    for m in meshes:
        scene.add(pyrender.Mesh.from_trimesh(m, smooth=False, material=white))
    f = carm.sid_mm / carm.pixel_mm
    # pyrender's pixel (col, row) spans [col, col + 1] x [row, row + 1] (rows from the top);
    # our pixel centres are at integers, hence the half-pixel shift
    cam = pyrender.IntrinsicsCamera(fx=f, fy=f, cx=carm.principal_px[0] + 0.5,
                                    cy=carm.principal_px[1] + 0.5, znear=10.0, zfar=5000.0)
    # carm: +z forward, +y down; OpenGL camera: -z forward, +y up
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    scene.add(cam, pose=carm.carm2robot.as_matrix() @ flip)
    r = pyrender.OffscreenRenderer(carm.width_px, carm.height_px)
    try:
        color, _ = r.render(scene, flags=pyrender.RenderFlags.FLAT)
    finally:
        r.delete()
    return color[..., 0] >= 128


def _femur_like(rng):
    """A bent, closed shaft with a head: a union of a capsule and a sphere, tilted."""
    shaft = trimesh.creation.capsule(height=160.0, radius=14.0, count=[48, 24])
    head = trimesh.creation.icosphere(subdivisions=4, radius=24.0)
    head.apply_translation((28.0, 0.0, 95.0))
    mesh = trimesh.boolean.union([shaft, head], engine="manifold")
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))
    mesh.apply_transform(rot)
    mesh.apply_translation(rng.uniform(-20.0, 20.0, 3))
    return mesh


@pytest.mark.parametrize("pose, offset", [((0.0, 0.0, 0.0), (0.0, 0.0)),
                                          ((25.0, -40.0, 15.0), (7.0, -11.0))])
def test_pyrender_silhouette_matches_ray_cast_mask(pose, offset):
    rng = np.random.default_rng(21)
    mesh = _femur_like(rng)
    assert mesh.is_watertight
    fluoro = FluoroscopeSpec(noise=False, distortion=False, principal_offset_px=offset)
    view = ViewSpec(orbital_deg=pose[0], angular_deg=pose[1], roll_deg=pose[2],
                    isocenter_mm=(5.0, -10.0, 0.0))
    carm = make_carm(fluoro, view)
    frame = render(carm, [Body("femur", "cortical_bone", mesh=mesh)], fluoro=fluoro)
    ours = frame.bone_mask
    theirs = _pyrender_silhouette(carm, [mesh]) & frame.fov
    inter = (ours & theirs).sum()
    union = (ours | theirs).sum()
    assert ours.sum() > 5000
    assert inter / union >= 0.99, inter / union
    # the check can fail: a one-pixel shift of the image drops the agreement
    shifted = np.roll(theirs, (1, 1), axis=(0, 1))
    assert (ours & shifted).sum() / (ours | shifted).sum() < inter / union - 0.005
