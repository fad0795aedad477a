"""The C-arm fluoroscope with an image intensifier. (Issue 4 fills this module.)"""

from __future__ import annotations

from testbed.spec import Positive, Spec


class FluoroscopeSpec(Spec):
    """``[fluoroscope]``: the C-arm and its image intensifier."""

    source_to_image_mm: Positive = 1000.0


class ViewSpec(Spec):
    """``[[views]]``: one C-arm pose."""

    name: str = "view"
