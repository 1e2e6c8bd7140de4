"""The server's path in one process: one connection fed messages by a fake socket.

What a small call costs srvwire's server, without the sockets, the other process and the noise
of a shared machine: a :class:`srvwire.serving.ServedConnection` (the one ``serve`` makes for
each connection) reads ``--calls`` requests, as srvwire's client writes them, from a connection
that holds them in memory, and answers each through the benchmark's ``RobotStateQuery``
handler; the replies are kept, counted and checked. The figure is the process's CPU time per
call (on a shared machine it moves less than wall time does), the minimum of ``--repeat`` runs
(the least disturbed one), and each run ends with a check that every call was answered with
the expected reply.

Two ways the messages arrive:

* ``pipelined`` (W2's shape): every message is there when the reader asks, so ``recv`` never
  suspends and the replies are written back to back;
* ``one-by-one`` (W3's shape): each message arrives in a loop callback of its own, as a read of
  a socket delivers it, so each call costs the reader a wake-up too.

With ``--push`` the connection hands each message over as it arrives
(:meth:`~srvwire.transports.base.Connection.deliver_to`, as the picows transport does), so a
server that takes pushed messages answers it in that callback; pipelined, every message then
arrives in one callback, as one read of a socket holding them all would deliver them.

With ``--steps`` it prints, instead of times, the Python bytecode instructions each function
runs per call (``sys.settrace`` with opcode events; the calls of ``--calls`` less those of a
tenth as many): where the Python around the typed work is, function by function, exactly and
whatever the machine's load.

Run it with another checkout's ``src`` first on ``PYTHONPATH`` to compare two versions of
srvwire, old and new alternating::

    python benchmarks/server_path.py                       # this checkout
    PYTHONPATH=/path/to/old/src python benchmarks/server_path.py
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import statistics
import time
from collections import deque
from typing import Any

from srvwire.dispatch import ServiceRegistry
from srvwire.serving import ServedConnection
from srvwire.transports.base import Connection, TransportClosed

from common import CALL_TIMEOUT, SERVICE, SMALL_REQUEST, print_steps, python_steps, reply_fields
from typed import RobotStateQuery


async def get_robot_state(request: Any) -> Any:
    return RobotStateQuery.Response(**reply_fields(request.query_type))


PARAMS = json.dumps(SMALL_REQUEST, separators=(",", ":"))


def request_text(id: int) -> str:
    """A call as srvwire's client writes it: the time left in ``_meta``, then the fields.

    The params are written once, so that making the messages (which happens before the clock
    starts, but inside an instruction count of the whole process) costs little per call.
    """
    timeout = CALL_TIMEOUT - 0.000013
    return (
        f'{{"jsonrpc":"2.0","id":{id},"method":"{SERVICE}",'
        f'"params":{{"_meta":{{"timeout":{timeout!r}}},{PARAMS[1:]}}}'
    )


class FakeConnection(Connection):
    """A connection whose peer's messages are in memory; what is sent is kept."""

    def __init__(self, messages: list[str], one_by_one: bool, push: bool = False) -> None:
        self.remote_address = ("127.0.0.1", 1)
        self.identity = None
        self.loop = asyncio.get_running_loop()
        self.pending = deque(messages)
        self.arrived: deque[str] = deque()
        self.waiter: asyncio.Future[None] | None = None
        self.sent: list[bytes] = []
        self.one_by_one = one_by_one
        self.push = push
        self.receive: Any = None  # what deliver_to was given
        self.done = self.loop.create_future()
        if one_by_one:
            self.loop.call_soon(self.arrive)
        elif push:
            self.loop.call_soon(self.arrive, len(self.pending))
        else:
            self.arrived.extend(self.pending)
            self.pending.clear()

    def arrive(self, count: int = 1) -> None:
        """``count`` messages arrive, as a socket read would deliver them."""
        arrived = self.arrived
        pending = self.pending
        for _ in range(count):
            arrived.append(pending.popleft())
        receive = self.receive
        if receive is not None:
            while arrived:
                receive(arrived.popleft())
            if pending:
                return  # recv waits only for the end
        waiter = self.waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def deliver_to(self, receive: Any) -> bool:
        if not self.push:
            return False
        while self.arrived:
            receive(self.arrived.popleft())
        self.receive = receive
        return True

    async def recv(self) -> str | bytes:
        while not self.arrived:
            if not self.pending:
                if not self.done.done():
                    self.done.set_result(None)
                raise TransportClosed(1000, "")
            self.waiter = self.loop.create_future()
            try:
                await self.waiter
            finally:
                self.waiter = None
        return self.arrived.popleft()

    async def send(self, message: str | bytes) -> None:
        self.sent.append(message if isinstance(message, bytes) else message.encode())
        if self.one_by_one and self.pending:
            self.loop.call_soon(self.arrive)  # the next call comes once this one is answered

    @property
    def congested(self) -> bool:
        return False

    async def writable(self) -> None:
        return None

    async def close(self, code: int = 1000, reason: str = "") -> None:
        return None

    @property
    def close_code(self) -> int | None:
        return 1000 if self.done.done() else None

    @property
    def close_reason(self) -> str:
        return ""


