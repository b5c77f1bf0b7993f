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


# ---- the application's own layers (docs/architecture.md) ------------------------------------
REPO = DRIVERS.parent


def sources(*folders: str) -> list[Path]:
    return sorted(p for f in folders for p in (REPO / f).rglob("*.py"))


def imports_of(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) for every import anywhere in the file; names are those of `from m import a, b`."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.lineno, "." * node.level + (node.module or ""), [a.name for a in node.names]))
    return found


def offenders(folders: tuple[str, ...], forbidden: tuple[str, ...]) -> list[str]:
    return [
        f"{path.relative_to(REPO)}:{line}: {module}"
        for path in sources(*folders)
        for line, module, _ in imports_of(path)
        if any(module == f or module.startswith(f + ".") for f in forbidden)
    ]


@pytest.mark.parametrize(
    "folders, forbidden, why",
    [
        (
            ("cell/service", "cell/web"),
            ("cell.commands", "cell.cli"),
            "interfaces hold the service's API, not commands",
        ),
        (("cell/calibration",), ("cell.sim",), "a simulated capture is passed in, never rendered here"),
        (
            ("cell/vision", "cell/calibration"),
            ("cell.service", "cell.web", "cell.commands", "cell.cli", "cell.assembly"),
            "vision and calibration are below everything that uses them",
        ),
        (
            ("cell/runner.py", "cell/statemachine.py", "cell/core"),
            ("cell.service", "cell.web", "cell.commands", "cell.cli", "cell.sim", "cell.history", "cell.telemetry"),
            "the core knows no interface and no simulated world",
        ),
    ],
)
def test_the_application_layers_point_one_way(folders, forbidden, why):
    found = offenders(folders, forbidden)
    assert not found, f"{why}:\n" + "\n".join(found)


def test_the_domain_core_imports_nothing_else_of_the_cell():
    """cell/core (commands, roles, the command table, events, the records) is the bottom of the
    application: everything else depends on it, it on nothing of the cell but itself."""
    files = sources("cell/core")
    assert len(files) >= 5, "expected the domain core under cell/core"
    found = [
        f"{path.relative_to(REPO)}:{line}: {module}"
        for path in files
        for line, module, _ in imports_of(path)
        if is_cell(module) and not (module == "cell.core" or module.startswith("cell.core."))
    ]
    assert not found, "the domain core imports the rest of the cell:\n" + "\n".join(found)


# What one interface or consumer package may import of another: the domain core, access (users,
# throttle, certificates), the history readers' API, and any package's config models (leaves).
SHARED = ("cell.core", "cell.access", "cell.history.query")
PACKAGES = ("cell/service", "cell/web", "cell/history", "cell/telemetry", "cell/access")


def crosses(module: str, own: str) -> bool:
    """Whether `module` is another of PACKAGES than `own`, and not one of what they may share."""
    dotted = {p.replace("/", "."): p for p in PACKAGES}
    other = next((d for d in dotted if module == d or module.startswith(d + ".")), None)
    if other is None or dotted[other] == own:
        return False
    if any(module == s or module.startswith(s + ".") for s in SHARED):
        return False
    return not module.endswith(".config")


@pytest.mark.parametrize("package", PACKAGES)
def test_interfaces_and_consumers_depend_on_the_core_not_on_each_other(package):
    """History, telemetry, OPC UA and the service, the screen and access meet in cell/core; none
    imports another (a config model or the history readers' API excepted)."""
    found = [
        f"{path.relative_to(REPO)}:{line}: {module}"
        for path in sources(package)
        for line, module, _ in imports_of(path)
        if crosses(module, package)
    ]
    assert not found, f"{package} imports another interface or consumer:\n" + "\n".join(found)


@pytest.mark.parametrize(
    "module, own, expected",
    [
        ("cell.service.ledger", "cell/telemetry", True),
        ("cell.web.config", "cell/service", False),
        ("cell.core.records", "cell/web", False),
        ("cell.history.store", "cell/web", True),
        ("cell.history.query", "cell/web", False),
        ("cell.service.service", "cell/service", False),
    ],
)
def test_the_crossing_rule(module, own, expected):
    assert crosses(module, own) is expected


def test_devices_are_built_in_one_place():
    """Only cell/assembly.py (and the simulated world's own emulated arm) build devices from a config."""
    builders = {
        "drivers.arm.factory": {"make_arm"},
        "drivers.cameras.factory": {"make_camera"},
        "cell.sim.cell": {"sim_cell"},
    }
    allowed = {"cell/assembly.py", "cell/sim/emulated_arm.py", "cell/sim/cell.py"}
    found = [
        f"{path.relative_to(REPO)}:{line}: {module} {sorted(set(names) & builders[module])}"
        for path in sources("cell", "scripts")
        if str(path.relative_to(REPO)) not in allowed
        for line, module, names in imports_of(path)
        if module in builders and set(names) & builders[module]
    ]
    assert not found, "devices built outside cell/assembly.py:\n" + "\n".join(found)


def test_no_module_imports_another_modules_private_names():
    found = [
        f"{path.relative_to(REPO)}:{line}: from {module} import {', '.join(n for n in names if n.startswith('_'))}"
        for path in sources("cell", "drivers", "scripts", "tests")
        for line, module, names in imports_of(path)
        if any(n.startswith("_") and not n.startswith("__") for n in names)
    ]
    assert not found, "private names imported across modules:\n" + "\n".join(found)
