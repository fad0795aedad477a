"""Table II of the paper: error at the pins after registration from 11 starts, over many cases.

Each trial is one simulated case of the scene (``experiment2``: four views, two proximal and
two distal, femur on an OR table; case ``i`` of the study seed, as ``testbed run`` and
``testbed generate`` simulate it): registration from the pin-based registration (the paper's
starting pose, with its own error: :func:`studies.scoring.pin_reference`) and from five 5 deg
and five 7 deg rotations of it about seeded random axes through the pins' centroid. The error
at each pin is the distance between its position under the estimated and the true
``ct2robot``, and, as the paper measured it, under that reference.

The report puts, per pin, the simulated distribution over the cases (median and IQR over
every case and perturbed start; the identity start apart) beside the paper's values, and the
calibration validation of every view beside the paper's 0.1-0.4 mm, with the targets of a
clinic-realistic simulation: mean pin error 1.8-4.2 mm, each pin's median within a factor
of 1.5 of the paper's, validation within 0.1-0.4 mm.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from studies.common import cell_text, markdown_table, one_line, plain_log_ticks
from studies.end_to_end import (
    PAPER_METHOD,
    PAPER_TABLE2,
    PIN_NAMES,
    case_rows,
    prepare_case,
    registration_rows,
    table2_starts,
    views_lost_markdown,
)
from studies.scoring import (
    REFERENCE_CT_SIGMA_MM,
    REFERENCE_ROBOT_SIGMA_MM,
    case_reference,
    pin_errors,
)

TITLE = "the paper's Table II: pin errors after registration from 11 perturbed starts"
DEFAULT_SCENE = "experiment2"
CASES = 20
QUICK_CASES = 1
#: the targets of a clinic-realistic simulation (issue: the testbed's errors must predict
#: the paper's)
TARGET_MEAN_MM = (1.8, 4.2)
TARGET_MEDIAN_RATIO = 1.5
TARGET_VALIDATION_MM = (0.1, 0.4)


def paper_medians() -> dict[str, float]:
    """Per pin, the median of the paper's Table II over its readable perturbed starts."""
    rows = [v for k, v in PAPER_TABLE2.items() if k != "identity"]
    return {p: float(np.median([r[i] for r in rows])) for i, p in enumerate(PIN_NAMES)}


def trial(tr) -> list[dict]:
    """One case and its 11 (quick: 5) starts."""
    from testbed.scene import load_scene

    case = prepare_case(load_scene(tr.scene), tr.seed_sequence)
    # the paper's starts: its pin-based registration, and that turned
    reference = case_reference(case.sim.truth, tr.seed_sequence)
    starts = table2_starts(case, tr.seed_sequence, quick=bool(tr.params["quick"]),
                           pose=reference)
    ref_rows = [{"metric": "reference_error", "value": e, "unit": "mm", "pin": p}
                for p, e in pin_errors(reference, case.ct2robot, case.pins_ct).items()]
    paper = {k: v for k, v in PAPER_METHOD.items() if k != "registration"}
    return (case_rows(case) + ref_rows
            + registration_rows(case, starts, reference=reference, method_name="default")
            + registration_rows(case, starts, reference=reference, method_name="paper",
                                **paper,
                                **PAPER_METHOD["registration"]))


def check_scene(scene, path) -> None:
    """Refuse, before any work (``studies.run_study``), a scene that locates a pin."""
    from studies.common import refuse_fixed_pin

    refuse_fixed_pin(scene, path, "table2")


