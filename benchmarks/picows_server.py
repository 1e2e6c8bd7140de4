"""The raw-picows baseline server: the baseline's JSON-RPC 2.0 responder on ``picows``' callbacks.

The same work as ``baseline_server.py`` (orjson both ways, one dict lookup per call, nothing
validated, batches and notifications ignored, no ``$/services``), on ``picows``' native API:
each frame arrives in ``on_ws_frame`` from the event loop's read callback and the reply is
written there, synchronously, with no task, no stream and no ``await``. Only whole, unfragmented
messages are read, which is all the benchmark's clients send. It is the floor of the picows
transport, as ``baseline_server.py`` is the floor of the websockets one.

With ``--cork`` (``picows-corked`` and ``picows-corked-deadline`` in ``run.py``) the replies
made while picows hands over the frames of one read are held and written together once the
read's last frame is answered: one system call for them all, as srvwire's server writes the
replies of one read. A lone reply still goes through picows' ``send``.
"""

from __future__ import annotations

import argparse
import functools
from collections.abc import Callable
from typing import Any

import orjson
from picows import WSFrame, WSListener, WSMsgType, WSTransport, WSUpgradeRequest, ws_create_server

from common import MAX_MESSAGE, SERVICE, ServerControl, emit, reply_fields, run, server_parser

Handler = Callable[[Any], Any]


def get_robot_state(params: Any) -> Any:
    query_type = params.get("query_type", "") if isinstance(params, dict) else ""
    return reply_fields(query_type)


HANDLERS: dict[str, Handler] = {SERVICE: get_robot_state, SERVICE.lstrip("/"): get_robot_state}
PARSE_ERROR = orjson.dumps(
    {"jsonrpc": "2.0", "id": None, "error": {"code": -32700, "message": "Parse error"}}
)


class Responder(WSListener):  # type: ignore[misc]
    """One connection: answer each request frame as it arrives."""

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        reply = self.answer(transport, frame)
        if reply is not None:
            transport.send(WSMsgType.TEXT, reply)

    def answer(self, transport: WSTransport, frame: WSFrame) -> bytes | None:
        """The reply to ``frame``, if it takes one; a close frame is answered and the
        connection ended here."""
        kind = frame.msg_type
        if kind == WSMsgType.CLOSE:
            transport.send_close(frame.get_close_code(), frame.get_close_message())
            transport.disconnect()
            return None
        if kind != WSMsgType.TEXT and kind != WSMsgType.BINARY:
            return None
        try:
            message = orjson.loads(frame.get_payload_as_memoryview())
        except orjson.JSONDecodeError:
            return PARSE_ERROR
        if not isinstance(message, dict) or "id" not in message:
            return None  # a batch or a notification: the baseline has no use for either
        handler = HANDLERS.get(message.get("method", ""))
        if handler is None:
            error = {"code": -32601, "message": "Method not found"}
            reply = {"jsonrpc": "2.0", "id": message["id"], "error": error}
        else:
            reply = {"jsonrpc": "2.0", "id": message["id"], "result": handler(message["params"])}
        return orjson.dumps(reply)


def header(size: int) -> bytes:
    """The header of a server's final, unmasked text frame of ``size`` bytes (RFC 6455, 5.2)."""
    if size < 126:
        return bytes((0x81, size))
    if size < 2**16:
        return bytes((0x81, 126)) + size.to_bytes(2, "big")
    return bytes((0x81, 127)) + size.to_bytes(8, "big")


class HoldingResponder(Responder):
    """One connection: the replies to one read's frames, framed and written together."""

    def __init__(self) -> None:
        super().__init__()
        self._held: list[bytes] = []  # the framed replies of this read so far

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        if self._held and frame.msg_type == WSMsgType.CLOSE:
            self.flush(transport)  # the replies before the close go first
        reply = self.answer(transport, frame)
        if reply is not None:
            self._held += (header(len(reply)), reply)
        if self._held and frame.last_in_buffer:
            self.flush(transport)

    def flush(self, transport: WSTransport) -> None:
        """Write the replies held while answering one read's frames, in one system call."""
        held = self._held
        if len(held) == 2:
            transport.send(WSMsgType.TEXT, held[1])  # picows frames a lone reply itself
        elif held:
            transport.underlying_transport.write(b"".join(held))
        held.clear()


def accept(request: WSUpgradeRequest, cork: bool = False) -> WSListener:
    """A listener for each connection; with ``cork``, one that holds the replies of a read."""
    return HoldingResponder() if cork else Responder()


async def main(
    args: argparse.Namespace, accept: Callable[[WSUpgradeRequest], WSListener] = accept
) -> None:
    """Serve ``accept``'s listeners until ``run.py`` says stop (``floor_picows_server.py``
    serves its own with this too)."""
    control = ServerControl()
    server = await ws_create_server(accept, args.host, 0, max_frame_size=MAX_MESSAGE)
    emit("listening", port=server.sockets[0].getsockname()[1])
    await control.stopped.wait()
    server.close()


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(main, args, functools.partial(accept, cork=args.cork)), args)
