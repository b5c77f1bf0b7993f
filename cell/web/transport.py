"""The screen's connections: TLS, and limits so that no client can starve the screen, OPC UA or
the process of descriptors.

uvicorn (h11) has no deadline for a request's headers: a client that sends a request line and
then nothing holds its connection, and its file descriptor, for ever; 1,100 of them under
`ulimit -n 1024` leave the whole process unable to accept or open anything. So the screen
accepts its connections itself (`LimitedServer`, a uvicorn.Server that builds its own
listener), and every accepted connection goes through a `Gate`:

- admission: at most `max_connections_per_address` open from one client address (any more
  are reset at once: their descriptor is freed in microseconds), and at most
  `max_connections` in all: past that a newcomer takes the place of a connection that is
  only waiting (for its request's headers, or idle between requests): the oldest of the
  address holding the most, so machines holding many half-sent requests cannot lock out a
  real client;
- one deadline from accept for the TLS handshake and the request headers
  (`header_timeout_s`), then one for the body (`body_timeout_s`); a keep-alive connection
  gets a fresh header deadline with each request's first bytes;
- a client that takes nothing we send for `write_stall_s` once `send_buffer_kb` are queued
  for it (an event stream nobody reads) is reset, which ends its stream;
- TLS (when a context is given) is started by the gate with the same deadline.

Refusals are counted and logged as one line a minute per reason (`Tally`), never one per
connection.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from cell.asyncwait import wait_event
from cell.errors import ConfigError
from cell.logratelimit import Tally

log = logging.getLogger(__name__)

EARLY_DATA_MAX_BYTES = 65536  # bytes a client may send between the TLS handshake and the hand-over
THIS_PC = frozenset({"127.0.0.1", "::1", "::ffff:127.0.0.1"})  # the addresses a browser on this PC comes from
ACCEPT_BATCH = 32  # connections asyncio accepts at one wake-up (its `backlog`), before their Gates run
LISTEN_QUEUE = 1024  # the kernel's queue of connections waiting to be accepted


@dataclass(frozen=True)
class TransportLimits:
    header_timeout_s: float = 10.0
    body_timeout_s: float = 120.0
    keepalive_timeout_s: float = 5.0
    max_connections: int = 256
    max_connections_per_address: int = 32
    write_stall_s: float = 15.0
    send_buffer_bytes: int = 256 * 1024

    @classmethod
    def from_web(cls, web: Any) -> TransportLimits:
        """From a WebConfig (cell.web.config)."""
        return cls(
            header_timeout_s=web.header_timeout_s,
            body_timeout_s=web.body_timeout_s,
            keepalive_timeout_s=web.keepalive_timeout_s,
            max_connections=web.max_connections,
            max_connections_per_address=web.max_connections_per_address,
            write_stall_s=web.write_stall_s,
            send_buffer_bytes=web.send_buffer_kb * 1024,
        )


class Admission:
    """Open connections per client address and in total (touched from the server's loop only)."""

    def __init__(self, limits: TransportLimits) -> None:
        self.limits = limits
        self.per_address: Counter[str] = Counter()
        self.open = 0

    def refusal(self, address: str) -> str | None:
        """Why a connection from `address` may not be admitted even at the cost of a waiting one (None: it may).
        This PC's own browser (127.0.0.1, ::1) is not capped per address: its tabs share one address."""
        if address in THIS_PC:
            return None
        if self.per_address[address] >= self.limits.max_connections_per_address:
            return f"refused: {self.limits.max_connections_per_address} open from one address (max_connections_per_address)"
        return None

    @property
    def full(self) -> bool:
        return self.open >= self.limits.max_connections

    def admit(self, address: str) -> None:
        self.per_address[address] += 1
        self.open += 1

    def release(self, address: str) -> None:
        self.open -= 1
        self.per_address[address] -= 1
        if self.per_address[address] <= 0:
            del self.per_address[address]


class Ticket:
    """One admitted connection; `release()` gives its place back, once, whoever calls it."""

    def __init__(self, admission: Admission, address: str) -> None:
        self.admission, self.address = admission, address
        self._held = True

    def release(self) -> None:
        if self._held:
            self._held = False
            self.admission.release(self.address)


def _cancel(handle: asyncio.TimerHandle | None) -> None:
    if handle is not None:
        handle.cancel()


class LimitedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with deadlines for headers and body, and a cut for clients that do not read."""

    def __init__(
        self, *args: Any, limits: TransportLimits, ticket: Ticket, deadline: float, waiting: Waiting, **kw: Any
    ):
        super().__init__(*args, **kw)
        self.limits, self.ticket, self.waiting = limits, ticket, waiting
        self.tally = waiting.tally
        self._first_deadline = deadline  # loop time by which the first request's headers must be in
        self._header_timer: asyncio.TimerHandle | None = None
        self._body_timer: asyncio.TimerHandle | None = None
        self._stall_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]  # as uvicorn's own
        super().connection_made(transport)
        transport.set_write_buffer_limits(high=self.limits.send_buffer_bytes)
        self._header_timer = self.loop.call_at(self._first_deadline, self._cut, "cut: request headers too slow")
        self.waiting.add(self)

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._follow_request()

    def _follow_request(self) -> None:
        """Arm or disarm the header and body deadlines from where h11 stands in the client's request."""
        if self.transport.is_closing():
            return
        theirs = self.conn.their_state
        if theirs is h11.IDLE:
            self.waiting.add(self)  # for headers, or idle between requests: the first to go when all are taken
            started = bool(self.conn.trailing_data[0])  # bytes of a next request are in (a kept-alive connection)
            if self._header_timer is None and started:
                self._header_timer = self.loop.call_later(
                    self.limits.header_timeout_s, self._cut, "cut: request headers too slow"
                )
            return
        self.waiting.discard(self)
        _cancel(self._header_timer)
        self._header_timer = None
        if theirs is h11.SEND_BODY:
            if self._body_timer is None:
                self._body_timer = self.loop.call_later(
                    self.limits.body_timeout_s, self._cut, "cut: request body too slow"
                )
        else:
            _cancel(self._body_timer)
            self._body_timer = None

    def on_response_complete(self) -> None:
        _cancel(self._body_timer)
        self._body_timer = None
        super().on_response_complete()  # may start a pipelined request
        self._follow_request()

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall_timer is None:
            self._stall_timer = self.loop.call_later(self.limits.write_stall_s, self._cut, "cut: client not reading")

    def resume_writing(self) -> None:
        super().resume_writing()
        _cancel(self._stall_timer)
        self._stall_timer = None

    def shutdown(self) -> None:
        """The server is stopping: a response stuck in a send to a client that does not read (an event
        stream whose reader is slow or gone) is reset now, so that it ends cleanly; otherwise uvicorn's,
        which waits for the response to finish and, past its grace period, cancels it and logs a
        traceback for each one."""
        if self.cycle is not None and not self.cycle.response_complete and self.flow.write_paused:
            self.evict()
            return
        super().shutdown()

    def _cut(self, reason: str) -> None:
        self.tally.note(reason, self.ticket.address)
        self.evict()

    def evict(self) -> None:
        """Reset the connection now (nothing queued is worth waiting for) and give its place back."""
        self.waiting.discard(self)
        self.ticket.release()
        self.transport.abort()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._header_timer, self._body_timer, self._stall_timer):
            _cancel(timer)
        self._header_timer = self._body_timer = self._stall_timer = None
        self.waiting.discard(self)
        self.ticket.release()
        super().connection_lost(exc)


