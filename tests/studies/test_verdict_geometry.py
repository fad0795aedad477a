"""The method's verdict on a pose its views leave loosely determined (simulate, estimate,
compare with the truth)."""

from __future__ import annotations

import pytest

from reglib.pipeline import MAX_WEAK_MOTION_MM, MIN_VIEW_FIT
from studies.end_to_end import run_case
from testbed.scene import find_scene, load_scene, parse_scene


@pytest.mark.slow
@pytest.mark.parametrize("pair", [("proximal_ap", "distal_oblique"),
                                  ("proximal_oblique", "distal_ap")])
def test_one_view_per_end_of_the_femur_is_refused_and_was_wrong(pair):
    """Clinic experiment2 with one view per end of the femur: the registration fits the
    contours as well as with four views (median distance ~0.4-0.55 mm) but the bone can slide
    along the beams; the verdict refuses it, and the truth confirms it was loose. One draw
    does not show it: at the scene's seed the first pair ended 0.72 mm off, then 0.58 mm
    (2026-11-28, the coarse stage's pose solve stopped after 5 inner iterations), against
    0.38 mm with the four views; right by chance, as the weak-geometry rule cannot know. So
    the truth is read over three seeds (2026-11-28: the first pair 0.58 / 1.93 / 1.56 mm,
    the second 7.74 / 3.88 / 3.18 mm; the four views 0.38 / 0.46 / 0.39 mm; weakest motion
    8.3-13.8 mm, every run refused). History at the scene's seed: 0.80 and more than 2 mm against
    0.30 after the CT contour fixes of 2026-11-26; 1.3 mm against 0.52 before them; before
    one robot swept every view, 3.7 and 4.3 mm; the second pair was accepted under a first
    limit of 8 mm, at 7.8."""
    scene = load_scene(find_scene("experiment2"))
    two = scene.model_copy(update={"views": tuple(v for v in scene.views if v.name in pair)})
    errors = []
    for seed in (scene.scene.seed, 1, 2):
        res, _, _, est = run_case(two, seed=seed)
        # refused for the geometry whether the loop converged or not
        assert not est.accepted, seed
        assert "loosely determined" in est.message, seed
        assert est.quality["weak_motion_mm"] > MAX_WEAK_MOTION_MM, seed
        errors.append(res["mtre_mm"])
    # the truth: the median error well above the four views' (0.38-0.46 mm at these seeds)
    assert sorted(errors)[1] > 1.0, errors


@pytest.mark.slow
def test_the_four_views_of_the_clinic_are_accepted_within_1_mm():
    scene = load_scene(find_scene("experiment2"))
    res, _, _, est = run_case(scene, seed=scene.scene.seed)
    assert est.accepted and res["mtre_mm"] < 1.0
    assert est.quality["weak_motion_mm"] < 0.6 * MAX_WEAK_MOTION_MM


@pytest.mark.slow
def test_a_view_that_misses_the_anatomy_of_its_ct_surface_is_refused_and_was_wrong():
    """Clinic experiment2 with a femur drawn far from the mean (shape_variation 3, seed 5:
    about 600 mm, its head beyond the proximal views, which show only the shaft): the whole
    median distance passed (0.72 mm) and the pose was accepted 7.7 mm off (a pin 17.9 mm);
    no path of the proximal views passes within 2 mm of the surfaces' apparent contours. The
    per-view fit refuses it and names the view; the truth: 1.95 mm off, against 0.52 mm for
    the mean femur's four views at this seed (more than 2 mm before one robot swept every
    view)."""
    d = load_scene(find_scene("experiment2")).model_dump(mode="json")
    d["phantom"].update(shape_variation=3.0, shape_seed=5)
    scene = parse_scene(d)
    res, _, _, est = run_case(scene, seed=scene.scene.seed)
    assert not est.accepted
    assert "view proximal_ap does not fit" in est.message
    assert est.quality["worst_view_fit"] < MIN_VIEW_FIT
    # the truth: more than twice the mean femur's four views (0.38 mm at this seed); 1.95 mm
    # before the CT operator's per-slice streams (2026-11-27), 1.34 mm with them
    assert res["mtre_mm"] > 1.0


@pytest.mark.slow
def test_slices_outlined_off_the_bone_are_left_out_and_said():
    """Clinic experiment2 with the operator's bone threshold at 150 HU (allowed), seed 1 (a
    review, 2026-11-27): slices at the distal end were outlined around something else than
    the bone, and the whole run ended in the surface's tiling error. The slices whose
    contours continue no neighbour's are left out, the estimate says so in its warnings,
    and the pose is found (measured: 3 slices left out, mTRE 0.40 mm, accepted). The
    operator here reuses clicks however far off the bone they lie: since 2026-11-29 the
    clinic's operator clicks anew there (``ct_reclick_off_px``), and at 150 HU outlines no
    slice off the bone (measured: none left out, mTRE 0.52 mm, accepted)."""
    d = load_scene(find_scene("experiment2")).model_dump(mode="json")
    d["operator"]["ct_bone_threshold_hu"] = 150.0
    d["operator"]["ct_reclick_off_px"] = 10_000.0
    res, _, _, est = run_case(parse_scene(d), seed=1)
    notes = [w for w in est.warnings if "left out of its surface" in w]
    assert len(notes) == 1 and notes[0].startswith("CT region 'distal': ")
    assert est.accepted and res["mtre_mm"] < 1.0


