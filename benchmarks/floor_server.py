"""The floor server: the least a typed JSON-RPC 2.0 server on ``websockets`` must do per call.

It is built like the baseline (``websockets``' asyncio server with compression off, one read
loop per connection, each call answered inline with no task per call) but typed, as srvwire is:
pydantic_core decodes the message, the envelope is checked, ``params._meta.timeout`` becomes a
deadline, the params are validated into the generated ``RobotStateQuery.Request``, an async
handler returns a typed ``Response``, and pydantic serializes it, spliced into the reply
envelope. Each of these gets its error reply: a message that is not JSON, an invalid request,
an unknown method, invalid params (a bad ``_meta`` included), a deadline that has passed when
the handler is about to run, and a handler that raises or returns what ``Response`` cannot
serialize.

It does nothing more: no batches, notifications, cancellation, typed errors or logging, and no
``$/services`` notification. The deadline is checked once, after validation; nothing stops a
handler that is still running when it passes.

Each message is answered by :func:`answer`, a coroutine the read loop calls, so nothing of a
call (the decoded message, the request, the response, the reply's bytes) is still referenced
once its reply is sent. A read loop whose locals kept the last reply alive until the next
message arrived would change how glibc trims its heap after each of W4's large replies (about 50
page faults per reply instead of about 1 600) and make W4 look some 30 % cheaper than it is on
any server that releases a call's objects when the call ends.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from pydantic_core import ValidationError, from_json, to_json
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from common import SERVICE, reply_fields, run, serve_websockets, server_parser
from typed import RobotStateQuery

PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603
DEADLINE_EXCEEDED = -32001  # the code srvwire uses


@dataclass(frozen=True, slots=True)
class Service:
    """What answering one method takes: its request validator, handler and response serializer."""

    validate: Callable[[Any], Any]
    handler: Callable[[Any], Awaitable[Any]]
    serialize: Callable[..., bytes]


async def get_robot_state(request: Any) -> Any:
    return RobotStateQuery.Response(**reply_fields(request.query_type))


ROBOT_STATE = Service(
    RobotStateQuery.Request.__pydantic_validator__.validate_python,
    get_robot_state,
    RobotStateQuery.Response.__pydantic_serializer__.to_json,
)
SERVICES = {SERVICE: ROBOT_STATE, SERVICE.lstrip("/"): ROBOT_STATE}


def error_reply(id_json: bytes, code: int, message: str) -> bytes:
    """Return an error reply to the request whose id, written as JSON, is ``id_json``."""
    error = to_json({"code": code, "message": message})
    return b"".join((b'{"jsonrpc":"2.0","id":', id_json, b',"error":', error, b"}"))


async def reply_to(data: str | bytes) -> bytes | None:
    """Return the reply to one message, or None for a batch or a notification."""
    try:
        message = from_json(data)
    except ValueError:
        return error_reply(b"null", PARSE_ERROR, "Parse error")
    if type(message) is not dict or "id" not in message:
        return None  # a batch or a notification: out of scope here, as in the baseline
    request_id = message["id"]
    if type(request_id) is int:
        id_json = str(request_id).encode()
    elif type(request_id) is str or request_id is None:
        id_json = to_json(request_id)  # quoted and escaped
    else:
        return error_reply(b"null", INVALID_REQUEST, "Invalid Request")
    method = message.get("method")
    if message.get("jsonrpc") != "2.0" or type(method) is not str:
        return error_reply(id_json, INVALID_REQUEST, "Invalid Request")
    service = SERVICES.get(method)
    if service is None:
        return error_reply(id_json, METHOD_NOT_FOUND, "Method not found")
    params = message.get("params")
    if params is None:
        params = {}
    elif type(params) is not dict:
        return error_reply(id_json, INVALID_PARAMS, "Invalid params")
    meta = params.pop("_meta", {})
    if type(meta) is not dict:
        return error_reply(id_json, INVALID_PARAMS, "Invalid params")
    timeout = meta.get("timeout")
    if timeout is None:
        deadline = None
    elif type(timeout) in (int, float) and 0 <= timeout < math.inf:
        deadline = time.monotonic() + timeout
    else:
        return error_reply(id_json, INVALID_PARAMS, "Invalid params")
    try:
        request = service.validate(params)
    except ValidationError:
        return error_reply(id_json, INVALID_PARAMS, "Invalid params")
    if deadline is not None and time.monotonic() > deadline:
        return error_reply(id_json, DEADLINE_EXCEEDED, "Deadline exceeded")
    # The response is dropped as soon as it is serialized and the reply is joined in one copy,
    # as srvwire's server does: on W4, each extra 1.7 MB buffer alive at once would add about
    # 400 page faults per reply.
    try:
        result = service.serialize(await service.handler(request), by_alias=True, warnings="error")
    except Exception:
        return error_reply(id_json, INTERNAL_ERROR, "Internal error")
    return b"".join((b'{"jsonrpc":"2.0","id":', id_json, b',"result":', result, b"}"))


async def answer(connection: ServerConnection, data: str | bytes) -> None:
    """Send the reply to one message, if it takes one; nothing of the call outlives this."""
    reply = await reply_to(data)
    if reply is not None:
        await connection.send(reply, text=True)


async def respond(connection: ServerConnection) -> None:
    try:
        while True:
            await answer(connection, await connection.recv(decode=False))
    except ConnectionClosed:
        return


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(serve_websockets, respond, args.host), args)
