"""Benchmark of the two-plane TPS calibration: fit, and the X-ray path map of a whole view.

Instance: a C-arm view of the testbed (``testbed.fluoroscope``, distortion on), a near and a
far plane at the default sweep's fractions of the source-to-image distance
(``testbed.robot.SweepSpec``), a grid of markers in each
(``--rows`` x ``--beads`` per plane, those inside the field kept) projected exactly. Timed:

- ``fit``: the two thin-plate splines (``reglib.calibration.calibrate``);
- ``path_map``: the X-ray path of every pixel of the 640 x 480 view
  (``Calibration.path_map``: two vectorised TPS evaluations, a subtraction and a
  normalisation);
- ``rbf_eval``: one plain ``scipy.interpolate.RBFInterpolator`` evaluation (three outputs)
  of the near plane's spline on the same pixels (``path_map`` needs two such);
- ``svd_fit`` and ``svd_path_map``: the paper's direct SVD solve and a plain numpy
  evaluation (``tps_fit_svd`` / ``tps_evaluate``, in chunks), the reference.

The validator: the largest difference between the two path maps (mm at the isocenter
depth) and the largest distance between calibrated and true paths there.

Run: ``python -m studies.bench.calibration [--rows 9] [--beads 8] [--repeat 3] [--out CSV]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from reglib.calibration import calibrate, tps_evaluate, tps_fit_svd
from reglib.markers import Markers


def make_instance(rows: int = 9, beads: int = 8):
    """A distorted view and exactly projected markers of two planes: ``(carm, markers)``."""
    from testbed.fluoroscope import FluoroscopeSpec, ViewSpec, make_carm
    from testbed.robot import SweepSpec

    carm = make_carm(FluoroscopeSpec(), ViewSpec(name="bench", isocenter_mm=(800, 0, 200)))
    R, src, ax = carm.carm2robot.R, carm.source_robot, carm.axis_robot
    frame, plane, bead, xy, robot = [], [], [], [], []
    f = 0
    sw = SweepSpec()
    for p, frac in enumerate((sw.near_fraction, sw.far_fraction)):
        radius = frac * carm.fov_radius_mm
        for y in np.linspace(-0.9, 0.9, rows) * radius:
            f += 1
            x = np.linspace(-0.95, 0.95, beads) * radius
            pts = src + frac * carm.sid_mm * ax + x[:, None] * R[:, 0] + y * R[:, 1]
            px = carm.project(pts)
            inside = carm.fov_rho(px) <= 0.97
            frame.append(np.full(inside.sum(), f))
            plane.append(np.full(inside.sum(), p))
            bead.append(np.flatnonzero(inside))
            xy.append(px[inside])
            robot.append(pts[inside])
    m = Markers("bench", *(np.concatenate(a) for a in (frame, plane, bead, xy, robot)))
    return carm, m


def _best(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def _svd_paths(coefs, centres, xy, chunk=20000):
    a = np.empty((len(xy), 3))
    b = np.empty((len(xy), 3))
    for i in range(0, len(xy), chunk):
        a[i:i + chunk] = tps_evaluate(coefs[0], centres[0], xy[i:i + chunk])
        b[i:i + chunk] = tps_evaluate(coefs[1], centres[1], xy[i:i + chunk])
    d = b - a
    return a, d / np.linalg.norm(d, axis=1, keepdims=True)


def run_benchmark(rows: int = 9, beads: int = 8, repeat: int = 3,
                  smoothing: float = 0.01) -> pd.DataFrame:
    carm, m = make_instance(rows, beads)
    W, H = carm.width_px, carm.height_px
    grid = carm.pixel_grid().reshape(-1, 2)
    t_fit, cal = _best(lambda: calibrate(m, smoothing=smoothing), repeat)
    t_map, (o, d) = _best(lambda: cal.path_map(W, H), repeat)
    t_rbf, _ = _best(lambda: cal.near.interpolator(grid), repeat)
    sel = [m.plane == p for p in (0, 1)]
    t_svd_fit, coefs = _best(
        lambda: [tps_fit_svd(m.xy_px[s], m.robot[s], smoothing) for s in sel], repeat)
    centres = [m.xy_px[s] for s in sel]
    t_svd_map, (o2, d2) = _best(lambda: _svd_paths(coefs, centres, grid), max(1, repeat - 2))

    iso = carm.source_robot + 650.0 * carm.axis_robot
    ax = carm.axis_robot

    def cross(o, d):
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        return o + (((iso - o) @ ax) / (d @ ax))[:, None] * d

    fov = carm.fov_mask().ravel()
    agree = np.abs(cross(o, d) - cross(o2, d2)).max()
    to, td = carm.pixel_ray_map()
    err = np.linalg.norm(cross(o, d) - cross(to, td), axis=1)[fov]
    n = int(len(m.bead))
    rows_out = [
        ("fit", t_fit), ("path_map", t_map), ("rbf_eval", t_rbf),
        ("svd_fit", t_svd_fit), ("svd_path_map", t_svd_map),
    ]
    df = pd.DataFrame([dict(metric="time", stage=k, value=v, unit="s", markers=n,
                            pixels=W * H) for k, v in rows_out])
    extra = pd.DataFrame([
        dict(metric="svd_vs_rbf_max", value=agree, unit="mm", markers=n, pixels=W * H),
        dict(metric="ray_error_iso_max", value=err.max(), unit="mm", markers=n,
             pixels=W * H),
        dict(metric="ray_error_iso_mean", value=err.mean(), unit="mm", markers=n,
             pixels=W * H),
    ])
    return pd.concat([df, extra], ignore_index=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=9)
    p.add_argument("--beads", type=int, default=8)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--out", default=None, help="write the table as CSV")
    a = p.parse_args(argv)
    df = run_benchmark(a.rows, a.beads, a.repeat)
    from studies.common import markdown_table

    print(markdown_table(df.fillna("")))
    if a.out:
        df.to_csv(a.out, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
