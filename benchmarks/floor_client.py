"""The floor client: the least a typed JSON-RPC 2.0 caller on ``websockets`` must do per call.

It is built like the baseline (one reader task per connection, pending futures by integer id,
compression off) but typed, as srvwire is: each call takes a generated ``RobotStateQuery.Request``,
serializes it with pydantic with ``_meta.timeout`` spliced in, waits for the reply for at most
that long, and validates the reply's ``result`` into a typed ``Response``. The reader decodes
every message with pydantic_core and drops those without a pending id (such as srvwire's
``$/services`` notification).

It does nothing more: no batches, notifications, cancellation, task per waiting call,
reconnection, typed errors or logging. An error reply raises a plain ``RuntimeError``.
"""

from __future__ import annotations

import asyncio
import itertools
from contextlib import AsyncExitStack
from typing import Any

from pydantic_core import from_json, to_json
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed

from common import CALL_TIMEOUT, MAX_MESSAGE, SERVICE
from typed import RobotStateQuery, make_request, values_of
from workloads import Adapter, Call, main

serialize_request = RobotStateQuery.Request.__pydantic_serializer__.to_json
validate_response = RobotStateQuery.Response.__pydantic_validator__.validate_python

# What comes between a request's id and its own fields, with the deadline every call carries.
PARAMS_PREFIX = (
    b',"method":'
    + to_json(SERVICE)
    + b',"params":{"_meta":{"timeout":'
    + repr(float(CALL_TIMEOUT)).encode()
    + b"}"
)


class FloorConnection:
    """Pending calls by id over one WebSocket connection, resolved by one reader task."""

    def __init__(self, connection: ClientConnection) -> None:
        self._connection = connection
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._ids = itertools.count(1)
        self._reader = asyncio.create_task(self._read())

    async def call(self, request: Any) -> Any:
        fields = serialize_request(request, by_alias=True)  # b'{"query_type":...}'
        rest = fields[1:] if fields == b"{}" else b"," + fields[1:]
        request_id = next(self._ids)
        message = b'{"jsonrpc":"2.0","id":' + str(request_id).encode() + PARAMS_PREFIX + rest + b"}"
        future = asyncio.get_running_loop().create_future()
        self._pending[request_id] = future
        try:
            await self._connection.send(message, text=True)
            reply = await asyncio.wait_for(future, CALL_TIMEOUT)
        finally:
            self._pending.pop(request_id, None)
        if "error" in reply:
            raise RuntimeError(f"error reply: {reply['error']}")
        return validate_response(reply["result"])

    async def close(self) -> None:
        await self._connection.close()
        await self._reader

    async def _read(self) -> None:
        try:
            while True:
                message = from_json(await self._connection.recv(decode=False))
                if not isinstance(message, dict):
                    continue
                future = self._pending.pop(message.get("id", 0), None)
                if future is not None and not future.done():
                    future.set_result(message)
        except ConnectionClosed as exc:
            for future in self._pending.values():
                if not future.done():
                    future.set_exception(exc)


async def open_connection(url: str, stack: AsyncExitStack) -> Call:
    connection = await connect(url, compression=None, max_size=MAX_MESSAGE)
    caller = FloorConnection(connection)
    stack.push_async_callback(caller.close)
    return caller.call


if __name__ == "__main__":
    main(Adapter(open_connection, make_request, values_of), __doc__ or "")
