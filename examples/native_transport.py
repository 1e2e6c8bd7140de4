"""The quickstart on the native transport: picows on both ends, uvloop when it is installed."""

import asyncio
from typing import Any

import srvwire

AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")
server = srvwire.Server()


@server.service("/add_two_ints", AddTwoInts)
async def add_two_ints(request: Any, response: Any) -> Any:
    response.sum = request.a + request.b
    return response


async def main() -> None:
    # The same server and client as with websockets: only the transport's name changes.
    async with srvwire.serve(server, "127.0.0.1", 0, transport="picows") as running:
        async with srvwire.connect(running.url, transport="picows") as client:
            response = await client.call("/add_two_ints", {"a": 2, "b": 3}, timeout=1.0)
            print("2 + 3 =", response.sum, "over", running.transport.name)


try:
    import uvloop  # srvwire[fast] installs it: a faster event loop, for either transport
except ImportError:
    asyncio.run(main())
else:
    uvloop.run(main())
