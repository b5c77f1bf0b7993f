"""Waiting for an asyncio.Event with a timeout, without losing a cancellation.

Python 3.11's `asyncio.wait_for(event.wait(), timeout)` returns normally when its task is
cancelled in the same loop iteration as the event is set: the cancellation is lost, and a loop
around it (a publisher, a heartbeat) goes on for ever while whoever cancelled it awaits its end.
That hung the OPC UA server's stop (seen once in the suite: 90 s, then a timeout).
`asyncio.timeout` keeps the cancellation (tests/test_asyncwait.py shows both).
"""

from __future__ import annotations

import asyncio


async def wait_event(event: asyncio.Event, timeout_s: float) -> bool:
    """Whether `event` was set within `timeout_s`; a cancellation always propagates."""
    try:
        async with asyncio.timeout(timeout_s):
            await event.wait()
    except TimeoutError:
        return False
    return True
