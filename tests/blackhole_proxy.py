"""A black-holing TCP proxy on loopback, for a PostgreSQL path that goes silent (a half-open
connection): tests/test_history_pg_faults.py (the store's close) and tests/test_serve_pg_blackhole.py
(the whole service's SIGTERM)."""

from __future__ import annotations

import contextlib
import socket
import threading


class BlackHoleProxy:
    """A TCP proxy on loopback to `port`: it forwards both ways until `silence()`, then keeps
    every connection open, reads what comes and forwards nothing (a half-open path: TCP stays
    up, keepalives are answered by this host, no answer ever comes). `swallowed` counts the
    bytes read and dropped since (what a client sent into the silence)."""

    def __init__(self, port: int):
        self.upstream = ("127.0.0.1", port)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.silent = threading.Event()
        self.sockets: list[socket.socket] = []
        self.swallowed = 0
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, name="proxy-accept", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
                upstream = socket.create_connection(self.upstream)
            except OSError:
                return
            with self._lock:
                self.sockets += [client, upstream]
            for src, dst in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(src, dst), name="proxy-pump", daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                return
            if self.silent.is_set():
                if not data:
                    return  # no FIN passed on either
                with self._lock:
                    self.swallowed += len(data)
                continue
            try:
                if not data:
                    dst.shutdown(socket.SHUT_WR)
                    return
                dst.sendall(data)
            except OSError:
                return

    def url(self, user: str = "cell") -> str:
        return f"postgresql://{user}@127.0.0.1:{self.port}/postgres"

    def silence(self) -> None:
        self.silent.set()

    def close(self) -> None:
        self.listener.close()
        with self._lock:
            for s in self.sockets:
                with contextlib.suppress(OSError):
                    s.close()
