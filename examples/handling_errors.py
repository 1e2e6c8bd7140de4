"""Every way a call can fail, each caught as its own exception class.

It serves three services on a free port, makes calls that succeed and calls that fail — a
request that does not validate, a misspelt service name, a handler slower than the deadline, an
application error, a server that went away — and prints what each one raised. Then it shows a
client that reconnects by itself. Run it with ``python examples/handling_errors.py``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import srvwire

AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")
SetBool = srvwire.load_service("std_srvs/srv/SetBool")

server = srvwire.Server()


@server.service("/add_two_ints", AddTwoInts)
async def add_two_ints(request: Any, response: Any) -> Any:
    response.sum = request.a + request.b
    return response


@server.service("/slow_add", AddTwoInts)
async def slow_add(request: Any, response: Any) -> Any:
    await asyncio.Event().wait()  # never set: only the caller's deadline ends this call
    return response


# --8<-- [start:raise]
BATTERY_LOW = 4001  # an application error code, documented for the callers of this service


@server.service("/robot1/enable_motors", SetBool)
async def enable_motors(request: Any, response: Any) -> Any:
    battery = 0.07
    if request.data and battery < 0.2:
        raise srvwire.ServiceError(
            BATTERY_LOW, "battery too low to enable the motors", {"battery": battery}
        )
    response.success = True
    return response


# --8<-- [end:raise]


# --8<-- [start:catch]
async def add(client: srvwire.Client, service: str, **fields: Any) -> None:
    try:
        response = await client.call(service, fields, timeout=0.5)
    except srvwire.InvalidParams as error:
        for problem in error.errors:
            print(f"invalid request: {problem['path']}: {problem['message']}")
    except srvwire.ServiceNotFound as error:
        print("no such service; did you mean", error.data["candidates"])
    except srvwire.DeadlineExceeded:
        print("too slow; the call was cancelled on the server")
    except srvwire.ServiceUnavailable as error:  # includes ConnectionLost
        print("server unavailable:", error.message)
    else:
        print("sum:", response.sum)


# --8<-- [end:catch]


# --8<-- [start:application]
async def enable(client: srvwire.Client) -> None:
    try:
        await client.call("/robot1/enable_motors", {"data": True})
    except srvwire.ServiceError as error:
        if error.code != BATTERY_LOW:
            raise
        print("battery at", error.data["battery"])


# --8<-- [end:application]


# --8<-- [start:reconnect]
async def call_when_ready(url: str) -> srvwire.RunningServer:
    # Nothing listens at url yet. With reconnect=True, opening does not fail: the client keeps
    # dialling in the background, and wait_for_ready=True makes the call wait for the server.
    async with srvwire.connect(url, reconnect=True) as client:
        call = asyncio.create_task(
            client.call("/add_two_ints", {"a": 20, "b": 22}, wait_for_ready=True, timeout=10)
        )
        running = await srvwire.serve(server, "127.0.0.1", port_of(url))  # the server is back
        response = await call
        print("sum after reconnecting:", response.sum)
    return running


# --8<-- [end:reconnect]


def port_of(url: str) -> int:
    return int(url.rsplit(":", 1)[1])


async def main() -> None:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        url = running.url
        async with srvwire.connect(url) as client:
            await add(client, "/add_two_ints", a=1, b=2)
            await add(client, "/add_two_ints", a=1, b="two")
            await add(client, "/add_to_ints", a=1, b=2)
            await add(client, "/slow_add", a=1, b=2)
            await enable(client)
            await running.close()  # the server goes away while the client is connected
            await add(client, "/add_two_ints", a=1, b=2)
    running = await call_when_ready(url)
    await running.close()


if __name__ == "__main__":
    logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")
    asyncio.run(main())
