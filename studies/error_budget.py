"""Error budget: where the error at the pins comes from, by stage and by error source.

Two attributions of the Table II error (the quick Table II starts of each case: identity,
two 5 deg and two 7 deg rotations):

- **by source** (the world): the scene (the clinic profile, e.g. ``experiment2``) is
  compared field by field with its ideal profile (``<name>-ideal.toml`` beside the scene
  file, or the named scene ``<name>-ideal`` when it has the scene's set-up, e.g.
  ``experiment2-ideal``; else the shipped ideal magnitudes, :func:`shipped_ideal_fields`);
  every field that differs is an error source (fields that belong
  together, such as the distortion's coefficients, are one source: :data:`SOURCE_GROUPS`).
  Each source is switched **off** in the clinic (set to its ideal value) and **on alone** in
  the ideal profile; the drop (off) and the rise (alone) of the mean pin error against the
  clinic and the ideal runs are its share, drawn as a tornado chart. Nothing here knows the
  sources' names: a field added to the profiles is a new source.
- **by stage** (the method): on the clinic cases, each estimated input of the registration
  is replaced by its truth (true calibration, true surfaces, true X-ray contours, all
  three); the drop in error when a stage is made perfect is the share of that stage.

Each trial is one case of one configuration (``config``: ``clinic``, ``ideal``, ``off`` or
``alone``, with ``source``); case ``i`` has the same seed in every configuration, so the
configurations differ only by the source.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd

from studies.common import cell_text, markdown_table
from studies.end_to_end import (
    case_rows,
    prepare_case,
    registration_rows,
    table2_starts,
    views_lost_markdown,
)

TITLE = "error budget: pin errors by error source (off / on alone) and by stage (truth in)"
DEFAULT_SCENE = "experiment2"
ORACLE_CONFIGS = ((), ("calibration",), ("surfaces",), ("contours",),
                  ("calibration", "surfaces", "contours"))
CASES = 3
QUICK_CASES = 1
#: fields of the scene that form one error source: regex on the dotted field path -> source
SOURCE_GROUPS = (
    (r"^fluoroscope\.distortion_drift", "distortion drift"),
    (r"^fluoroscope\.(distortion|pincushion_|distortion_|earth_field|s_rotation|s_shift|"
     r"local_distortion)", "intensifier distortion"),
    (r"^fluoroscope\.(focal_spot)", "focal-spot blur"),
    (r"^fluoroscope\.(mtf|intensifier_blur|video_blur)", "intensifier and video blur"),
    (r"^fluoroscope\.video_noise", "camera noise"),
    (r"^fluoroscope\.(scatter)", "scatter"),
    (r"^fluoroscope\.(noise|photons_per_pixel|abc_photons)", "quantum noise"),
    (r"^fluoroscope\.(video_|gain|offset|black_u8|white_u8|display_range)", "video"),
    (r"^fluoroscope\.(glare|vignetting)", "glare and vignetting"),
    (r"^robot\.(kinematic|absolute|link_error|joint_offset|calibration_error)",
     "robot accuracy"),
    (r"^robot\.rod\.sag", "rod sag"),
    (r"^robot\.rod\.(bead_|youngs|density)", "bead placement"),
    (r"^robot\.rod_mount", "rod mounting"),
    (r"^ct\.(metal_streaks|streak_hu)", "CT metal streaks"),
    (r"^ct\.(max_slice_thickness_mm|slice_thickness_mm)", "CT slice thickness"),
    (r"^ct\.noise_", "CT noise"),
    (r"^operator\.ct_", "operator on CT"),
    (r"^operator\.", "operator on X-ray"),
)
#: paths that are not error sources (names; the registration's options; the anatomy: the
#: ideal profile keeps the femur its regression thresholds were set on; how the quanta are
#: sampled, one law either way); the set-up, views included, must be equal (GEOMETRY)
NOT_SOURCES = (r"^scene\.", r"^registration\.", r"^workspace\.", r"^phantom\.",
               r"^fluoroscope\.quantum_sampler$")
#: the set-up, which an ideal profile must share with its clinic scene: where the patient
#: lies, the views and the instruments (not sources: a review paired a moved patient with the
#: shipped ideal profile, and the error budget listed the patient's pose as a source)
GEOMETRY = (r"^patient\.", r"^views", r"^instruments")


# --------------------------------------------------------------------------- profiles
def _flatten(d, prefix="") -> dict:
    out = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    else:
        out[prefix] = d
    return out


def _set(d: dict, path: str, value) -> None:
    keys = path.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def source_of(path: str) -> str:
    """The error source a scene field belongs to (its own path when no group matches)."""
    for pattern, name in SOURCE_GROUPS:
        if re.search(pattern, path):
            return name
    return path


def error_sources(clinic, ideal) -> dict[str, dict[str, tuple]]:
    """Source -> {field path: (clinic value, ideal value)} for every field that differs.
    Raises SceneError naming the fields when the two differ in their set-up
    (:data:`GEOMETRY`): the budget compares magnitudes of one set-up."""
    from testbed.spec import SceneError

    a = _flatten(clinic.model_dump(mode="json"))
    b = _flatten(ideal.model_dump(mode="json"))
    moved = [p for p in sorted(set(a) | set(b))
             if any(re.search(g, p) for g in GEOMETRY) and a.get(p) != b.get(p)]
    if moved:
        raise SceneError(
            f"the ideal profile ({ideal.scene.name}) differs from the scene "
            f"({clinic.scene.name}) in its set-up, not only in error magnitudes: "
            f"{', '.join(moved[:4])}{' ...' if len(moved) > 4 else ''}; the error budget "
            "needs an ideal profile with the same patient pose, views and instruments "
            "(<scene>-ideal.toml beside the scene file)")
    out: dict[str, dict[str, tuple]] = {}
    for path in sorted(set(a) | set(b)):
        if any(re.search(p, path) for p in NOT_SOURCES):
            continue
        if a.get(path) != b.get(path):
            out.setdefault(source_of(path), {})[path] = (a.get(path), b.get(path))
    return out


def variant(base, fields: dict[str, object]):
    """``base`` scene with the dotted ``fields`` set (validated like a scene file)."""
    from testbed.scene import parse_scene

    d = base.model_dump(mode="json")
    for path, value in fields.items():
        _set(d, path, value)
    return parse_scene(d, source=f"{base.scene.name} (error-budget variant)")


def ideal_scene_path(scene_path) -> str | None:
    """The ideal profile of a scene: ``<name>-ideal`` beside it or among the named scenes."""
    from pathlib import Path

    from testbed.scene import SceneError, find_scene

    p = Path(scene_path)
    cand = p.with_name(p.stem + "-ideal.toml")
    if cand.is_file():
        return str(cand)
    try:
        return str(find_scene(p.stem + "-ideal"))
    except (SceneError, ValueError):
        return None


#: the shipped profiles whose difference defines the ideal magnitudes that stand in for a
#: scene without its own ideal profile
SHIPPED_PAIR = ("experiment2", "experiment2-ideal")
#: ``params["ideal"]`` of a scene without its own ideal profile
SHIPPED = "shipped"


def shipped_ideal(scene):
    """``scene`` with its error sources at the shipped ideal profile's magnitudes (see
    :func:`shipped_ideal_fields`), the rest (femur, set-up, options) its own. For a scene
    without its own ideal profile (a held-out review: every held-out scene got no budget by
    source, and table2 pointed to a section that was then not written)."""
    values, _ = shipped_ideal_fields(scene)
    out = variant(scene, values)
    return out.model_copy(update={"scene": out.scene.model_copy(
        update={"name": f"{scene.scene.name} (shipped ideal magnitudes)"})})


def shipped_ideal_fields(scene) -> tuple[dict, dict]:
    """The fields :func:`shipped_ideal` sets, and the sources it leaves at the scene's value
    with why: ``({path: ideal value}, {source: reason})``.

    Each field in which ``experiment2-ideal`` differs from ``experiment2``
    (:func:`error_sources`) takes the ideal profile's value, source by source, except:
    a number the scene already holds at a smaller magnitude (the ideal never makes a source
    larger: a scene's 0.5 px clicks became 1 px, a review), and a source whose values the
    scene's other fields refuse (e.g. its own ``[ct] slice_thickness_mm`` beside the ideal
    ``max_slice_thickness_mm``: one such clash had dropped every source, a review)."""
    from testbed.scene import find_scene, load_scene

    clinic, ideal = (load_scene(find_scene(n)) for n in SHIPPED_PAIR)
    own = _flatten(scene.model_dump(mode="json"))
    values, skipped = {}, {}
    for source, fields in error_sources(clinic, ideal).items():
        take = {}
        for path, (_, v) in fields.items():
            mine = own.get(path)
            number = (isinstance(v, int | float) and not isinstance(v, bool)
                      and isinstance(mine, int | float) and not isinstance(mine, bool))
            if not (number and abs(mine) <= abs(v)) and mine != v:
                take[path] = v
        if not take:
            continue
        try:
            variant(scene, {**values, **take})
        except ValueError as exc:
            skipped[source] = str(exc).splitlines()[-1][:200]
            continue
        values.update(take)
    return values, skipped


def ideal_profile(clinic, ideal: str):
    """The ideal profile a trial's ``params["ideal"]`` names: a scene file, or
    :data:`SHIPPED` (:func:`shipped_ideal` of ``clinic``)."""
    from testbed.scene import load_scene

    return shipped_ideal(clinic) if ideal == SHIPPED else load_scene(ideal)


def no_budget_reason(scene, scene_path) -> str:
    """Why a scene gets no budget by source (:func:`trial_params` found no source to vary)."""
    own = ideal_scene_path(scene_path)
    if own and _beside(own, scene_path):
        return (f"The scene equals its ideal profile `{own}` in every error source: no "
                "source to switch off")
    _, skipped = shipped_ideal_fields(scene)
    if skipped:
        return ("The shipped ideal magnitudes cannot be applied to this scene ("
                + "; ".join(f"{k}: {v}" for k, v in skipped.items())
                + f"); give it an ideal profile, `{Path(scene_path).stem}-ideal.toml` "
                "beside it")
    return (f"Every error source the budget knows (the fields in which `{SHIPPED_PAIR[1]}` "
            f"differs from `{SHIPPED_PAIR[0]}`) is at its shipped ideal magnitude or below "
            "in this scene: no source to switch off (other fields are not switched)")


def _beside(profile, scene_path) -> bool:
    """Whether ``profile`` lies in the scene file's own folder (the user's own profile)."""
    return Path(profile).resolve().parent == Path(scene_path).resolve().parent


# --------------------------------------------------------------------------- trials
def _scene_of(tr):
    from testbed.scene import load_scene

    clinic = load_scene(tr.scene)
    cfg = tr.params["config"]
    if cfg == "clinic":
        return clinic
    ideal = ideal_of(clinic, ideal_profile(clinic, tr.params["ideal"]))
    if cfg == "ideal":
        return ideal
    fields = error_sources(clinic, ideal)[tr.params["source"]]
    if cfg == "off":
        return variant(clinic, {k: v[1] for k, v in fields.items()})
    return variant(ideal, {k: v[0] for k, v in fields.items()})  # "alone"


def ideal_of(clinic, ideal_profile):
    """The ideal configuration of ``clinic``: its scene with every error source at the
    ideal profile's magnitude. What is no source (the femur, the registration's options,
    the workspace check: :data:`NOT_SOURCES`) stays the clinic scene's; the ideal profile's
    own were used before, and a user's femur was compared with the shipped one without a
    word (a review)."""
    sources = error_sources(clinic, ideal_profile)
    return variant(clinic, {k: v[1] for fields in sources.values() for k, v in fields.items()})


def trial(tr) -> list[dict]:
    """One case of one configuration; the clinic configuration adds the stage budget."""
    case = prepare_case(_scene_of(tr), tr.seed_sequence)
    starts = table2_starts(case, tr.seed_sequence, quick=True)
    rows = case_rows(case)
    oracles = ORACLE_CONFIGS if tr.params["config"] == "clinic" else ((),)
    for oracle in oracles:
        rows += registration_rows(case, starts, oracle=oracle)
    return rows


def trial_params(scene_path, *, cases: int) -> list[dict]:
    """Per case: the clinic configuration, the ideal one and each source off and alone; the
    ideal profile is the scene's own (``<name>-ideal.toml``) or else the shipped magnitudes
    (:data:`SHIPPED`); with no source to vary (a scene already at them), the clinic
    configuration alone."""
    from testbed.scene import load_scene
    from testbed.spec import SceneError

    clinic = load_scene(scene_path)
    ideal = ideal_scene_path(scene_path)
    if ideal and not _beside(ideal, scene_path):
        # a named scene's profile found by the file's name (a user's copy of experiment2
        # elsewhere): used when it has the scene's set-up, else the shipped magnitudes (a
        # review: a moved patient's copy was refused, exit 2, where one named otherwise ran)
        try:
            error_sources(clinic, load_scene(ideal))
        except SceneError:
            ideal = None
    ideal = ideal or SHIPPED
    sources = error_sources(clinic, ideal_profile(clinic, ideal))
    if not sources:
        ideal = ""
    params = [{"config": "clinic", "source": "", "ideal": ideal, "case": i}
              for i in range(cases)]
    if not ideal:
        return params
    for i in range(cases):
        params.append({"config": "ideal", "source": "", "ideal": ideal, "case": i})
        for s in sources:
            for cfg in ("off", "alone"):
                params.append({"config": cfg, "source": s, "ideal": ideal, "case": i})
    return params


def make_budget_trials(scene_path, seed: int, *, cases: int) -> list:
    """The study's trials (:func:`trial_params`): every configuration of case ``i``
    simulated from case ``i``'s seed (not the trial index's); a stored trial is reused only
    for the same scene and ideal profile (their every field and the files they name), as
    :func:`studies.runner.run_study_trials` keys its trials."""
    from studies.runner import Trial, fingerprint, scene_fingerprint
    from testbed.scene import load_scene
    from testbed.simulate import case_seed

    params = trial_params(scene_path, cases=cases)
    ideal = params[0]["ideal"]
    clinic = load_scene(scene_path)
    digest = fingerprint(texts=["ideal: the clinic's set-up, the profile's magnitudes",
                                scene_fingerprint(clinic),
                                scene_fingerprint(ideal_profile(clinic, ideal)) if ideal
                                else ""])
    return [Trial.from_seed_sequence(i, str(scene_path), case_seed(seed, p["case"]), p, digest)
            for i, p in enumerate(params)]


def check_scene(scene, path) -> None:
    """Refuse, before any work (``studies.run_study``), a scene that locates a pin."""
    from studies.common import refuse_fixed_pin

    refuse_fixed_pin(scene, path, "error-budget")


def run(ctx) -> pd.DataFrame:
    from studies.runner import run_context_trials

    trials = make_budget_trials(ctx.scene_path, int(ctx.seed),
                                cases=QUICK_CASES if ctx.quick else CASES)
    params = [t.params for t in trials]
    df = run_context_trials(ctx, trial, trials)
    pe = df[(df.metric == "pin_error")]
    if pe.empty:
        ctx.report("Pin errors (mm)", "No registration finished.")
        return df
    ctx.report("The method's verdict on these registrations", verdict_markdown(df))
    ideal = params[0]["ideal"]
    stem = Path(ctx.scene_path).stem
    if ideal:
        src = error_sources(ctx.scene, ideal_profile(ctx.scene, ideal))
        skipped = shipped_ideal_fields(ctx.scene)[1] if ideal == SHIPPED else {}
        what = (f"its ideal profile `{ideal}`" if ideal != SHIPPED else
                f"the shipped ideal magnitudes (no `{stem}-ideal.toml` with this scene's "
                f"set-up was found beside the scene file or among the named scenes: every "
                f"field in which `{SHIPPED_PAIR[1]}` differs from `{SHIPPED_PAIR[0]}` at "
                f"`{SHIPPED_PAIR[1]}`'s value, unless the scene's is smaller"
                + ("; left at the scene's value, as the scene refuses the ideal one: "
                   + "; ".join(f"{k} ({v})" for k, v in skipped.items()) if skipped else "")
                + ")")
        ctx.report("Error sources", f"The clinic profile `{ctx.scene_path}` against {what}, "
                   "field by field. The `ideal` and `alone` "
                   "configurations are the clinic scene with these fields changed: its femur, "
                   "registration options and workspace check stay the clinic scene's, "
                   "whatever the ideal profile sets there.\n\n" + markdown_table(pd.DataFrame(
                       [{"source": s, "field": f, "clinic": json.dumps(v[0]),
                         "ideal": json.dumps(v[1])}
                        for s, fields in src.items() for f, v in fields.items()])))
        changes = view_changes(df)
        t = source_table(pe, changes)
        # the cases that registered, not the cases planned (a review, h90: a case that failed
        # whole left the caveat for fewer cases silent)
        n_cases = int(pe["case"].nunique()) if "case" in pe else len({p["case"] for p in params})
        ctx.report("By source: mean pin error (mm), off and alone",
                   "`clinic`: every source at its clinic magnitude; `ideal`: every source at "
                   "its ideal magnitude. `off`: the clinic with this source at its ideal "
                   "magnitude; `alone`: the ideal configuration with only this source at its "
                   "clinic magnitude. `removed` = clinic - off, `added` = alone - ideal; "
                   "sorted by `added`. "
                   "Each source draws from a random stream of its own, so `off` and "
                   "`alone` differ from `clinic` and `ideal` by that source only."
                   + _negative_note(t, n_cases)
                   + _view_change_note(changes) + "\n\n"
                   + markdown_table(t.fillna({"views": ""}) if "views" in t else t, ".3f"))
        _tornado(ctx, t)
        from studies.table2 import set_up_note

        ctx.report("What would close the gap to the paper", set_up_note(ctx.scene)
                   + gap_markdown(t, cases=n_cases))
    else:
        ctx.report("By source", no_budget_reason(ctx.scene, ctx.scene_path)
                   + ": only the stage budget is run.")
    ctx.report("By stage: pin errors (mm) with truth substituted", stage_markdown(pe))
    lost = views_lost_markdown(df[df.metric != "failed"], by=("config", "source"))
    if lost:
        ctx.report("Views left out", lost)
    return df


def stage_markdown(pe: pd.DataFrame) -> str:
    """The stage budget: per oracle, the clinic configuration's pin errors and the share of
    the mean error that substituting the truth removes (a negative share said and read: a
    held-out review found it on four scenes without a word)."""
    stage = pe[pe.config == "clinic"].groupby("oracle")["value"].agg(
        ["mean", "median", "max"]).reset_index()
    base = stage.set_index("oracle")["mean"].get("none", float("nan"))
    stage["share of mean error removed"] = 1.0 - stage["mean"] / base
    worse = stage[stage["share of mean error removed"] < 0]["oracle"].tolist()
    note = ("\n\nA negative share (" + ", ".join(f"`{w}`" for w in worse) + ") means the "
            "truth made the error larger, over these cases (with few of them, possibly by "
            "chance): a true input is not necessarily the one the method does best with. "
            "The true X-ray contours (`studies.oracles.true_contours`), for one, are the "
            "femur's whole apparent contour, its inner curves and the parts under "
            "instruments included, where the estimated ones follow the outline the operator "
            "could see, and the CT surfaces they are matched with leave out the femoral head "
            "either way. The cause was not measured." if worse else "")
    return ("The cases of the scene as given (the `clinic` configuration). Mean, median "
            "and max over the pins, the starts and the cases; "
            "`none` is the realistic pipeline, `calibration+contours+surfaces` leaves only "
            "the registration's own error: the true contours are the true surface's "
            "apparent contours, so the data agree exactly at the true pose and its error is "
            "near 0 by construction whenever the loop converges there (it checks the "
            "registration finds the truth, not how far real data move it).\n\n"
            + markdown_table(stage, ".3f") + note)


def verdict_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per configuration, source and oracle: registrations, how many converged and how many
    the method's verdict accepted (the means of this report are over all of them)."""
    keys = ["config", "source", "oracle"]
    v = df[df.metric.isin(["converged", "accepted"])]
    if v.empty:
        return pd.DataFrame(columns=[*keys, "registrations", "converged", "accepted"])
    v = v.assign(oracle=v.oracle.fillna("none"), source=v.source.fillna(""))
    t = v.pivot_table(index=[*keys, "trial", "start"], columns="metric", values="value",
                      aggfunc="first").reset_index()
    out = t.groupby(keys).agg(registrations=("accepted", "size"),
                              converged=("converged", "sum"),
                              accepted=("accepted", "sum")).reset_index()
    return out.astype({"converged": int, "accepted": int})


