"""The typed floor client on picows: the floor's typed JSON-RPC 2.0 caller on ``picows``' callbacks.

It is built like the raw picows client (``picows_client.py``: pending futures by integer id,
each resolved inside ``on_ws_frame`` as its reply arrives, picows' synchronous ``send`` per call,
no reader task) and does exactly the typed work of the floor's client on ``websockets``
(``floor_client.py``), with its serializer, validator and request prefix: each call takes a
generated ``RobotStateQuery.Request``, serializes it with pydantic with ``_meta.timeout``
spliced in, waits for the reply, and validates the reply's ``result`` into a typed
``Response``. Every reply is decoded with pydantic_core; one without a pending id (srvwire's
``$/services`` notification) is dropped; an error reply raises a plain ``RuntimeError``.

The wait is ``asyncio.wait_for(future, CALL_TIMEOUT)``, the deadline srvwire's design has its
client enforce, at its cheapest: on Python 3.11 the future is srvwire's ``Answer``, whose reply
releases ``wait_for``'s waiter at once, so the caller wakes at the next loop turn instead of
the one after (on 3.12+, where ``wait_for`` awaits the future itself, it is a plain future).
With ``--no-deadline`` (``floor-picows-bare`` in ``run.py``) a plain future is awaited bare,
so a run beside the default says what the deadline costs on this transport.

With ``--cork`` (``floor-picows-corked``) the calls made in one turn of the event loop are held
and written together at the turn's end (or once they pass ``CLIENT_WRITE_AT`` bytes), each
masked with a fresh key by websockets' C ``apply_mask``: one system call for them all, as
srvwire's client on picows writes the calls of a turn. As there, the first call after a read
that brought one reply is written at once (one call at a time, nothing would join it), and a
lone call goes through picows' ``send``, which frames and masks it in C.
"""

from __future__ import annotations

import argparse
import asyncio
import os
from contextlib import AsyncExitStack
from typing import Any

from picows import WSFrame, WSMsgType, WSTransport, ws_connect
from pydantic_core import from_json
from websockets.speedups import apply_mask

from srvwire.link import Answer
from srvwire.transports.picows import CLIENT_WRITE_AT

from common import CALL_TIMEOUT, MAX_MESSAGE
from floor_client import PARAMS_PREFIX, serialize_request, validate_response
from picows_client import Caller
from typed import make_request, values_of
from workloads import Adapter, Call, main


class TypedCaller(Caller):
    """Pending calls by id over one connection, resolved as their replies arrive: raw picows'
    caller (its connection, its close, its futures failed when the connection ends), typed."""

    def __init__(self, deadline: bool, cork: bool = False) -> None:
        super().__init__()
        self._deadline = deadline
        self._cork = cork
        self._held: list[bytes] = []  # with --cork: the calls of this turn, not yet written
        self._held_size = 0
        self._handed = 0  # replies the current read has brought so far
        self._single = False  # the last read brought one reply, and no call was made since

    async def call(self, request: Any) -> Any:  # type: ignore[override]
        assert self.transport is not None
        fields = serialize_request(request, by_alias=True)  # b'{"query_type":...}'
        rest = fields[1:] if fields == b"{}" else b"," + fields[1:]
        request_id = next(self._ids)
        message = b'{"jsonrpc":"2.0","id":' + str(request_id).encode() + PARAMS_PREFIX + rest + b"}"
        future: asyncio.Future[Any] = (
            Answer(loop=self._loop) if self._deadline else self._loop.create_future()
        )
        self._pending[request_id] = future
        try:
            if self._cork:
                self.hold(message)
            else:
                self.transport.send(WSMsgType.TEXT, message)
            if self._deadline:
                reply = await asyncio.wait_for(future, CALL_TIMEOUT)
            else:
                reply = await future
        finally:
            self._pending.pop(request_id, None)
        if "error" in reply:
            raise RuntimeError(f"error reply: {reply['error']}")
        return validate_response(reply["result"])

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
            message = from_json(frame.get_payload_as_bytes())
            if isinstance(message, dict):
                future = self._pending.pop(message.get("id", 0), None)
                if future is not None and not future.done():
                    future.set_result(message)
                    self._handed += 1
        if self._cork and frame.last_in_buffer:
            self._single = self._handed == 1
            self._handed = 0


def adapter(deadline: bool, cork: bool = False) -> Adapter:
    """How the workloads call through this client, with or without a deadline on each wait,
    each call written alone or the calls of a turn together."""

    async def open_connection(url: str, stack: AsyncExitStack) -> Call:
        _, caller = await ws_connect(
            lambda: TypedCaller(deadline, cork), url, max_frame_size=MAX_MESSAGE
        )
        stack.push_async_callback(caller.close)
        return caller.call

    return Adapter(open_connection, make_request, values_of)


def asked() -> argparse.Namespace:
    """The options that shape the adapter: ``no_deadline`` and ``cork``.

    Read before :func:`workloads.main` parses the whole command line, since the adapter is made
    first; ``common.add_process_options`` declares the options, so that parse accepts them too.
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--no-deadline", action="store_true")
    parser.add_argument("--cork", action="store_true")
    return parser.parse_known_args()[0]


def deadline_asked() -> bool:
    """Whether the command line leaves the deadline on (no ``--no-deadline``)."""
    return not asked().no_deadline


if __name__ == "__main__":
    main(adapter(deadline_asked(), asked().cork), __doc__ or "")
