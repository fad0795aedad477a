"""How a correct-looking distal surface pulled the pose away (issue 12, item 1).

One varied femur (experiment2, ``[phantom] shape_variation = 1``, right, case seed 2; the
true calibration, no sweep simulated): its reconstructed distal surface lies 0.1-0.2 mm
from the bone on average, yet the registration with the paper's point-to-path residual
ended 6.3 mm off from 3 mm starts, where the true surfaces give 0.15 mm.

The mechanism, measured at the true pose: a few CT contour vertices per slice stayed
1-2.5 mm inside the bone (the snake left them off the edge and the sub-pixel step held
them there). Each is a dent of the tiled surface; a dent seen at a grazing angle (near
the bone's outline, where the X-ray paths are) makes a small closed apparent contour, and
there were 36 and 24 of them from the two distal views (the true surface: 0 and 2). The
paper's Step B gives an external path the *farthest* contour it stabs, and a small loop
within ``max_stab_distance_mm`` (10 mm) of the outline is stabbed by the paths around it,
so 23 % and 34 % of the paths that the true surface matches within 1 mm were matched 1 to
10 mm off, to those loops. Fixed in ``reglib.contours.refine_subpixel`` (the neighbours'
edges); this test keeps the whole chain honest on the femur that showed it.
"""

import dataclasses

import numpy as np
import pytest

from reglib.apparent import apparent_contours, prepare_surface
from reglib.register import match_view
from studies.scoring import start_at_mtre

SEED = 2
#: the femur's shape seed when the mechanism was found (then drawn from case seed 2's shape
#: stream alone; testbed.simulate now mixes the scene's shape_seed in, so it is pinned here;
#: so are its level condyles, drawn before the knee's joint-line angle existed: 89.9 deg
#: with this seed's variation, 0.1 mm of tilt)
FEMUR_SHAPE_SEED = 2143825141
SMALL_LOOP_EDGES = 8


@pytest.fixture(scope="module")
def case():
    import testbed.simulate
    from studies.end_to_end import prepare_case
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    phantom = scene.phantom.model_copy(update={"shape_variation": 1.0, "side": "right"})
    workspace = scene.workspace.model_copy(update={"check": False})
    scene = scene.model_copy(update={"phantom": phantom, "workspace": workspace})

    def the_femur_that_showed_it(scene, _shape_stream):
        return scene.model_copy(update={"phantom": scene.phantom.model_copy(
            update={"shape_seed": FEMUR_SHAPE_SEED, "distal_joint_angle_deg": 90.0})})

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(testbed.simulate, "_case_scene", the_femur_that_showed_it)
        return prepare_case(scene, SEED, sweeps=False)


def _distal_views(case):
    return [v for v in case.stages.views if v.name.startswith("distal")]


def _true_distal(case):
    from studies.oracles import true_surfaces

    return true_surfaces(case.sim, case.stages.surfaces)["distal"]


def test_estimated_distal_surface_shows_few_spurious_apparent_contours(case):
    est = prepare_surface(*case.stages.surfaces["distal"])
    true = prepare_surface(*_true_distal(case))
    robot2ct = case.ct2robot.inverse()
    for v in _distal_views(case):
        c = robot2ct.apply(v.center)
        small = [sum(1 for x in apparent_contours(top, c)
                     if x.closed and len(x.vertex_ids) <= SMALL_LOOP_EDGES)
                 for top in (est, true)]
        assert small[1] <= 3, (v.name, small)
        assert small[0] <= 8, (v.name, small)       # was 36 and 24


def _line_residuals(surfaces, view, pose):
    tops = [prepare_surface(*s) for s in surfaces]
    p, _, _, _ = match_view(tops, view, pose, max_stab_distance_mm=10.0)
    w = pose.apply(p) - view.origins
    return np.linalg.norm(w - np.sum(w * view.directions, axis=1)[:, None] * view.directions,
                          axis=1)


def test_paths_the_true_surface_matches_are_matched_by_the_estimated_one(case):
    from studies.oracles import true_surfaces

    est = [case.stages.surfaces[r] for r in sorted(case.stages.surfaces)]
    tru = true_surfaces(case.sim, case.stages.surfaces)
    tru = [tru[r] for r in sorted(tru)]
    for v in _distal_views(case):
        r_true = _line_residuals(tru, v, case.ct2robot)
        r_est = _line_residuals(est, v, case.ct2robot)
        good = r_true < 1.0
        assert good.sum() > 250, v.name
        wrong = float(np.mean(r_est[good] > 1.0))
        assert wrong < 0.18, (v.name, wrong)            # was 0.23 and 0.34


@pytest.mark.parametrize("residual,bound_mm", [("line", 1.0), ("normal", 0.6)])
def test_registration_from_3mm_lands_on_the_pins(case, residual, bound_mm):
    """The estimated surfaces from two 3 mm starts, one loop (no coarse stage, no restarts):
    was 6.3 mm with the point-to-path residual and 0.27 mm with the across-contour one.

    Over six noise realisations of this case (the fast and the exact quantum sampler, four
    reseeded) the fixed chain gave 0.19-0.55 mm (line) and 0.10-0.41 mm (normal); the
    bounds sit above that spread, so they catch the mechanism (mm), not a realisation."""
    from reglib.pipeline import estimate

    options = dataclasses.replace(case.options, strategy="single", restarts=0,
                                  registration={**case.options.registration,
                                                "residual": residual})
    pins = np.array(list(case.pins_ct.values()))
    for k in range(2):
        start = start_at_mtre(case.ct2robot, pins, 3.0, np.random.default_rng([0, k, 30]))
        est = estimate(case.sim.observation, start, options=options, stages=case.stages)
        err = np.linalg.norm(est.ct2robot.apply(pins) - case.ct2robot.apply(pins), axis=1)
        assert err.mean() < bound_mm, (residual, k, err)
        assert est.accepted, est.message
