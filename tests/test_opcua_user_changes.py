"""Removing a user, or giving them another role, ends their OPC UA sessions at once (issue 28, What to
build item 2): before, a session kept the role it logged in with until the service restarted.
`run-cell serve --dry-run` with a users file, real asyncua clients over Basic256Sha256 SignAndEncrypt,
and the change made as an admin makes it (`run-cell user remove`, or the users file rewritten)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys

import pytest
from asyncua import ua

from cell.access.users import UserEntry, hash_password, read_users, write_users
from cell.core.events import Role
from tests.probes import REPO, Credentials, make_client_certificate, secure_client, wait_until
from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

USERS = {"otto": ("otto-pass-1", Role.OPERATOR), "olga": ("olga-pass-1", Role.OPERATOR)}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    work = tmp_path_factory.mktemp("user-changes")
    certs = work / "certs"
    write_users(work / "users.json", [UserEntry(n, r, hash_password(pw, 1000)) for n, (pw, r) in USERS.items()])
    (work / "line.toml").write_text(f'[service]\nusers_file = "users.json"\ncertificate_dir = "{certs}"\n')
    key, cert, uri = asyncio.run(make_client_certificate(work / "client", "plc"))
    (certs / "trusted").mkdir(parents=True)
    (certs / "trusted" / "plc.der").write_bytes(cert.read_bytes())
    serve = ServeProcess(work, "--config", str(work / "line.toml"))
    yield serve, Credentials(key, cert, uri, certs / "server-cert.der"), work
    assert serve.stop() == 0, "\n".join(serve.lines[-30:])


def ended_log(serve: ServeProcess, work, user: str) -> bool:
    text = "\n".join(serve.lines)
    log = work / "logs"
    if log.is_dir():
        text += "".join(p.read_text(errors="replace") for p in log.rglob("*.log"))
    return f"the session of user {user!r}" in text


async def call(cell, ns: int, method: str) -> str:
    """The method's outcome: "Good", the status code's name, or "connection closed"."""
    try:
        await asyncio.wait_for(cell.call_method(f"{ns}:{method}"), 20)
        return "Good"
    except ua.UaStatusCodeError as e:
        return ua.StatusCode(e.code).name
    except (ConnectionError, ua.UaError, asyncio.CancelledError, TimeoutError) as e:
        return f"connection closed ({type(e).__name__})"


async def wait_state(cell, ns: int, want: str, timeout_s: float = 60.0) -> None:
    """Until the cell's VisionState reads `want` (the safe stop of a Halt runs on the service's worker)."""
    node = await cell.get_child(f"{ns}:VisionState")
    deadline = asyncio.get_running_loop().time() + timeout_s
    while (state := await node.read_value()) != want:
        assert asyncio.get_running_loop().time() < deadline, f"VisionState still {state}, not {want}"
        await asyncio.sleep(0.05)


async def session_across_a_change(serve, credentials, user: str, after: str, change) -> list[str]:
    """Log in as `user`, Halt and Reset (what an operator may do), make the change, call `after`, then Halt."""
    client = await secure_client(
        f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", credentials, user=user, password=USERS[user][0]
    )
    await client.connect()
    try:
        ns = await client.get_namespace_index("urn:pick-cell")
        cell = await client.nodes.objects.get_child(f"{ns}:Cell")
        outcomes = [await call(cell, ns, "Halt")]
        await wait_state(cell, ns, "Halted")  # a Halt between jobs makes the parked arm safe first
        outcomes.append(await call(cell, ns, "Reset"))
        await wait_state(cell, ns, "Ready")
        await asyncio.to_thread(change)
        outcomes.append(await call(cell, ns, after))
        outcomes.append(await call(cell, ns, "Halt"))  # anything at all, once the session ended
        return outcomes
    finally:
        try:
            await asyncio.wait_for(client.disconnect(), 10)
        except Exception:  # the server closed the connection: nothing left to close
            pass


def refused(outcome: str) -> bool:
    return outcome == "BadUserAccessDenied" or outcome.startswith("connection closed")


def test_a_removed_user_loses_their_open_session(served):
    serve, credentials, work = served

    def remove() -> None:
        done = subprocess.run(
            [sys.executable, "-m", "cell.cli", "user", "remove", "otto", "--config", str(work / "line.toml")],
            cwd=work,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 0, done.stdout + done.stderr

    outcomes = asyncio.run(session_across_a_change(serve, credentials, "otto", "Reset", remove))
    assert outcomes[:2] == ["Good", "Good"], outcomes  # an operator may Halt and Reset
    assert refused(outcomes[2]) and refused(outcomes[3]), outcomes
    wait_until(lambda: ended_log(serve, work, "otto"), 20, "the end of otto's session logged")


def test_a_role_taken_away_ends_the_session(served):
    serve, credentials, work = served

    def demote() -> None:  # what `run-cell user passwd olga --role viewer` writes, through the users file API
        users = read_users(work / "users.json")
        users["olga"] = UserEntry("olga", Role.VIEWER, users["olga"].password_hash)
        write_users(work / "users.json", users.values())

    outcomes = asyncio.run(session_across_a_change(serve, credentials, "olga", "StartSingleJob", demote))
    assert outcomes[:2] == ["Good", "Good"], outcomes
    assert refused(outcomes[2]) and refused(outcomes[3]), outcomes
    wait_until(lambda: ended_log(serve, work, "olga"), 20, "the end of olga's session logged")
