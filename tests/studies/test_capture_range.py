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


def test_a_femur_given_as_a_mesh_has_region_centres_at_its_ends(tmp_path):
    """A user mesh has no named landmarks: its ends stand for them (a held-out review:
    every scene with [phantom] mesh_path stopped with "internal error: KeyError:
    'head_center'"). On the procedural femur exported as a mesh, they lie within 40 mm of
    the landmarks' centres, and the shipped views pass the region check."""
    import numpy as np

    from studies.common import check_view_regions, region_centres
    from testbed.phantom import make_phantom
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    ph = make_phantom(scene.phantom)
    path = tmp_path / "femur.stl"
    ph.femur.export(path)
    spec = scene.phantom.model_copy(update={
        "mesh_path": str(path), "mesh_pins_mm": {k: tuple(v) for k, v in ph.pins.items()}})
    mesh_ph = make_phantom(spec)
    assert mesh_ph.landmarks == {}
    want, got = region_centres(ph), region_centres(mesh_ph)
    for region in ("proximal", "distal"):
        assert np.linalg.norm(got[region] - want[region]) < 40.0, region
    check_view_regions(scene.model_copy(update={"phantom": spec}), phantom=mesh_ph)


def test_testbed_run_warns_of_a_mislabelled_view():
    from studies.end_to_end import _region_label_warnings
    from testbed.scene import find_scene, load_scene

    scene = load_scene(find_scene("experiment2"))
    assert _region_label_warnings(scene) == []
    views = list(scene.views)
    views[2] = views[2].model_copy(update={"region": "proximal"})
    (w,) = _region_label_warnings(scene.model_copy(update={"views": tuple(views)}))
    assert "views[2].region" in w and "whose verdict counts each region's views" in w
    assert "give(s) no region" not in w     # model_copy keeps the fields set


def test_the_capture_range_is_the_farthest_start_tried():
    """Not the passing bins' upper edge, which with few starts per bin claimed more than any
    start tried (30 mm reported, 21.7 mm the farthest start)."""
    import pandas as pd

    from studies.capture_range import capture_range

    s = pd.DataFrame({"method": ["m"] * 3, "bin": [0, 1, 2],
                      "success_rate": [1.0, 1.0, 0.5],
                      "start_mtre_max": [8.0, 17.5, 29.0]})
    assert capture_range(s, [0.0, 10.0, 20.0, 30.0]) == {"m": 17.5}
    s.loc[0, "success_rate"] = 0.0
    assert capture_range(s, [0.0, 10.0, 20.0, 30.0]) == {"m": 0.0}


def test_a_range_whose_every_bin_passed_is_reported_as_a_lower_bound():
    """A review (h87): "default: 30.0 mm" read as a measured range where every bin up to
    the farthest start tried had passed; such a range is "at least", a found one is not."""
    import pandas as pd

    from studies.capture_range import capture_range, range_lines

    edges = [0.0, 10.0, 20.0, 30.0]
    s = pd.DataFrame({"method": ["all"] * 3 + ["part"] * 3, "bin": [0, 1, 2] * 2,
                      "success_rate": [1.0, 1.0, 1.0, 1.0, 1.0, 0.5],
                      "start_mtre_max": [8.0, 17.5, 29.0, 8.0, 17.5, 29.0]})
    lines = range_lines(s, edges, capture_range(s, edges))
    assert lines == ["- all: **at least 29.0 mm** (every bin passed: the farthest start tried; "
                     "the range may reach further)", "- part: **17.5 mm**"]
    # a bin with no start of the method is no pass
    short = s[~((s.method == "all") & (s.bin == 2))]
    assert range_lines(short, edges, capture_range(short, edges))[0] == "- all: **17.5 mm**"


