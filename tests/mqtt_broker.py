"""A real MQTT broker for the telemetry tests: Debian's mosquitto on a free loopback port with a
config of its own (anonymous, or users from a password file), started and killed by the test;
and a Sparkplug B listener that decodes every message it sees."""

from __future__ import annotations

import getpass
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from cell.telemetry.sparkplug import decode, parse_topic, payload, value_of
from tests.ports import free_port

MOSQUITTO = shutil.which("mosquitto") or next(
    (p for p in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if Path(p).exists()), None
)
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd")

needs_mosquitto = pytest.mark.skipif(
    MOSQUITTO is None, reason="the mosquitto broker is not installed (Debian package mosquitto; .ci/run installs it)"
)


OPENSSL = shutil.which("openssl")


@dataclass(frozen=True)
class Tls:
    """A test CA, the broker's certificate (for 127.0.0.1) and client certificates, made by openssl."""

    ca: Path
    server_cert: Path
    server_key: Path
    clients: dict[str, tuple[Path, Path]]  # common name -> (certificate, key)


def make_tls(folder: Path, clients: tuple[str, ...]) -> Tls:
    folder.mkdir(parents=True, exist_ok=True)

    def run(*args: str) -> None:
        subprocess.run([OPENSSL, *args], check=True, capture_output=True, timeout=60, cwd=folder)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=test-ca",
        "-keyout", "ca.key", "-out", "ca.pem")  # fmt: skip
    names = {"server": "/CN=127.0.0.1"} | {c: f"/CN={c}" for c in clients}
    for name, subject in names.items():
        run("req", "-newkey", "rsa:2048", "-nodes", "-subj", subject, "-keyout", f"{name}.key", "-out", f"{name}.csr")
        ext = folder / f"{name}.ext"
        ext.write_text("subjectAltName = IP:127.0.0.1\n" if name == "server" else "extendedKeyUsage = clientAuth\n")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-days", "2", "-extfile", ext.name, "-out", f"{name}.pem")  # fmt: skip
    return Tls(
        folder / "ca.pem",
        folder / "server.pem",
        folder / "server.key",
        {c: (folder / f"{c}.pem", folder / f"{c}.key") for c in clients},
    )


def wait_for(cond: Callable[[], Any], timeout_s: float = 30.0, what: str = "condition") -> Any:
    end = time.monotonic() + timeout_s
    while not (got := cond()):
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)
    return got


