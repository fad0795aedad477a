"""The capture-range study's scene checks."""

import pytest


def test_a_view_labelled_with_the_other_region_is_refused():
    """Studies that re-aim or group views by region refuse a view whose isocentre lies at the
    other end of the femur (a review labelled proximal_ap 'distal': capture-range moved it by
    the condyles' shift)."""
    from studies.common import check_view_regions
    from testbed.scene import find_scene, load_scene
    from testbed.spec import SceneError

    scene = load_scene(find_scene("experiment2"))
    check_view_regions(scene)                           # the shipped labels are right
    views = list(scene.views)
    views[0] = views[0].model_copy(update={"region": "distal"})
    with pytest.raises(SceneError, match=r"views\[0\]\.region: view 'proximal_ap' is "
                                         r"labelled 'distal'"):
        check_view_regions(scene.model_copy(update={"views": tuple(views)}))


def test_testbed_run_warns_of_a_mislabelled_view():
    from studies.end_to_end import _region_label_warnings
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    assert _region_label_warnings(scene) == []
    views = list(scene.views)
    views[2] = views[2].model_copy(update={"region": "proximal"})
    (w,) = _region_label_warnings(scene.model_copy(update={"views": tuple(views)}))
    assert "views[2].region" in w and "does not use the label" in w
