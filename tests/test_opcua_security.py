"""OPC UA beyond loopback, probed as an attacker on the plant network would (issue 21): a None
channel, a Sign-only channel, a plain-text password, an untrusted certificate and guessed
passwords are refused; a trusted, encrypted client with a user gets its role; 1,000 clients
that subscribe and vanish do not lock out a fresh one.

The server is tests/limits_server.py in a subprocess: cell.service.opcua_security's
GuardedServer, as `run-cell serve` runs it, with users op (operator) and eng (engineer)."""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
import time

import httpx
import pytest
from asyncua import Client, ua

from tests.probes import REPO, Credentials, ProbeServer, make_client_certificate, secure_client, wait_until

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

NS = "urn:pick-cell"
# the 1,000 clients: scripts/bench_security.py --only vanish
VANISHING_CLIENTS = int(os.environ.get("CELL_TEST_VANISHING_CLIENTS", "250"))


def status(server: ProbeServer) -> dict:
    return httpx.get(server.screen_url + "api/status", timeout=10).json()


async def trusted_credentials(server: ProbeServer, name: str, trust: bool = True) -> Credentials:
    key, cert, uri = await make_client_certificate(server.workdir / "clients", name)
    if trust:
        trusted = server.certs / "trusted"
        trusted.mkdir(parents=True, exist_ok=True)
        shutil.copy(cert, trusted / f"{name}.der")
    return Credentials(key, cert, uri, server.certs / "server-cert.der")


async def halt_as(client: Client) -> str:
    """Connect, call Cell.Halt, disconnect: the role the server saw (caller_origin)."""
    await client.connect()
    try:
        ns = await client.get_namespace_index(NS)
        cell = await client.nodes.objects.get_child([f"{ns}:Cell"])
        return await cell.call_method(f"{ns}:Halt")
    finally:
        await client.disconnect()


async def refusal(client: Client) -> str:
    """The status code name the server refused the client with (the test fails if it was accepted)."""
    try:
        role = await halt_as(client)
    except ua.UaStatusCodeError as e:
        return ua.StatusCode(e.code).name
    except (ConnectionError, TimeoutError) as e:
        return f"connection closed ({type(e).__name__})"
    raise AssertionError(f"the server accepted the client and ran Halt as {role!r}")


@pytest.fixture(scope="module")
def secure(tmp_path_factory):
    """A server with users: off loopback it would offer only Basic256Sha256 SignAndEncrypt."""
    server = ProbeServer(tmp_path_factory.mktemp("opcua"), users=True, limits={"login": {"backoff_first_s": 0}})
    yield server
    assert server.stop() == 0, "\n".join(server.lines[-30:])


def test_a_none_channel_serves_discovery_only(secure):
    async def probe():
        endpoints = await Client(secure.opcua_url, timeout=10).connect_and_get_server_endpoints()
        offered = {(e.SecurityPolicyUri.rsplit("#", 1)[1], e.SecurityMode.name) for e in endpoints}
        assert offered == {("Basic256Sha256", "SignAndEncrypt")}
        plain = Client(secure.opcua_url, timeout=10, watchdog_intervall=15)  # no security: a None channel
        plain.set_user("op")
        plain.set_password("op-pass-1")  # a plain-text token on a plain channel: the probe
        return await refusal(plain)

    assert asyncio.run(probe()) == "BadSecurityModeInsufficient"
    assert status(secure)["opcua_sessions"] == 0
    assert "Traceback" not in "\n".join(secure.lines)


def test_sign_only_untrusted_and_wrong_password_are_refused(secure):
    async def probe():
        good = await trusted_credentials(secure, "hmi")
        sign = await secure_client(secure.opcua_url, good, mode="Sign")
        stranger = await trusted_credentials(secure, "stranger", trust=False)
        untrusted = await secure_client(secure.opcua_url, stranger)
        wrong = await secure_client(secure.opcua_url, good, user="op", password="op-pass-2")
        return await refusal(sign), await refusal(untrusted), await refusal(wrong)

    assert asyncio.run(probe()) == ("BadSecurityModeRejected", "BadCertificateUntrusted", "BadUserAccessDenied")
    rejected = list((secure.certs / "rejected").glob("*.der"))
    assert len(rejected) == 1 and "stranger" in rejected[0].name  # saved for an admin to approve
    assert status(secure)["opcua_sessions"] == 0


def test_trusted_encrypted_users_get_their_roles_and_approval_needs_no_restart(secure):
    async def probe():
        good = await trusted_credentials(secure, "plc")
        operator = await halt_as(await secure_client(secure.opcua_url, good, user="op", password="op-pass-1"))
        engineer = await halt_as(await secure_client(secure.opcua_url, good, user="eng", password="eng-pass-1"))
        late = await trusted_credentials(secure, "late", trust=False)
        first = await refusal(await secure_client(secure.opcua_url, late))
        for saved in (secure.certs / "rejected").glob("*late*.der"):  # what an admin does: docs/security.md
            saved.rename(secure.certs / "trusted" / saved.name)
        approved = await halt_as(await secure_client(secure.opcua_url, late))
        return operator, engineer, first, approved

    assert asyncio.run(probe()) == ("operator", "engineer", "BadCertificateUntrusted", "operator")


