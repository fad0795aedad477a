"""Regression suite for reglib: the accuracy each stage keeps on a small seeded reference case.

The reference sets are simulated here, once per test session (module-scoped fixtures): the
ideal profile of the paper's second experiment (``scenes/experiment2-ideal.toml``: every
error source small) in a lighter form (a 5-row calibration sweep per plane), seed 11, with
one proximal and one distal view for the stages and with its four views for the
registration (two near-parallel views leave the depth along their beams to the noise's
draw). Every stage of reglib runs on them as in the end-to-end job and is scored against
the simulator's truth:

- calibration: validation distances (mm) of one view's validation row to its calibrated
  X-ray paths;
- surfaces: mean distance (mm) from the reconstructed CT surfaces to the true femur;
- X-ray contours: mean distance (px) of the snake's points to the true apparent contour;
- registration: pin errors (mm) from seeded starts, with estimated inputs and with true ones
  (the latter isolates the pose solver), and how many starts converge.

Each threshold is the figure measured when the suite was written, with a margin (about 1.5x,
rounded up), written beside it; a change that makes a stage worse than that fails. Figures
that are better than measured pass: tighten the thresholds when reglib improves.
"""

import re

import numpy as np
import pytest

from testbed.scene import parse_scene

pytestmark = pytest.mark.slow

SEED = 11


def _scene(views=("proximal_ap", "distal_ap")):
    """The ideal profile (scenes/experiment2-ideal.toml) with a 5-row sweep per plane, to
    keep the suite quick, and ``views`` of its views (None: all four)."""
    from testbed.scene import find_scene, load_scene

    d = load_scene(find_scene("experiment2-ideal")).model_dump(mode="json")
    d["scene"]["name"], d["scene"]["seed"] = "regression", SEED
    if views is not None:
        d["views"] = [v for v in d["views"] if v["name"] in views]
    d["robot"]["sweep"]["rows_per_plane"] = 5
    return parse_scene(d)


TRUE_INPUTS = ("calibration", "surfaces", "contours")
N_STARTS = 5
# registration options written out, so that a change of the scene defaults does not change
# what this suite measures: reglib's own defaults (across-contour residual, Tukey 4.685)
REGISTRATION = {"strategy": "single", "method": "robust", "residual": "normal",
                "tukey_a": 4.685, "selection": "paper", "max_stab_distance_mm": 10.0,
                "max_iterations": 50}


@pytest.fixture(scope="module")
def case():
    """Two views, one per end of the femur: every stage but the registration."""
    from studies.end_to_end import prepare_case

    return prepare_case(_scene(), SEED)


@pytest.fixture(scope="module")
def case4():
    """The four views: the registration. Two parallel views (``case``) hold the bone's depth
    along their beams only through the magnification, and its largest pin error went with
    the noise's draw, not with reglib: 0.61, 0.71, 1.35, 2.22, 1.78, 1.49, 1.36 and 0.80 mm
    at seeds 11-18 (2026-11-27), 0.04-0.27 mm of it across the beams. With the four views:
    0.26-0.48 mm at seeds 11-16, so a limit here bounds reglib, not one draw."""
    from studies.end_to_end import prepare_case

    return prepare_case(_scene(views=None), SEED)


def _starts(case, angle_deg, *, about=None):
    from studies.scoring import perturbed_start

    rngs = np.random.SeedSequence([SEED, int(angle_deg * 10)]).spawn(N_STARTS)
    return [perturbed_start(case.ct2robot, case.pins_ct, angle_deg, np.random.default_rng(r),
                            about=about) for r in rngs]


def _register_all(case, starts, *, oracle=(), fixed_pin=None):
    """Per start: (largest pin error mm, converged)."""
    from studies.end_to_end import register_case

    out = []
    for s in starts:
        res, errs = register_case(case, s, oracle=oracle, fixed_pin=fixed_pin, **REGISTRATION)
        out.append((max(errs.values()), bool(res.converged)))
    return out


