"""Base of every scene section model (kept apart so that section modules can import it)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Spec", "Vec2", "Vec3", "Positive", "NonNegative"]


class Spec(BaseModel):
    """A scene section: frozen, strict types (no str->float coercion), unknown keys rejected.

    Put units in field names (``_mm``, ``_deg``, ``_px``, ``_s``) and state the default.
    Raise ``ValueError`` in validators; the scene loader turns it into a ``SceneError``
    naming the file and the field.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