def run(ctx) -> pd.DataFrame:
    from studies.runner import run_study_trials

    n = QUICK_CASES if ctx.quick else CASES
    df = run_study_trials(ctx, trial, [{"case": i, "quick": bool(ctx.quick)} for i in range(n)])
    ok = df[df.metric != "failed"]
    failures = df.attrs.get("failures", {})
    if ok.empty or "statistic" not in ok:
        ctx.report("Pin errors (mm) beside the paper's Table II",
                   "No case finished: nothing to tabulate.")
        if failures:
            ctx.report("Failed cases",
                       "\n".join(f"- case {k}: {v}" for k, v in failures.items()))
        return df
    ctx.report("Pin errors (mm) beside the paper's Table II",
               table2_markdown(ok) + cases_note(ctx.scene))
    if "method" in ok and (ok["method"] == "paper").any():
        ctx.report("The paper's registration method in the same world",
                   "The same cases and starts registered with the method as the paper published "
                   "it (one loop, point-to-path residual, Tukey a = 2, no restarts; "
                   "`studies.end_to_end.PAPER_METHOD`) instead of reglib's default "
                   "(coarse-fine, across-contour residual, a = 4.685, restarts). If the gap to "
                   "the paper came from its registration method, this table would close it; "
                   "what it leaves is the world's.\n\n" + table2_markdown(ok, method="paper"))
    ref = ok[ok.metric == "reference_error"]
    if len(ref):
        ctx.report("Against the paper's kind of reference",
                   "The paper measured its errors against a pin-based registration, itself in "
                   "error: here the pins located in CT, each with a Gaussian error "
                   f"({REFERENCE_CT_SIGMA_MM} mm per axis), and touched by the case's robot, "
                   "with its own absolute error at each pin (the error its sweeps share in "
                   f"part; a Gaussian {REFERENCE_ROBOT_SIGMA_MM} mm per axis where it could "
                   "not reach one), registered by least squares. That reference lies "
                   f"{ref['value'].median():.2f} mm (median, {ref['value'].max():.2f} mm at "
                   "most) from the truth at the pins; the errors against it:\n\n"
                   + table2_markdown(ok, "pin_error_vs_reference"))
    ctx.report("Calibration validation (mm) beside the paper's 0.1-0.4 mm",
               validation_markdown(ok))
    lost = views_lost_markdown(ok)
    if lost:
        ctx.report("Views left out", lost)
    ctx.report("Targets of a clinic-realistic simulation",
               set_up_note(ctx.scene) + targets_markdown(ok))
    if failures:
        ctx.report("Failed cases", "\n".join(f"- case {k}: {v}" for k, v in failures.items()))
    _figure(ctx, ok)
    return df


