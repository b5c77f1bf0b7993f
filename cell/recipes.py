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
    class_no = 3                   # what a robot program is told (docs/robots.md); default: numbered from 3
    bin_robot_mm = [200.0, 160.0, 60.0]   # none: found, counted and left on the table

The recipe's id is its file name without `.toml`. `RecipeBook` lists, loads, validates,
adds (written whole or not at all; a bad recipe is refused with what and where) and removes
them; the line service decides when one becomes the active recipe (only in Ready).
"""

from __future__ import annotations

import hashlib
import logging
import math
import re
import tomllib
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationError, model_validator

from cell.atomicfile import write_bytes_atomic, write_text_atomic
from cell.config import CellConfig
from cell.core.parts import BUILT_IN_PARTS, NAME_PATTERN, PartClass, PartRegistry
from cell.core.records import RecipeInfo
from cell.errors import CellError, InputError
from cell.planning import BUILT_IN_CLASS_NO, workspace_violation
from cell.run_config import ClassPlan, PlanningConfig
from cell.vision.config import PartsConfig
from cell.vision.shapes import ShapeModel, ShapeModelError, load_model, sha256_of
from drivers.config import Strict

PickedClass = Literal["bolt", "nut"]
RECIPE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MAX_RECIPE_BYTES = 64 * 1024
TAUGHT_CLASS_NO_BASE = 3  # taught types without a class_no are numbered from here, in the recipe's order
MAX_CLASS_NO = 32767  # a robot's signed 16-bit register holds it (docs/robots.md, Modbus CLASS_NO)
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
    class_no: int | None = Field(
        None,
        ge=TAUGHT_CLASS_NO_BASE,
        le=MAX_CLASS_NO,
        description="the number a robot program is told for this type (docs/robots.md); none: numbered from "
        f"{TAUGHT_CLASS_NO_BASE} in the recipe's order (bolt is 1, nut 2); robot_server.class_numbers overrides it",
    )

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
        given: dict[int, str] = {}
        for name, t in self.types.items():
            if t.class_no is not None and t.class_no in given:
                raise ValueError(
                    f"types.{name}.class_no = {t.class_no}: {given[t.class_no]!r} has that number already; "
                    "give each type its own"
                )
            if t.class_no is not None:
                given[t.class_no] = name
        return self

    def class_numbers(self) -> dict[str, int]:
        """The class_no a robot program is told for each class (docs/robots.md): bolt 1, nut 2, each taught
        type its `class_no`, else the next number from TAUGHT_CLASS_NO_BASE not given to another, in order."""
        out = dict(BUILT_IN_CLASS_NO)
        taken = {t.class_no for t in self.types.values() if t.class_no is not None}
        n = TAUGHT_CLASS_NO_BASE
        for name, t in self.types.items():
            if t.class_no is not None:
                out[name] = t.class_no
                continue
            while n in taken:
                n += 1
            out[name], n = n, n + 1
        return out

    def unbinned(self) -> list[str]:
        """The taught types without a bin: found and counted, left on the table."""
        return [name for name, t in self.types.items() if t.bin_robot_mm is None]

    def unbinned_words(self, recipe: str) -> str | None:
        """What an operator is told once about the taught types without a bin, or None when all have one."""
        names = self.unbinned()
        if not names:
            return None
        which = ", ".join(names)
        verb = "has" if len(names) == 1 else "have"
        return (
            f"recipe {recipe}: {which} {verb} no bin: found and counted but left on the table "
            f"(give types.NAME.bin_robot_mm, or teach again with --bin-robot-mm X Y Z or --bin-of TYPE)"
        )

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


@dataclass(frozen=True)
class TaughtAdded:
    """What `add_taught_type` wrote: the model file, its hash, the type's bin and class_no, and the recipe's
    taught types left without a bin (this one among them when it has none)."""

    model_path: Path
    sha256: str
    bin_robot_mm: tuple[float, float, float] | None
    class_no: int
    unbinned: tuple[str, ...]

    def lines(self, name: str, recipe: str) -> list[str]:
        """What the teacher is told: where the type goes (or that it stays), its class_no."""
        if self.bin_robot_mm is None:
            where = f"{name}: no bin: found and counted, left on the table"
        else:
            where = f"{name}: into the bin at robot ({', '.join(f'{v:g}' for v in self.bin_robot_mm)}) mm"
        out = [f"{where}; the robot is told class_no {self.class_no}"]
        others = [n for n in self.unbinned if n != name]
        if others:
            verb = "has" if len(others) == 1 else "have"
            out.append(f"recipe {recipe}: {', '.join(others)} {verb} no bin either: left on the table")
        return out


def check_bin(where: str, bin_robot_mm: object, planning: PlanningConfig) -> tuple[float, float, float]:
    """A bin as three finite numbers (robot mm) inside the configured workspace and reach, or InputError."""
    try:
        x, y, z = (float(v) for v in bin_robot_mm)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise InputError(f"{where}: give the bin as three numbers X Y Z (robot mm)") from None
    if not all(math.isfinite(v) for v in (x, y, z)):
        raise InputError(f"{where} ({bin_robot_mm}): every coordinate a finite number of mm")
    if why := workspace_violation(planning.workspace, x, y, z):
        raise InputError(
            f"{where} ({x:g}, {y:g}, {z:g}) mm: {why}",
            hint="a bin the arm reaches (planning.workspace in the cell config), or none to teach now and place later",
        )
    return x, y, z


def bin_of(recipe: Recipe | None, planning: PlanningConfig, of: str) -> tuple[float, float, float]:
    """The bin another class of the recipe goes to (a taught type's, or bolt's and nut's: the recipe's
    [pick.CLASS], else the config's planning.CLASS), or InputError naming those that have one."""
    if of in BUILT_IN_CLASS_NO:
        plan = recipe.pick.get(of) if recipe is not None else None  # type: ignore[call-overload]
        return (plan or planning.for_class(of)).bin_robot_mm
    types = {} if recipe is None else recipe.types
    t = types.get(of)
    if t is not None and t.bin_robot_mm is not None:
        return t.bin_robot_mm
    have = [*BUILT_IN_CLASS_NO, *(n for n, x in types.items() if x.bin_robot_mm is not None)]
    said = f"{of!r} has no bin itself" if t is not None else f"the recipe has no type {of!r}"
    raise InputError(f"--bin-of {of}: {said}", hint=f"the types with a bin: {', '.join(have)}")


def bins_of(recipe: Recipe | None, planning: PlanningConfig) -> dict[str, tuple[float, float, float]]:
    """Every class of the recipe that has a bin, with it (what a new type may share)."""
    out = {cls: bin_of(recipe, planning, cls) for cls in BUILT_IN_CLASS_NO}
    for name, t in ({} if recipe is None else recipe.types).items():
        if t.bin_robot_mm is not None:
            out[name] = t.bin_robot_mm
    return out


def read_recipe_if_any(path: Path) -> Recipe | None:
    """The recipe file, validated, or None when there is none yet (RecipeError when it cannot be used)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise RecipeError(f"{path}: cannot read recipe: {e}") from None
    return parse_recipe(text, str(path))


def _toml_float(v: float) -> str:
    return repr(round(float(v), 4))


def add_taught_type(
    path: Path, model: ShapeModel, bin_robot_mm: tuple[float, float, float] | None = None, bin_note: str = ""
) -> TaughtAdded:
    """Write the model file beside the recipe (models/NAME-<sha>.json) and name it in the recipe
    (`[types.NAME]`, replacing a former teaching of that name; the recipe created if absent). Both
    written whole or not at all, the recipe validated first. A type taught again keeps its class_no, bin
    and moves unless a bin is given; a new one gets the next free class_no, written down so it stays."""
    path = Path(path)
    data = model.to_json().encode("utf-8")
    sha = sha256_of(data)
    relative = f"models/{model.name}-{sha[:12]}.json"
    recipe = read_recipe_if_any(path)  # a broken recipe is not made worse
    before = None if recipe is None else recipe.types.get(model.name)
    numbers = {} if recipe is None else recipe.class_numbers()
    if before is not None:  # what the robot has been told for it stays
        class_no = numbers[model.name]
    else:
        taken = set(numbers.values())
        class_no = next(n for n in range(TAUGHT_CLASS_NO_BASE, MAX_CLASS_NO + 1) if n not in taken)
    section = [
        f"[types.{model.name}]",
        f'model = "{relative}"',
        f'model_sha256 = "{sha}"',
        f"height_mm = {round(model.height_mm, 4)!r}",  # as the model file has it
        f"class_no = {class_no}",
    ]
    where = bin_robot_mm if bin_robot_mm is not None else (None if before is None else before.bin_robot_mm)
    if where is not None:
        note = f"  # {bin_note}" if bin_note and bin_robot_mm is not None else ""
        section.append(f"bin_robot_mm = [{', '.join(_toml_float(v) for v in where)}]{note}")
    if before is not None:  # its moves, where they still hold at the height taught now
        for key in ("pick_above_table_mm", "approach_above_table_mm"):
            value = getattr(before, key)
            if key in before.model_fields_set and value is not None:
                section.append(f"{key} = {_toml_float(value)}")
        try:
            TaughtType.model_validate(tomllib.loads("\n".join(section[1:])))
        except (ValidationError, tomllib.TOMLDecodeError) as e:
            log.warning("types.%s: its moves are dropped, they do not hold at the new height: %s", model.name, e)
            section = [line for line in section if not line.startswith(("pick_above", "approach_above"))]
    if recipe is not None:
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        at = _section_range(lines, model.name)
        if at is None:
            lines = [*lines, "", *section] if lines else section
        else:
            lines = [*lines[: at[0]], *section, "", *lines[at[1] :]]
        new = "\n".join(lines).rstrip("\n") + "\n"
    else:
        new = 'description = "taught part types"\n\n' + "\n".join(section) + "\n"
    written = parse_recipe(new, str(path))
    target = path.parent / relative
    target.parent.mkdir(parents=True, exist_ok=True)
    write_bytes_atomic(target, data)
    write_text_atomic(path, new)
    return TaughtAdded(target, sha, where, class_no, tuple(written.unbinned()))


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
