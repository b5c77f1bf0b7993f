"""docs/config.md is the config models' own reference (`run-cell config reference`), never stale; every
example config (configs/*.toml, the TOML blocks of the docs) loads as run-cell loads it."""

from __future__ import annotations

import re
import tomllib
import warnings
from pathlib import Path

import pytest
from pydantic import BaseModel, Field

from cell.access.security import check_exposure
from cell.cli import main
from cell.commands.config import REGENERATE, reference, undescribed_keys, unit_of
from cell.config import CellConfig, load_config
from cell.telemetry.publisher import password_from_env
from drivers.config import Strict

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "config.md"
CONFIGS = sorted((ROOT / "configs").glob("*.toml"))


def test_docs_config_md_is_the_generated_reference() -> None:
    expected = reference()
    committed = DOC.read_text(encoding="utf-8") if DOC.exists() else ""
    assert committed == expected, (
        f"docs/config.md is stale (the config models changed): regenerate it with `{REGENERATE}`"
    )
    missing = undescribed_keys()
    if missing:  # reported, not failed: the page says "(no description)" for each
        warnings.warn(
            f"{len(missing)} config keys have no description (Field(description=...)): {', '.join(missing)}",
            stacklevel=1,
        )


def _model_keys(model: type[BaseModel], path: str = "") -> dict[str, set[str]]:
    """Each table's keys, walked from the models independently of the generator."""
    out: dict[str, set[str]] = {path: set()} if path else {}
    for key, field in model.model_fields.items():
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            where = f"{path}.{key}" if path else key
            if path:
                out[path].add(key)
            out.update(_model_keys(sub, where))
        elif path:
            out[path].add(key)
    return out


def _doc_keys(text: str) -> dict[str, set[str]]:
    out: dict[str, set[str]] = {}
    table = None
    for line in text.splitlines():
        if m := re.fullmatch(r"## \[([a-z0-9_.]+)\]", line):
            table = m.group(1)
            out[table] = set()
        elif table is not None and (m := re.match(r"\| `([a-z0-9_]+)` \|", line)):
            out[table].add(m.group(1))
    return out


def test_every_table_and_key_of_the_models_has_its_row() -> None:
    assert _doc_keys(reference()) == _model_keys(CellConfig)


def _row(text: str, table: str, key: str) -> list[str]:
    section = text.split(f"\n## [{table}]\n", 1)[1].split("\n## ", 1)[0]
    line = next(x for x in section.splitlines() if x.startswith(f"| `{key}` |"))
    return [c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]]


def test_a_key_without_description_is_listed_and_says_so() -> None:
    class Inner(Strict):
        told: int = Field(1, description="a key that says what it is")
        untold_mm: float = 2.0

    class Outer(Strict):
        inner: Inner = Inner()

    assert _row(reference(Outer), "inner", "untold_mm")[3:] == ["mm", "(no description)"]
    assert _row(reference(Outer), "inner", "told")[4] == "a key that says what it is"
    assert undescribed_keys(Outer) == ["inner.untold_mm"]


def test_rows_say_type_bounds_default_unit_and_description() -> None:
    text = reference()
    assert _row(text, "arm.serial", "motion_timeout_s") == [
        "`motion_timeout_s`",
        "float (> 0, ≤ 600)",
        "`10.0`",
        "s",
        "shortest wait for motion to finish: the floor of each move's own timeout (its expected time from length, "
        "feed, max_rate_mm_min and acceleration_mm_s2, times motion_margin_factor, plus motion_margin_s), and the "
        "wait when nothing is queued",
    ]
    # a sub-table's defaults are its parent's (the Dynamixel workspace is not the serial arm's box)
    assert _row(text, "arm.dynamixel.workspace", "x_min_mm")[2] == "`-400.0`"
    assert _row(text, "arm.serial.workspace", "x_min_mm")[2] == "`0.0`"
    assert _row(text, "arm", "kind")[1] == 'one of "serial" \\| "dynamixel" \\| "mock" \\| "sim" \\| "robot-server"'
    assert _row(text, "calibration", "camera_height_mm")[1:3] == ["float, or unset (> 0)", "unset"]
    assert _row(text, "drift", "marks_mm")[1:4] == ["list of [float, float]", "`[]`", "mm"]
    assert _row(text, "arm.serial", "speed_mm_s")[3] == "mm/s"
    assert _row(text, "arm", "serial")[1:] == ["table", "see below", "none", "see [`[arm.serial]`](#armserial)"]
    assert _row(text, "plate", "columns")[3] == "none"
    # a default the machine computes is described: the page must not depend on the PC that wrote it
    import socket

    edge = _row(text, "telemetry.mqtt", "edge_node_id")[2]
    assert edge.startswith("computed: the host name") and socket.gethostname() not in edge


