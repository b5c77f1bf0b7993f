"""`run-cell serve` in a subprocess, driven by asyncua's client as a PLC would: knowing only the
namespace URI and the BrowseNames (Objects/Cell/...), nothing of the server's Python objects."""

from __future__ import annotations

import asyncio
import os
import select
import signal
import socket
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest
from asyncua import Client, ua

from cell.audit import read_events
from tests.ports import free_port

pytestmark = pytest.mark.timeout(240)  # runs run-cell serve as a subprocess

REPO = Path(__file__).resolve().parents[1]
NS = "urn:pick-cell"
COUNTERS = ["PickedBolts", "PickedNuts", "Misses", "Retries", "Failed", "Unreachable", "UnknownLeft"]
VARIABLES = [
    "VisionState",
    "CellState",
    *COUNTERS,
    "Shift",
    "LastPickClass",
    "LastPickTableMm",
    "LastPickRobotMm",
    "LastPickAngleDeg",
    "LastPickOutcome",
    "LastPickTime",
    "ActiveAlarm",
    "Heartbeat",
    "CalibrationModel",
    "CalibrationCvRmsMm",
    "CalibrationCvMaxMm",
    "CalibrationTime",
]
METHODS = ["StartSingleJob", "StartContinuous", "Stop", "Pause", "Resume", "Halt", "Reset"]


class Serve:
    """`run-cell serve ...` in a subprocess; ready when it prints its `ready:` line."""

    def __init__(self, tmp: Path, *args: str, env: dict | None = None):
        self.port, self.http_port = free_port(), free_port()
        self.log_dir = tmp / "logs"
        cmd = [
            sys.executable,
            "-m",
            "cell.cli",
            "serve",
            "--log-dir",
            str(self.log_dir),
            "--opcua-port",
            str(self.port),
            "--http-port",
            str(self.http_port),
            *args,
        ]
        self.proc = subprocess.Popen(
            cmd,
            cwd=tmp,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})},
        )
        self.url = f"opc.tcp://127.0.0.1:{self.port}/cell"
        self.output = ""

    def wait_ready(self, timeout_s: float = 90.0) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            ready, _, _ = select.select([self.proc.stdout], [], [], 0.5)
            if ready:
                line = self.proc.stdout.readline()
                self.output += line
                if line.startswith("ready:"):
                    return line
                if not line and self.proc.poll() is not None:
                    break
        self.stop()
        raise AssertionError(f"serve did not get ready:\n{self.output}")

    def stop(self, timeout_s: float = 30.0) -> int:
        if self.proc.stdout.closed:
            return self.proc.returncode
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait(5)
        self.output += self.proc.stdout.read()
        self.proc.stdout.close()
        return rc


