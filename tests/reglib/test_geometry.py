import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from reglib.geometry import (
    RigidTransform,
    assert_transform_close,
    cayley,
    cayley_from_matrix,
    closest_point_to_lines,
    lines_through,
    point_line_distances,
    skew,
)


def test_skew_is_cross_product():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 50, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(a), b), np.cross(a, b), atol=1e-14)


def test_cayley_round_trip_and_definition():
    rng = np.random.default_rng(1)
    for _ in range(200):
        u = rng.normal(size=3) * rng.uniform(0.01, 5)
        Q = cayley(u)
        U = skew(u)
        np.testing.assert_allclose(Q, (np.eye(3) - U) @ np.linalg.inv(np.eye(3) + U), atol=1e-12)
        np.testing.assert_allclose(Q.T @ Q, np.eye(3), atol=1e-12)
        assert np.linalg.det(Q) == pytest.approx(1.0)
        np.testing.assert_allclose(cayley_from_matrix(Q), u, rtol=1e-9, atol=1e-12)
    # small rotations: Q ~ I - 2U, angle 2 atan |u| about -u
    u = np.array([1e-4, -2e-4, 3e-4])
    np.testing.assert_allclose(cayley(u), np.eye(3) - 2 * skew(u), atol=1e-6)  # O(|u|^2)
    u = np.array([0.0, 0.0, np.tan(np.radians(20))])
    rv = Rotation.from_matrix(cayley(u)).as_rotvec()
    np.testing.assert_allclose(rv, [0, 0, -np.radians(40)], atol=1e-12)


def test_cayley_at_180_degrees_raises():
    Q = Rotation.from_rotvec([0, np.pi, 0]).as_matrix()
    with pytest.raises(ValueError, match="180"):
        cayley_from_matrix(Q)


def test_rigid_transform_algebra():
    rng = np.random.default_rng(2)
    a = RigidTransform.from_rotation(Rotation.random(random_state=rng), rng.normal(size=3) * 50)
    b = RigidTransform.from_rotation(Rotation.random(random_state=rng), rng.normal(size=3) * 50)
    p = rng.normal(size=(20, 3)) * 100
    np.testing.assert_allclose((a @ b).apply(p), a.apply(b.apply(p)), atol=1e-10)
    np.testing.assert_allclose((~a).apply(a.apply(p)), p, atol=1e-10)
    np.testing.assert_allclose(RigidTransform.from_matrix(a.as_matrix()).R, a.R)
    assert_transform_close(RigidTransform.from_dict(a.to_dict()), a, mm=1e-12, deg=1e-10)
    with pytest.raises(AssertionError):
        assert_transform_close(a, b, mm=1.0, deg=1.0)
    with pytest.raises(ValueError, match=r"proper rotation \(\|RtR - I\| = 0.00e\+00, det -1; "
                                         r"a reflection\)"):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    # points of the wrong shape are named, not left to numpy's matmul message
    for bad in (np.zeros((4, 2)), 5.0, np.zeros(2)):
        with pytest.raises(ValueError, match=r"RigidTransform.apply: points: expected \(N, 3\)"):
            a.apply(bad)


def test_lines_and_center_of_perspective():
    rng = np.random.default_rng(3)
    c = np.array([10.0, -20.0, 5.0])
    pts = rng.normal(size=(30, 3)) * 100 + [0, 0, 600]
    o, d = lines_through(np.broadcast_to(c, pts.shape), pts)
    np.testing.assert_allclose(point_line_distances(pts, o, d), 0, atol=1e-10)
    np.testing.assert_allclose(closest_point_to_lines(o + 5 * d, d), c, atol=1e-9)
    with pytest.raises(ValueError, match="parallel"):
        closest_point_to_lines(pts, np.broadcast_to([0, 0, 1.0], pts.shape))


def test_composition_and_inverse_stay_rigid_and_read_only():
    """Products and inverses skip the constructor's checks: they must still be proper
    rotations (to rounding, also after many compositions), read-only, and equal to the
    4x4 matrix algebra."""
    rng = np.random.default_rng(4)
    ts = [RigidTransform.from_rotvec(rng.normal(size=3), rng.normal(size=3) * 50.0)
          for _ in range(200)]
    acc = RigidTransform.identity()
    mat = np.eye(4)
    for T in ts:
        acc = acc @ T.inverse()
        mat = mat @ np.linalg.inv(T.as_matrix())
    np.testing.assert_allclose(acc.as_matrix(), mat, atol=1e-9)
    assert np.abs(acc.R.T @ acc.R - np.eye(3)).max() < 1e-12 and np.linalg.det(acc.R) > 0
    for arr in (acc.R, acc.t, ts[0].inverse().R, (ts[0] @ ts[1]).t):
        assert not arr.flags.writeable
    RigidTransform(acc.R, acc.t)                    # passes the full checks


