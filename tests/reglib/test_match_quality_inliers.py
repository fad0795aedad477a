"""Mutation audit 3: match_quality's inlier_fraction is the share of matches the solver
KEPT (weight > 0), not the mean Tukey weight; the verdict's 0.5 limit reads it."""
from types import SimpleNamespace

import numpy as np

from reglib.pipeline import EstimateOptions, match_quality, verdict


def _res(weights, n_views=2):
    w = np.asarray(weights, dtype=float)
    n = len(w)
    return SimpleNamespace(residuals=np.full(n, 0.2), weights=w,
                           view_index=np.arange(n) % n_views,
                           sensitivity=np.full(6, 0.5), pivot_gain=float("nan"))


def test_inlier_fraction_counts_kept_matches_not_their_weights():
    # 80 % of the matches kept, each with a down-weighting Tukey weight of 0.4
    w = np.r_[np.full(80, 0.4), np.zeros(20)]
    q = match_quality(_res(w))
    assert abs(q["inlier_fraction"] - 0.8) < 1e-12
    assert abs(q["min_view_inlier_fraction"] - 0.8) < 1e-12


def test_down_weighted_but_kept_matches_do_not_refuse_the_pose():
    w = np.r_[np.full(80, 0.4), np.zeros(20)]
    q = match_quality(_res(w))
    reasons = verdict(True, q, "", EstimateOptions(), 2)
    assert not any("inlier fraction" in r for r in reasons), reasons


def test_per_view_figures_name_the_worst_view():
    """max_view_median_mm is the WORST view's median (min over views passed the suite)."""
    n = 40
    r = np.r_[np.full(n, 0.2), np.full(n, 0.9)]
    w = np.r_[np.ones(n), np.r_[np.ones(n // 2), np.zeros(n // 2)]]
    res = SimpleNamespace(residuals=r, weights=w, view_index=np.r_[np.zeros(n), np.ones(n)],
                          sensitivity=np.full(6, 0.5), pivot_gain=float("nan"))
    q = match_quality(res)
    assert abs(q["max_view_median_mm"] - 0.9) < 1e-12
    assert abs(q["min_view_inlier_fraction"] - 0.5) < 1e-12
    assert abs(q["median_residual_mm"] - 0.55) < 1e-12
