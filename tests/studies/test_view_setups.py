"""The view-setups study: subsets of a scene's views, the verdict scored against the truth."""

from __future__ import annotations

import pandas as pd
import pytest

from studies.view_setups import confusion, setups


def test_setups_are_all_views_each_left_out_and_one_per_region():
    views = {"pa": "proximal", "po": "proximal", "da": "distal", "do": "distal"}
    s = setups(views)
    assert s["all"] == ("pa", "po", "da", "do")
    assert s["without po"] == ("pa", "da", "do")
    pairs = {k: v for k, v in s.items() if " + " in k}
    assert set(pairs.values()) == {("da", "pa"), ("da", "po"), ("do", "pa"), ("do", "po")}
    assert len(s) == 1 + 4 + 4
    assert list(setups(views, quick=True)) == ["all", "without pa", "da + pa"]
    # two views, one per region: nothing to leave out, and the pair is the whole set
    assert list(setups({"p": "proximal", "d": "distal"})) == ["all"]


def test_confusion_counts():
    wide = pd.DataFrame({"accepted": [1, 1, 0, 0, 1], "mtre": [0.5, 2.5, 1.0, 3.0, 1.99]})
    assert confusion(wide) == {"true accepts": 2, "false accepts": 1, "false refusals": 1,
                               "true refusals": 1}


@pytest.mark.slow
def test_quick_study_refuses_one_view_per_end_and_accepts_all_views(tmp_path):
    """Clinic experiment2, one case: all four views accepted within 1 mm; one view per end
    refused, and the truth says it was more than 2 mm off (~12 s)."""
    from studies.cli import main

    assert main(["study", "view-setups", "--quick", "--out", str(tmp_path)]) == 0
    df = pd.read_csv(tmp_path / "results.csv")
    wide = df[df.metric.isin(["mtre", "accepted", "weak_motion_mm"])].pivot_table(
        index="setup", columns="metric", values="value")
    assert wide.loc["all", "accepted"] == 1 and wide.loc["all", "mtre"] < 1.0
    pair = [s for s in wide.index if " + " in s]
    assert len(pair) == 1
    assert wide.loc[pair[0], "accepted"] == 0 and wide.loc[pair[0], "mtre"] > 2.0
    assert wide.loc[pair[0], "weak_motion_mm"] > 2 * wide.loc["all", "weak_motion_mm"]
    counts = df[df.trial == -1].set_index("metric")["value"]
    assert counts["false_accepts"] == 0
    assert counts.drop("accepts_with_a_pin_off").sum() == 3
    # the accepts with a pin off, counted again from the per-pin rows: a three-view set-up
    # may be accepted with one pin 2-3 mm off (the verdict's weak-motion limit allows it:
    # reglib.pipeline.MAX_WEAK_MOTION_MM); "without proximal_ap" was, at 2.71 mm, with the CT
    # operator's per-slice streams (2026-11-27), under 2 mm before
    pins = df[df.metric == "pin_error"].groupby("setup")["value"].max()
    off = sum(pins[s] >= 2.0 for s in wide.index if wide.loc[s, "accepted"] == 1)
    assert counts["accepts_with_a_pin_off"] == off
    report = (tmp_path / "report.md").read_text()
    assert "false accepts" in report and (tmp_path / "view_setups.png").is_file()
    assert f"with a pin 2 mm or more off (whatever the mTRE): **{off}**" in report
    assert "worst pin max (mm)" in report      # the pins reached the table (a review)


def test_accepts_with_a_pin_off_are_counted_whatever_the_mtre():
    from studies.view_setups import accepts_with_a_pin_off

    wide = pd.DataFrame({"accepted": [1, 1, 0, 1], "mtre": [0.5, 1.5, 1.0, 2.5],
                         "max_pin": [0.9, 3.1, 4.0, 2.0]})
    assert accepts_with_a_pin_off(wide) == 2       # 1.5 mm mTRE with a 3.1 mm pin, and 2.5
    assert confusion(wide)["true accepts"] == 2    # the mean alone calls 1.5 mm right
    assert accepts_with_a_pin_off(wide.drop(columns="max_pin")) == 0


def test_the_closing_line_names_false_accepts():
    from studies.view_setups import closing_line

    assert "price of never accepting" in closing_line({"false accepts": 0})
    line = closing_line({"false accepts": 2})
    assert line.startswith("**2 false accept(s)**") and "price" not in line


def test_a_set_up_whose_cases_used_different_view_counts_shows_the_range():
    """A review (h78): a view lost in one case (its calibration refused) was hidden behind
    the first case's count ("all | 4" where one case registered 3 views)."""
    from studies.view_setups import summary

    wide = pd.DataFrame({"setup": ["all"] * 3 + ["one"] * 2, "views": [4, 3, 4, 2, 2],
                         "accepted": [1, 0, 1, 0, 0], "mtre": [0.5, 1.0, 0.6, 3.0, 2.5],
                         "weak_motion_mm": [3.0, 5.0, 3.1, 9.0, 8.0]})
    s = summary(wide).set_index("set-up")
    assert s.loc["all", "views"] == "3-4" and s.loc["one", "views"] == 2
