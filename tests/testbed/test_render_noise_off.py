"""Mutation audit 3: with fluoroscope.noise = false, a rendered frame carries no noise at
all, the camera's (video_noise_u8) included: two seeds give the same 8-bit image. Adding
the camera noise regardless of `noise` passed the suite."""
import numpy as np

from testbed.fluoroscope import FluoroscopeSpec, ViewSpec, make_carm, render


def test_noise_off_means_no_camera_noise_either():
    f = FluoroscopeSpec(noise=False, width_px=128, height_px=128)
    assert f.video_noise_u8 > 0
    carm = make_carm(f, ViewSpec(name="ap", isocenter_mm=(800.0, 0.0, 200.0)))
    a = render(carm, [], fluoro=f, rng=1).image_u8
    b = render(carm, [], fluoro=f, rng=2).image_u8
    assert np.array_equal(a, b), int(np.abs(a.astype(int) - b).max())
    # with noise on, the seeds differ
    g = f.model_copy(update={"noise": True})
    c = render(carm, [], fluoro=g, rng=1).image_u8
    d = render(carm, [], fluoro=g, rng=2).image_u8
    assert not np.array_equal(c, d)
