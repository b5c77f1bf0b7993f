"""Interoperability: Eclipse Tahu's own Sparkplug B codec (npm `sparkplug-payload`, the reference
JavaScript implementation) decodes what the cell encodes, and the cell decodes what Tahu encodes.

sparkplug-payload is installed with npm into this test run's temporary folder (never the
repository), once per session. No `node`: skipped, saying so."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from cell.telemetry.sparkplug import DataType, Metric, decode, payload, value_of

TAHU = "sparkplug-payload@1.0.3"
SCRIPT = Path(__file__).parent / "node" / "sparkplug_interop.cjs"
pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(300),
    pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed: no Tahu codec to test against"),
]


@pytest.fixture(scope="session")
def tahu_modules(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.getbasetemp().parent / "sparkplug-payload"
    root.mkdir(exist_ok=True)
    env = {**os.environ, "HOME": str(root), "npm_config_cache": str(root / ".npm")}
    with open(root / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / ".installed").exists():
            npm = shutil.which("npm")
            if npm is None:
                pytest.fail("node is installed but npm is not: cannot install sparkplug-payload")
            (root / "package.json").write_text('{"name": "sparkplug-interop-test", "private": true}\n')
            cmd = [npm, "install", "--no-audit", "--no-fund", "--omit=dev", "--ignore-scripts", TAHU]
            run = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=240, env=env)
            if run.returncode != 0:
                pytest.fail(f"npm install {TAHU} failed (exit {run.returncode}):\n{run.stderr[-3000:]}")
            (root / ".installed").write_text(TAHU)
    return root / "node_modules"


def test_tahu_reads_the_cell_and_the_cell_reads_tahu(tahu_modules: Path):
    sent = [
        Metric("bdSeq", DataType.INT64, 3),
        Metric("Node Control/Rebirth", DataType.BOOLEAN, False),
        Metric("Counters/Picked", DataType.UINT64, 2**40),
        Metric("Rate/Parts Per Minute", DataType.DOUBLE, 12.5),
        Metric("Last Pick/Jaw Angle deg", DataType.DOUBLE, None),
        Metric("State", DataType.STRING, "ContinuousExecution"),
        Metric("Alarm/Warnings", DataType.UINT64, 2),
        Metric("offset", DataType.INT32, -5),
    ]
    run = subprocess.run(
        ["node", str(SCRIPT), payload(sent, seq=0, birth=True).hex()],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "NODE_PATH": str(tahu_modules)},
    )
    assert run.returncode == 0, run.stderr
    tahu = json.loads(run.stdout)
    assert str(tahu["seq"]) == "0"
    expected = [
        ("bdSeq", "Int64", "3"),
        ("Node Control/Rebirth", "Boolean", False),
        ("Counters/Picked", "UInt64", str(2**40)),
        ("Rate/Parts Per Minute", "Double", 12.5),
        ("Last Pick/Jaw Angle deg", "Double", None),
        ("State", "String", "ContinuousExecution"),
        ("Alarm/Warnings", "UInt64", "2"),
        ("offset", "Int32", -5),
    ]
    assert [(m["name"], m["type"], m["value"]) for m in tahu["metrics"]] == expected

    command = decode(bytes.fromhex(tahu["command"]))
    assert command.timestamp == 1700000000000 and not command.HasField("seq")
    assert [(m.name, value_of(m)) for m in command.metrics] == [
        ("Node Control/Rebirth", True),
        ("small", -3),
        ("big", -7),
    ]