def test_bad_transforms_and_lines_are_named():
    M = np.eye(4)
    M[3] = [0.0, 0.0, 1.0, 0.0]                      # projective, not rigid
    with pytest.raises(ValueError, match=r"last row is \[0, 0, 0, 1\], got \[0.0, 0.0, 1.0, 0.0\]"):
        RigidTransform.from_matrix(M)
    M = np.eye(4)
    M[3, 0] = 1e-3
    with pytest.raises(ValueError, match="last row"):
        RigidTransform.from_matrix(M)
    with pytest.raises(ValueError, match="complex"):
        RigidTransform.from_matrix(np.eye(4) + 0j)
    with pytest.raises(ValueError, match="t has complex values"):
        RigidTransform(np.eye(3), [1 + 2j, 0.0, 0.0])
    with pytest.raises(ValueError, match="translation up to 1e\\+300 mm"):
        RigidTransform(np.eye(3), [1e300, 0.0, 0.0])
    with pytest.raises(ValueError, match="Q: contains NaN"):
        cayley_from_matrix(np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="Q: not a proper rotation"):
        cayley_from_matrix(2 * np.eye(3))
    o = np.zeros((4, 3))
    d = np.tile([0.0, 0.0, 1.0], (4, 1))
    with pytest.raises(ValueError, match="one line per point"):
        point_line_distances(np.zeros((3, 3)), o, d)
    with pytest.raises(ValueError, match="no lines given"):
        closest_point_to_lines(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"weights must be \(4,\)"):
        closest_point_to_lines(o + np.eye(4, 3), np.tile([0.0, 0.6, 0.8], (4, 1)), [1.0, 2.0])


def test_small_entry_points_name_their_bad_argument():
    """A bad-input review (2026-11-27) found these ending in a KeyError, an AttributeError, a
    numpy core-dimension error, 'cannot convert float NaN to integer', an OpenCV assertion
    or a 2-point 'contour': each now names the argument and what was expected."""
    from reglib.contours import resample_polygon
    from reglib.markers import detect_markers
    from reglib.pipeline import xray_contours
    from reglib.surface import surface_from_contours

    with pytest.raises(ValueError, match=r"from_dict: .* missing \['t'\]"):
        RigidTransform.from_dict({"R": np.eye(3)})
    with pytest.raises(ValueError, match="from_rotation: rotation: expected a scipy"):
        RigidTransform.from_rotation(None)
    with pytest.raises(ValueError, match=r"apply_vectors: vectors: expected \(N, 3\)"):
        RigidTransform(np.eye(3), np.zeros(3)).apply_vectors(np.ones((3, 2)))
    with pytest.raises(ValueError, match="points_xy: the polygon holds NaN"):
        resample_polygon([[0.0, 0.0], [np.nan, 1.0], [1.0, 1.0]], 1.0)
    with pytest.raises(ValueError, match="at least 3 x 3 px, got \\(0, 0\\)"):
        detect_markers(np.zeros((0, 0)), np.zeros((0, 0)))
    with pytest.raises(ValueError, match="previous: values up to 1e\\+300"):  # float32: inf
        detect_markers(np.full((20, 20), 1e300), np.full((20, 20), 1e300))
    with pytest.raises(ValueError, match="xray_contours: pixel_mm .* must lie in"):
        xray_contours("v", np.zeros((64, 64)), {}, pixel_mm=1e-12)
    ring = [np.c_[10 * np.cos(t), 10 * np.sin(t), np.full_like(t, z)]
            for z in (0.0, 2.0) for t in [np.linspace(0, 2 * np.pi, 24, endpoint=False)]]
    with pytest.raises(ValueError, match="simplify_tol_mm: expected a number of mm"):
        surface_from_contours([[c] for c in ring], simplify_tol_mm="0.1")
    assert surface_from_contours([[c] for c in ring]).faces.shape[1] == 3
    from reglib.contours import gradient_potential, refine_subpixel

    img = np.zeros((32, 32))
    img[8:24, 8:24] = 100.0
    bad = img.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="gradient_potential: image holds NaN"):
        gradient_potential(bad, 1.0)
    square = np.array([[8.0, 8.0], [23.0, 8.0], [23.0, 23.0], [8.0, 23.0]])
    pot = gradient_potential(img, 1.0)
    assert refine_subpixel(pot, square).shape == (4, 2)
    with pytest.raises(ValueError, match="contour_xy: expected .* with NaN or inf"):
        refine_subpixel(pot, np.vstack([square, [np.nan, 1.0]]))


def test_robust_scale_is_the_mad_over_its_normal_factor_and_nan_for_nothing():
    """``median(|r|) / 0.6745``: about 1 on many standard normal residuals; no residuals give
    NaN without numpy's "mean of empty slice" warning (a bad-input review)."""
    import warnings

    from reglib.geometry import robust_scale

    r = np.random.default_rng(3).normal(0.0, 2.0, 20000)
    assert robust_scale(r) == pytest.approx(2.0, rel=0.03)
    assert robust_scale([-3.0, 1.0, 2.0]) == pytest.approx(2.0 / 0.6745, rel=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(robust_scale([]))


def test_a_rotation_just_past_its_rounding_limit_does_not_read_as_the_limit():
    """h75: a start scaled by 1.0005 was refused with "|R^T R - I| = 0.001, at most
    0.001"; the figure now shows the digits that set it past the limit."""
    from reglib.geometry import ROUNDED_ROTATION_TOL, as_rigid_transform

    m = np.eye(4)
    m[:3, :3] *= 1.0005
    with pytest.raises(ValueError, match=r"\|R\^T R - I\| = 0\.001000\d*, at most 0\.001,"):
        as_rigid_transform(m, "initial")
    m[:3, :3] = np.eye(3) * 1.1
    with pytest.raises(ValueError, match=r"\|R\^T R - I\| = 0\.21, at most 0\.001,"):
        as_rigid_transform(m, "initial")
    assert ROUNDED_ROTATION_TOL == 1e-3
