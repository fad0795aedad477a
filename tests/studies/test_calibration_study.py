"""The calibration study end to end on a small scene (one view, quick)."""

import pandas as pd
import pytest

SCENE = """
[scene]
name = "calib-test"
kind = "operating_room"
seed = 4

[[views]]
name = "ap"
isocenter_mm = [800.0, 0.0, 200.0]

[robot.sweep]
rows_per_plane = 6
"""


@pytest.mark.slow
def test_calibration_study_writes_validation_distances_per_view(tmp_path):
    from studies import run_study

    scene = tmp_path / "calib.toml"
    scene.write_text(SCENE)
    out = run_study("calibration", tmp_path / "out", scene=str(scene), quick=True)
    df = pd.read_csv(out / "results.csv")
    for col in ("trial", "metric", "value", "unit", "view"):
        assert col in df.columns
    val = df[df.metric == "validation_distance"]
    assert len(val) >= 6 and set(val.view) == {"ap"} and set(val.unit) == {"mm"}
    # the clinic profile (every error source at its published magnitude): about the paper's
    # 0.1-0.4 mm (measured 0.03-0.45 mm on this seed; 0.03-0.2 mm with the ideal profile)
    assert val.value.max() < 0.6 and val.value.median() < 0.3
    ray = df[(df.metric == "ray_error_iso") & (df.stat == "mean")]
    assert len(ray) == 1 and ray.value.item() < 0.8  # clinic: ~0.5 mm (docs/error-model.md)
    assert df[df.metric == "sweep_time"].value.item() == pytest.approx(14.0)
    assert set(df.experiment.dropna()) == {"smoothing", "beads", "rows"}
    report = (out / "report.md").read_text()
    assert "Validation distances per view" in report and "0.1-0.4 mm" in report
    # the largest is said of the views run (--quick: one), against the paper's range (the
    # clinic's target) and the ideal profile's 0.1 mm goal, both (a held-out review: "over
    # all views" with one run, judged against 0.1 mm alone where table2 used 0.1-0.4)
    vmax = val.value.max()
    inside = "within" if 0.1 <= vmax <= 0.4 else "outside"
    assert (f"the largest over the 1 view(s) run is {vmax:.3f} mm: {inside} the paper's range"
            in report), report
    # the table's distances to the micrometre (".3g" printed 1.0001 mm as "1", a review),
    # and the validation's blind spot said beside it
    true_max = df[(df.metric == "validation_distance_true")].value.max()
    assert f"| {vmax:.3f} | " in report and f"| {true_max:.3f} | " in report, report
    assert "the validation cannot see it" in report


def test_the_sensitivity_table_is_one_views():
    """The worst view's rows, not the largest figure of each cell over the views (which put
    one view's ray error beside another's validation distance)."""
    import pandas as pd

    from studies.calibration import sensitivity_table

    rows = []
    for view, val, ray in (("a", (0.30, 0.50), (0.60, 0.10)), ("b", (0.45, 0.40), (0.20, 0.30))):
        for param, v, r in zip((4, 6), val, ray, strict=True):
            rows += [{"view": view, "experiment": "beads", "param": param,
                      "metric": "validation_max", "value": v},
                     {"view": view, "experiment": "beads", "param": param,
                      "metric": "ray_error_iso_mean", "value": r}]
    worst, t = sensitivity_table(pd.DataFrame(rows))
    assert worst == "b"     # mean validation 0.425 against 0.40
    assert t[["param", "validation_max", "ray_error_iso_mean"]].values.tolist() == [
        [4, 0.45, 0.20], [6, 0.40, 0.30]]


def test_a_sensitivity_setting_that_cannot_calibrate_is_said(tmp_path):
    """experiment2's proximal_ap cannot calibrate from 2 rod positions per plane; the
    setting was dropped without a word (a review). It is a row and a line of the report."""
    from studies import run_study

    out = run_study("calibration", tmp_path / "out", quick=True, progress=False)
    df = pd.read_csv(out / "results.csv")
    failed = df[df.metric == "sensitivity_failed"]
    assert len(failed) >= 1 and set(failed.experiment) <= {"smoothing", "beads", "rows"}
    r = failed.iloc[0]
    line = f"{r.experiment} = {r.param:g} ({r.view})"
    assert line in (out / "report.md").read_text()
