"""Pure-ASGI middleware around the screen app, outermost: what holds for every reply whatever
the routes do.

- Over HTTPS: `Strict-Transport-Security` on every reply, and every cookie `Secure` (the
  app sets HttpOnly and SameSite=Strict itself; `Secure` is added here if it is missing).
- Event streams (`/api/events`): at most `max_streams_per_address` open from one client
  address, so one machine cannot take every screen slot (the rest get 503 and the page
  tries again by itself); this PC's own browser (127.0.0.1, ::1) is bounded by the
  screen's `max_screens` only.
"""

from __future__ import annotations

import asyncio
import threading
from collections import Counter
from collections.abc import Awaitable, Callable
from typing import Any

from starlette.responses import JSONResponse

from cell.web.transport import THIS_PC

STREAM_PATHS = frozenset({"/api/events"})


class Shield:
    def __init__(
        self,
        app: Any,
        *,
        https: bool,
        hsts_max_age_s: int = 31_536_000,
        max_streams_per_address: int = 4,
        stream_paths: frozenset[str] = STREAM_PATHS,
    ) -> None:
        self.app, self.https = app, https
        self.hsts = f"max-age={hsts_max_age_s}".encode() if https and hsts_max_age_s > 0 else None
        self.max_streams = max_streams_per_address
        self.stream_paths = stream_paths
        self.streams: Counter[str] = Counter()  # open streams per address (the server's loop only)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        if self.https:
            send = self._secure(send)
        if scope.get("path") not in self.stream_paths:
            return await self.app(scope, receive, send)
        address = (scope.get("client") or ("?", 0))[0]
        if self.streams[address] >= self.max_streams and address not in THIS_PC:  # this PC's tabs: max_screens
            reply = JSONResponse(
                {
                    "error": f"{self.max_streams} screens are already open from {address} (service.web.max_streams_per_address)"
                },
                status_code=503,
                headers={"retry-after": "5"},
            )
            return await reply(scope, receive, send)
        self.streams[address] += 1
        try:
            await self.app(scope, receive, send)
        finally:
            self.streams[address] -= 1
            if self.streams[address] <= 0:
                del self.streams[address]

    def _secure(self, send: Any) -> Any:
        async def wrapped(message: dict) -> None:
            if message["type"] == "http.response.start":
                headers = [
                    (k, _secure_cookie(v) if k.lower() == b"set-cookie" else v) for k, v in message.get("headers", [])
                ]
                if self.hsts is not None:
                    headers.append((b"strict-transport-security", self.hsts))
                message = {**message, "headers": headers}
            await send(message)

        return wrapped


def _secure_cookie(value: bytes) -> bytes:
    attributes = [part.strip().lower() for part in value.split(b";")[1:]]
    return value if b"secure" in attributes else value + b"; Secure"


async def set_on_disconnect(receive: Callable[[], Awaitable[dict]], event: threading.Event) -> None:
    """Set `event` when the client goes away (for work in a thread or process to stop): run it as a task
    once the request's body has been read, and cancel the task when the reply is ready."""
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            event.set()
            return
        await asyncio.sleep(0)