def test_calibration_validation_distances():
    """One view swept and calibrated: markers of the validation row to their X-ray paths."""
    from studies.calibration import calibrate_view

    rows = calibrate_view(_scene(), 0, np.random.default_rng(SEED))
    d = np.array([r["value"] for r in rows if r["metric"] == "validation_distance"])
    assert len(d) >= 8, "too few validation markers detected"
    # measured: 8 markers, max 0.098 mm, mean 0.058 mm (commit ceaed24); max 0.136 mm, mean
    # 0.072 mm after the per-region detection threshold (f9a48f4). Paper: 0.1-0.4 mm.
    assert d.max() < 0.2
    assert d.mean() < 0.11


def test_surfaces_mean_distance_to_true_femur(case):
    from studies.surfaces import distances_to_truth

    assert set(case.surfaces) == {"distal", "proximal"}
    for region, (v, f) in sorted(case.surfaces.items()):
        d = distances_to_truth(case.sim.world.phantom, v, f, n_samples=5000,
                               rng=np.random.default_rng(SEED))
        # measured: mean distal 0.110 mm, proximal 0.098 mm; 95th percentile 0.41 / 0.27 mm
        assert d.mean() < 0.17, region
        assert np.percentile(d, 95) < 0.65, region


def test_xray_contours_mean_distance_to_true_outline(case):
    from scipy.spatial import cKDTree

    from studies.oracles import silhouette_points

    femur = case.sim.world.phantom.femur.copy()
    femur.apply_transform(case.ct2robot.as_matrix())
    for v, carm in case.sim.carms.items():
        xy = case.stages.contours[v].xy
        assert len(xy) > 300, v
        sil = silhouette_points(femur, carm.source_robot, step_mm=0.2)
        true_xy = carm.project(sil)
        d, _ = cKDTree(true_xy).query(xy)
        # measured: mean proximal_ap 0.35 px, distal_ap 0.43 px; median 0.26 / 0.24 px
        assert d.mean() < 0.65, v
        assert np.median(d) < 0.4, v


def test_a_view_of_grey_noise_traces_nothing(case):
    """A review gave one view a frame of flat grey plus noise: the operator's clicks were
    traced along the noise and the estimate accepted at mTRE 1.5 mm. With the case's own
    clicks on such frames (noise of 1-8 grey levels) every trace is now refused as standing
    no higher than the frame's noise, and the view has no contour (reglib leaves it out and
    names it); the real frames keep every trace."""
    from reglib.pipeline import xray_contours
    from reglib.xray_contours import field_of_view_mask

    obs = case.sim.observation
    rng = np.random.default_rng(SEED)
    for v in case.sim.carms:
        img = np.asarray(obs.images[f"xray_{v}"], dtype=float)
        clicks = obs.arrays[f"xray_clicks_{v}"]
        real = xray_contours(v, obs.images[f"xray_{v}"], clicks)
        assert len(real.xy) > 300 and not real.problems, (v, real.problems)
        mask = field_of_view_mask(img)
        for sd in (1.0, 8.0):
            grey = np.where(mask, img[mask].mean() + rng.normal(0.0, sd, img.shape), img)
            con = xray_contours(v, np.clip(np.rint(grey), 0, 255).astype(np.uint8), clicks)
            assert len(con.xy) == 0, (v, sd)
            assert len(con.problems) == len(clicks["external"])
            assert all("above the frame's noise" in p for p in con.problems), con.problems


