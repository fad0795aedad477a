"""The error budget's bookkeeping: sources found by comparing two profiles, variants, table."""

import re

import pandas as pd
import pytest

from studies.error_budget import error_sources, source_of, source_table, variant
from testbed.scene import find_scene, load_scene, parse_scene


@pytest.fixture(scope="module")
def clinic():
    return load_scene(find_scene("experiment2"))


def _ideal(clinic):
    d = clinic.model_dump(mode="json")
    d["fluoroscope"]["pincushion_k1"] = 0.0
    d["fluoroscope"]["pincushion_k2"] = 0.0
    d["ct"]["metal_streaks"] = False
    d["operator"]["xray_click_noise_px"] = 0.25
    return parse_scene(d)


def test_sources_are_the_fields_that_differ_grouped(clinic):
    ideal = _ideal(clinic)
    src = error_sources(clinic, ideal)
    assert set(src) == {"intensifier distortion", "CT metal streaks", "operator on X-ray"}
    assert set(src["intensifier distortion"]) == {"fluoroscope.pincushion_k1",
                                                 "fluoroscope.pincushion_k2"}
    assert src["CT metal streaks"] == {"ct.metal_streaks": (True, False)}
    assert error_sources(clinic, clinic) == {}
    assert source_of("fluoroscope.some_new_field") == "fluoroscope.some_new_field"


def test_the_sampler_is_no_source_and_a_moved_set_up_is_refused(clinic):
    """A review: the shipped pair listed the quanta's sampler (fast or exact: the same law)
    as a source, and a scene whose patient was moved, paired with the shipped ideal
    profile, listed the patient's pose as two sources."""
    from testbed.spec import SceneError

    shipped = error_sources(clinic, load_scene(find_scene("experiment2-ideal")))
    assert not any("quantum_sampler" in f for fields in shipped.values() for f in fields)
    assert "quantum noise" in shipped
    d = clinic.model_dump(mode="json")
    d["patient"]["position_mm"] = [835.0, 205.0, 200.0]
    with pytest.raises(SceneError, match=r"differs from the scene .* set-up.*"
                                         r"patient\.position_mm"):
        error_sources(parse_scene(d), clinic)


def test_off_and_alone_variants_change_only_that_source(clinic):
    ideal = _ideal(clinic)
    fields = error_sources(clinic, ideal)["intensifier distortion"]
    off = variant(clinic, {k: v[1] for k, v in fields.items()})
    assert off.fluoroscope.pincushion_k1 == 0.0 and off.ct.metal_streaks
    assert set(error_sources(off, ideal)) == {"CT metal streaks", "operator on X-ray"}
    alone = variant(ideal, {k: v[0] for k, v in fields.items()})
    assert set(error_sources(alone, ideal)) == {"intensifier distortion"}


def test_source_table_attributes_removed_and_added():
    rows = []
    for cfg, src, val in (("clinic", "", 3.0), ("ideal", "", 0.5), ("off", "a", 1.0),
                          ("alone", "a", 2.0), ("off", "b", 2.9), ("alone", "b", 0.6)):
        rows += [{"config": cfg, "source": src, "oracle": "none", "value": val}] * 2
    t = source_table(pd.DataFrame(rows)).set_index("source")
    assert t.loc["a", "removed"] == pytest.approx(2.0)
    assert t.loc["a", "added"] == pytest.approx(1.5)
    assert t.loc["b", "removed"] == pytest.approx(0.1)
    assert list(t.index[2:]) == ["a", "b"]  # largest share first


def test_gap_table_gives_each_source_the_factor_that_would_reach_the_target():
    """Clinic 1.0 mm, ideal 0.3 mm; source a alone 0.5 mm (own 0.4 mm in quadrature),
    b alone 0.3 mm (adds nothing): to reach 1.8 mm, sqrt(1.8^2 - 1) = 1.497 mm is missing,
    so a would need sqrt(0.4^2 + 1.497^2) / 0.4 = 3.87 times its magnitude; b no factor."""
    import numpy as np

    from studies.error_budget import gap_markdown, gap_table

    rows = []
    for cfg, src, val in (("clinic", "", 1.0), ("ideal", "", 0.3), ("off", "a", 0.8),
                          ("alone", "a", 0.5), ("off", "b", 1.0), ("alone", "b", 0.3)):
        rows.append({"config": cfg, "source": src, "oracle": "none", "value": val})
    t = source_table(pd.DataFrame(rows))
    g = gap_table(t, 1.8).set_index("source")
    assert g.loc["a", "contribution_mm"] == pytest.approx(0.4)
    assert g.loc["a", "factor"] == pytest.approx(np.sqrt(0.16 + 1.8**2 - 1.0) / 0.4)
    assert np.isnan(g.loc["b", "factor"])
    assert "1.50 mm (in quadrature) is missing" in gap_markdown(t)
    rows[0]["value"] = 2.0
    assert "no source has to change" in gap_markdown(source_table(pd.DataFrame(rows)))


