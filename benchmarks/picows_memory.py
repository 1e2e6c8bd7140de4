"""Resident memory of connections that each once received one large message, then stay idle.

The measured process runs in a child: a server on ``--transport`` (picows or websockets) that
``--connections`` clients each send one message of ``--size`` bytes (answered with ``ok``),
or, with ``--side client``, a process holding that many client connections that were each
sent one reply of ``--size`` bytes. The peer is this process, on the websockets transport.
Once every message has been received, the child reports its ``VmRSS`` (from
``/proc/self/status``), its minor page faults and its CPU time since it started; run it with a
small ``--size`` for the baseline. ``--messages`` sends each connection that many, one at a
time, to count what reading the next large message costs once the pages are given back::

    python benchmarks/picows_memory.py --transport picows --connections 200 --size 1048576
    python benchmarks/picows_memory.py --transport picows --connections 200 --size 100
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import resource
import sys
from asyncio.subprocess import PIPE
from typing import Any

from srvwire.transports.base import Connection, Options, Transport, TransportClosed
from srvwire.transports.picows import PicowsTransport
from srvwire.transports.websockets import WebSocketsTransport

OPTIONS = Options(max_message_size=2**24, ping_interval=None, ping_timeout=None)


def transport(name: str) -> Transport:
    return PicowsTransport() if name == "picows" else WebSocketsTransport()


def rss_kib() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status")


async def child(args: argparse.Namespace) -> None:
    """The measured process: the server (it reads the port and the go from stdin's lines) or
    the clients (their server's port is an argument)."""
    loop = asyncio.get_running_loop()
    stdin = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(stdin), sys.stdin)
    if args.side == "server":

        async def answer(connection: Connection) -> None:
            while True:
                await connection.recv()
                await connection.send("ok")

        listener = await transport(args.transport).listen(answer, "127.0.0.1", 0, OPTIONS)
        print(listener.port, flush=True)
        await stdin.readline()  # every client has had its answer
    else:
        url = f"ws://127.0.0.1:{args.port}/"
        connections = [
            await transport(args.transport).connect(url, OPTIONS) for _ in range(args.connections)
        ]
        for connection in connections:  # one at a time, as the server's side
            for _ in range(args.messages):
                await connection.send("go")
                await connection.recv()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu = usage.ru_utime + usage.ru_stime
    print(rss_kib(), usage.ru_minflt, f"{cpu:.3f}", flush=True)
    await stdin.readline()
    if args.side == "client":
        for connection in connections:
            await connection.close()


async def parent(args: argparse.Namespace) -> None:
    payload = "x" * args.size
    command = [__file__, "--child", "--side", args.side]
    command += ["--transport", args.transport, "--connections", str(args.connections)]
    command += ["--messages", str(args.messages)]
    peer = WebSocketsTransport()
    pipes: dict[str, Any] = {"stdin": PIPE, "stdout": PIPE}
    if args.side == "server":
        process = await asyncio.create_subprocess_exec(sys.executable, *command, **pipes)
        assert process.stdin is not None and process.stdout is not None
        url = f"ws://127.0.0.1:{int(await process.stdout.readline())}/"
        clients = [await peer.connect(url, OPTIONS) for _ in range(args.connections)]
        for client in clients:  # one at a time: the server holds one message at once
            for _ in range(args.messages):
                await client.send(payload)
                assert await client.recv() == "ok"
        process.stdin.write(b"\n")
    else:

        async def reply(connection: Connection) -> None:
            for _ in range(args.messages):
                await connection.recv()
                await connection.send(payload)
            with contextlib.suppress(TransportClosed):
                await connection.recv()  # until the child closes it

        listener = await peer.listen(reply, "127.0.0.1", 0, OPTIONS)
        command += ["--port", str(listener.port)]
        process = await asyncio.create_subprocess_exec(sys.executable, *command, **pipes)
        assert process.stdin is not None and process.stdout is not None
    rss, faults, cpu = (await process.stdout.readline()).split()
    process.stdin.write(b"\n")
    process.stdin.close()
    await process.wait()
    print(f"{args.side} on {args.transport}, {args.connections} connections, "
          f"{args.messages} message(s) of {args.size} bytes each: "
          f"VmRSS {int(rss) / 1024:.1f} MiB, {int(faults)} minor page faults, "
          f"CPU {float(cpu):.3f} s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--transport", choices=["picows", "websockets"], default="picows")
    parser.add_argument("--side", choices=["server", "client"], default="server")
    parser.add_argument("--connections", type=int, default=200)
    parser.add_argument("--size", type=int, default=2**20)
    parser.add_argument("--messages", type=int, default=1, help="each connection receives")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        asyncio.run(child(args))
    else:
        asyncio.run(parent(args))


if __name__ == "__main__":
    main()
