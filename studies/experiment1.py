"""The paper's experiment 1: two views (proximal, distal) plus the proximal pin.

The proximal pin is located in CT and by the robot, so only the rotation about it is
optimised (``fixed_pin``). As in the paper, the starts are the pin-based registration (its
pins located in CT and touched by the robot, each with its own error:
:func:`studies.scoring.pin_reference`, the reference of ``table2``) turned by the scene's
``start_rotation_deg`` (9 deg) about random axes through the pin: the pin stays where that
registration put it, with its error. The paper found the distal pins within 2 mm this way
(against its pin-based reference), and about 5 mm with the fluoroscopic views alone; both
variants are run on the same simulated case, and the errors are reported against the truth
and against the reference. Each trial is one case (case ``i`` of the study seed).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from studies.common import markdown_table
from studies.end_to_end import case_rows, prepare_case, registration_rows, views_lost_markdown
from studies.scoring import case_reference, judge_seed, perturbed_start, pin_errors

TITLE = "the paper's experiment 1: two views plus the proximal pin, 9 deg starts"
DEFAULT_SCENE = "experiment1"
CASES = 1
STARTS = 5
QUICK_STARTS = 2
#: the judge's seed salt of this study's starts
START_SALT = 1


def trial(tr) -> list[dict]:
    from testbed.scene import load_scene

    scene = load_scene(tr.scene)
    case = prepare_case(scene, tr.seed_sequence)
    angle = scene.registration.start_rotation_deg
    pin = scene.registration.fixed_pin or "proximal"
    reference = case_reference(case.sim.truth, tr.seed_sequence)
    rngs = judge_seed(tr.seed_sequence, START_SALT).spawn(int(tr.params["starts"]))
    starts = {f"rot{angle:g}_{k + 1}": perturbed_start(reference, case.pins_ct, angle,
                                                       np.random.default_rng(r), about=pin)
              for k, r in enumerate(rngs)}
    rows = case_rows(case)
    rows += [{"metric": "reference_error", "value": e, "unit": "mm", "pin": p}
             for p, e in pin_errors(reference, case.ct2robot, case.pins_ct).items()]
    for variant, fixed in ((pinned_variant(pin), pin), ("views alone", None)):
        rows += [{**r, "variant": variant}
                 for r in registration_rows(case, starts, fixed_pin=fixed,
                                            reference=reference)]
    return rows


def pinned_variant(pin: str) -> str:
    """The name of the variant with ``pin`` located (the paper's: the proximal pin; a
    scene's ``[registration] fixed_pin`` may name another, which the report called
    'proximal', a review)."""
    return f"with {pin} pin"


def run(ctx) -> pd.DataFrame:
    from studies.runner import run_study_trials

    pin = ctx.scene.registration.fixed_pin or "proximal"

    starts = QUICK_STARTS if ctx.quick else STARTS
    df = run_study_trials(ctx, trial, [{"case": i, "starts": starts} for i in range(CASES)])
    ok = df[df.metric != "failed"]
    pe = ok[ok.metric == "pin_error"]
    if pe.empty:
        ctx.report("Pin errors (mm)", "No registration finished.")
        return df
    tab = pe.pivot_table(index=["trial", "variant", "start"], columns="pin",
                         values="value").reset_index()
    w = ok[ok.metric.isin(["converged", "accepted", "mtre"])].pivot_table(
        index=["trial", "variant", "start"], columns="metric", values="value").reset_index()
    # the paper's claim is per pin (the distal pins within 2 mm): an mTRE within 2 mm can
    # hold a pin 4 mm off (a held-out review, the views alone)
    pins = [c for c in tab.columns if c not in ("trial", "variant", "start")]
    worst = tab.assign(worst_pin=tab[pins].max(axis=1))[
        ["trial", "variant", "start", "worst_pin"]]
    w = w.merge(worst, on=["trial", "variant", "start"], how="left")
    parts = []
    for v, d in w.groupby("variant"):
        parts.append(f"{v}: of {len(d)} starts, {int(d['converged'].sum())} converged, "
                     f"{int(d['accepted'].sum())} accepted by the method's verdict, "
                     f"{int((d['mtre'] < 2.0).sum())} within 2 mm mTRE of the truth, "
                     f"{int((d['worst_pin'] < 2.0).sum())} with every pin within 2 mm")
    verdict = "; ".join(parts)
    ctx.report("Pin errors (mm)",
               "The paper: distal pins within 2 mm with the proximal pin; about 5 mm with the "
               f"views alone. Here the {pin} pin is located.\n\n{verdict}.\n\n"
               + markdown_table(tab, ".2f"))
    ref = ok[ok.metric == "reference_error"]
    vs_ref = ok[ok.metric == "pin_error_vs_reference"]
    if len(ref) and len(vs_ref):
        tab_ref = vs_ref.pivot_table(index=["trial", "variant", "start"], columns="pin",
                                     values="value").reset_index()
        at = ref.set_index("pin")["value"]
        ctx.report("Against the pin-based reference (as the paper measured)",
                   "The starts are made from a pin-based registration with its own error "
                   "(pins located in CT and touched by the robot, as in `table2`); it lies "
                   + ", ".join(f"{v:.2f} mm at {k}" for k, v in at.items())
                   + f" from the truth, and the located {pin} pin keeps that error. The "
                   "errors against that reference:\n\n" + markdown_table(tab_ref, ".2f"))
    lost = views_lost_markdown(ok)
    if lost:
        ctx.report("Views left out", lost)
    ctx.report("Against the paper", "\n".join(paper_lines(pe, vs_ref, w, pin)))
    _figure(ctx, pe, w, pin)
    return df


def paper_lines(pe: pd.DataFrame, vs_ref: pd.DataFrame, w: pd.DataFrame,
                pin: str = "proximal") -> list[str]:
    """The report's lines against the paper's two findings (a review, h87: the report gave
    none, and the simulation had reversed the paper's finding that the pin helps without a
    word): with the pin located, every other pin within 2 mm (met or missed, against the
    truth and against the pin-based reference, as the paper measured); the views alone
    about 5 mm (a figure, not a bound: shown beside it); and whether the pin helped, with
    how many of each were accepted (a review, h90: the views alone were all refused).
    ``pe``/``vs_ref``: the rows of ``pin_error`` / ``pin_error_vs_reference``; ``w`` per
    variant, trial and start its ``accepted``. A located pin other than the proximal one is
    not the paper's set-up: its lines say so and compare nothing with the paper."""
    with_pin = pinned_variant(pin)
    key = ["trial", "start"]
    others = pe[pe.pin != pin]
    worst = others.groupby(["variant", *key])["value"].max()
    # per variant, how many of the starts with a pin error the verdict accepted
    accepted = (w.set_index(["variant", *key])["accepted"] > 0.5).reindex(worst.index)
    n_acc = accepted.fillna(False).astype(int).groupby(level="variant").sum()
    variants = set(worst.index.get_level_values("variant"))
    paper = pin == "proximal"
    lines = [] if paper else [
        f"- not the paper's set-up: the paper located the proximal pin, this scene the {pin} "
        "pin; the figures below are not compared with the paper's"]

    if with_pin in variants:
        wp = worst.xs(with_pin, level="variant")
        ok = int((wp <= PAPER_WITH_PIN_MM).sum())
        ref = vs_ref[(vs_ref.pin != pin) & (vs_ref.variant == with_pin)]
        ref_txt = ""
        if len(ref):
            rw = ref.groupby(key)["value"].max()
            ref_txt = (f"; against the pin-based reference, as the paper measured: "
                       f"{int((rw <= PAPER_WITH_PIN_MM).sum())} of {len(rw)}, the largest "
                       f"{rw.max():.2f} mm")
        word = ("met" if ok == len(wp) else "**missed**") if paper else "measured"
        lines.append(
            f"- {word}: with the {pin} pin located, every other pin within "
            f"{PAPER_WITH_PIN_MM:g} mm of the truth from {ok} of {len(wp)} starts, the largest "
            f"{wp.max():.2f} mm ({n_acc[with_pin]} of {len(wp)} accepted by the "
            f"method's verdict){ref_txt}"
            + (f" (the paper: the distal pins within {PAPER_WITH_PIN_MM:g} mm)" if paper else ""))
    med = others.groupby("variant")["value"].median()
    if "views alone" in variants:
        va = worst.xs("views alone", level="variant")
        lines.append(f"- the views alone: the other pins' median error {med['views alone']:.2f} "
                     f"mm, the largest {va.max():.2f} mm ({n_acc['views alone']} of "
                     f"{len(va)} accepted)" + (f" (the paper: about {PAPER_VIEWS_ALONE_MM:g} "
                                               "mm; a figure, not a bound)" if paper else ""))
    if paper and with_pin in med.index and "views alone" in med.index:
        a, b = float(med[with_pin]), float(med["views alone"])
        counts = (f"{n_acc[with_pin]} and {n_acc['views alone']} accepted; the medians "
                  "include refused starts")
        if not (np.isfinite(a) and np.isfinite(b)):
            lines.append("- not comparable: a variant has no finite pin error")
        else:
            lines.append(
                f"- {'as the paper' if a < b else '**unlike the paper**'}: the located pin "
                f"{'lowers' if a < b else 'does not lower'} the other pins' median error "
                f"({a:.2f} mm with it, {b:.2f} mm without; {counts}; the paper: within "
                f"{PAPER_WITH_PIN_MM:g} mm against about {PAPER_VIEWS_ALONE_MM:g} mm)")
    n_cases = pe["trial"].nunique() if "trial" in pe else 1
    lines.append(f"\nThese are {n_cases} case(s), each one femur, one pose and one draw of "
                 "every error source, registered from several starts: the spread over the "
                 "draws is that of `testbed run experiment1 --seed S` over seeds (README, "
                 "section 'The verdict: `accepted`').")
    return lines


