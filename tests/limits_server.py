"""A server process for the limit and security probes: the screen's transport (TLS, deadlines,
caps, the Shield) over a small screen-like app, and the guarded OPC UA server, in one process
as `run-cell serve` has them, so both share one descriptor table (and its RLIMIT_NOFILE).

    python -m tests.limits_server WORKDIR [--tls] [--users] [--opcua-port N] [--http-port N]

prints `ready: screen URL; opcua URL` and serves until SIGTERM. The app's routes:
`/api/state` (a small JSON reply), `/api/events` (server-sent events: a ~4 KB state ten
times a second, as a running cell's screen gets), `/api/status` (this process's open
descriptors, the transport's and OPC UA's counts: what the probes check). OPC UA: object
Cell (namespace urn:pick-cell) with variable Heartbeat and method Halt, which returns the
caller's role (cell.service.opcua_security.caller_origin). Users (with --users): op/op-pass-1
(operator) and eng/eng-pass-1 (engineer), PBKDF2 at 1,000 iterations to keep tests fast;
`--check-delay-s` makes each password check last that long (as the real 600,000 iterations do),
and /api/status counts the checks made (`password_checks`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import resource
import signal
import threading
import time
from pathlib import Path

from asyncua import ua
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, StreamingResponse
from starlette.routing import Route

from cell.access.throttle import LoginThrottle
from cell.access.users import Authenticator, UserEntry, hash_password, write_users
from cell.config import CellConfig
from cell.core.events import Role
from cell.errors import CellError
from cell.imagedecode import decode_limited
from cell.oplog import log_to_file
from cell.service.opcua_security import GuardedServer, GuardSettings, caller_origin
from cell.web.shield import Shield, set_on_disconnect
from cell.web.tls import server_context
from cell.web.transport import ServerThread, TransportLimits

USERS = {"op": ("op-pass-1", Role.OPERATOR), "eng": ("eng-pass-1", Role.ENGINEER)}
NAMESPACE = "urn:pick-cell"


def open_descriptors() -> int:
    return len(os.listdir("/proc/self/fd"))


def build_app(status: dict) -> Starlette:
    async def state(request: Request) -> JSONResponse:
        return JSONResponse({"ok": True, "heartbeat": status["heartbeat"]})

    async def events(request: Request) -> StreamingResponse:
        async def stream():
            i = 0
            while True:
                yield f"event: state\ndata: {json.dumps({'i': i, 'pad': 'x' * 4000})}\n\n"
                i += 1
                await asyncio.sleep(0.1)

        return StreamingResponse(stream(), media_type="text/event-stream")

    async def report(request: Request) -> JSONResponse:
        return JSONResponse(status["report"]())

    async def upload(request: Request) -> JSONResponse:
        """As the screen's plate upload: the body (at most 25 MB), decoded within limits, stopped if the client goes."""
        pieces, size = [], 0
        async for piece in request.stream():
            pieces.append(piece)
            size += len(piece)
            if size > 25 * 2**20:
                return JSONResponse({"error": "upload too large"}, 413)
        body = b"".join(pieces)
        gone = threading.Event()
        watcher = asyncio.create_task(set_on_disconnect(request.receive, gone))
        try:
            image = await run_in_threadpool(decode_limited, body, max_px=1920 * 1080, timeout_s=10, cancelled=gone)
        except CellError as e:
            return JSONResponse({"error": str(e)}, 422)
        finally:
            watcher.cancel()
        return JSONResponse({"shape": list(image.shape)})

    return Starlette(
        routes=[
            Route("/api/state", state),
            Route("/api/events", events),
            Route("/api/status", report),
            Route("/api/upload", upload, methods=["POST"]),
        ]
    )


