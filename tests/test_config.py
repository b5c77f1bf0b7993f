"""Config files: every shipped TOML validates; mistakes are named with key and unit."""

import argparse
from pathlib import Path
from typing import get_args

import pytest

from cell.cli import build_parser
from cell.config import load_config
from cell.errors import ConfigError
from cell.sim.cell import sim_arm_kind
from cell.vision.config import Preset
from drivers.arm.config import ArmConfig, ArmKind
from drivers.arm.factory import make_arm
from drivers.arm.mock import MockArm
from drivers.errors import ConfigError as DriverConfigError

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.toml"))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_validate(path):
    load_config(path)


def test_paper_config_is_the_paper_preset():
    cfg = load_config(Path(__file__).resolve().parents[1] / "configs" / "paper.toml")
    assert cfg.detection.preset == "paper" and cfg.calibration.model == "quadratic"
    assert cfg.detection.paper.hsv_lower == (10, 0, 100) and cfg.detection.paper.hsv_upper == (250, 250, 250)
    assert (cfg.detection.paper.min_area_px, cfg.detection.paper.max_area_px) == (500, 2000)
    assert (cfg.plate.columns, cfg.plate.rows, cfg.plate.pitch_x_mm, cfg.plate.pitch_y_mm, cfg.plate.diameter_mm) == (
        13,
        12,
        22,
        16,
        10,
    )


@pytest.mark.parametrize(
    "text,message",
    [
        ("[plate]\ncolums = 13\n", "plate.colums: Extra inputs are not permitted"),
        ("[plate]\ndiameter_mm = 30\n", "plate.diameter_mm (30.0 mm) must be smaller than both pitches"),
        ("[detection.paper]\nmin_area_px = 3000\n", "min_area_px (3000.0 px) must be below max_area_px (2000 px)"),
        ("[calibration]\nmodel = 'cubic'\n", "calibration.model"),
        ("[plate\n", "not valid TOML"),
    ],
)
def test_config_errors_name_the_key(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    assert message in str(e.value) and str(path) in str(e.value)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "none.toml")


def test_sim_names_the_simulated_arm_and_mock_is_its_old_spelling_only_there():
    assert sim_arm_kind(ArmConfig(kind="sim")) == sim_arm_kind(ArmConfig(kind="mock")) == "sim"
    assert sim_arm_kind(ArmConfig(kind="dynamixel")) == "dynamixel"
    assert isinstance(make_arm(ArmConfig(kind="mock")), MockArm)
    with pytest.raises(DriverConfigError, match="needs camera.source 'sim'"):
        make_arm(ArmConfig(kind="sim"))


def test_cli_choices_are_the_configs_literals():
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    arm = next(a for a in build_parser()._actions if a.dest == "arm")
    assert tuple(arm.choices) == get_args(ArmKind) == ("serial", "dynamixel", "mock", "sim", "robot-server")
    assert next(a for a in sub["jog"]._actions if a.dest == "arm").choices == get_args(ArmKind)
    assert next(a for a in sub["locate"]._actions if a.dest == "preset").choices == get_args(Preset)
