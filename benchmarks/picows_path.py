"""Both ends on picows in one process: a srvwire server and srvwire clients, over real sockets.

What a small call costs srvwire on the native transport, server and client together, with the
socket reads and writes of a real connection (on 127.0.0.1) but without a second process, so
that callgrind can count it: the instructions of ``--calls`` calls minus those of half as many,
divided by the difference, are the cost of one call, which a busy neighbour does not change
(the kernel's work for the sockets is not counted). Three shapes, as the harness's workloads:

* ``sequential`` (W1): one connection, one call at a time;
* ``fan-in`` (W3): ``--connections`` connections (20), each one call at a time;
* ``pipelined`` (W2): one connection, 64 calls in flight.

Every call passes a typed ``RobotStateQuery.Request`` and checks its typed reply; the script
exits with an error otherwise. ``--transport websockets`` runs both ends on the default
transport instead, to count what a call costs there the same way. Run it with another
checkout's ``src`` first on ``PYTHONPATH`` to count an older version::

    valgrind --tool=callgrind --callgrind-out-file=/dev/null \\
        python benchmarks/picows_path.py --shape fan-in --calls 2560     # then --calls 1280
"""

from __future__ import annotations

import argparse
import asyncio
import time
from typing import Any

from srvwire.client import Client, connect
from srvwire.server import Server, serve

from common import CALL_TIMEOUT, SERVICE, SMALL_REQUEST, print_steps, python_steps, reply_fields
from typed import RobotStateQuery

SHAPES = {"sequential": (1, 1), "fan-in": (None, 1), "pipelined": (1, 64)}
"""Each shape's connections (None: ``--connections``) and calls in flight per connection."""


async def get_robot_state(request: Any) -> Any:
    return RobotStateQuery.Response(**reply_fields(request.query_type))


async def calls(client: Client, count: int) -> None:
    request = RobotStateQuery.Request(**SMALL_REQUEST)
    expected = reply_fields(SMALL_REQUEST["query_type"])["names"]
    for _ in range(count):
        reply = await client.call(SERVICE, request, timeout=CALL_TIMEOUT)
        if reply.names != expected:
            raise SystemExit(f"unexpected reply: {reply!r}")


async def run(shape: str, count: int, connections: int, transport: str = "picows") -> float:
    """Make about ``count`` calls in ``shape`` on ``transport`` (:func:`made`); return the
    process's CPU time per call, in µs."""
    conns, in_flight = SHAPES[shape]
    conns = connections if conns is None else conns
    server = Server()
    server.add_service(SERVICE, RobotStateQuery, get_robot_state)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        clients = [
            await connect(running.url, transport=transport, timeout=CALL_TIMEOUT)
            for _ in range(conns)
        ]
        each = made(shape, count, connections) // (conns * in_flight)
        started = time.process_time()
        await asyncio.gather(*(calls(client, each) for client in clients for _ in range(in_flight)))
        elapsed = time.process_time() - started
        for client in clients:
            await client.close()
    return elapsed / (each * conns * in_flight) * 1e6


def made(shape: str, count: int, connections: int) -> int:
    """How many of ``count`` calls :func:`run` makes: as many as divide evenly among the
    shape's callers."""
    conns, in_flight = SHAPES[shape]
    callers = (connections if conns is None else conns) * in_flight
    return count // callers * callers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else "")
    parser.add_argument("--shape", choices=list(SHAPES), default="sequential")
    parser.add_argument("--calls", type=int, default=2560)
    parser.add_argument("--connections", type=int, default=20, help="for fan-in")
    parser.add_argument("--transport", choices=["picows", "websockets"], default="picows")
    parser.add_argument(
        "--steps", action="store_true", help="print bytecode instructions per call, by function"
    )
    args = parser.parse_args()
    if args.steps:

        def calls(count: int) -> int:
            asyncio.run(run(args.shape, count, args.connections, args.transport))
            return made(args.shape, count, args.connections)

        print_steps(f"{args.shape}, both ends", python_steps(calls, args.calls))
        return
    per_call = asyncio.run(run(args.shape, args.calls, args.connections, args.transport))
    print(f"{args.shape}: {per_call:.1f} µs of CPU per call, both ends")


if __name__ == "__main__":
    main()
