"""Many cells, one broker: five `run-cell serve --dry-run` processes (small 960 x 540 cameras) publish
Sparkplug B to one mosquitto; one listener counts each cell's picks from its DDATA, and each
count equals the cell's own (its /metrics, parsed with prometheus_client's parser)."""

from __future__ import annotations

import concurrent.futures
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.mqtt_broker import Broker, Listener, needs_mosquitto, picks_seen, wait_for
from tests.ports import free_port
from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420), needs_mosquitto]
CELLS = 5

CONFIG = """
[camera]
width_px = 960
height_px = 540
[sim]
reference_marks_mm = []
[sim.feeder]
parts_per_minute = 0
[run]
log_dir = "logs"
[service]
capture_interval_s = 0.2
[telemetry.mqtt]
url = "{url}"
group_id = "fleet"
edge_node_id = "{node}"
"""


def own_counts(url: str) -> dict[str, float]:
    """The cell's own numbers from its /metrics: picks by outcome and its state."""
    out: dict[str, float] = {}
    for family in text_string_to_metric_families(httpx.get(url + "metrics", timeout=30).text):
        for s in family.samples:
            if s.name == "cell_picks_total":
                out[s.labels["outcome"]] = out.get(s.labels["outcome"], 0) + s.value
            elif s.name == "cell_state" and s.value == 1:
                out["state:" + s.labels["cell_state"]] = 1
            elif s.name == "cell_shift_parts" and s.labels["counter"] in ("picked_bolts", "picked_nuts"):
                out["shift_picked"] = out.get("shift_picked", 0) + s.value
    return out


def start_job(url: str) -> None:
    with httpx.Client(base_url=url, timeout=30) as client:
        csrf = client.get("/api/session").json()["csrf"]
        reply = client.post("/api/command/StartSingleJob", headers={"x-csrf-token": csrf})
        assert reply.status_code == 200, reply.text


def test_five_cells_one_broker_every_pick_counted_per_cell(tmp_path):
    with Broker(tmp_path) as broker:
        listener = Listener(broker.port, group_id="fleet")
        nodes = [f"cell-{i}" for i in range(1, CELLS + 1)]
        for node in nodes:
            (tmp_path / node).mkdir()
            (tmp_path / node / "cell.toml").write_text(CONFIG.format(url=broker.url, node=node))
        procs: dict[str, ServeProcess] = {}
        try:
            with concurrent.futures.ThreadPoolExecutor(CELLS) as pool:
                futures = {
                    n: pool.submit(ServeProcess, tmp_path / n, "--config", "cell.toml", timeout_s=240) for n in nodes
                }
                procs = {n: f.result() for n, f in futures.items()}
            for node in nodes:
                wait_for(lambda n=node: listener.of("DBIRTH", n), 60, f"{node}'s DBIRTH")
            for node in nodes:
                start_job(procs[node].url)
            for node in nodes:
                url = procs[node].url
                # /metrics counts picks in its own subscriber, which may lag the state a little: wait until
                # it has counted what the shift's counters say
                own = wait_for(
                    lambda u=url: (
                        (c := own_counts(u)).get("state:Ready")
                        and c.get("picked")
                        and c["picked"] == c.get("shift_picked")
                        and c
                    ),
                    300,
                    f"{node} done, its /metrics caught up",
                )
                wait_for(lambda n=node, c=own: picks_seen(listener, n) >= c["picked"], 60, f"{node}'s picks published")
                assert picks_seen(listener, node) == own["picked"] == own["shift_picked"] == 17, node
        finally:
            codes = {n: p.stop() for n, p in procs.items()}
        assert codes == dict.fromkeys(nodes, 0)
        wait_for(lambda: {m.edge_node_id for m in listener.of("NDEATH")} == set(nodes), 60, "every cell's NDEATH")
        assert {m.edge_node_id for m in listener.of("NBIRTH")} == set(nodes)
        listener.close()


def test_serve_refuses_a_missing_broker_password(tmp_path):
    """The password comes from the environment only: a missing variable stops serve with one clear line."""
    (tmp_path / "cell.toml").write_text(
        CONFIG.format(url="mqtt://127.0.0.1:1", node="cell-x")
        + 'user = "cell-x"\npassword_env = "CELL_X_MQTT_PASSWORD_UNSET"\n'
    )
    env = {k: v for k, v in os.environ.items() if k != "CELL_X_MQTT_PASSWORD_UNSET"}
    ports = ["--http-port", str(free_port()), "--opcua-port", str(free_port())]
    done = subprocess.run(
        [sys.executable, "-m", "cell.cli", "serve", "--dry-run", "--config", "cell.toml", *ports],
        cwd=tmp_path,
        env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    assert "CELL_X_MQTT_PASSWORD_UNSET is not set or empty" in done.stderr
    assert "Traceback" not in done.stderr
