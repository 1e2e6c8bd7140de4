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
"""

from __future__ import annotations

import argparse
import asyncio
from contextlib import AsyncExitStack
from typing import Any

from picows import WSFrame, WSMsgType, WSTransport, ws_connect
from pydantic_core import from_json

from srvwire.link import Answer

from common import CALL_TIMEOUT, MAX_MESSAGE
from floor_client import PARAMS_PREFIX, serialize_request, validate_response
from picows_client import Caller
from typed import make_request, values_of
from workloads import Adapter, Call, main


class TypedCaller(Caller):
    """Pending calls by id over one connection, resolved as their replies arrive: raw picows'
    caller (its connection, its close, its futures failed when the connection ends), typed."""

    def __init__(self, deadline: bool) -> None:
        super().__init__()
        self._deadline = deadline

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

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        kind = frame.msg_type
        if kind != WSMsgType.TEXT and kind != WSMsgType.BINARY:
            return
        message = from_json(frame.get_payload_as_bytes())
        if not isinstance(message, dict):
            return
        future = self._pending.pop(message.get("id", 0), None)
        if future is not None and not future.done():
            future.set_result(message)


def adapter(deadline: bool) -> Adapter:
    """How the workloads call through this client, with or without a deadline on each wait."""

    async def open_connection(url: str, stack: AsyncExitStack) -> Call:
        _, caller = await ws_connect(lambda: TypedCaller(deadline), url, max_frame_size=MAX_MESSAGE)
        stack.push_async_callback(caller.close)
        return caller.call

    return Adapter(open_connection, make_request, values_of)


def deadline_asked() -> bool:
    """Whether the command line leaves the deadline on (no ``--no-deadline``).

    Read before :func:`workloads.main` parses the whole command line, since the adapter is made
    first; ``common.add_process_options`` declares the option, so that parse accepts it too.
    """
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--no-deadline", action="store_true")
    return not parser.parse_known_args()[0].no_deadline


if __name__ == "__main__":
    main(adapter(deadline_asked()), __doc__ or "")