@pytest.mark.parametrize(
    "key, unit",
    [
        ("speed_mm_s", "mm/s"),
        ("noise_area_mm2", "mm²"),
        ("timeout_s", "s"),
        ("latency_timer_ms", "ms"),
        ("session_h", "h"),
        ("images_max_days", "days"),
        ("width_px", "px"),
        ("joint_min_deg", "degrees"),
        ("max_scale_change_pct", "%"),
        ("max_upload_mb", "MiB (2^20 bytes)"),
        ("send_buffer_kb", "KiB (1024 bytes)"),
        ("max_frame_rate_hz", "Hz"),
        ("audit_max_bytes", "bytes"),
        ("parts_per_minute", "per minute"),
        ("columns", "none"),
        ("hsv_lower", "none"),
    ],
)
def test_unit_from_the_key_suffix(key: str, unit: str) -> None:
    assert unit_of(key) == unit


def test_config_reference_command_writes_the_page(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "config.md"
    assert main(["config", "reference", "--out", str(out)]) == 0
    assert out.read_text(encoding="utf-8") == reference()
    assert main(["config", "reference"]) == 0
    assert capsys.readouterr().out.endswith(reference())


def test_config_check_names_the_wrong_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[arm.serial]\nmotion_timout_s = 40\n", encoding="utf-8")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"run-cell config: error: {bad}: invalid config: arm.serial.motion_timout_s: " in err
    assert "Traceback" not in err


# The environment a config's secrets come from: the test gives each variable a value, as the unit's
# EnvironmentFile would (the password is never in the file).
def _with_secrets(config: CellConfig, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in (config.service.password_env, config.telemetry.mqtt.password_env):
        if name:
            monkeypatch.setenv(name, "a-test-password")


def _run_cell_accepts(config: CellConfig) -> None:
    """What run-cell checks of a config before it opens anything: listening beyond loopback needs users;
    an MQTT password variable must be set."""
    import os

    check_exposure(config.service)
    password_from_env(config.telemetry.mqtt, dict(os.environ))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_example_config_loads_as_run_cell_loads_it(
    path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["config", "check", str(path)]) == 0, capsys.readouterr().err
    assert capsys.readouterr().out == f"{path}: valid\n"
    config = load_config(path)
    _with_secrets(config, monkeypatch)
    _run_cell_accepts(config)


def test_configs_folder_holds_the_examples() -> None:
    assert {"sim.toml", "example-line.toml", "arm-grbl.toml", "arm-dynamixel.toml"} <= {p.name for p in CONFIGS}


def _doc_toml_blocks() -> list[tuple[str, str]]:
    blocks = []
    for doc in sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md")]):
        for i, m in enumerate(re.finditer(r"^```toml\n(.*?)^```", doc.read_text(encoding="utf-8"), re.M | re.S)):
            blocks.append((f"{doc.relative_to(ROOT)}#{i + 1}", m.group(1)))
    return blocks


DOC_BLOCKS = _doc_toml_blocks()


@pytest.mark.parametrize("where, text", DOC_BLOCKS, ids=[w for w, _ in DOC_BLOCKS])
def test_every_toml_example_in_the_docs_is_a_valid_config(
    where: str, text: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "example.toml"
    path.write_text(text, encoding="utf-8")
    config = load_config(path)
    _with_secrets(config, monkeypatch)
    _run_cell_accepts(config)
    # the commented-out lines of an example are settings to switch on: they must be valid too
    uncommented = re.sub(r"^# (\w+ = )", r"\1", text, flags=re.M)
    if uncommented != text:
        path.write_text(uncommented, encoding="utf-8")
        tomllib.loads(uncommented)
        load_config(path)


def test_every_config_file_the_docs_name_is_shipped() -> None:
    named = set()
    for doc in [ROOT / "README.md", *(ROOT / "docs").glob("*.md")]:
        named |= set(re.findall(r"configs/([\w.-]+\.toml)", doc.read_text(encoding="utf-8")))
    named.discard("line.toml")  # the unit's own config, made from example-line.toml on the line PC
    assert named <= {p.name for p in CONFIGS}, named - {p.name for p in CONFIGS}
