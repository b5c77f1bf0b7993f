"""The screen's connections under attack (issue 21): deadlines for headers and bodies, caps per
client address and in total, TLS with HSTS and Secure cookies, clients that do not read.

The fast cases run cell.web.transport in this process over a small app; the probes from the
issue (1,100 unfinished requests under `ulimit -n 1024`, 50 unread event streams) run
tests/limits_server.py in a subprocess, the screen's transport and the guarded OPC UA server
in one process as `run-cell serve` has them. Other "machines" are other loopback addresses
(127.0.0.2 ...), since the caps are per client address."""

from __future__ import annotations

import asyncio
import resource
import socket
import ssl
import time
from pathlib import Path

import httpx
import pytest
from asyncua import Client
from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import JSONResponse, PlainTextResponse
from starlette.routing import Route

from cell.web.shield import Shield
from cell.web.tls import ensure_self_signed, server_context
from cell.web.transport import ServerThread, TransportLimits
from tests.probes import ProbeServer, Slowloris, connect_from, wait_until
from tests.serve_process import ServeProcess

pytestmark = pytest.mark.timeout(60)


def small_app() -> Starlette:
    async def state(request: Request) -> JSONResponse:
        return JSONResponse({"ok": True})

    async def upload(request: Request) -> PlainTextResponse:
        body = await request.body()
        return PlainTextResponse(str(len(body)))

    async def login(request: Request) -> JSONResponse:
        reply = JSONResponse({"ok": True})
        reply.set_cookie("cell_session", "abc", httponly=True, samesite="strict")
        return reply

    return Starlette(
        routes=[
            Route("/api/state", state),
            Route("/api/upload", upload, methods=["POST"]),
            Route("/api/login", login, methods=["POST"]),
        ]
    )


def small_server(header_timeout_s: float) -> ServerThread:
    """The small app behind the transport with small caps (8 in all, 4 per address)."""
    limits = TransportLimits(
        header_timeout_s=header_timeout_s, body_timeout_s=0.5, max_connections=8, max_connections_per_address=4
    )
    server = ServerThread(Shield(small_app(), https=False), "127.0.0.1", 0, limits)
    server.start()
    return server


@pytest.fixture
def quick():
    server = small_server(header_timeout_s=0.5)
    yield server
    server.stop()


@pytest.fixture
def patient():
    server = small_server(header_timeout_s=30)
    yield server
    server.stop()


def closed_by_server(sock: socket.socket, within_s: float) -> bool:
    """True when the server closes (FIN or reset) the connection within `within_s` (what it sends meanwhile,
    e.g. the rest of an earlier response, is read and dropped)."""
    deadline = time.monotonic() + within_s
    while (left := deadline - time.monotonic()) > 0:
        sock.settimeout(left)
        try:
            if sock.recv(65536) == b"":
                return True
        except ConnectionResetError:
            return True
        except TimeoutError:
            return False
    return False


def test_unfinished_headers_and_bodies_are_cut(quick):
    line_only = connect_from("127.0.0.1", quick.port)
    line_only.sendall(b"GET /api/state HTTP/1.1\r\n")
    silent = connect_from("127.0.0.1", quick.port)
    slow_body = connect_from("127.0.0.1", quick.port)
    slow_body.sendall(b"POST /api/upload HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n0123456789")
    for sock in (line_only, silent, slow_body):
        assert closed_by_server(sock, 10), "the server kept an unfinished request open past its deadline"
        sock.close()
    tally = quick.server.tally.total
    assert tally["cut: request headers too slow"] == 2 and tally["cut: request body too slow"] == 1
    assert httpx.post(quick.url + "api/upload", content=b"x" * 100).text == "100"  # a whole body is fine


def test_a_kept_alive_connections_next_request_gets_a_deadline_too(quick):
    sock = connect_from("127.0.0.1", quick.port)
    sock.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\n\r\n")
    sock.settimeout(5)
    assert sock.recv(4096).startswith(b"HTTP/1.1 200")
    sock.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\n")  # the next request, never finished
    assert closed_by_server(sock, 10)
    sock.close()


