"""Table I of the paper: time per pose solve for 20, 100 and 1000 points, per method.

Timed (CPU time) in this process on the paper's synthetic set-up
(``scenes/points-lines.toml``), on two kinds of data: ``clean`` (noise-free) and ``noisy``
(Gaussian noise of 0.01, a hundredth of the cloud, on every point). Each configuration is
timed ``repeats`` times on fresh seeded instances; the table gives the median. Beside our
methods, PoseLib (C++, the ``poselib`` package of the ``bench`` extra) on the same data as
the reference measured in the same run: ``poselib_ransac`` is its full estimator (P3P
RANSAC + LM refinement; the bundle is central, so its pinhole solver applies) and
``poselib_refine`` its LM refinement alone from the same identity start as ours. The
paper's figures (IBM RS6000, 1997) are printed beside.

This is a benchmark, not a test: the ratio to PoseLib is what carries over between machines.
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from studies.common import markdown_table

TITLE = "the paper's Table I: median time per pose solve, beside PoseLib"
DEFAULT_SCENE = "points-lines"
METHODS = ("lm", "linear", "robust", "ransac")
PAPER_MS = {(100, "lm"): 790, (100, "linear"): 690, (100, "robust"): 28,
            (20, "lm"): 200, (20, "linear"): 42, (20, "robust"): 9.6, (1000, "robust"): 250}


def _poselib_solvers():
    try:
        import poselib
    except ImportError:
        return {}

    def frame(case):
        c = case.origins[0]
        mean_dir = case.directions.mean(0)
        z = mean_dir / np.linalg.norm(mean_dir)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R_cw = np.stack([x, np.cross(z, x), z])  # world -> camera rotation
        b = case.directions @ R_cw.T
        f = 1000.0
        uv = f * b[:, :2] / b[:, 2:3]
        cam = {"model": "PINHOLE", "width": 2000, "height": 2000, "params": [f, f, 0.0, 0.0]}
        return R_cw, c, uv, cam

    def to_points2lines(pose, R_cw, c):
        # x_cam = R p + t and x_cam = R_cw (x_world - c)
        return R_cw.T @ pose.R, R_cw.T @ pose.t + c

    def ransac(case):
        R_cw, c, uv, cam = frame(case)
        pose, _ = poselib.estimate_absolute_pose(uv, case.points, cam,
                                                 {"max_reproj_error": 2.0}, {})
        return to_points2lines(pose, R_cw, c)

    def refine(case):
        R_cw, c, uv, cam = frame(case)
        init = poselib.CameraPose()
        init.R = R_cw
        init.t = -R_cw @ c
        pose, _ = poselib.refine_absolute_pose(uv, case.points, init, cam, {})
        return to_points2lines(pose, R_cw, c)

    return {"poselib_ransac": ransac, "poselib_refine": refine}


def time_solves(spec, n_points, noise, repeats, seed, methods=METHODS, *, with_poselib=True):
    """Rows of (method, n_points, data, repeat, time s, landmark error)."""
    from reglib.geometry import RigidTransform
    from reglib.pose import solve_pose
    from testbed.synthetic import landmark_error, make_points_lines

    rng = np.random.default_rng(seed)
    cases = [make_points_lines(spec, rng, n_points=n_points, noise_std=noise,
                               outlier_fraction=1.0 if noise else 0.0) for _ in range(repeats)]
    solvers = {m: (lambda case, m=m: solve_pose(case.points, case.origins, case.directions, m,
                                                rng=0)) for m in methods}
    if with_poselib:
        solvers.update(_poselib_solvers())
    rows = []
    for name, solve in solvers.items():
        solve(cases[0])  # warm-up (numba compilation, caches)
        for k, case in enumerate(cases):
            t0 = time.process_time()  # CPU time: the machine is shared
            out = solve(case)
            dt = time.process_time() - t0
            est = out.transform if hasattr(out, "transform") else RigidTransform(*out)
            rows.append({"method": name, "n_points": n_points, "repeat": k,
                         "time_s": dt,
                         "error": landmark_error(est, case.points2lines, case.landmarks)})
    return rows


def run(ctx) -> pd.DataFrame:
    spec = ctx.scene.synthetic
    sizes = (20, 100, 1000)
    repeats = {20: 200, 100: 200, 1000: 30} if not ctx.quick else {20: 10, 100: 10, 1000: 3}
    rows = []
    for data, noise in (("clean", 0.0), ("noisy", 0.01)):
        for n in sizes:
            for r in time_solves(spec, n, noise, repeats[n], ctx.seed + n):
                rows.append({**r, "data": data})
    raw = pd.DataFrame(rows)
    long = []
    for r in raw.itertuples(index=False):
        trial = f"{r.data}-{r.n_points}-{r.repeat}"
        base = {"trial": trial, "method": r.method, "n_points": r.n_points, "data": r.data}
        long.append({**base, "metric": "time", "value": r.time_s, "unit": "s"})
        long.append({**base, "metric": "landmark_error", "value": r.error, "unit": ""})
    df = pd.DataFrame(long)
    _report(ctx, raw)
    return df


def median_table(raw: pd.DataFrame) -> pd.DataFrame:
    med = raw.groupby(["data", "n_points", "method"])["time_s"].median().mul(1e3)
    t = med.unstack("method").reset_index()
    t.columns.name = None
    return t


def _report(ctx, raw):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = median_table(raw)
    paper = pd.DataFrame([{"n_points": n, "method": m, "paper_ms": v}
                          for (n, m), v in PAPER_MS.items()])
    paper = paper.pivot(index="n_points", columns="method", values="paper_ms")
    paper.columns = [f"paper {c}" for c in paper.columns]
    t = t.merge(paper.reset_index(), on="n_points", how="left")
    if "poselib_ransac" in t:
        t["robust / poselib_ransac"] = t["robust"] / t["poselib_ransac"]
        t["robust / poselib_refine"] = t["robust"] / t["poselib_refine"]
        if "ransac" in t:  # issue 13's goal: within 3x on the noisy rows
            t["ransac / poselib_ransac"] = t["ransac"] / t["poselib_ransac"]
    ratios = ("Ratios are ours over PoseLib's (goal for RANSAC on the noisy rows: at most 3)."
              if "poselib_ransac" in t else
              "PoseLib is not installed (`pip install -e '.[bench]'`), so its times and the "
              "ratios to them are missing.")
    ctx.report("Median time per solve (ms)",
               "Median CPU time over fresh seeded instances, this machine, one core; the "
               "paper's IBM RS6000 times beside. The table's sizes (20, 100, 1000 points) and "
               "its two data sets (clean; noise 0.01 on every point) replace the scene's "
               "n_points, noise_std and outlier_fraction; its other fields stand. "
               f"{ratios}\n\n"
               + markdown_table(t, ".3g"))
    # per data set: a median over clean (about 1e-15) and noisy (about 1e-2) solves together
    # described neither
    err = (raw.groupby(["data", "n_points", "method"])["error"].median().unstack("method")
           .reset_index())
    err.columns.name = None
    # a time (and a ratio to it) is of a solve that failed where its error is large: said,
    # not left to the reader (PoseLib's refine ended 1-2 cloud sizes off on a held-out
    # geometry and the ratios read as if it had solved, a review)
    # failed: above the scene's success_threshold, as fig9 and the synthetic run count (a
    # fixed 0.1 called every noisy solve failed on a held-out scene whose landmarks lie 100
    # cloud sizes away, h26)
    threshold = ctx.scene.synthetic.success_threshold
    med = raw.groupby(["data", "n_points", "method"])["error"].median()
    failed = [f"{m} on {d} {n}" for (d, n, m), e in med.items() if e > threshold]
    warn = (f"\n\n**Solves that failed** (the median of the solves' largest landmark errors "
            f"above {threshold:g}, the "
            "scene's success_threshold; their times and the ratios to them are of failed "
            "solves): " + ", ".join(failed) + "." if failed else "")
    ctx.report("Median max landmark error of the timed solves",
               "Per data set (clean: exact lines, noisy: the noise of the timing table's "
               "noisy rows).\n\n" + markdown_table(err, ".2g") + warn)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, data in zip(axes, ("clean", "noisy")):
        sub = raw[raw.data == data].groupby(["method", "n_points"])["time_s"].median() * 1e3
        for method in sub.index.get_level_values(0).unique():
            s = sub.loc[method]
            ax.loglog(s.index, s.values, "o-", label=method)
        ax.set_title(f"{data} data")
        ax.set_xlabel("points")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("median time per solve (ms)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(ctx.figure("table1_times.png", "median solve time against number of points"),
                dpi=110)
    plt.close(fig)
    ctx.table = t