def verdict_markdown(df: pd.DataFrame) -> str:
    """The verdict table with a warning when the means include refused poses (a review: a
    one-view scene's 'mean pin error' of 190 mm was of 25 refused poses, and the report
    said nothing of the verdict)."""
    from studies.common import markdown_table

    t = verdict_table(df)
    if t.empty:
        return "No registration reported a verdict."
    refused = int((t.registrations - t.accepted).sum())
    total = int(t.registrations.sum())
    head = (f"Every mean and median of this report is over all {total} registrations, "
            "accepted or not: the budget attributes the error of the pipeline as it runs. ")
    if not refused:
        return head + "All were accepted by the method's own verdict."
    head += (f"**{refused} of them were refused by the method's own verdict** (not "
             "converged, or converged to a pose it does not trust): where a configuration "
             "is mostly refused, its figures describe failures, not accuracy. The "
             "configurations with refusals:")
    return head + "\n\n" + markdown_table(t[t.accepted < t.registrations])


def view_changes(df: pd.DataFrame) -> dict:
    """(config, source) -> text naming the views whose use differs from the configuration
    it is compared with (``off`` with ``clinic``, ``alone`` with ``ideal``) in the same case,
    from the ``view_used`` rows: "-distal_ap (case 0)" lost there, "+..." used there only.

    A view lost changes a case's pin errors by more than most sources do, and the budget
    gave that change to the source (a held-out review: "scatter off" had distal_ap refused
    and was reported as -0.61 mm)."""
    u = df[df.metric == "view_used"]
    if u.empty or "config" not in u:
        return {}
    case = "case" if "case" in u else "trial"
    u = u.assign(source=u.source.fillna("").astype(str) if "source" in u else "")
    used = {(r.config, r.source, r[case], r.view): r.value > 0 for _, r in u.iterrows()}
    against = {"off": "clinic", "alone": "ideal"}
    out: dict = {}
    for (cfg, src, c, v), ok in sorted(used.items(), key=str):
        ref = used.get((against.get(cfg), "", c, v))
        if ref is None or ref == ok:
            continue
        out.setdefault((cfg, src), []).append(f"{'+' if ok else '-'}{v} (case {cell_text(c)})")
    return {k: ", ".join(v) for k, v in out.items()}


