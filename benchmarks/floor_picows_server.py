"""The typed floor on picows: the floor's typed JSON-RPC 2.0 responder on ``picows``' callbacks.

It is built like the raw picows server (``picows_server.py``: each frame answered inside
``on_ws_frame``, the reply written there with picows' synchronous ``send``, no task, no stream,
no reader) and does exactly the typed work of the floor on ``websockets`` (``floor_server.py``),
by calling the same :func:`floor_server.reply_to`: pydantic_core decodes the message, the
envelope is checked, ``params._meta.timeout`` becomes a deadline, the params are validated into
the generated ``RobotStateQuery.Request``, the async handler returns a typed ``Response`` and
pydantic serializes it into the reply envelope. Every error reply is the floor's, byte for byte.

The handler is a coroutine, and ``on_ws_frame`` cannot await: each message's answer is stepped
inline as far as it goes. A handler that returns without waiting (the benchmark's) is answered
in that one step, inside the callback, with nothing scheduled. One that waits has the rest of
its answer driven by a task (``srvwire.inline.finish``, as srvwire's server finishes a call
that waits), started at that point, while later frames are answered meanwhile.

It does nothing more than the floor (no batches, notifications, cancellation, ``$/services``),
and, as the raw picows server, reads only whole, unfragmented messages.
"""

from __future__ import annotations

import asyncio
import functools

from picows import WSFrame, WSListener, WSMsgType, WSTransport, WSUpgradeRequest

from srvwire import inline
from srvwire.inline import Pending

from common import run, server_parser
from floor_server import reply_to
from picows_server import main as serve

DONE = object()  # what ``next`` returns for an answer that finished in its first step


async def answer(transport: WSTransport, data: bytes) -> None:
    """Send the reply to one message, if it takes one; nothing of the call outlives this."""
    reply = await reply_to(data)
    if reply is not None:
        transport.send(WSMsgType.TEXT, reply)


async def finish(pending: Pending) -> None:
    """Drive an answer that waited at its first step to its end, in a task of its own."""
    await inline.finish(pending)


class TypedResponder(WSListener):  # type: ignore[misc]
    """One connection: answer each request frame as it arrives, typed as the floor's."""

    def __init__(self) -> None:
        super().__init__()
        self._waiting: set[asyncio.Task[None]] = set()  # answers whose handler waits

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        kind = frame.msg_type
        if kind == WSMsgType.CLOSE:
            transport.send_close(frame.get_close_code(), frame.get_close_message())
            transport.disconnect()
            return
        if kind != WSMsgType.TEXT and kind != WSMsgType.BINARY:
            return
        # pydantic_core decodes bytes, not a view of picows' buffer: one copy, as websockets'
        # recv(decode=False) makes for the floor.
        coroutine = answer(transport, frame.get_payload_as_bytes())
        # Stepped with ``next``, which ends without raising StopIteration when it finishes.
        yielded = next(coroutine.__await__(), DONE)
        if yielded is not DONE:
            task = asyncio.ensure_future(finish(Pending(coroutine, yielded, None)))
            self._waiting.add(task)
            task.add_done_callback(self._waiting.discard)


def accept(request: WSUpgradeRequest) -> WSListener:
    return TypedResponder()


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(serve, args, accept), args)
