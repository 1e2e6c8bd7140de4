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
its answer driven by a task, started at that point, while later frames are answered meanwhile.

It does nothing more than the floor (no batches, notifications, cancellation, ``$/services``),
and, as the raw picows server, reads only whole, unfragmented messages.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import types
from collections.abc import Coroutine, Generator
from typing import Any

from picows import WSFrame, WSListener, WSMsgType, WSTransport, WSUpgradeRequest, ws_create_server

from common import MAX_MESSAGE, ServerControl, emit, run, server_parser
from floor_server import reply_to

DONE = object()  # what ``next`` returns for an answer that finished in its first step


async def answer(transport: WSTransport, data: bytes) -> None:
    """Send the reply to one message, if it takes one; nothing of the call outlives this."""
    reply = await reply_to(data)
    if reply is not None:
        transport.send(WSMsgType.TEXT, reply)


@types.coroutine
def rest_of(steps: Generator[Any, Any, None], yielded: Any) -> Generator[Any, Any, None]:
    """Drive an answer that waited at its first step to its end, as ``await`` would have."""
    while True:
        try:
            sent = yield yielded
        except BaseException as exc:  # a cancellation of the task, passed on to the answer
            step: Any = steps.throw
            argument: Any = exc
        else:
            step = steps.send
            argument = sent
        try:
            yielded = step(argument)
        except StopIteration:
            return


async def finish(steps: Generator[Any, Any, None], yielded: Any) -> None:
    await rest_of(steps, yielded)


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
        coroutine: Coroutine[Any, Any, None] = answer(transport, frame.get_payload_as_bytes())
        steps = coroutine.__await__()
        # Stepped with ``next``, which ends without raising StopIteration when it finishes.
        yielded = next(steps, DONE)
        if yielded is not DONE:
            task = asyncio.ensure_future(finish(steps, yielded))
            self._waiting.add(task)
            task.add_done_callback(self._waiting.discard)


def accept(request: WSUpgradeRequest) -> WSListener:
    return TypedResponder()


async def main(args: argparse.Namespace) -> None:
    control = ServerControl()
    server = await ws_create_server(accept, args.host, 0, max_frame_size=MAX_MESSAGE)
    emit("listening", port=server.sockets[0].getsockname()[1])
    await control.stopped.wait()
    server.close()


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(main, args), args)
