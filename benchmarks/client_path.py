"""The client's CPU per call, in-process: ``client.call`` against a connection that answers at once.

No server, no socket, no transport: a fake :class:`~srvwire.transports.base.Connection`
announces the benchmark's service (with its fingerprint, as a srvwire server does), and answers
each request it is sent with the small ``RobotStateQuery`` reply a srvwire server writes. The
replies to the requests of one turn of the loop arrive together at the next turn, in one
callback, as one socket read would bring them: queued for the client's reader task, or with
``--push`` handed to the client one by one from that callback (``Connection.deliver_to``, as
both network transports do, where the client asks for it). With ``--proxy`` the calls go
through a :class:`~srvwire.client.ServiceProxy` made once. What is measured is everything the
client does per call above the transport: ``Client.call``, the link, the session, writing the
request, the deadline, routing and decoding the reply, asyncio's futures and timers.

With ``--server websockets`` (or ``picows``) the client talks to a real srvwire server instead,
the harness's ``srvwire_server.py`` started in a process of its own (this checkout's srvwire,
not measured), over that transport on 127.0.0.1: what is measured is then the client's whole
path, its transport's reading and writing included, as ``client.call`` pays it on a socket.

Shapes, each timed over ``--calls`` calls (CPU time of the process, ``time.process_time``):

* **pipelined**: 64 tasks call in a loop, so 64 calls are in flight, as in the harness's W2;
* **sequential**: one task calls in a loop, one call at a time, as in W1;
* **fan-in** (asked for with ``--shapes``): 100 connections, each with its own fake
  connection, reader and caller calling one call at a time, as in W3 (here every connection's
  reply arrives in the same loop turn, as if the server answered them all at once).

Several source trees can be compared in the same run (``--src old/src --src src``): each is
measured in a child process of its own, first on ``sys.path``, and the trees alternate within
every repeat; the figure is the minimum over ``--repeat`` runs (the least disturbed by other
processes), and the table gives each tree's ratio to the first one. ``--raw`` (with ``--server
websockets``) measures the harness's raw websockets client (``baseline_client.py``) in the same
shapes, against the same server, as one more row.

``--keep-heap`` calls ``srvwire.keep_freed_heap()`` in each child first (the raw client too),
so that no block of a socket read's size is mapped from the kernel and given back per read: what
a process that once freed a larger block gets from glibc's own adjustment of its thresholds (the
harness's clients do, building W4's request), where a small client that never did maps and
unmaps asyncio's 256 KiB read buffer on every read.

    python benchmarks/client_path.py                       # this checkout's src/
    python benchmarks/client_path.py --src OLD/src --src src --repeat 7
    python benchmarks/client_path.py --src OLD/src --src src --server websockets --instructions
    python benchmarks/client_path.py --server websockets --shapes fan-in --raw --instructions
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import re
import subprocess
import sys
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterator, Sequence
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RAW = "raw websockets"  # the row of --raw: the harness's baseline client, not a source tree
PIPELINE = 64  # calls in flight in the pipelined shape, as W2
FAN_IN = 100  # connections in the fan-in shape, as W3
TIMEOUT = 30.0  # every call's deadline, as the harness's
WARMUP = 200  # calls on each connection before the measured ones: the type, the fingerprint, caches


def measure(calls: int, shapes: list[str], push: bool, url: str | None = None,
            transport: str = "websockets", proxy: bool = False,
            raw: bool = False, loop: str = "asyncio",
            warmup: int = WARMUP) -> dict[str, float]:  # fmt: skip
    """Measure this process's srvwire (the one first on ``sys.path``); µs of CPU per call
    (``url``: of a real server, on ``transport``; ``raw``: the raw websockets client there;
    ``loop``: asyncio or uvloop; ``warmup``: calls on each connection first)."""
    from srvwire.client import connect
    from srvwire.protocol import services_notification
    from srvwire.transports.base import Connection, Transport, TransportClosed
    from srvwire.typeregistry import fingerprint, full_definition

    from common import SERVICE, SMALL_REQUEST, SRV_TYPE, reply_fields
    from typed import RobotStateQuery

    definition = full_definition(RobotStateQuery)
    assert definition is not None
    announcement = services_notification(
        [(SERVICE, SRV_TYPE)], {SERVICE: fingerprint(definition)}
    ).serialize()
    result = RobotStateQuery.Response(**reply_fields("position")).model_dump_json().encode()
    id_of = re.compile(rb'"id":([0-9]+)')

    class Answering(Connection):
        """Answers every request with the small reply, as a srvwire server writes it."""

        remote_address = ("fake", 0)
        identity = None

        def __init__(self) -> None:
            self.messages: deque[str | bytes] = deque([announcement.decode()])
            self.waiter: asyncio.Future[None] | None = None
            self.loop = asyncio.get_running_loop()
            self.ended = False
            self.receive: Any = None
            self.arriving: list[str] = []

        async def recv(self) -> str | bytes:
            while not self.messages:
                if self.ended:
                    raise TransportClosed(1000)
                self.waiter = self.loop.create_future()
                try:
                    await self.waiter
                finally:
                    self.waiter = None
            return self.messages.popleft()

        async def send(self, message: str | bytes) -> None:
            data = message if isinstance(message, bytes) else message.encode()
            found = id_of.search(data)
            if found is None:  # a notification ($/cancel): nothing to answer
                return
            reply = b'{"jsonrpc":"2.0","id":' + found[1] + b',"result":' + result + b"}"
            if not self.arriving:  # the replies of one turn arrive together, in one callback
                self.loop.call_soon(self.arrive)
            self.arriving.append(reply.decode())

        def arrive(self) -> None:
            """What a transport's read callback does with the replies of one socket read."""
            arriving, self.arriving = self.arriving, []
            if self.receive is not None:
                for reply in arriving:
                    self.receive(reply)
                return
            self.messages.extend(arriving)
            self.wake()

        def deliver_to(self, receive: Any) -> bool:
            if not push:
                return False
            while self.messages:
                receive(self.messages.popleft())
            self.receive = receive
            return True

        def wake(self) -> None:
            if self.waiter is not None and not self.waiter.done():
                self.waiter.set_result(None)

        @property
        def congested(self) -> bool:
            return False

        async def writable(self) -> None:
            return None

        async def close(self, code: int = 1000, reason: str = "") -> None:
            self.ended = True
            self.wake()

        @property
        def close_code(self) -> int | None:
            return 1000 if self.ended else None

        @property
        def close_reason(self) -> str:
            return ""

    class Fake(Transport):
        name = "fake"

        async def listen(self, *args: Any, **kwargs: Any) -> Any:
            raise NotImplementedError

        async def connect(self, url: str, options: Any, **kwargs: Any) -> Connection:
            return Answering()

        def check_url(self, url: str) -> None:
            return None

    async def open_raw(stack: AsyncExitStack) -> Any:
        """A connection of the harness's raw websockets client to ``url``."""
        from baseline_client import BaselineConnection
        from websockets.asyncio.client import connect as websockets_connect

        assert url is not None
        opened = BaselineConnection(await websockets_connect(url, compression=None))
        stack.push_async_callback(opened.close)
        return opened

    def calling_raw(connection: Any) -> Callable[[int], Awaitable[None]]:
        """``n`` calls one after the other on a raw client's ``connection``."""
        from baseline_client import make_request

        request = make_request(SMALL_REQUEST)

        async def calling(n: int) -> None:
            for _ in range(n):
                reply = await connection.call(SERVICE, request)
                assert type(reply) is dict

        return calling

    def caller(client: Any) -> Callable[[int], Awaitable[None]]:
        """``n`` calls one after the other on ``client``: ``client.call(SERVICE, request)``,
        or the same through a ServiceProxy made once."""
        if raw:
            return calling_raw(client)
        request = RobotStateQuery.Request(**SMALL_REQUEST)
        proxied = client.proxy(SERVICE)

        async def calling(n: int) -> None:
            for _ in range(n):
                reply = await client.call(SERVICE, request)
                assert type(reply) is RobotStateQuery.Response

        async def proxying(n: int) -> None:
            for _ in range(n):
                reply = await proxied(request)
                assert type(reply) is RobotStateQuery.Response

        return proxying if proxy else calling

    async def run() -> dict[str, float]:
        figures: dict[str, float] = {}
        async with AsyncExitStack() as stack:
            clients = []
            for _ in range(FAN_IN if "fan-in" in shapes else 1):
                if raw:
                    clients.append(await open_raw(stack))
                    continue
                opened = (
                    connect("ws://fake", transport=Fake(), timeout=TIMEOUT)
                    if url is None
                    else connect(url, transport=transport, timeout=TIMEOUT)
                )
                clients.append(await stack.enter_async_context(opened))
            for client in clients:
                await caller(client)(warmup)
            for shape in shapes:
                if shape == "fan-in":  # one caller per connection
                    callers = [caller(client) for client in clients]
                else:
                    callers = [caller(clients[0])] * (PIPELINE if shape == "pipelined" else 1)
                each = calls // len(callers)
                started = time.process_time()
                await asyncio.gather(*(call(each) for call in callers))
                spent = time.process_time() - started
                figures[shape] = spent / (each * len(callers)) * 1e6
        return figures

    if loop == "uvloop":
        import uvloop

        return uvloop.run(run())
    return asyncio.run(run())


