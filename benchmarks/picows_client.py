"""The raw-picows baseline client: the baseline's id-multiplexed caller on ``picows``' callbacks.

As ``baseline_client.py`` (futures by integer id, orjson, the same ``_meta.timeout`` on the wire
and no deadline enforced), but replies arrive in ``on_ws_frame`` and resolve their future
there: no reader task. ``send`` is synchronous; a call awaits only its reply.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
from contextlib import AsyncExitStack
from typing import Any

import orjson
from picows import WSFrame, WSListener, WSMsgType, WSTransport, ws_connect

from common import CALL_TIMEOUT, MAX_MESSAGE, SERVICE
from workloads import Adapter, Call, main


class Caller(WSListener):  # type: ignore[misc]
    """Pending calls by id over one connection, resolved as their replies arrive."""

    def __init__(self) -> None:
        super().__init__()
        self.transport: WSTransport | None = None
        self._loop = asyncio.get_running_loop()
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._ids = itertools.count(1)

    def on_ws_connected(self, transport: WSTransport) -> None:
        self.transport = transport

    async def call(self, method: str, params: Any) -> Any:
        assert self.transport is not None
        request_id = next(self._ids)
        future = self._loop.create_future()
        self._pending[request_id] = future
        message = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
        try:
            self.transport.send(WSMsgType.TEXT, orjson.dumps(message))
            return await future
        finally:
            self._pending.pop(request_id, None)

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        if frame.msg_type != WSMsgType.TEXT:
            return
        message = orjson.loads(frame.get_payload_as_memoryview())
        if not isinstance(message, dict):
            return
        future = self._pending.pop(message.get("id", 0), None)
        if future is None or future.done():
            return
        if "error" in message:
            future.set_exception(RuntimeError(f"error reply: {message['error']}"))
        else:
            future.set_result(message["result"])

    def on_ws_disconnected(self, transport: WSTransport) -> None:
        for future in self._pending.values():
            if not future.done():
                future.set_exception(ConnectionResetError("the connection closed"))

    async def close(self) -> None:
        assert self.transport is not None
        self.transport.send_close()
        self.transport.disconnect()
        await self.transport.wait_disconnected()


async def open_connection(url: str, stack: AsyncExitStack) -> Call:
    _, caller = await ws_connect(Caller, url, max_frame_size=MAX_MESSAGE)
    stack.push_async_callback(caller.close)
    return functools.partial(caller.call, SERVICE)


def make_request(fields: dict[str, Any]) -> Any:
    return {**fields, "_meta": {"timeout": CALL_TIMEOUT}}


def values_of(reply: Any) -> int:
    return len(reply["values"])


if __name__ == "__main__":
    main(Adapter(open_connection, make_request, values_of), __doc__ or "")
