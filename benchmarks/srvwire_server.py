"""The srvwire side's server: one ``RobotStateQuery`` service on ``srvwire.server``, as a user
writes it.

The handler is ``async`` and returns a typed ``Response`` built from the shared reply data, so
every call pays for what a real srvwire service pays for: request validation, the handler's
task, response validation and encoding. The only options changed from the defaults are
``max_message_size``, so W4's large replies fit on the way back from the server too, and
``max_connections``, so MEM's 1 000 idle connections are all admitted.
``--transport picows`` serves on the native transport instead of ``websockets``;
``--keep-heap`` calls ``srvwire.keep_freed_heap()`` first.
"""

from __future__ import annotations

import argparse
import functools
from typing import Any

from srvwire.server import Server, serve

from common import MAX_MESSAGE, SERVICE, ServerControl, emit, reply_fields, run, server_parser
from typed import RobotStateQuery


async def get_robot_state(request: Any) -> Any:
    return RobotStateQuery.Response(**reply_fields(request.query_type))


async def main(args: argparse.Namespace) -> None:
    control = ServerControl()
    # MEM holds 1 000 connections, past the default cap of 512: raised, as a user would.
    server = Server(max_message_size=MAX_MESSAGE, max_connections=2000)
    server.add_service(SERVICE, RobotStateQuery, get_robot_state)
    async with serve(server, args.host, 0, transport=args.transport) as running:
        emit("listening", port=running.port)
        await control.stopped.wait()


if __name__ == "__main__":
    args = server_parser(__doc__ or "").parse_args()
    if args.keep_heap:  # imported only then: the harness also runs older srvwire with this script
        from srvwire.heap import keep_freed_heap

        keep_freed_heap()
    run(functools.partial(main, args), args)
