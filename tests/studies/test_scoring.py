"""The judge's scoring helpers: starts, target errors, the pin-based reference."""

from types import SimpleNamespace

import numpy as np
import pytest

from reglib.geometry import RigidTransform
from studies.scoring import (
    REFERENCE_SALT,
    judge_seed,
    mtre,
    perturbed_start,
    pin_errors,
    pin_reference,
    run_start,
    start_at_mtre,
)

PINS = {"proximal": np.array([10.0, 5.0, 420.0]), "distal_1": np.array([-20.0, 8.0, 40.0]),
        "distal_2": np.array([25.0, -6.0, 35.0])}
TRUTH = RigidTransform.from_rotvec([0.2, -0.1, 0.3]) @ RigidTransform(np.eye(3), [800, 0, 200])


def test_perturbed_start_turns_about_the_pins_centroid():
    s = perturbed_start(TRUTH, PINS, 7.0, np.random.default_rng(1))
    c = np.mean(list(PINS.values()), axis=0)
    assert np.allclose(s.apply(c), TRUTH.apply(c))
    ang = np.degrees(np.arccos((np.trace(s.R @ TRUTH.R.T) - 1) / 2))
    assert ang == pytest.approx(7.0)
    about = perturbed_start(TRUTH, PINS, 9.0, 2, about="proximal")
    assert pin_errors(about, TRUTH, PINS)["proximal"] < 1e-9
    assert min(pin_errors(about, TRUTH, PINS).values()) < max(pin_errors(s, TRUTH, PINS).values())


def test_mtre_is_the_mean_of_the_targets_distances_and_pin_errors_each_ones():
    """Against hand-computed distances (a mutation audit: mTRE as their median passed every
    test; the capture-range study's bins and results rest on it). A turn of 0.01 rad about
    z moves targets 10, 20 and 60 mm from the axis by 0.1, 0.2 and 0.6 mm (to 1e-6)."""
    turn = RigidTransform.from_rotvec([0.0, 0.0, 0.01])
    targets = np.array([[10.0, 0.0, 5.0], [0.0, 20.0, -3.0], [-60.0, 0.0, 100.0]])
    chord = 2.0 * np.sin(0.005)
    got = mtre(TRUTH @ turn, TRUTH, targets)
    assert got == pytest.approx(chord * (10.0 + 20.0 + 60.0) / 3.0, rel=1e-9)
    errs = pin_errors(TRUTH @ turn, TRUTH, dict(zip(("proximal", "distal_1", "distal_2"),
                                                     targets, strict=True)))
    assert [errs[k] for k in ("proximal", "distal_1", "distal_2")] == pytest.approx(
        [chord * 10.0, chord * 20.0, chord * 60.0], rel=1e-9)


def test_start_at_mtre_hits_the_target():
    t = np.array(list(PINS.values()))
    for target in (0.0, 3.0, 17.5):
        s = start_at_mtre(TRUTH, t, target, np.random.default_rng(int(target)))
        assert mtre(s, TRUTH, t) == pytest.approx(target, abs=2e-3)
    with pytest.raises(ValueError, match="target_mm"):
        start_at_mtre(TRUTH, t, -1.0, 0)


def test_pin_reference_is_exact_without_noise_and_in_error_with_it():
    truth = SimpleNamespace(points={"pins_ct": PINS}, transforms={"ct2robot": TRUTH})
    exact = pin_reference(truth, 0, ct_sigma_mm=0.0, robot_sigma_mm=0.0)
    assert max(pin_errors(exact, TRUTH, PINS).values()) < 1e-9
    errs = [max(pin_errors(pin_reference(truth, k), TRUTH, PINS).values()) for k in range(200)]
    # three pins, 0.25 mm per axis on each side: errors of a few tenths of a mm
    assert 0.1 < np.median(errs) < 0.8
    assert np.linalg.det(pin_reference(truth, 3).R) == pytest.approx(1.0)