class Gate(asyncio.Protocol):
    """The first protocol of every accepted connection: admission, TLS, then the HTTP protocol."""

    def __init__(self, server: LimitedServer) -> None:
        self.server = server
        self.loop = asyncio.get_running_loop()
        self.transport: asyncio.Transport | None = None
        self.ticket: Ticket | None = None
        self._early: list[bytes] = []
        self._early_bytes = 0
        self._task: asyncio.Task[None] | None = None
        self._handed_over = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        if not isinstance(transport, asyncio.Transport):  # what asyncio's TCP server hands a protocol
            raise TypeError(f"screen: a {type(transport).__name__} is not a stream transport")
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if peer else "?"
        if not self.server.make_room(address):
            transport.abort()
            return
        self.server.admission.admit(address)
        self.transport = transport
        self.ticket = Ticket(self.server.admission, address)
        self.server.waiting.add(self)
        self.deadline = self.loop.time() + self.server.limits.header_timeout_s
        sock = transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):  # what the kernel queues counts toward "not reading" too
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.server.limits.send_buffer_bytes // 2)
        if self.server.ssl_context is None:
            self._hand_over(transport)
        else:
            self._task = self.loop.create_task(self._start_tls(self.server.ssl_context))

    async def _start_tls(self, context: ssl.SSLContext) -> None:
        assert self.transport is not None and self.ticket is not None
        try:
            tls = await self.loop.start_tls(
                self.transport,
                self,
                context,
                server_side=True,
                ssl_handshake_timeout=max(0.1, self.deadline - self.loop.time()),
            )
        except (OSError, ssl.SSLError, TimeoutError, ConnectionError) as e:
            self.server.tally.note(f"cut: TLS handshake failed or too slow ({type(e).__name__})", self.ticket.address)
            self.transport.abort()
            self._done()
            return
        if tls is None or tls.is_closing():
            self._done()
            return
        self._hand_over(tls)

    def _hand_over(self, transport: asyncio.Transport) -> None:
        assert self.ticket is not None
        self._handed_over = True
        self.server.waiting.discard(self)
        http = self.server.make_http(self.ticket, self.deadline)
        transport.set_protocol(http)
        http.connection_made(transport)
        early, self._early = b"".join(self._early), []
        if early:
            http.data_received(early)

    def data_received(self, data: bytes) -> None:
        """Only between the TLS handshake and the hand-over: kept for the HTTP protocol."""
        self._early.append(data)
        self._early_bytes += len(data)
        if self._early_bytes > EARLY_DATA_MAX_BYTES and self.transport is not None:
            self.transport.abort()

    def eof_received(self) -> bool | None:
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        if not self._handed_over:
            if self._task is not None and self._task is not asyncio.current_task():
                self._task.cancel()
            self._done()

    def _done(self) -> None:
        self.server.waiting.discard(self)
        if self.ticket is not None:
            self.ticket.release()

    def evict(self) -> None:
        self._done()
        if self.transport is not None:
            self.transport.abort()


