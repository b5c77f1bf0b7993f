"""Roles hold on OPC UA and the screen (issue 21), end to end: `run-cell serve --dry-run` with a
users file, a viewer who may Halt but not start, an operator who may start and reset; the screen
over HTTPS only with a Secure, HttpOnly, SameSite=Strict cookie."""

from __future__ import annotations

import asyncio
import ssl

import httpx
import pytest
from asyncua import ua

from cell.access.users import UserEntry, hash_password, write_users
from cell.core.events import Role
from tests.probes import Credentials, make_client_certificate, secure_client
from tests.serve_process import ServeProcess

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

USERS = {"vera": ("vera-pass-1", Role.VIEWER), "otto": ("otto-pass-1", Role.OPERATOR)}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    work = tmp_path_factory.mktemp("roles")
    certs = work / "certs"
    write_users(work / "users.json", [UserEntry(n, r, hash_password(pw, 1000)) for n, (pw, r) in USERS.items()])
    (work / "line.toml").write_text(
        f'[service]\nusers_file = "users.json"\ncertificate_dir = "{certs}"\n'
        "[service.login]\nmax_failures_per_user = 3\nbackoff_first_s = 0\n"
    )
    key, cert, uri = asyncio.run(make_client_certificate(work / "client", "plc"))
    (certs / "trusted").mkdir(parents=True)
    (certs / "trusted" / "plc.der").write_bytes(cert.read_bytes())
    serve = ServeProcess(work, "--config", str(work / "line.toml"))
    yield serve, Credentials(key, cert, uri, certs / "server-cert.der"), certs
    assert serve.stop() == 0, "\n".join(serve.lines[-30:])


async def call_as(serve: ServeProcess, credentials: Credentials, user: str, *methods: str) -> list[str]:
    """Each method's outcome for `user`: "Good" or the status code's name."""
    client = await secure_client(
        f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", credentials, user=user, password=USERS[user][0]
    )
    out = []
    async with client:
        ns = await client.get_namespace_index("urn:pick-cell")
        cell = await client.nodes.objects.get_child(f"{ns}:Cell")
        for method in methods:
            try:
                await cell.call_method(f"{ns}:{method}")
                out.append("Good")
            except ua.UaStatusCodeError as e:
                out.append(ua.StatusCode(e.code).name)
    return out


async def halted(serve: ServeProcess, credentials: Credentials, timeout_s: float = 60.0) -> None:
    client = await secure_client(
        f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", credentials, user="vera", password=USERS["vera"][0]
    )
    async with client:
        ns = await client.get_namespace_index("urn:pick-cell")
        state = await client.nodes.objects.get_child([f"{ns}:Cell", f"{ns}:VisionState"])
        end = asyncio.get_running_loop().time() + timeout_s
        while (value := await state.read_value()) != "Halted":
            assert asyncio.get_running_loop().time() < end, f"VisionState {value!r}, not Halted"
            await asyncio.sleep(0.1)


def test_opcua_roles(served):
    serve, credentials, _ = served
    assert asyncio.run(call_as(serve, credentials, "vera", "StartSingleJob", "Halt", "Reset")) == [
        "BadUserAccessDenied",  # a viewer may not start
        "Good",  # anyone who may see the cell may Halt
        "BadUserAccessDenied",  # nor reset
    ]
    asyncio.run(halted(serve, credentials))  # a Halt is Halted once the arm's safe stop is done
    assert asyncio.run(call_as(serve, credentials, "otto", "Reset")) == ["Good"]  # an operator may


def test_the_screen_is_https_only_with_roles(served):
    serve, _, certs = served
    assert serve.url.startswith("https://")
    trust = ssl.create_default_context(cafile=str(certs / "screen-cert.pem"))
    with httpx.Client(base_url=serve.url, verify=trust, timeout=10) as viewer:
        r = viewer.post("api/login", json={"user": "vera", "password": "vera-pass-1"})
        cookie = r.headers["set-cookie"]
        assert r.status_code == 200 and "HttpOnly" in cookie and "Secure" in cookie and "SameSite=strict" in cookie
        assert r.headers["strict-transport-security"].startswith("max-age=")
        token = r.json()["csrf"]
        assert viewer.post("api/command/StartSingleJob", headers={"x-csrf-token": token}).status_code == 403
    with pytest.raises(httpx.HTTPError):
        httpx.get(serve.url.replace("https://", "http://"), timeout=5)


def test_guessing_a_password_on_the_screen_raises_a_warning_alarm_on_opc_ua(served):
    serve, credentials, certs = served
    trust = ssl.create_default_context(cafile=str(certs / "screen-cert.pem"))
    with httpx.Client(base_url=serve.url, verify=trust, timeout=10) as guesser:
        codes = [
            guesser.post("api/login", json={"user": "mallory", "password": f"guess-{i}"}).status_code for i in range(4)
        ]
    assert codes[:3] == [401, 401, 401] and codes[3] == 429  # the fourth try is not even checked

    async def warnings() -> list[str]:
        client = await secure_client(
            f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", credentials, user="otto", password=USERS["otto"][0]
        )
        async with client:
            ns = await client.get_namespace_index("urn:pick-cell")
            return await (await client.nodes.objects.get_child([f"{ns}:Cell", f"{ns}:ActiveWarnings"])).read_value()

    found = asyncio.run(warnings())
    assert any("3 failed logins for user mallory: locked out" in w for w in found), found
