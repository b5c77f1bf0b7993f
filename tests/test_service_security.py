"""Who may connect: loopback by default, beyond it only with a user and a hashed or env password."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from cell.access.network import is_loopback
from cell.access.security import check_exposure, hash_password, password_ok
from cell.errors import ConfigError
from cell.service.config import ServiceConfig

pytestmark = pytest.mark.timeout(60)  # two cases run run-cell serve as a subprocess

REPO = Path(__file__).resolve().parents[1]


def test_loopback_names():
    """One rule for every server (cell.access.network): literal loopback addresses and localhost only."""
    assert all(is_loopback(h) for h in ("127.0.0.1", "127.0.0.2", "::1", "[::1]", "localhost", "LocalHost"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "192.168.1.10", "::", "no-such-host.invalid", "cellpc.local"))


def test_a_hashed_password_checks_and_is_not_stored_in_clear():
    stored = hash_password("s3cret-pass", iterations=1000)
    assert "s3cret" not in stored and stored.startswith("pbkdf2_sha256$1000$")
    cfg = ServiceConfig(user="plc", password_hash=stored)
    assert password_ok(cfg, "plc", "s3cret-pass")
    assert not password_ok(cfg, "plc", "s3cret-pasS") and not password_ok(cfg, "root", "s3cret-pass")
    assert not password_ok(cfg, None, None)


def test_an_env_password(monkeypatch):
    cfg = ServiceConfig(user="plc", password_env="CELL_PW_TEST")
    assert not password_ok(cfg, "plc", "")  # unset: nobody gets in
    monkeypatch.setenv("CELL_PW_TEST", "from-env")
    assert password_ok(cfg, "plc", "from-env") and not password_ok(cfg, "plc", "other")


def test_beyond_loopback_needs_a_user_and_a_password(monkeypatch):
    check_exposure(ServiceConfig())  # loopback: fine without
    for cfg, missing in (
        (ServiceConfig(host="0.0.0.0"), "service.user"),
        (ServiceConfig(host="10.0.0.5", user="plc"), "service.password_hash"),
        (ServiceConfig(host="10.0.0.5", user="plc", password_env="CELL_PW_UNSET"), "CELL_PW_UNSET"),
    ):
        with pytest.raises(ConfigError, match=missing):
            check_exposure(cfg)
    with pytest.raises(ConfigError, match="not a pbkdf2_sha256"):
        check_exposure(ServiceConfig(host="0.0.0.0", user="plc", password_hash="plain-text"))
    check_exposure(ServiceConfig(host="0.0.0.0", user="plc", password_hash=hash_password("x" * 8, iterations=1000)))


def test_serve_refuses_a_bad_port_in_one_line():
    r = subprocess.run(
        [sys.executable, "-m", "cell.cli", "serve", "--dry-run", "--opcua-port", "70000"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert r.returncode == 2 and "--opcua-port 70000: a port is 1-65535" in r.stderr and "Traceback" not in r.stderr


def test_serve_refuses_a_taken_port_before_building_anything(tmp_path):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "cell.cli",
                "serve",
                "--dry-run",
                "--log-dir",
                str(tmp_path),
                "--opcua-port",
                str(port),
            ],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO,
        )
    assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{port}" in r.stderr and "Traceback" not in r.stderr
    assert not list(tmp_path.glob("cell-*.jsonl"))  # refused before the service opened its log
