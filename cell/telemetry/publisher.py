"""The cell as a Sparkplug B 3.0 edge node on the plant's MQTT broker (paho-mqtt).

One edge node (`edge_node_id`, this PC) with one device (`device_id`, the cell) in a group
(`group_id`). On every MQTT session: the NDEATH is the connection's Will (QoS 1, with the
session's bdSeq: +1 for each new CONNECT, 255 wraps to 0, continued across restarts from a small
file in the cell's data folder, 0 the very first time), the node
subscribes to its NCMD (and, with commands on, its device's DCMD) topic, then publishes NBIRTH
(seq 0, bdSeq, `Node Control/Rebirth` false) and DBIRTH (seq 1, every device metric with its
type and current value). After that each change goes out as DDATA with seq +1 (wrapping at
255): each finished pick as it happens, and what the service's snapshot shows (state,
counters, rate, alarm, calibration) whenever it changes. An NCMD `Node Control/Rebirth` = true
publishes the births again (same bdSeq: same session). Stopping publishes NDEATH, then
disconnects.

Off the control thread: the publisher is a subscriber of the event bus (its own thread, its
own bounded queue); paho's network thread does the sending and reconnects with exponential
backoff. While the broker is away updates are dropped and counted (the history store keeps
every event; the next births carry the current values), and nothing waits: the picks go on.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import ssl
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ParamSpec, Protocol, cast

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode

from cell.core.commands import AccessDenied, Command, CommandRefused, CommandResult
from cell.core.eventbus import EventBus, Subscription
from cell.core.events import (
    AlarmCleared,
    AlarmRaised,
    CalibrationInstalled,
    Event,
    Interface,
    JobEnded,
    JobStarted,
    Origin,
    PartClassesChanged,
    PartFailed,
    PickVerified,
    Role,
    SnapshotChanged,
    StateChanged,
    VisionStateChanged,
)
from cell.core.parts import PartRegistry
from cell.core.records import PickRecords, Snapshot
from cell.errors import ConfigError
from cell.telemetry import metrics as M
from cell.telemetry.config import MqttConfig
from cell.telemetry.sparkplug import Metric, Topics, decode, next_seq, now_ms, payload, value_of

log = logging.getLogger(__name__)

KINDS = (
    SnapshotChanged,
    PickVerified,
    PartFailed,
    StateChanged,
    VisionStateChanged,
    JobStarted,
    JobEnded,
    AlarmRaised,
    AlarmCleared,
    CalibrationInstalled,
    PartClassesChanged,
)
WARNING_KEY = "telemetry-mqtt"
_CLOSE_WAIT_S = 3.0
_ERROR_LOG_INTERVAL_S = (
    60.0  # unexpected errors in commands, and in paho's callbacks: each logged at most once a minute
)
INTERNAL_ERROR = "internal_error"  # Command/Last Refusal when handling a command failed unexpectedly
P = ParamSpec("P")


class _Throttled:
    """Logs an error with its traceback at most once per `interval_s`, saying how many were left out."""

    def __init__(self, interval_s: float = _ERROR_LOG_INTERVAL_S):
        self.interval_s = interval_s
        self._last = -float("inf")
        self._left_out = 0
        self._lock = threading.Lock()

    def error(self, message: str, *args: object) -> None:
        with self._lock:
            now = time.monotonic()
            if now - self._last < self.interval_s:
                self._left_out += 1
                return
            self._last, left_out, self._left_out = now, self._left_out, 0
        more = f" ({left_out} more like it since the last report)" if left_out else ""
        log.error(message + more, *args, exc_info=True)


class ServiceView(Protocol):
    """What the publisher needs of the line service (cell.core.api.LineServiceAPI has it)."""

    def snapshot(self) -> Snapshot: ...

    @property
    def parts(self) -> PartRegistry: ...

    def command(self, command: Command, origin: Origin = ..., request: Any = None) -> CommandResult: ...

    def raise_warning(self, key: str, reason: str, hint: str, source: str) -> None: ...

    def clear_warning(self, key: str) -> None: ...


def password_from_env(cfg: MqttConfig, environ: dict[str, str]) -> str | None:
    """The broker password, read from the environment variable the config names (never from the file)."""
    if cfg.password_env is None:
        return None
    password = environ.get(cfg.password_env)
    if not password:
        raise ConfigError(
            f"telemetry.mqtt.password_env: the environment variable {cfg.password_env} is not set or empty",
            hint=f"export {cfg.password_env} with the broker password for user {cfg.user!r}, or remove "
            "telemetry.mqtt.user and password_env",
        )
    return password


def bd_seq_file(folder: Path, cfg: MqttConfig) -> Path:
    """The file keeping this edge node's bdSeq in `folder` (one per group and edge node)."""
    name = "".join(c if c.isalnum() or c in "._-" else "_" for c in f"{cfg.group_id}-{cfg.edge_node_id}")
    return Path(folder) / f"sparkplug-bdseq-{name}.json"