async def serve(args: argparse.Namespace) -> None:
    workdir = Path(args.workdir)
    log_to_file(workdir / "serve.log")
    for name in ("asyncua", "uvicorn"):  # as cell.service.opcua quiets them: the log keeps what matters
        logging.getLogger(name).setLevel(logging.WARNING)
    config = CellConfig()
    config.calibration.active_path = workdir / "calibration" / "active.json"
    config.service.certificate_dir = workdir / "certs"
    if args.users:
        config.service.users_file = workdir / "users.json"
        write_users(
            config.service.users_file,
            [UserEntry(n, role, hash_password(pw, 1000)) for n, (pw, role) in USERS.items()],
        )
    for key, value in json.loads(args.limits).items():  # e.g. {"opcua_limits": {"max_connections": 64}}
        if isinstance(value, dict):
            section = getattr(config.service, key)
            for field, v in value.items():
                setattr(section, field, v)
        else:
            setattr(config.service, key, value)
    users = Authenticator(config.service)
    throttle = LoginThrottle(config.service.login)
    checks = {"made": 0}
    counting = threading.Lock()

    def authenticate(user: str, password: str) -> Role | None:
        with counting:
            checks["made"] += 1
        if args.check_delay_s > 0:
            time.sleep(args.check_delay_s)  # the time a real hash takes (off the event loop, as the server calls it)
        return users.authenticate(user, password)

    status: dict = {"heartbeat": 0}

    # the screen's transport
    web = config.service.web
    limits = TransportLimits.from_web(web)
    ssl_context = server_context(None, None, config.service.certificate_dir, "127.0.0.1") if args.tls else None
    app = Shield(build_app(status), https=args.tls, max_streams_per_address=web.max_streams_per_address)
    screen = ServerThread(app, "127.0.0.1", args.http_port, limits, ssl_context)
    screen.start()

    # OPC UA
    secure = users.configured
    settings = GuardSettings.from_config(config, "urn:pick-cell:server", secure)
    opcua = GuardedServer(settings, authenticate if secure else None, throttle, users.credential if secure else None)
    await opcua.init()
    endpoint = f"opc.tcp://127.0.0.1:{args.opcua_port}/cell"
    opcua.set_endpoint(endpoint)
    await opcua.set_application_uri("urn:pick-cell:server")
    if secure:
        await opcua.secure()
    else:
        opcua.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        opcua.set_identity_tokens([ua.AnonymousIdentityToken])
    ns = await opcua.register_namespace(NAMESPACE)
    cell = await opcua.nodes.objects.add_object(ua.NodeId("Cell", ns), ua.QualifiedName("Cell", ns))
    heartbeat = await cell.add_variable(ua.NodeId("Heartbeat", ns), ua.QualifiedName("Heartbeat", ns), 0)

    async def halt(parent):
        origin = caller_origin()
        return [ua.Variant(origin.role.value if origin is not None else "none", ua.VariantType.String)]

    await cell.add_method(ua.NodeId("Halt", ns), ua.QualifiedName("Halt", ns), halt, [], [ua.VariantType.String])
    await opcua.start()

    def report() -> dict:
        iserver = opcua.iserver
        return {
            "open_descriptors": open_descriptors(),
            "nofile_limit": resource.getrlimit(resource.RLIMIT_NOFILE)[0],
            "screen_open": screen.server.admission.open,
            "screen_tally": dict(screen.server.tally.total),
            "streams": dict(app.streams),
            "opcua_connections": len(opcua.bserver.clients) if opcua.bserver else 0,
            "opcua_sessions": len(iserver._external_sessions),
            "opcua_subscriptions": len(iserver.subscription_service.subscriptions),
            "opcua_tally": dict(opcua.guard.tally.total),
            "password_checks": checks["made"],
            "cpu_s": sum(os.times()[:2]),
        }

    status["report"] = report
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    print(f"ready: screen {screen.url}; opcua {endpoint}", flush=True)
    while not stop.is_set():
        status["heartbeat"] += 1
        await heartbeat.write_value(status["heartbeat"])
        try:
            await asyncio.wait_for(stop.wait(), 0.5)
        except TimeoutError:
            pass
    await opcua.stop()
    await asyncio.to_thread(screen.stop)


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("workdir")
    p.add_argument("--tls", action="store_true")
    p.add_argument("--users", action="store_true")
    p.add_argument("--http-port", type=int, default=0)
    p.add_argument("--opcua-port", type=int, required=True)
    p.add_argument("--check-delay-s", type=float, default=0.0, help="how long each password check takes")
    p.add_argument("--limits", default="{}", help="JSON: service sub-sections and fields to override")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    asyncio.run(serve(args))


if __name__ == "__main__":
    main()