def test_a_stored_trial_is_not_reused_after_either_profile_changed(tmp_path):
    """The trials' keys hold the scene's and its ideal profile's every field: an edit of
    either runs the trials again (a review: an edited clinic scene reused the old pin errors
    under the new scene's report)."""
    from studies.error_budget import make_budget_trials

    src = find_scene("experiment2").parent
    for name in ("experiment2.toml", "experiment2-ideal.toml"):
        (tmp_path / name).write_text((src / name).read_text())

    def keys():
        return [t.key for t in make_budget_trials(tmp_path / "experiment2.toml", 3, cases=1)]

    before = keys()
    assert before == keys() and len(set(before)) == len(before) > 2
    for name in ("experiment2.toml", "experiment2-ideal.toml"):
        p = tmp_path / name
        text = p.read_text()
        assert "[fluoroscope]\n" in text
        edited = re.sub(r"(?m)^focal_spot_mm = .*$", "focal_spot_mm = 0.9", text)
        if edited == text:
            edited = text.replace("[fluoroscope]\n", "[fluoroscope]\nfocal_spot_mm = 0.9\n", 1)
        p.write_text(edited)
        after = keys()
        assert not set(after) & set(before), name
        p.write_text(text)
    assert keys() == before


def test_the_ideal_configuration_keeps_the_clinic_scenes_set_up(clinic):
    """A review: the ideal and alone configurations took the ideal profile's femur and
    registration, so a user's femur was paired with the shipped one. The ideal
    configuration is now the clinic scene with every source at its ideal magnitude."""
    from studies.error_budget import ideal_of

    profile = load_scene(find_scene("experiment2-ideal"))
    d = clinic.model_dump(mode="json")
    d["phantom"]["length_mm"] = 420.0           # a user's femur, not the shipped one
    d["phantom"]["side"] = "left"
    mine = parse_scene(d)
    ideal = ideal_of(mine, profile)
    assert ideal.phantom == mine.phantom and ideal.registration == mine.registration
    assert error_sources(ideal, profile) == {}   # every source at the profile's magnitude
    assert set(error_sources(mine, ideal)) == set(error_sources(mine, profile))


def test_the_verdict_section_counts_the_refused_registrations():
    """A one-view scene's 'mean pin error' of 190 mm was of 25 refused poses, and the
    report said nothing of the verdict (a review)."""
    from studies.error_budget import verdict_markdown, verdict_table

    rows = []
    for start, acc in enumerate([1.0, 0.0, 0.0]):
        for metric, value in (("accepted", acc), ("converged", 1.0)):
            rows.append({"trial": 0, "start": start, "metric": metric, "value": value,
                         "config": "clinic", "source": None, "oracle": None})
    for start in range(2):
        rows.append({"trial": 1, "start": start, "metric": "accepted", "value": 1.0,
                     "config": "ideal", "source": None, "oracle": None})
        rows.append({"trial": 1, "start": start, "metric": "converged", "value": 1.0,
                     "config": "ideal", "source": None, "oracle": None})
    df = pd.DataFrame(rows)
    t = verdict_table(df).set_index("config")
    assert t.loc["clinic", "registrations"] == 3 and t.loc["clinic", "accepted"] == 1
    assert t.loc["ideal", "accepted"] == 2
    text = verdict_markdown(df)
    assert "over all 5 registrations" in text and "**2 of them were refused" in text
    assert "| clinic |" in text and "| ideal |" not in text    # only those with refusals
    ok = verdict_markdown(df[df.config == "ideal"])
    assert "All were accepted" in ok and "|" not in ok


