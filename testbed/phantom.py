"""The simulated patient: a procedural femur with pins and a soft-tissue envelope.

(Issue 3 fills this module; the scene section is declared here so scenes can name it.)
"""

from __future__ import annotations

from typing import Literal

from testbed.spec import Spec


class PhantomSpec(Spec):
    """``[phantom]``: the femur phantom."""

    side: Literal["left", "right"] = "right"
