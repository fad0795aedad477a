"""Error budget: where the error at the pins comes from.

The Table II cases of one simulated ``experiment2`` case, registered with the estimated
inputs, then with one input replaced by its truth at a time (true calibration: the true
pixel -> ray map; true surfaces: the phantom's femur over the scanned regions; true X-ray
contours: the femur's exact apparent contour), then with all three (what is left is the
registration itself: matching on apparent contours and the tessellation). The drop in error
when a stage is made perfect is the share of that stage.
"""

from __future__ import annotations

import pandas as pd

from studies.common import markdown_table
from studies.end_to_end import registration_rows, simulate_case, table2_starts
from studies.table2 import case_summary

TITLE = "error budget: pin errors with true calibration, surfaces or contours substituted"
DEFAULT_SCENE = "experiment2"
CONFIGS = ((), ("calibration",), ("surfaces",), ("contours",),
           ("calibration", "surfaces", "contours"))


def run(ctx) -> pd.DataFrame:
    case = simulate_case(ctx.scene, ctx.seed)
    starts = table2_starts(case, ctx.seed, quick=True)  # identity, 2 x 5 deg, 2 x 7 deg
    rows = []
    for oracle in CONFIGS:
        rows += registration_rows(case, starts, oracle=oracle)
    df = pd.DataFrame(rows)
    ctx.report("Case", case_summary(case))
    pe = df[df.metric == "pin_error"]
    t = pe.groupby("oracle")["value"].agg(["mean", "median", "max"]).reset_index()
    base = t.set_index("oracle").loc["none", "mean"]
    t["share of mean error removed"] = 1.0 - t["mean"] / base
    ctx.report("Pin errors (mm) by substituted truth",
               "Mean, median and max over the pins and the starts; `none` is the realistic "
               "pipeline, `calibration+contours+surfaces` leaves only the registration's own "
               "error.\n\n" + markdown_table(t, ".3f"))
    return df
