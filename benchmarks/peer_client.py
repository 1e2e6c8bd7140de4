"""The JSON-RPC peer's client: ``jsonrpc-websocket``'s ``Server``, as its documentation shows.

Each connection is a ``Server(url, timeout=...)`` whose ``ws_connect`` opens the WebSocket (on an
aiohttp ``ClientSession`` of its own, which the library closes with the connection) and starts
the library's reader task. A call is the method called with keyword arguments, which the library
sends as the named ``params``: the request's fields and the ``_meta.timeout`` every other client
sends too. The constructor's ``timeout`` is how long the library waits for each reply, the
deadline every other client enforces. The method's name, ``/get_robot_state``, is not a Python
identifier, so it is looked up with ``getattr`` rather than written as an attribute.

What the library does per call is its own: a ``uuid4`` string id, the request encoded with the
standard ``json`` module, an ``asyncio.Event`` and a timeout per pending call, and the reply's
``result`` returned as it was decoded (a plain dict, nothing validated). The only option changed
from aiohttp's defaults is ``max_msg_size``, raised as on every other client (W4's replies fit
the default too); aiohttp's client offers no compression unless asked.
"""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack
from typing import Any

from jsonrpc_websocket import Server

from common import CALL_TIMEOUT, MAX_MESSAGE, SERVICE
from workloads import Adapter, Call, main


async def close(server: Server, reader: asyncio.Task[None]) -> None:
    """Close the connection, then let the library's reader task finish."""
    await server.close()
    await reader


async def open_connection(url: str, stack: AsyncExitStack) -> Call:
    server = Server(url, timeout=CALL_TIMEOUT, max_msg_size=MAX_MESSAGE)
    reader = await server.ws_connect()
    stack.push_async_callback(close, server, reader)
    method = getattr(server, SERVICE)

    async def call(params: dict[str, Any]) -> Any:
        return await method(**params)

    return call


def make_request(fields: dict[str, Any]) -> Any:
    return {**fields, "_meta": {"timeout": CALL_TIMEOUT}}


def values_of(reply: Any) -> int:
    return len(reply["values"])


if __name__ == "__main__":
    main(Adapter(open_connection, make_request, values_of), __doc__ or "")
