"""The screen's HTTP server: uvicorn in its own thread, beside the OPC UA server.

The socket is bound here, before the thread starts, so a port in use or an address this
machine does not have is a one-line error at start, not a log line in a thread.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
from collections.abc import Callable

import uvicorn

from cell.config import CellConfig
from cell.errors import ConfigError
from cell.service.api import LineServiceAPI
from cell.web.app import build_app
from cell.web.auth import Access
from cell.web.config import WebConfig

log = logging.getLogger(__name__)


def bind(host: str, port: int) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host.strip("[]"), port))
        sock.listen(64)
    except OSError as e:
        sock.close()
        raise ConfigError(
            f"screen: cannot listen on {host}:{port}: {e.strerror or e}",
            hint="another program has the port (choose --http-port or service.http_port) or the address is not this machine's",
        ) from None
    return sock


def screen_server(service: LineServiceAPI, config: CellConfig) -> WebServer:
    """The screen on `service.host`:`service.http_port`, with the service's user and password if set."""
    from cell.service.security import credentials_configured, password_ok

    svc = config.service
    check = (lambda user, password: password_ok(svc, user, password)) if credentials_configured(svc) else None
    return WebServer(service, config, svc.web, svc.host, svc.http_port, check)


class ScreenInterface:
    """The screen as one of `run-cell serve`'s interfaces: start() and stop() coroutines, ready_text."""

    def __init__(self, service: LineServiceAPI, config: CellConfig):
        self.service, self.config = service, config
        self.server: WebServer | None = None

    async def start(self) -> None:
        self.server = screen_server(self.service, self.config)  # binds: a port in use is a ConfigError here
        await asyncio.to_thread(self.server.start)

    async def stop(self) -> None:
        if self.server is not None:
            await asyncio.to_thread(self.server.stop)

    @property
    def ready_text(self) -> str:
        return f"screen {self.server.url}"

    @property
    def starting_text(self) -> str:
        svc = self.config.service
        return f"the operator screen on {svc.host}:{svc.http_port}"


class WebServer:
    """Start, address, stop. Stopping ends every open event stream and joins the thread."""

    def __init__(
        self,
        service: LineServiceAPI,
        config: CellConfig,
        web: WebConfig,
        host: str,
        port: int,
        check_password: Callable[[str, str], bool] | None = None,
    ):
        self.access = Access(host, web, check_password)  # refuses a non-loopback bind without a password
        self.app = build_app(service, config, web, self.access)
        self.host = host
        self._sock = bind(host, port)
        self.port = self._sock.getsockname()[1]
        self._server = uvicorn.Server(
            uvicorn.Config(
                self.app,
                log_config=None,
                access_log=False,
                lifespan="on",
                timeout_graceful_shutdown=2,
            )
        )
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self, timeout_s: float = 10.0) -> None:
        self._thread = threading.Thread(
            target=self._server.run, kwargs={"sockets": [self._sock]}, name="screen-http", daemon=True
        )
        self._thread.start()
        deadline = threading.Event()
        for _ in range(int(timeout_s / 0.02)):
            if self._server.started or not self._thread.is_alive():
                break
            deadline.wait(0.02)
        if not self._server.started:
            self.stop()
            raise ConfigError(f"screen: the HTTP server on {self.url} did not start within {timeout_s:g} s")
        log.info(
            "screen listening on %s (login %s)",
            self.url,
            "required" if self.access.login_required else "not required: loopback only",
        )

    def stop(self) -> None:
        self.app.screen.hub.close()  # ends the event streams, so shutdown need not wait for them
        self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout=10)
            if self._thread.is_alive():
                log.warning("screen: HTTP thread still running 10 s after stop")
            self._thread = None
        self._sock.close()
