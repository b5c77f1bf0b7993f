"""`run-cell config reference|check`: the config reference generated from the models, and a config checked.

docs/config.md is `run-cell config reference --out docs/config.md`: every key of every TOML table the
cell reads, walked from `CellConfig`'s pydantic models, with its type (and the bounds the model
enforces), its default, its unit (from the key's suffix: `_mm`, `_s`, ...) and the Field's
description. tests/test_config_reference.py fails when the committed page is not this output.
"""

from __future__ import annotations

import argparse
import enum
import inspect
import json
import math
import re
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePath
from typing import Any

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo

REGENERATE = "run-cell config reference --out docs/config.md"

# The unit a key's name ends in; the longest matching suffix wins (`speed_mm_s` is mm/s, not s).
UNITS: dict[str, str] = {
    "_mm_min": "mm/min",
    "_mm_s": "mm/s",
    "_mm2": "mm²",
    "_mm": "mm",
    "_ms": "ms",
    "_s": "s",
    "_h": "h",
    "_days": "days",
    "_px": "px",
    "_deg": "degrees",
    "_pct": "%",
    "_hz": "Hz",
    "_bytes": "bytes",
    "_kb": "KiB (1024 bytes)",
    "_mb": "MiB (2^20 bytes)",
    "_ticks": "servo ticks",
    "_per_minute": "per minute",
}
NO_UNIT = "none"
NO_DESCRIPTION = "(no description)"


def unit_of(key: str) -> str:
    """The unit the key's name states, or "none"."""
    for suffix in sorted(UNITS, key=len, reverse=True):
        if key.endswith(suffix):
            return UNITS[suffix]
    return NO_UNIT


@dataclass(frozen=True)
class Row:
    key: str
    type: str
    default: str
    unit: str
    description: str


@dataclass(frozen=True)
class Table:
    """One TOML table: `[arm.serial]`, its purpose and its keys."""

    path: str
    about: str
    rows: tuple[Row, ...]

    @property
    def heading(self) -> str:
        return f"[{self.path}]"

    @property
    def anchor(self) -> str:
        """GitHub's anchor for the heading: lower case, punctuation but - and _ dropped."""
        return re.sub(r"[^a-z0-9_\- ]", "", self.heading.lower()).replace(" ", "-")


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The model a field holds (itself, or optional), or None for a plain value."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        models = [a for a in typing.get_args(annotation) if isinstance(a, type) and issubclass(a, BaseModel)]
        if len(models) == 1:
            return models[0]
        if models:
            raise TypeError(f"{annotation}: a union of tables; teach cell/commands/config.py to document it")
    return None


