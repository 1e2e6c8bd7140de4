"""The JSON-RPC peer's server: the same service on ``aiohttp-json-rpc``, as its documentation shows.

A ``JsonRpc`` object holds the method, added with ``rpc.add_methods`` under the name every
other side serves (``/get_robot_state``), and its ``handle_request`` is the route of an aiohttp
``Application``. The handler is ``async``, takes the library's ``JsonRpcRequest`` and returns the
shared reply data as a plain dict, which the library encodes with the standard ``json`` module.

What the library does per message is its own: it decodes and checks the envelope, runs each
request in a task of its own, passes the params dict as it came (nothing is validated against
a schema, and ``_meta`` is simply one more key), and writes each reply with one ``send_str``.
The library builds its ``WebSocketResponse`` itself, with aiohttp's defaults (a 4 MiB message
cap, which W4's 1.7 MB replies fit; compression offered only if the client asks, and the peer's
client does not). It has no deadlines and no ``$/services`` notification.
"""

from __future__ import annotations

import argparse
import functools
from typing import Any

from aiohttp import web
from aiohttp_json_rpc import JsonRpc

from common import SERVICE, ServerControl, emit, reply_fields, run, server_parser


async def get_robot_state(request: Any) -> Any:
    params = request.params
    query_type = params.get("query_type", "") if isinstance(params, dict) else ""
    return reply_fields(query_type)


async def main(args: argparse.Namespace) -> None:
    control = ServerControl()
    rpc = JsonRpc()
    rpc.add_methods(("", get_robot_state, SERVICE))  # (prefix, method, name)
    app = web.Application()
    app.router.add_route("*", "/", rpc.handle_request)
    runner = web.AppRunner(app)
    await runner.setup()
    try:
        await web.TCPSite(runner, args.host, 0).start()
        emit("listening", port=runner.addresses[0][1])
        await control.stopped.wait()
    finally:
        await runner.cleanup()


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    run(functools.partial(main, args), args)
