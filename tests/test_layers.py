"""Layers point one way: cell/ uses drivers/, drivers/ never imports cell/ (not even inside a function)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

DRIVERS = Path(__file__).resolve().parents[1] / "drivers"


def imported_modules(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) for every import statement anywhere in the tree. A relative import is
    kept with its dots: inside drivers/ it cannot climb above the drivers package."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.lineno, "." * node.level + (node.module or "")))
    return found


def is_cell(module: str) -> bool:
    return module == "cell" or module.startswith("cell.")


def test_drivers_import_nothing_from_cell():
    files = sorted(DRIVERS.rglob("*.py"))
    assert len(files) > 10, f"expected the driver sources under {DRIVERS}"
    offenders = [
        f"{path.relative_to(DRIVERS.parent)}:{line}: {module}"
        for path in files
        for line, module in imported_modules(ast.parse(path.read_text(), str(path)))
        if is_cell(module)
    ]
    assert not offenders, "drivers/ imports the application:\n" + "\n".join(offenders)


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from cell.errors import CellError", True),
        ("def f():\n    import cell.config as c", True),
        ("class A:\n    def f(self):\n        from cell import errors", True),
        ("import cellular, drivers.errors\nfrom drivers.arm import base", False),
    ],
)
def test_the_walk_finds_imports_at_any_depth(source, expected):
    assert any(is_cell(m) for _, m in imported_modules(ast.parse(source))) is expected