def _figure(ctx, df: pd.DataFrame) -> None:
    """Per pin, the simulated pin errors of the perturbed starts (a box per method: quartiles,
    whiskers at the 5th and 95th percentiles) beside the paper's Table II values
    (diamonds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pe = df[(df.metric == "pin_error") & (df.start != "identity")]
    if pe.empty:
        return
    methods = [m for m in ("default", "paper") if len(_of_method(pe, m))]
    fig, ax = plt.subplots(figsize=(9.5, 4.2))
    width = 0.8 / (len(methods) + 1)
    paper = [v for k, v in PAPER_TABLE2.items() if k != "identity"]
    for i, pin in enumerate(PIN_NAMES):
        for j, m in enumerate(methods):
            x = i + (j - len(methods) / 2) * width
            vals = _of_method(pe, m)
            vals = vals[vals.pin == pin]["value"].to_numpy()
            ax.boxplot(vals, positions=[x], widths=width * 0.8, whis=(5, 95),
                       showfliers=False, patch_artist=True,
                       boxprops={"facecolor": ("tab:blue", "tab:orange")[j], "alpha": 0.5},
                       medianprops={"color": "k"})
        xp = i + (len(methods) / 2) * width
        ax.plot(np.full(len(paper), xp), [r[i] for r in paper], "D", color="tab:red",
                ms=5, label="paper, Table II" if i == 0 else None)
    for j, m in enumerate(methods):
        ax.plot([], [], "s", color=("tab:blue", "tab:orange")[j], alpha=0.5,
                label={"default": "simulated, reglib default", "paper": "simulated, the "
                       "paper's method"}[m])
    ax.set_xticks(range(len(PIN_NAMES)), PIN_NAMES)
    ax.set_ylabel("error at the pin (mm)")
    ax.set_yscale("log")
    plain_log_ticks(ax)
    ax.set_title("Pin errors from the 5 and 7 deg starts (boxes: quartiles, whiskers 5-95 %)",
                 fontsize=9)
    # beside the axes: inside, it covered the paper's markers (a review)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax.grid(axis="y", alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(ctx.figure("table2_pins.png", "Pin errors after registration from the "
                           "perturbed starts, simulated (per method) beside the paper's "
                           "Table II"), dpi=110)
    plt.close(fig)


def _iqr(x) -> str:
    q1, q3 = np.percentile(x, [25, 75])
    return f"{q1:.2f}-{q3:.2f}"


def _of_method(df: pd.DataFrame, method: str) -> pd.DataFrame:
    """The rows of one registration method (rows without a ``method`` are the default's)."""
    if "method" not in df:
        return df if method == "default" else df.iloc[:0]
    m = df["method"].fillna("default")
    return df[(m == method) | df["metric"].isin(CASE_METRICS)]


#: per-case metrics (no registration method)
CASE_METRICS = ("validation_distance", "calibration_ok", "view_used", "contour_pixels",
                "sim_time", "reference_error")


def table2_markdown(df: pd.DataFrame, metric: str = "pin_error", *,
                    method: str = "default") -> str:
    df = _of_method(df, method)
    pe = df[df.metric == metric]
    if pe.empty:
        return "No registration finished."
    paper = paper_medians()
    ident = PAPER_TABLE2["identity"]
    rows = []
    for i, pin in enumerate(PIN_NAMES):
        pert = pe[(pe.pin == pin) & (pe.start != "identity")]["value"].to_numpy()
        idn = pe[(pe.pin == pin) & (pe.start == "identity")]["value"].to_numpy()
        rows.append({
            "pin": pin,
            "median (perturbed)": float(np.median(pert)) if pert.size else np.nan,
            "IQR (perturbed)": _iqr(pert) if pert.size else "",
            "paper median": paper[pin],
            "ratio": float(np.median(pert)) / paper[pin] if pert.size else np.nan,
            "median (identity)": float(np.median(idn)) if idn.size else np.nan,
            "IQR (identity)": _iqr(idn) if idn.size else "",
            "paper identity": ident[i],
        })
    n_cases = df["trial"].nunique()
    conv = df[df.metric == "converged"]["value"]
    acc = df[df.metric == "accepted"]["value"]
    # counts, not rates: "100% converged" stood for 219 of 220 (a held-out review, h95)
    return (markdown_table(pd.DataFrame(rows), ".2f")
            + f"\n\n{n_cases} case(s), {len(conv)} registrations: {int(conv.sum())} of "
            f"{len(conv)} converged, {int(acc.sum())} of {len(acc)} accepted by reglib's verdict "
            "(computed without the truth; the "
            "paper's method had none). Paper: 1.2-3.7 mm, once "
            "4.8 mm; per-pin medians of its readable rows "
            + ", ".join(f"{k} {v:.2f}" for k, v in paper.items()) + " mm."
            + _refused_included(pe))


#: a registration whose worst pin ends farther than this (mm) is counted as far off
FAR_OFF_MM = 5.0


def _refused_included(pe: pd.DataFrame) -> str:
    """A sentence when the quartiles above include registrations far off: how many ended
    beyond :data:`FAR_OFF_MM` at a pin, and the largest (a review, h87: the paper's
    method's table and its whiskers hid 9 registrations ending 5-68 mm off, refused by the
    verdict)."""
    keys = [k for k in ("trial", "start") if k in pe]
    if not keys:
        return ""
    worst = pe.groupby(keys)["value"].max()
    far = worst[worst > FAR_OFF_MM]
    if far.empty:
        return ""
    return (f" The figures include every registration, refused or not: {len(far)} of "
            f"{len(worst)} ended more than {FAR_OFF_MM:g} mm off at a pin (up to "
            f"{float(far.max()):.1f} mm); `results.csv` holds each one's `accepted`.")


def validation_markdown(df: pd.DataFrame) -> str:
    v = df[(df.metric == "validation_distance") & (df.statistic == "max")]
    if v.empty:
        return "No calibration was validated."
    t = v.groupby("view")["value"].agg(["median", "min", "max"]).reset_index()
    ok = df[df.metric == "calibration_ok"].groupby("view")["value"].mean().rename(
        "share passed").reset_index()
    t = t.merge(ok, on="view")
    used = df[df.metric == "view_used"]
    if len(used):   # results of before view_used was recorded have none
        t = t.merge(used.groupby("view")["value"].mean().rename("share used").reset_index(),
                    on="view", how="left")
    return markdown_table(t, ".3f") + (
        "\n\nLargest distance per view and case between the validation row's robot-reported "
        "bead positions and the calibrated X-ray paths of their images (median, min and max "
        "over the cases); a view fails above 1 mm. `share passed`: of the cases, those whose "
        "calibration passed"
        + ("; `share used`: those whose view the registration used (a view can be left out "
           "after its calibration passed: section 'Views left out')" if len(used) else "")
        + ".")


def cases_note(scene) -> str:
    """What the cases share and what each draws (a review, h87: "20 case(s)" read as 20
    patients, where the shipped scene's cases are one femur at one pose)."""
    phantom, patient = getattr(scene, "phantom", None), getattr(scene, "patient", None)
    if phantom is None or patient is None:
        return ""
    same_femur = phantom.mesh_path is not None or float(phantom.shape_variation) == 0.0
    same_pose = (not any(float(x) > 0 for x in patient.position_sd_mm)
                 and not any(float(x) > 0 for x in patient.rotation_sd_deg))
    femur = ("one femur" if same_femur else
             f"a femur drawn per case (`[phantom] shape_variation = "
             f"{float(phantom.shape_variation):g}`)")
    pose = ("at one pose under the same views" if same_pose else
            "placed per case (`[patient] position_sd_mm`, `rotation_sd_deg`) under the same "
            "views")
    return (f"\n\nThe cases are {femur} {pose}, as the paper's Table II is one specimen; "
            "each case draws its own errors of every source of the scene's error model "
            "(robot, rod, image chain, CT, the operator's clicks; docs/error-model.md) from "
            "its seed, so the spread is that of a repeated procedure, not of a population.")


def set_up_note(scene) -> str:
    """A line before the targets when the scene is not the set-up they are of (the paper's
    Table II: four views of a clinic), empty otherwise: a review ran table2 on two-view and
    ideal-profile scenes and read "missed" against targets never meant for them."""
    differs = []
    if len(scene.views) != 4:
        differs.append(f"{len(scene.views)} view(s), where the paper's Table II had 4")
    fluoro = getattr(scene, "fluoroscope", None)
    if fluoro is not None and fluoro == fluoro.ideal():
        differs.append("the ideal profile's fluoroscope (no blur, scatter or local distortion), "
                       "where the targets are a clinic's")
    if not differs:
        return ""
    return ("**This scene is not the set-up the targets are of**: it has "
            + "; and ".join(differs) + ". Read the lines below as a comparison with the "
            "paper's experiment 2, not as targets of this scene.\n\n")


def _first_refusal(df: pd.DataFrame) -> str:
    """", and its verdict's `reason`; the first: ..." for the first refused registration
    with a recorded reason (results of before reasons were recorded: "")."""
    acc = df[(df.metric == "accepted") & (df.value == 0)]
    if "reason" not in acc:
        return ""
    acc = acc[acc["reason"].fillna("").astype(str) != ""]
    if acc.empty:
        return ""
    r = acc.iloc[0]
    where = ", ".join(f"{k} {cell_text(r[k])}" for k in ("case", "start")
                      if k in r and cell_text(r[k]))
    return f", and its verdict's `reason`; the first ({where}): {one_line(r['reason'], 300)}"


def targets_markdown(df: pd.DataFrame) -> str:
    full = df
    df = _of_method(df, "default")
    pe = df[(df.metric == "pin_error")]
    if pe.empty:
        return "No registration finished: no target can be checked."
    paper = paper_medians()
    mean = float(pe["value"].mean())
    lines = []
    # the figures below are of every registration; say so when the method refused some
    # (a held-out review: 0 of 10 accepted and a target reported "met")
    acc = df[df.metric == "accepted"]["value"]
    conv = df[df.metric == "converged"]["value"]
    if len(acc) and (acc == 0).any():
        lines.append(
            f"- **note**: {int((acc == 0).sum())} of {len(acc)} registrations were refused by "
            f"the method's own verdict ({int((conv == 0).sum())} did not converge); the figures "
            "below include them, though a clinic would not use a refused pose: `results.csv` "
            "holds each registration's `accepted`" + _first_refusal(df))

    # every pose refused: the figures are of poses no clinic would use, and a target they
    # meet is no verdict on the method (a review: 5 of 5 refused, the mean "met")
    none_accepted = len(acc) > 0 and not (acc > 0).any()

    def check(ok, text, of_poses=True):
        word = ("**not judged** (every pose refused)" if none_accepted and of_poses
                else "met" if ok else "**missed**")
        lines.append(f"- {word}: {text}")

    check(TARGET_MEAN_MM[0] <= mean <= TARGET_MEAN_MM[1],
          f"mean pin error {mean:.2f} mm (target {TARGET_MEAN_MM[0]}-{TARGET_MEAN_MM[1]} mm)")
    if mean < TARGET_MEAN_MM[0]:
        lines.append(
            f"  - to reach {TARGET_MEAN_MM[0]} mm an independent error of "
            f"{np.sqrt(TARGET_MEAN_MM[0]**2 - mean**2):.2f} mm at the pins is missing (errors "
            "adding in quadrature); `testbed study error-budget` attributes the error to each "
            "source and gives the factor by which each source's magnitude would have to grow "
            "to supply it (section 'What would close the gap to the paper'; from the "
            "scene's ideal profile, `<name>-ideal.toml` beside the scene file, or else the "
            "shipped ideal magnitudes).")
    # like with like (a review, h87: the line above measures the gap to the target's lower
    # bound, not to the paper): the paper's own mean over its readable rows
    paper_mean = float(np.mean(list(PAPER_TABLE2.values())))
    if mean < paper_mean:
        lines.append(
            f"  - against the paper's own mean, {paper_mean:.2f} mm over its readable rows of "
            f"Table II (the identity start included, as here): {mean / paper_mean:.2f} x it; "
            f"an independent {np.sqrt(paper_mean**2 - mean**2):.2f} mm at the pins is missing "
            "to reach it")
    vs_ref = df[df.metric == "pin_error_vs_reference"]
    if len(vs_ref):
        lines.append(
            f"  - measured as the paper measured it, against the pin-based reference: mean "
            f"{float(vs_ref['value'].mean()):.2f} mm (the pins' errors against the truth "
            "include the robot's error that the reference, touched by the same robot, shares)")
    for pin in PIN_NAMES:
        m = float(pe[(pe.pin == pin) & (pe.start != "identity")]["value"].median())
        r = m / paper[pin]
        check(1 / TARGET_MEDIAN_RATIO <= r <= TARGET_MEDIAN_RATIO,
              f"{pin}: median {m:.2f} mm = {r:.2f} x the paper's {paper[pin]:.2f} mm (target "
              f"within {TARGET_MEDIAN_RATIO}x)")
    v = df[(df.metric == "validation_distance") & (df.statistic == "max")]["value"]
    if len(v):   # to 0.001 mm: 0.404 mm, outside the target, printed as 0.40 (a review)
        check(bool(((v >= TARGET_VALIDATION_MM[0]) & (v <= TARGET_VALIDATION_MM[1])).all()),
              f"calibration validation {v.min():.3f}-{v.max():.3f} mm over every view and case "
              f"(target {TARGET_VALIDATION_MM[0]}-{TARGET_VALIDATION_MM[1]} mm)",
              of_poses=False)
        vv = df[(df.metric == "validation_distance") & (df.statistic == "max")]
        med = vv.groupby(vv["view"] if "view" in vv else pd.Series("", index=vv.index))[
            "value"].median()
        inside = (med >= TARGET_VALIDATION_MM[0]) & (med <= TARGET_VALIDATION_MM[1])
        lines.append(
            f"  - read per view, as the paper reports one experiment: the median over the cases "
            f"of each view's largest distance is {med.min():.3f}-{med.max():.3f} mm, inside "
            f"the range for {int(inside.sum())} of {len(med)} views; "
            f"{int(((v < TARGET_VALIDATION_MM[0]) | (v > TARGET_VALIDATION_MM[1])).sum())} of "
            f"{len(v)} view-cases lie outside it.")
    paper = _of_method(full, "paper")
    pp = paper[(paper.metric == "pin_error")] if "method" in full else paper.iloc[:0]
    if len(pp):
        acc = paper[paper.metric == "accepted"]["value"]
        lines.append(
            f"- the paper's registration method on the same cases and starts: mean pin error "
            f"{pp['value'].mean():.2f} mm, median {pp['value'].median():.2f} mm"
            + (f", {int((acc == 0).sum())} of {len(acc)} registrations refused by the "
               "method's verdict" if len(acc) else "")
            + " (not a target: it shows how much of the gap the registration method explains)")
    return "\n".join(lines)