#: the paper's experiment 1 (Sec. V): distal pins within 2 mm with the proximal pin, about
#: 5 mm with the fluoroscopic views alone
PAPER_WITH_PIN_MM, PAPER_VIEWS_ALONE_MM = 2.0, 5.0


def _figure(ctx, pe: pd.DataFrame, w: pd.DataFrame, pin: str = "proximal") -> None:
    """The error of each pin but the located ``pin`` per start, the two variants side by
    side, the accepted ones filled, with the paper's figures as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    distal = pe[pe.pin != pin]
    variants = [pinned_variant(pin), "views alone"]
    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for x, variant in enumerate(variants):
        d = distal[distal.variant == variant].merge(
            w[["trial", "variant", "start", "accepted"]], on=["trial", "variant", "start"])
        jitter = np.linspace(-0.15, 0.15, max(len(d), 1))[: len(d)]
        acc = d["accepted"].to_numpy() > 0.5
        ax.scatter(x + jitter[acc], d["value"].to_numpy()[acc], color="C0",
                   label="accepted" if x == 0 else None)
        ax.scatter(x + jitter[~acc], d["value"].to_numpy()[~acc], facecolors="none",
                   edgecolors="C3", label="refused" if x == 0 else None)
    for y, text in ((PAPER_WITH_PIN_MM, "paper, with the pin"),
                    (PAPER_VIEWS_ALONE_MM, "paper, views alone")):
        ax.axhline(y, color="grey", ls=":", lw=1)
        ax.text(1.45, y, text, fontsize=7, va="bottom", ha="right", color="grey")
    ax.set_xticks(range(len(variants)), variants)
    ax.set_xlim(-0.5, 1.5)
    ax.set_ylabel("error of the other pins (mm)" if pin != "proximal"
                  else "distal pin error (mm)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    others = "distal pin" if pin == "proximal" else "pin but the located one"
    fig.savefig(ctx.figure("experiment1.png", f"The error of each {others} per start, with the "
                           f"{pin} pin located and with the views alone (filled: accepted "
                           "by the method's verdict; dotted: the paper's figures)"), dpi=110)
    plt.close(fig)