def test_run_start_is_reproducible_from_the_case_seed():
    truth = SimpleNamespace(points={"pins_ct": PINS}, transforms={"ct2robot": TRUTH})
    scene = SimpleNamespace(registration=SimpleNamespace(start_rotation_deg=5.0, fixed_pin=None))
    ss = np.random.SeedSequence(5, spawn_key=(0,))
    a, b = run_start(truth, scene, ss), run_start(truth, scene, ss)
    assert np.array_equal(a.as_matrix(), b.as_matrix())
    c = run_start(truth, scene, np.random.SeedSequence(5, spawn_key=(1,)))
    assert not np.allclose(a.as_matrix(), c.as_matrix())


def test_a_case_whose_truth_lost_a_pin_is_named():
    """The score's truth check (a review: a case whose truth lost a pin stopped with a bare
    KeyError, one with a NaN pin with a message about a RigidTransform)."""
    from types import SimpleNamespace

    import numpy as np
    import pytest

    from studies.score import _check_truth

    pins = {"proximal": [0.0, 0.0, 400.0], "distal_1": [-20.0, 0.0, 20.0],
            "distal_2": [20.0, 0.0, 20.0]}
    ok = SimpleNamespace(transforms={"ct2robot": object()}, points={"pins_ct": pins})
    _check_truth(ok, "case_0000")
    lost = SimpleNamespace(transforms=ok.transforms, points={"pins_ct": {
        k: v for k, v in pins.items() if k != "distal_2"}})
    with pytest.raises(ValueError, match=r"case_0000: .*lacks the pin 'distal_2'"):
        _check_truth(lost, "case_0000")
    nan = SimpleNamespace(transforms=ok.transforms, points={"pins_ct": {
        **pins, "proximal": [np.nan, 0.0, 1.0]}})
    with pytest.raises(ValueError, match=r"pin 'proximal' .*3 finite numbers"):
        _check_truth(nan, "case_0000")
    with pytest.raises(ValueError, match="lacks transforms/ct2robot"):
        _check_truth(SimpleNamespace(transforms={}, points=ok.points), "case_0000")


def test_table2_starts_are_made_from_the_given_pose():
    from studies.end_to_end import table2_starts

    truth = SimpleNamespace(points={"pins_ct": PINS}, transforms={"ct2robot": TRUTH})
    ref = pin_reference(truth, 4)
    case = SimpleNamespace(ct2robot=TRUTH, pins_ct=PINS)
    ss = np.random.SeedSequence(5, spawn_key=(0,))
    from_ref = table2_starts(case, ss, pose=ref)
    from_truth = table2_starts(case, ss)
    assert len(from_ref) == 11
    assert from_ref["identity"] is ref and from_truth["identity"] is TRUTH
    c = np.mean(list(PINS.values()), axis=0)
    for name, s in from_ref.items():
        # every start keeps the pins' centroid where the reference puts it, off the truth's
        assert np.allclose(s.apply(c), ref.apply(c))
        assert not np.allclose(s.apply(c), TRUTH.apply(c), atol=1e-3)
        if name != "identity":   # the same turn about the centroid as from the truth
            turn_ref, turn_truth = s @ ref.inverse(), from_truth[name] @ TRUTH.inverse()
            assert np.allclose(turn_ref.R, turn_truth.R)


def test_a_dataset_index_whose_cases_are_no_list_is_named(tmp_path):
    """A review's dataset.json with "cases": "case_0000" was read letter by letter (nine
    missing cases 'c', 'a', 's', ...)."""
    import json

    from studies.score import missing_cases

    (tmp_path / "dataset.json").write_text(json.dumps({"cases": "case_0000"}))
    with pytest.raises(ValueError, match=r"dataset\.json: 'cases' must be a list of case "
                                         r"folder names, got 'case_0000'"):
        missing_cases(tmp_path)
    (tmp_path / "dataset.json").write_text(json.dumps({"cases": ["case_0000"]}))
    assert missing_cases(tmp_path) == ["case_0000"]


