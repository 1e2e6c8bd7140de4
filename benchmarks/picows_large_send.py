"""A picows server's large messages, in one process: what sending them costs, with their reading.

A srvwire server on the picows transport sends ``--messages`` text messages of ``--size``
bytes (1.7 MB, W4's reply) on one connection to a plain socket in the same process, which
reads them into one buffer it keeps: every frame's header is checked, and in the warm-up the
payload too. The figure is the process's CPU time per message, sender and
reader together, after ``WARMUP`` messages; the reader's part is the same in every version,
so two versions compare by their difference. Run it with another checkout's ``src`` first on
``PYTHONPATH`` to measure an older version, and under ``perf stat -e page-faults`` or
``strace -c`` for what the kernel does::

    python benchmarks/picows_large_send.py [--messages 300] [--loop uvloop]
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import os
import socket
import time

from srvwire.transports.base import Connection, Options
from srvwire.transports.picows import PicowsTransport

WARMUP = 10
HEADER = 10  # a server's frame header for a message of 64 KiB or more


async def opened(port: int) -> socket.socket:
    """A plain socket past the WebSocket opening handshake with 127.0.0.1:``port``."""
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setblocking(False)
    await loop.sock_connect(sock, ("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    opening = (
        f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    await loop.sock_sendall(sock, opening.encode())
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += await loop.sock_recv(sock, 4096)
    if not answer.startswith(b"HTTP/1.1 101 "):
        raise SystemExit(f"the server refused the connection: {answer!r}")
    return sock


async def read(sock: socket.socket, message: bytes, count: int, whole: bool) -> None:
    """Read ``count`` frames of ``message`` from ``sock``; exit unless each has its header
    (and, if ``whole``, its payload)."""
    loop = asyncio.get_running_loop()
    frame = len(message) + HEADER
    header = bytes((0x81, 127)) + len(message).to_bytes(8, "big")
    buffer = bytearray(frame)
    view = memoryview(buffer)
    for _ in range(count):
        have = 0
        while have < frame:
            got = await loop.sock_recv_into(sock, view[have:frame])
            if not got:
                raise SystemExit("the connection closed before every message arrived")
            have += got
        if buffer[:HEADER] != header or (whole and buffer[HEADER:] != message):
            raise SystemExit("a message arrived other than it was sent")


async def run(size: int, messages: int) -> float:
    """Send ``messages`` messages of ``size`` bytes; return the CPU time per message, in ms."""
    accepted: asyncio.Queue[Connection] = asyncio.Queue()
    done = asyncio.Event()

    async def handler(connection: Connection) -> None:
        accepted.put_nowait(connection)
        await done.wait()

    listener = await PicowsTransport().listen(
        handler, "127.0.0.1", 0, Options(max_message_size=None)
    )
    sock = await opened(listener.port)
    try:
        server = await accepted.get()
        message = b"[" + b"1.5," * ((size - 5) // 4) + b"2.5]"
        for count in (WARMUP, messages):
            reader = asyncio.create_task(read(sock, message, count, whole=count == WARMUP))
            started = time.process_time()
            for _ in range(count):
                await server.send(message)
            await reader
            elapsed = time.process_time() - started
    finally:
        done.set()
        sock.close()
        listener.close()
        await listener.wait_closed()
    return elapsed / messages * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else "")
    parser.add_argument("--size", type=int, default=1_687_000, help="bytes a message")
    parser.add_argument("--messages", type=int, default=300)
    parser.add_argument("--loop", choices=["asyncio", "uvloop"], default="asyncio")
    args = parser.parse_args()
    if args.size < 2**16:
        parser.error("--size must be at least 65536 (the header is then 10 bytes)")
    if args.loop == "uvloop":
        import uvloop

        per_message = uvloop.run(run(args.size, args.messages))
    else:
        per_message = asyncio.run(run(args.size, args.messages))
    print(f"{args.loop}: {per_message:.3f} ms of CPU per message, sender and reader")


if __name__ == "__main__":
    main()
