"""Mutation audit 3: untangle_contour keeps the lobe of larger |area| whatever the
orientation (comparing signed areas passed: the existing figure-eight has its big lobe
counter-clockwise); resample_polygon of a closed polygon does not repeat its first point
(only a slow regression test noticed, through the pins: 0.1995 -> 0.2664 mm mTRE)."""
import numpy as np
import pytest

from reglib.contours import resample_polygon, untangle_contour


@pytest.mark.parametrize("clockwise_big", [False, True])
def test_untangle_keeps_the_big_lobe_in_either_orientation(clockwise_big):
    t = np.linspace(0, 2 * np.pi, 80, endpoint=False)
    big = np.column_stack([10 + 10 * np.cos(t), 10 * np.sin(t)])
    small = np.column_stack([-3 - 3 * np.cos(t), 3 * np.sin(t)])[::-1]
    eight = np.vstack([big[1:], small[1:]])
    if clockwise_big:
        eight = eight[::-1]
    kept = untangle_contour(eight)
    assert kept[:, 0].min() > -0.5 and abs(kept[:, 0].max() - 20) < 0.1


def test_closed_resampling_is_even_and_does_not_repeat_the_start():
    t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    circle = np.column_stack([50 * np.cos(t), 50 * np.sin(t)])
    r = resample_polygon(circle, 2.0, closed=True)
    gaps = np.linalg.norm(np.diff(np.vstack([r, r[:1]]), axis=0), axis=1)
    assert gaps.min() > 0.95 * gaps.max(), (gaps.min(), gaps.max())
    # open: both ends kept
    o = resample_polygon(circle[:200], 2.0, closed=False)
    np.testing.assert_allclose(o[[0, -1]], circle[[0, 199]], atol=1e-12)