def test_a_plain_text_password_on_a_signed_channel_is_refused(tmp_path):
    """With Sign offered too, the password must come encrypted with the policy; sent in clear it is refused."""

    class PlainTextClient(Client):
        def _add_user_auth(self, params, username, password):
            super()._add_user_auth(params, username, password)
            params.UserIdentityToken.Password = password.encode()
            params.UserIdentityToken.EncryptionAlgorithm = None

    policies = ["Basic256Sha256_SignAndEncrypt", "Basic256Sha256_Sign"]
    server = ProbeServer(tmp_path, users=True, limits={"opcua_security_policies": policies})
    try:

        async def probe():
            good = await trusted_credentials(server, "plc")
            plain = await secure_client(server.opcua_url, good, mode="Sign")
            plain.__class__ = PlainTextClient
            refused = await refusal(plain)
            encrypted = await halt_as(await secure_client(server.opcua_url, good, mode="Sign"))
            return refused, encrypted

        assert asyncio.run(probe()) == ("BadIdentityTokenRejected", "operator")
    finally:
        assert server.stop() == 0


def test_guessing_passwords_locks_the_user_out(tmp_path):
    server = ProbeServer(
        tmp_path, users=True, limits={"login": {"backoff_first_s": 0, "max_failures_per_user": 3, "lockout_s": 600}}
    )
    try:

        async def probe():
            good = await trusted_credentials(server, "plc")
            guesses = [
                await refusal(await secure_client(server.opcua_url, good, password=f"guess-{i}")) for i in range(3)
            ]
            locked = await refusal(await secure_client(server.opcua_url, good))  # the right password, too late
            other = await halt_as(await secure_client(server.opcua_url, good, user="eng", password="eng-pass-1"))
            return guesses, locked, other

        guesses, locked, other = asyncio.run(probe())
        assert guesses == ["BadUserAccessDenied"] * 3 and locked == "BadUserAccessDenied" and other == "engineer"
        assert status(server)["opcua_tally"].get("refused: login throttled") == 1
        wait_until(
            lambda: "user 'op' locked out" in (server.workdir / "serve.log").read_text(), 10, "the lockout logged"
        )
    finally:
        assert server.stop() == 0


def test_parallel_guesses_get_no_more_password_checks_than_the_rule_allows(tmp_path):
    """issue 28 defect 10 on OPC UA: the throttle was asked (refuse_for) but counted a try only once its check
    had failed, so guesses sent at once were all checked. Now each try counts as it begins: of 8 parallel
    guesses from one address, at most max_failures_per_user (3) get their password checked. Each check lasts
    0.5 s here (as the real hash does), so the guesses meet while the first ones are being checked."""
    server = ProbeServer(
        tmp_path,
        users=True,
        limits={"login": {"backoff_first_s": 0, "max_failures_per_user": 3, "lockout_s": 600}},
        check_delay_s=0.5,
    )
    try:

        async def probe():
            good = await trusted_credentials(server, "plc")
            guessers = [
                await secure_client(server.opcua_url, good, password=f"guess-{i}", timeout_s=30) for i in range(8)
            ]
            return await asyncio.gather(*(refusal(g) for g in guessers))

        assert asyncio.run(probe()) == ["BadUserAccessDenied"] * 8
        report = status(server)
        assert report["password_checks"] == 3, report
        assert report["opcua_tally"].get("refused: login throttled") == 5, report
    finally:
        assert server.stop() == 0


@pytest.mark.timeout(300)  # ~20 s of CPU for 1,000 secure handshakes on both sides; wall time follows the load
def test_vanished_clients_are_reclaimed_and_a_fresh_client_gets_in(tmp_path):
    """The issue's probe: clients that subscribe and drop their TCP connection. Their sessions must
    go with their connections; meanwhile a live client is answered all along (within 1 s is the
    acceptance, a wall time: scripts/bench_security.py measures it), and afterwards a fresh client
    gets a session. All from 127.0.0.1, so the cap per address is raised above a batch (50 at a
    time) for this test; and as they all log in as one user from that address, 8 at a time, the login
    throttle's limits too (it lets one check of a name or an address be in flight at a time with back-off,
    and counts the checks in flight towards the lockout: issue 28)."""
    login = {"backoff_first_s": 0, "max_failures_per_user": 1000, "max_failures_per_address": 1000}
    server = ProbeServer(
        tmp_path, users=True, limits={"opcua_limits": {"max_connections_per_address": 64}, "login": login}
    )
    try:
        good = asyncio.run(trusted_credentials(server, "plc"))
        key, cert, server_cert = good.paths
        flood = subprocess.Popen(
            [sys.executable, "-m", "tests.vanishing_clients", server.opcua_url]
            + [str(server_cert), str(key), str(cert), good.uri, str(VANISHING_CLIENTS), "50", "8"],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )

        async def watch() -> list[float]:
            live = await secure_client(server.opcua_url, good)
            await live.connect()
            ns = await live.get_namespace_index(NS)
            heartbeat = live.get_node(ua.NodeId("Heartbeat", ns))
            latencies = []
            try:
                while flood.poll() is None:
                    t0 = time.monotonic()
                    await asyncio.wait_for(heartbeat.read_value(), 10)
                    latencies.append(time.monotonic() - t0)
                    await asyncio.sleep(0.25)
            finally:
                await live.disconnect()
            return latencies

        latencies = asyncio.run(watch())
        out = flood.communicate(timeout=30)[0]
        assert f"subscribed {VANISHING_CLIENTS} of {VANISHING_CLIENTS}" in out, out[-2000:]
        wait_until(lambda: status(server)["opcua_sessions"] == 0, 20, "every vanished client's session reclaimed")
        assert status(server)["opcua_subscriptions"] == 0
        # Every read of the live client was answered (each within its 10 s wait) all through the flood; how
        # fast (the acceptance: within 1 s) is a wall time, measured by `scripts/bench_security.py --only vanish`.
        assert latencies, "the live client read nothing while the clients came and went"
        assert asyncio.run(fresh_halt(server, good)) == "operator"
    finally:
        assert server.stop() == 0


async def fresh_halt(server: ProbeServer, good: Credentials) -> str:
    return await halt_as(await secure_client(server.opcua_url, good))