async def one_run(calls: int, one_by_one: bool, push: bool = False) -> float:
    """Serve ``calls`` calls on one connection; return the CPU time per call, in seconds."""
    registry = ServiceRegistry()
    registry.add(SERVICE, RobotStateQuery, get_robot_state)
    messages = [request_text(id) for id in range(1, calls + 1)]
    conn = FakeConnection(messages, one_by_one, push)
    served = ServedConnection(
        conn, registry, max_in_flight=256, executor=None, logger=logging.getLogger("bench")
    )
    started = time.process_time()
    await served.serve()
    elapsed = time.process_time() - started
    expected = registry.get(SERVICE)
    assert expected is not None
    if len(conn.sent) != calls:
        raise SystemExit(f"{len(conn.sent)} replies to {calls} calls")
    for id, reply in ((1, conn.sent[0]), (calls, conn.sent[-1])):
        decoded = json.loads(reply)
        if decoded.get("id") != id or decoded["result"]["names"] != reply_fields("")["names"]:
            raise SystemExit(f"unexpected reply to call {id}: {reply!r}")
    return elapsed / calls


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else "")
    parser.add_argument("--calls", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--mode", choices=["pipelined", "one-by-one", "both"], default="both")
    parser.add_argument("--loop", choices=["asyncio", "uvloop"], default="asyncio")
    parser.add_argument("--json", action="store_true", help="print one JSON line per mode")
    parser.add_argument(
        "--push", action="store_true", help="hand each message over as it arrives (deliver_to)"
    )
    parser.add_argument(
        "--steps", action="store_true", help="print bytecode instructions per call, by function"
    )
    args = parser.parse_args()
    modes = ["pipelined", "one-by-one"] if args.mode == "both" else [args.mode]
    for mode in modes:
        if args.steps:

            def calls(count: int, one_by_one: bool = mode == "one-by-one") -> int:
                asyncio.run(one_run(count, one_by_one, args.push))
                return count

            counted = python_steps(calls, args.calls)
            if args.json:
                print(json.dumps({"mode": mode, "steps": counted}))
            else:
                print_steps(mode, counted)
            continue
        runs = []
        for _ in range(args.repeat):
            coroutine = one_run(args.calls, mode == "one-by-one", args.push)
            if args.loop == "uvloop":
                import uvloop

                runs.append(uvloop.run(coroutine))
            else:
                runs.append(asyncio.run(coroutine))
        best, median = min(runs) * 1e6, statistics.median(runs) * 1e6
        if args.json:
            print(json.dumps({"mode": mode, "min_us": best, "median_us": median}))
        else:
            print(f"{mode:>10}: {best:.2f} µs per call (min of {args.repeat}; median {median:.2f})")


if __name__ == "__main__":
    main()