class Broker:
    """mosquitto on 127.0.0.1:port; `users` turns anonymous access off (password file), `tls` turns on
    TLS with client certificates."""

    def __init__(self, workdir: Path, users: dict[str, str] | None = None, tls: Tls | None = None):
        self.workdir, self.port, self.users, self.tls = workdir, free_port(), users, tls
        self.proc: subprocess.Popen | None = None
        lines = ["persistence false", "log_dest stderr", "log_type error"]
        lines += [f"user {getpass.getuser()}"]  # run as root, mosquitto would drop to its own user: keep ours
        if tls is not None:  # TLS only, each client known by its certificate's common name
            lines += [f"cafile {tls.ca}", f"certfile {tls.server_cert}", f"keyfile {tls.server_key}"]
            lines += ["require_certificate true", "use_identity_as_username true", "allow_anonymous false"]
        elif users:
            pwfile = workdir / "passwords"
            pwfile.write_text("")
            for user, password in users.items():
                subprocess.run([MOSQUITTO_PASSWD, "-b", str(pwfile), user, password], check=True, timeout=30)
            lines += ["allow_anonymous false", f"password_file {pwfile}"]
        else:
            lines += ["allow_anonymous true"]
        self.settings = lines

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.tls else 'mqtt'}://127.0.0.1:{self.port}"

    def start(self, new_port: bool = False) -> Broker:
        """Start on `port` (a fresh free port with `new_port`, as after a restart: the old one may be
        taken meanwhile); a port lost to another process between choosing and binding is chosen again."""
        for attempt in range(3):
            if new_port or attempt:
                self.port = free_port()
            conf = self.workdir / f"mosquitto-{self.port}.conf"
            conf.write_text("\n".join([f"listener {self.port} 127.0.0.1", *self.settings]) + "\n")
            self.proc = subprocess.Popen(
                [MOSQUITTO, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
            )
            if wait_for(self._accepts_or_ended, 20, f"mosquitto on {self.port}") == "listening":
                return self
            error = self.proc.stderr.read()
            self.proc.stderr.close()
        raise AssertionError(f"mosquitto did not start: {error}")

    def _accepts_or_ended(self) -> str:
        if self.proc.poll() is not None:
            return "ended"
        with socket.socket() as s:
            s.settimeout(0.5)
            return "listening" if s.connect_ex(("127.0.0.1", self.port)) == 0 else ""

    def kill(self) -> None:
        """The broker dies without a word (SIGKILL): clients see their connection drop."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
            self.proc.stderr.close()
        self.proc = None

    def __enter__(self) -> Broker:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.kill()


@dataclass
class Message:
    topic: str
    kind: str  # NBIRTH, DDATA ...
    edge_node_id: str
    device_id: str | None
    seq: int | None
    metrics: dict[str, Any]  # name -> value (the last one if a name repeats)
    datatypes: dict[str, int]
    qos: int
    retain: bool
    connection: int = 0  # the listener's connection it came on (+1 each time the listener reconnects)


class Listener:
    """A Sparkplug host's view of the broker: subscribes to spBv1.0/GROUP/# and decodes everything;
    reconnects by itself when the broker comes back."""

    def __init__(
        self,
        port: int,
        group_id: str = "#",
        user: str | None = None,
        password: str | None = None,
        tls: tuple[Path, Path, Path] | None = None,  # (CA, certificate, key)
    ):
        self.messages: list[Message] = []
        self._lock = threading.Lock()
        self.topic = "spBv1.0/#" if group_id == "#" else f"spBv1.0/{group_id}/#"
        self.connected = threading.Event()
        self.connections = 0
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"listener-{id(self)}", clean_session=True)
        if user:
            self.client.username_pw_set(user, password)
        if tls is not None:
            self.client.tls_set(ca_certs=str(tls[0]), certfile=str(tls[1]), keyfile=str(tls[2]))
        self.client.reconnect_delay_set(1, 2)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = lambda *a: self.connected.clear()
        self.client.on_message = self._on_message
        self.client.connect_async("127.0.0.1", port, keepalive=10)
        self.client.loop_start()
        wait_for(self.connected.is_set, 20, "the listener's connection")

    def _on_connect(self, client, userdata, flags, reason, properties) -> None:
        if not reason.is_failure:
            self.connections += 1
            client.subscribe(self.topic, qos=1)
            self.connected.set()

    def _on_message(self, client, userdata, msg) -> None:
        parsed = parse_topic(msg.topic)
        if parsed is None:
            return
        _, kind, node, device = parsed
        pb = decode(msg.payload)
        types = {m.name: m.datatype for m in pb.metrics if m.HasField("datatype")}
        message = Message(
            msg.topic,
            kind,
            node,
            device,
            pb.seq if pb.HasField("seq") else None,
            {m.name: value_of(m, types.get(m.name) or None) for m in pb.metrics},
            types,
            msg.qos,
            msg.retain,
            self.connections,
        )
        with self._lock:
            self.messages.append(message)

    def of(self, kind: str, node: str | None = None) -> list[Message]:
        with self._lock:
            return [m for m in self.messages if m.kind == kind and (node is None or m.edge_node_id == node)]

    def all(self, node: str | None = None) -> list[Message]:
        with self._lock:
            return [m for m in self.messages if node is None or m.edge_node_id == node]

    def publish_metric(self, topic: str, name: str, value: bool) -> None:
        """A command as a host sends one: QoS 0, not retained, a timestamp and no seq."""
        from cell.telemetry.sparkplug import DataType, Metric

        self.client.publish(topic, payload([Metric(name, DataType.BOOLEAN, value)], seq=None), qos=0)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def picks_seen(listener: Listener, node: str | None = None, outcome: str = "picked") -> int:
    """Picks the listener saw: DDATA messages whose Last Pick/Outcome is `outcome`."""
    return sum(m.metrics.get("Last Pick/Outcome") == outcome for m in listener.of("DDATA", node))


class Proxy:
    """A TCP pipe 127.0.0.1:port -> the broker, to cut the cell's network while the broker lives:
    `cut()` drops every open connection (as a pulled cable noticed at once); new ones still pass.
    `hold()` stops taking what the cell sends (a stalled link: the cell's socket fills, nothing is
    lost, the broker's way back still flows) until `release()`; `receive_buffer` shrinks the pipe's
    receive buffer so that a hold fills the cell's socket sooner."""

    def __init__(self, target_port: int, receive_buffer: int | None = None):
        self.target_port = target_port
        self._flowing = threading.Event()
        self._flowing.set()
        self._server = socket.create_server(("127.0.0.1", 0))
        if receive_buffer is not None:  # before any connection: accepted sockets inherit it
            self._server.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.port = self._server.getsockname()[1]
        self._conns: list[socket.socket] = []
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=5)
            except OSError:
                client.close()
                continue
            upstream.settimeout(None)
            with self._lock:
                self._conns += [client, upstream]
            for a, b, held in ((client, upstream, True), (upstream, client, False)):
                threading.Thread(target=self._pipe, args=(a, b, held), daemon=True).start()

    def hold(self) -> None:
        self._flowing.clear()

    def release(self) -> None:
        self._flowing.set()

    def _pipe(self, src: socket.socket, dst: socket.socket, held: bool) -> None:
        try:
            while not held or self._flowing.wait():
                if not (data := src.recv(65536)):
                    break
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def cut(self) -> None:
        with self._lock:
            conns, self._conns = self._conns, []
        for s in conns:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def close(self) -> None:
        self._closed = True
        self._flowing.set()
        self._server.close()
        self.cut()
