"""Every bad input the cell was tried with before going on a line (issue 8): each ends in one
line on stderr naming what and where, the documented exit code, nothing half-written and no
temporary file left behind."""

from __future__ import annotations

import errno
import json
import os
import struct
import zlib
from pathlib import Path

import cv2
import pytest

from cell.calibration.models import CameraMap
from cell.calibration.store import Calibration
from cell.camera_model import CameraModel
from cell.cli import main
from cell.commands import recalibrate
from cell.config import CellConfig
from cell.sim.render import render_plate

# Whole runs of the cell or of recalibrations (slow); ptys and subprocesses must never hang the suite.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

W, H = 1280, 720
CAMERA = CameraModel.looking_down(W, H, 0.30, (132, 88), tilt_deg=3, k1=-0.06)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    cv2.imwrite(str(d / "plate.png"), render_plate(CAMERA, CellConfig().plate, seed=1))
    wrong_pitch = CellConfig().plate.model_copy(update={"pitch_x_mm": 20.0})  # printed 20 x 16, configured 22 x 16
    cv2.imwrite(str(d / "plate-20mm.png"), render_plate(CAMERA, wrong_pitch, seed=1))
    (d / "cell.toml").write_text(f"[camera]\nwidth_px = {W}\nheight_px = {H}\n")
    Calibration("camera", CameraMap(CAMERA), (W, H), CAMERA).save(d / "cal.json")
    return d


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if p.name.endswith(".tmp") or p.stat().st_size == 0)


def recal(work, out, *extra, capsys):
    code = recalibrate.main(
        [
            "--image",
            str(work / "plate.png"),
            "--out",
            str(out),
            "--config",
            str(work / "cell.toml"),
            "--log",
            str(work / "cell.log"),
            "--quiet",
            *map(str, extra),
        ]
    )
    return code, capsys.readouterr().err


# ---- recalibration ---------------------------------------------------------------------------
def test_recalibrate_out_a_folder(work, tmp_path, capsys):
    code, err = recal(work, tmp_path, capsys=capsys)
    assert (
        code == 2
        and one_line(err)
        == f"recalibrate: error: {tmp_path}: is a folder; --out must name the "
        "calibration file (hint: e.g. --out cal/active.json)"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["out", "report-dir", "backup"])
@pytest.mark.parametrize("failure,code", [(errno.ENOSPC, 3), (errno.EROFS, 2)])
def test_recalibrate_on_a_full_or_read_only_filesystem(work, tmp_path, capsys, monkeypatch, where, failure, code):
    """The write fails where it would on a full or read-only disk: the file's own temporary copy."""
    out = tmp_path / "cal" / "active.json"
    out.parent.mkdir()
    out.write_bytes((work / "cal.json").read_bytes())
    before = out.read_bytes()
    target = {"out": out.parent, "report-dir": tmp_path / "report", "backup": out.parent / "backups"}[where]
    real_open = open

    def failing_open(file, mode="r", *a, **k):
        if "w" in mode and Path(file).parent == target:
            raise OSError(failure, os.strerror(failure), str(file))
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr("builtins.open", failing_open)
    code_, err = recal(work, out, "--report-dir", tmp_path / "report", "--accept-change", capsys=capsys)
    assert code_ == code
    line = one_line(err)
    assert line.startswith("recalibrate: error: ") and os.strerror(failure) in line and str(target) in line
    assert out.read_bytes() == before
    assert leftovers(tmp_path) == []


def test_recalibrate_interrupted_leaves_the_active_file_and_no_temporary(work, tmp_path, capsys, monkeypatch):
    out = tmp_path / "active.json"
    out.write_bytes((work / "cal.json").read_bytes())
    real = recalibrate.calibrate

    def interrupted(*a, **k):
        os.kill(os.getpid(), 2)  # Ctrl-C while fitting
        return real(*a, **k)

    monkeypatch.setattr(recalibrate, "calibrate", interrupted)
    code, err = recal(work, out, capsys=capsys)
    assert code == 130 and one_line(err) == "recalibrate: stopped: Ctrl-C; the active calibration is unchanged"
    assert out.read_bytes() == (work / "cal.json").read_bytes() and leftovers(tmp_path) == []


