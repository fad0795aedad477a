"""Tables and figures from long-format results (``trial, metric, value, unit`` + parameters).

Results first, figures from the tables in a separate step (STYLE.md). Failed trials (rows
``metric="failed"`` written by :mod:`studies.runner`) count: they are reported in the
``failed`` column of :func:`summarize` and as failures in :func:`success_rate`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from studies.runner import FAILED_METRIC

__all__ = ["plot_metric", "success_rate", "summarize"]


def _check(df: pd.DataFrame, metric: str, by: Sequence[str]) -> list[str]:
    missing = [c for c in ("trial", "metric", "value", "unit", *by) if c not in df.columns]
    if missing:
        raise ValueError(f"results lack the columns {missing}")
    if not (df.metric == metric).any():
        known = sorted(set(df.metric) - {FAILED_METRIC})
        raise ValueError(f"no rows with metric {metric!r}; metrics present: {known}")
    return list(by)


def summarize(df: pd.DataFrame, metric: str, by: Sequence[str] = ()) -> pd.DataFrame:
    """Statistics of ``metric`` per group of ``by`` columns.

    Returns
    -------
    DataFrame with the ``by`` columns, ``n`` (rows with a finite value), ``failed`` (failed
    trials in the group; a failed trial has only its trial parameters, so it counts in every
    group of a row-level key such as ``pin``), ``mean``, ``median``, ``p95``, ``max`` (in
    the metric's unit) and ``unit``.
    """
    by = _check(df, metric, by)
    rows = df[(df.metric == metric) & np.isfinite(df.value)]
    units = sorted(set(df.loc[df.metric == metric, "unit"]))
    if len(units) != 1:
        raise ValueError(f"metric {metric!r} has several units {units}; cannot summarise")
    agg = {"n": ("value", "size"), "mean": ("value", "mean"), "median": ("value", "median"),
           "p95": ("value", lambda v: float(np.quantile(v, 0.95))), "max": ("value", "max")}
    if by:
        out = rows.groupby(by, dropna=False).agg(**agg).reset_index()
        failed = df[df.metric == FAILED_METRIC]
        # groups made only of failed trials (all their ``by`` values known) appear with n = 0
        known = failed.dropna(subset=by)[by].drop_duplicates()
        out = out.merge(known, on=by, how="outer").sort_values(by, ignore_index=True)
        out["n"] = out["n"].fillna(0).astype(int)
        # a failed trial has no row-level keys (e.g. ``pin``): it counts in every group that
        # its known keys match
        counts = []
        for key in out[by].itertuples(index=False):
            m = np.ones(len(failed), dtype=bool)
            for col, val in zip(by, key):
                m &= failed[col].isna().to_numpy() | (failed[col] == val).to_numpy()
            counts.append(int(failed.trial[m].nunique()))
        out["failed"] = counts
    else:
        v = rows.value.to_numpy()
        empty = v.size == 0
        out = pd.DataFrame([{
            "n": v.size, "mean": np.nan if empty else v.mean(),
            "median": np.nan if empty else np.median(v),
            "p95": np.nan if empty else np.quantile(v, 0.95),
            "max": np.nan if empty else v.max(),
            "failed": int(df.loc[df.metric == FAILED_METRIC, "trial"].nunique())}])
    out["unit"] = units[0]
    return out[[*by, "n", "failed", "mean", "median", "p95", "max", "unit"]]


def success_rate(df: pd.DataFrame, metric: str, threshold: float, by: Sequence[str] = (), *,
                 confidence: float = 0.95) -> pd.DataFrame:
    """Share of trials whose ``metric`` is below ``threshold``, per group, with its Wilson
    score interval (``scipy.stats.binomtest``).

    A trial succeeds when it has a ``metric`` row with a finite value ``< threshold``; a
    failed trial, or one whose value is NaN, counts as a failure. With several rows of the
    metric per trial (e.g. per pin) the trial succeeds only if all of them do. ``by`` must
    be trial parameters (a failed trial has no row-level keys such as ``pin``).

    Returns
    -------
    DataFrame with the ``by`` columns, ``trials``, ``successes``, ``rate``, ``lo``, ``hi``.
    """
    from scipy.stats import binomtest

    by = _check(df, metric, by)
    cols = ["trial", *by]
    rel = df[(df.metric == metric) | (df.metric == FAILED_METRIC)]
    ok = (rel.metric == metric) & np.isfinite(rel.value) & (rel.value < threshold)
    per_trial = rel.assign(ok=ok).groupby(cols, dropna=False).ok.all().reset_index()
    groups = per_trial.groupby(by, dropna=False) if by else [((), per_trial)]
    out = []
    for key, g in groups:
        n, k = len(g), int(g.ok.sum())
        ci = binomtest(k, n).proportion_ci(confidence_level=confidence, method="wilson")
        key = key if isinstance(key, tuple) else (key,)
        out.append({**dict(zip(by, key)), "trials": n, "successes": k, "rate": k / n,
                    "lo": ci.low, "hi": ci.high})
    return pd.DataFrame(out, columns=[*by, "trials", "successes", "rate", "lo", "hi"])


def plot_metric(df: pd.DataFrame, metric: str, x: str, path, *, hue: str | None = None,
                logy: bool = False, title: str | None = None) -> Path:
    """Median of ``metric`` against parameter ``x`` with the 5-95 % band, one line per value
    of ``hue``; written to ``path`` (PNG). Returns the path."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    by = [x] + ([hue] if hue else [])
    _check(df, metric, by)
    rows = df[(df.metric == metric) & np.isfinite(df.value)]
    unit = rows.unit.iloc[0] if len(rows) else ""
    fig, ax = plt.subplots(figsize=(5.5, 3.8), dpi=120)
    for label, g in (rows.groupby(hue, dropna=False) if hue else [(None, rows)]):
        q = g.groupby(x).value.quantile([0.05, 0.5, 0.95]).unstack()
        line, = ax.plot(q.index, q[0.5], marker="o", label=None if hue is None else
                        f"{hue}={label}")
        ax.fill_between(q.index, q[0.05], q[0.95], color=line.get_color(), alpha=0.2)
    ax.set_xlabel(x)
    ax.set_ylabel(f"{metric} ({unit})" if unit else metric)
    if logy:
        ax.set_yscale("log")
    if hue:
        ax.legend()
    ax.set_title(title or f"{metric}: median and 5-95 % band")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