def test_a_located_pins_start_keeps_the_pin_based_registrations_error():
    """With a fixed pin (experiment1) the run's start is the pin-based registration turned
    about that pin: the pin is where that registration puts it, not where the truth does."""
    truth = SimpleNamespace(points={"pins_ct": PINS}, transforms={"ct2robot": TRUTH})
    ss = np.random.SeedSequence(5, spawn_key=(0,))
    free = SimpleNamespace(registration=SimpleNamespace(start_rotation_deg=9.0, fixed_pin=None))
    pinned = SimpleNamespace(registration=SimpleNamespace(start_rotation_deg=9.0,
                                                          fixed_pin="proximal"))
    start = run_start(truth, pinned, ss)
    ref = pin_reference(truth, judge_seed(ss, REFERENCE_SALT))
    at_pin = pin_errors(start, TRUTH, PINS)["proximal"]
    assert at_pin == pytest.approx(pin_errors(ref, TRUTH, PINS)["proximal"], abs=1e-9)
    assert at_pin > 0.01
    assert pin_errors(start, ref, PINS)["proximal"] < 1e-9
    # without a fixed pin the start is the truth turned about the pins' centroid
    c = np.mean(list(PINS.values()), axis=0)
    assert np.allclose(run_start(truth, free, ss).apply(c), TRUTH.apply(c))


def test_the_reference_takes_the_positions_the_robot_reported_where_it_has_them():
    """pin_reference: the case's robot touched the pins (truth points
    'pins_robot_digitized'); its reports, not a Gaussian, are the robot side; a pin it
    could not reach keeps the Gaussian."""
    shift = np.array([0.3, -0.2, 0.4])
    touched = {k: TRUTH.apply(v) + shift for k, v in PINS.items()}
    truth = SimpleNamespace(points={"pins_ct": PINS, "pins_robot_digitized": touched},
                            transforms={"ct2robot": TRUTH})
    ref = pin_reference(truth, 0, ct_sigma_mm=0.0)
    for e in pin_errors(ref, TRUTH, PINS).values():   # the robot's offset, whole
        assert e == pytest.approx(np.linalg.norm(shift), abs=1e-9)
    assert pin_reference(truth, 0, ct_sigma_mm=0.0, robot_sigma_mm=5.0).t == pytest.approx(
        ref.t)                                        # the Gaussian is not used
    partial = SimpleNamespace(points={"pins_ct": PINS, "pins_robot_digitized": {
        "proximal": touched["proximal"]}}, transforms={"ct2robot": TRUTH})
    assert not np.allclose(pin_reference(partial, 0, ct_sigma_mm=0.0).t, ref.t)


def test_a_stored_scene_with_a_removed_field_is_still_read():
    """A dataset written before [robot.sweep] park_distance_mm was removed (it never had an
    effect) still scores; a scene file that names it is refused as an unknown key."""
    import tomllib

    from studies.score import parse_stored_scene
    from testbed.scene import SceneError, find_scene, parse_scene

    data = tomllib.loads(find_scene("experiment2").read_text())
    data.setdefault("robot", {}).setdefault("sweep", {})["park_distance_mm"] = 250.0
    assert parse_stored_scene(data, source="case.json").robot.sweep.validation_offset_mm == 5.0
    assert data["robot"]["sweep"]["park_distance_mm"] == 250.0     # the caller's dict kept
    with pytest.raises(SceneError, match="park_distance_mm.*unknown key"):
        parse_scene(data, source="scene.toml")
    pins_array = SimpleNamespace(points={"pins_ct": PINS,
                                         "pins_robot_digitized": np.zeros((3, 3))},
                                 transforms={"ct2robot": TRUTH})
    assert np.allclose(pin_reference(pins_array, 0).t, pin_reference(
        SimpleNamespace(points={"pins_ct": PINS}, transforms={"ct2robot": TRUTH}), 0).t)


