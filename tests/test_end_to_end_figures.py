"""The shipped runs' end figures, pinned: a change detector for the whole chain.

`testbed run` on the shipped scenes gives the same mTRE to the last bit on every x86-64
machine with AVX2 (studies.numerics pins the numeric environment). A third mutation audit
found five changes of the simulated world or the method that moved these figures by
0.03-0.13 mm with every other test passing (one distortion drift for every view, the
S-distortion's shift reversed, sweep frames differenced against the first, a resampled
contour repeating its start, the pins nested in the wrong body). A deliberate change that
moves them re-measures them here and says why in its commit; the tolerance leaves room
for a machine's last digits only.
"""

import pytest

from studies.end_to_end import run_case
from testbed.scene import find_scene, load_scene

#: scene -> (mTRE mm of `testbed run SCENE --json` at the scene's seed, accepted), measured
#: on 2026-11-27 (dab4b29); re-measured the same day when every error source was given a
#: random stream of its own (CT streaks and noise, the robot's four sources, each frame's
#: quanta and camera): before, 0.1995360832552225 and 0.3697306833885958 mm; and again
#: when the CT operator's clicks took a stream per slice (0.17743297781137793 and
#: 0.3625819890505408 mm before); and on 2026-11-28 when the estimate's coarse stage took
#: 5 inner iterations of its pose solve instead of 20 (reglib.pipeline.COARSE_STAGE;
#: 0.24976294256396078 and 0.38217079219609945 mm before); and on 2026-11-29 when the CT
#: surfaces' simplification stopped measuring points the tiling left unused (experiment2's
#: distal surface 12195 -> 3766 triangles; the ideal profile's has none and is unchanged;
#: 0.38215709859776825 mm before); and on 2026-11-29 when the CT operator clicked anew where
#: reused clicks lay off the bone (testbed.operator, ct_reclick_off_px: experiment2's
#: lateral condyle had been outlined as a sliver over 3 mm; the ideal profile clicks every
#: slice and is unchanged; 0.3832782431001747 mm before; 0.46067908056422785 mm with a first
#: version of the rule, which judged the plain distance and the reuse going up alone); and
#: on 2026-11-29 (later) when reglib drew again a CT slice's contours that strayed more than
#: 3 mm from both neighbours' (reglib.contours.DISAGREEMENT_MM: experiment2's proximal slice
#: at z = 407.4 mm had its trochanter lobe cut off; the ideal profile's contours at its seed
#: all agree;
#: 0.5165422348059007 mm before)
PINNED = {"experiment2-ideal": (0.24976284732175802, True),
          "experiment2": (0.460944190159504, True)}
TOL_MM = 0.002


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PINNED))
def test_the_shipped_runs_end_where_they_were_measured(name):
    scene = load_scene(find_scene(name))
    result, *_ = run_case(scene, seed=scene.scene.seed)
    mtre, accepted = PINNED[name]
    assert result["accepted"] is accepted
    assert result["mtre_mm"] == pytest.approx(mtre, abs=TOL_MM), (
        f"{name}: mTRE {result['mtre_mm']!r} mm, pinned {mtre!r}: a change of the world or "
        "the method moved the end figure; if deliberate, re-measure and update PINNED")
