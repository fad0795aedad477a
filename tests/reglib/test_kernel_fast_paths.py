"""The compiled pose kernels' fast paths against their twins, bit for bit.

``reglib._pose_numba.irls`` sums its normal equations with normals and six unknowns in
``_normals_system6`` (``generic=True``: the general loop, the twin), and
``reglib._ransac_numba.hypotheses`` stops scoring a hypothesis that cannot reach the best
inlier count (``prune=False``: every pair scored, the twin; the numpy
``_ransac_hypotheses_numpy`` the reference). Both must give exactly the twin's result: the
capture-range study's rows are compared before and after on whole trials, and these tests
hold the kernels to it on random cases.
"""

import numpy as np
import pytest

from reglib.geometry import RigidTransform
from reglib.pose import _ransac_hypotheses_numpy, _ransac_samples, _scale_of
from testbed.scene import SyntheticSpec
from testbed.synthetic import make_points_lines

pytest.importorskip("numba")
from reglib import _pose_numba, _ransac_numba  # noqa: E402


def _case(seed, n, outliers, noise=0.05):
    return make_points_lines(SyntheticSpec(), np.random.default_rng(seed), n_points=n,
                             noise_std=noise, outlier_fraction=outliers)


def _normals(rng, d):
    a = rng.normal(size=d.shape)
    nrm = a - np.sum(a * d, axis=1, keepdims=True) * d
    return nrm / np.linalg.norm(nrm, axis=1, keepdims=True)


@pytest.mark.parametrize("seed", range(6))
def test_irls_normals_fast_path_equals_the_generic_loop_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    c = _case(seed, int(rng.integers(6, 400)), outliers=0.3)
    nrm = _normals(rng, c.directions)
    start = RigidTransform.from_rotvec(rng.normal(size=3) * 0.05, rng.normal(size=3)
                                       ) @ c.points2lines
    x0 = start.apply(c.points)
    for robust in (True, False):
        for iterations in (1, 3, 20):
            args = (x0, c.origins, c.directions, nrm, True, np.zeros(3), False, robust,
                    4.685, iterations, 1e-10, 6)
            fast = _pose_numba.irls(*args)
            slow = _pose_numba.irls(*args, generic=True)
            for a, b in zip(fast, slow):
                np.testing.assert_array_equal(a, b)
            # and the result is a real solve: the residuals fell from the start's
            if iterations == 20 and not robust:
                d0 = np.abs(np.sum((x0 - c.origins) * nrm, axis=1))
                assert np.sum(fast[2] ** 2) < np.sum(d0 ** 2)


def test_irls_fast_path_serves_only_normals_with_six_unknowns():
    """With a fixed point or the point-to-line residual the general loop runs either way
    (generic or not, the same)."""
    rng = np.random.default_rng(3)
    c = _case(3, 50, outliers=0.2)
    x0 = c.points2lines.apply(c.points) + rng.normal(size=(50, 3)) * 0.1
    f = x0.mean(axis=0)
    for use_normals, use_fixed in ((False, False), (True, True), (False, True)):
        args = (x0, c.origins, c.directions, _normals(rng, c.directions), use_normals, f,
                use_fixed, True, 4.685, 10, 1e-10, 3)
        for a, b in zip(_pose_numba.irls(*args), _pose_numba.irls(*args, generic=True)):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(8))
def test_ransac_pruned_scoring_equals_full_scoring_and_the_reference(seed):
    rng = np.random.default_rng(50 + seed)
    n = int(rng.integers(10, 600))
    c = _case(50 + seed, n, outliers=float(rng.uniform(0.1, 0.7)))
    p = c.points
    # the pairs in the lines' frame moved off the truth, as a registration iteration has them
    o, d = c.origins, c.directions
    thr = 0.02 * _scale_of(p)
    samples = _ransac_samples(np.random.default_rng(seed), n, 300)
    for cheirality in (True, False):
        args = (p, o, d, samples, thr, 0.999, 300, 200, cheirality)
        pruned = _ransac_numba.hypotheses(*args)
        full = _ransac_numba.hypotheses(*args, prune=False)
        for a, b in zip(pruned, full):
            np.testing.assert_array_equal(a, b)
        # the numpy reference: the same best count and trials (its rotations come from an
        # SVD, the kernel's from two frames, so a borderline sample's cheirality may differ)
        ref = _ransac_hypotheses_numpy(*args)
        assert pruned[2] == ref[2] and pruned[4] == ref[4]
        np.testing.assert_allclose(pruned[0], ref[0], atol=1e-8)
        # the best hypothesis holds most of the inliers (a real search, not an empty one)
        assert pruned[2] >= 3


@pytest.mark.parametrize("seed", range(5))
def test_linearised_normal_equations_in_scalars_equal_the_row_loop_bit_for_bit(seed):
    """The linearised iterations' (``iterate``, and the rank test's ``rank_gram``) normal
    equations, summed in scalars, against the row-array loop they replaced."""
    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(3, 500))
    P = rng.normal(size=(n, 3)) * 40.0
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    Nb = _pose_numba.perp_basis(d)
    res = rng.normal(size=(2, n))
    w = np.where(rng.random(n) < 0.3, 0.0, rng.random(n))    # Tukey-like, some zero
    m = P[w > 0].mean(axis=0)
    C, g = _pose_numba.normal_equations(P, Nb, res, w, *m)
    C0, g0 = _pose_numba.normal_equations_rows(P, Nb, res, w, *m)
    np.testing.assert_array_equal(C, C0)
    np.testing.assert_array_equal(g, g0)
    # and they are the normal equations: C = J^T W J for the rows [2 n x (P - m), n]
    J = np.concatenate([2.0 * np.cross(P - m, Nb, axis=-1) * -1.0, Nb], axis=-1)  # (2, n, 6)
    Jw = J * w[None, :, None]
    np.testing.assert_allclose(C, np.einsum("kni,knj->ij", Jw, J), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(g, np.einsum("kni,kn->i", Jw, res), rtol=1e-10, atol=1e-9)