def test_a_frame_not_taken_where_its_view_was_calibrated_leaves_the_view_out(case):
    """A review gave views frames shifted by 20 px, mirrored, turned or of another view:
    8 estimates were accepted 2-13 mm off. Each view's frame is now compared with its
    sweep's reference frame (the same C-arm pose): its own frame passes; shifted (with the
    operator's clicks shifted alike), turned, or the other view's, the view is left out
    and named, and with one view left the estimate is refused."""
    import dataclasses

    from reglib.pipeline import prepare, sweep_agreement

    obs = case.sim.observation
    views = list(case.sim.carms)
    for v in views:
        assert sweep_agreement(v, obs.images[f"xray_{v}"], obs.images[f"sweep_{v}"],
                               obs.arrays[f"sweep_{v}"], 0.4) == ""
    v, other = views
    x = np.asarray(obs.images[f"xray_{v}"])
    clicks = dict(obs.arrays[f"xray_clicks_{v}"])
    moved = {**clicks, "clicks_xy": np.asarray(clicks["clicks_xy"]) + [20.0, 0.0]}
    for frame, cl, why in ((np.roll(x, 20, axis=1), moved, r"shifted by \(\+20, \+0\) px"),
                           (x[::-1, ::-1], clicks, "do not show the same scene"),
                           (obs.images[f"xray_{other}"], obs.arrays[f"xray_clicks_{other}"],
                            "do not show the same scene")):
        o = dataclasses.replace(obs, images={**obs.images, f"xray_{v}": frame},
                                arrays={**obs.arrays, f"xray_clicks_{v}": cl})
        st = prepare(o, options=case.options, surfaces=case.stages.surfaces,
                     calibrations=case.stages.calibrations)
        assert [w.name for w in st.views] == [other]
        assert re.search(why, st.failed[v]), st.failed[v]


def test_a_frame_of_another_size_than_its_sweep_leaves_the_view_out(case):
    """A review (2026-11-27) cropped the X-ray frames by 12 px (the clicks moved alike): the
    sweep's calibration read them in a frame it does not describe, and the estimate was
    accepted with the pins 5.2-5.5 mm off. A view whose frame, or field-of-view mask, is not
    its sweep frames' size is now left out and named with both sizes."""
    import dataclasses

    from reglib.pipeline import frame_size_problem, prepare

    obs = case.sim.observation
    v, other = list(case.sim.carms)
    x = np.asarray(obs.images[f"xray_{v}"])
    H, W = x.shape
    assert frame_size_problem(v, x.shape, obs.images[f"sweep_{v}"],
                              obs.arrays[f"xray_fov_{v}"]) == ""
    clicks = dict(obs.arrays[f"xray_clicks_{v}"])
    cropped = {**clicks, "clicks_xy": np.asarray(clicks["clicks_xy"]) - 12.0}
    fov = np.asarray(obs.arrays[f"xray_fov_{v}"])
    for frame, mask, why in (
            (x[12:, 12:], fov, rf"X-ray frame is {H - 12} x {W - 12} px .* sweep's frames "
                               rf"{H} x {W} px"),
            (x[12:, 12:], fov[12:, 12:], rf"X-ray frame is {H - 12} x {W - 12} px"),
            (x, fov[12:, 12:], rf"field-of-view mask .* is {H - 12} x {W - 12} px")):
        o = dataclasses.replace(obs, images={**obs.images, f"xray_{v}": frame},
                                arrays={**obs.arrays, f"xray_fov_{v}": mask,
                                        f"xray_clicks_{v}": cropped if frame is not x
                                        else clicks})
        # with the calibrations given, and calibrating here (a review: calibrate_view
        # refused the mask of another size, and the whole estimate ended)
        for given in (case.stages.calibrations, None):
            st = prepare(o, options=case.options, surfaces=case.stages.surfaces,
                         calibrations=given)
            assert [w.name for w in st.views] == [other]
            assert re.search(why, st.failed[v]), st.failed[v]


