"""The one base of every config model, driver and application alike (cell's config reuses it)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    """Unknown keys are errors (a typo names itself); assignments are validated like loading;
    NaN and inf are refused (NaN passes every bound: `x > 0` and `x <= 10` are both false)."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)