def test_one_address_is_capped_and_a_crowd_of_waiting_ones_makes_room(patient):
    tally = patient.server.tally.total
    mine = [connect_from("127.0.0.2", patient.port) for _ in range(6)]  # 4 admitted, 2 reset at once
    refused = "refused: 4 open from one address (max_connections_per_address)"
    wait_until(lambda: tally[refused] == 2, 10, "two connections over the per-address cap refused")
    crowd = [connect_from(f"127.0.0.{i}", patient.port) for i in range(3, 7)]  # all 8 places taken now
    for s in crowd:
        s.sendall(b"GET /api/state HTTP/1.1\r\n")
    wait_until(lambda: patient.server.admission.open == 8, 10, "all 8 places taken")
    r = httpx.get(patient.url + "api/state", timeout=5)  # the oldest waiting connection gives way
    assert r.json() == {"ok": True}
    assert tally["evicted: a waiting connection, all places taken"] == 1
    assert sum(closed_by_server(s, 5) for s in mine[:1]) == 1  # the oldest was the first of 127.0.0.2's
    for s in mine + crowd:
        s.close()


@pytest.fixture
def secure(tmp_path):
    limits = TransportLimits(header_timeout_s=0.5)
    context = server_context(None, None, tmp_path, "127.0.0.1")
    server = ServerThread(Shield(small_app(), https=True), "127.0.0.1", 0, limits, context)
    server.start()
    yield server, tmp_path
    server.stop()


def test_https_with_hsts_and_secure_cookies(secure):
    server, certs = secure
    assert server.url.startswith("https://")
    trust = ssl.create_default_context(cafile=str(certs / "screen-cert.pem"))
    with httpx.Client(verify=trust, timeout=10) as client:
        r = client.post(server.url + "api/login")
        assert r.status_code == 200
        assert r.headers["strict-transport-security"] == "max-age=31536000"
        cookie = r.headers["set-cookie"]
        assert "HttpOnly" in cookie and "SameSite=strict" in cookie and cookie.endswith("; Secure")
    with pytest.raises(httpx.HTTPError):
        httpx.get(server.url.replace("https://", "http://") + "api/state", timeout=5)  # no plain HTTP
    silent = connect_from("127.0.0.1", server.port)  # connects, never starts the handshake
    assert closed_by_server(silent, 10)
    silent.close()
    tally = server.server.tally.total
    wait_until(lambda: sum(n for k, n in tally.items() if k.startswith("cut: TLS handshake")) >= 2, 10, "both cut")


def test_the_made_certificate_is_kept_and_its_key_private(tmp_path):
    cert, key = ensure_self_signed(tmp_path, "10.1.2.3")
    first = cert.read_bytes()
    assert key.stat().st_mode & 0o077 == 0
    assert ensure_self_signed(tmp_path, "10.1.2.3") == (cert, key) and cert.read_bytes() == first
    from cryptography import x509

    names = x509.load_pem_x509_certificate(first).extensions.get_extension_for_class(x509.SubjectAlternativeName)
    assert "10.1.2.3" in {str(ip) for ip in names.value.get_values_for_type(x509.IPAddress)}