class _ShiftedPaths:
    """A view's calibration whose paths of the pixels ``moved_xy`` (px) are moved sideways by
    ``shift_mm`` (robot mm), as a spline that extrapolates past the sweep's beads moves the
    outline's paths there; its planes, its markers' paths and its center of perspective are
    the calibration's."""

    def __init__(self, calibration, shift_mm: float, moved_xy):
        self.calibration, self.shift_mm = calibration, shift_mm
        self.moved_xy = np.asarray(moved_xy, dtype=np.float64)
        self.near, self.far = calibration.near, calibration.far

    def paths(self, xy):
        xy = np.asarray(xy, dtype=np.float64)
        o, d = self.calibration.paths(xy)
        side = np.cross(d, [0.0, 0.0, 1.0])
        side /= np.linalg.norm(side, axis=1, keepdims=True)
        moved = (xy[:, None, :] == self.moved_xy[None]).all(axis=2).any(axis=1)
        return o + self.shift_mm * moved[:, None] * side, d

    def center_of_perspective(self):
        return self.calibration.center_of_perspective()


def test_a_view_whose_paths_miss_its_source_is_left_out_and_named(case):
    """A held-out review (2026-11-28) found calibrations used where the sweep's beads never
    reached: the paths of the bone's outline missed the calibrated source by a median 3-10
    mm (1.1-8 mm off at the bone) with a validation of 0.2-0.5 mm, and poses were accepted
    with mTRE 2.1-2.6 mm; past 10 mm the registration's own check ended the whole estimate.
    Such a view is now left out, named with the figure; the simulated views pass well
    within the limit."""
    import dataclasses

    from reglib.pipeline import MAX_PATH_MISS_MM, prepare, supported_centre

    v, other = list(case.sim.carms)
    cals = case.stages.calibrations
    for name in (v, other):    # the simulated calibrations: within the clinic's spread
        assert case.stages.path_miss_mm[name] < 0.6 * MAX_PATH_MISS_MM, case.stages.path_miss_mm
        # the source where the covered markers' paths meet: near the true focal spot (the
        # paths are nearly parallel, so a source is found to mm along the beam)
        err = np.linalg.norm(supported_centre(cals[name].calibration)
                             - case.sim.carms[name].source_robot)
        assert err < 5.0, (name, err)
    xy = case.stages.contours[v].xy
    part = xy[xy[:, 0] > np.median(xy[:, 0]) - 20.0]     # a little over half the outline
    for shift, moved, limit, left_out, why in (
            (1.0, xy, MAX_PATH_MISS_MM, False, ""),
            (4.0, xy, MAX_PATH_MISS_MM, True, r"miss the calibrated source by a median "
             r"[34]\.\d mm \(at most 2\.5 mm, EstimateOptions\.max_path_miss_mm"),
            (6.0, part, MAX_PATH_MISS_MM, True, r"by a median [3-6]\.\d mm"),
            # the limit lifted: the registration's own check (10 mm) names the view and
            # leaves it out instead of ending the estimate
            (30.0, xy, 1e9, True, r"calibration: .*is not where the view's paths meet")):
        bad = {**cals, v: dataclasses.replace(cals[v],
                                              calibration=_ShiftedPaths(cals[v].calibration,
                                                                        shift, moved))}
        opts = dataclasses.replace(case.options, max_path_miss_mm=limit)
        st = prepare(case.sim.observation, options=opts, surfaces=case.stages.surfaces,
                     calibrations=bad, contours=case.stages.contours)
        assert [w.name for w in st.views] == ([other] if left_out else [v, other]), shift
        if left_out:
            assert re.search(why, st.failed[v]), st.failed[v]
            # the calibration kept in the stages says so too (the run's JSON had shown
            # calibration_ok true beside the failure)
            assert not st.calibrations[v].ok and st.calibrations[v].message == st.failed[v]
        else:
            assert v not in st.failed and st.calibrations[v].ok


