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


def _coverage(scene):
    from studies.common import region_centres
    from studies.end_to_end import ct_coverage_warnings
    from testbed.ct import slice_schedule

    phantom = build_world(scene, np.random.default_rng(0)).phantom
    z, regions = slice_schedule(phantom, scene.ct)
    return ct_coverage_warnings(scene.views, region_centres(phantom), z,
                                list(regions.values()))


def test_views_of_a_region_the_ct_did_not_scan_are_named():
    """Only the knee scanned (a uniform CT from -2 to 120 mm of a 450 mm femur) with the
    proximal views kept: each proximal view is named with the missing stretch, the distal
    ones are not; the shipped clinical schedule and a uniform CT of the whole femur cover
    every view."""
    scene = load_scene(find_scene("experiment2"))
    assert _coverage(scene) == []
    whole = scene.model_copy(update={"ct": scene.ct.model_copy(
        update={"schedule": "uniform", "uniform_spacing_mm": 10.0})})
    assert _coverage(whole) == []
    knee = scene.model_copy(update={"ct": whole.ct.model_copy(
        update={"uniform_range_mm": (-2.0, 120.0)})})
    warnings = _coverage(knee)
    proximal = [i for i, v in enumerate(scene.views) if v.region == "proximal"]
    assert len(proximal) == 2 and len(warnings) == len(proximal), warnings
    for i, w in zip(proximal, warnings, strict=True):
        assert w.startswith(f"views[{i}] ({scene.views[i].name!r}, region 'proximal'): the CT "
                            "has no slices at its anatomy"), w
        assert "contoured stretches z -2 to 118 mm" in w, w
    # an anatomy centre a few mm beyond the last contoured slice (the operator stops at a
    # femoral head's last slice of one section) is no missing stretch (a review)
    from studies.common import region_centres
    from studies.end_to_end import CT_COVERAGE_MARGIN_MM, ct_coverage_warnings

    phantom = build_world(scene, np.random.default_rng(0)).phantom
    zc = float(region_centres(phantom)["proximal"][2])
    z = np.array([0.0, 50.0, zc - 40.0, zc - 4.0])
    views = scene.views
    assert ct_coverage_warnings(views, region_centres(phantom), z, [[0, 1], [2, 3]]) == []
    z_far = np.array([0.0, 50.0, zc - 80.0, zc - CT_COVERAGE_MARGIN_MM - 1.0])
    assert len(ct_coverage_warnings(views, region_centres(phantom), z_far,
                                    [[0, 1], [2, 3]])) == 2


def test_a_moving_femur_is_announced_first():
    """[patient] motion_mm / motion_deg > 0: one warning line naming both fields, and
    testbed run's text puts it first (a review: accepted 8.5-10 mm off at 3 mm / 1 deg with
    no word of the motion in the output)."""
    from studies.end_to_end import motion_warnings
    from studies.main_job import format_result
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    assert motion_warnings(scene) == []
    moved = scene.model_copy(update={"patient": scene.patient.model_copy(
        update={"motion_mm": 3.0, "motion_deg": 1.0})})
    (w,) = motion_warnings(moved)
    assert "motion_mm = 3" in w and "motion_deg = 1" in w and "verdict" in w
    text = format_result({"scene": "s", "kind": "operating_room", "seed": 1,
                          "scene_warnings": [w], "pins": {"proximal": 1.0}, "mtre_mm": 1.0,
                          "converged": True, "accepted": True, "outputs": {},
                          "timings": {}})
    assert text.splitlines()[0] == f"WARNING: {w}"


def _first_line_of_run_text(warning: str) -> str:
    """The first line of ``testbed run``'s text for a result whose scene warnings are
    another line and ``warning``."""
    from studies.main_job import format_result

    return format_result({"scene": "s", "kind": "operating_room", "seed": 1,
                          "scene_warnings": ["other", warning], "pins": {"proximal": 1.0},
                          "mtre_mm": 1.0, "converged": True, "accepted": True,
                          "outputs": {}, "timings": {}}).splitlines()[0]


