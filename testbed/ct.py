"""The CT scanner simulation. (Issue 3 fills this module.)"""

from __future__ import annotations

from testbed.spec import Positive, Spec


class CTSpec(Spec):
    """``[ct]``: the CT scanner and its slice schedule."""

    pixel_mm: Positive = 0.8