class Waiting:
    """The connections only waiting (a handshake, a request's headers, or idle between requests), per client
    address, oldest first. The one to give way is the oldest of the address holding the most: a real client
    holds one or a few, a flood of half-sent requests holds many from each of its machines."""

    def __init__(self, tally: Tally) -> None:
        self.tally = tally
        self._by_address: dict[str, dict[Any, None]] = {}

    def add(self, connection: Any) -> None:
        self._by_address.setdefault(connection.ticket.address, {})[connection] = None

    def discard(self, connection: Any) -> None:
        ticket = getattr(connection, "ticket", None)
        if ticket is None:
            return
        mine = self._by_address.get(ticket.address)
        if mine is not None:
            mine.pop(connection, None)
            if not mine:
                del self._by_address[ticket.address]

    def victim(self) -> Any | None:
        if not self._by_address:
            return None
        heaviest = max(self._by_address.values(), key=len)
        return next(iter(heaviest))

    def __len__(self) -> int:
        return sum(len(m) for m in self._by_address.values())

    def __iter__(self) -> Iterator[Any]:
        return iter([c for m in self._by_address.values() for c in m])


TICK_S = 1.0  # uvicorn's housekeeping tick (the Date header, should_exit): 0.1 s in uvicorn


class LimitedServer(uvicorn.Server):
    """A uvicorn server whose connections pass a Gate: limits and deadlines, and TLS when given a context."""

    def __init__(
        self,
        config: uvicorn.Config,
        limits: TransportLimits,
        ssl_context: ssl.SSLContext | None = None,
        name: str = "screen",
    ) -> None:
        super().__init__(config)
        self.limits, self.ssl_context = limits, ssl_context
        self.admission = Admission(limits)
        self.tally = Tally(name)
        self.waiting = Waiting(self.tally)
        self._tick_loop: asyncio.AbstractEventLoop | None = None
        self._tick_wake: asyncio.Event | None = None

    async def main_loop(self) -> None:
        """uvicorn's, ticking once a TICK_S rather than ten times a second (each tick takes Python's
        interpreter lock from the control thread for a moment); `request_exit` ends it at once."""
        self._tick_loop, self._tick_wake = asyncio.get_running_loop(), asyncio.Event()
        counter = 0
        should_exit = await self.on_tick(counter)
        while not should_exit:
            counter = (counter + 10) % 864000  # on_tick refreshes the Date header when counter % 10 == 0
            await wait_event(self._tick_wake, TICK_S)
            should_exit = await self.on_tick(counter)

    def request_exit(self) -> None:
        """From any thread: stop serving now (uvicorn's should_exit, and the tick woken)."""
        self.should_exit = True
        loop, wake = self._tick_loop, self._tick_wake
        if loop is not None and wake is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                loop.call_soon_threadsafe(wake.set)

    def make_room(self, address: str) -> bool:
        """Whether a connection from `address` may come in, evicting the oldest waiting one if all places are taken."""
        refused = self.admission.refusal(address)
        if refused is None and self.admission.full:
            victim = self.waiting.victim()
            if victim is None:
                refused = f"refused: {self.limits.max_connections} open connections, all busy (max_connections)"
            else:
                self.tally.note("evicted: a waiting connection, all places taken", victim.ticket.address)
                victim.evict()
        if refused is not None:
            self.tally.note(refused, address)
            return False
        return True

    def make_http(self, ticket: Ticket, deadline: float) -> LimitedH11Protocol:
        return LimitedH11Protocol(
            config=self.config,
            server_state=self.server_state,
            app_state=self.lifespan.state,
            _loop=asyncio.get_running_loop(),
            limits=self.limits,
            ticket=ticket,
            deadline=deadline,
            waiting=self.waiting,
        )

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        """uvicorn's startup for given sockets, with our Gate as the protocol and TLS done by the gate."""
        if not sockets:
            raise ValueError("LimitedServer serves sockets bound beforehand (cell.web.server.bind)")
        await self.lifespan.startup()
        if self.lifespan.should_exit:
            self.should_exit = True
            return
        loop = asyncio.get_running_loop()
        self.servers = []
        for sock in sockets:
            # asyncio accepts up to `backlog` sockets per wake-up before any of them reaches its Gate: keep that
            # batch small so a flood cannot take every descriptor between two looks; the kernel's queue stays long.
            self.servers.append(await loop.create_server(lambda: Gate(self), sock=sock, backlog=ACCEPT_BATCH))
            sock.listen(LISTEN_QUEUE)
        self.started = True

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for connection in self.waiting:  # handshakes and half-sent requests: nothing to finish
            connection.evict()
        await super().shutdown(sockets)


