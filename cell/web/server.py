"""The screen's HTTP server: uvicorn in its own thread, beside the OPC UA server.

The socket is bound here, before the thread starts, so a port in use or an address this
machine does not have is a one-line error at start, not a log line in a thread.
Whenever users are configured the screen speaks only HTTPS (cell.web.tls); connections pass
the limits of cell.web.transport (header and body deadlines, caps per client address and in
total, clients that do not read dropped) and the Shield (HSTS, Secure cookies, event streams
per address). Plain HTTP is left only for loopback without users.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path

from cell.access.network import reachable_urls
from cell.access.throttle import LoginThrottle
from cell.config import CellConfig
from cell.core.api import LineServiceAPI
from cell.core.events import Role
from cell.web.app import build_app
from cell.web.auth import Access
from cell.web.config import WebConfig
from cell.web.shield import Shield
from cell.web.tls import server_context
from cell.web.transport import ServerThread, TransportLimits

log = logging.getLogger(__name__)


def screen_server(service: LineServiceAPI, config: CellConfig, throttle: LoginThrottle | None = None) -> WebServer:
    """The screen on `service.host`:`service.http_port`, with the service's users if any (then HTTPS only).
    `throttle`: the service's login throttle, shared with OPC UA (one is made if not given)."""
    from cell.access.users import Authenticator

    svc = config.service
    users = Authenticator(svc)
    authenticate = users.authenticate if users.configured else None
    throttle = throttle or LoginThrottle(svc.login)
    return WebServer(
        service,
        config,
        svc.web,
        svc.host,
        svc.http_port,
        authenticate=authenticate,
        throttle=throttle,
        credential=users.credential if users.configured else None,
    )


class ScreenInterface:
    """The screen as one of `run-cell serve`'s interfaces: start() and stop() coroutines, ready_text."""

    def __init__(self, service: LineServiceAPI, config: CellConfig, throttle: LoginThrottle | None = None):
        self.service, self.config, self.throttle = service, config, throttle
        self.server: WebServer | None = None

    async def start(self) -> None:
        # binds: a port in use is a ConfigError here
        self.server = screen_server(self.service, self.config, self.throttle)
        await asyncio.to_thread(self.server.start)

    async def stop(self) -> None:
        if self.server is not None:
            await asyncio.to_thread(self.server.stop)

    @property
    def ready_text(self) -> str:
        if self.server is None:
            return "screen (not started)"
        # a wildcard bind (0.0.0.0, ::) as the machine's addresses, which someone can type into a browser
        return f"screen {reachable_urls('https' if self.server.https else 'http', self.server.host, self.server.port)}"

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
        *,
        authenticate: Callable[[str, str], Role | None] | None = None,
        throttle: LoginThrottle | None = None,
        certificate_dir: Path | None = None,
        credential: Callable[[str], str | None] | None = None,
    ):
        """`authenticate(user, password) -> Role | None` (or the older `check_password`): None without users.
        With users the screen is HTTPS only, its certificate from service.web or made in `certificate_dir`.
        `credential(user)`: the user's fingerprint now (Authenticator.credential): sessions end when it changes."""
        from cell.access.security import certificate_dir as default_certificate_dir

        # refuses a non-loopback bind without users
        self.access = Access(
            host, web, check_password, authenticate=authenticate, throttle=throttle, credential=credential
        )
        self.app = build_app(service, config, web, self.access)
        self.host = host
        self.https = self.access.login_required
        ssl_context = None
        if self.https:
            cert_dir = certificate_dir or default_certificate_dir(config)
            ssl_context = server_context(web.tls_certificate, web.tls_key, cert_dir, host)
        self.limits = TransportLimits.from_web(web)
        self.asgi = Shield(
            self.app,
            https=self.https,
            hsts_max_age_s=web.hsts_max_age_s,
            max_streams_per_address=web.max_streams_per_address,
        )
        self.serving = ServerThread(self.asgi, host, port, self.limits, ssl_context)  # binds: errors now
        self.port = self.serving.port

    @property
    def url(self) -> str:
        return self.serving.url

    def start(self, timeout_s: float = 10.0) -> None:
        self.serving.start(timeout_s)
        log.info(
            "screen listening on %s (login %s)",
            self.url,
            "required, HTTPS only" if self.access.login_required else "not required: loopback only",
        )

    def stop(self) -> None:
        self.app.screen.hub.close()  # ends the event streams, so shutdown need not wait for them
        self.serving.stop()
