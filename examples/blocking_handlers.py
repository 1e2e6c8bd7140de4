"""Blocking (plain ``def``) handlers: threads, a per-service limit, and stopping early.

It serves a slow blocking service and a fast one from a pool of four threads, calls the slow one
with a deadline it cannot meet, and shows the handler stopping early because it waits with
``context.wait`` instead of ``time.sleep``. Run it with ``python examples/blocking_handlers.py``.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import srvwire

AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")
Trigger = srvwire.load_service("std_srvs/srv/Trigger")

stopped_at: list[int] = []
stopped = threading.Event()

# --8<-- [start:server]
# The one place where the number of threads for blocking handlers is set.
server = srvwire.Server(executor=srvwire.HandlerThreads(max_workers=4))


# At most one calibration at a time: the others wait for it, within their deadline.
@server.service("/calibrate", Trigger, max_concurrency=1)
def calibrate(request: Any, response: Any, context: srvwire.Context) -> Any:
    for step in range(20):
        # Not time.sleep(0.5): this returns True at once when the caller stops waiting.
        if context.wait(0.5):
            stopped_at.append(step)
            stopped.set()
            return response
        # ... move the arm one step ...
    response.success = True
    return response


@server.service("/add_two_ints", AddTwoInts)
def add_two_ints(request: Any, response: Any) -> Any:
    response.sum = request.a + request.b
    return response


# --8<-- [end:server]


async def main() -> None:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url) as client:
            try:
                await client.call("/calibrate", {}, timeout=0.2)
            except srvwire.DeadlineExceeded:
                print("calibrate: the deadline passed")
            await asyncio.to_thread(stopped.wait, 10)
            print(f"the handler stopped early, at step {stopped_at[0]}")
            response = await client.call("/add_two_ints", {"a": 2, "b": 3})
            print("2 + 3 =", response.sum)


if __name__ == "__main__":
    asyncio.run(main())