def _optional(annotation: Any) -> tuple[Any, bool]:
    """The annotation without None, and whether None was allowed."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        rest = [a for a in args if a is not type(None)]
        if len(rest) < len(args):
            return (rest[0] if len(rest) == 1 else typing.Union[tuple(rest)]), True  # noqa: UP007
    return annotation, False


def type_name(annotation: Any) -> str:
    """A reader's name for a value's type: float, int, string, path, one of "a" | "b", list of ..."""
    annotation, optional = _optional(annotation)
    name = _plain_type_name(annotation)
    return f"{name}, or unset" if optional else name


def _plain_type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Literal:
        return "one of " + " | ".join(_toml(a) for a in args)
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return "one of " + " | ".join(_toml(m.value) for m in annotation)
    if origin in (list, set, frozenset) or (origin is tuple and len(args) == 2 and args[1] is Ellipsis):
        inner = _plain_type_name(args[0])
        return f"list of ({inner})" if " " in inner and not inner.startswith("[") else f"list of {inner}"
    if origin is tuple:
        return "[" + ", ".join(_plain_type_name(a) for a in args) + "]"
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_plain_type_name(a) for a in args)
    if origin is dict:
        return f"table of {_plain_type_name(args[0])} to {_plain_type_name(args[1])}"
    simple = {bool: "bool", int: "int", float: "float", str: "string", Path: "path", PurePath: "path"}
    if annotation in simple:
        return simple[annotation]
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "table"
    return str(annotation).replace("typing.", "")


def _bounds(field: FieldInfo) -> str:
    """What the model allows beyond the type: `> 0, ≤ 60`, `1-64 characters`, `matching ^...$`."""
    said: list[str] = []
    low = high = None
    for m in field.metadata:
        if isinstance(m, annotated_types.Gt):
            said.append(f"> {_number(m.gt)}")
        elif isinstance(m, annotated_types.Ge):
            said.append(f"≥ {_number(m.ge)}")
        elif isinstance(m, annotated_types.Lt):
            said.append(f"< {_number(m.lt)}")
        elif isinstance(m, annotated_types.Le):
            said.append(f"≤ {_number(m.le)}")
        elif isinstance(m, annotated_types.MinLen):
            low = m.min_length
        elif isinstance(m, annotated_types.MaxLen):
            high = m.max_length
        elif getattr(m, "pattern", None):
            said.append(f"matching `{m.pattern}`")
    if low is not None or high is not None:
        items = "character" if _optional(field.annotation)[0] is str else "item"
        if high is None:
            said.append(f"at least {low} {items}{'s' if low != 1 else ''}")
        elif low is None:
            said.append(f"at most {high} {items}{'s' if high != 1 else ''}")
        else:
            said.append(f"{low}-{high} {items}s")
    return ", ".join(said)


def _number(value: Any) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    return f"{value:_}" if isinstance(value, int) and abs(value) >= 100_000 else str(value)


def _toml(value: Any) -> str:
    """A value as it is written in the TOML file."""
    if value is None:
        return "unset"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, enum.Enum):
        return _toml(value.value)
    if isinstance(value, int | float):
        if isinstance(value, float) and not math.isfinite(value):
            return str(value)
        return repr(value)
    if isinstance(value, PurePath):
        return json.dumps(str(value), ensure_ascii=False)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list | tuple | set | frozenset):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return json.dumps(str(value), ensure_ascii=False)


def _default(field: FieldInfo, value: Any) -> str:
    """The default as written in TOML, or what computes it (a default taken from the machine, e.g. its
    host name, is described, not printed: the page must not change with the PC that writes it)."""
    factory = field.default_factory
    if (
        factory is not None
        and inspect.isfunction(factory)
        and factory.__name__ != "<lambda>"
        and inspect.getdoc(factory)
    ):
        first = (inspect.getdoc(factory) or "").split("\n\n", 1)[0].replace("\n", " ").rstrip(".")
        return f"computed: {first[0].lower()}{first[1:]}"
    if value is None:
        return "unset"
    return f"`{_toml(value)}`"


def _about(model: type[BaseModel], field: FieldInfo | None) -> str:
    """A table's purpose: the description its field gives it, else its model's docstring."""
    own = re.sub(r"^`?\[[^\]]+\]`?:?\s*", "", field.description or "").strip() if field is not None else ""
    if own:
        return own[0].upper() + own[1:]
    doc = inspect.cleandoc(model.__dict__.get("__doc__") or "")  # its own, not the base's
    about = re.sub(r"^`?\[[^\]]+\]`?:?\s*", "", doc.split("\n\n", 1)[0].replace("\n", " ")).strip()
    return about[:1].upper() + about[1:]


def tables(
    model: type[BaseModel], default: BaseModel, path: str = "", field: FieldInfo | None = None
) -> Iterator[Table]:
    """The TOML tables of `model` and below, in the models' order; defaults read off `default`, the
    parent's default instance (a sub-table's defaults may be the parent's, not its model's)."""
    rows: list[Row] = []
    below: list[tuple[str, type[BaseModel], BaseModel, FieldInfo]] = []
    for key, f in model.model_fields.items():
        name = f.alias or key
        sub = _model_in(f.annotation)
        value = getattr(default, key)
        if sub is not None:
            where = f"{path}.{name}" if path else name
            optional = _optional(f.annotation)[1]
            kind = "table, optional" if optional else "table"
            rows.append(Row(name, kind, "see below" if value is not None else "unset", NO_UNIT, f"see [{where}]"))
            below.append((where, sub, value if value is not None else sub(), f))
            continue
        kind = type_name(f.annotation)
        bounds = _bounds(f)
        description = " ".join((f.description or NO_DESCRIPTION).split())
        rows.append(Row(name, f"{kind} ({bounds})" if bounds else kind, _default(f, value), unit_of(name), description))
    if path:
        yield Table(path, _about(model, field), tuple(rows))
    for where, sub, value, f in below:
        yield from tables(sub, value, where, f)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def reference(model: type[BaseModel] | None = None) -> str:
    """docs/config.md: every table and key of the cell's config."""
    if model is None:
        from cell.config import CellConfig

        model = CellConfig
    found = list(tables(model, model()))
    keys = sum(1 for t in found for r in found_rows(t))
    undescribed = sum(1 for t in found for r in found_rows(t) if r.description == NO_DESCRIPTION)
    out = [
        "# Config reference",
        "",
        f"<!-- Generated from the config models by `{REGENERATE}`; do not edit by hand. "
        "tests/test_config_reference.py fails when this page is stale. -->",
        "",
        "Every key `run-cell --config FILE` (and `serve`, `teach`, `user`, `history`, ...) reads, one "
        "section per TOML table, in the order of the models in `cell/config.py`. Every key is optional: "
        "a key left out takes the default shown. A key the models do not know is an error that names it "
        "(a typo never passes silently), and so is a value outside its type or its bounds. Check a file "
        "without starting anything: `run-cell config check FILE`.",
        "",
        "- **Type**: `string`, `int`, `float`, `bool`, `path` (a string; relative paths are taken from the "
        "folder `run-cell` runs in), `one of ...` (exactly these strings), `[float, float]` (a TOML array "
        "of exactly that many values), `list of ...` (any length), `table` (a sub-table, its own section "
        "here). `, or unset` means the key may be left out with no value at all (the default `unset`). "
        "Bounds the models enforce follow in brackets.",
        "- **Unit**: read off the key's name (`_mm`, `_s`, `_px`, `_deg`, `_pct`, `_mb` ...); `none` for "
        "counts, ratios, names and switches.",
        "- The example configs in `configs/` show keys in context; `configs/example-line.toml` is a line "
        "cell, `configs/sim.toml` the simulated one.",
        "",
        f"{len(found)} tables, {keys} keys; {undescribed} keys have no description yet.",
        "",
        "## Tables",
        "",
    ]
    out += [f"- [`{t.heading}`](#{t.anchor}){': ' + t.about if t.about else ''}" for t in found]
    for t in found:
        out += ["", f"## {t.heading}", ""]
        if t.about:
            out += [t.about, ""]
        out += ["| Key | Type | Default | Unit | Description |", "|---|---|---|---|---|"]
        for r in t.rows:
            out.append(
                f"| `{r.key}` | {_cell(r.type)} | {_cell(r.default)} | {r.unit} | {_linked(_cell(r.description))} |"
            )
    return "\n".join(out) + "\n"


