"""OPC UA clients that connect securely, log in, subscribe, and vanish: in batches, each batch
in a forked child that exits without closing anything (as a crashed or unplugged PLC does),
so the server sees every TCP connection of the batch drop with its session and subscription
still open.

    python -m tests.vanishing_clients URL SERVER_CERT KEY CERT URI COUNT [BATCH [CONCURRENCY]]

prints `subscribed N of COUNT` at the end (a line per failed client before it).
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
from pathlib import Path

from asyncua import ua

from tests.probes import Credentials, secure_client


class _Quiet:
    def datachange_notification(self, node, value, data) -> None:
        pass


async def one(url: str, credentials: Credentials) -> bool:
    client = await secure_client(url, credentials, timeout_s=20)
    try:
        await client.connect()
        subscription = await client.create_subscription(500, _Quiet())
        await subscription.subscribe_data_change(
            client.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime))
        )
        return True
    except Exception as e:  # counted, not raised: the caller compares the count
        print(f"client failed: {type(e).__name__}: {e}", flush=True)
        return False


async def main(url: str, server_cert: str, key: str, cert: str, uri: str, count: int, concurrency: int) -> int:
    gate = asyncio.Semaphore(concurrency)
    credentials = Credentials(Path(key), Path(cert), uri, Path(server_cert))

    async def limited() -> bool:
        async with gate:
            return await one(url, credentials)

    results = await asyncio.gather(*(limited() for _ in range(count)))
    return sum(results)


def batch_in_child(args: list[str], count: int, concurrency: int) -> int:
    """Fork; the child runs `count` clients and vanishes (os._exit: no CloseSession, no DeleteSubscriptions),
    reporting how many subscribed in its exit status."""
    pid = os.fork()
    if pid == 0:
        try:
            done = asyncio.run(main(*args, count, concurrency))
        finally:
            sys.stdout.flush()
        os._exit(min(done, 255))
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


if __name__ == "__main__":
    logging.basicConfig(level=logging.CRITICAL)
    url, server_cert, key, cert, uri, count = sys.argv[1:7]
    batch = int(sys.argv[7]) if len(sys.argv) > 7 else 50
    concurrency = int(sys.argv[8]) if len(sys.argv) > 8 else 8
    total, left = 0, int(count)
    while left > 0:
        total += batch_in_child([url, server_cert, key, cert, uri], min(batch, left), concurrency)
        left -= batch
    print(f"subscribed {total} of {count}", flush=True)
