"""Helpers for the security and limit probes: the probe server in a subprocess (tests/limits_server.py,
optionally under `ulimit -n`), OPC UA client certificates and clients, sockets from other
loopback addresses (127.0.0.2, ...: a different "machine" for the per-address caps)."""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

from tests.ports import free_port

REPO = Path(__file__).resolve().parents[1]
READY = re.compile(r"^ready: screen (\S+); opcua (\S+)")


class ProbeServer:
    """tests/limits_server.py in a subprocess; `nofile`: its RLIMIT_NOFILE (soft and hard), as `ulimit -n`."""

    def __init__(
        self,
        workdir: Path,
        *,
        tls: bool = False,
        users: bool = False,
        nofile: int | None = None,
        limits: dict | None = None,
        timeout_s: float = 60.0,
        check_delay_s: float = 0.0,
    ) -> None:
        self.workdir = workdir
        self.opcua_port = free_port()
        cmd = [sys.executable, "-m", "tests.limits_server", str(workdir), "--opcua-port", str(self.opcua_port)]
        cmd += ["--tls"] * tls + ["--users"] * users + ["--limits", json.dumps(limits or {})]
        cmd += ["--check-delay-s", str(check_delay_s)]

        def limit() -> None:
            if nofile is not None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

        env = {**os.environ, "PYTHONPATH": str(REPO)}
        self.proc = subprocess.Popen(
            cmd,
            cwd=workdir,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
            preexec_fn=limit,
        )
        self.lines: list[str] = []
        self.screen_url, self.opcua_url = self._wait_ready(timeout_s)
        self._drain = threading.Thread(target=self._read_rest, daemon=True)
        self._drain.start()

    def _wait_ready(self, timeout_s: float) -> tuple[str, str]:
        timer = threading.Timer(timeout_s, self.proc.kill)
        timer.start()
        assert self.proc.stdout is not None  # stdout=PIPE
        try:
            for line in self.proc.stdout:
                self.lines.append(line.rstrip())
                if m := READY.match(line):
                    return m.group(1), m.group(2)
        finally:
            timer.cancel()
        self.proc.wait(timeout=10)
        raise RuntimeError(f"probe server ended (exit {self.proc.returncode}):\n" + "\n".join(self.lines[-30:]))

    def _read_rest(self) -> None:
        assert self.proc.stdout is not None  # stdout=PIPE
        for line in self.proc.stdout:
            self.lines.append(line.rstrip())

    @property
    def certs(self) -> Path:
        return self.workdir / "certs"

    def stop(self, timeout_s: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._drain.join(timeout=5)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode


def connect_from(address: str, port: int, timeout_s: float = 5.0) -> socket.socket:
    """A TCP connection to 127.0.0.1:`port` from the loopback `address` (another "client machine")."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    s.bind((address, 0))
    s.connect(("127.0.0.1", port))
    return s


def wait_until(condition, timeout_s: float, what: str, every_s: float = 0.1):
    """condition() until it is truthy (returned), or AssertionError saying `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s (last: {value!r})")
        time.sleep(every_s)


async def make_client_certificate(folder: Path, name: str) -> tuple[Path, Path, str]:
    """A self-signed OPC UA client certificate: (key, cert .der, application URI)."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    folder.mkdir(parents=True, exist_ok=True)
    key, cert, uri = folder / f"{name}-key.pem", folder / f"{name}-cert.der", f"urn:pick-cell-test:{name}"
    await setup_self_signed_certificate(
        key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": name}
    )
    return key, cert, uri


class Credentials:
    """A client's certificate and key and the server's certificate, loaded once (loading a key checks it: ~30 ms)."""

    def __init__(self, key: Path, cert: Path, uri: str, server_cert: Path) -> None:
        self.paths = (key, cert, server_cert)
        self.uri = uri
        self.loaded: tuple | None = None

    async def load(self) -> tuple:
        if self.loaded is None:
            from asyncua.crypto import uacrypto

            key, cert, server_cert = self.paths
            self.loaded = (
                await uacrypto.load_private_key(str(key)),
                await uacrypto.load_certificate(str(cert)),
                await uacrypto.load_certificate(str(server_cert)),
            )
        return self.loaded


async def secure_client(
    url: str,
    credentials: Credentials,
    user: str = "op",
    password: str = "op-pass-1",
    mode: str = "SignAndEncrypt",
    timeout_s: float = 10.0,
):
    """An asyncua Client set up for Basic256Sha256 with the given certificate (not connected yet)."""
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    key, cert, server_cert = await credentials.load()
    client = Client(url, timeout=timeout_s, watchdog_intervall=15)  # a loaded machine answers the 1 s probe late
    client.application_uri = credentials.uri
    policy = SecurityPolicyBasic256Sha256(server_cert, cert, key, getattr(ua.MessageSecurityMode, mode))
    client.security_policy = policy  # type: ignore[assignment]  # asyncua types it as its default, SecurityPolicyNone
    client.uaclient.set_security(client.security_policy)
    client.set_user(user)
    client.set_password(password)
    return client


class Slowloris(threading.Thread):
    """Opens `count` connections from 127.0.0.2.. (`per_address` each), each sending only a request
    line, and holds them until stopped (as the issue's probe did: it never finishes a request)."""

    def __init__(self, port: int, count: int, per_address: int) -> None:
        super().__init__(daemon=True)
        self.port, self.count, self.per_address = port, count, per_address
        self.stopping = threading.Event()
        self.opened = 0
        self.failed: list[str] = []

    def run(self) -> None:
        socks = []
        for i in range(self.count):
            try:
                s = connect_from(f"127.0.0.{2 + i // self.per_address}", self.port, timeout_s=5)
                s.sendall(b"GET /api/state HTTP/1.1\r\n")
                socks.append(s)
                self.opened += 1
            except OSError as e:  # a reset while connecting: the server refused or evicted it
                self.failed.append(type(e).__name__)
                self.opened += 1
        self.stopping.wait()
        for s in socks:
            s.close()


# ---- decompression bombs ------------------------------------------------------------------------
MB = 1 << 20


def chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png(width: int, height: int, stream: bytes, colour: int = 2, depth: int = 8, interlace: int = 0) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    idats = b"".join(chunk(b"IDAT", stream[i : i + MB]) for i in range(0, len(stream), MB))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idats + chunk(b"IEND", b"")


def zeros_stream(total_mb: int) -> bytes:
    """A valid zlib stream of `total_mb` MiB of zeros, built without compressing them all: after a full flush
    each MiB of zeros compresses to the same bytes, and the Adler-32 of n zeros is (n mod 65521) << 16 | 1."""
    c = zlib.compressobj(9)
    head = c.compress(b"\0" * MB) + c.flush(zlib.Z_FULL_FLUSH)
    block = c.compress(b"\0" * MB) + c.flush(zlib.Z_FULL_FLUSH)
    assert block == c.compress(b"\0" * MB) + c.flush(zlib.Z_FULL_FLUSH)
    end = c.flush()[:-4]  # the empty final block (byte-aligned after a full flush), without c's Adler-32
    adler = ((total_mb * MB) % 65521) << 16 | 1
    return head + block * (total_mb - 1) + end + struct.pack(">I", adler)
