"""The raw-picows baseline server: the baseline's JSON-RPC 2.0 responder on ``picows``' callbacks.

The same work as ``baseline_server.py`` (orjson both ways, one dict lookup per call, nothing
validated, batches and notifications ignored, no ``$/services``), on ``picows``' native API:
each frame arrives in ``on_ws_frame`` from the event loop's read callback and the reply is
written there, synchronously, with no task, no stream and no ``await``. Only whole, unfragmented
messages are read, which is all the benchmark's clients send. It is the floor of the picows
transport, as ``baseline_server.py`` is the floor of the websockets one.
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
        kind = frame.msg_type
        if kind == WSMsgType.CLOSE:
            transport.send_close(frame.get_close_code(), frame.get_close_message())
            transport.disconnect()
            return
        if kind != WSMsgType.TEXT and kind != WSMsgType.BINARY:
            return
        try:
            message = orjson.loads(frame.get_payload_as_memoryview())
        except orjson.JSONDecodeError:
            transport.send(WSMsgType.TEXT, PARSE_ERROR)
            return
        if not isinstance(message, dict) or "id" not in message:
            return  # a batch or a notification: the baseline has no use for either
        handler = HANDLERS.get(message.get("method", ""))
        if handler is None:
            error = {"code": -32601, "message": "Method not found"}
            reply = {"jsonrpc": "2.0", "id": message["id"], "error": error}
        else:
            reply = {"jsonrpc": "2.0", "id": message["id"], "result": handler(message["params"])}
        transport.send(WSMsgType.TEXT, orjson.dumps(reply))


def accept(request: WSUpgradeRequest) -> WSListener:
    return Responder()


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
    run(functools.partial(main, args), args)
