"""Mutation audit 3: register stops, unconverged, when the solver keeps fewer than
min_inlier_fraction of the matches. No test reached that stop: halving the limit passed
the whole suite."""

from reglib.register import register
from studies.bench.registration import make_scene


def test_too_few_inliers_stop_the_loop():
    scene = make_scene()
    tops, views, true = scene.surfaces, list(scene.views.values()), scene.true
    res = register(tops, views, true)
    frac = res.history[0].inlier_fraction
    assert res.converged and 0.55 < frac < 0.95, frac
    # a limit just above what the solver keeps: refused at the first iteration
    lim = min(1.0, frac + 0.03)
    stopped = register(tops, views, true, min_inlier_fraction=lim)
    assert not stopped.converged and stopped.iterations == 1
    assert stopped.reason.startswith("too few inliers at iteration 1"), stopped.reason
