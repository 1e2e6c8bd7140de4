"""The raw-picows baseline client: the baseline's id-multiplexed caller on ``picows``' callbacks.

As ``baseline_client.py`` (futures by integer id, orjson, the same ``_meta.timeout`` on the wire
and no deadline enforced), but replies arrive in ``on_ws_frame`` and resolve their future
there: no reader task. ``send`` is synchronous; a call awaits only its reply.

With ``--cork`` (``picows-corked`` in ``run.py``) the calls made in one turn of the event loop
are held and written together at the turn's end (or once they pass ``CLIENT_WRITE_AT`` bytes),
each masked with a key of its own by websockets' C ``apply_mask``, as srvwire's client on picows
writes the calls of a turn; the first call after a read that brought one reply is written at
once. With ``--deadline`` as well (``picows-corked-deadline``) each wait is
``asyncio.wait_for(future, CALL_TIMEOUT)`` on srvwire's ``Answer``, the deadline srvwire's
design has its client enforce, at its cheapest. Nothing is typed either way: the pair says
what the least a design that batches and keeps that deadline can reach on this transport.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import itertools
import os
from contextlib import AsyncExitStack
from typing import Any

import orjson
from picows import WSFrame, WSListener, WSMsgType, WSTransport, ws_connect
from websockets.speedups import apply_mask

from srvwire.link import Answer
from srvwire.transports.picows import CLIENT_WRITE_AT

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


class HoldingCaller(Caller):
    """Raw picows' caller, with the calls of a turn written together (``cork``) and each wait
    under ``asyncio.wait_for`` (``deadline``); the typed floor's caller builds on it too."""

    decode = staticmethod(orjson.loads)
    """How a reply's payload is decoded (bytes to a dict)."""

    def __init__(self, deadline: bool, cork: bool = False) -> None:
        super().__init__()
        self._deadline = deadline
        self._cork = cork
        self._held: list[bytes] = []  # with cork: the calls of this turn, not yet written
        self._held_size = 0
        self._handed = 0  # replies the current read has brought so far
        self._single = False  # the last read brought one reply, and no call was made since

    async def call(self, method: str, params: Any) -> Any:
        # As Caller.call, written out whole: the typed floor's call is too, so that neither
        # pays a coroutine level the other does not.
        request_id = next(self._ids)
        message = {"jsonrpc": "2.0", "id": request_id, "method": method, "params": params}
        future: asyncio.Future[Any] = (
            Answer(loop=self._loop) if self._deadline else self._loop.create_future()
        )
        self._pending[request_id] = future
        try:
            self.write(orjson.dumps(message))
            if self._deadline:
                reply = await asyncio.wait_for(future, CALL_TIMEOUT)
            else:
                reply = await future
        finally:
            self._pending.pop(request_id, None)
        if "error" in reply:
            raise RuntimeError(f"error reply: {reply['error']}")
        return reply["result"]

    def write(self, message: bytes) -> None:
        """Write a call at once, or with ``cork`` hold it for the turn's end."""
        assert self.transport is not None
        if self._cork:
            self.hold(message)
        else:
            self.transport.send(WSMsgType.TEXT, message)

    def hold(self, message: bytes) -> None:
        """Hold ``message`` until the turn ends, or write what is held once it is large."""
        if self._single:  # one call at a time: nothing would join it
            self._single = False
            assert self.transport is not None
            self.flush()
            self.transport.send(WSMsgType.TEXT, message)
            return
        if not self._held:
            self._loop.call_soon(self.flush)
        self._held.append(message)
        self._held_size += len(message)
        if self._held_size >= CLIENT_WRITE_AT:
            self.flush()

    def flush(self) -> None:
        """Write the held calls in one system call, each a final text frame masked with a key
        of its own (RFC 6455, 5.3)."""
        held = self._held
        transport = self.transport
        if not held or transport is None or transport.is_close_frame_sent:
            held.clear()
        elif len(held) == 1:
            transport.send(WSMsgType.TEXT, held.pop())
        else:
            keys = os.urandom(4 * len(held))
            parts: list[bytes] = []
            for index, data in enumerate(held):
                size = len(data)
                key = keys[4 * index : 4 * index + 4]
                if size < 126:
                    parts.append(bytes((0x81, 0x80 | size)))
                else:
                    parts.append(bytes((0x81, 0x80 | 126)) + size.to_bytes(2, "big"))
                parts += (key, apply_mask(data, key))
            held.clear()
            transport.underlying_transport.write(b"".join(parts))
        self._held_size = 0

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        kind = frame.msg_type
        if kind == WSMsgType.TEXT or kind == WSMsgType.BINARY:
            message = self.decode(frame.get_payload_as_bytes())
            if isinstance(message, dict):
                future = self._pending.pop(message.get("id", 0), None)
                if future is not None and not future.done():
                    future.set_result(message)
                    self._handed += 1
        if self._cork and frame.last_in_buffer:
            self._single = self._handed == 1
            self._handed = 0


async def open_connection(url: str, stack: AsyncExitStack) -> Call:
    _, caller = await ws_connect(Caller, url, max_frame_size=MAX_MESSAGE)
    stack.push_async_callback(caller.close)
    return functools.partial(caller.call, SERVICE)


def holding_adapter(deadline: bool, cork: bool) -> Adapter:
    """How the workloads call through :class:`HoldingCaller`."""

    async def open_holding(url: str, stack: AsyncExitStack) -> Call:
        _, caller = await ws_connect(
            lambda: HoldingCaller(deadline, cork), url, max_frame_size=MAX_MESSAGE
        )
        stack.push_async_callback(caller.close)
        return functools.partial(caller.call, SERVICE)

    return Adapter(open_holding, make_request, values_of)


def make_request(fields: dict[str, Any]) -> Any:
    return {**fields, "_meta": {"timeout": CALL_TIMEOUT}}


def values_of(reply: Any) -> int:
    return len(reply["values"])


def asked() -> argparse.Namespace:
    """The options that shape a picows client's adapter: ``cork``, and ``deadline`` (raw picows
    waits bare unless told) or ``no_deadline`` (the typed floor keeps its deadline unless told).

    Read before :func:`workloads.main` parses the whole command line, since the adapter is made
    first; ``common.add_process_options`` declares the options, so that parse accepts them too.
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--cork", action="store_true")
    parser.add_argument("--deadline", action="store_true")
    parser.add_argument("--no-deadline", action="store_true")
    return parser.parse_known_args()[0]


if __name__ == "__main__":
    options = asked()
    if options.cork or options.deadline:
        main(holding_adapter(options.deadline, options.cork), __doc__ or "")
    else:
        main(Adapter(open_connection, make_request, values_of), __doc__ or "")