def found_rows(table: Table) -> Iterator[Row]:
    """The table's keys holding values (its sub-tables are counted where they are listed)."""
    return (r for r in table.rows if not r.type.startswith("table"))


def _linked(description: str) -> str:
    """`see [a.b]` rows link to their section."""
    m = re.fullmatch(r"see \[([^\]]+)\]", description)
    if m is None:
        return description
    t = Table(m.group(1), "", ())
    return f"see [`{t.heading}`](#{t.anchor})"


def undescribed_keys(model: type[BaseModel] | None = None) -> list[str]:
    """The keys whose Field has no description (`arm.serial.baud`, ...)."""
    if model is None:
        from cell.config import CellConfig

        model = CellConfig
    return [
        f"{t.path}.{r.key}" for t in tables(model, model()) for r in found_rows(t) if r.description == NO_DESCRIPTION
    ]


def register(sub: Any) -> None:
    p = sub.add_parser(
        "config",
        help="the config reference (every key, type, default, unit) or a config file checked",
        description="The cell's configuration: `reference` prints docs/config.md, every key of every table "
        "with its type, default, unit and description, generated from the models; `check FILE` loads a "
        "config exactly as run-cell does and says whether it is valid.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    ref = verbs.add_parser(
        "reference",
        help="print the config reference as Markdown (docs/config.md)",
        description=f"Print the config reference as Markdown; `{REGENERATE}` rewrites the committed page.",
    )
    ref.add_argument("--out", type=Path, help="write it to this file (atomically) instead of standard output")
    ref.set_defaults(func=cmd_reference)
    check = verbs.add_parser(
        "check",
        help="load a config file as run-cell does: valid, or every wrong key named",
        description="Load a config file (TOML) through the models as every run-cell command does; exit 0 "
        "and say so when it is valid, else name each wrong key (exit 2).",
    )
    check.add_argument("file", type=Path, metavar="FILE", help="the config (TOML)")
    check.set_defaults(func=cmd_check)


def cmd_reference(args: argparse.Namespace) -> int:
    text = reference()
    if args.out is None:
        print(text, end="")
        return 0
    from cell.atomicfile import write_text_atomic
    from cell.errors import output_error

    try:
        write_text_atomic(args.out, text)
    except OSError as e:
        raise output_error(args.out, e) from None
    print(f"wrote {args.out}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from cell.config import load_config

    load_config(args.file)  # a ConfigError names the file and each wrong key
    print(f"{args.file}: valid")
    return 0