def child(
    src: str,
    calls: int,
    shapes: list[str],
    push: bool,
    prefix: Sequence[str] = (),
    server: Sequence[str] = (),
    proxy: bool = False,
    keep_heap: bool = False,
    loop: str = "asyncio",
    warmup: int = WARMUP,
) -> Any:
    """Run :func:`measure` in a child process with ``src`` first on its path; return what it
    printed, parsed, and what it wrote on stderr (``prefix``: a command to run it under;
    ``server``: the options naming the real server, if any; ``src`` :data:`RAW`: the raw
    websockets client, with this checkout's srvwire for the shared benchmark code)."""
    tree = HERE.parent / "src" if src == RAW else Path(src).resolve()
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), str(HERE)]))
    env["PYTHONHASHSEED"] = "0"  # the same work in every run, for the instruction counts
    command = [sys.executable, __file__, "--child", "--calls", str(calls)]
    if push:
        command.append("--push")
    if proxy:
        command.append("--proxy")
    if src == RAW:
        command.append("--raw")
    if keep_heap:
        command.append("--keep-heap")
    command += ["--loop", loop, "--warmup", str(warmup)]
    done = subprocess.run(
        [*prefix, *command, "--shapes", ",".join(shapes), *server],
        env=env,
        check=False,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(f"measuring {src} failed:\n{done.stderr}")
    return json.loads(done.stdout.splitlines()[-1]), done.stderr


def instructions(src: str, calls: int, shape: str, push: bool, server: Sequence[str],
                 proxy: bool = False, keep_heap: bool = False,
                 loop: str = "asyncio", warmup: int = WARMUP) -> float:  # fmt: skip
    """Instructions per call (valgrind's count): the difference between a run of ``calls``
    and one of three times as many, so that starting up and warming up cancel out."""
    counted = []
    for n in (calls, 3 * calls):
        _, err = child(src, n, [shape], push, VALGRIND, server, proxy, keep_heap, loop, warmup)
        found = re.search(r"I\s+refs:\s+([0-9,]+)", err)
        if found is None:
            raise SystemExit(f"valgrind did not count {src}'s instructions:\n{err}")
        counted.append(int(found[1].replace(",", "")))
    return (counted[1] - counted[0]) / (2 * calls)


VALGRIND = ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]


