"""The baseline server: a minimal JSON-RPC 2.0 responder written directly on ``websockets``.

It is what the stack costs with no framework: ``websockets``' asyncio server with compression
off, orjson to decode and encode, a dict from method name to handler, and one reply per request
sent straight back from the connection's read loop. It validates nothing, runs each call inline
(no task per call), and ignores batches and notifications. It does not send ``$/services``.
"""

from __future__ import annotations

import functools
from collections.abc import Awaitable, Callable
from typing import Any

import orjson
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from common import SERVICE, reply_fields, run, serve_websockets, server_parser

Handler = Callable[[Any], Awaitable[Any]]


async def get_robot_state(params: Any) -> Any:
    query_type = params.get("query_type", "") if isinstance(params, dict) else ""
    return reply_fields(query_type)


HANDLERS: dict[str, Handler] = {SERVICE: get_robot_state, SERVICE.lstrip("/"): get_robot_state}


async def respond(connection: ServerConnection) -> None:
    try:
        while True:
            data = await connection.recv(decode=False)
            try:
                message = orjson.loads(data)
            except orjson.JSONDecodeError:
                error = {"code": -32700, "message": "Parse error"}
                await connection.send(
                    orjson.dumps({"jsonrpc": "2.0", "id": None, "error": error}), text=True
                )
                continue
            if not isinstance(message, dict) or "id" not in message:
                continue  # a batch or a notification: the baseline has no use for either
            request_id = message["id"]
            handler = HANDLERS.get(message.get("method", ""))
            if handler is None:
                error = {"code": -32601, "message": "Method not found"}
                reply = {"jsonrpc": "2.0", "id": request_id, "error": error}
            else:
                result = await handler(message.get("params"))
                reply = {"jsonrpc": "2.0", "id": request_id, "result": result}
            await connection.send(orjson.dumps(reply), text=True)
    except ConnectionClosed:
        return


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(serve_websockets, respond, args.host), args)
