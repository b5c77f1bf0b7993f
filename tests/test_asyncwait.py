"""cell.asyncwait.wait_event: a loop waiting on an event with a timeout ends when cancelled, even
when the cancellation comes in the same loop iteration as the event (Python 3.11's wait_for then
returns normally and the loop never ends: what hung the OPC UA server's stop once)."""

from __future__ import annotations

import asyncio
import contextlib

from cell.asyncwait import wait_event


async def _loop_until_cancelled(waiter, event: asyncio.Event) -> None:
    while True:
        await waiter(event)
        event.clear()


async def _cancellations_kept(waiter, tries: int = 20) -> int:
    kept = 0
    for _ in range(tries):
        event = asyncio.Event()
        task = asyncio.create_task(_loop_until_cancelled(waiter, event))
        for _ in range(3):
            await asyncio.sleep(0)  # the task is waiting on the event
        event.set()
        task.cancel()  # in the same iteration
        done, _ = await asyncio.wait({task}, timeout=5.0)
        kept += bool(done) and task.cancelled()
        if not done:  # the cancellation was lost: end it for good
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    return kept


def test_a_cancellation_as_the_event_is_set_ends_the_loop():
    assert asyncio.run(_cancellations_kept(lambda e: wait_event(e, 1.0))) == 20


def test_wait_for_would_have_lost_it_here():
    """The reason for wait_event: on this interpreter, wait_for loses the cancellation (when a later
    Python keeps it, this test says so and wait_event may go)."""
    import sys

    # a lost cancellation ends on wait_for's timeout: short, so the 20 tries take a second
    kept = asyncio.run(_cancellations_kept(lambda e: asyncio.wait_for(e.wait(), 0.05)))
    if sys.version_info < (3, 12):
        assert kept == 0
    else:
        assert kept == 20


def test_wait_event_says_whether_the_event_came():
    async def scenario() -> tuple[bool, bool]:
        event = asyncio.Event()
        missed = await wait_event(event, 0.01)
        asyncio.get_running_loop().call_soon(event.set)
        return missed, await wait_event(event, 30.0)

    assert asyncio.run(scenario()) == (False, True)
