"""The simulated plate's fit kept in the user's cache folder: a later process loads the very
calibration the first one fitted; a damaged, foreign or stale file is fitted again and rewritten,
a folder that cannot be written is only logged, and `sim.plate_cache = false` never touches it."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

import cell.sim.cell as simcell
from cell.assembly import cell_config
from cell.config import CellConfig
from cell.sim import platefit
from cell.sim.rig import default_camera


@pytest.fixture
def fits(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list[int]:
    """A fresh process's view: no fit in memory, the cache folder under tmp_path; counts the fits."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(simcell, "_PLATE_FITS", {})
    calls: list[int] = []
    real = simcell.calibrate

    def counted(*a, **k):  # type: ignore[no-untyped-def]
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(simcell, "calibrate", counted)
    return calls


def _config() -> CellConfig:
    config = cell_config(None, True)
    config.camera.width_px, config.camera.height_px = 960, 540  # a quicker fit than the default 1080p
    return config


def _fit(config: CellConfig) -> tuple[simcell.Calibration, str]:
    simcell._PLATE_FITS.clear()  # as a new process would start
    return simcell.plate_calibration(config, default_camera(config.camera.width_px, config.camera.height_px))


def _fitted(calibration: simcell.Calibration) -> dict[str, object]:
    """What a fit found (all but the time it was made)."""
    return {k: v for k, v in calibration.to_dict().items() if k != "created_utc"}


def _files(tmp_path: Path) -> list[Path]:
    return sorted((tmp_path / "xdg" / "pick-cell" / "sim").glob("plate-*.json"))


@pytest.mark.timeout(120)
def test_a_later_process_loads_the_calibration_the_first_fitted(fits: list[int], tmp_path: Path) -> None:
    config = _config()
    first, why = _fit(config)
    assert len(fits) == 1 and len(_files(tmp_path)) == 1
    again, why_again = _fit(config)
    assert len(fits) == 1, "loaded, not fitted again"
    assert (again.content_id, why_again) == (first.content_id, why)
    pixels = np.mgrid[0:960:13, 0:540:11].reshape(2, -1).T.astype(np.float64)
    for height_mm in (0.0, 12.0):
        np.testing.assert_array_equal(
            again.pixel_to_table_mm(pixels, height_mm), first.pixel_to_table_mm(pixels, height_mm)
        )


@pytest.mark.timeout(120)
@pytest.mark.parametrize("damage", ["truncated", "not a fit", "another key", "corrupt calibration", "another code"])
def test_a_damaged_or_foreign_fit_is_fitted_again_and_rewritten(
    damage: str, fits: list[int], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    config = _config()
    first, _ = _fit(config)
    (path,) = _files(tmp_path)
    d = json.loads(path.read_text())
    if damage == "truncated":
        path.write_text(path.read_text()[: len(path.read_text()) // 2])
    elif damage == "not a fit":
        path.write_text(json.dumps({"schema": "something else"}))
    elif damage == "another key":
        path.write_text(json.dumps({**d, "key": d["key"].replace("960", "961")}))
    elif damage == "corrupt calibration":
        d["calibration"]["camera"]["camera_matrix"][0][0] = -1.0  # a camera that does not face the table
        path.write_text(json.dumps(d))
    else:  # the renderer or the fit changed since: a new file, the old one left to age out
        monkeypatch.setattr(platefit, "code_fingerprint", lambda: "changed")
    with caplog.at_level(logging.WARNING, logger="cell.sim.platefit"):
        again, _ = _fit(config)
    assert len(fits) == 2, "fitted again"
    assert _fitted(again) == _fitted(first)
    if damage != "another code":
        assert any("unusable" in r.getMessage() for r in caplog.records), "the bad file is logged"
    fits.clear()
    _fit(config)
    assert fits == [], "the rewritten file is used next time"


@pytest.mark.timeout(120)
def test_a_cache_folder_that_cannot_be_written_is_only_logged(
    fits: list[int], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    with caplog.at_level(logging.WARNING, logger="cell.sim.platefit"):
        calibration, _ = _fit(_config())
    assert len(fits) == 1 and calibration.model_name
    assert any("not kept" in r.getMessage() for r in caplog.records)


@pytest.mark.timeout(120)
def test_plate_cache_off_fits_every_time_and_writes_nothing(fits: list[int], tmp_path: Path) -> None:
    config = _config()
    config.sim.plate_cache = False
    _fit(config)
    _fit(config)
    assert len(fits) == 2 and not (tmp_path / "xdg").exists()
