"""Figure of the image intensifier's distortion: one view rendered without and with
distortion, and the true displacement field (distorted minus undistorted position) at that
pose and at a second pose turned by ``--turn-deg`` (the S-distortion follows the Earth's
field, so the field changes with the pose).

Run: ``python -m studies.figures_fluoroscope [SCENE] [--view 0] [--out DIR] [--seed 0]``;
writes ``DIR/fluoroscope_distortion.png`` and ``DIR/fluoroscope_distortion.csv`` (the
displacement statistics the figure shows).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd


def distortion_figure(scene, view: int, out_dir: Path, *, seed: int = 0,
                      turn_deg: float = 40.0) -> Path:
    """Render the figure; returns the PNG's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from studies.bench.render import bench_world
    from testbed.fluoroscope import make_carm, render

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    bodies = bench_world(scene, rng)
    fluoro, vspec = scene.fluoroscope, scene.views[view]
    carm = make_carm(fluoro, vspec, distortion=True, view_index=view)
    turned = make_carm(fluoro, vspec.model_copy(
        update={"angular_deg": float(np.clip(vspec.angular_deg + turn_deg, -180, 180))}),
        distortion=True)
    plain = render(carm, bodies, fluoro=fluoro, rng=np.random.default_rng(seed),
                   distortion=False)
    dist = render(carm, bodies, fluoro=fluoro, rng=np.random.default_rng(seed))

    fig, ax = plt.subplots(2, 2, figsize=(12, 9.5))
    ax[0, 0].imshow(plain.image_u8, cmap="gray", vmin=0, vmax=255)
    ax[0, 0].set_title(f"{vspec.name}: without distortion (ideal pinhole)")
    ax[0, 1].imshow(dist.image_u8, cmap="gray", vmin=0, vmax=255)
    ax[0, 1].set_title("with the intensifier's distortion")
    rows = []
    for a, c, label in ((ax[1, 0], carm, vspec.name),
                        (ax[1, 1], turned, f"C-arm turned {turn_deg:g} deg (angular)")):
        disp = c.displacement_field()
        fov = c.fov_mask()
        mag = np.linalg.norm(disp, axis=-1)
        shown = np.where(fov, mag, np.nan)
        im = a.imshow(shown, cmap="viridis", vmin=0, vmax=np.nanmax(shown))
        step = 32
        yy, xx = np.mgrid[step // 2:c.height_px:step, step // 2:c.width_px:step]
        keep = fov[yy, xx]
        a.quiver(xx[keep], yy[keep], disp[yy, xx, 0][keep], disp[yy, xx, 1][keep],
                 color="white", angles="xy", scale_units="xy", scale=0.1, width=0.003)
        a.set_title(f"displacement (px, arrows x10): {label}")
        fig.colorbar(im, ax=a, fraction=0.035, label="|distorted - undistorted| (px)")
        rows.append({"pose": label, "max_px": float(mag[fov].max()),
                     "median_px": float(np.median(mag[fov])),
                     "rotation_edge_deg": float(np.degrees(c.distortion.rotation_edge_rad)),
                     "shift_x_px": c.distortion.shift_px[0],
                     "shift_y_px": c.distortion.shift_px[1]})
    for a in ax.ravel():
        a.set_xlabel("x (px)")
        a.set_ylabel("y (px)")
    fig.tight_layout()
    png = out_dir / "fluoroscope_distortion.png"
    fig.savefig(png, dpi=90)
    plt.close(fig)
    pd.DataFrame(rows).to_csv(out_dir / "fluoroscope_distortion.csv", index=False)
    return png


def main(argv=None) -> int:
    from testbed.scene import find_scene, load_scene

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="experiment2")
    p.add_argument("--view", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("out/figures"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--turn-deg", type=float, default=40.0)
    a = p.parse_args(argv)
    scene = load_scene(find_scene(a.scene))
    png = distortion_figure(scene, a.view, a.out, seed=a.seed, turn_deg=a.turn_deg)
    print(f"wrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
