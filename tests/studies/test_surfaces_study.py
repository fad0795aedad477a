"""Smoke run of the surfaces study (--quick): the table, the figure, sane distances."""

import numpy as np
import pandas as pd
import pytest

from studies import run_study
from testbed.scene import find_scene


def _scene(tmp_path):
    try:
        return str(find_scene("experiment2"))
    except ValueError:
        path = tmp_path / "scene.toml"
        path.write_text('[scene]\nkind = "operating_room"\n\n[[views]]\nname = "v"\n')
        return str(path)


@pytest.mark.slow
def test_surfaces_study_quick(tmp_path):
    out = run_study("surfaces", tmp_path / "out", scene=_scene(tmp_path), seed=3, quick=True)
    df = pd.read_csv(out / "results.csv")
    assert {"trial", "metric", "value", "unit", "surface", "statistic", "method"} <= set(df)
    d = df[df.metric == "surface_distance"]
    assert set(d.unit) == {"mm"}
    assert set(d.surface) == {"proximal", "distal"}
    assert set(d.statistic) == {"mean", "p95", "max"}
    assert set(d.method) == {"contours", "marching_cubes"}
    assert len(d) == 12
    v = d.set_index(["surface", "method", "statistic"]).value
    for surface in ("proximal", "distal"):
        for method in ("contours", "marching_cubes"):
            mean, p95, mx = (v[surface, method, s] for s in ("mean", "p95", "max"))
            assert 0 < mean <= p95 <= mx < 10.0
        # The goal of the issue: contour surfaces within 0.5 mm of the truth on average.
        assert v[surface, "contours", "mean"] <= 0.5
    # the other way, from the true femur between the slices to the reconstruction
    # (measured at seed 3 with the scene's operator: 0.12-0.17 mm for the contour surfaces;
    # from them to the truth 0.12-0.22 mm)
    b = df[df.metric == "truth_distance"].set_index(["surface", "method", "statistic"]).value
    assert len(b) == 12 and set(df[df.metric == "truth_distance"].unit) == {"mm"}
    for surface in ("proximal", "distal"):
        mean, p95, mx = (b[surface, "contours", s] for s in ("mean", "p95", "max"))
        assert 0 < mean <= p95 <= mx < 10.0 and mean <= 0.5
    assert "mean <= 0.5 mm both ways" in (out / "report.md").read_text()
    tri = df[(df.metric == "triangles") & (df.method == "contours")].set_index("surface").value
    assert 500 < tri["proximal"] < 10_000 and 500 < tri["distal"] < 20_000
    assert np.all(df[df.metric == "time"].value > 0)
    assert (out / "surfaces_distance.png").stat().st_size > 10_000
    assert "Distance to the true femur surface" in (out / "report.md").read_text()


def test_a_failed_first_case_costs_only_itself(tmp_path, monkeypatch):
    """The figure is drawn from the first case that finished: it re-simulated case 0, which
    failed again and lost the other cases' results (a review)."""
    import studies.surfaces as su

    def trial(tr):
        if tr.index == 0:
            raise RuntimeError("case 0 cannot be simulated")
        return [dict(metric="surface_distance", value=0.2, unit="mm", surface=s,
                     statistic=st, method=m) for s in ("proximal", "distal")
                for st in ("mean", "p95", "max") for m in ("contours", "marching_cubes")] + [
            dict(metric="triangles", value=100.0, unit="count", surface=s, statistic="",
                 method=m) for s in ("proximal", "distal") for m in ("contours", "marching_cubes")]

    drawn = []

    def case(tr, quick):
        drawn.append(tr.index)
        raise RuntimeError("stop after choosing the case")

    monkeypatch.setattr(su, "trial", trial)
    monkeypatch.setattr(su, "_case", case)
    monkeypatch.setattr(su, "QUICK_CASES", 3)
    with pytest.raises(RuntimeError, match="stop after choosing"):
        run_study("surfaces", tmp_path / "out", scene=_scene(tmp_path), seed=3, quick=True,
                  progress=False)
    assert drawn == [1]


def test_the_truths_side_sees_what_a_surface_leaves_out():
    """A surface that lies on the truth but covers half of it: 0 mm from it to the truth,
    while from the truth (between the heights given) half the points are far off. Only the
    second direction saw coarse slices miss a condyle's curve (a held-out review)."""
    import trimesh

    from studies.surfaces import distances_from_truth, distances_to_truth

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    phantom = type("P", (), {"femur": sphere})()
    half = sphere.faces[sphere.triangles_center[:, 0] > 0]
    to = distances_to_truth(phantom, sphere.vertices, half, n_samples=2000, rng=1)
    back = distances_from_truth(phantom, sphere.vertices, half, (-5.0, 5.0), n_samples=2000,
                                rng=1)
    assert to.max() < 1e-6
    assert len(back) > 1000
    far = np.mean(back > 5.0)
    assert 0.35 < far < 0.55          # the x < 0 half, but for a band near the cut
    assert back.max() > 25.0          # the back: the cut edge lies R sqrt(2) away
    whole = distances_from_truth(phantom, sphere.vertices, sphere.faces, (-5.0, 5.0),
                                 n_samples=2000, rng=1)
    assert whole.max() < 1e-6
    # no truth between the heights: nothing measured
    assert distances_from_truth(phantom, sphere.vertices, half, (30.0, 40.0)).size == 0


def test_a_surface_far_off_the_bone_somewhere_is_said_beside_its_mean():
    """A review (h87): a contour surface's 10.1 mm maximum went without a word while its
    mean met the goal. The note comes from the worst case, not the mean of the cases'
    maxima (a review, h90: 3.6 / 3.9 / 5.8 mm averaged to 4.4 mm, no note), either way
    measured, and only past FAR_MM."""
    from studies.surfaces import FAR_MM, _goal_lines, worst_case_max

    rows = []
    for trial, (to_max, from_max) in enumerate([(3.6, 1.0), (3.9, 1.0), (FAR_MM + 0.8, 2.0)]):
        for metric, mx in (("surface_distance", to_max), ("truth_distance", from_max)):
            rows.append({"trial": trial, "metric": metric, "method": "contours",
                         "surface": "proximal", "statistic": "max", "value": mx})
        for metric, mx in (("surface_distance", 2.0), ("truth_distance", FAR_MM + 2.0 * trial)):
            rows.append({"trial": trial, "metric": metric, "method": "contours",
                         "surface": "distal", "statistic": "max", "value": mx})
    rows.append({"trial": 0, "metric": "surface_distance", "method": "marching_cubes",
                 "surface": "distal", "statistic": "max", "value": 50.0})
    worst = worst_case_max(pd.DataFrame(rows))
    assert worst["proximal", "to"] == (FAR_MM + 0.8, 2) and worst["distal", "from"][1] == 2
    tab = pd.DataFrame({"surface": ["proximal", "distal"], "method": ["contours"] * 2,
                        "mean": [0.12, 0.2], "max": [4.4, 2.0], "truth's mean": [0.1, 0.2]})
    text = _goal_lines(tab, worst)
    assert text.count("met:") == 4 and "**missed**" not in text
    notes = [ln for ln in text.splitlines() if ln.startswith("- **note**")]
    assert len(notes) == 2, notes
    assert any(f"proximal surface reaches {FAR_MM + 0.8:.1f} mm from the truth in case 2"
               in n for n in notes)
    assert any("distal surface leaves the truth up to" in n and "case 2" in n for n in notes)
    assert "note" not in _goal_lines(tab, {("proximal", "to"): (FAR_MM - 0.1, 0)})