def test_scenes_the_study_cannot_use_are_refused_before_any_trial(tmp_path, capsys):
    """A review: a mesh femur failed every trial ('no plausible femur in 50 draws'), a
    fixed pin was ignored (capture range 0 mm, no word), a view labelled with the other
    region failed every trial in a message naming no file; all exited 1 after the work."""
    from studies.capture_range import check_scene
    from studies.cli import main
    from testbed.scene import find_scene, load_scene

    path = find_scene("experiment2")
    scene = load_scene(path)
    check_scene(scene, path)                    # the shipped scene is fine
    mesh = scene.model_copy(update={"phantom": scene.phantom.model_copy(
        update={"mesh_path": "femur.stl"})})
    pin = scene.model_copy(update={"registration": scene.registration.model_copy(
        update={"fixed_pin": "proximal"})})
    other = "distal" if scene.views[0].region == "proximal" else "proximal"
    swapped = scene.model_copy(update={"views": (scene.views[0].model_copy(
        update={"region": other}), *scene.views[1:])})
    for bad, message in ((mesh, r"\[phantom\] mesh_path: capture-range draws"),
                         (pin, r"\[registration\] fixed_pin = 'proximal': capture-range"),
                         (swapped, r"views\[0\]\.region")):
        with pytest.raises(ValueError, match=message) as err:
            check_scene(bad, path)
        assert str(path) in str(err.value)
    # through the command: exit 2 in one line, no folder left
    text = path.read_text().replace('region = "proximal"', 'region = "distal"', 1)
    (tmp_path / "sw.toml").write_text(text)
    out = tmp_path / "cr"
    assert main(["study", "capture-range", "--quick", "--scene", str(tmp_path / "sw.toml"),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "sw.toml" in err and "region" in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_a_study_whose_trials_all_failed_lists_each_error_once(tmp_path):
    """A review: capture-range listed every failed trial twice, under its own heading and
    under 'Failed trials'."""
    import pandas as pd

    from studies.common import StudyContext, finish_study, nothing_finished
    from testbed.scene import find_scene, load_scene

    path = find_scene("points-lines")
    ctx = StudyContext(name="capture-range", out=tmp_path, scene_path=path,
                       scene=load_scene(path), seed=1)
    df = pd.DataFrame([{"trial": 0, "metric": "failed", "value": 1.0, "unit": ""}])
    df.attrs["failures"] = {0: "ValueError: boom"}
    assert nothing_finished(ctx, df, "Capture range")
    finish_study(ctx, df)
    report = (tmp_path / "report.md").read_text()
    assert report.count("boom") == 1 and "No trial finished: 1 failed" in report


def test_flag_scores_count_false_accepts_and_rejects_and_their_ratios():
    """Six starts of one method, each kind of outcome (a mutation audit: false rejects
    counted as refused failures passed every test; the function had none)."""
    import numpy as np
    import pandas as pd

    from studies.capture_range import SUCCESS_MM, flag_scores

    accepted = [1, 1, 1, 0, 0, 0]
    final = np.array([0.5, 0.2, 3.0, 0.5, 4.0, 5.0]) * SUCCESS_MM
    rows = []
    for i, (a, f) in enumerate(zip(accepted, final, strict=True)):
        rows += [{"trial": i, "method": "m", "start": 0, "metric": "accepted", "value": a},
                 {"trial": i, "method": "m", "start": 0, "metric": "final_mtre", "value": f}]
    r = flag_scores(pd.DataFrame(rows)).iloc[0]
    assert (r["starts"], r["accepted"], r["successes"]) == (6, 3, 3)
    assert (r["false accepts"], r["false rejects"]) == (1, 1)
    assert r["precision"] == pytest.approx(2 / 3) and r["recall"] == pytest.approx(2 / 3)


def test_the_baselines_register_each_start_once_and_the_default_as_a_user_gets_it(
        monkeypatch):
    """Every method but the primary runs with no restarts: with the estimate's 12, which
    ran for every start of linear, robust-line and ransac (their verdicts refuse them), a
    start cost 10-15x more and scored the best of 13 starts, not one registration (from
    26-29 mm, robust-line and ransac ended 0.6-1.7 mm off with them, 2.1-50 mm without)."""
    from types import SimpleNamespace

    import numpy as np

    import studies.capture_range as cr
    import studies.end_to_end as e2e
    from reglib.geometry import RigidTransform
    from studies.runner import make_trials
    from testbed.scene import find_scene

    truth = RigidTransform(np.eye(3), np.array([800.0, 0.0, 200.0]))
    pins = {"proximal": np.array([0.0, 0.0, 400.0]), "distal_1": np.array([20.0, 0.0, 50.0]),
            "distal_2": np.array([-20.0, 0.0, 50.0])}
    fake_case = SimpleNamespace(pins_ct=pins, ct2robot=truth)
    calls = []

    def register_case(case, start, **opts):
        calls.append(opts)
        est = SimpleNamespace(ct2robot=truth, converged=True, accepted=True,
                              quality={"restarts": 0, "median_residual_mm": 0.2})
        return est, {}

    monkeypatch.setattr(e2e, "prepare_case", lambda scene, seed, sweeps: fake_case)
    monkeypatch.setattr(e2e, "register_case", register_case)
    params = cr.trial_params(cases=1, starts_per_bin=2, others_per_bin=1, bins=(0.0, 10.0))
    (tr,) = make_trials(str(find_scene(cr.DEFAULT_SCENE)), 5, params)
    rows = cr.trial(tr)
    by_method = {}
    for opts in calls:
        name = next(m for m, o in cr.METHODS.items()
                    if all(opts.get(k) == v for k, v in o.items() if k != "solver_options")
                    and set(opts) - {"solver_options"} == set(o))
        by_method.setdefault(name, []).append(opts)
    assert len(by_method.pop(cr.PRIMARY)) == 2 and "restarts" not in cr.METHODS[cr.PRIMARY]
    assert sorted(by_method) == sorted(set(cr.METHODS) - {cr.PRIMARY})
    for name, got in by_method.items():
        assert len(got) == 1 and got[0]["restarts"] == 0, (name, got)
    # the restarts taken are written per start
    assert sum(r["metric"] == "restarts" for r in rows) == len(calls)