def test_a_strong_pincushion_puts_the_supported_centre_at_the_focal_spot():
    """A pincushion 4 times the ideal profile's: the near plane's markers at the field's edge
    bend its fitted paths, and the point nearest all of them (center_of_perspective) lies
    13.8-15.6 mm from the focal spot; where the markers both planes cover meet
    (supported_centre) lies within 1 mm of it, and the path check that leaves views out
    measures the outline's paths from that point (a mutation audit, h99: measuring them
    from center_of_perspective passed every test)."""
    from reglib.pipeline import MAX_PATH_MISS_MM, path_miss, supported_centre
    from studies.end_to_end import prepare_case

    d = _scene().model_dump(mode="json")
    d["fluoroscope"]["pincushion_k1"] *= 4.0
    d["fluoroscope"]["pincushion_k2"] *= 4.0
    strong = prepare_case(parse_scene(d), SEED)
    st = strong.stages
    assert [w.name for w in st.views] == list(strong.sim.carms) and not st.failed, st.failed
    for v, carm in strong.sim.carms.items():
        cal = st.calibrations[v].calibration
        assert np.linalg.norm(supported_centre(cal) - carm.source_robot) < 1.0, v
        assert np.linalg.norm(cal.center_of_perspective() - carm.source_robot) > 8.0, v
        o, dirs = cal.paths(st.contours[v].xy)
        assert st.path_miss_mm[v] == path_miss(supported_centre(cal), o, dirs), v
        assert st.path_miss_mm[v] < MAX_PATH_MISS_MM


def test_a_view_whose_validation_fails_is_left_out_and_named(case):
    """A validation bead the robot reports 3 mm across the beam from where it was: the
    view's calibration fails its validation, and prepare() leaves the view out, names it
    and keeps the failed calibration as not ok, while the other view is used (a mutation
    audit, h99: with the failed calibration used all the same, every test passed; the
    calibration itself is attached, so only the flag keeps it out of the registration)."""
    import dataclasses

    from reglib.pipeline import prepare

    obs = case.sim.observation
    v, other = list(case.sim.carms)
    sweep = dict(obs.arrays[f"sweep_{v}"])
    reported = np.array(sweep["beads_reported"], dtype=np.float64, copy=True)
    f = int(np.flatnonzero(np.asarray(sweep["plane"]) == 2)[0])     # the validation row
    across = np.cross(case.sim.carms[v].axis_robot, [1.0, 0.0, 0.0])
    reported[f, 3] += 3.0 * across / np.linalg.norm(across)
    o = dataclasses.replace(obs, arrays={**obs.arrays,
                                         f"sweep_{v}": {**sweep, "beads_reported": reported}})
    st = prepare(o, options=case.options, surfaces=case.stages.surfaces,
                 contours=case.stages.contours)
    assert [w.name for w in st.views] == [other]
    assert "largest distance" in st.failed[v], st.failed[v]
    cal = st.calibrations[v]
    assert not cal.ok and cal.message == st.failed[v] and cal.calibration is not None
    assert 2.0 < np.max(cal.validation_mm) < 4.0, cal.validation_mm
    assert other not in st.failed and st.calibrations[other].ok


def test_a_view_left_out_after_its_calibration_passed_reads_as_not_used(case):
    """A held-out review (2026-11-28): table2, experiment1 and error-budget recorded
    ``calibration_ok`` alone, and a view left out after its calibration passed (here: no
    bone contour traced on its frame) read as passed. ``view_used`` says it was not used,
    with the method's reason, and the report section lists it."""
    import dataclasses

    import pandas as pd

    from reglib.pipeline import prepare
    from studies.end_to_end import case_rows, views_lost_markdown

    v, other = list(case.sim.carms)
    empty = dataclasses.replace(case.stages.contours[v], xy=np.zeros((0, 2)),
                                external=np.zeros(0, bool))
    st = prepare(case.sim.observation, options=case.options, surfaces=case.stages.surfaces,
                 calibrations=case.stages.calibrations,
                 contours={**case.stages.contours, v: empty})
    lost = dataclasses.replace(case, stages=st)
    rows = pd.DataFrame([{**r, "trial": 0, "case": 0} for r in case_rows(lost)])
    flag = rows[rows.metric == "calibration_ok"].set_index("view").value
    used = rows[rows.metric == "view_used"].set_index("view")
    assert flag[v] == 1.0 and flag[other] == 1.0     # the calibration passed ...
    assert used.value[v] == 0.0 and used.value[other] == 1.0      # ... the view not used
    assert used.reason[v].startswith("no bone contour could be traced") and not \
        used.reason[other]
    text = views_lost_markdown(rows)
    assert "**1 view-case(s) were left out" in text
    assert f"- {v}, case 0: no bone contour could be traced" in text
    # every view used: one line saying so
    ok = pd.DataFrame([{**r, "trial": 0, "case": 0} for r in case_rows(case)])
    assert views_lost_markdown(ok).startswith("Every view was used in every case (1 case(s)")


