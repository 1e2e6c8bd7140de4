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

With ``--cork`` (``floor-picows-corked`` in ``run.py``) the replies made while picows hands
over the frames of one read are held and written together when the read's last frame has been
answered: one system call for them all, as srvwire's server writes the replies of one read. A
lone reply still goes through picows' ``send``; a reply made later, by a task, is sent at once.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable

from picows import WSFrame, WSListener, WSMsgType, WSTransport, WSUpgradeRequest

from srvwire import inline
from srvwire.inline import Pending

from common import run, server_parser
from floor_server import reply_to
from picows_server import HoldingResponder, header, main as serve

DONE = object()  # what ``next`` returns for an answer that finished in its first step


async def answer(send: Callable[[bytes], None], data: bytes) -> None:
    """Send the reply to one message, if it takes one; nothing of the call outlives this."""
    reply = await reply_to(data)
    if reply is not None:
        send(reply)


async def finish(pending: Pending) -> None:
    """Drive an answer that waited at its first step to its end, in a task of its own."""
    await inline.finish(pending)


class TypedResponder(HoldingResponder):
    """One connection: answer each request frame as it arrives, typed as the floor's; with
    ``cork``, the replies of a read are held and written as the raw picows server holds them."""

    def __init__(self, cork: bool = False) -> None:
        super().__init__()
        self._waiting: set[asyncio.Task[None]] = set()  # answers whose handler waits
        self._cork = cork
        self._transport: WSTransport | None = None
        self._stepping = False  # whether a frame's answer is being stepped in on_ws_frame

    def on_ws_connected(self, transport: WSTransport) -> None:
        self._transport = transport

    def send(self, reply: bytes) -> None:
        """Write ``reply``, or with ``--cork`` hold it while a read's frames are answered."""
        assert self._transport is not None
        if self._stepping:
            self._held += (header(len(reply)), reply)
        else:
            self._transport.send(WSMsgType.TEXT, reply)

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        kind = frame.msg_type
        if kind == WSMsgType.CLOSE:
            self.flush(transport)  # the replies before the close go first
            transport.send_close(frame.get_close_code(), frame.get_close_message())
            transport.disconnect()
            return
        if kind != WSMsgType.TEXT and kind != WSMsgType.BINARY:
            if self._held and frame.last_in_buffer:
                self.flush(transport)
            return
        # pydantic_core decodes bytes, not a view of picows' buffer: one copy, as websockets'
        # recv(decode=False) makes for the floor.
        coroutine = answer(self.send, frame.get_payload_as_bytes())
        # Stepped with ``next``, which ends without raising StopIteration when it finishes.
        self._stepping = self._cork
        try:
            yielded = next(coroutine.__await__(), DONE)
        finally:
            self._stepping = False
        if yielded is not DONE:
            task = asyncio.ensure_future(finish(Pending(coroutine, yielded, None)))
            self._waiting.add(task)
            task.add_done_callback(self._waiting.discard)
        if self._held and frame.last_in_buffer:
            self.flush(transport)


def accept(request: WSUpgradeRequest, cork: bool = False) -> WSListener:
    """A listener for each connection; with ``cork``, one that holds the replies of a read."""
    return TypedResponder(cork)


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(serve, args, functools.partial(accept, cork=args.cork)), args)
