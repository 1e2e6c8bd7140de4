"""The baseline client: an id-multiplexed JSON-RPC 2.0 caller written directly on ``websockets``.

One reader task per connection decodes every reply with orjson and resolves the waiting call's
future by id; messages without a pending id (such as srvwire's ``$/services`` notification) are
dropped. Requests carry the same ``_meta.timeout`` srvwire's client sends, so both put the same
bytes on the wire, but nothing enforces a deadline. Compression is off.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
from contextlib import AsyncExitStack
from typing import Any

import orjson
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from common import CALL_TIMEOUT, MAX_MESSAGE, SERVICE
from workloads import Adapter, Call, main


class BaselineConnection:
    """Pending calls by id over one WebSocket connection, resolved by one reader task."""

    def __init__(self, connection: ClientConnection) -> None:
        self._connection = connection
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._ids = itertools.count(1)
        self._reader = asyncio.create_task(self._read())

    async def call(self, method: str, params: Any) -> Any:
        request_id = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        message = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
        try:
            await self._connection.send(orjson.dumps(message), text=True)
            return await future
        finally:
            self._pending.pop(request_id, None)

    async def close(self) -> None:
        await self._connection.close()
        await self._reader

    async def _read(self) -> None:
        try:
            while True:
                message = orjson.loads(await self._connection.recv(decode=False))
                if not isinstance(message, dict):
                    continue
                future = self._pending.pop(message.get("id", 0), None)
                if future is None or future.done():
                    continue
                if "error" in message:
                    future.set_exception(RuntimeError(f"error reply: {message['error']}"))
                else:
                    future.set_result(message["result"])
        except ConnectionClosed as exc:
            for future in self._pending.values():
                if not future.done():
                    future.set_exception(exc)


async def open_connection(url: str, stack: AsyncExitStack) -> Call:
    connection = await connect(url, compression=None, max_size=MAX_MESSAGE)
    caller = BaselineConnection(connection)
    stack.push_async_callback(caller.close)
    return functools.partial(caller.call, SERVICE)


def make_request(fields: dict[str, Any]) -> Any:
    return {**fields, "_meta": {"timeout": CALL_TIMEOUT}}


def values_of(reply: Any) -> int:
    return len(reply["values"])


if __name__ == "__main__":
    main(Adapter(open_connection, make_request, values_of), __doc__ or "")
