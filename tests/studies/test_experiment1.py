"""The paper's experiment 1 starts from a pin-based registration with its own error, and the
located pin keeps it (studies/experiment1.py)."""

import pytest

from studies import experiment1
from studies.runner import Trial
from testbed.scene import find_scene


@pytest.mark.slow
def test_the_located_pin_keeps_the_pin_based_registrations_error():
    trial = Trial(0, str(find_scene("experiment1")), 199606, (0,), {"case": 0, "starts": 1})
    rows = experiment1.trial(trial)
    ref = {r["pin"]: r["value"] for r in rows if r["metric"] == "reference_error"}
    assert set(ref) == {"proximal", "distal_1", "distal_2"}
    # the reference is a registration in error, not the truth
    assert min(ref.values()) > 0.01

    def of(metric, variant):
        return {r["pin"]: r["value"] for r in rows
                if r["metric"] == metric and r.get("variant") == variant}

    pinned = of("pin_error", "with proximal pin")
    # rotation about the located pin only: its error is the reference's there, to the
    # registration's tolerance, and it is the reference's own pin against that reference
    assert pinned["proximal"] == pytest.approx(ref["proximal"], abs=0.02)
    assert of("pin_error_vs_reference", "with proximal pin")["proximal"] < 0.02
    # the distal pins are free: registered, not kept at the start's 9 deg (tens of mm off)
    start = [r["value"] for r in rows if r["metric"] == "start_mtre"]
    assert min(start) > 10.0
    assert max(pinned["distal_1"], pinned["distal_2"]) < 5.0
    assert len(of("pin_error", "views alone")) == 3


@pytest.mark.slow
def test_testbed_run_reports_how_far_the_located_pins_error_moves_the_bone():
    """`testbed run experiment1`: with a located pin the registration turns the bone about
    it, and an error of the pin comes out several times larger at the far end (a held-out
    review: seed 10 accepted with both distal pins 3.0-3.2 mm off, the pin at the
    reference's error). The run reports the gain (reglib.register.fixed_point_gain, whose
    linear answer tests/reglib/test_register.py checks against re-registrations)."""
    from studies.end_to_end import run_case
    from testbed.scene import load_scene

    result, _, _, _ = run_case(load_scene(find_scene("experiment1")), seed=10)
    q = result["quality"]
    assert 1.5 < q["pivot_gain"] <= q["pivot_gain_max"] < 8.0, q
    lines = dict(result["extra_lines"])
    assert f"{q['pivot_gain_max']:.1f} times at its farthest point" in lines["located pin's error"]


@pytest.mark.slow
def test_the_report_counts_starts_with_every_pin_within_2_mm(tmp_path):
    """The paper's claim is per pin; an mTRE within 2 mm can hold a pin 4 mm off (a
    held-out review: the views alone, the proximal pin 4.0 mm off, counted "within 2 mm
    mTRE"). The report counts both, and the per-pin count agrees with its table."""
    import re

    import pandas as pd

    from studies.cli import main

    assert main(["study", "experiment1", "--quick", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "report.md").read_text()
    df = pd.read_csv(tmp_path / "results.csv")
    pe = df[df.metric == "pin_error"].pivot_table(index=["trial", "variant", "start"],
                                                   columns="pin", values="value")
    for variant, d in pe.groupby(level="variant"):
        m = re.search(rf"{variant}: of (\d+) starts.*?(\d+) with every pin within 2 mm", text)
        assert m, text
        assert int(m.group(2)) == int((d.max(axis=1) < 2.0).sum())
    # the section against the paper (a review, h87: none; the pin's reversal unsaid): its
    # count of starts with the distal pins within 2 mm, and which variant did better
    distal = pe.drop(columns="proximal")
    wp = distal.xs("with proximal pin", level="variant").max(axis=1)
    m = re.search(r"- (met|\*\*missed\*\*): with the proximal pin located, every other pin "
                  r"within 2 mm of the truth from (\d+) of (\d+) starts, the largest "
                  r"([\d.]+) mm", text)
    assert m, text
    assert int(m.group(2)) == int((wp <= 2.0).sum()) and int(m.group(3)) == len(wp)
    assert (m.group(1) == "met") == bool((wp <= 2.0).all())
    assert float(m.group(4)) == pytest.approx(wp.max(), abs=0.006)
    med = distal.stack().groupby(level="variant").median()
    helped = med["with proximal pin"] < med["views alone"]
    assert ("- as the paper: the located pin lowers" in text) == helped
    assert ("- **unlike the paper**: the located pin does not lower" in text) == (not helped)


def test_the_lines_against_the_paper_take_several_cases_and_another_located_pin():
    """A review (h90): with two cases the lines failed ("cannot reindex on an axis with
    duplicate labels"), a NaN median read as "unlike the paper", and a scene locating
    another pin was compared with the paper's proximal-pin set-up."""
    import numpy as np
    import pandas as pd

    from studies.experiment1 import paper_lines

    rows, acc = [], []
    for trial in (0, 1):
        for start in ("rot9_1", "rot9_2"):
            for variant, err in (("with proximal pin", 1.0 + 1.5 * trial), ("views alone", 4.0)):
                for pin in ("proximal", "distal_1", "distal_2"):
                    rows.append({"trial": trial, "start": start, "variant": variant,
                                 "pin": pin, "value": 0.5 if pin == "proximal" else err})
                acc.append({"trial": trial, "start": start, "variant": variant,
                            "accepted": float(variant != "views alone")})
    pe, w = pd.DataFrame(rows), pd.DataFrame(acc)
    text = "\n".join(paper_lines(pe, pe.iloc[:0], w))
    assert "from 2 of 4 starts, the largest 2.50 mm (4 of 4 accepted" in text
    assert "**missed**" in text and "(0 of 4 accepted)" in text
    assert "- as the paper: the located pin lowers" in text and "These are 2 case(s)" in text
    nan = pe.assign(value=np.where(pe.variant == "views alone", np.nan, pe.value))
    assert "- not comparable" in "\n".join(paper_lines(nan, pe.iloc[:0], w))
    other = pe.assign(pin=pe.pin.replace({"proximal": "distal_1", "distal_1": "proximal"}),
                      variant=pe.variant.replace({"with proximal pin": "with distal_1 pin"}))
    w2 = w.assign(variant=w.variant.replace({"with proximal pin": "with distal_1 pin"}))
    text = "\n".join(paper_lines(other, pe.iloc[:0], w2, pin="distal_1"))
    assert text.startswith("- not the paper's set-up") and "unlike the paper" not in text
    assert "as the paper" not in text and "- measured: with the distal_1 pin located" in text