@pytest.mark.slow
def test_ct_surfaces_of_the_wrong_hand_are_refused_and_were_wrong():
    """A held-out review (2026-11-28) registered a femur surface of its own (the phantom's
    mesh) flipped front to back (a CT axis reversed, or the other side's bone): the AP
    views' outlines hardly change, and the pose was accepted with a pin 26.9 mm off, every
    figure inside its limit. Mirrored back across the views' beam the surface fits clearly
    better: refused, and the truth agrees. The right surface's mirror fits worse: accepted.
    (The operator's CT surfaces, flipped, are refused by their median distance already.)"""
    import numpy as np

    from reglib import estimate, prepare
    from reglib.pipeline import MIRROR_FIT_RATIO, MIRRORED

    scene = load_scene(find_scene("experiment2"))
    _, case, start, est = run_case(scene, seed=scene.scene.seed)
    obs, st = case.sim.observation, est.stages
    mesh = case.sim.truth.meshes["femur"]
    v, f = np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces)
    c = v.mean(axis=0)

    def flip(p):   # ct y (front to back) reversed about the mesh's centre
        return (np.asarray(p) - c) * [1.0, -1.0, 1.0] + c

    pins = case.pins_ct
    for flipped, surface, planned in ((False, (v, f), pins),
                                      (True, (flip(v), f[:, ::-1].copy()),
                                       {k: flip(p) for k, p in pins.items()})):
        st2 = prepare(obs, calibrations=st.calibrations, contours=st.contours,
                      surfaces={"femur": surface})
        e = estimate(obs, start, stages=st2)
        ratio = e.quality["mirror_median_mm"] / e.quality["median_residual_mm"]
        err = max(np.linalg.norm(e.ct2robot.apply(planned[k]) - case.ct2robot.apply(p))
                  for k, p in pins.items())
        if not flipped:
            assert e.accepted and ratio > 1.5 and err < 1.0
        else:   # the truth: the pins as planned on the flipped CT land far from the pins
            assert not e.accepted and e.message.startswith(MIRRORED)
            assert ratio < MIRROR_FIT_RATIO and err > 5.0


@pytest.mark.slow
def test_two_views_and_a_pin_on_a_coarse_ct_are_refused_and_were_wrong():
    """experiment1 (two views and a located pin) on CT slices 10 mm apart (a held-out review,
    2026-11-28): accepted with distal pins 5.8 and 7.5 mm off at a weakest motion of 4.8 mm;
    the surfaces' error between coarse slices is not in the contours' median distance that
    the weakest motion scales with. The limit shrinks with the slice gap ((8/10)^2 x 6 mm)."""
    from reglib.pipeline import weak_motion_limit

    d = load_scene(find_scene("experiment1")).model_dump(mode="json")
    d["ct"].update(schedule="uniform", uniform_spacing_mm=10.0)
    scene = parse_scene(d)
    res, case, _, est = run_case(scene, seed=scene.scene.seed)
    assert est.stages.slice_gap_mm == pytest.approx(10.0)
    assert weak_motion_limit(case.options, est.stages.slice_gap_mm) == pytest.approx(3.84)
    assert not est.accepted
    assert "limit 3.8 mm: 6 mm x (8/10.0)^2 for CT slices contoured up to 10.0 mm" \
        in est.message
    assert max(res["pins"].values()) > 4.0     # the truth: it was wrong


@pytest.mark.slow
def test_slices_thicker_than_their_gaps_are_read_as_gaps_and_accepts_lie_within_the_stated_motion():
    """experiment2 with every slice 10 mm thick on its 1/6 mm schedule (a held-out review,
    2026-11-28, h80): accepted at mTRE 2.25 mm with a pin 3.09 mm off, the gaps no wider
    than 6 mm. The slices' thickness, which the observation gives, now counts as a gap: the
    weakest motion's limit is 3.84 mm. Since the CT operator clicks anew where the bone moved
    off its clicks (2026-11-29) the scene's seed ends at a knife's edge: pins 3.05-3.19 mm
    off, weakest motion 3.82 mm, accepted (before: 6.26 mm, refused). The contract tested:
    a pose the verdict accepts lies within the weakest motion it states; a pose it refuses
    names the slices' thickness (seed 3: pins 2.84-2.93 mm off, refused)."""
    from reglib.pipeline import weak_motion_limit, z_resolution

    d = load_scene(find_scene("experiment2")).model_dump(mode="json")
    d["ct"].update(slice_thickness_mm=10.0)
    scene = parse_scene(d)
    for seed in (scene.scene.seed, 3):
        res, case, _, est = run_case(scene, seed=seed)
        assert est.stages.slice_gap_mm <= 6.0 + 1e-6
        assert est.stages.slice_thickness_mm == pytest.approx(10.0)
        assert z_resolution(est.stages) == (pytest.approx(10.0), "10.0 mm thick")
        assert weak_motion_limit(case.options, 10.0) == pytest.approx(3.84)
        worst = max(res["pins"].values())
        if est.accepted:
            assert worst <= est.quality["weak_motion_mm"] <= 3.84, (seed, worst)
        else:
            assert "for CT slices contoured up to 10.0 mm thick" in est.message, seed
        if seed == 3:
            assert not est.accepted and worst > 2.0      # the truth: it was wrong


