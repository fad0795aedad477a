"""testbed run warns when a view's field of view misses the anatomy of its region."""

from types import SimpleNamespace

import numpy as np

from studies.end_to_end import _aim_warnings
from testbed.fluoroscope import make_carm
from testbed.scene import find_scene, load_scene
from testbed.world import build_world


def _case(scene):
    world = build_world(scene, np.random.default_rng(0))
    carms = {v.name: make_carm(scene.fluoroscope, v, view_index=i)
             for i, v in enumerate(scene.views)}
    return SimpleNamespace(sim=SimpleNamespace(world=world, scene=scene, carms=carms))


def test_views_aimed_for_a_shorter_femur_are_named():
    """A femur of 550 mm under experiment2's views (aimed for its femur of about 450 mm):
    the femoral head lies 1.5-1.6 field radii off the proximal views' centres, which the
    verdict then refuses as views that do not fit; the warning says why and what to move.
    The shipped scene's views all reach their anatomy."""
    scene = load_scene(find_scene("experiment2"))
    assert _aim_warnings(_case(scene)) == []
    long = scene.model_copy(update={"phantom": scene.phantom.model_copy(
        update={"length_mm": 550.0})})
    warnings = _aim_warnings(_case(long))
    assert len(warnings) == 2, warnings
    for i, w in enumerate(warnings):
        assert w.startswith(f"views[{i}] ({scene.views[i].name!r}, region 'proximal'): the "
                            "field of view misses the proximal anatomy"), w
        assert f"aim views[{i}].isocenter_mm at it" in w
