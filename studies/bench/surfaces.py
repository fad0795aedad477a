"""Benchmark of the CT surface chain: ``python -m studies.bench.surfaces [--repeat N]``.

Prints the CPU time (``time.process_time``: one core, unaffected by other jobs sharing the
machine) of each stage for the default phantom and protocol (phantom, CT, contours,
tiling, simplification, per region) and the total of CT + both surfaces, the figure the
acceptance asks to stay under 10 s on one core.
"""

from __future__ import annotations

import os

# One core: no multi-threaded BLAS (set before numpy is imported).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from reglib.contours import contours_from_ct  # noqa: E402
from reglib.surface import surface_from_contours  # noqa: E402
from testbed.ct import CTSpec, scan  # noqa: E402
from testbed.operator import OperatorSpec, ct_clicks  # noqa: E402
from testbed.phantom import PhantomSpec, make_phantom  # noqa: E402


def bench(seed: int = 0, simplify_tol_mm: float = 0.3, click_every_mm: float = 6.0) -> dict:
    """One run; returns stage -> seconds (and triangle counts)."""
    rng = np.random.default_rng(seed)
    out = {}
    clock = time.process_time  # CPU time of this (single-threaded) process
    t = clock()
    ph = make_phantom(PhantomSpec())
    out["phantom"] = clock() - t
    t = clock()
    ct = scan(ph, CTSpec(), rng=rng)
    out["ct"] = clock() - t
    # The simulated user is not timed: it stands for a person clicking.
    user = ct_clicks(ct.volume_hu, ct.slice_z_mm, ct.regions, pixel_mm=ct.pixel_mm,
                     spec=OperatorSpec(ct_reclick_every_mm=click_every_mm), rng=rng)
    for region in ("proximal", "distal"):
        slices, clicks = [int(k) for k in user[region].slices], user[region].clicks
        t = clock()
        cs = contours_from_ct(ct.volume_hu, ct.slice2ct, slices, clicks)
        out[f"contours_{region}"] = clock() - t
        t = clock()
        surf = surface_from_contours(sorted(cs, key=lambda s: s.z_mm))
        out[f"tiling_{region}"] = clock() - t
        t = clock()
        simp = surface_from_contours(sorted(cs, key=lambda s: s.z_mm),
                                     simplify_tol_mm=simplify_tol_mm)
        # (tiles again the reduced contours and checks the distances: includes a tiling)
        out[f"simplification_{region}"] = clock() - t
        out[f"triangles_{region}"] = (surf.n_triangles, simp.n_triangles)
    out["total_ct_and_surfaces"] = sum(v for k, v in out.items()
                                       if k.split("_")[0] in ("ct", "contours", "tiling",
                                                              "simplification"))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    from studies.numerics import usable_cores

    print(f"CT surface chain, default phantom and clinical protocol ({usable_cores()} cores "
          "visible, "
          f"load average {os.getloadavg()[0]:.1f})")
    for r in range(args.repeat):
        res = bench(args.seed + r)
        for k, v in res.items():
            if k.startswith("triangles"):
                print(f"  {k:28s} {v[0]} tiled -> {v[1]} simplified")
            else:
                print(f"  {k:28s} {v:7.2f} s (CPU)")
        ok = res["total_ct_and_surfaces"] < 10.0
        print(f"  goal CT + both surfaces < 10 s: {'met' if ok else 'NOT met'}")


if __name__ == "__main__":
    main()