def uvicorn_config(app: Any, limits: TransportLimits) -> uvicorn.Config:
    """The uvicorn settings the limited server runs with (h11: the protocol LimitedH11Protocol extends)."""
    return uvicorn.Config(
        app,
        http="h11",
        log_config=None,
        access_log=False,
        lifespan="on",
        timeout_graceful_shutdown=2,
        timeout_keep_alive=limits.keepalive_timeout_s,  # type: ignore[arg-type]  # uvicorn says int; call_later takes a float
    )


def bind(host: str, port: int, what: str = "screen") -> socket.socket:
    """The listening socket, bound now: a port in use or an address not this machine's is a ConfigError at start."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host.strip("[]"), port))
        sock.listen(128)
    except OSError as e:
        sock.close()
        raise ConfigError(
            f"{what}: cannot listen on {host}:{port}: {e.strerror or e}",
            hint="another program has the port (choose --http-port or service.http_port) or the address is not this machine's",
        ) from None
    return sock


class ServerThread:
    """An ASGI app served by a LimitedServer in its own thread: bind (in the constructor), start, url, stop."""

    def __init__(
        self,
        app: Any,
        host: str,
        port: int,
        limits: TransportLimits,
        ssl_context: ssl.SSLContext | None = None,
        name: str = "screen",
    ) -> None:
        self.host, self.name = host, name
        self._sock = bind(host, port, name)
        self.port = self._sock.getsockname()[1]
        self.server = LimitedServer(uvicorn_config(app, limits), limits, ssl_context, name)
        self.https = ssl_context is not None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'https' if self.https else 'http'}://{host}:{self.port}/"

    def start(self, timeout_s: float = 10.0) -> None:
        self._thread = threading.Thread(
            target=self.server.run, kwargs={"sockets": [self._sock]}, name=f"{self.name}-http", daemon=True
        )
        self._thread.start()
        waiter = threading.Event()
        for _ in range(int(timeout_s / 0.02)):
            if self.server.started or not self._thread.is_alive():
                break
            waiter.wait(0.02)
        if not self.server.started:
            self.stop()
            raise ConfigError(f"{self.name}: the HTTP server on {self.url} did not start within {timeout_s:g} s")

    def stop(self) -> None:
        self.server.request_exit()
        if self._thread is not None:
            self._thread.join(timeout=10)
            if self._thread.is_alive():
                log.warning("%s: HTTP thread still running 10 s after stop", self.name)
            self._thread = None
        self._sock.close()
