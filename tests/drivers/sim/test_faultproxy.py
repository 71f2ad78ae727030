"""The fault proxies close even when one of their tasks swallows a cancellation (Python 3.11's ``wait_for`` drops one
that lands as the awaited future completes, CPython gh-86296: a gateway's line master then looped on, and awaiting it
after a single ``cancel()`` hung the link-fault test until its 15-minute timeout)."""

from __future__ import annotations

import asyncio
import contextlib

from drivers.sim.faultproxy import SerialGateway, cancel_and_wait


async def _swallows_one_cancellation(queue: asyncio.Queue) -> None:
    """What the line master did when ``wait_for`` dropped the cancellation: carry on to its next await."""
    with contextlib.suppress(asyncio.CancelledError):  # dropped, as wait_for did
        await asyncio.sleep(3600)
    await queue.get()  # waits for a request that never comes


async def test_cancel_and_wait_ends_a_task_that_swallowed_the_first_cancellation():
    task = asyncio.create_task(_swallows_one_cancellation(asyncio.Queue()))
    await asyncio.sleep(0)
    await asyncio.wait_for(cancel_and_wait([task], wait_s=0.05), 5.0)
    assert task.cancelled()


async def test_gateway_closes_with_a_line_master_that_swallowed_its_cancellation():
    line = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)  # the controller's serial line (silent)
    gw = SerialGateway(line.sockets[0].getsockname()[:2], client_framing="tcp", line_timeout_s=0.1)
    await gw.start()
    gw._tasks[1].cancel()  # the real line master ends; put one in its place that swallows a cancellation
    gw._tasks[1] = asyncio.create_task(_swallows_one_cancellation(asyncio.Queue()))
    await asyncio.sleep(0)
    await asyncio.wait_for(gw.close(), 10.0)  # before: awaited the task after one cancel(), forever
    assert all(t.done() for t in gw._tasks)
    line.close()