def test_a_scene_without_its_ideal_profile_gets_the_shipped_magnitudes(clinic, tmp_path):
    """A held-out review: no held-out scene had a `<stem>-ideal.toml`, so none got a budget
    by source (and table2 pointed to a section that was not written). The shipped ideal
    magnitudes now stand in: each field in which experiment2-ideal differs from experiment2
    at its ideal value, on the scene's own set-up and femur; a scene already at them (the
    ideal profile itself) has no source to vary, and the report says why."""
    from studies.error_budget import SHIPPED, no_budget_reason, shipped_ideal, trial_params

    text = find_scene("experiment2").read_text()
    moved = re.sub(r"(?m)^position_mm = .*$", "position_mm = [835.0, 205.0, 200.0]", text,
                   count=1)
    assert moved != text
    mine_path = tmp_path / "held_out.toml"
    mine_path.write_text(moved.replace("[fluoroscope]\n", "[fluoroscope]\nfocal_spot_mm = 0.9\n",
                                       1))
    mine = load_scene(mine_path)
    ideal = shipped_ideal(mine)
    assert ideal.patient == mine.patient and ideal.views == mine.views
    assert ideal.phantom == mine.phantom and ideal.registration == mine.registration
    shipped = error_sources(clinic, load_scene(find_scene("experiment2-ideal")))
    assert set(error_sources(mine, ideal)) == set(shipped)
    assert error_sources(mine, ideal)["focal-spot blur"]["fluoroscope.focal_spot_mm"] == (0.9, 0.0)
    params = trial_params(mine_path, cases=1)
    assert {p["ideal"] for p in params} == {SHIPPED}
    assert {p["config"] for p in params} == {"clinic", "ideal", "off", "alone"}
    assert len(params) == 2 + 2 * len(shipped)
    own = tmp_path / "experiment2-ideal.toml"      # no experiment2-ideal-ideal beside it
    own.write_text(find_scene("experiment2-ideal").read_text())
    assert [p["config"] for p in trial_params(own, cases=1)] == ["clinic"]
    assert "at its shipped ideal magnitude or below" in no_budget_reason(load_scene(own), own)


def test_the_stage_budget_says_when_a_true_input_made_the_error_larger():
    """A held-out review: the true contours made the pin error larger on four scenes and the
    report said nothing."""
    from studies.error_budget import stage_markdown

    rows = [{"config": "clinic", "oracle": o, "value": v}
            for o, vals in (("none", (1.0, 1.2)), ("calibration", (0.4, 0.6)),
                            ("contours", (1.8, 2.2))) for v in vals]
    text = stage_markdown(pd.DataFrame(rows))
    assert "-0.818" in text and "A negative share (`contours`)" in text
    assert "`calibration`" not in text.split("A negative share")[1]
    better = stage_markdown(pd.DataFrame([r for r in rows if r["oracle"] != "contours"]))
    assert "0.545" in better and "negative share" not in better


def test_the_shipped_fallback_skips_what_the_scene_refuses_or_already_has_smaller(
        tmp_path):
    """A held-out review of the fallback: a scene with its own [ct] slice_thickness_mm lost
    its whole budget (the ideal max_slice_thickness_mm clashes with it; now that source
    alone stays at the scene's value, and the report names it); a scene's 0.5 px X-ray
    clicks became 1 px in its 'ideal' (a number already smaller stays); a moved patient's
    copy named experiment2.toml elsewhere found the shipped experiment2-ideal by name and
    was refused for its set-up (it now gets the shipped magnitudes)."""
    from studies.error_budget import SHIPPED, shipped_ideal_fields, trial_params

    text = find_scene("experiment2").read_text()
    mine = tmp_path / "mine.toml"
    mine.write_text(text + "\n[ct]\nslice_thickness_mm = 3.0\n\n[operator]\n"
                    "xray_click_noise_px = 0.5\n")
    scene = load_scene(mine)
    assert scene.ct.slice_thickness_mm == 3.0 and scene.operator.xray_click_noise_px == 0.5
    values, skipped = shipped_ideal_fields(scene)
    assert list(skipped) == ["CT slice thickness"] and "ct.max_slice_thickness_mm" not in values
    assert "operator.xray_click_noise_px" not in values
    assert values["fluoroscope.focal_spot_mm"] == 0.0
    configs = {(p["config"], p["source"]) for p in trial_params(mine, cases=1)}
    assert ("off", "focal-spot blur") in configs
    assert not {s for _, s in configs} & {"CT slice thickness", "operator on X-ray"}
    moved = tmp_path / "elsewhere" / "experiment2.toml"
    moved.parent.mkdir()
    moved.write_text(re.sub(r"(?m)^position_mm = .*$", "position_mm = [835.0, 205.0, 200.0]",
                            text, count=1))
    assert {p["ideal"] for p in trial_params(moved, cases=1)} == {SHIPPED}