def test_a_distortion_drift_beyond_the_clinics_is_warned_of():
    """Held-out reviews: a distortion drift between the sweep and the shot of 3-10 times the
    clinic default was accepted with pins 2-6.7 mm off, every verdict figure inside its
    limit. Beyond twice the default, one warning naming the field and the factor; none for
    the shipped profiles, none at twice, none when the distortion is off."""
    from studies.end_to_end import drift_warnings
    from testbed.scene import find_scene, load_scene

    for name in ("experiment2", "experiment2-ideal", "experiment1"):
        assert drift_warnings(load_scene(find_scene(name))) == [], name
    scene = load_scene(find_scene("experiment2"))
    for update, shown in (({"distortion_drift_mm": 1.0}, "distortion_drift_mm = 1 (5.0 "),
                          ({"distortion_drift_mm": 0.4}, None),
                          ({"distortion_drift_mm": 1.0, "distortion": False}, None)):
        worse = scene.model_copy(update={
            "fluoroscope": scene.fluoroscope.model_copy(update=update)})
        got = drift_warnings(worse)
        if shown is None:
            assert got == [], update
        else:
            (w,) = got
            assert w.startswith("[fluoroscope] ") and shown in w and "verdict cannot see" in w
    # testbed run's text puts it first
    assert _first_line_of_run_text(w) == f"WARNING: {w}"


def test_a_robot_less_accurate_than_the_clinics_is_warned_of():
    """A held-out review (h77): kinematic offsets at 3-10 times the clinic default were
    accepted at mTRE 2-7 mm with every verdict figure inside its limit (the calibration is
    made in the frame the robot reports). Beyond twice the default, one warning naming
    the field and the factor; the shipped profiles get none."""
    from studies.end_to_end import robot_warnings
    from testbed.scene import find_scene, load_scene

    for name in ("experiment2", "experiment2-ideal", "experiment1"):
        assert robot_warnings(load_scene(find_scene(name))) == [], name
    scene = load_scene(find_scene("experiment2"))
    for update, shown in (({"kinematic_offset_mm": 0.225}, "kinematic_offset_mm = 0.225 (3.0 "),
                          ({"kinematic_offset_deg": 0.05}, "kinematic_offset_deg = 0.05 (6.7 "),
                          ({"kinematic_offset_mm": 0.15}, None)):
        worse = scene.model_copy(update={"robot": scene.robot.model_copy(update=update)})
        got = robot_warnings(worse)
        if shown is None:
            assert got == []
        else:
            (w,) = got
            assert w.startswith("[robot] ") and shown in w and "verdict cannot see" in w
    # testbed run's text puts it first
    assert _first_line_of_run_text(w) == f"WARNING: {w}"


def test_a_pin_between_distant_ct_slices_is_warned_of():
    """A held-out sweep: on uniform 6-7.5 mm slices experiment1 was accepted with pins up
    to 4.5 mm off, against 2.07 mm on the clinical schedule (1 mm about each pin). Slices
    more than PIN_SLICE_WARN_MM apart across a pin give one warning naming each such pin
    and its gap; the shipped scenes' schedules, and a pin beyond the stack, give none."""
    import numpy as np

    from studies.end_to_end import PIN_SLICE_WARN_MM, pin_detail_warnings, scene_warnings
    from testbed.scene import find_scene, load_scene

    pins = {"proximal": np.array([0.0, 0.0, 400.0]), "distal_1": np.array([0.0, 0.0, 30.0]),
            "distal_2": np.array([0.0, 0.0, 900.0])}
    z = np.arange(0.0, 451.0, 6.8)
    (w,) = pin_detail_warnings(pins, z)
    assert "6.8 mm across 'proximal'" in w and "6.8 mm across 'distal_1'" in w
    assert "distal_2" not in w
    assert "verdict cannot see" in w
    fine = np.r_[np.arange(0.0, 45.0, 1.0), np.arange(45.0, 385.0, 6.0), np.arange(385, 416.0)]
    assert pin_detail_warnings(pins, fine) == []
    assert pin_detail_warnings(pins, np.arange(0.0, 451.0, PIN_SLICE_WARN_MM)) == []
    assert pin_detail_warnings(pins, np.zeros(0)) == []
    # a slice through the pin: the gaps beside it count
    (w,) = pin_detail_warnings({"p": np.array([0.0, 0.0, 34.0])},
                               np.r_[27.2, 34.0, np.arange(35.0, 60.0)])
    assert "6.8 mm across 'p'" in w
    assert pin_detail_warnings({"p": np.array([0.0, 0.0, 34.0])}, np.arange(30.0, 40.0)) == []
    assert pin_detail_warnings({"p": np.array([0.0, 0.0, 34.0])}, np.array([34.0])) == []
    (w,) = pin_detail_warnings({"p": np.array([0.0, 0.0, 34.0])}, np.array([34.0, 40.0]))
    assert "6.0 mm across 'p'" in w
    # the shipped scenes are warned of nothing of the kind; a uniform 6.8 mm CT is
    for name in ("experiment2", "experiment1"):
        scene = load_scene(find_scene(name))
        assert not any("either side of a pin" in x for x in scene_warnings(scene, 1)), name
    coarse = scene.model_copy(update={"ct": scene.ct.model_copy(update={
        "schedule": "uniform", "uniform_spacing_mm": 6.8})})
    assert sum("either side of a pin" in x for x in scene_warnings(coarse, 1)) == 1
    # testbed run's text puts it first, with the other warnings the verdict cannot see (a
    # held-out review found it after "verdict: accepted")
    assert _first_line_of_run_text(w) == f"WARNING: {w}"