@contextlib.contextmanager
def real_server(transport: str) -> Iterator[list[str]]:
    """Run the harness's srvwire server on ``transport`` until exit; yield the options that
    point a child at it."""
    server = subprocess.Popen(
        [sys.executable, str(HERE / "srvwire_server.py"), "--transport", transport],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None
        port = json.loads(server.stdout.readline())["port"]
        yield ["--url", f"ws://127.0.0.1:{port}", "--transport", transport]
    finally:
        assert server.stdin is not None
        server.stdin.close()  # the server stops when its stdin closes
        server.wait(timeout=30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--src", action="append", help="a srvwire source tree (repeatable)")
    parser.add_argument("--calls", type=int, default=64_000, help="calls per shape and run")
    parser.add_argument("--repeat", type=int, default=5, help="runs per tree (the minimum counts)")
    parser.add_argument("--shapes", default="pipelined,sequential")
    parser.add_argument(
        "--instructions",
        action="store_true",
        help="count instructions per call under valgrind instead (slow; not disturbed by "
        "other processes); --calls is then the smaller of the two runs (default 2 000)",
    )
    parser.add_argument(
        "--push",
        action="store_true",
        help="the connection hands each reply to the client as it arrives, where the client "
        "asks for it (Connection.deliver_to, as both network transports do), instead of "
        "queueing it for the client's reader task",
    )
    parser.add_argument(
        "--server",
        choices=["websockets", "picows"],
        help="call a real srvwire server on this transport instead of the fake connection",
    )
    parser.add_argument(
        "--proxy",
        action="store_true",
        help="call through a ServiceProxy (client.proxy(name)(request)) instead of client.call",
    )
    parser.add_argument(
        "--raw",
        action="store_true",
        help="with --server websockets: measure the harness's raw websockets client too, as one "
        "more row",
    )
    parser.add_argument(
        "--keep-heap",
        action="store_true",
        help="call srvwire.keep_freed_heap() first in every child, so that no read maps memory",
    )
    parser.add_argument(
        "--loop", choices=["asyncio", "uvloop"], default="asyncio", help="the client's event loop"
    )
    parser.add_argument(
        "--warmup",
        type=int,
        default=WARMUP,
        help=f"calls on each connection before the measured ones ({WARMUP}; the test suite's "
        "smoke runs take fewer)",
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--url", help=argparse.SUPPRESS)
    parser.add_argument("--transport", default="websockets", help=argparse.SUPPRESS)
    args = parser.parse_args()
    shapes = args.shapes.split(",")
    if args.raw and not args.child and args.server != "websockets":
        parser.error("--raw measures the raw websockets client: it needs --server websockets")
    if args.child:
        if args.keep_heap:
            from srvwire.heap import keep_freed_heap

            keep_freed_heap()
        figures = measure(
            args.calls,
            shapes,
            args.push,
            args.url,
            args.transport,
            args.proxy,
            args.raw,
            args.loop,
            args.warmup,
        )
        print(json.dumps(figures))
        return
    with contextlib.ExitStack() as stack:
        server = [] if args.server is None else stack.enter_context(real_server(args.server))
        report(args, parser, shapes, server)


def report(
    args: argparse.Namespace, parser: argparse.ArgumentParser, shapes: list[str], server: list[str]
) -> None:
    """Measure every source tree and print the tables."""
    sources = (args.src or [str(HERE.parent / "src")]) + ([RAW] if args.raw else [])
    if args.instructions:
        calls = 2_000 if args.calls == parser.get_default("calls") else args.calls
        for shape in shapes:
            print(f"{shape} (instructions per call, valgrind)")
            counts = [
                instructions(
                    src,
                    calls,
                    shape,
                    args.push,
                    server,
                    args.proxy,
                    args.keep_heap,
                    args.loop,
                    args.warmup,
                )
                for src in sources
            ]
            for src, count in zip(sources, counts, strict=True):
                print(f"  {count:8.0f}  ratio {count / counts[0]:.3f}  {src}")
        return
    runs: dict[str, dict[str, list[float]]] = {src: {s: [] for s in shapes} for src in sources}
    for _ in range(args.repeat):
        for src in sources:
            measured = child(
                src,
                args.calls,
                shapes,
                args.push,
                (),
                server,
                args.proxy,
                args.keep_heap,
                args.loop,
                args.warmup,
            )[0]
            for shape, value in measured.items():
                runs[src][shape].append(value)
    first = sources[0]
    for shape in shapes:
        print(f"{shape} (µs of client CPU per call, minimum of {args.repeat}; all runs)")
        for src in sources:
            values = runs[src][shape]
            ratio = min(values) / min(runs[first][shape])
            listed = " ".join(f"{v:.2f}" for v in values)
            print(f"  {min(values):6.2f}  ratio {ratio:.3f}  {src}  [{listed}]")


if __name__ == "__main__":
    main()