@pytest.mark.slow
def test_a_least_squares_pose_pulled_by_outliers_is_refused_and_was_wrong():
    """The capture-range study (2026-11-29, clinic profile, seed 1996) accepted the "linear"
    baseline (plain least squares over the matches) 3.2 mm off on its first random case,
    every verdict figure inside its limit. The robust solve from that pose moves the bone
    by about 4 mm to the truth: refused, and the truth agrees. From the robust pose the
    same solve does not move: accepted, with no such test (the method is robust)."""
    import numpy as np

    import studies.capture_range as cr
    from reglib.pipeline import PULLED, EstimateOptions, robust_shift
    from studies.end_to_end import prepare_case, register_case
    from studies.runner import make_trials
    from studies.scoring import PIN_NAMES, mtre

    tr = make_trials(str(find_scene("experiment2")), 1996,
                     cr.trial_params(cases=1, starts_per_bin=1))[0]
    scene_rng, sim_ss, _, _ = tr.rng().spawn(4)
    case = prepare_case(cr.case_scene(load_scene(tr.scene), scene_rng),
                        int(sim_ss.integers(0, 2**63 - 1)), sweeps=False)
    pins = np.array([case.pins_ct[k] for k in PIN_NAMES])
    lin, _ = register_case(case, case.ct2robot, **cr.METHODS["linear"])
    rob, _ = register_case(case, case.ct2robot, **cr.METHODS["robust"])
    assert lin.converged and not lin.accepted and lin.message.startswith(PULLED)
    limit = EstimateOptions().accept_max_robust_shift_mm
    assert lin.quality["robust_shift_mm"] > limit and mtre(lin.ct2robot, case.ct2robot,
                                                           pins) > 2.0
    assert rob.accepted and "robust_shift_mm" not in rob.quality
    assert mtre(rob.ct2robot, case.ct2robot, pins) < 1.0
    st = rob.stages
    tops = [st.topology(r) for r in sorted(st.surfaces)]
    opts = {**case.options.registration, "residual": "normal", "method": "linear"}
    assert robust_shift(tops, st.views, rob.ct2robot, opts) < 0.1
    assert robust_shift(tops, st.views, lin.ct2robot, opts) == pytest.approx(
        lin.quality["robust_shift_mm"])
    # the figure is the converged robust solve's: its own 50-iteration registration moves
    # the surfaces as far, within 1 % (a single iteration falls 3 % short)
    from reglib.register import register

    full = register(tops, st.views, lin.ct2robot, **{**opts, "method": "robust",
                                                     "max_iterations": 50})
    v = np.vstack([t.vertices for t in tops])
    moved = np.sqrt(np.mean(np.sum((full.ct2robot.apply(v) - lin.ct2robot.apply(v)) ** 2,
                                   axis=1)))
    assert lin.quality["robust_shift_mm"] == pytest.approx(moved, rel=0.01)
    # the caller's own divergence limits below the pull do not hide it (h94: with
    # max_motion_mm = 3 the robust solve "diverged", the figure was NaN and the pose 3.2 mm
    # off was accepted)
    for tight in ({"max_motion_mm": 2.0}, {"max_rotation_deg": 0.5}):
        assert robust_shift(tops, st.views, lin.ct2robot, {**opts, **tight}) == pytest.approx(
            lin.quality["robust_shift_mm"])
    again, _ = register_case(case, lin.ct2robot, **cr.METHODS["linear"], max_motion_mm=3.0)
    assert not again.accepted and again.message.startswith(PULLED)


@pytest.mark.slow
def test_a_robust_solve_with_a_huge_tukey_constant_is_checked_as_least_squares():
    """experiment2 with ``[registration] tukey_a = 50`` (a held-out review, h95): every match
    kept, as by least squares; the pose was accepted with the proximal pin 3.5 mm off, the
    check of poses registered otherwise than by the default solve skipped (a robust
    contour-normal solve), and its own solve, run with the caller's constant, moved the
    pose 0.13 mm. The check's solve keeps register's constant: it moves the pose 2.4 mm,
    and the estimate is refused."""
    from reglib.pipeline import PULLED, ROBUST_SHIFT_MM

    d = load_scene(find_scene("experiment2")).model_dump(mode="json")
    d["registration"]["tukey_a"] = 50.0
    res, case, _, est = run_case(parse_scene(d), seed=1996)
    assert not est.accepted and est.message.startswith(PULLED), est.message
    assert est.quality["robust_shift_mm"] > 2.0 * ROBUST_SHIFT_MM
    assert max(res["pins"].values()) > 3.0                   # the truth: it was wrong
