"""Capture range of the registration: success rate against the initial error, per pose method.

The standard methodology for 2-D/3-D registration (van de Kraats et al., IEEE TMI 2005):
starts are drawn so that their initial mTRE (mean distance between the start's and the true
positions of the targets, here the three pins) covers 0-30 mm in bins; every start is
registered and called a success when its final mTRE is below 2 mm; the *capture range* is
the largest initial mTRE up to which at least 95 % of the starts succeed (the upper edge of
the last bin of the unbroken run of bins from 0 mm at >= 95 %).

One trial = one random case and all its starts for every method, so the slow simulation is
done once per case:

- the case: a random femur (left or right, every shape parameter drawn uniformly over its
  documented range, :func:`random_femur`), the scene's views re-aimed at its anatomy with
  their C-arm angles (orbital, angular) jittered by up to ``JITTER_DEG``, and its own image
  noise and user clicks; the CT
  surfaces are reconstructed and the X-ray contours traced by reglib as in the end-to-end
  job (:func:`studies.end_to_end.prepare_case` with ``sweeps=False``);
- **oracle calibration**: the X-ray paths of the contour pixels are the true pixel -> ray
  map of each C-arm instead of a two-plane calibration from a simulated sweep. The sweep
  simulation dominates a case's time (about 15 s per view) and its error (validation
  distances about 0.1 mm) is studied by the ``calibration`` study; surfaces and contours stay
  estimated;
- the starts: in each bin, ``starts_per_bin`` target mTREs drawn uniformly; for each, a
  random 6-D perturbation direction (rotation about the pins' centroid, in radians times the
  pins' mean distance to it, and translation in mm) scaled by bisection so that the start's
  mTRE at the pins equals the target;
- every start is registered by each pose method of :data:`METHODS`.

Size: by default 6 cases x 10 bins x 3 starts (180 starts for ``default``, 60 for each
other method); it ran in 20 s on 2 workers of a quiet 2-core Zen 5 EPYC (2026-11-28,
later: a case 1.9 s of simulation and estimation and 3.1 s of registrations), in 2 min
34 s on a 2-core Xeon while two other jobs shared the cores (the same day: a case 8.3 s
and 29 s), and in 5 min 18 s while the baselines still took the estimate's restarts.
``--quick``: 2 cases, 3 bins of 10 mm, 1 start each (under a minute).

Rows (long format, one start each, columns ``method``, ``bin``, ``start``): ``start_mtre``
(mm), ``final_mtre`` (mm), ``success`` (0/1), ``converged`` (0/1), ``time`` (s), and per trial
``sim_time`` (s, the case's simulation and estimation before registration).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from studies.common import check_view_regions, plain_log_ticks, region_centres

TITLE = "capture range: registration success rate vs initial mTRE (0-30 mm), per pose method"
#: the issue's conditions: the ideal profile's magnitudes (the method's capture range, not
#: the clinic's noise); any operating-room scene can be given with --scene
DEFAULT_SCENE = "experiment2-ideal"

SUCCESS_MM = 2.0
CAPTURE_RATE = 0.95
BIN_EDGES_MM = tuple(float(x) for x in range(0, 33, 3))   # 0, 3, ..., 30
JITTER_DEG = 3.0
#: method -> keyword arguments of studies.end_to_end.register_case. "default" is reglib's
#: default, as a user gets it (reglib.estimate's coarse-fine strategy: the point-to-path
#: residual to come near, then the across-contour residual to converge; and its restarts,
#: turned starts tried when a result is refused); the others run the loop once
#: ("single", no restarts): "robust" and "linear" with the across-contour residual and the
#: loop's own solver, "robust-line" and "ransac" with the paper's point-to-path residual
#: and reglib.pose's robust (Tukey) and RANSAC solvers (capped at 25 iterations: with 50 a
#: start costs 12 s and the pins still move by hundredths of a mm). With the estimate's 12
#: restarts, which ran for every start of these (their verdicts refuse them all), a
#: "linear", "robust-line" or "ransac" start cost 10-15x more and its success was that of
#: the best of 13 starts, not the capture range of one registration: from 26-29 mm,
#: "robust-line" and "ransac" reached 0.6-1.7 mm with restarts and 2.1-50 mm without.
_ONCE = {"strategy": "single", "restarts": 0}
METHODS = {
    "default": {},
    "robust": {**_ONCE, "method": "robust", "residual": "normal"},
    "linear": {**_ONCE, "method": "linear", "residual": "normal"},
    "robust-line": {**_ONCE, "method": "robust", "residual": "line", "max_iterations": 25},
    "ransac": {**_ONCE, "method": "ransac", "residual": "line", "max_iterations": 25},
}
#: the default pipeline's method: it registers every start; the others the first
#: ``others_per_bin`` starts of each bin (fewer rows of the baselines: the primary is what
#: the study is for)
PRIMARY = "default"
#: the method's own quality figures written per start (reglib.pipeline.match_quality), to
#: study the verdict against the truth
QUALITY_ROWS = (("median_residual_mm", "mm"), ("p90_residual_mm", "mm"), ("near_fraction", ""),
                ("inlier_fraction", ""), ("max_view_median_mm", "mm"),
                ("min_view_inlier_fraction", ""), ("iterations", ""),
                ("pose_sensitivity", ""), ("weak_motion_mm", "mm"),
                ("worst_view_fit", ""), ("restarts", ""))
DEFAULT_SIZE = {"cases": 6, "starts_per_bin": 3, "others_per_bin": 1}
QUICK_SIZE = {"cases": 2, "starts_per_bin": 1, "others_per_bin": 1}
QUICK_BINS_MM = (0.0, 10.0, 20.0, 30.0)


# --------------------------------------------------------------------------- the case
#: the femur's shape parameters, each drawn uniformly over its whole documented range
#: (the bounds of testbed.phantom.PhantomSpec)
SHAPE_FIELDS = ("length_mm", "head_radius_mm", "neck_length_mm", "neck_radius_mm",
                "neck_shaft_angle_deg", "anteversion_deg", "shaft_diameter_mm",
                "cortical_thickness_mm", "end_cortex_mm", "shaft_bow_mm", "condyle_width_mm",
                "notch_width_mm", "condyle_depth_mm", "distal_joint_angle_deg")
#: how many femurs to draw at most before giving up on one case (implausible combinations,
#: e.g. a neck wider than the head, are drawn again)
MAX_SHAPE_DRAWS = 50


def _bounds(field: str) -> tuple[float, float]:
    from testbed.phantom import field_bounds

    lo, hi = field_bounds(field)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"PhantomSpec.{field} has no documented range")
    return lo, hi


def random_femur(base, rng):
    """A ``PhantomSpec`` of ``base`` with a random side and every shape parameter drawn over
    its documented range, rejecting implausible femurs (the phantom cannot be built, or the
    thigh does not enclose the bone). Returns ``(spec, phantom)``."""
    from testbed.phantom import MAX_CORTEX_SHARE, make_phantom

    last = None
    for _ in range(MAX_SHAPE_DRAWS):
        upd = {f: float(rng.uniform(*_bounds(f))) for f in SHAPE_FIELDS}
        upd["side"] = str(rng.choice(["left", "right"]))
        upd["shape_variation"] = 0.0
        if upd["neck_radius_mm"] >= 0.9 * upd["head_radius_mm"] \
                or upd["notch_width_mm"] >= 0.45 * upd["condyle_width_mm"] \
                or upd["cortical_thickness_mm"] >= MAX_CORTEX_SHARE * upd["shaft_diameter_mm"]:
            continue
        # the thigh and knee envelopes grow with the bone, as they do in patients
        upd["thigh_radius_mm"] = max(base.thigh_radius_mm, upd["shaft_diameter_mm"] + 45.0)
        upd["knee_radius_mm"] = max(base.knee_radius_mm,
                                    0.5 * upd["condyle_width_mm"] + 25.0,
                                    0.5 * upd["condyle_depth_mm"] + 25.0)
        try:
            spec = base.model_copy(update=upd)
            spec = type(base).model_validate(spec.model_dump())
            # make_phantom refuses a femur its thigh does not enclose (every vertex tested)
            return spec, make_phantom(spec)
        except (ValueError, RuntimeError) as exc:
            last = exc
    raise ValueError(f"no plausible femur in {MAX_SHAPE_DRAWS} draws (last: {last})")


def case_scene(scene, rng, *, jitter_deg: float = JITTER_DEG):
    """The scene of one random case: a random femur, views re-aimed at its anatomy with
    jittered C-arm angles.

    Parameters
    ----------
    scene : testbed.scene.Scene
        An operating-room scene with views.
    rng : numpy.random.Generator
        Draws the femur (side and every shape parameter over its documented range,
        :func:`random_femur`) and the angle offsets.
    jitter_deg : float
        Offsets of each view's ``orbital_deg`` and ``angular_deg``, uniform in
        ``[-jitter_deg, jitter_deg]`` (deg).

    Each view keeps its offset from the centre of its region's anatomy (head, neck and
    trochanters; the condyles) in the scene's femur: the radiographer centres the C-arm on
    the anatomy of this femur as on the scene's; on the other side the oblique angles
    (``angular_deg``, about the femur's long axis) are mirrored.
    """
    from testbed.phantom import make_phantom

    ct2robot = scene.patient.ct2robot()
    old = region_centres(make_phantom(scene.phantom))
    check_view_regions(scene, {k: ct2robot.apply(c) for k, c in old.items()})
    spec, ph = random_femur(scene.phantom, rng)
    new = region_centres(ph)
    views = []
    # the other side is the mirror image across the femur's long axis (robot y): the
    # obliques turn the other way about it
    mirror = -1.0 if spec.side != scene.phantom.side else 1.0
    for v in scene.views:
        d_orb, d_ang = rng.uniform(-jitter_deg, jitter_deg, size=2)
        update = {"orbital_deg": float(np.clip(v.orbital_deg + d_orb, -180.0, 180.0)),
                  "angular_deg": float(np.clip(mirror * v.angular_deg + d_ang, -180.0, 180.0))}
        region = getattr(v, "region", "")
        if region in new:
            shift = ct2robot.apply(new[region]) - ct2robot.apply(old[region])
            update["isocenter_mm"] = tuple(float(x) for x in np.asarray(v.isocenter_mm) + shift)
        views.append(v.model_copy(update=update))
    # no sweep is simulated here (oracle calibration), and the views are re-aimed at each
    # femur: the workspace of these random cases is not checked (the report says so)
    workspace = scene.workspace.model_copy(update={"check": False})
    return scene.model_copy(update={"phantom": spec, "views": tuple(views),
                                    "workspace": workspace})


# --------------------------------------------------------------------------- the starts
# --------------------------------------------------------------------------- one trial
def trial(tr) -> list[dict]:
    """One random case, and every start of every bin registered by every method."""
    from studies.end_to_end import prepare_case, register_case
    from studies.scoring import PIN_NAMES, mtre, start_at_mtre
    from testbed.scene import load_scene

    p = tr.params
    edges = np.asarray(p["bins"].split(","), dtype=float) if isinstance(p["bins"], str) \
        else np.asarray(BIN_EDGES_MM)
    methods = p["methods"].split(",")
    rng = tr.rng()
    scene_rng, sim_ss, start_rng, solver_rng = rng.spawn(4)
    t0 = time.perf_counter()
    scene = case_scene(load_scene(tr.scene), scene_rng, jitter_deg=float(p["jitter_deg"]))
    case = prepare_case(scene, int(sim_ss.integers(0, 2**63 - 1)), sweeps=False)
    sim_time = time.perf_counter() - t0
    pins = np.array([case.pins_ct[k] for k in PIN_NAMES])
    truth = case.ct2robot
    rows = [{"metric": "sim_time", "value": sim_time, "unit": "s"}]
    k = 0
    for b in range(len(edges) - 1):
        for j in range(int(p["starts_per_bin"])):
            target = float(start_rng.uniform(edges[b], edges[b + 1]))
            start = start_at_mtre(truth, pins, target, start_rng)
            m0 = mtre(start, truth, pins)
            for method in methods:
                if method != PRIMARY and j >= int(p["others_per_bin"]):
                    continue
                opts = dict(METHODS[method])
                if method == "ransac":  # its sampling: seeded per start (register has no rng)
                    opts["solver_options"] = {"rng": np.random.default_rng(
                        solver_rng.integers(0, 2**63 - 1))}
                t1 = time.perf_counter()
                est, _ = register_case(case, start, **opts)
                dt = time.perf_counter() - t1
                m1 = mtre(est.ct2robot, truth, pins)
                base = {"method": method, "bin": b, "start": k}
                rows += [
                    {**base, "metric": "start_mtre", "value": m0, "unit": "mm"},
                    {**base, "metric": "final_mtre", "value": m1, "unit": "mm"},
                    {**base, "metric": "success", "value": float(m1 < SUCCESS_MM), "unit": ""},
                    {**base, "metric": "converged", "value": float(est.converged), "unit": ""},
                    {**base, "metric": "accepted", "value": float(est.accepted), "unit": ""},
                    *({**base, "metric": k, "value": float(est.quality[k]), "unit": u}
                      for k, u in QUALITY_ROWS if k in est.quality),
                    {**base, "metric": "time", "value": dt, "unit": "s"},
                ]
            k += 1
    return rows


def trial_params(*, cases: int, starts_per_bin: int, others_per_bin: int | None = None,
                 bins=BIN_EDGES_MM, methods=None, jitter_deg: float = JITTER_DEG) -> list[dict]:
    """The trials' parameters: one per case (the bins and methods as comma-joined strings).

    ``starts_per_bin`` starts per bin and case are registered by :data:`PRIMARY`, the first
    ``others_per_bin`` (default: all) of them by the other methods too."""
    others_per_bin = starts_per_bin if others_per_bin is None else others_per_bin
    methods = list(METHODS) if methods is None else list(methods)
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        raise ValueError(f"methods: unknown {unknown}; expected some of {list(METHODS)}")
    if cases < 1 or starts_per_bin < 1:
        raise ValueError(f"cases and starts_per_bin must be >= 1, got {cases}, {starts_per_bin}")
    b = np.asarray(bins, dtype=float)
    if b.ndim != 1 or len(b) < 2 or np.any(np.diff(b) <= 0) or b[0] < 0:
        raise ValueError(f"bins: expected increasing edges >= 0 mm, got {list(bins)}")
    return [{"case": i, "starts_per_bin": int(starts_per_bin),
             "others_per_bin": int(min(others_per_bin, starts_per_bin)),
             "bins": ",".join(f"{x:g}" for x in b), "methods": ",".join(methods),
             "jitter_deg": float(jitter_deg)} for i in range(cases)]


# --------------------------------------------------------------------------- summary
def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Per method and bin: starts, success rate, final mTRE median / 90th percentile, time."""
    d = df[df.metric.isin(["start_mtre", "final_mtre", "success", "time"])]
    wide = d.pivot_table(index=["trial", "method", "bin", "start"], columns="metric",
                         values="value").reset_index()
    g = wide.groupby(["method", "bin"])
    out = pd.DataFrame({
        "starts": g.size(),
        "start_mtre_min": g["start_mtre"].min(),
        "start_mtre_max": g["start_mtre"].max(),
        "success_rate": g["success"].mean(),
        "final_mtre_median": g["final_mtre"].median(),
        "final_mtre_p90": g["final_mtre"].quantile(0.9),
        "time_median": g["time"].median(),
    }).reset_index()
    out["bin"] = out["bin"].astype(int)
    return out


def capture_range(s: pd.DataFrame, edges, *, rate: float = CAPTURE_RATE) -> dict:
    """Method -> capture range (mm): over the run of bins from the first in which every bin
    has a success rate >= ``rate``, the largest initial mTRE started from (0 if the first bin
    fails). Not the last bin's upper edge: with few starts per bin that claimed up to 8 mm
    more than any start tried (a review: 30 mm reported, 21.7 mm the farthest start)."""
    out = {}
    for method, d in s.groupby("method"):
        d = d.set_index("bin")
        cr = 0.0
        for b in range(len(edges) - 1):
            if b not in d.index or d.loc[b, "success_rate"] < rate:
                break
            cr = max(cr, float(d.loc[b, "start_mtre_max"]))
        out[method] = cr
    return out


def range_lines(s: pd.DataFrame, edges, cr: dict, *, rate: float = CAPTURE_RATE) -> list[str]:
    """The report's line per method of :func:`capture_range`'s ``cr``: a range whose every
    bin passed is censored by the farthest start tried, not found, and says so (a review,
    h87: "30.0 mm" read as measured)."""
    n_bins = len(edges) - 1
    whole = {m: bool((d.set_index("bin").reindex(range(n_bins))["success_rate"]
                      >= rate).all()) for m, d in s.groupby("method")}
    return [f"- {m}: **at least {cr[m]:.1f} mm** (every bin passed: the farthest start "
            "tried; the range may reach further)" if whole.get(m) else
            f"- {m}: **{cr[m]:.1f} mm**" for m in cr]


def check_scene(scene, path) -> None:
    """ValueError naming the scene file and field, before any trial, for a scene this study
    cannot use: each of its cases draws a procedural femur (a ``[phantom] mesh_path`` femur
    failed every trial with "no plausible femur in 50 draws"), starts free of any located
    pin (a ``[registration] fixed_pin`` was ignored without a word: capture range 0 mm), and
    re-aims each view at its region's anatomy (a view labelled with the other region failed
    every trial, its message naming no file)."""
    from studies.common import refuse_fixed_pin
    from testbed.spec import SceneError

    if scene.phantom.mesh_path is not None:
        raise ValueError(f"{path}: [phantom] mesh_path: capture-range draws a procedural femur "
                         "of random shape per case and cannot use a mesh; give a scene with "
                         "the procedural femur (e.g. experiment2)")
    refuse_fixed_pin(scene, path, "capture-range")
    try:
        check_view_regions(scene)
    except SceneError as exc:
        raise ValueError(f"{path}: {exc}") from None


def run(ctx) -> pd.DataFrame:
    from studies.common import markdown_table, nothing_finished
    from studies.runner import run_study_trials

    size = QUICK_SIZE if ctx.quick else DEFAULT_SIZE
    bins = QUICK_BINS_MM if ctx.quick else BIN_EDGES_MM
    params = trial_params(bins=bins, **size)
    df = run_study_trials(ctx, trial, params)
    if nothing_finished(ctx, df, "Capture range"):
        return df
    failures = df.attrs.get("failures", {})
    ok = df[df.metric != "failed"]
    s = summary(ok)
    edges = np.asarray(bins, dtype=float)
    s.insert(2, "initial_mtre_bin", [f"{edges[b]:g}-{edges[b + 1]:g}" for b in s["bin"]])
    cr = capture_range(s, edges)
    sim = ok[ok.metric == "sim_time"]["value"]
    reg = ok[ok.metric == "time"]["value"]
    lines = range_lines(s, edges, cr)
    ctx.report("Capture range", "\n".join([
        f"Largest initial mTRE (at the three pins) up to which >= {CAPTURE_RATE:.0%} of the "
        f"starts end with a final mTRE < {SUCCESS_MM:g} mm, per pose method "
        "(published capture ranges for 2-D/3-D registration: 4-11 mm):", "", *lines, "",
        f"Cases: {ok.trial.nunique()} random femur(s)"
        + (f" of {size['cases']}, the others failed (see 'Failed trials')"
           if ok.trial.nunique() < size["cases"] else "")
        + "; left or right, every shape parameter uniform "
        "over its documented range, views re-aimed at each femur's anatomy, C-arm angles "
        f"jittered by up to {JITTER_DEG:g} deg, "
        f"{size['starts_per_bin']} start(s) per bin and case for {PRIMARY} (reglib's "
        "estimate as a user gets it, with its restarts when a result is refused), "
        f"{size['others_per_bin']} for the other methods (each loop run once from the "
        f"start, no restarts); {len(failures)} failed trial(s)."
        " Calibration: **oracle** (the true pixel -> ray map of each C-arm; no sweep is "
        "simulated, and the workspace of these re-aimed random views is not checked), "
        "surfaces and X-ray contours estimated by reglib. With fewer than 20 "
        "starts in a bin, >= 95 % means every start of the bin: one failure ends the range.",
        f"Time per case: simulation and estimation {sim.median():.1f} s (median); "
        f"registration {reg.median():.2f} s per start and method (median), "
        f"{reg.sum() / max(len(sim), 1):.1f} s per case in all."]))
    tab = s.drop(columns=["bin"]).rename(columns={
        "initial_mtre_bin": "initial mTRE (mm)", "start_mtre_min": "min start (mm)",
        "start_mtre_max": "max start (mm)", "success_rate": "success rate",
        "final_mtre_median": "final mTRE median (mm)", "final_mtre_p90": "final mTRE p90 (mm)",
        "time_median": "time median (s)"})
    ctx.report("Success rate per bin", markdown_table(tab, ".3g"))
    if failures:
        ctx.report("Failed trials", "\n".join(f"- trial {k}: {v}" for k, v in failures.items()))
    flags = flag_scores(ok)
    ctx.report("The method's own verdict against the truth", markdown_table(flags, ".3f") + (
        f"\n\nPer method: `accepted` (the method's verdict, computed without the truth) "
        f"against success (final mTRE < {SUCCESS_MM:g} mm). Precision: the share of accepted "
        "results that are right; recall: the share of right results that were accepted. A "
        "blank precision means the method accepted no start, a blank recall that no start "
        "succeeded (a ratio of none)."))
    _figures(ctx, ok, s, edges)
    rows = [{"trial": -1, "metric": "capture_range", "value": cr[m], "unit": "mm", "method": m}
            for m in cr]
    for r in flags.itertuples(index=False):
        rows += [{"trial": -1, "metric": "flag_precision", "value": r.precision, "unit": "",
                  "method": r.method},
                 {"trial": -1, "metric": "flag_recall", "value": r.recall, "unit": "",
                  "method": r.method}]
    return pd.concat([df, pd.DataFrame(rows)], ignore_index=True)


def flag_scores(df: pd.DataFrame) -> pd.DataFrame:
    """Per method: precision and recall of ``accepted`` against success (final mTRE below
    :data:`SUCCESS_MM`), and the counts behind them."""
    w = df[df.metric.isin(["accepted", "final_mtre"])].pivot_table(
        index=["trial", "method", "start"], columns="metric", values="value").reset_index()
    out = []
    for m, d in w.groupby("method"):
        ok = d["final_mtre"] < SUCCESS_MM
        acc = d["accepted"] > 0.5
        tp, fp, fn = int((acc & ok).sum()), int((acc & ~ok).sum()), int((~acc & ok).sum())
        out.append({"method": m, "starts": len(d), "accepted": int(acc.sum()),
                    "successes": int(ok.sum()), "false accepts": fp, "false rejects": fn,
                    "precision": tp / (tp + fp) if tp + fp else float("nan"),
                    "recall": tp / (tp + fn) if tp + fn else float("nan")})
    return pd.DataFrame(out)


def _method_styles(methods) -> dict:
    """method -> (marker, line style, sideways rank about 0): distinct for up to 5 methods
    and repeating beyond."""
    markers, dashes = "osD^v", ("-", "--", "-.", ":", (0, (5, 1, 1, 1)))
    n = len(methods)
    return {m: (markers[i % 5], dashes[i % 5], i - (n - 1) / 2) for i, m in enumerate(methods)}


def _figures(ctx, df, s, edges):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = 0.5 * (edges[:-1] + edges[1:])
    # methods with the same rates drew one line over another (a review, h87: "default" lay
    # hidden under "robust"): each its own marker and dash, nudged sideways by a tenth of
    # a bin, the legend beside the axes
    style = _method_styles(sorted(s["method"].unique()))
    step = float(np.min(np.diff(edges))) if len(edges) > 1 else 1.0
    fig, ax = plt.subplots(figsize=(7.2, 4))
    for method, d in s.groupby("method"):
        marker, dash, k = style[method]
        ax.plot(centres[d["bin"].to_numpy(int)] + 0.1 * step * k, 100 * d["success_rate"],
                marker=marker, ls=dash, label=method, ms=5, alpha=0.85)
    ax.axhline(100 * CAPTURE_RATE, color="grey", ls="--", lw=1)
    ax.set_xlabel("initial mTRE at the pins (mm)")
    ax.set_ylabel(f"success rate (final mTRE < {SUCCESS_MM:g} mm), %")
    ax.set_ylim(-3, 103)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(ctx.figure("capture_success.png", "Success rate against the initial mTRE, "
                           "per pose method (dashed: 95 %)"), dpi=110)
    plt.close(fig)

    wide = df[df.metric.isin(["start_mtre", "final_mtre"])].pivot_table(
        index=["trial", "method", "start"], columns="metric", values="value").reset_index()
    fig, ax = plt.subplots(figsize=(7.2, 4))
    for method, d in wide.groupby("method"):
        ax.plot(d["start_mtre"], np.maximum(d["final_mtre"], 1e-3), ls="none",
                marker=style.get(method, ("o", "-", 0))[0], ms=4, label=method, alpha=0.6)
    ax.axhline(SUCCESS_MM, color="grey", ls="--", lw=1)
    ax.set_yscale("log")
    plain_log_ticks(ax)
    ax.set_xlabel("initial mTRE at the pins (mm)")
    ax.set_ylabel("final mTRE at the pins (mm)")
    # beside the axes: inside, it covered points (a review, h87)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    fig.savefig(ctx.figure("capture_final_error.png", "Final against initial mTRE, one point "
                           "per start and method (dashed: the 2 mm success threshold)"),
                dpi=110)
    plt.close(fig)