class BdSeqStore:
    """The bdSeq of this edge node's last MQTT CONNECT, kept in a small JSON file written atomically
    (a temporary file, flushed to disk, renamed over the old one): a new process continues the
    sequence (Sparkplug B: +1 for each new session, 255 wraps to 0) instead of starting at 0 again,
    which a host would take for the session it already saw. Without a folder nothing is kept."""

    def __init__(self, path: Path | None):
        self.path = path
        self._warned = False

    def first(self) -> int:
        """The bdSeq for this process's first CONNECT: the last one kept + 1, or 0 when none is."""
        if self.path is None:
            return 0
        try:
            kept = json.loads(self.path.read_text(encoding="utf-8"))["bd_seq"]
            if not isinstance(kept, int) or not 0 <= kept <= 255:
                raise ValueError(f"bd_seq {kept!r} is not 0..255")
        except FileNotFoundError:
            return 0
        except (OSError, ValueError, KeyError, TypeError) as e:
            log.warning(
                "telemetry: cannot read the kept Sparkplug bdSeq from %s (%s); starting at 0 (a host may take "
                "this session's birth for an old one until the next reconnect); the file is rewritten",
                self.path,
                e,
            )
            return 0
        return next_seq(kept)

    def keep(self, bd_seq: int) -> None:
        """Record the bdSeq of the CONNECT about to be sent; a failure is logged once and does not stop MQTT."""
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump({"bd_seq": bd_seq}, f)
                f.write("\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
            self._warned = False
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink()
            if not self._warned:
                self._warned = True
                log.warning(
                    "telemetry: cannot keep the Sparkplug bdSeq in %s (%s); the next start may repeat a bdSeq: "
                    "check that the folder is writable (telemetry.mqtt.state_dir)",
                    self.path,
                    e,
                )


def certificate_name(path: Path | None) -> str:
    """The common name of this cell's TLS client certificate (the broker's user for it), else 'tls-client'."""
    if path is None:
        return ""
    try:
        from cryptography import x509
        from cryptography.x509.oid import NameOID

        cert = x509.load_pem_x509_certificate(Path(path).read_bytes())
        names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        return str(names[0].value) if names else "tls-client"
    except (OSError, ValueError, ImportError):
        return "tls-client"


class SparkplugPublisher:
    """Sparkplug B edge node over paho-mqtt; `start()` after the service exists, `close()` after it stopped."""

    def __init__(
        self, cfg: MqttConfig, service: ServiceView, password: str | None = None, state_dir: Path | None = None
    ):
        """`state_dir`: where bdSeq is kept between runs when the config names no `state_dir` (None: not kept)."""
        self.cfg, self.service = cfg, service
        self.topics = Topics(cfg.group_id, cfg.edge_node_id, cfg.device_id)
        self.commands = cfg.commands
        # the part classes the births name a counter of (grown while serving: PartClassesChanged, a rebirth)
        self.parts: PartRegistry = service.parts
        self._lock = threading.RLock()  # seq, the births and every publish, in order
        self._counts = threading.Lock()
        folder = cfg.state_dir if cfg.state_dir is not None else state_dir
        self._bd_seq_store = BdSeqStore(bd_seq_file(folder, cfg) if folder is not None else None)
        self.bd_seq = self._bd_seq_store.first()  # the bdSeq of the Will registered for the next (or current) CONNECT
        self.session_bd_seq: int | None = None  # the bdSeq of the session now up
        self._seq = 0
        self.born = False
        self._birth_due = False  # connected, but the births could not be handed over: sent again when they can
        self.births_dropped = 0  # tries at the births the client could not take
        self._births_failing = 0
        self.dropped = 0
        self.published = 0
        self.births = 0
        self._unsent = 0
        self._values: dict[str, Any] = {**M.NO_PICK, **(M.NO_COMMAND if self.commands else {})}
        self._records = PickRecords()
        self._cycle: dict[str, float] = {}
        self._closing = False
        self._refused = False
        self.command_errors = 0  # commands whose handling raised something other than a refusal
        self.callback_errors = 0  # anything else raised in paho's callbacks (kept from paho's thread)
        self._command_log, self._callback_log = _Throttled(), _Throttled()
        self._role = Role(cfg.command_role) if cfg.command_role is not None else None
        self._sub: Subscription | None = None
        self.client = self._client(password)
        self._user = cfg.user or certificate_name(cfg.client_cert_file)  # who the broker knows this cell as

    # ---- the MQTT client --------------------------------------------------------------------
    def _client(self, password: str | None) -> mqtt.Client:
        cfg = self.cfg
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=f"{cfg.group_id}:{cfg.edge_node_id}",
            clean_session=True,  # Sparkplug: always a clean session
            protocol=mqtt.MQTTv311,
        )
        if cfg.user is not None:
            client.username_pw_set(cfg.user, password)
        if cfg.tls:
            certfile = str(cfg.client_cert_file) if cfg.client_cert_file else None
            keyfile = str(cfg.client_key_file) if cfg.client_key_file else None
            try:
                client.tls_set(
                    ca_certs=str(cfg.ca_file) if cfg.ca_file else None,
                    certfile=certfile,
                    keyfile=keyfile,
                    cert_reqs=ssl.CERT_REQUIRED,
                )
            except (OSError, ssl.SSLError, ValueError) as e:
                raise ConfigError(
                    f"telemetry.mqtt: cannot load the TLS files: {e}",
                    hint="check ca_file, client_cert_file and client_key_file (PEM, readable)",
                ) from None
        client.reconnect_delay_set(min_delay=max(1, round(cfg.reconnect_min_s)), max_delay=round(cfg.reconnect_max_s))
        # paho re-raises what a callback raises and its network thread ends with it: telemetry would
        # stop without a word. Every callback is guarded (logged, counted, the thread goes on).
        client.on_connect = self._guarded(self._on_connect)
        client.on_disconnect = self._guarded(self._on_disconnect)
        client.on_message = self._guarded(self._on_message)
        client.on_connect_fail = self._guarded(self._on_connect_fail)
        client.on_publish = self._guarded(self._on_publish)
        self._set_will(client)
        return client

    def _guarded(self, callback: Callable[P, None]) -> Callable[P, None]:
        def guarded(*args: P.args, **kwargs: P.kwargs) -> None:
            try:
                callback(*args, **kwargs)
            except Exception:
                with self._counts:
                    self.callback_errors += 1
                self._callback_log.error("telemetry: %s failed; the MQTT client goes on", callback.__name__)

        return guarded

    def _set_will(self, client: mqtt.Client) -> None:
        death = payload([Metric(M.BD_SEQ, M.D.INT64, self.bd_seq)], seq=None, birth=True)
        client.will_set(self.topics.node("NDEATH"), death, qos=1, retain=False)

    # ---- life -------------------------------------------------------------------------------
    def start(self, bus: EventBus) -> None:
        if self.commands and self._role is None:
            log.warning(
                "telemetry.mqtt.commands is on but command_role is not set: every MQTT command is refused "
                '(set command_role, e.g. "operator", to let the plant\'s host start and stop the cell)'
            )
        self._sub = bus.subscribe("telemetry-mqtt", self.handle, kinds=KINDS, maxsize=self.cfg.queue_max)
        self._grow(self.service.parts)  # grown before the subscription began (not born yet: nothing sent)
        with self._lock:
            self._bd_seq_store.keep(self.bd_seq)
        self.client.connect_async(self.cfg.host, self.cfg.port, keepalive=self.cfg.keepalive_s)
        self.client.loop_start()
        log.info(
            "telemetry: Sparkplug B edge node %s/%s/%s -> %s",
            self.cfg.group_id,
            self.cfg.edge_node_id,
            self.cfg.device_id,
            self.cfg.url,
        )

    def close(self, bus: EventBus | None = None) -> None:
        """Publish what is queued, then NDEATH (an intentional disconnect), then disconnect."""
        if self._sub is not None:
            if bus is not None:
                bus.unsubscribe(self._sub, _CLOSE_WAIT_S)
            else:
                self._sub.close(_CLOSE_WAIT_S)
        with self._lock:
            self._closing = True
            self._birth_due = False
            info = None
            if self.born:
                death = payload([Metric(M.BD_SEQ, M.D.INT64, self.session_bd_seq)], seq=None, birth=True)
                info = self.client.publish(self.topics.node("NDEATH"), death, qos=1, retain=False)
            self.born = False
        if info is not None and info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS:
            with contextlib.suppress(RuntimeError, ValueError):
                info.wait_for_publish(_CLOSE_WAIT_S)
        self.client.disconnect()
        self.client.loop_stop()
        log.info("telemetry: stopped (%d published, %d dropped)", self.published, self.dropped)

    # ---- paho's thread: session, births, commands ------------------------------------------------
    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        if reason.is_failure:
            self._refused = True
            log.error("telemetry: the broker %s refused the connection: %s", self.cfg.url, reason)
            self._warn(f"the plant broker {self.cfg.url} refused the connection: {reason}")
            return
        self._refused = False
        with self._counts:
            self.dropped += self._unsent  # what the last session never sent
            self._unsent = 0
        client.subscribe(self.topics.node("NCMD"), qos=1)
        if self.commands:
            client.subscribe(self.topics.device("DCMD"), qos=1)
        with self._lock:
            self.session_bd_seq = self.bd_seq
            self._birth()
        log.info("telemetry: connected to %s (bdSeq %d)", self.cfg.url, self.session_bd_seq)
        self._clear_warning()

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        with self._lock:
            self.born = self._birth_due = False
            self._births_failing = 0
            closing = self._closing
            if not closing:  # the next CONNECT is a new session (after close() none follows)
                self.bd_seq = next_seq(self.bd_seq)
                self._set_will(client)
                self._bd_seq_store.keep(self.bd_seq)
        if not closing and not self._refused:
            log.warning("telemetry: lost the broker %s (%s); reconnecting", self.cfg.url, reason)
            self._warn(f"the plant broker {self.cfg.url} is unreachable: telemetry is not being published")

    def _on_connect_fail(self, client: mqtt.Client, userdata: Any) -> None:
        log.debug("telemetry: cannot reach %s; retrying", self.cfg.url)
        self._warn(f"the plant broker {self.cfg.url} is unreachable: telemetry is not being published")

    def _on_message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        try:
            received = decode(bytes(message.payload))
        except Exception as e:  # anything on our topics that is not a Sparkplug payload
            log.warning("telemetry: %s: not a Sparkplug B payload (%s); ignored", message.topic, e)
            return
        if message.topic == self.topics.node("NCMD"):
            if any(m.name == M.REBIRTH and value_of(m, M.D.BOOLEAN) is True for m in received.metrics):
                log.info("telemetry: rebirth requested")
                with self._lock:
                    self._birth()
        elif message.topic == self.topics.device("DCMD") and self.commands:
            for m in received.metrics:
                if m.name in M.MQTT_COMMANDS and value_of(m, M.D.BOOLEAN) is True:
                    self._command(M.MQTT_COMMANDS[m.name])

    def _on_publish(self, client: mqtt.Client, userdata: Any, mid: int, reason: Any, properties: Any) -> None:
        with self._counts:
            self._unsent = max(self._unsent - 1, 0)
            room = self._unsent <= self.cfg.unsent_max // 2
        if self._birth_due and room:  # the client's queue drained: the births it had no room for go now
            with self._lock:
                if self._birth_due:
                    self._birth()

    def _command(self, command: Command) -> None:
        """A DCMD through the one command table, as any interface; the answer goes back as DDATA. Nothing
        it raises leaves here (paho's network thread would end with it): an unexpected error is logged,
        counted and answered as refused (`internal_error`)."""
        result: dict[str, str | bool] = {"Command/Last Name": command.value, "Command/Last Job Id": ""}
        try:
            if self._role is None:  # no role configured: MQTT may do nothing
                raise AccessDenied(
                    command,
                    f"{command.value} refused: MQTT commands have no role (telemetry.mqtt.command_role is not "
                    'set); set command_role (e.g. "operator") to let the plant\'s host send commands',
                )
            origin = Origin(Interface.MQTT, self._user, role=self._role, address=f"{self.cfg.host}:{self.cfg.port}")
            done = self.service.command(command, origin)
            result.update({"Command/Last Accepted": True, "Command/Last Refusal": "", "Command/Last Message": ""})
            result["Command/Last Job Id"] = done.job_id or ""
        except CommandRefused as e:
            result.update(
                {"Command/Last Accepted": False, "Command/Last Refusal": e.reason.value, "Command/Last Message": str(e)}
            )
        except Exception as e:  # an audit write failure, a bug: answered, logged, counted; never re-raised
            with self._counts:
                self.command_errors += 1
            self._command_log.error("telemetry: the MQTT command %s failed unexpectedly", command.value)
            message = (
                f"{command.value}: the cell could not handle it ({type(e).__name__}: {e}); check the cell's "
                "state and its log before sending it again"
            )
            result.update(
                {
                    "Command/Last Accepted": False,
                    "Command/Last Refusal": INTERNAL_ERROR,
                    "Command/Last Message": message,
                }
            )
        with self._lock:
            self._data(result, force=True)

    # ---- births and data (under the lock) ------------------------------------------------------------
    def _birth(self) -> bool:
        """NBIRTH (seq 0) and DBIRTH (seq 1) with every metric's current value; DATA may follow. Births the
        client cannot take (its queue full, the publish refused) are due: sent again as soon as the queue
        drains (`_on_publish`) or before the next data, on the same connection; a new one births anew."""
        self.born = False
        self._birth_due = True
        with self._counts:
            room = self.cfg.unsent_max - self._unsent >= 2  # both births, or neither (no NBIRTH alone)
        if room and self._birth_sent():
            self.born, self._birth_due = True, False
            self.births += 1
            if self._births_failing:
                log.info("telemetry: births sent on the same connection after %d tries", self._births_failing + 1)
                self._births_failing = 0
            return True
        with self._counts:
            self.births_dropped += 1
        if not self._births_failing:
            log.warning(
                "telemetry: the births could not be handed to the MQTT client (%d messages not yet sent); they are "
                "sent again as soon as it has room, and data waits for them",
                self._unsent,
            )
        self._births_failing += 1
        return False

    def _birth_sent(self) -> bool:
        self._values.update(M.snapshot_values(self.service.snapshot(), self.parts))
        node = [
            Metric(M.BD_SEQ, M.D.INT64, self.session_bd_seq),
            Metric(M.REBIRTH, M.D.BOOLEAN, False),
            Metric(M.DROPPED, M.D.UINT64, self.dropped),
        ]
        self._seq = 0
        if not self._send(self.topics.node("NBIRTH"), node, birth=True):
            return False
        specs = M.device_specs(self.commands, self.parts)
        device = [Metric(s.name, s.dtype, self._values.get(s.name)) for s in specs]
        return self._send(self.topics.device("DBIRTH"), device, birth=True)

    def _data(self, values: dict[str, Any], force: bool = False) -> None:
        """DDATA with the values that changed (all given ones with `force`)."""
        changed = {k: v for k, v in values.items() if force or self._values.get(k, _UNSET) != v}
        self._values.update(values)
        if not changed:
            return
        if not self.born and self._birth_due and self._birth() and not force:
            return  # the births just sent carry these values (and newer ones): no DDATA older than them
        if not self.born:
            with self._counts:
                self.dropped += 1
            return
        types = {s.name: s.dtype for s in M.device_specs(self.commands, self.parts)}
        self._send(self.topics.device("DDATA"), [Metric(k, types[k], v) for k, v in changed.items()], birth=False)

    def _send(self, topic: str, metrics: list[Metric], birth: bool) -> bool:
        """Publish at QoS 0, not retained (Sparkplug's rule for births and data); seq +1 when handed over."""
        with self._counts:
            if self._unsent >= self.cfg.unsent_max:
                self.dropped += 1
                return False
        stamp = now_ms()
        stamped = [Metric(m.name, m.dtype, m.value, stamp) for m in metrics]
        info = self.client.publish(topic, payload(stamped, self._seq, birth=birth, timestamp_ms=stamp), qos=0)
        if info.rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
            with self._counts:
                self.dropped += 1
            return False
        with self._counts:
            self._unsent += 1
            self.published += 1
        self._seq = next_seq(self._seq)
        return True

    # ---- the bus subscriber's thread -------------------------------------------------------------
    def handle(self, event: Event) -> None:
        if isinstance(event, PartClassesChanged):
            self._grow(event.parts)
            return
        if isinstance(event, PickVerified):
            self._cycle[event.pick_id] = event.cycle_ms
        record = self._records.of(event)
        if record is not None:
            cycle = self._cycle.pop(record.pick_id, None) if record.outcome != "failed" else None
            with self._lock:
                self._data(M.pick_values(record, cycle), force=True)  # every pick, even one like the last
            return
        if isinstance(event, StateChanged) and not self.born and not self._birth_due:
            return  # the runner's steps while the broker is away: the next birth reads the snapshot again
        if len(self.service.parts) > len(self.parts):  # its PartClassesChanged dropped (a full queue)
            self._grow(self.service.parts)
        with self._lock:  # read and published under one lock: no birth between them (it would be newer)
            self._data(M.snapshot_values(self.service.snapshot(), self.parts))

    def _grow(self, parts: PartRegistry) -> None:
        """New part classes: their counters are new metrics, which Sparkplug B announces only in a birth: the
        births are sent again (same session, same bdSeq; NBIRTH's seq 0), the new counters in the DBIRTH. No
        DDATA names them before it. While the broker is away the next birth carries them."""
        with self._lock:
            if len(parts) <= len(self.parts):
                return
            new = [p.sparkplug_name for p in parts if p.name not in self.parts]
            self.parts = parts
            if self.born or self._birth_due:
                log.info("telemetry: births sent again for the new metrics %s", ", ".join(new))
                self._birth()

    # ---- the service's warning while the broker is away ---------------------------------------------
    def _warn(self, reason: str) -> None:
        if self._closing:
            return
        with contextlib.suppress(Exception):  # the warning is for the operator; it must not break the client
            self.service.raise_warning(
                WARNING_KEY,
                reason,
                "the cell goes on picking; check the broker and the network (telemetry.mqtt.url), "
                "the plant database still records everything",
                "telemetry",
            )

    def _clear_warning(self) -> None:
        with contextlib.suppress(Exception):
            self.service.clear_warning(WARNING_KEY)

    def stats(self) -> dict[str, int]:
        with self._counts:
            return {
                "published": self.published,
                "dropped": self.dropped,
                "births": self.births,
                "births_dropped": self.births_dropped,
                "command_errors": self.command_errors,
                "callback_errors": self.callback_errors,
            }


_UNSET = object()


def attach_mqtt(
    cfg: MqttConfig,
    bus: EventBus,
    resources: contextlib.ExitStack,
    hooks: object,
    environ: dict[str, str] | None = None,
    log_dir: Path | None = None,
) -> SparkplugPublisher | None:
    """The publisher for `run-cell serve` (hooks = the line service), closed with `resources`. bdSeq is
    kept in telemetry.mqtt.state_dir, else in `data` beside `log_dir` (logs/ -> data/)."""
    if not all(callable(getattr(hooks, name, None)) for name in ("snapshot", "command")):
        log.warning("telemetry.mqtt is published by `run-cell serve` only; this run is not published")
        return None
    password = password_from_env(cfg, dict(os.environ if environ is None else environ))
    state_dir = Path(log_dir).parent / "data" if log_dir is not None else None
    publisher = SparkplugPublisher(cfg, cast(ServiceView, hooks), password, state_dir)  # its methods checked above
    publisher.start(bus)
    resources.callback(publisher.close, bus)
    return publisher
