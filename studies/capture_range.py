"""Capture range of the registration: success rate against the initial error, per pose method.

The standard methodology for 2-D/3-D registration (van de Kraats et al., IEEE TMI 2005):
starts are drawn so that their initial mTRE (mean distance between the start's and the true
positions of the targets, here the three pins) covers 0-30 mm in bins; every start is
registered and called a success when its final mTRE is below 2 mm; the *capture range* is
the largest initial mTRE up to which at least 95 % of the starts succeed (the upper edge of
the last bin of the unbroken run of bins from 0 mm at >= 95 %).

One trial = one random case and all its starts for every method, so the slow simulation is
done once per case:

- the case: a random femur (``[phantom] shape_variation``, default 1.0 population standard
  deviation, its own ``shape_seed``), the scene's views with their C-arm angles (orbital,
  angular) jittered by up to ``JITTER_DEG``, and its own image noise and user clicks; the CT
  surfaces are reconstructed and the X-ray contours traced by reglib as in the end-to-end
  job (:mod:`studies.end_to_end`);
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

Size: by default 6 cases x 10 bins x 3 starts (180 starts for ``robust``, 60 for each other
method); it ran in 5 min 18 s on 2 workers on this 2-core machine when quiet, and about
10 min (with three methods) while other jobs shared the cores. ``--quick``: 2 cases, 3 bins
of 10 mm, 1 start each (under a minute).

Rows (long format, one start each, columns ``method``, ``bin``, ``start``): ``start_mtre``
(mm), ``final_mtre`` (mm), ``success`` (0/1), ``converged`` (0/1), ``time`` (s), and per trial
``sim_time`` (s, the case's simulation and estimation before registration).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from reglib.geometry import RigidTransform

TITLE = "capture range: registration success rate vs initial mTRE (0-30 mm), per pose method"
DEFAULT_SCENE = "experiment2"

SUCCESS_MM = 2.0
CAPTURE_RATE = 0.95
BIN_EDGES_MM = tuple(float(x) for x in range(0, 33, 3))   # 0, 3, ..., 30
JITTER_DEG = 3.0
SHAPE_VARIATION = 1.0
#: pose method -> keyword arguments of reglib.register.register. "robust" and "linear" use
#: the loop's own solver on the across-contour residual (register's default); "robust-line"
#: and "ransac" the paper's point-to-path residual (the scenes' [registration] default) with
#: reglib.pose's robust (Tukey) and RANSAC solvers. The line-residual methods are capped at
#: 25 iterations (about 0.25 s each on a 4-view case; with 50 a start costs 12 s and the pins
#: still move by hundredths of a mm).
METHODS = {
    "robust": {"method": "robust", "residual": "normal"},
    "linear": {"method": "linear", "residual": "normal"},
    "robust-line": {"method": "robust", "residual": "line", "max_iterations": 25},
    "ransac": {"method": "ransac", "residual": "line", "max_iterations": 25},
}
#: the default pipeline's method: it registers every start; the others the first
#: ``others_per_bin`` starts of each bin (they cost 5-10x more per start)
PRIMARY = "robust"
DEFAULT_SIZE = {"cases": 6, "starts_per_bin": 3, "others_per_bin": 1}
QUICK_SIZE = {"cases": 2, "starts_per_bin": 1, "others_per_bin": 1}
QUICK_BINS_MM = (0.0, 10.0, 20.0, 30.0)


# --------------------------------------------------------------------------- the case
def case_scene(scene, rng, *, jitter_deg: float = JITTER_DEG):
    """The scene of one random case: its own femur shape and jittered C-arm angles.

    Parameters
    ----------
    scene : testbed.scene.Scene
        An operating-room scene with views.
    rng : numpy.random.Generator
        Draws the femur's ``shape_seed`` and the angle offsets.
    jitter_deg : float
        Offsets of each view's ``orbital_deg`` and ``angular_deg``, uniform in
        ``[-jitter_deg, jitter_deg]`` (deg).
    """
    variation = scene.phantom.shape_variation or SHAPE_VARIATION
    phantom = scene.phantom.model_copy(update={
        "shape_variation": variation, "shape_seed": int(rng.integers(0, 2**31 - 1))})
    views = []
    for v in scene.views:
        d_orb, d_ang = rng.uniform(-jitter_deg, jitter_deg, size=2)
        views.append(v.model_copy(update={
            "orbital_deg": float(np.clip(v.orbital_deg + d_orb, -180.0, 180.0)),
            "angular_deg": float(np.clip(v.angular_deg + d_ang, -180.0, 180.0))}))
    return scene.model_copy(update={"phantom": phantom, "views": tuple(views)})


def simulate_without_sweeps(scene, seed, *, n_clicks: int = 8, click_noise_px: float = 1.0):
    """A :class:`studies.end_to_end.CaseData` like ``simulate_case`` but with no calibration
    sweep (``calibration`` is None in every view: use ``oracle=("calibration",)``).

    World, CT, reconstructed surfaces, X-ray frames and snake contours are simulated and
    estimated as in :func:`studies.end_to_end.simulate_case`.
    """
    from studies.end_to_end import CaseData, ViewData, estimate_surfaces, snake_contours
    from testbed.ct import scan
    from testbed.fluoroscope import make_carm, render
    from testbed.world import build_world

    if scene.scene.kind != "operating_room" or not scene.views:
        raise ValueError(f"scene {scene.scene.name!r}: the capture-range study needs an "
                         "operating_room scene with [[views]]")
    world_ss, ct_ss, click_ss, xray_ss = np.random.SeedSequence(seed).spawn(4)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    world = build_world(scene, np.random.default_rng(world_ss))
    ct = scan(world.phantom, scene.ct, np.random.default_rng(ct_ss))
    timings["world+ct"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    click_rng = np.random.default_rng(click_ss)
    surfaces, true_surfaces = estimate_surfaces(world, ct, click_rng)
    timings["surfaces"] = time.perf_counter() - t0
    views = []
    xray_rngs = np.random.default_rng(xray_ss).spawn(len(scene.views))
    for i, vspec in enumerate(scene.views):
        t0 = time.perf_counter()
        carm = make_carm(scene.fluoroscope, vspec, view_index=i)
        frame = render(carm, world.bodies, fluoro=scene.fluoroscope, rng=xray_rngs[i])
        timings["xray"] = timings.get("xray", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        xy, ext = snake_contours(frame, click_rng, n_clicks=n_clicks,
                                 click_noise_px=click_noise_px)
        timings["contours"] = timings.get("contours", 0.0) + time.perf_counter() - t0
        views.append(ViewData(name=vspec.name, region=vspec.region, carm=carm,
                              calibration=None, contour_xy=xy, contour_external=ext,
                              true_contour_xy=np.zeros((0, 2)), true_external=np.zeros(0, bool),
                              frame=frame))
    return CaseData(scene, seed, world, surfaces, true_surfaces, views, timings)


# --------------------------------------------------------------------------- the starts
def mtre(pose: RigidTransform, truth: RigidTransform, targets_ct) -> float:
    """Mean distance (mm) between the targets (N, 3) ct mm mapped by ``pose`` and ``truth``."""
    t = np.asarray(targets_ct, dtype=np.float64)
    return float(np.mean(np.linalg.norm(pose.apply(t) - truth.apply(t), axis=1)))


def start_at_mtre(truth: RigidTransform, targets_ct, target_mm: float, rng,
                  *, tol_mm: float = 1e-3) -> RigidTransform:
    """A start ``ct2robot`` whose mTRE at ``targets_ct`` (N, 3) ct mm is ``target_mm``.

    A random direction in the 6-D space (rotation vector about the targets' centroid, in rad
    times their mean distance to it, i.e. mm at the targets; translation in mm), uniform on
    the sphere, is scaled by bisection until the mTRE matches within ``tol_mm``.
    """
    if not np.isfinite(target_mm) or target_mm < 0:
        raise ValueError(f"target_mm: expected a finite mTRE >= 0 mm, got {target_mm}")
    rng = np.random.default_rng(rng)
    t = np.asarray(targets_ct, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) < 1:
        raise ValueError(f"targets_ct: expected an (N, 3) array of points, got {t.shape}")
    centre = truth.apply(t.mean(axis=0))
    radius = max(float(np.mean(np.linalg.norm(t - t.mean(axis=0), axis=1))), 1.0)
    u = rng.normal(size=6)
    u /= np.linalg.norm(u)

    def pose(s):
        rot = RigidTransform.from_rotvec(s * u[:3] / radius)
        about = RigidTransform(rot.R, centre - rot.R @ centre + s * u[3:])
        return about @ truth

    if target_mm == 0:
        return truth
    lo, hi = 0.0, target_mm
    while mtre(pose(hi), truth, t) < target_mm:
        hi *= 2.0
        if hi > 1e4:
            raise ValueError(f"target_mm = {target_mm}: cannot reach that mTRE")
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if mtre(pose(mid), truth, t) < target_mm:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-9 or abs(mtre(pose(mid), truth, t) - target_mm) < tol_mm:
            break
    return pose(0.5 * (lo + hi))


# --------------------------------------------------------------------------- one trial
def trial(tr) -> list[dict]:
    """One random case, and every start of every bin registered by every method."""
    from reglib.register import register
    from studies.end_to_end import PIN_NAMES, reglib_inputs
    from testbed.scene import load_scene

    p = tr.params
    edges = np.asarray(p["bins"].split(","), dtype=float) if isinstance(p["bins"], str) \
        else np.asarray(BIN_EDGES_MM)
    methods = p["methods"].split(",")
    rng = tr.rng()
    scene_rng, sim_ss, start_rng, solver_rng = rng.spawn(4)
    t0 = time.perf_counter()
    scene = case_scene(load_scene(tr.scene), scene_rng, jitter_deg=float(p["jitter_deg"]))
    case = simulate_without_sweeps(scene, int(sim_ss.integers(0, 2**63 - 1)))
    surfaces, views = reglib_inputs(case, oracle=("calibration",))
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
                res = register(surfaces, views, start, **opts)
                dt = time.perf_counter() - t1
                m1 = mtre(res.ct2robot, truth, pins)
                base = {"method": method, "bin": b, "start": k}
                rows += [
                    {**base, "metric": "start_mtre", "value": m0, "unit": "mm"},
                    {**base, "metric": "final_mtre", "value": m1, "unit": "mm"},
                    {**base, "metric": "success", "value": float(m1 < SUCCESS_MM), "unit": ""},
                    {**base, "metric": "converged", "value": float(res.converged), "unit": ""},
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
    """Method -> capture range (mm): upper edge of the last bin of the run from the first bin
    in which every bin has a success rate >= ``rate`` (0 if the first bin fails)."""
    out = {}
    for method, d in s.groupby("method"):
        d = d.set_index("bin")["success_rate"]
        cr = 0.0
        for b in range(len(edges) - 1):
            if b not in d.index or d[b] < rate:
                break
            cr = float(edges[b + 1])
        out[method] = cr
    return out


def run(ctx) -> pd.DataFrame:
    from studies.common import markdown_table
    from studies.runner import run_study_trials

    size = QUICK_SIZE if ctx.quick else DEFAULT_SIZE
    bins = QUICK_BINS_MM if ctx.quick else BIN_EDGES_MM
    params = trial_params(bins=bins, **size)
    df = run_study_trials(ctx, trial, params)
    failures = df.attrs.get("failures", {})
    ok = df[df.metric != "failed"]
    s = summary(ok)
    edges = np.asarray(bins, dtype=float)
    s.insert(2, "initial_mtre_bin", [f"{edges[b]:g}-{edges[b + 1]:g}" for b in s["bin"]])
    cr = capture_range(s, edges)
    sim = ok[ok.metric == "sim_time"]["value"]
    reg = ok[ok.metric == "time"]["value"]
    lines = [f"- {m}: **{cr[m]:g} mm**" for m in cr]
    ctx.report("Capture range", "\n".join([
        f"Largest initial mTRE (at the three pins) up to which >= {CAPTURE_RATE:.0%} of the "
        f"starts end with a final mTRE < {SUCCESS_MM:g} mm, per pose method "
        "(published capture ranges for 2-D/3-D registration: 4-11 mm):", "", *lines, "",
        f"Cases: {size['cases']} random femurs (shape variation {SHAPE_VARIATION:g} SD unless "
        f"the scene sets one), C-arm angles jittered by up to {JITTER_DEG:g} deg, "
        f"{size['starts_per_bin']} start(s) per bin and case for {PRIMARY}, "
        f"{size['others_per_bin']} for the other methods; {len(failures)} failed trial(s)."
        " Calibration: **oracle** (the true pixel -> ray map of each C-arm; no sweep is "
        "simulated), surfaces and X-ray contours estimated by reglib. With fewer than 20 "
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
    _figures(ctx, ok, s, edges)
    return df


def _figures(ctx, df, s, edges):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    centres = 0.5 * (edges[:-1] + edges[1:])
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, d in s.groupby("method"):
        ax.plot(centres[d["bin"].to_numpy(int)], 100 * d["success_rate"], "o-", label=method)
    ax.axhline(100 * CAPTURE_RATE, color="grey", ls="--", lw=1)
    ax.set_xlabel("initial mTRE at the pins (mm)")
    ax.set_ylabel(f"success rate (final mTRE < {SUCCESS_MM:g} mm), %")
    ax.set_ylim(-3, 103)
    ax.legend()
    fig.tight_layout()
    fig.savefig(ctx.figure("capture_success.png", "Success rate against the initial mTRE, "
                           "per pose method (dashed: 95 %)"), dpi=110)
    plt.close(fig)

    wide = df[df.metric.isin(["start_mtre", "final_mtre"])].pivot_table(
        index=["trial", "method", "start"], columns="metric", values="value").reset_index()
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, d in wide.groupby("method"):
        ax.plot(d["start_mtre"], np.maximum(d["final_mtre"], 1e-3), ".", label=method,
                alpha=0.7)
    ax.axhline(SUCCESS_MM, color="grey", ls="--", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("initial mTRE at the pins (mm)")
    ax.set_ylabel("final mTRE at the pins (mm)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(ctx.figure("capture_final_error.png", "Final against initial mTRE, one point "
                           "per start and method (dashed: the 2 mm success threshold)"),
                dpi=110)
    plt.close(fig)
