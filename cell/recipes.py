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

    [types.bracket-l]              # a taught part type (run-cell part teach writes this)
    model = "models/bracket-l-1f2e3d4c5b6a.json"
    model_sha256 = "1f2e3d4c5b6a..."   # the model file's sha256: a file that does not match is refused
    height_mm = 3.0

The recipe's id is its file name without `.toml`. `RecipeBook` lists, loads, validates,
adds (written whole or not at all; a bad recipe is refused with what and where) and removes
them; the line service decides when one becomes the active recipe (only in Ready).
"""

from __future__ import annotations

import hashlib
import logging
import re
import tomllib
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from cell.atomicfile import write_bytes_atomic, write_text_atomic
from cell.config import CellConfig
from cell.core.parts import BUILT_IN_PARTS, NAME_PATTERN, PartClass, PartRegistry
from cell.core.records import RecipeInfo
from cell.errors import CellError
from cell.run_config import ClassPlan
from cell.vision.config import PartsConfig
from cell.vision.shapes import ShapeModel, ShapeModelError, load_model, sha256_of
from drivers.config import Strict

PickedClass = Literal["bolt", "nut"]
RECIPE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MAX_RECIPE_BYTES = 64 * 1024
SUFFIX = ".toml"
log = logging.getLogger(__name__)


class RecipeError(CellError):
    """A recipe that cannot be used: unknown, unreadable, invalid, or a name that is not allowed."""


MODEL_PATH = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+)*$")


class TaughtType(Strict):
    """A part type taught from example images: its shape model file, named by its hash."""

    model: str = Field(
        description="the shape model file (JSON), relative to the recipe's folder; written by `run-cell part teach`"
    )
    model_sha256: str = Field(
        pattern=r"^[0-9a-f]{64}$", description="the model file's sha256; a file that does not match is refused"
    )
    height_mm: float = Field(gt=0, le=200, description="the part's height above the table (its thickness lying)")
    bin_robot_mm: tuple[float, float, float] | None = Field(
        None,
        description="where the gripper opens over this type's bin, robot frame; none: found and counted, not picked",
    )
    pick_above_table_mm: float | None = Field(
        None, ge=0, le=100, description="tool point height when the jaws close; none: half the part's height"
    )
    approach_above_table_mm: float = Field(40.0, gt=0, le=300, description="height of moves above the table")

    @model_validator(mode="after")
    def _relative(self) -> TaughtType:
        if not MODEL_PATH.match(self.model) or ".." in self.model.split("/"):
            raise ValueError(f"model {self.model!r}: a relative path inside the recipe's folder (no '..')")
        if self.pick_above_table_mm is not None and self.pick_above_table_mm >= self.height_mm:
            raise ValueError(
                f"pick_above_table_mm = {self.pick_above_table_mm:g} mm: the jaws would close above the part "
                f"({self.height_mm:g} mm high); give a height below it"
            )
        if self.approach_above_table_mm <= self.height_mm:
            raise ValueError(
                f"approach_above_table_mm = {self.approach_above_table_mm:g} mm: not above the part "
                f"({self.height_mm:g} mm high)"
            )
        return self

    def plan(self) -> ClassPlan | None:
        """How the planner picks this type (jaws closed along its taught grip), or None without a bin."""
        if self.bin_robot_mm is None:
            return None
        pick = self.height_mm / 2 if self.pick_above_table_mm is None else self.pick_above_table_mm
        return ClassPlan(
            pick_above_table_mm=pick,
            approach_above_table_mm=self.approach_above_table_mm,
            jaw_across_axis=False,
            bin_robot_mm=self.bin_robot_mm,
        )


class Recipe(Strict):
    """What a recipe file holds (see the module's docstring)."""

    description: str = Field("", max_length=500)
    products: list[str] = Field(default_factory=list, description="product ids this recipe serves")
    pick_order: Literal["nearest", "rows", "as-found"] = Field(
        "nearest", description="nearest to the gripper first; rows: table Y then X; as-found: vision's order"
    )
    pick: dict[PickedClass, ClassPlan] = Field(
        description="the classes this recipe picks, each with its bin and moves; classes not listed stay on the table"
    )
    parts: PartsConfig = Field(
        PartsConfig(), description="vision limits: sizes that tell bolts, nuts and the rest apart"
    )

    types: dict[str, TaughtType] = Field(
        default_factory=dict, description="part types taught from images (`run-cell part teach`), by name"
    )

    @model_validator(mode="before")
    @classmethod
    def _taught_only(cls, data: object) -> object:
        """A recipe of taught types alone (as `run-cell part teach` creates one) needs no [pick]."""
        if isinstance(data, dict) and data.get("types") and "pick" not in data:
            return {**data, "pick": {}}
        return data

    @model_validator(mode="after")
    def _picks_something(self) -> Recipe:
        if not self.pick and not self.types:
            raise ValueError("pick: name at least one class to pick ([pick.bolt] or [pick.nut]) or teach a type")
        for name in self.types:
            if not NAME_PATTERN.match(name) or name in BUILT_IN_PARTS or name == "unknown":
                raise ValueError(
                    f"types.{name}: a taught type's name is 1-32 lower-case letters, digits, - and _, starting with a "
                    "letter, and not bolt, nut or unknown"
                )
        return self

    @property
    def classes(self) -> frozenset[str]:
        """The classes this recipe picks: its [pick] classes and its taught types that have a bin."""
        return frozenset(self.pick) | frozenset(self.taught_plans())

    def taught_plans(self) -> dict[str, ClassPlan]:
        """The taught types the cell picks (those with a bin), each with its moves."""
        return {name: plan for name, t in self.types.items() if (plan := t.plan()) is not None}

    def registry(self) -> PartRegistry:
        """The built-in part classes and this recipe's taught types after them (counted by name)."""
        return BUILT_IN_PARTS.with_classes(taught_class(name) for name in self.types)

    def apply(self, config: CellConfig) -> CellConfig:
        """`config` with this recipe's handling and vision limits in force (a class the recipe
        does not pick keeps the config's plan; `classes` says which are picked)."""
        planning = config.planning.model_copy(
            update={"pick_order": self.pick_order, **{cls: plan for cls, plan in self.pick.items()}}
        )
        return config.model_copy(update={"planning": planning, "parts": self.parts})


def taught_class(name: str) -> PartClass:
    """A taught type as a part class: its counter is named by its name plus s (PickedBracketLs)."""
    plural = name if len(name) >= 32 or name.endswith("s") else name + "s"
    return PartClass(name, plural)


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


def load_shape_models(recipe: Recipe, folder: Path) -> list[ShapeModel]:
    """The recipe's taught types' models, each file checked against the hash the recipe names."""
    models = []
    for name, t in recipe.types.items():
        model = load_model(Path(folder) / t.model, t.model_sha256)
        if model.name != name:
            raise RecipeError(f"{Path(folder) / t.model}: a model of {model.name!r}, but the recipe names it {name!r}")
        if abs(model.height_mm - t.height_mm) > 1e-6:
            raise RecipeError(
                f"types.{name}.height_mm = {t.height_mm:g}, but its model was taught at {model.height_mm:g} mm",
                hint=f"teach {name!r} again at the height it has (run-cell part teach --height-mm)",
            )
        models.append(model)
    return models


def load_recipe_file(path: Path) -> tuple[Recipe, list[ShapeModel]]:
    """A recipe file and its taught types' models (RecipeError, ShapeModelError saying what)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecipeError(f"{path}: recipe not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise RecipeError(f"{path}: cannot read recipe: {e}") from None
    recipe = parse_recipe(text, str(path))
    return recipe, load_shape_models(recipe, path.parent)


def _section_range(lines: list[str], name: str) -> tuple[int, int] | None:
    """Lines [start, end) of the `[types.NAME]` table and its sub-tables, if the text has one."""
    header = re.compile(r"^\s*\[\s*types\s*\.\s*\"?" + re.escape(name) + r"\"?\s*(\.|\])")
    start = next((i for i, line in enumerate(lines) if header.match(line)), None)
    if start is None:
        return None
    end = start + 1
    while end < len(lines) and not (lines[end].lstrip().startswith("[") and not header.match(lines[end])):
        end += 1
    return start, end


def add_taught_type(path: Path, model: ShapeModel) -> tuple[Path, str]:
    """Write the model file beside the recipe (models/NAME-<sha>.json) and name it in the recipe
    (`[types.NAME]`, replacing a former teaching of that name; the recipe created if absent). Both
    written whole or not at all, the recipe validated first. Returns the model's path and sha256."""
    path = Path(path)
    data = model.to_json().encode("utf-8")
    sha = sha256_of(data)
    relative = f"models/{model.name}-{sha[:12]}.json"
    section = [
        f"[types.{model.name}]",
        f'model = "{relative}"',
        f'model_sha256 = "{sha}"',
        f"height_mm = {round(model.height_mm, 4)!r}",  # as the model file has it
    ]
    if path.exists():
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise RecipeError(f"{path}: cannot read recipe: {e}") from None
        parse_recipe(text, str(path))  # a broken recipe is not made worse
        lines = text.splitlines()
        where = _section_range(lines, model.name)
        if where is None:
            lines = [*lines, "", *section] if lines else section
        else:
            lines = [*lines[: where[0]], *section, "", *lines[where[1] :]]
        new = "\n".join(lines).rstrip("\n") + "\n"
    else:
        new = 'description = "taught part types"\n\n' + "\n".join(section) + "\n"
    parse_recipe(new, str(path))
    target = path.parent / relative
    target.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(target, data)
    write_text_atomic(path, new)
    return target, sha


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
        """The recipe, validated, its taught types' model files checked against their hashes."""
        return self.load_with_shapes(recipe_id)[0]

    def load_with_shapes(self, recipe_id: str) -> tuple[Recipe, tuple[ShapeModel, ...]]:
        """The recipe, validated, and its taught types' shape models (each checked against its hash)."""
        path = self.path(recipe_id)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise RecipeError(f"recipe {recipe_id!r} not found in {self.folder}") from None
        except (OSError, UnicodeDecodeError) as e:
            raise RecipeError(f"{path}: cannot read recipe: {e}") from None
        recipe = parse_recipe(text, str(path))
        return recipe, tuple(load_shape_models(recipe, self.folder))

    def taught_parts(self) -> PartRegistry:
        """The built-in part classes and the taught types of every valid recipe in the folder (each
        name once): the counters an interface made at start-up offers, whichever recipe is prepared."""
        parts = BUILT_IN_PARTS
        for info in self.list():
            if info.error:
                continue
            try:
                parts = parts.with_classes(self.load(info.recipe_id).registry())
            except (RecipeError, ShapeModelError, ValueError) as e:
                log.warning("recipe %s: its taught types are not counted: %s", info.recipe_id, e)
        return parts

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
