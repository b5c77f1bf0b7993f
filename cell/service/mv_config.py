"""`[service.machine_vision]`: the OPC 40100-1 Machine Vision model's settings: the cell's
identity (DI Identification), where recipes live, how many results are kept for clients
that were away, and where the address space cache goes."""

from __future__ import annotations

from pathlib import Path

from pydantic import Field

from cell.core.events import Role
from drivers.config import Strict


class MachineVisionConfig(Strict):
    serial_number: str = Field(
        "", max_length=64, description="this cell's serial number (DI Identification SerialNumber); empty: unset"
    )
    manufacturer: str = Field("pick-cell", min_length=1, max_length=64, description="DI Identification Manufacturer")
    asset_id: str = Field("", max_length=64, description="the plant's own name or tag for this cell (DI AssetId)")
    client_role: Role = Field(
        Role.ENGINEER,
        description="the most an OPC UA client may do: the anonymous client on loopback (no users) acts with "
        "this role, a logged-in user with their own role capped at it; engineer may also switch and add "
        "recipes; operator only runs jobs; viewer only watches (and may Halt)",
    )
    recipes_dir: Path = Field(Path("recipes"), description="recipe TOML files, one per recipe (cell.recipes)")
    results_kept: int = Field(
        1000,
        ge=1,
        le=1_000_000,
        description="the newest results kept in memory for GetResultById / GetResultListFiltered (older ones: "
        "GetResultById from the history store); the memory they take grows until this many are kept",
    )
    recipes_max: int = Field(
        200,
        ge=1,
        le=10_000,
        description="recipes in RecipeManagement's Recipes at most (files and recipes being written together); "
        "AddRecipe past it is refused with BadTooManyOperations",
    )
    recipe_transfers_max: int = Field(
        4,
        ge=1,
        le=64,
        description="recipes being written through their Handle at once (AddRecipe until Close; each holds up to "
        "64 KiB); AddRecipe past it is refused with BadTooManyOperations",
    )
    recipe_transfer_timeout_s: float = Field(
        60.0,
        gt=0,
        le=3600,
        description="a recipe transfer with no call on its Handle for this long is dropped, with its node",
    )
    result_lookups_max: int = Field(
        4,
        ge=1,
        le=64,
        description="GetResultById lookups in the history store at once (one runs, the others wait); past it a "
        "result not in memory is answered BadResourceUnavailable at once",
    )
    result_lookup_timeout_s: float = Field(
        5.0,
        gt=0,
        le=60,
        description="the longest GetResultById waits for the history store's answer about a result no longer in "
        "memory (BadResourceUnavailable after it); other clients are served meanwhile",
    )
    model_cache: bool = Field(True, description="cache the address space built from the NodeSets (faster starts)")
    model_cache_dir: Path | None = Field(
        None,
        description="where that cache goes; default $XDG_CACHE_HOME/pick-cell/opcua (~/.cache/...), under systemd "
        "$CACHE_DIRECTORY/opcua (configs/pick-cell.service: /var/cache/pick-cell/opcua)",
    )