def test_the_tornado_draws_both_shares_signed_on_one_axis(tmp_path, monkeypatch):
    """A source whose removal made the error larger (removed < 0) is drawn left of 0, and
    one that adds error right of it, for both bars: the chart drew the removal negated,
    so a negative removal showed as a bar on the right, read as an added error."""
    import matplotlib.figure

    from studies.error_budget import _tornado

    t = pd.DataFrame({"source": ["(clinic)", "a", "b"], "removed": [None, -0.12, 0.10],
                      "added": [None, 0.07, 0.26]})
    seen = {}

    def keep(fig, *args, **kwargs):
        seen["fig"] = fig

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)

    class Ctx:
        def figure(self, name, caption):
            return tmp_path / name

    _tornado(Ctx(), t)
    ax = seen["fig"].axes[0]
    bars = {(round(p.get_y() + p.get_height() / 2, 2), p.get_facecolor()[:3]): p.get_width()
            for p in ax.patches}
    labels = [x.get_text() for x in ax.get_yticklabels()]
    widths = sorted(bars.values())
    assert labels == ["b", "a"] and widths == sorted([-0.12, 0.10, 0.07, 0.26])
    # each source's bars sit about its tick: "a" (tick 1) has the negative removal
    a = [w for (y, _), w in bars.items() if abs(y - 1) < 0.5]
    assert sorted(a) == [-0.12, 0.07]


def test_the_report_names_the_sources_whose_removal_made_the_error_larger():
    from studies.error_budget import _negative_note

    t = pd.DataFrame({"source": ["(clinic)", "a", "b"], "removed": [None, -0.12, 0.10],
                      "added": [None, 0.07, 0.26]})
    note = _negative_note(t, 3)
    assert "Switching off 1 source(s)" in note and "a (-0.120 mm)" in note
    assert "b (" not in note and "over 3 case(s)" in note
    assert _negative_note(t.assign(removed=[None, 0.12, 0.10]), 3) == ""


def test_a_source_whose_configuration_lost_a_view_is_marked():
    """A held-out review: on one scene "scatter off" had distal_ap refused, and the budget
    reported its -0.61 mm as the source's. The views used differently from the
    configuration compared with (off: clinic, alone: ideal; same case) are named, and the
    report says the figure is not the source's alone."""
    from studies.end_to_end import views_lost_markdown
    from studies.error_budget import _view_change_note, view_changes

    rows = []
    for cfg, src, val, lost in (("clinic", "", 1.0, ()), ("ideal", "", 0.5, ("b",)),
                                ("off", "s", 1.6, ("b",)), ("alone", "s", 0.7, ()),
                                ("off", "t", 0.9, ()), ("alone", "t", 0.6, ("b",))):
        for case in (0, 1):
            rows.append({"config": cfg, "source": src, "oracle": "none", "value": val,
                         "metric": "pin_error", "case": case, "trial": 0})
            for view in ("a", "b"):
                gone = view in lost and case == 1
                rows.append({"config": cfg, "source": src, "metric": "view_used",
                             "value": float(not gone), "view": view, "case": case,
                             "trial": 0, "reason": "no bone contour" if gone else ""})
    df = pd.DataFrame(rows)
    changes = view_changes(df)
    # s off lost b where the clinic used it; s alone used b where the ideal lost it; t
    # alone lost b as the ideal did: no change
    assert changes == {("off", "s"): "-b (case 1)", ("alone", "s"): "+b (case 1)"}
    t = source_table(df[df.metric == "pin_error"], changes).set_index("source")
    assert t.loc["s", "views"] == "off: -b (case 1); alone: +b (case 1)"
    assert not t.loc["t", "views"]
    assert t.loc["s", "removed"] == pytest.approx(-0.6)    # the figure stays as measured
    note = _view_change_note(changes)
    assert "**1 source(s) changed which views were registered** (s;" in note
    assert _view_change_note({}) == ""
    lost = views_lost_markdown(df, by=("config", "source"))
    assert "**3 view-case(s) were left out" in lost
    assert "- b, case 1 (config off, source s): no bone contour" in lost
    # 12 pairs of configuration and view: the table keeps the 3 with a loss
    assert lost.count("\n| ") == 1 + 3 and "The other 9 combinations of config, source and view" \
        in lost


def test_the_gap_says_when_it_rests_on_fewer_cases_than_the_study_and_sorts_by_added():
    """A review (h87): `--quick`'s one case printed a source's factor without a caveat, and
    the table was sorted by `removed`, which cancellations make negative over few cases,
    while its text said to read `added` first."""
    from studies.error_budget import CASES, gap_markdown

    rows = []
    for cfg, src, val in (("clinic", "", 1.0), ("ideal", "", 0.3), ("off", "a", 1.1),
                          ("alone", "a", 0.5), ("off", "b", 0.8), ("alone", "b", 0.35)):
        rows.append({"config": cfg, "source": src, "oracle": "none", "value": val})
    t = source_table(pd.DataFrame(rows))
    assert list(t.source[2:]) == ["a", "b"]          # a adds 0.2 mm, b 0.05 (removed: -0.1, 0.2)
    assert gap_markdown(t, cases=1).startswith("**From 1 case(s)**")
    assert "**From" not in gap_markdown(t, cases=CASES)
    assert "**From" not in gap_markdown(t)
