"""The one base of every config model, driver and application alike (cell's config reuses it)."""
from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    """Unknown keys are errors (a typo names itself); assignments are validated like loading."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)