# ---- the probes, against a server process ----------------------------------------
def _raise_own_limit(needed: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < needed:
        if hard != resource.RLIM_INFINITY and hard < needed:
            pytest.skip(f"this test opens {needed} sockets; its own descriptor limit is {hard} (ulimit -Hn)")
        resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_1100_unfinished_requests_under_ulimit_1024(tmp_path):
    """The issue's probe against `run-cell serve --dry-run` under `ulimit -n 1024`, picking in continuous
    mode: 1,100 connections that send a request line and nothing more. The screen and OPC UA must answer a
    real client all along (within 1 s is the acceptance, a wall time: scripts/bench_security.py), the
    picks must go on, the process must keep descriptors to spare, and the log must not fill with the
    same failure."""
    _raise_own_limit(1400)
    serve = ServeProcess(tmp_path, nofile=1024)
    screen = serve.url
    attack = Slowloris(int(screen.rsplit(":", 1)[1].strip("/")), 1100, per_address=20)
    try:
        token = httpx.get(screen + "api/session", timeout=10).json()["csrf"]
        r = httpx.post(screen + "api/command/StartContinuous", headers={"x-csrf-token": token}, timeout=10)
        assert r.status_code == 200, r.text

        def picked() -> int:
            counters = httpx.get(screen + "api/state", timeout=30).json()["counters"]
            return counters["picked_bolts"] + counters["picked_nuts"]

        wait_until(picked, 60, "the first pick")

        async def opcua_reads(seconds: float) -> list[float]:
            client = Client(
                f"opc.tcp://127.0.0.1:{serve.opcua_port}/cell", timeout=10, watchdog_intervall=15
            )  # loopback, no users
            await client.connect()
            try:
                ns = await client.get_namespace_index("urn:pick-cell")
                node = await client.nodes.objects.get_child([f"{ns}:Cell", f"{ns}:Heartbeat"])
                out, end = [], time.monotonic() + seconds
                while time.monotonic() < end:
                    t0 = time.monotonic()
                    await asyncio.wait_for(node.read_value(), 10)
                    out.append(time.monotonic() - t0)
                    await asyncio.sleep(0.2)
                return out
            finally:
                await client.disconnect()

        attack.start()
        wait_until(lambda: attack.opened >= 1100, 60, "1,100 attacking connections opened")
        before = picked()
        # The burst itself queues in the kernel's accept queue ahead of anyone else (a first request waits for
        # it: ~0.3 s measured); the acceptance is about the screen while the unfinished requests are held (the
        # header deadline, 10 s, then frees them), so the requests counted come after a first one got through.
        httpx.get(screen + "api/state", timeout=30).raise_for_status()
        answers = [httpx.get(screen + "api/state", timeout=30).raise_for_status().status_code for _ in range(10)]
        opcua = asyncio.run(opcua_reads(3.0))
        wait_until(lambda: picked() > before, 60, "picks going on during the attack")
        descriptors = len(list(Path(f"/proc/{serve.proc.pid}/fd").iterdir()))
    finally:
        attack.stopping.set()
        attack.join(timeout=30)
        code = serve.stop()
    assert code == 0, "\n".join(serve.lines[-30:])
    assert descriptors < 700, f"run-cell serve held {descriptors} of its 1024 descriptors"
    # The screen (10 requests, each within its 30 s timeout) and OPC UA (each read within 10 s) answered all through
    # the attack; how fast (the acceptance: within 1 s) is a wall time, measured by
    # `scripts/bench_security.py --only slowloris`.
    assert len(answers) == 10 and opcua, f"OPC UA read {len(opcua)} times during the attack"
    log = "".join(p.read_text() for p in (tmp_path / "logs").glob("serve-*.log"))
    assert "Too many open files" not in log
    complaints = [line for line in log.splitlines() if " WARNING " in line or " ERROR " in line]
    assert len(complaints) < 30, f"{len(complaints)} warnings for one attack: not rate-limited:\n" + "\n".join(
        complaints[:40]
    )


@pytest.mark.slow
def test_50_unread_event_streams(tmp_path):
    """The issue's probe: event streams that never read. One address gets 4; the rest answer 503 and
    the page tries again later; the unread ones are dropped once their buffers fill, and a real
    screen keeps getting events and answers all along."""
    server = ProbeServer(tmp_path, limits={"web": {"write_stall_s": 2.0, "send_buffer_kb": 64}})
    port = int(server.screen_url.rsplit(":", 1)[1].strip("/"))
    try:
        unread, statuses, latencies = [], [], []
        for i in range(50):
            s = connect_from(f"127.0.0.{2 + i // 4}", port)  # 13 "machines", 4 streams each (one over: 503)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
            unread.append(s)
        s = connect_from("127.0.0.2", port)  # a fifth from the first machine
        s.sendall(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
        s.settimeout(5)
        assert s.recv(100).startswith(b"HTTP/1.1 503")
        s.close()
        with httpx.stream("GET", server.screen_url + "api/events", timeout=10) as events:
            lines = events.iter_lines()
            got = 0
            deadline = time.monotonic() + 60
            while True:
                line = next(lines)
                got += line.startswith("event: state")
                if got % 10 == 0 and line.startswith("event: state"):
                    t0 = time.monotonic()  # a real client's request while the unread streams are open
                    statuses.append(httpx.get(server.screen_url + "api/status", timeout=10).json())
                    latencies.append(time.monotonic() - t0)
                    if statuses[-1]["streams"] == {"127.0.0.1": 1}:
                        break  # every unread stream dropped; ours still flowing
                assert time.monotonic() < deadline, f"unread streams still open: {statuses[-1]['streams']}"
        tally = statuses[-1]["screen_tally"]
        assert tally.get("cut: client not reading", 0) >= 48, tally
        # The screen answered every request (each within its 10 s timeout) while the unread streams were open; how
        # fast (the acceptance: within 1 s) is a wall time, measured by `scripts/bench_security.py --only streams`.
        assert latencies, "the screen was asked nothing while the unread streams were open"
        for s in unread:
            s.close()
    finally:
        assert server.stop() == 0, "\n".join(server.lines[-30:])
