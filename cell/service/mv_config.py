"""`[service.machine_vision]`: the OPC 40100-1 Machine Vision model's settings: the cell's
identity (DI Identification), where recipes live, how many results are kept for clients
that were away, and where the address space cache goes."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from cell.events import Role
from drivers.config import Strict


class MachineVisionConfig(Strict):
    serial_number: str = Field(
        "", max_length=64, description="this cell's serial number (DI Identification SerialNumber); empty: unset"
    )
    manufacturer: str = Field("pick-cell", min_length=1, max_length=64, description="DI Identification Manufacturer")
    asset_id: str = Field("", max_length=64, description="the plant's own name or tag for this cell (DI AssetId)")
    client_role: Role = Field(
        Role.ENGINEER,
        description="the role an OPC UA client acts with (the configured user, or anyone on loopback): "
        "engineer may also switch and add recipes; operator only runs jobs",
    )
    recipes_dir: Path = Field(Path("recipes"), description="recipe TOML files, one per recipe (cell.recipes)")
    results_kept: int = Field(
        10000, ge=1, le=1_000_000, description="results kept in memory for GetResultById / GetResultListFiltered"
    )
    model_cache: bool = Field(True, description="cache the address space built from the NodeSets (faster starts)")
    model_cache_dir: Path | None = Field(
        None, description="where that cache goes; default $XDG_CACHE_HOME/pick-cell/opcua (~/.cache/...)"
    )
