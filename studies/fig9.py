"""Fig. 9 of the paper: pose error against noise and the fraction of corrupted points.

The synthetic points-and-lines set-up of ``scenes/points-lines.toml`` (NOTES.md s3): for
every noise standard deviation (0 to 0.33, a third of the cloud's diameter) and fraction of
corrupted points (0 to 80 %), ``repeats`` seeded instances; every pose method solves the same
instance; the error is the largest landmark distance between the estimated and the true
transforms (unitless, unit-cube units). A solve counts as a success when that error is below
the scene's ``success_threshold`` (0.1, a tenth of the cloud).
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from studies.common import markdown_table

TITLE = "the paper's Fig. 9: landmark error vs noise and outlier fraction, per pose method"
DEFAULT_SCENE = "points-lines"
METHODS = ("lm", "linear", "robust", "ransac")
NOISE = (0.0, 0.033, 0.066, 0.1, 0.15, 0.2, 0.25, 0.33)
FRACTIONS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


def trial(tr) -> list[dict]:
    """One instance (noise, outlier fraction), solved by every method."""
    from reglib.pose import solve_pose
    from testbed.scene import load_scene
    from testbed.synthetic import landmark_error, make_points_lines

    spec = load_scene(tr.scene).synthetic
    rng = tr.rng()
    case = make_points_lines(spec, rng, noise_std=tr.params["noise"],
                             outlier_fraction=tr.params["outliers"])
    rows = []
    for method in METHODS:
        t0 = time.perf_counter()
        res = solve_pose(case.points, case.origins, case.directions, method, rng=rng)
        dt = time.perf_counter() - t0
        err = landmark_error(res.transform, case.points2lines, case.landmarks)
        rows += [
            {"metric": "landmark_error", "value": err, "unit": "", "method": method},
            {"metric": "success", "value": float(err < spec.success_threshold), "unit": "",
             "method": method},
            {"metric": "converged", "value": float(res.converged), "unit": "", "method": method},
            {"metric": "time", "value": dt, "unit": "s", "method": method},
        ]
    return rows


def run(ctx) -> pd.DataFrame:
    from studies.common import nothing_finished
    from studies.runner import run_study_trials

    noise = (0.0, 0.1, 0.33) if ctx.quick else NOISE
    fractions = (0.0, 0.4, 0.7) if ctx.quick else FRACTIONS
    repeats = 2 if ctx.quick else 10
    params = [{"noise": s, "outliers": f, "repeat": k}
              for s in noise for f in fractions for k in range(repeats)]
    df = run_study_trials(ctx, trial, params)
    if not nothing_finished(ctx, df, "Success at the largest noise"):
        _report(ctx, df, noise, fractions)
    return df


def summary(df: pd.DataFrame) -> pd.DataFrame:
    """Per method, noise and fraction: median landmark error and success rate."""
    err = df[df.metric == "landmark_error"].groupby(["method", "noise", "outliers"])["value"]
    ok = df[df.metric == "success"].groupby(["method", "noise", "outliers"])["value"]
    return pd.DataFrame({"median_error": err.median(), "success_rate": ok.mean()}).reset_index()


def _report(ctx, df, noise, fractions):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = summary(df)
    threshold = ctx.scene.synthetic.success_threshold   # what the trials counted against
    fig, axes = plt.subplots(2, len(METHODS), figsize=(4 * len(METHODS), 7), squeeze=False)
    for j, method in enumerate(METHODS):
        sub = s[s.method == method]
        for i, (col, title, cmap, vmax) in enumerate(
            [("median_error", "median max landmark error", "viridis", 0.5),
             ("success_rate", f"success rate (error < {threshold:g})", "RdYlGn", 1.0)]
        ):
            grid = sub.pivot(index="noise", columns="outliers", values=col).reindex(
                index=list(noise), columns=list(fractions))
            ax = axes[i, j]
            im = ax.imshow(grid.values, origin="lower", cmap=cmap, vmin=0, vmax=vmax,
                           aspect="auto")
            ax.set_xticks(range(len(fractions)), [f"{f:.0%}" for f in fractions], fontsize=7)
            ax.set_yticks(range(len(noise)), [f"{x:.2f}" for x in noise], fontsize=7)
            ax.set_xlabel("corrupted points")
            ax.set_ylabel("noise std (cloud units)")
            ax.set_title(f"{method}: {title}", fontsize=9)
            for (r, c), v in np.ndenumerate(grid.values):
                if np.isfinite(v):
                    ax.text(c, r, f"{v:.2f}", ha="center", va="center", fontsize=6,
                            color="w" if (v < 0.5 * vmax) == (col == "median_error") else "k")
            fig.colorbar(im, ax=ax, fraction=0.046)
    fig.suptitle("Pose from points and lines (paper Fig. 9 set-up), "
                 f"{int(df.trial.nunique())} instances")
    fig.tight_layout()
    fig.savefig(ctx.figure("fig9_heatmaps.png", "median landmark error and success rate"),
                dpi=110)
    plt.close(fig)

    worst = s[s.noise == max(noise)]
    table = worst.pivot(index="outliers", columns="method", values="success_rate").reset_index()
    ctx.report(
        f"Success rate at noise {max(noise)} (a third of the cloud's diameter)",
        f"Fraction of instances whose max landmark error is below {threshold:g} (the "
        "scene's success_threshold). The figure's grid of noise and corrupted fractions "
        "replaces the scene's noise_std and outlier_fraction; its other fields (n_points, "
        "rotation_deg, landmarks, ...) stand. The paper: the robust "
        "method copes with about 40 % of such points; LM and linear only with < 5 %.\n\n"
        + markdown_table(table, ".2f"),
    )
    med = s.pivot_table(index=["noise", "outliers"], columns="method",
                        values="median_error").reset_index()
    ctx.report("Median max landmark error", markdown_table(med, ".3g"))