def test_a_methods_result_that_is_no_rigid_pose_is_named():
    """score's reading of a method's result: a complex matrix lost its imaginary part and
    was scored (a review), None was 'shape ()'; each is now named; a pose in any real
    form is read as it is."""
    from studies.score import _as_pose

    pose = RigidTransform.from_rotvec([0.1, -0.2, 0.3], [10.0, 20.0, 30.0])
    m = pose.as_matrix()
    for value in (m, m.tolist(), pose, m.astype(np.float32).astype(np.float64)):
        assert np.allclose(_as_pose(value, "x").as_matrix(), m)
    complex_values = "returned: the .4, 4. ct2robot matrix has complex values"
    for value, match in ((m.astype(complex) + 1j, complex_values),
                         (m.astype(complex), complex_values),
                         (None, "returned: expected a RigidTransform or a .4, 4. ct2robot "
                                "matrix of numbers, got NoneType"),
                         ("pose", "returned: .* got str"), (m[:3], r"shape \(3, 4\)"),
                         (m * 2.0, "not a rigid transform"),
                         # a rotation with a bad last row: that row named, not the rotation
                         (np.vstack([m[:3], [0.1, 0.0, 0.0, 1.0]]),
                          r"not a rigid transform: its last row is \[0\.1, 0, 0, 1\], "
                          r"expected \[0, 0, 0, 1\]$"),
                         # a review: booleans and strings were cast and scored (853 mm off)
                         (np.eye(4, dtype=bool), "returned: .* got an array of bool"),
                         (m.astype(str), "returned: .* got an array of <U"),
                         (np.asarray(m, dtype=object), "returned: .* got an array of object"),
                         # a scale beyond a rounded rotation's: refused, with its figure
                         (np.block([[m[:3, :3] * 1.002, m[:3, 3:]], [m[3:]]]),
                          r"method x returned: .* not a rigid transform .*R\^T R - I\| = 0.004"),
                         (np.block([[m[:3, :3], np.full((3, 1), 1e300)], [m[3:]]]),
                          r"method x returned: .* not a rigid transform: .*translation")):
        with pytest.raises(ValueError, match=match):
            _as_pose(value, "x")
    # a pose printed with 4 decimals (print(estimate), a review) or scaled by 1 + 1e-6 is
    # read as its nearest rotation: within the rounding of the matrix it was printed from
    for value in (np.round(m, 4), np.block([[m[:3, :3] * 1.0000009, m[:3, 3:]], [m[3:]]])):
        got = _as_pose(value, "x")
        assert np.allclose(got.R.T @ got.R, np.eye(3), atol=1e-12)
        assert np.abs(got.as_matrix() - m).max() < 1e-4
    # whole numbers are numbers
    eye = np.eye(4, dtype=np.int64)
    eye[:3, 3] = (1, 2, 3)
    assert np.allclose(_as_pose(eye, "x").t, (1, 2, 3))


def test_the_run_line_says_the_iterations_once():
    """testbed run's 'registration:' line read 'no convergence after 50 iterations (last
    step 35 mm) after 50 iterations' (a review); a reason that names its iterations keeps
    them once, others get them appended, and a registration not run says so."""
    from types import SimpleNamespace

    from studies.end_to_end import _registration_line

    def est(reason, n, ran=True):
        return SimpleNamespace(registration=object() if ran else None, message="",
                               quality={"reason": reason, "iterations": n})

    assert _registration_line(est("no convergence after 50 iterations (last step 35 mm)",
                                  50)) == "no convergence after 50 iterations (last step 35 mm)"
    assert _registration_line(est("the last 5 steps were all below", 12)) == (
        "the last 5 steps were all below after 12 iterations")
    assert _registration_line(est("", 0, ran=False)).startswith("not run")