def source_table(pe: pd.DataFrame, changes: dict | None = None) -> pd.DataFrame:
    """Per source: the mean pin error off and alone, what switching it off removes and what
    it adds alone (mm); from the ``pin_error`` rows without oracle. ``changes``
    (:func:`view_changes`) adds a ``views`` column naming, per source, the views used
    differently from the configuration compared with; its figures are then not the
    source's alone."""
    pe = pe[pe.oracle == "none"]
    mean = pe.groupby(["config", "source"])["value"].mean()
    clinic = float(mean.get(("clinic", ""), np.nan))
    ideal = float(mean.get(("ideal", ""), np.nan))
    rows = []
    for s in sorted(set(pe.source) - {""}):
        off = float(mean.get(("off", s), np.nan))
        alone = float(mean.get(("alone", s), np.nan))
        rows.append({"source": s, "off": off, "alone": alone, "removed": clinic - off,
                     "added": alone - ideal})
        if changes:
            rows[-1]["views"] = "; ".join(f"{cfg}: {changes[cfg, s]}" for cfg in ("off", "alone")
                                          if (cfg, s) in changes)
    t = pd.DataFrame(rows)
    if len(t):
        # by what each adds alone: its removal from the clinic mixes in the other sources'
        # cancellations, negative for most sources over few cases (a review, h87: 13 of 16
        # on one case, the table sorted by it while its text said to read `added` first)
        t = t.sort_values("added", ascending=False, na_position="last")
    head = pd.DataFrame([{"source": "(clinic)", "off": clinic, "alone": np.nan,
                          "removed": np.nan, "added": np.nan},
                         {"source": "(ideal)", "off": np.nan, "alone": ideal,
                          "removed": np.nan, "added": np.nan}])
    return pd.concat([head, t], ignore_index=True)