def test_a_signal_while_the_calibration_is_replaced_waits_for_both_files(work, tmp_path, capsys, monkeypatch):
    out = tmp_path / "active.json"
    out.write_bytes((work / "cal.json").read_bytes())
    real = Calibration.save

    def save(self, path):
        os.kill(os.getpid(), 15)  # SIGTERM between the backup and the new file
        real(self, path)

    monkeypatch.setattr(Calibration, "save", save)
    code, err = recal(work, out, "--accept-change", capsys=capsys)
    assert code == 0
    (backup,) = (tmp_path / "backups").iterdir()
    assert backup.read_bytes() == (work / "cal.json").read_bytes()
    assert Calibration.load(out).image_size == (W, H) and leftovers(tmp_path) == []


def test_a_plate_with_another_pitch_is_refused(work, tmp_path, capsys):
    out = tmp_path / "active.json"
    code = recalibrate.main(
        [
            "--image",
            str(work / "plate-20mm.png"),
            "--out",
            str(out),
            "--config",
            str(work / "cell.toml"),
            "--log",
            str(work / "cell.log"),
            "--quiet",
        ]
    )
    line = one_line(capsys.readouterr().err)
    assert code == 3 and line.startswith("recalibrate: refused: the plate's circles are round only if ")
    assert "pitch_x_mm / pitch_y_mm is 1.25" in line and "not the configured 22 / 16 = 1.375" in line
    assert not out.exists()


def test_a_large_change_against_the_active_calibration_needs_accept_change(work, tmp_path, capsys):
    out = tmp_path / "active.json"
    moved = CameraModel.looking_down(W, H, 0.33, (140, 88), tilt_deg=3, k1=-0.06)  # camera raised and shifted
    Calibration("camera", CameraMap(moved), (W, H), moved).save(out)
    before = out.read_bytes()
    code, err = recal(work, out, capsys=capsys)
    line = one_line(err)
    assert code == 3 and "% > calibration.max_scale_change_pct 2" in line
    assert "> calibration.max_origin_change_mm 5" in line and "rerun with --accept-change" in line
    assert out.read_bytes() == before
    code, err = recal(work, out, "--accept-change", capsys=capsys)
    assert code == 0 and out.read_bytes() != before
    (backup,) = (tmp_path / "backups").iterdir()
    assert backup.read_bytes() == before


def test_a_huge_image_is_refused_from_its_header(work, tmp_path, capsys):
    """A 20000 x 20000 PNG header (the pixels would need 1.2 GB) is refused without decoding."""
    big = tmp_path / "big.png"
    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0)
    big.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", 13)
        + b"IHDR"
        + ihdr
        + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
        + b"\0" * 1000
    )
    code = recalibrate.main(["--image", str(big), "--out", str(tmp_path / "a.json"), "--log", str(work / "cell.log")])
    line = one_line(capsys.readouterr().err)
    assert code == 2 and "image is 20000 x 20000 px (400000000 px), more than camera.max_image_px" in line
    assert main(["locate", "--image", str(big), "--calibration", str(work / "cal.json")]) == 2
    assert "20000 x 20000 px (400000000 px), more than camera.max_image_px" in one_line(capsys.readouterr().err)


# ---- calibration files -----------------------------------------------------------------------
def _corrupt(work, tmp_path, change) -> Path:
    data = json.loads((work / "cal.json").read_text())
    change(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))  # json writes NaN and Infinity as bare tokens, as a broken tool would
    return path


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda d: d["camera"]["tvec"].__setitem__(2, float("nan")), "camera.tvec[2] is not a finite number"),
        (
            lambda d: d["camera"]["camera_matrix"][0].__setitem__(0, float("inf")),
            "camera.camera_matrix[0][0] is not a finite number",
        ),
        (lambda d: d["camera"]["tvec"].__setitem__(2, -d["camera"]["tvec"][2]), "not above the table, looking at it"),
        (lambda d: d.__setitem__("image_size", [0, 720]), "image size 0 x 720 px is outside 16..20000 px"),
        (lambda d: d.__setitem__("image_size", [640, 480]), "camera model is 1280 x 720 px, the calibration 640 x 480"),
    ],
    ids=["nan-pose", "inf-focal", "camera-below-table", "zero-width", "size-mismatch"],
)
def test_an_impossible_calibration_is_refused_on_load(work, tmp_path, capsys, change, message):
    bad = _corrupt(work, tmp_path, change)
    for argv in (
        ["locate", "--image", str(work / "plate.png"), "--calibration", str(bad), "--json"],
        ["map", "--calibration", str(bad), "10", "10"],
    ):
        assert main(argv) == 2
        out = capsys.readouterr()
        assert out.out == "" and message in one_line(out.err) and str(bad) in out.err


