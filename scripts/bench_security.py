"""The issue-21 probes as measurements: what an attacker on the plant network costs the cell.

    .venv/bin/python scripts/bench_security.py [--clients 1000] [--only slowloris,streams,vanish,bomb,upload,guess]

Each probe runs tests/limits_server.py in a subprocess (the screen's transport and the guarded
OPC UA server in one process, as `run-cell serve` has them) and prints what a real client saw
meanwhile. Wall times depend on the machine's load; CPU times are the processes' own.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import resource
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import httpx  # noqa: E402
from asyncua import Client, ua  # noqa: E402

from cell.service.ua_values import node_id  # noqa: E402
from tests.probes import (  # noqa: E402
    Credentials,
    ProbeServer,
    Slowloris,
    connect_from,
    make_client_certificate,
    png,
    secure_client,
    wait_until,
    zeros_stream,
)


def status(server: ProbeServer) -> dict:
    return httpx.get(server.screen_url + "api/status", timeout=30).json()


def timed(call) -> float:
    t0 = time.monotonic()
    call()
    return time.monotonic() - t0


def ms(values: list[float]) -> str:
    p95 = sorted(values)[int(0.95 * (len(values) - 1))]
    return (
        f"median {1e3 * statistics.median(values):.0f} ms, p95 {1e3 * p95:.0f} ms, max {1e3 * max(values):.0f} ms "
        f"({len(values)} requests)"
    )


async def opcua_reads(url: str, seconds: float, credentials: Credentials | None = None) -> list[float]:
    client = await secure_client(url, credentials) if credentials else Client(url, timeout=10)
    await client.connect()
    try:
        ns = await client.get_namespace_index("urn:pick-cell")
        node = client.get_node(node_id("Heartbeat", ns))
        out, end = [], time.monotonic() + seconds
        while time.monotonic() < end:
            t0 = time.monotonic()
            await node.read_value()
            out.append(time.monotonic() - t0)
            await asyncio.sleep(0.2)
        return out
    finally:
        await client.disconnect()


def slowloris(work: Path) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, 4096), hard))
    server = ProbeServer(work, nofile=1024)
    attack = Slowloris(int(server.screen_url.rsplit(":", 1)[1].strip("/")), 1100, per_address=20)
    try:
        attack.start()
        wait_until(lambda: attack.opened >= 1100, 60, "attack opened")
        first = timed(lambda: httpx.get(server.screen_url + "api/state", timeout=30))
        wait_until(
            lambda: sum(status(server)["screen_tally"].values()) + status(server)["screen_open"] >= 1100, 60, "taken in"
        )
        screen = [timed(lambda: httpx.get(server.screen_url + "api/state", timeout=30)) for _ in range(20)]
        opcua = asyncio.run(opcua_reads(server.opcua_url, 4))
        report = status(server)
    finally:
        attack.stopping.set()
        attack.join(30)
        server.stop()
    print("slowloris: 1,100 connections sending only a request line, server under ulimit -n 1024")
    print(f"  first request while the 1,100 arrived: {1e3 * first:.0f} ms")
    print(f"  screen while they are held: {ms(screen)}; OPC UA reads: {ms(opcua)}")
    print(f"  server descriptors open: {report['open_descriptors']} of 1024; connections held {report['screen_open']}")
    print(f"  counts: {report['screen_tally']}")
    log = (work / "serve.log").read_text().splitlines()
    print(
        f"  log: {sum(' WARNING ' in x or ' ERROR ' in x for x in log)} warning/error lines, 'Too many open files': {sum('Too many open files' in x for x in log)}"
    )


def streams(work: Path) -> None:
    server = ProbeServer(work)  # the defaults: write_stall_s 15, send_buffer_kb 256
    port = int(server.screen_url.rsplit(":", 1)[1].strip("/"))
    socks = []
    try:
        t0 = time.monotonic()
        for i in range(50):
            s = connect_from(f"127.0.0.{2 + i // 4}", port)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            s.sendall(b"GET /api/events HTTP/1.1\r\nHost: x\r\n\r\n")
            socks.append(s)
        latencies = []
        while status(server)["streams"]:
            latencies.append(timed(lambda: httpx.get(server.screen_url + "api/state", timeout=30)))
            time.sleep(0.5)
            if time.monotonic() - t0 > 300:
                break
        dropped_after = time.monotonic() - t0
        report = status(server)
    finally:
        for s in socks:
            s.close()
        server.stop()
    print("unread event streams: 50 from 13 addresses, each stream ~40 KB/s, defaults (stall 15 s, 256 KB)")
    print(f"  all unread streams dropped after {dropped_after:.0f} s; screen meanwhile: {ms(latencies)}")
    print(f"  counts: {report['screen_tally']}")


def vanish(work: Path, count: int) -> None:
    # every client logs in as one user from one address, 8 at a time: past the login throttle's limits
    login = {"backoff_first_s": 0, "max_failures_per_user": 1000, "max_failures_per_address": 1000}
    server = ProbeServer(work, users=True, limits={"opcua_limits": {"max_connections_per_address": 64}, "login": login})
    try:
        key, cert, uri = asyncio.run(make_client_certificate(work / "clients", "plc"))
        (server.certs / "trusted").mkdir(parents=True, exist_ok=True)
        shutil.copy(cert, server.certs / "trusted" / "plc.der")
        good = Credentials(key, cert, uri, server.certs / "server-cert.der")
        before = status(server)
        t0 = time.monotonic()
        children = resource.getrusage(resource.RUSAGE_CHILDREN)
        flood = subprocess.Popen(
            [sys.executable, "-m", "tests.vanishing_clients", server.opcua_url, str(server.certs / "server-cert.der")]
            + [str(key), str(cert), uri, str(count), "50", "8"],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=subprocess.PIPE,
            text=True,
        )

        async def live() -> list[float]:
            reads = []
            while flood.poll() is None:
                reads += await opcua_reads(server.opcua_url, 2, good)
            return reads

        reads = asyncio.run(live())
        out = flood.communicate()[0].strip().splitlines()[-1]
        took = time.monotonic() - t0
        wait_until(lambda: status(server)["opcua_sessions"] == 0, 60, "sessions reclaimed")
        after = status(server)
        idle0 = after["cpu_s"]
        time.sleep(5)
        idle = (status(server)["cpu_s"] - idle0) / 5
        used = resource.getrusage(resource.RUSAGE_CHILDREN)
    finally:
        server.stop()
    print(f"vanishing OPC UA clients: {out} (secure, logged in), {took:.0f} s wall")
    print(f"  live client reads meanwhile: {ms(reads)}")
    print(
        f"  server CPU {1e3 * (after['cpu_s'] - before['cpu_s']) / count:.1f} ms per client; sessions left: 0; idle after: {100 * idle:.1f} % of a core"
    )
    print(
        f"  the clients' CPU: {1e3 * (used.ru_utime + used.ru_stime - children.ru_utime - children.ru_stime) / count:.1f} ms per client"
    )


def bomb() -> None:
    import cv2
    import numpy as np

    from cell.imagedecode import png_check

    data = png(1920, 1080, zeros_stream(20 * 1024))
    t0 = time.process_time()
    try:
        png_check(data)
    except Exception as e:
        refused = str(e)
    check = time.process_time() - t0
    small = png(1920, 1080, zeros_stream(1024))
    t0 = time.process_time()
    cv2.imdecode(np.frombuffer(small, np.uint8), cv2.IMREAD_COLOR)
    per_gb = time.process_time() - t0
    print(f"PNG bomb: {len(data) / 2**20:.1f} MiB, header 1920 x 1080, 20 GiB of zeros inside")
    print(f"  refused in {1e3 * check:.1f} ms of CPU: {refused}")
    print(f"  for comparison cv2.imdecode inflates it all: {per_gb:.2f} s of CPU per GiB of zeros")


def upload(work: Path) -> None:
    """The bomb through the screen's upload route, ten times, while a client reads the state: how long it waited."""
    data = png(1920, 1080, zeros_stream(20 * 1024))
    server = ProbeServer(work)
    latencies: list[float] = []
    codes: list[int] = []
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            latencies.append(timed(lambda: httpx.get(server.screen_url + "api/state", timeout=30).raise_for_status()))
            time.sleep(0.05)

    watcher = threading.Thread(target=watch)
    try:
        watcher.start()
        codes = [httpx.post(server.screen_url + "api/upload", content=data, timeout=60).status_code for _ in range(10)]
    finally:
        done.set()
        watcher.join(60)
        server.stop()
    print(f"PNG bomb uploaded to the screen 10 times ({len(data) / 2**20:.1f} MiB each): answers {sorted(set(codes))}")
    print(f"  screen meanwhile: {ms(latencies)} (the acceptance: 1 s)")


