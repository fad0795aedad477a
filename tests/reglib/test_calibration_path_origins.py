"""Mutation audit 3: Calibration.paths documents origins on the NEAR plane (the source
side). Nothing checked it: origins on the far plane passed the whole suite."""
import numpy as np

from reglib.calibration import Calibration
from reglib.tps import ThinPlateSpline


def _calibration():
    gx, gy = np.meshgrid(np.linspace(0, 500, 6), np.linspace(0, 500, 6))
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    # a point source at (0, 0, -1000) mm: the near plane z = 300, the far plane z = 500
    src = np.array([250.0 * 0.4, 250.0 * 0.4, -1000.0])
    far = np.column_stack([xy * 0.4, np.full(len(xy), 500.0)])
    near = src + (far - src) * (1300.0 / 1500.0)
    return (Calibration("v", ThinPlateSpline.fit(xy, near), ThinPlateSpline.fit(xy, far)),
            xy, near, far, src)


def test_path_origins_lie_on_the_near_plane_and_point_to_the_far_plane():
    cal, xy, near, far, src = _calibration()
    o, d = cal.paths(xy)
    np.testing.assert_allclose(o, cal.near(xy), atol=1e-9)
    np.testing.assert_allclose(o[:, 2], 300.0, atol=0.05)
    # directed from near to far (away from the source)
    assert np.all(np.sum((far - o) * d, axis=1) > 0)
    np.testing.assert_allclose(cal.center_of_perspective(xy), src, atol=0.5)