def gap_table(t: pd.DataFrame, target_mm: float) -> pd.DataFrame:
    """Per source, how much larger its magnitude would have to be for the clinic's mean pin
    error to reach ``target_mm``, to first order.

    Assumptions, stated in the report: independent sources add in quadrature at the pins,
    and a source's own contribution ``a = sqrt(alone^2 - ideal^2)`` (mm) grows in
    proportion to its magnitude. The missing error is ``m = sqrt(target^2 - clinic^2)``;
    the source alone would have to contribute ``sqrt(a^2 + m^2)``, i.e. its magnitude times
    ``sqrt(a^2 + m^2) / a``. Sources that add nothing alone get no factor (NaN).
    """
    clinic = float(t.loc[t.source == "(clinic)", "off"].iloc[0])
    ideal = float(t.loc[t.source == "(ideal)", "alone"].iloc[0])
    missing = float(np.sqrt(max(target_mm**2 - clinic**2, 0.0)))
    rows = []
    for _, r in t[~t.source.str.startswith("(")].iterrows():
        a = float(np.sqrt(max(r["alone"] ** 2 - ideal**2, 0.0)))
        rows.append({"source": r["source"], "contribution_mm": a,
                     "factor": np.sqrt(a**2 + missing**2) / a if a > 1e-3 else np.nan})
    out = pd.DataFrame(rows)
    return out.sort_values("factor") if len(out) else out


