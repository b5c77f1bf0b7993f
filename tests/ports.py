"""Free TCP ports for the servers the tests start, handed out so that two never meet.

Asking the kernel for port 0 and closing the socket (the usual trick) hands the same port out
again: two calls in a row can return one port (a serve's OPC UA and screen then collide), and
another xdist worker can take it before the server binds. So ports come from below the kernel's
ephemeral range (where it never puts a client's or a port-0 socket), each xdist worker from a
slice of its own, each port once per process, and only after a test bind says it is free now."""

from __future__ import annotations

import itertools
import os
import socket
import threading
from pathlib import Path

SPAN = 12_000  # ports below the ephemeral range shared out among the workers


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _worker_slice() -> range:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    count = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))
    high = _ephemeral_low()
    low = max(1025, high - SPAN)
    width = (high - low) // max(count, index + 1)
    start = low + index * width
    return range(start, start + width)


_lock = threading.Lock()
_candidates = itertools.cycle(_worker_slice())
_given: set[int] = set()


def _bindable(port: int) -> bool:
    for host in ("127.0.0.1", "0.0.0.0"):
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True


def free_port() -> int:
    """A loopback TCP port nobody holds, never handed out before in this process."""
    with _lock:
        for _ in range(len(_worker_slice())):
            port = next(_candidates)
            if port not in _given and _bindable(port):
                _given.add(port)
                return port
    raise RuntimeError("no free port left in this test worker's slice")
