"""W4's two large steps in one process: writing a 1.7 MB reply, and reading it, each two ways.

What a large reply costs each side without the sockets and the other process, and, above all,
how many page faults it takes: a fault count does not move with the load of a shared machine,
and on W4 the faults are what the allocator's choices cost (see docs/performance.md, "Large
replies written whole").

* ``write``: the handler's ``Response`` built from the 100 000 values, the reply written, and
  framed as websockets frames it; ``two-step`` writes the result and then the envelope around
  it (``json_writer`` + ``write_response``, as srvwire did), ``one-pass`` both at once
  (``reply_writer``, as it does now).
* ``read``: the frame's text decoded from UTF-8 and the result validated into the typed
  ``Response``; ``slice`` validates the result sliced out of the message (``RawReply.result``,
  as srvwire did), ``whole`` the whole message with its envelope (``ModelDecoder.from_reply``).
* ``carry``: the written reply carried from a server's connection to a client's over loopback
  TCP, both ends in this process (so the figures are both ends' together, the kernel's copies
  included): ``websockets`` on websockets' own connections (``send(text=True)``, ``recv``),
  ``srvwire`` on srvwire's websockets transport, the reply handed to a receiver as a client's
  link takes it (``deliver_to``).

Each step first checks that both ways make the same (bytes, or an equal ``Response`` of every
value), then runs ``--calls`` times after a warm-up; the figures are minor page faults and CPU
milliseconds per step. The ways run in separate processes, since what one leaves in the heap
decides the faults of the next; ``--keep-heap`` calls ``srvwire.keep_freed_heap()`` first in
each::

    python benchmarks/large_path.py [--calls 100] [--keep-heap]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import resource
import subprocess
import sys
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect
from websockets.asyncio.server import serve
from websockets.frames import Frame, Opcode

from srvwire.heap import keep_freed_heap
from srvwire.models import ModelDecoder, json_writer, reply_writer
from srvwire.protocol import peek_reply, write_response
from srvwire.transports.base import Options
from srvwire.transports.websockets import WebSocketsTransport

from common import LARGE_VALUES_COUNT, MAX_MESSAGE, reply_fields
from typed import RobotStateQuery

WAYS = {
    "write": ("two-step", "one-pass"),
    "read": ("slice", "whole"),
    "carry": ("websockets", "srvwire"),
}
WARMUP = 5


def step(side: str, way: str) -> Callable[[int], Any]:
    """The step of ``side`` done ``way``, for the call with this id; it returns what it made."""
    model = RobotStateQuery.Response
    fields = reply_fields("large")
    if side == "write":
        result = json_writer(model, "strings", strict=True)
        whole = reply_writer(model, "strings", strict=True)

        def write(id: int) -> bytes:
            response = model(**fields)
            if way == "two-step":
                written = write_response(id, result(response))
            else:
                written = whole(id, response)
            del response  # as the server lets go of it before the send
            return Frame(Opcode.TEXT, written).serialize(mask=False)

        return write
    payload = reply_writer(model, "strings")(1, model(**fields))
    if side == "carry":
        return Carrier(way, payload)
    decoder = ModelDecoder(model)

    def read(id: int) -> Any:
        raw = peek_reply(payload.decode())
        assert raw is not None and raw.id == 1
        if way == "slice":
            return decoder.from_json(raw.result)
        return decoder.from_reply(raw.message, raw.id)

    return read


class Carrier:
    """Carries a payload from a server's end of a connection to a client's, one way; the
    connection is opened at once, on an event loop of its own, and held until :meth:`close`."""

    def __init__(self, way: str, payload: bytes) -> None:
        self.loop = asyncio.new_event_loop()
        self.payload = payload
        self.done = asyncio.Event()  # the server's end is held open until it is set
        opening = self.open_websockets() if way == "websockets" else self.open_srvwire()
        self.carry = self.loop.run_until_complete(opening)

    def __call__(self, id: int) -> Any:
        return self.loop.run_until_complete(self.carry())

    def close(self) -> None:
        self.loop.run_until_complete(self.closing())
        self.loop.close()

    async def hold(self, connection: Any) -> None:
        self.accepted.set_result(connection)
        await self.done.wait()

    async def open_websockets(self) -> Callable[[], Coroutine[Any, Any, Any]]:
        self.accepted: asyncio.Future[Any] = self.loop.create_future()
        limits: Any = {"max_size": MAX_MESSAGE, "compression": None}
        server = await serve(self.hold, "127.0.0.1", 0, **limits)
        client = await connect(f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}", **limits)
        sender = await self.accepted

        async def closing() -> None:
            await client.close()
            self.done.set()
            server.close()
            await server.wait_closed()

        async def carry() -> Any:
            await sender.send(self.payload, text=True)
            return await client.recv()

        self.closing = closing
        return carry

    async def open_srvwire(self) -> Callable[[], Coroutine[Any, Any, Any]]:
        self.accepted = self.loop.create_future()
        options = Options(max_message_size=MAX_MESSAGE)
        transport = WebSocketsTransport()
        listener = await transport.listen(self.hold, "127.0.0.1", 0, options)
        client = await transport.connect(listener.url, options)
        sender = await self.accepted
        arrived: list[asyncio.Future[Any]] = []
        client.deliver_to(lambda message: arrived.pop().set_result(message))

        async def closing() -> None:
            await client.close()
            self.done.set()
            listener.close()
            await listener.wait_closed()

        async def carry() -> Any:
            arrival = self.loop.create_future()
            arrived.append(arrival)
            await sender.send(self.payload)
            return await arrival

        self.closing = closing
        return carry


def measure(side: str, way: str, calls: int) -> dict[str, Any]:
    """Run one step ``calls`` times in this process; return faults and CPU ms per step."""
    run = step(side, way)
    if side == "carry":  # the text of the message written, as the other way carries it
        expected = reply_writer(RobotStateQuery.Response, "strings")(
            1, RobotStateQuery.Response(**reply_fields("large"))
        ).decode()
        made = run(0)
    else:
        other = step(side, next(w for w in WAYS[side] if w != way))
        made, expected = run(0), other(0)  # the two ways agree, before anything is measured
        del other
    if made != expected or (side == "read" and len(made.values) != LARGE_VALUES_COUNT):
        raise SystemExit(f"{side} {way}: not what the other way makes")
    del made, expected
    for id in range(WARMUP):
        made = run(id)
        del made
    usage = resource.getrusage(resource.RUSAGE_SELF)
    for id in range(calls):
        made = run(id)
        del made
    after = resource.getrusage(resource.RUSAGE_SELF)
    if isinstance(run, Carrier):
        run.close()
    cpu = (after.ru_utime + after.ru_stime) - (usage.ru_utime + usage.ru_stime)
    return {
        "side": side,
        "way": way,
        "faults": (after.ru_minflt - usage.ru_minflt) / calls,
        "cpu_ms": cpu / calls * 1000,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--calls", type=int, default=100)
    parser.add_argument("--keep-heap", action="store_true")
    parser.add_argument("--one", nargs=2, metavar=("SIDE", "WAY"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one is not None:  # one way, in a process of its own
        if args.keep_heap and not keep_freed_heap():
            raise SystemExit("keep_freed_heap() could not change this C library's allocator")
        print(json.dumps(measure(*args.one, args.calls)))
        return
    extra = ["--keep-heap"] if args.keep_heap else []
    kept = " (freed heap kept)" if args.keep_heap else ""
    print(f"{LARGE_VALUES_COUNT} float64 values a reply, {args.calls} calls{kept}")
    print(f"{'step':6} {'way':9} {'faults/step':>12} {'CPU ms/step':>12}")
    for side, ways in WAYS.items():
        for way in ways:
            argv = [sys.executable, Path(__file__), "--calls", str(args.calls), "--one", side, way]
            done = subprocess.run(
                [*argv, *extra],
                capture_output=True,
                text=True,
                check=True,
            )
            row = json.loads(done.stdout)
            print(f"{side:6} {way:9} {row['faults']:12.0f} {row['cpu_ms']:12.2f}")


if __name__ == "__main__":
    main()
