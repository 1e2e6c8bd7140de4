"""srvwire's log as the logging page recommends it: start and stop lines, and an access log.

It configures logging, serves one service with the access log on, makes a call and a call to a
service that does not exist, and prints the answers; the log lines go to standard error. Run it
with ``python examples/logging_setup.py``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import srvwire

AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")


def configure_logging() -> None:
    # --8<-- [start:config]
    # Every library's warnings and errors (the root logger stays at WARNING)...
    logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # ...and srvwire's INFO lines: where it listens, shutdown, and the access log.
    logging.getLogger("srvwire").setLevel(logging.INFO)
    # --8<-- [end:config]


# --8<-- [start:server]
server = srvwire.Server(access_log=True)  # a line per call on the srvwire.access logger


@server.service("/add_two_ints", AddTwoInts)
async def add_two_ints(request: Any, response: Any) -> Any:
    response.sum = request.a + request.b
    return response


# --8<-- [end:server]


async def main() -> None:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url) as client:
            response = await client.call("/add_two_ints", {"a": 2, "b": 3})
            print("2 + 3 =", response.sum)
            try:
                await client.call("/add_to_ints", {"a": 2, "b": 3})
            except srvwire.ServiceNotFound as error:
                print("not found:", error.message)


if __name__ == "__main__":
    configure_logging()
    asyncio.run(main())
