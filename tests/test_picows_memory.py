"""A picows connection that once received a large message does not keep the memory of it.

``picows`` grows a connection's read buffer to hold a frame and never shrinks it; the picows
transport hands the pages it grew by back to the system once the frame is read. Measured as
the resident memory (``VmRSS``) of a process holding many idle connections that each received
one large message, against the same process after small messages only
(``benchmarks/picows_memory.py``, which runs the measured process on its own).
"""

from __future__ import annotations

import asyncio
import ctypes
import mmap
import os
import re

import pytest

from srvwire.transports.base import Connection, Options
from srvwire.transports.picows import KEEP_READ, PicowsConnection, PicowsTransport
from support import ROOT, run_benchmark, scaled, tls_on_localhost

SCRIPT = ROOT / "benchmarks" / "picows_memory.py"
CONNECTIONS = 40
LARGE = 2**20


def rss_mib(*args: str) -> float:
    """The measured process's resident memory, as the benchmark reports it."""
    output = run_benchmark(SCRIPT, "--connections", str(CONNECTIONS), *args).stdout
    match = re.search(r"VmRSS ([0-9.]+) MiB", output)
    assert match, output
    return float(match.group(1))


@pytest.mark.parametrize("side", ["server", "client"])
def test_connections_give_back_the_read_buffer_a_large_message_grew(side: str) -> None:
    small = rss_mib("--transport", "picows", "--side", side, "--size", "100")
    large = rss_mib("--transport", "picows", "--side", side, "--size", str(LARGE))
    # Kept, each connection would hold its 1 MiB message's buffer: 40 MiB more in all.
    assert large - small < CONNECTIONS * LARGE / 2**20 / 4, (small, large)


def resident(connection: PicowsConnection) -> tuple[int, int]:
    """Of the pages of ``connection``'s picows read buffer past its first ``KEEP_READ`` free
    bytes, how many are resident (``mincore``), and how many there are."""
    assert connection._ws is not None
    view = connection._ws.underlying_transport.get_protocol().get_buffer(-1)
    start = ctypes.addressof(ctypes.c_char.from_buffer(view))
    page = mmap.PAGESIZE
    first = -(-(start + KEEP_READ) // page) * page
    end = (start + len(view)) // page * page
    pages = max(0, (end - first) // page)
    vector = (ctypes.c_ubyte * pages)()
    mincore = ctypes.CDLL(None, use_errno=True).mincore
    mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p]
    assert mincore(first, end - first, vector) == 0, os.strerror(ctypes.get_errno())
    return sum(byte & 1 for byte in vector), pages


@pytest.mark.parametrize("tls", [False, True], ids=["ws", "wss"])
async def test_the_pages_a_large_frame_took_are_not_resident_once_it_is_read(tls: bool) -> None:
    """Each end, with and without TLS: after a 1 MiB message, picows' read buffer is over 1 MiB
    long, and none of its pages past the first ``KEEP_READ`` free bytes is resident."""
    server_tls, client_tls = tls_on_localhost(tls)
    accepted: asyncio.Queue[Connection] = asyncio.Queue()
    done = asyncio.Event()

    async def handler(connection: Connection) -> None:
        accepted.put_nowait(connection)
        await done.wait()

    transport = PicowsTransport()
    listener = await transport.listen(handler, "127.0.0.1", 0, Options(), ssl=server_tls)
    try:
        async with asyncio.timeout(scaled(10)):
            client = await transport.connect(listener.url, Options(), ssl=client_tls)
            server = await accepted.get()
            assert isinstance(client, PicowsConnection)
            assert isinstance(server, PicowsConnection)
            message = "x" * (2**20 - 100)
            await client.send(message)
            assert await server.recv() == message
            await server.send(message)
            assert await client.recv() == message
            for end in (server, client):
                kept, pages = resident(end)
                assert pages * mmap.PAGESIZE > 2**20 - KEEP_READ and kept == 0, (kept, pages)
            await client.close()
    finally:
        done.set()
        listener.close()
        await listener.wait_closed()