def gap_markdown(t: pd.DataFrame, cases: int | None = None) -> str:
    """The gap to the Table II target and :func:`gap_table`'s factors; with ``cases``
    below :data:`CASES`, a caveat first (a review, h87: one case's factor of 3.33 was
    printed as the source's)."""
    from studies.table2 import TARGET_MEAN_MM

    clinic = float(t.loc[t.source == "(clinic)", "off"].iloc[0])
    lo = TARGET_MEAN_MM[0]
    if not np.isfinite(clinic):
        return "No clinic registration finished."
    if clinic >= lo:
        return (f"The clinic's mean pin error {clinic:.2f} mm reaches the Table II target "
                f"({lo}-{TARGET_MEAN_MM[1]} mm): no source has to change.")
    g = gap_table(t, lo)
    missing = float(np.sqrt(lo**2 - clinic**2))
    few = (f"**From {cases} case(s)**: each figure below is one draw of every source, and "
           "a source's `added` over so few cases is its draw as much as its magnitude; read "
           f"the factors from the study without `--quick` ({CASES} cases) or more.\n\n"
           if cases is not None and cases < CASES else "")
    return few + (f"The clinic's mean pin error {clinic:.2f} mm is below the Table II target's "
            f"{lo} mm: an independent error of {missing:.2f} mm (in quadrature) is missing. "
            "To first order (sources add in quadrature; a source's pin error grows in "
            "proportion to its magnitude), each source alone would have to be this many times "
            "its clinic magnitude to supply it; a factor far above the spread of the "
            "published figures (docs/error-model.md) says the gap lies elsewhere (an error "
            "source not modelled, or the paper's conditions).\n\n"
            + markdown_table(g, ".2f"))