def guess(work: Path) -> None:
    server = ProbeServer(work, users=True)
    try:
        key, cert, uri = asyncio.run(make_client_certificate(work / "clients", "plc"))
        (server.certs / "trusted").mkdir(parents=True, exist_ok=True)
        shutil.copy(cert, server.certs / "trusted" / "plc.der")
        good = Credentials(key, cert, uri, server.certs / "server-cert.der")

        async def attempts(seconds: float) -> tuple[int, int]:
            tried = refused = 0
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                client = await secure_client(server.opcua_url, good, password=f"guess-{tried}")
                try:
                    await client.connect()
                    await client.disconnect()
                except ua.UaStatusCodeError:
                    refused += 1
                tried += 1
            return tried, refused

        tried, refused = asyncio.run(attempts(20))
        report = status(server)
    finally:
        server.stop()
    checked = tried - report["opcua_tally"].get("refused: login throttled", 0)
    print(f"password guessing over OPC UA for 20 s (one trusted client, defaults): {tried} tries, {refused} refused")
    print(f"  passwords actually checked: {checked} (the rest refused by the back-off and lockout unchecked)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--clients", type=int, default=1000, help="vanishing OPC UA clients")
    p.add_argument("--only", default="slowloris,streams,vanish,bomb,upload,guess")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # the refusals are the point: not their tracebacks
    chosen = set(args.only.split(","))
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("slowloris", "streams", "vanish", "bomb", "upload", "guess"):
            if name not in chosen:
                continue
            work = Path(tmp) / name
            work.mkdir()
            if name == "vanish":
                vanish(work, args.clients)
            elif name == "bomb":
                bomb()
            else:
                globals()[name](work)
            print(flush=True)


if __name__ == "__main__":
    main()
