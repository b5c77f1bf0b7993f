"""Recipes: a named part catalogue and how its parts are handled, one TOML file each.

A recipe says which classes of part the cell picks (and so which it leaves on the table),
where each goes (its bin), how it is picked (pick and approach heights, jaws across the
axis), in which order, and the vision limits that tell the classes apart. Every section is
one of the cell's own config models (`ClassPlan`, `PartsConfig`), so a recipe is validated
exactly as a config file is: unknown keys, units out of range, NaN are errors naming the key.

    # recipes/bolts-only.toml
    description = "M5-M8 bolts into the left bin; nuts stay"
    products = ["kit-17"]          # the product ids this recipe serves (OPC 40100-1 LinkedProducts)
    pick_order = "nearest"

    [pick.bolt]
    pick_above_table_mm = 3.5
    jaw_across_axis = true
    bin_robot_mm = [-200.0, 60.0, 60.0]

    [parts.bolt]                   # vision limits (PartsConfig), defaults where not given
    length_mm = [13.0, 56.0]

The recipe's id is its file name without `.toml`. `RecipeBook` lists, loads, validates,
adds (written whole or not at all; a bad recipe is refused with what and where) and removes
them; the line service decides when one becomes the active recipe (only in Ready).
"""

from __future__ import annotations

import hashlib
import re
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from cell.atomicfile import write_text_atomic
from cell.config import CellConfig
from cell.core.records import RecipeInfo
from cell.errors import CellError
from cell.run_config import ClassPlan
from cell.vision.config import PartsConfig
from drivers.config import Strict

PartClass = Literal["bolt", "nut"]
RECIPE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MAX_RECIPE_BYTES = 64 * 1024
SUFFIX = ".toml"


class RecipeError(CellError):
    """A recipe that cannot be used: unknown, unreadable, invalid, or a name that is not allowed."""


class Recipe(Strict):
    """What a recipe file holds (see the module's docstring)."""

    description: str = Field("", max_length=500)
    products: list[str] = Field(default_factory=list, description="product ids this recipe serves")
    pick_order: Literal["nearest", "rows", "as-found"] = Field(
        "nearest", description="nearest to the gripper first; rows: table Y then X; as-found: vision's order"
    )
    pick: dict[PartClass, ClassPlan] = Field(
        description="the classes this recipe picks, each with its bin and moves; classes not listed stay on the table"
    )
    parts: PartsConfig = Field(
        PartsConfig(), description="vision limits: sizes that tell bolts, nuts and the rest apart"
    )

    @model_validator(mode="after")
    def _picks_something(self) -> Recipe:
        if not self.pick:
            raise ValueError("pick: name at least one class to pick ([pick.bolt] or [pick.nut])")
        return self

    @property
    def classes(self) -> frozenset[str]:
        return frozenset(self.pick)

    def apply(self, config: CellConfig) -> CellConfig:
        """`config` with this recipe's handling and vision limits in force (a class the recipe
        does not pick keeps the config's plan; `classes` says which are picked)."""
        planning = config.planning.model_copy(
            update={"pick_order": self.pick_order, **{cls: plan for cls, plan in self.pick.items()}}
        )
        return config.model_copy(update={"planning": planning, "parts": self.parts})


def parse_recipe(text: str, where: str) -> Recipe:
    """Validate a recipe's TOML text; RecipeError naming `where` and every bad key."""
    if len(text.encode("utf-8")) > MAX_RECIPE_BYTES:
        raise RecipeError(f"{where}: recipe larger than {MAX_RECIPE_BYTES // 1024} KiB")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(f"{where}: not valid TOML: {e}") from None
    try:
        return Recipe.model_validate(data)
    except ValidationError as e:
        raise RecipeError(f"{where}: invalid recipe: {_errors(e)}", hint="see docs/opcua-machinevision.md") from None


def _errors(err: ValidationError) -> str:
    out = []
    for e in err.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        out.append(f"{loc}: {e['msg'].removeprefix('Value error, ')}")
    return "; ".join(out)


def check_recipe_id(recipe_id: str) -> str:
    if not RECIPE_ID.match(recipe_id):
        raise RecipeError(
            f"recipe id {recipe_id!r} not allowed",
            hint="1-64 letters, digits, '_', '-', '.', starting with a letter or digit",
        )
    return recipe_id


class RecipeBook:
    """The recipe files in one folder. Thread-safe enough for one writer: every write is atomic."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def path(self, recipe_id: str) -> Path:
        return self.folder / f"{check_recipe_id(recipe_id)}{SUFFIX}"

    def list(self) -> list[RecipeInfo]:
        """Every `*.toml` in the folder, by id; invalid ones listed with their error."""
        if not self.folder.is_dir():
            return []
        return [self._info(p) for p in sorted(self.folder.glob(f"*{SUFFIX}")) if RECIPE_ID.match(p.stem)]

    def _info(self, path: Path) -> RecipeInfo:
        try:
            data = path.read_bytes()
            stat = path.stat()
        except OSError as e:
            return RecipeInfo(path.stem, path, "", datetime.fromtimestamp(0, UTC), (), f"cannot read: {e.strerror}")
        modified = datetime.fromtimestamp(stat.st_mtime, UTC)
        sha = hashlib.sha256(data).hexdigest()
        try:
            recipe = parse_recipe(data.decode("utf-8"), str(path))
        except (RecipeError, UnicodeDecodeError) as e:
            return RecipeInfo(path.stem, path, sha, modified, (), str(e))
        return RecipeInfo(path.stem, path, sha, modified, tuple(recipe.products))

    def info(self, recipe_id: str) -> RecipeInfo:
        path = self.path(recipe_id)
        if not path.is_file():
            raise RecipeError(f"recipe {recipe_id!r} not found in {self.folder}")
        return self._info(path)

    def sha256(self, recipe_id: str) -> str:
        """The recipe file's hash (OPC 40100-1's recipe Hash), without validating it; RecipeError if absent."""
        try:
            return hashlib.sha256(self.path(recipe_id).read_bytes()).hexdigest()
        except OSError as e:
            raise RecipeError(f"recipe {recipe_id!r} not found in {self.folder}: {e.strerror}") from None

    def load(self, recipe_id: str) -> Recipe:
        path = self.path(recipe_id)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise RecipeError(f"recipe {recipe_id!r} not found in {self.folder}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise RecipeError(f"{path}: cannot read recipe: {e}") from None
        return parse_recipe(text, str(path))

    def add(self, recipe_id: str, text: str) -> RecipeInfo:
        """Validate, then write whole. The same content again is accepted (nothing changes);
        other content under an existing id is refused: remove the old recipe first."""
        path = self.path(recipe_id)
        parse_recipe(text, f"recipe {recipe_id!r}")
        if path.exists():
            if path.read_bytes() == text.encode("utf-8"):
                return self._info(path)
            raise RecipeError(
                f"recipe {recipe_id!r} already exists in {self.folder} with other content",
                hint="remove it first, or add the new one under another id",
            )
        self.folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, text)
        return self._info(path)

    def remove(self, recipe_id: str) -> None:
        path = self.path(recipe_id)
        try:
            path.unlink()
        except FileNotFoundError:
            raise RecipeError(f"recipe {recipe_id!r} not found in {self.folder}") from None
        except OSError as e:
            raise RecipeError(f"{path}: cannot remove recipe: {e.strerror}") from None