def _negative_note(t: pd.DataFrame, cases: int) -> str:
    """A sentence on the sources whose removal made the mean error larger, if any."""
    neg = t[~t.source.str.startswith("(") & (t["removed"] < 0)]
    if neg.empty:
        return ""
    names = ", ".join(f"{r.source} ({r.removed:+.3f} mm)" for r in neg.itertuples())
    return (f" Switching off {len(neg)} source(s) made the mean pin error larger: {names}. "
            f"Errors of several sources cancel in part within a case, and over {cases} "
            f"case(s) that is not averaged out: read `added` first; ranking by `removed` "
            f"needs more cases.")


def _view_change_note(changes: dict) -> str:
    """A sentence on the sources whose configurations used other views than the ones they
    are compared with (:func:`view_changes`), if any."""
    if not changes:
        return ""
    names = sorted({s for _, s in changes})
    return (f" **{len(names)} source(s) changed which views were registered** ("
            + ", ".join(names) + "; column `views`: `-view` left out in the configuration "
            "and used in the one it is compared with, `+view` the reverse): their `removed` "
            "or `added` holds the effect of that view's loss as well as the source's, and "
            "is marked * in the chart; section 'Views left out' gives the reasons.")


def _tornado(ctx, t: pd.DataFrame) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = t[~t.source.str.startswith("(")].iloc[::-1]
    if t.empty:
        return
    fig, ax = plt.subplots(figsize=(7, 0.5 * len(t) + 1.5))
    y = np.arange(len(t))
    h = 0.38
    # both signed on one axis: > 0, the source accounts for that much of the error; < 0,
    # the error was larger without it (sources' errors cancel in part within a case).
    # Until 2026-11-27 the removal was drawn negated on the left, so a negative removal
    # showed as a bar on the right, read as an added error.
    ax.barh(y + h / 2, t["removed"], height=h, color="tab:blue",
            label="clinic - off (removed when switched off)")
    ax.barh(y - h / 2, t["added"], height=h, color="tab:red",
            label="alone - ideal (added when on alone)")
    ax.axvline(0, color="k", lw=0.8)
    changed = t["views"].fillna("").astype(bool) if "views" in t else np.zeros(len(t), bool)
    ax.set_yticks(y, [f"{n} *" if c else str(n) for n, c in zip(t["source"], changed)])
    ax.set_xlabel("mean pin error the source accounts for (mm; < 0: larger without it)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(ctx.figure("error_budget_tornado.png", "Each error source's share of the mean "
                           "pin error, two ways: the clinic less the clinic with the source "
                           "off (blue), and the ideal profile with the source alone less "
                           "the ideal (red); a bar left of 0 means the mean pin error was "
                           "larger without the source; a source marked * changed which "
                           "views were registered, and its bars hold that view's effect "
                           "too"), dpi=110)
    plt.close(fig)