class Cell:
    """A client's view of Objects/Cell, found by BrowseNames."""

    def __init__(self, client: Client):
        self.client = client

    async def open(self) -> Cell:
        self.ns = await self.client.get_namespace_index(NS)
        self.node = await self.client.nodes.objects.get_child(f"{self.ns}:Cell")
        return self

    async def var(self, name: str):
        return await self.node.get_child(f"{self.ns}:{name}")

    async def read(self, name: str):
        return await (await self.var(name)).read_value()

    async def call(self, method: str, *args):
        return await self.node.call_method(f"{self.ns}:{method}", *args)

    async def wait(self, name: str, cond, timeout_s: float = 30.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            value = await self.read(name)
            if cond(value):
                return value
            await asyncio.sleep(0.1)
        raise AssertionError(f"{name} = {value!r} after {timeout_s} s")


def with_cell(url: str, body, timeout_s: float = 60.0):
    async def go():
        async with Client(url, timeout=10, watchdog_intervall=15) as client:
            return await body(await Cell(client).open())

    return asyncio.run(asyncio.wait_for(go(), timeout_s))


class Changes:
    """A subscription's handler: data changes by node name, and events."""

    def __init__(self):
        self.values: dict[str, list] = {}
        self.events: list = []

    def datachange_notification(self, node, val, data):
        self.values.setdefault(node.nodeid.Identifier, []).append(val)

    def event_notification(self, event):
        self.events.append(event.get_event_props_as_fields_dict())


async def the_node_tree_by_browsenames(cell: Cell):
    names = {(await n.read_browse_name()).Name for n in await cell.node.get_children()}
    assert set(VARIABLES) | set(METHODS) <= names
    assert await cell.read("VisionState") == "Ready"
    types = {name: (await (await cell.var(name)).read_data_type_as_variant_type()) for name in VARIABLES}
    assert all(types[c] == ua.VariantType.UInt32 for c in COUNTERS + ["Heartbeat"])
    assert types["LastPickTableMm"] == ua.VariantType.Double and types["LastPickTime"] == ua.VariantType.DateTime
    assert await cell.read("CalibrationCvRmsMm") > 0 and await cell.read("CalibrationModel")
    stamp = (await (await cell.var("Heartbeat")).read_data_value()).SourceTimestamp
    age_s = (datetime.now(UTC) - stamp.replace(tzinfo=UTC)).total_seconds()
    assert -300 < age_s < 300  # values carry their own source timestamp (today's, not none or 1601), however loaded
    h0 = await cell.read("Heartbeat")
    await cell.wait("Heartbeat", lambda h: h >= h0 + 2)  # it keeps beating while nothing else changes
    later = (await (await cell.var("Heartbeat")).read_data_value()).SourceTimestamp
    assert later > stamp  # each beat is a fresh value with its own source timestamp


async def continuous_picks_rise_pause_resume_stop(cell: Cell):
    changes = Changes()
    sub = await cell.client.create_subscription(100, changes)
    await sub.subscribe_data_change([await cell.var(n) for n in ("PickedBolts", "PickedNuts", "CellState")])
    pick_type = await cell.client.nodes.base_event_type.get_child(f"{cell.ns}:PickEventType")
    await sub.subscribe_events(cell.node, pick_type)
    before = await cell.read("PickedBolts") + await cell.read("PickedNuts")
    await cell.call("StartContinuous")
    assert await cell.read("VisionState") == "ContinuousExecution"
    end = time.monotonic() + 40
    while sum(changes.values.get(n, [0])[-1] for n in ("PickedBolts", "PickedNuts")) < before + 3:
        assert time.monotonic() < end, f"picks did not rise: {changes.values}"
        await asyncio.sleep(0.1)
    assert await cell.read("LastPickOutcome") == "picked" and len(await cell.read("LastPickRobotMm")) == 3
    first = changes.events[0]  # each pick is also an event from Cell
    assert first["PartClass"].Value in ("bolt", "nut") and first["Outcome"].Value == "picked"
    assert len(first["RobotMm"].Value) == 3 and "picked at table" in first["Message"].Value.Text
    await cell.call("Pause")
    await cell.wait("CellState", lambda s: s == "PAUSED")
    held = await cell.read("PickedNuts") + await cell.read("PickedBolts")
    await asyncio.sleep(1.0)
    assert await cell.read("PickedNuts") + await cell.read("PickedBolts") == held
    await cell.call("Resume")
    await cell.wait("CellState", lambda s: s != "PAUSED")
    await cell.call("Stop")
    await cell.wait("VisionState", lambda s: s == "Ready")
    assert await cell.read("CellState") == "IDLE"  # between jobs it follows VisionState Ready
    assert "PAUSED" in changes.values["CellState"]
    await sub.delete()


async def wrong_states_are_bad_invalid_state(cell: Cell):
    for method in ("Reset", "Pause", "Resume", "Stop"):
        with pytest.raises(ua.UaStatusCodeError) as e:
            await cell.call(method)
        assert e.value.code == ua.StatusCodes.BadInvalidState
    assert await cell.read("VisionState") == "Ready"
    with pytest.raises(ua.UaStatusCodeError) as e:
        await cell.call("StartSingleJob", ua.Variant("rm -rf /", ua.VariantType.String))
    assert e.value.code == ua.StatusCodes.BadTooManyArguments
    await cell.call("StartContinuous")
    for method in ("StartSingleJob", "StartContinuous", "Reset", "Resume"):
        with pytest.raises(ua.UaStatusCodeError) as e:
            await cell.call(method)
        assert e.value.code == ua.StatusCodes.BadInvalidState
    assert await cell.read("VisionState") == "ContinuousExecution"
    with pytest.raises(ua.UaStatusCodeError):  # clients only read
        await (await cell.var("VisionState")).write_value("Ready")
    await cell.call("Stop")
    await cell.wait("VisionState", lambda s: s == "Ready")


async def halt_then_reset(cell: Cell):
    await cell.call("StartContinuous")
    await cell.wait("CellState", lambda s: s in ("PICK", "PLACE", "CAPTURE", "WAIT"))
    await cell.call("Halt")
    await cell.wait("VisionState", lambda s: s == "Halted")
    with pytest.raises(ua.UaStatusCodeError) as e:
        await cell.call("StartContinuous")
    assert e.value.code == ua.StatusCodes.BadInvalidState
    await cell.call("Reset")
    assert await cell.read("VisionState") == "Ready"


def garbage_and_a_vanishing_client_leave_the_cell_running(serve: Serve):
    with_cell(serve.url, lambda cell: cell.call("StartContinuous"))
    with socket.create_connection(("127.0.0.1", serve.port), timeout=5) as s:
        s.sendall(b"HELF\x00\x00\x00\x10garbage-garbage!" * 4)
    client = Client(serve.url, timeout=5)

    async def vanish():  # a session opened, then the connection cut without a goodbye
        await client.connect()
        client.uaclient.protocol.transport.abort()

    asyncio.run(vanish())

    async def check(cell):
        assert await cell.read("VisionState") == "ContinuousExecution"
        await cell.call("Stop")
        await cell.wait("VisionState", lambda s: s == "Ready")

    with_cell(serve.url, check)
    assert serve.proc.poll() is None


def test_a_plc_drives_the_built_in_shift(tmp_path):
    """`run-cell serve --dry-run`, no config: one server and the whole conversation in order
    (the steps share its state, so they are one test, whichever worker runs it)."""
    serve = Serve(tmp_path, "--dry-run")
    try:
        assert f"ready: OPC UA {serve.url}; screen http://127.0.0.1:{serve.http_port}/ " in serve.wait_ready()
        for step in (
            the_node_tree_by_browsenames,
            continuous_picks_rise_pause_resume_stop,
            wrong_states_are_bad_invalid_state,
            halt_then_reset,
        ):
            with_cell(serve.url, step)
        garbage_and_a_vanishing_client_leave_the_cell_running(serve)
        with_cell(serve.url, lambda cell: cell.call("StartContinuous"))
        with_cell(serve.url, lambda cell: cell.wait("CellState", lambda s: s in ("PICK", "PLACE", "CAPTURE", "WAIT")))
    finally:
        rc = serve.stop()
    assert rc == 0  # SIGTERM mid-job: the job halted, the process gone
    assert "stopped: cell halted safely" in serve.output
    events = [e for f in sorted(serve.log_dir.glob("cell-*.jsonl")) for e in read_events(f)]
    assert events[-1]["kind"] == "service_stop"
    assert [e["target"] for e in events if e["kind"] == "vision_state"][-1] == "Halted"


def test_beyond_loopback_without_credentials_is_refused(tmp_path):
    (tmp_path / "open.toml").write_text('[service]\nhost = "0.0.0.0"\n')
    serve = Serve(tmp_path, "--dry-run", "--config", str(tmp_path / "open.toml"))
    out, _ = serve.proc.communicate(timeout=60)
    assert serve.proc.returncode == 2
    assert "beyond loopback" in out and "service.user" in out and "Traceback" not in out


@pytest.mark.slow
@pytest.mark.parametrize("arm", ["serial", "dynamixel"])
def test_emulated_arms_pick_through_the_service(tmp_path, arm):
    serve = Serve(tmp_path, "--dry-run", "--arm", arm)
    try:
        serve.wait_ready()

        async def body(cell):
            await cell.call("StartContinuous")
            await cell.wait("PickedNuts", lambda n: n >= 2, timeout_s=60)
            await cell.call("Stop")
            await cell.wait("VisionState", lambda s: s == "Ready", timeout_s=30)
            assert await cell.read("Failed") == 0 and await cell.read("Misses") == 0

        with_cell(serve.url, body, timeout_s=120)
    finally:
        assert serve.stop() == 0
    assert "Traceback" not in serve.output


@pytest.mark.slow
def test_beyond_loopback_with_a_user_is_encrypted_and_checks_the_password(tmp_path):
    """host 0.0.0.0 with a user and a password from the environment: Basic256Sha256 SignAndEncrypt only,
    a certificate made on first start, the right password in, a wrong one and an unencrypted client out."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    certs = tmp_path / "certs"
    (tmp_path / "exposed.toml").write_text(
        f'[service]\nhost = "0.0.0.0"\nuser = "plc"\npassword_env = "CELL_TEST_PW"\ncertificate_dir = "{certs}"\n'
        "[camera]\nwidth_px = 960\nheight_px = 540\n"
    )
    key, cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"
    asyncio.run(
        setup_self_signed_certificate(
            key, cert, "urn:test-plc", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test-plc"}
        )
    )
    (certs / "trusted").mkdir(parents=True)  # the trust list (issue 21): this client's certificate is known
    (certs / "trusted" / "test-plc.der").write_bytes(cert.read_bytes())
    serve = Serve(
        tmp_path, "--dry-run", "--config", str(tmp_path / "exposed.toml"), env={"CELL_TEST_PW": "correct horse"}
    )
    try:
        ready = serve.wait_ready()  # bound to every address: the line names ones a client can type (issue 33)
        assert ready.startswith("ready: OPC UA opc.tcp://") and "0.0.0.0" not in ready
        assert f"opc.tcp://127.0.0.1:{serve.port}/cell" in ready
        assert (certs / "server-cert.der").is_file() and (certs / "server-key.pem").stat().st_mode & 0o077 == 0

        async def attempt(password: str | None, secure: bool = True):
            client = Client(serve.url, timeout=10, watchdog_intervall=15)
            client.application_uri = "urn:test-plc"  # as its certificate says (checked at CreateSession)
            if secure:
                await client.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
            if password is not None:
                client.set_user("plc")
                client.set_password(password)
            async with client:
                cell = await Cell(client).open()
                await cell.call("Halt")  # the user may command the cell, not only read it
                halted = await cell.wait("VisionState", lambda s: s == "Halted")  # after the arm's safe stop
                await cell.call("Reset")
                return halted, await cell.read("VisionState")

        assert asyncio.run(asyncio.wait_for(attempt("correct horse"), 30)) == ("Halted", "Ready")
        with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
            asyncio.run(asyncio.wait_for(attempt("wrong"), 30))
        with pytest.raises(ua.UaStatusCodeError, match="BadIdentityTokenRejected"):  # anonymous
            asyncio.run(asyncio.wait_for(attempt(None), 30))
        # a None channel serves discovery only: its CreateSession is refused (issue 21; docs/security.md)
        with pytest.raises(ua.UaStatusCodeError, match="BadSecurityModeInsufficient"):
            asyncio.run(asyncio.wait_for(attempt("correct horse", secure=False), 30))
    finally:
        assert serve.stop() == 0
