"""Mutation audit 3: estimate's verdict counts the views it REGISTERED, not the failed
ones too: with a view left out, fewer than accept_min_views remain and the pose is not
accepted. Counting the failed views as usable passed the whole suite (slow tests too)."""
from reglib.pipeline import EstimateOptions, Stages, estimate
from studies.bench.registration import make_scene


def _stages(views, failed):
    scene = make_scene()
    surfaces = {f"r{k}": (t.vertices, t.faces) for k, t in enumerate(scene.surfaces)}
    vs = [scene.views[n] for n in views]
    return Stages(calibrations={}, surfaces=surfaces, contours={}, views=vs,
                  failed=failed, timings={}), scene.true


def test_a_left_out_view_does_not_count_towards_accept_min_views():
    names = list(make_scene().views)
    stages, true = _stages(names[:2], {names[2]: "calibration failed"})
    opts = EstimateOptions(restarts=0, accept_min_views=3)
    est = estimate(None, true, options=opts, stages=stages)
    assert not est.accepted
    assert "only 2 usable view(s), need 3 to accept" in est.message, est.message
    assert f"left out: {names[2]}" in est.message
    # the same two views without a failed one: the same objection
    stages2, _ = _stages(names[:2], {})
    est2 = estimate(None, true, options=opts, stages=stages2)
    assert "only 2 usable view(s), need 3 to accept" in est2.message