def test_a_pin_no_ct_slice_shows_is_warned_of():
    """A held-out review: experiment1 with the proximal CT stretch ending 22 mm below the
    fixed pin; the simulated operator located it in the CT all the same, and the pose was
    accepted without a word. Pins within PIN_CT_MARGIN_MM of a slice are not warned of."""
    import numpy as np

    from studies.end_to_end import PIN_CT_MARGIN_MM, pin_coverage_warnings

    pins = {"proximal": np.array([0.0, 0.0, 400.0]), "distal_1": np.array([0.0, 0.0, 30.0])}
    z = np.r_[np.arange(0.0, 101.0, 6.0), np.arange(330.0, 379.0, 6.0)]    # 0-96, 330-378
    (w,) = pin_coverage_warnings(pins, z, "proximal")
    assert w.startswith("pin 'proximal' (z = 400 mm in the ct frame) lies 22 mm from the "
                        "nearest CT slice") and "registration.fixed_pin" in w
    (w,) = pin_coverage_warnings(pins, z, None)
    assert "fixed_pin" not in w and "pin-based reference of table2" in w
    assert _first_line_of_run_text(w) == f"WARNING: {w}"     # first in testbed run's text
    near = {"p": np.array([0.0, 0.0, 378.0 + PIN_CT_MARGIN_MM])}
    assert pin_coverage_warnings(near, z) == []
    assert pin_coverage_warnings(pins, np.zeros(0)) == []


def test_a_views_region_label_is_said_to_reach_the_verdict(tmp_path):
    """A held-out review (h81): the warning for a distal view labelled 'proximal' said the
    run does not use the label, but the observation's view_regions carry it to the verdict;
    a view that gives no region is read as 'proximal', and the warning names it."""
    from studies.end_to_end import _region_label_warnings
    from testbed.scene import find_scene, load_scene

    text = find_scene("experiment2").read_text()
    assert text.count('region = "distal"') == 2
    unlabelled = tmp_path / "no_region.toml"
    unlabelled.write_text(text.replace('region = "distal"\n', "", 1))
    (w,) = _region_label_warnings(load_scene(unlabelled))
    assert w.startswith("views[2].region: view 'distal_ap' is labelled 'proximal'"), w
    assert "the run passes the label to the method, whose verdict counts" in w
    assert w.endswith("views[2] give(s) no region, read as 'proximal'")
    # (a view labelled 'proximal' on purpose: tests/studies/test_capture_range.py)


def test_an_unchecked_workspace_is_among_the_warnings_and_said_first():
    """A held-out review (h81): with [workspace] check = false the JSON's warnings were
    empty; the opt-out is a scene warning, and the text's first line."""
    from studies.end_to_end import WORKSPACE_UNCHECKED
    from studies.main_job import format_result

    assert WORKSPACE_UNCHECKED.startswith("[workspace] check = false")
    text = format_result({"scene": "s", "kind": "operating_room", "seed": 1,
                          "scene_warnings": ["views[0]: other", WORKSPACE_UNCHECKED],
                          "pins": {"proximal": 1.0}, "mtre_mm": 1.0, "converged": True,
                          "accepted": True, "outputs": {}, "timings": {}})
    assert text.splitlines()[0] == f"WARNING: {WORKSPACE_UNCHECKED}"
    assert "WARNING: views[0]" not in text
