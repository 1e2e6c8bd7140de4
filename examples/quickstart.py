"""srvwire in one file: serve AddTwoInts, call it with a deadline, print the sum."""

import asyncio
from typing import Any

import srvwire

AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")  # from its .srv file
server = srvwire.Server()


@server.service("/add_two_ints", AddTwoInts)
async def add_two_ints(request: Any, response: Any) -> Any:
    response.sum = request.a + request.b  # the ROS 2 shape: fill in the response, return it
    return response


async def main() -> None:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:  # port 0: any free port
        async with srvwire.connect(running.url) as client:
            response = await client.call("/add_two_ints", {"a": 2, "b": 3}, timeout=1.0)
            print("2 + 3 =", response.sum)


asyncio.run(main())
