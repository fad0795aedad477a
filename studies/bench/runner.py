"""Benchmark of the study runner: trials per minute on 1 and 2 workers, parallel efficiency,
and the share of a trial's time per stage (simulation versus registration).

The default trial is a CPU-bound toy that needs no simulated world: ``solves`` points-to-lines
pose problems (random pose, points in a 100 mm cube seen from a source at the origin,
Gaussian noise on the points, solved by Levenberg-Marquardt with
``scipy.optimize.least_squares`` from a start perturbed by about 5 deg and 10 mm). It
reports the final rotation and translation errors and its time per stage
(``metric="time"``, ``stage`` = ``simulate`` or ``register``). Point ``--trial`` at another
top-level trial function (``module:function``) to time real trials; the stage shares come
from its ``time`` rows that have a ``stage`` key.

Run: ``python -m studies.bench.runner [--trials 40] [--solves 120] [--workers 1 2]``.
The parallel efficiency of ``w`` workers is ``rate(w) / (w * rate(1))``. A warm-up run
first starts the worker machinery (timed separately as ``warmup_s``); the table also gives
the median in-worker time of one trial, which grows when the cores are shared.
"""

from __future__ import annotations

import argparse
import importlib
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from studies.runner import Trial, make_trials, read_trials, run_trials


def _point_line_residuals(x, points, directions):
    """Perpendicular offsets (mm) of ``R p + t`` from the lines through the origin along
    ``directions`` (unit); ``x`` = rotation vector (rad) and ``t`` (mm). Shape (3N,)."""
    q = Rotation.from_rotvec(x[:3]).apply(points) + x[3:]
    along = np.sum(q * directions, axis=1, keepdims=True)
    return (q - along * directions).ravel()


def pose_trial(trial: Trial) -> list[dict]:
    """CPU-bound toy trial: ``params['solves']`` pose solves with ``params['n_points']``
    points and noise ``params['noise_mm']`` (mm); errors of the last solve and stage times."""
    p = trial.params
    rng = trial.rng()
    n_points, solves, noise = int(p.get("n_points", 20)), int(p.get("solves", 40)), \
        float(p.get("noise_mm", 0.1))
    t_sim = t_reg = 0.0
    rot_err = tra_err = np.nan
    for _ in range(solves):
        t0 = time.perf_counter()
        R_true = Rotation.random(random_state=rng)
        t_true = np.array([0.0, 0.0, 1000.0]) + rng.normal(0.0, 20.0, 3)
        points = rng.uniform(-50.0, 50.0, (n_points, 3))
        seen = R_true.apply(points) + t_true + rng.normal(0.0, noise, (n_points, 3))
        directions = seen / np.linalg.norm(seen, axis=1, keepdims=True)
        start = np.concatenate([(Rotation.from_rotvec(rng.normal(0.0, 0.05, 3)) * R_true)
                                .as_rotvec(), t_true + rng.normal(0.0, 6.0, 3)])
        t1 = time.perf_counter()
        sol = least_squares(_point_line_residuals, start, args=(points, directions),
                            method="lm", xtol=1e-12, ftol=1e-12)
        t2 = time.perf_counter()
        t_sim += t1 - t0
        t_reg += t2 - t1
        rot_err = np.degrees((Rotation.from_rotvec(sol.x[:3]) * R_true.inv()).magnitude())
        tra_err = float(np.linalg.norm(sol.x[3:] - t_true))
    return [
        {"metric": "rotation_error", "value": float(rot_err), "unit": "deg"},
        {"metric": "translation_error", "value": tra_err, "unit": "mm"},
        {"metric": "time", "value": t_sim, "unit": "s", "stage": "simulate"},
        {"metric": "time", "value": t_reg, "unit": "s", "stage": "register"},
    ]


def _resolve(spec: str):
    mod, _, fn = spec.partition(":")
    if not fn:
        raise SystemExit(f"--trial: expected 'module:function', got {spec!r}")
    return getattr(importlib.import_module(mod), fn)


def benchmark(trial_fn=pose_trial, *, n_trials: int = 40, solves: int = 120,
              workers=(1, 2), scene: str = "points-lines", seed: int = 0,
              scheduler=None, out_root=None,
              mp_context: str | None = None) -> pd.DataFrame:
    """Time the same trials on each worker count; one row per worker count.

    Columns: ``workers``, ``trials``, ``warmup_s`` (a first run of ``workers`` trials that
    starts the worker machinery, not counted in the rate), ``wall_s``, ``trials_per_min``,
    ``efficiency`` (``rate / (workers * base)``, base = the first row's rate per worker),
    ``median_trial_s`` (in-worker time of one trial), ``failed``, ``same_rows`` (the
    non-time rows equal those of the first worker count), then ``share_<stage>`` (mean share
    of the trial's stage time, from ``time`` rows with a ``stage`` key).
    """
    trials = make_trials(scene, seed, [{"solves": solves}] * n_trials)
    records, ref, base = [], None, None
    with tempfile.TemporaryDirectory(dir=out_root) as tmp:
        for w in workers:
            # warm-up: start the process machinery (the forkserver imports the modules once)
            # so that the timed run measures the steady state; its wall time is reported.
            t0 = time.perf_counter()
            run_trials(trial_fn, trials[:w], out_dir=Path(tmp) / f"warm{w}", workers=w,
                       progress=False, scheduler=scheduler if w != 1 else None,
                       mp_context=mp_context)
            warm = time.perf_counter() - t0
            out = Path(tmp) / f"w{w}"
            t0 = time.perf_counter()
            df = run_trials(trial_fn, trials, out_dir=out, workers=w, progress=False,
                            resume=False, scheduler=scheduler if w != 1 else None,
                            mp_context=mp_context)
            wall = time.perf_counter() - t0
            tr = read_trials(out)
            rows = df[df.metric != "time"].reset_index(drop=True)
            if ref is None:
                ref = rows
            rate = 60.0 * n_trials / wall
            base = base or rate / w
            rec = {"workers": w, "trials": n_trials, "warmup_s": warm, "wall_s": wall,
                   "trials_per_min": rate,
                   "efficiency": rate / (w * base), "median_trial_s": float(tr.seconds.median()),
                   "failed": int((tr.status == "failed").sum()),
                   "same_rows": bool(rows.equals(ref))}
            if "stage" in df.columns:
                t = df[(df.metric == "time") & df.stage.notna()]
                per = t.pivot_table(index="trial", columns="stage", values="value",
                                    aggfunc="sum")
                share = per.div(per.sum(axis=1), axis=0).mean()
                rec.update({f"share_{k}": float(v) for k, v in share.items()})
            records.append(rec)
    return pd.DataFrame(records)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=40, help="number of trials")
    ap.add_argument("--solves", type=int, default=120, help="pose solves per toy trial")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--trial", default=None, help="module:function of another trial function")
    ap.add_argument("--scene", default="points-lines")
    ap.add_argument("--scheduler", default=None, help="Dask scheduler address (workers > 1)")
    ap.add_argument("--mp-context", default=None, choices=["spawn", "forkserver"],
                    help="process start method (default: forkserver where available)")
    args = ap.parse_args(argv)
    fn = _resolve(args.trial) if args.trial else pose_trial
    res = benchmark(fn, n_trials=args.trials, solves=args.solves, workers=args.workers,
                    scene=args.scene, scheduler=args.scheduler,
                    mp_context=args.mp_context)
    from studies.common import markdown_table

    print(markdown_table(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
