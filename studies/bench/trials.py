"""Benchmark of real capture-range trials on the study runner: trials per minute on 1 and 2
workers, the parallel efficiency, and the share of a trial's time in simulation versus
registration.

Each trial is a :func:`studies.capture_range.trial`: one random case of the scene (world, CT,
reconstructed surfaces, X-ray frames and snake contours; oracle calibration, no sweep) and
its starts registered by the chosen pose methods. The default trial is a reduced one (3 bins
of initial mTRE, 0-30 mm, one start each, registered by all the study's methods) so that
the benchmark takes a few minutes; ``--starts-per-bin``, ``--methods`` and ``--bins`` make
it the study's own.

The same trials (same seeds) run on each worker count, into a fresh runner database; the
rows other than times must be identical across worker counts (``same_rows``). There is no
warm-up run (a trial lasts about a minute, starting the workers a second or two). The
parallel efficiency of ``w`` workers is ``rate(w) / (w * rate(1))``; on a machine whose
cores are shared with other jobs it falls below 1 for that reason too, which
``median_trial_s`` (the in-worker time of one trial) shows.

Run: ``python -m studies.bench.trials [--trials 2] [--workers 1 2]``.
"""

from __future__ import annotations

import os

# One BLAS thread per process (as in CI), set before numpy is imported: otherwise a single
# worker borrows the second core and the efficiency of 2 workers is understated.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import pandas as pd  # noqa: E402

from studies.runner import make_trials, read_trials, run_trials  # noqa: E402


def benchmark(*, n_trials: int = 2, workers=(1, 2), scene: str = "experiment2", seed: int = 0,
              starts_per_bin: int = 1, bins=(0.0, 10.0, 20.0, 30.0),
              methods=None, out_root=None) -> pd.DataFrame:
    """Time the same capture-range trials on each worker count; one row per count.

    Columns: ``workers``, ``trials``, ``wall_s``, ``trials_per_min``, ``efficiency``
    (``rate / (workers * rate per worker of the first row)``), ``median_trial_s``,
    ``failed``, ``same_rows``, ``sim_s`` and ``register_s`` (mean per trial: the case's
    simulation and estimation; all its registrations), ``share_simulation`` and
    ``share_registration`` (of their sum, mean over trials).
    """
    from studies.capture_range import trial, trial_params
    from testbed.scene import find_scene

    if n_trials < 1:
        raise ValueError(f"n_trials: expected >= 1, got {n_trials}")
    params = trial_params(cases=n_trials, starts_per_bin=starts_per_bin, bins=bins,
                          methods=methods)
    trials = make_trials(str(find_scene(scene)), seed, params)
    records, ref, base = [], None, None
    with tempfile.TemporaryDirectory(dir=out_root) as tmp:
        for w in workers:
            out = Path(tmp) / f"w{w}"
            t0 = time.perf_counter()
            df = run_trials(trial, trials, out_dir=out, workers=w, progress=False,
                            resume=False)
            wall = time.perf_counter() - t0
            tr = read_trials(out)
            keep = df[~df.metric.isin(["time", "sim_time"])].reset_index(drop=True)
            if ref is None:
                ref = keep
            rate = 60.0 * n_trials / wall
            base = base or rate / w
            sim = df[df.metric == "sim_time"].groupby("trial")["value"].sum()
            reg = df[df.metric == "time"].groupby("trial")["value"].sum()
            both = pd.concat([sim.rename("sim"), reg.rename("reg")], axis=1).fillna(0.0)
            tot = both.sum(axis=1)
            records.append({
                "workers": w, "trials": n_trials, "wall_s": wall, "trials_per_min": rate,
                "efficiency": rate / (w * base), "median_trial_s": float(tr.seconds.median()),
                "failed": int((tr.status == "failed").sum()), "same_rows": bool(keep.equals(ref)),
                "sim_s": float(both["sim"].mean()), "register_s": float(both["reg"].mean()),
                "share_simulation": float((both["sim"] / tot).mean()),
                "share_registration": float((both["reg"] / tot).mean()),
            })
    return pd.DataFrame(records)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=2, help="trials (cases) per worker count")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--scene", default="experiment2")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--starts-per-bin", type=int, default=1)
    ap.add_argument("--bins", type=float, nargs="+", default=[0.0, 10.0, 20.0, 30.0],
                    help="bin edges of initial mTRE (mm)")
    ap.add_argument("--methods", nargs="+", default=None,
                    help="pose methods of studies.capture_range.METHODS (default: all)")
    args = ap.parse_args(argv)
    res = benchmark(n_trials=args.trials, workers=args.workers, scene=args.scene,
                    seed=args.seed, starts_per_bin=args.starts_per_bin, bins=args.bins,
                    methods=args.methods)
    from studies.common import markdown_table

    print(markdown_table(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