def test_registration_pin_errors_with_true_inputs(case4):
    """The pose solver alone: with the true rays, surfaces and contours it finds the pose."""
    res = _register_all(case4, _starts(case4, 3.0), oracle=TRUE_INPUTS)
    errs = np.array([e for e, _ in res])
    # measured: every start converges, largest pin error 2e-11 mm (1e-11 mm at seeds 11-16)
    assert all(c for _, c in res)
    assert errs.max() < 1e-6


def test_registration_pin_errors_with_estimated_inputs(case4):
    """The whole method: from 3 deg starts every start converges to the same pose."""
    res = _register_all(case4, _starts(case4, 3.0))
    errs = np.array([e for e, _ in res])
    # measured on the ideal profile's four views (5-row sweeps): all 5 converge, largest pin
    # error 0.319 mm; 0.26-0.48 mm at seeds 11-16. The limit is the one set on the two-view
    # case (0.543 mm then; since 2026-11-27 on this case, see case4)
    assert all(c for _, c in res)
    assert errs.max() < 0.85
    fixed = _register_all(case4, _starts(case4, 3.0, about="proximal"), fixed_pin="proximal")
    ferrs = np.array([e for e, _ in fixed])
    # with the proximal pin fixed (the paper's experiment 1): all converge, 0.340 mm;
    # 0.24-0.48 mm at seeds 11-16 (1.15 mm on the two-view case: limit 1.75 mm then)
    assert all(c for _, c in fixed)
    assert ferrs.max() < 0.85


def test_two_parallel_views_leave_only_the_depth_along_their_beams_loose(case):
    """With one AP view per end of the femur the beams are near parallel: the pose is held
    across them and loosely along them (through the magnification alone). The error lies
    along the beams, and the verdict's weakest motion covers it."""
    from studies.end_to_end import register_case

    pins = np.array(list(case.pins_ct.values()))
    truth = case.ct2robot.apply(pins)
    for start in _starts(case, 3.0)[:2]:
        est, _ = register_case(case, start, **REGISTRATION)
        assert est.registration.converged
        d = est.ct2robot.apply(pins) - truth
        for v, carm in case.sim.carms.items():
            dc = d @ carm.carm2robot.R              # in the view's frame, +z its beam
            across, along = np.abs(dc[:, :2]).max(), np.abs(dc[:, 2]).max()
            # measured: across 0.06 mm (0.04-0.27 mm at seeds 11, 14, 15), along 0.61 mm
            # (0.6-2.2 mm at seeds 11-18)
            assert across < 0.45, v
            assert along < est.quality["weak_motion_mm"], v


def test_registration_success_from_larger_starts(case4):
    """From 5 deg starts: how many reach the pose (the 3 deg figures above, 6 mm / 1e-6 mm)."""
    res = _register_all(case4, _starts(case4, 5.0))
    ok = sum(e < 6.0 for e, _ in res)
    truth = _register_all(case4, _starts(case4, 5.0), oracle=TRUE_INPUTS)
    ok_true = sum(e < 1e-6 for e, _ in truth)
    # measured on the ideal profile's four views: estimated inputs 5 of 5 (0.319 mm; 5 of 5
    # at seeds 11-16), true inputs 5 of 5
    assert ok >= 5
    assert ok_true >= 4