def test_map_refuses_pixels_outside_the_image(work, tmp_path, capsys):
    assert main(["map", "--calibration", str(work / "cal.json"), "50000", "10"]) == 2
    assert one_line(capsys.readouterr().err).endswith(
        "pixel (50000, 10) is outside the calibrated 1280 x 720 px image; 1 such point(s)"
    )
    csv = tmp_path / "p.csv"
    csv.write_text("x_px,y_px\n10,10\n-3,700\n")
    assert main(["map", "--calibration", str(work / "cal.json"), "--pixels", str(csv), "--json"]) == 2
    out = capsys.readouterr()
    assert out.out == "" and f"{csv}: point 2: pixel (-3, 700) is outside" in one_line(out.err)


# ---- configs and the command line ------------------------------------------------------------
@pytest.mark.parametrize(
    "key,value",
    [
        ("sim.speed_mm_s", "nan"),
        ("planning.offset_x_mm", "inf"),
        ("arm.serial.speed_mm_s", "-inf"),
        ("parts.max_part_width_mm", "nan"),
    ],
)
def test_nan_and_inf_config_values_are_refused(tmp_path, capsys, key, value):
    *section, name = key.split(".")
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[{'.'.join(section)}]\n{name} = {value}\n")
    assert main(["--config", str(cfg), "--dry-run", "--log-dir", str(tmp_path / "logs")]) == 2
    line = one_line(capsys.readouterr().err)
    assert f"invalid config: {key}: Input should be a finite number" in line


@pytest.mark.parametrize(
    "argv",
    [
        ["--dry-run", "--offset-x-mm", "nan"],
        ["--dry-run", "--offset-y-mm", "inf"],
        ["jog", "--arm", "mock", "--to", "nan", "0", "50"],
    ],
)
def test_nan_on_the_command_line_is_refused(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and "not a finite number" in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(
    "points,message",
    [
        (["1", "nan", "0", "13", "10", "0", "144", "0", "10"], "circle 1: robot position (nan, 0.0) is not a finite"),
        (["1", "10", "20"] * 3, "teaching needs 3 or more distinct circles, got [1]"),
        (["1", "10", "20", "1", "10", "20", "13", "30", "20", "144", "10", "40"], "circle(s) [1] given more than once"),
        (["1", "10", "20", "2", "32", "20", "13", "274", "20"], "circles [1, 2, 13] lie on one line"),
    ],
    ids=["nan", "same-circle", "repeated", "collinear"],
)
def test_teach_refuses_points_that_cannot_fix_the_frame(tmp_path, capsys, points, message):
    argv = ["teach", "--dry-run"]
    for i in range(0, len(points), 3):
        argv += ["--point", *points[i : i + 3]]
    assert main(argv) == 2
    assert message in one_line(capsys.readouterr().err)


# ---- other outputs ---------------------------------------------------------------------------
def locate_annotate(work: Path, out) -> list[str]:
    """`run-cell locate` on the plate with its annotated image written to `out`."""
    return [
        "locate",
        "--image",
        str(work / "plate.png"),
        "--calibration",
        str(work / "cal.json"),
        "--annotate",
        str(out),
    ]


def test_locate_annotate_with_an_unknown_extension(work, tmp_path, capsys):
    out = tmp_path / "out.xyz"
    assert main(locate_annotate(work, out)) == 2
    assert (
        one_line(capsys.readouterr().err) == f"run-cell locate: error: {out}: cannot write an image as '.xyz' "
        "(hint: use .png or .jpg)"
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("failure,code", [(errno.ENOSPC, 3), (errno.EROFS, 2)])
def test_locate_annotate_and_calibrate_demo_on_a_failing_disk(work, tmp_path, capsys, monkeypatch, failure, code):
    real_open = open

    def failing_open(file, mode="r", *a, **k):
        if "w" in mode and str(file).startswith(str(tmp_path)):
            raise OSError(failure, os.strerror(failure), str(file))
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr("builtins.open", failing_open)
    assert main(locate_annotate(work, tmp_path / "a.png")) == code
    assert os.strerror(failure) in one_line(capsys.readouterr().err)
    assert main(["calibrate-demo", "--out-dir", str(tmp_path / "demo")]) == code
    err = capsys.readouterr().err
    assert os.strerror(failure) in one_line(err) and "plate.png" in err
    assert leftovers(tmp_path) == []


def test_run_log_dir_that_cannot_be_created(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["--dry-run", "--log-dir", str(blocker / "logs")]) == 2
    line = one_line(capsys.readouterr().err)
    assert line.startswith(f"run-cell: error: run.log_dir {blocker / 'logs'}: cannot create the audit log")
