"""solve_pose: simulate (the paper's points-and-lines set-up) -> estimate -> compare."""

import numpy as np
import pytest
from scipy.optimize import approx_fprime

from reglib import pose as pose_mod
from reglib.geometry import RigidTransform, cayley, skew
from reglib.pose import p3l_solutions, solve_pose
from testbed.scene import SyntheticSpec
from testbed.synthetic import landmark_error, make_points_lines

SPEC = SyntheticSpec()
METHODS = ["lm", "linear", "robust", "ransac"]


def _case(seed, **kw):
    return make_points_lines(SPEC, np.random.default_rng(seed), **kw)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n", [3, 6, 20, 1000])
def test_noise_free_recovery(method, n):
    if n < pose_mod.MIN_POINTS[method]:
        pytest.skip("fewer points than the method needs (tested in test_bad_input)")
    wrong = 0
    for seed in range(10):
        c = _case(seed, n_points=n)
        r = solve_pose(c.points, c.origins, c.directions, method, rng=seed)
        assert r.converged, r.message
        assert r.residuals.max() < 1e-9
        err = landmark_error(r.transform, c.points2lines, c.landmarks)
        if n == 3:
            # three points on three lines have up to 8 exact solutions: a local method may
            # land on another one; the truth must be among the minimal solver's solutions
            Rs, ts = p3l_solutions(c.points, c.origins, c.directions)
            errs = [landmark_error(RigidTransform(R, t), c.points2lines, c.landmarks)
                    for R, t in zip(Rs, ts)]
            assert min(errs) < 1e-9
            wrong += err > 1e-9
        else:
            assert err < 1e-9, (seed, err)
    assert wrong <= 2  # the paper's 30 deg starts reach the true solution almost always


def test_numba_kernel_matches_numpy_reference():
    pytest.importorskip("numba")
    rng = np.random.default_rng(11)
    for k in range(20):
        c = _case(k, n_points=int(rng.integers(5, 200)), noise_std=0.05 * (k % 3),
                  outlier_fraction=0.3)
        for method in ("linear", "robust"):
            a = solve_pose(c.points, c.origins, c.directions, method, backend="numpy")
            b = solve_pose(c.points, c.origins, c.directions, method, backend="numba")
            assert a.iterations == b.iterations and a.converged == b.converged
            np.testing.assert_allclose(a.R, b.R, atol=1e-9)
            np.testing.assert_allclose(a.t, b.t, atol=1e-9)
            # exact inliers make the robust scale ~1e-15: weights agree to rounding only
            np.testing.assert_array_equal(a.inliers, b.inliers)
            np.testing.assert_allclose(a.weights, b.weights, atol=1e-5)


def test_lm_jacobian_matches_finite_differences():
    rng = np.random.default_rng(4)
    c = _case(4, n_points=15, noise_std=0.1, outlier_fraction=0.5)
    p, o, d = c.points, c.origins, c.directions
    m = p.mean(0)
    Pc = p - m
    M = np.eye(3)[None] - d[:, :, None] * d[:, None, :]

    def fun(x):
        return np.einsum("nij,nj->ni", M, Pc @ cayley(x[:3]).T + m + x[3:] - o).ravel()

    E = skew(np.eye(3))
    for _ in range(5):
        x = rng.normal(size=6) * 0.3
        u = x[:3]
        Q = cayley(u)
        inv = np.linalg.inv(np.eye(3) + skew(u))
        J = np.empty((len(p), 3, 6))
        for k in range(3):
            J[:, :, k] = np.einsum("nij,nj->ni", M, Pc @ (-(np.eye(3) + Q) @ E[k] @ inv).T)
        J[:, :, 3:] = M
        J = J.reshape(-1, 6)
        Jn = np.array([approx_fprime(x, lambda y, i=i: fun(y)[i], 1e-7) for i in range(len(J))])
        np.testing.assert_allclose(J, Jn, atol=1e-5)
    # and the solver's own Jacobian is this one: LM converges in a handful of evaluations
    r = solve_pose(p, o, d, "lm")
    assert r.converged and r.iterations < 30


def _success_rate(method, frac, n, trials=50, seed=7):
    ok = 0
    for sd in np.random.SeedSequence(seed).spawn(trials):
        rng = np.random.default_rng(sd)
        c = make_points_lines(SPEC, rng, n_points=n, noise_std=0.33, outlier_fraction=frac)
        r = solve_pose(c.points, c.origins, c.directions, method, rng=rng)
        ok += landmark_error(r.transform, c.points2lines, c.landmarks) < 0.1
    return ok / trials


@pytest.mark.parametrize("n", [20, 100])
def test_robust_survives_40_percent_outliers(n):
    # the paper's claim: Tukey's biweight copes with ~40 % of points corrupted by noise of a
    # third of the cloud's diameter
    assert _success_rate("robust", 0.4, n) >= 0.95


@pytest.mark.slow
def test_ransac_survives_70_percent_outliers():
    assert _success_rate("ransac", 0.7, 20) >= 0.95


def test_least_squares_methods_break_down_with_outliers():
    # the comparison Fig. 9 makes: LM has no outlier rejection
    assert _success_rate("lm", 0.4, 20, trials=20) < 0.5


def test_p3l_solutions_are_exact():
    for seed in range(20):
        c = _case(seed, n_points=3)
        Rs, ts = p3l_solutions(c.points, c.origins, c.directions)
        assert 1 <= len(Rs) <= 8
        for R, t in zip(Rs, ts):
            moved = c.points @ R.T + t
            w = moved - c.origins
            perp = w - np.sum(w * c.directions, 1, keepdims=True) * c.directions
            assert np.abs(perp).max() < 1e-8


def test_failure_is_reported_not_silent():
    c = _case(5, n_points=20, noise_std=0.33, outlier_fraction=1.0)
    r = solve_pose(c.points, c.origins, c.directions, "linear", max_iterations=2, r=1e-3)
    assert not r and not r.converged and "no convergence" in r.message


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda p, o, d: (p[:2], o[:2], d[:2]), "needs at least"),
        (lambda p, o, d: (np.where(np.arange(30)[:, None] == 4, np.nan, p), o, d), "NaN"),
        (lambda p, o, d: (p, np.where(np.arange(30)[:, None] == 2, np.inf, o), d), "NaN or inf"),
        (lambda p, o, d: (p[:10], o, d), "same number"),
        (lambda p, o, d: (p, o[:, :2], d), r"\(N, 3\)"),
        (lambda p, o, d: (p, o, np.where(np.arange(30)[:, None] == 3, 0.0, d)), "zero-length"),
        (lambda p, o, d: (p, o, 2 * d), "unit vectors"),
        (lambda p, o, d: (np.outer(np.linspace(0, 1, 30), [1.0, 2, 3]), o * 0, d), "collinear"),
    ],
)
@pytest.mark.parametrize("method", METHODS)
def test_bad_input(mutate, match, method):
    c = _case(0, n_points=30)
    p, o, d = mutate(c.points, c.origins, c.directions)
    with pytest.raises(ValueError, match=match):
        solve_pose(p, o, d, method)


def test_unknown_method():
    c = _case(0)
    with pytest.raises(ValueError, match="method"):
        solve_pose(c.points, c.origins, c.directions, "gauss")
