"""Interoperability: a client on another OPC UA stack (node-opcua) drives the cell's Machine
Vision model knowing only the specification (tests/node/mv_client.cjs).

node-opcua-client is installed with npm into this test run's temporary folder (never the
repository), once per test session for all workers. No `node`: skipped, saying so. `node`
present but the install fails: the test fails, with npm's output."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.mv_harness import MachineVisionHarness, shared_cache_dir

NODE_OPCUA = "node-opcua-client@2.160.0"  # the last release that runs on Node 20 (later ones need Node >= 22.13)
CLIENT = Path(__file__).parent / "node" / "mv_client.cjs"
pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(420),
    pytest.mark.skipif(
        shutil.which("node") is None, reason="node is not installed: no second OPC UA stack to test with"
    ),
]


@pytest.fixture(scope="session")
def node_modules(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.getbasetemp().parent / "node-opcua"
    root.mkdir(exist_ok=True)
    with open(root / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = root / ".installed"
        if not done.exists():
            npm = shutil.which("npm")
            if npm is None:
                pytest.fail("node is installed but npm is not: cannot install node-opcua-client for the interop test")
            (root / "package.json").write_text('{"name": "mv-interop-test", "private": true}\n')
            cmd = [npm, "install", "--no-audit", "--no-fund", "--omit=dev", "--ignore-scripts", NODE_OPCUA]
            run = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=300, env=_env(root))
            if run.returncode != 0:
                pytest.fail(
                    f"npm install {NODE_OPCUA} failed (exit {run.returncode}):\n{run.stdout[-2000:]}\n{run.stderr[-3000:]}"
                )
            done.write_text(NODE_OPCUA)
    return root / "node_modules"


def _env(home: Path) -> dict[str, str]:
    """npm's cache and node-opcua's client certificate go under the test's folder, not the user's home."""
    return {
        **os.environ,
        "HOME": str(home),
        "XDG_CONFIG_HOME": str(home / ".config"),
        "npm_config_cache": str(home / ".npm"),
    }


def test_node_opcua_client_drives_the_vision_system(
    node_modules: Path, tmp_path_factory: pytest.TempPathFactory, tmp_path: Path
) -> None:
    harness = MachineVisionHarness(tmp_path, shared_cache_dir(tmp_path_factory)).start()
    try:
        env = {**_env(tmp_path / "home"), "NODE_PATH": str(node_modules)}
        run = subprocess.run(
            ["node", str(CLIENT), harness.endpoint], capture_output=True, text=True, timeout=240, env=env
        )
        assert run.returncode == 0, f"node-opcua client failed:\n{run.stdout[-2000:]}\n{run.stderr[-3000:]}"
        seen = json.loads(run.stdout.strip().splitlines()[-1])
        started = [req for cmd, origin, req in harness.service.commands if cmd.value == "StartContinuous"]
        assert len(started) == 1 and started[0].as_json() == {
            "product_id": "kit-node",
            "part_id": "part-node",
            "meas_id": "meas-node",
        }
        assert seen["events"] >= 2 and seen["resultId"] == f"{seen['jobId']}/1" and seen["resultState"] == 1
        assert seen["stateAfterStop"] == "Ready"
        assert seen["preparedInternalId"] == "nuts-only" and harness.service.recipe == "nuts-only"
        assert harness.results_job_ids() == [seen["jobId"]]
    finally:
        harness.stop()
