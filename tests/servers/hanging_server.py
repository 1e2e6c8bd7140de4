"""A real srvwire server whose ``/hang`` service never answers, for process-level fault tests.

Run as ``python hanging_server.py``. It prints the port it listens on (on 127.0.0.1) as its
first line, then ``started <n>`` each time a call reaches the handler, so a test knows exactly
when its calls are in flight before it kills this process.
"""

from __future__ import annotations

import asyncio

from srvwire.loader import load_service
from srvwire.server import Server, serve


async def main() -> None:
    server = Server()
    started = 0

    async def hang(request: object) -> None:
        nonlocal started
        started += 1
        print(f"started {started}", flush=True)
        await asyncio.Event().wait()

    server.add_service("/hang", load_service("std_srvs/srv/Trigger"), hang)
    async with serve(server, "127.0.0.1", 0) as running:
        print(running.port, flush=True)
        await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main())
