"""How the websockets transport reads its sockets: into one buffer per thread.

Every test runs on real sockets on 127.0.0.1. The buffer is shared by every connection of a
thread, so what matters is that nothing is read into it before what the last read brought was
taken out: a frame that arrives in pieces, on two connections at once, must come out whole.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import threading
import tracemalloc
from collections.abc import AsyncIterator, Callable

import pytest
import uvloop

from srvwire.transports.base import Connection, Options
from srvwire.transports.websockets import READ_SIZE, WebSocketsConnection, WebSocketsTransport
from support import scaled, tls_on_localhost
from test_transports import listening
from test_websockets_push import MODES, Taker, accept, received


def text_frame(payload: bytes) -> bytes:
    """An unmasked, final text frame (as a server writes it) of ``payload`` (< 64 KiB)."""
    return b"\x81\x7e" + struct.pack("!H", len(payload)) + payload


def reads_of(connection: Connection) -> asyncio.Queue[int]:
    """A queue that gets the size of every read ``connection`` makes from now on."""
    ws = connection._ws  # type: ignore[attr-defined]
    reads: asyncio.Queue[int] = asyncio.Queue()
    data_received = ws.data_received

    def reading(data: bytes) -> None:
        reads.put_nowait(len(data))
        data_received(data)

    ws.data_received = reading
    return reads


@contextlib.asynccontextmanager
async def two_clients(tls: bool) -> AsyncIterator[list[tuple[Connection, WebSocketsConnection]]]:
    """Two clients of one listener, each with the server's end of its connection."""
    transport = WebSocketsTransport()
    server_ssl, client_ssl = tls_on_localhost(tls)
    async with listening(transport, ssl=server_ssl) as (listener, accepted):
        ends = []
        try:
            async with asyncio.timeout(scaled(5)):
                for _ in range(2):
                    client = await transport.connect(listener.url, Options(), ssl=client_ssl)
                    ends.append((client, await accept(accepted)))
                yield ends
        finally:
            async with asyncio.timeout(scaled(5)):
                for client, _ in ends:
                    await client.close()


@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
@pytest.mark.parametrize("mode", MODES)
async def test_frames_that_arrive_in_pieces_on_two_connections_come_out_whole(
    mode: str, tls: bool
) -> None:
    """Each connection keeps the first piece of its frame while the other connection's piece,
    and then its own second piece, are read into the same buffer."""
    async with two_clients(tls) as ends:
        payloads = [bytes([65 + i]) * 1000 for i in range(2)]  # "AAA…", "BBB…"
        frames = [text_frame(payload) for payload in payloads]
        reads = [reads_of(client) for client, _ in ends]
        for half in (slice(None, 500), slice(500, None)):  # each in a read of its own
            for (_, server), frame, read in zip(ends, frames, reads, strict=True):
                server._ws.transport.write(frame[half])
                await read.get()
        async with asyncio.timeout(scaled(5)):
            for (client, _), payload in zip(ends, payloads, strict=True):
                assert await received(client, mode, 1) == [payload.decode()]


def test_a_thread_reads_every_connection_into_its_own_buffer() -> None:
    """Two connections of one thread read into one buffer; another thread into another."""

    async def buffers_read_into() -> set[int]:
        async with two_clients(tls=False) as ends:
            seen: set[int] = set()
            for client, server in ends:
                ws = client._ws  # type: ignore[attr-defined]
                get_buffer: Callable[[int], memoryview] = ws.get_buffer

                def getting(hint: int, get: Callable[[int], memoryview] = get_buffer) -> memoryview:
                    view = get(hint)
                    seen.add(id(view.obj))
                    return view

                ws.get_buffer = getting
                await server.send("ping")
                assert await client.recv() == "ping"
            return seen

    here = asyncio.run(buffers_read_into())
    there: list[set[int]] = []
    thread = threading.Thread(target=lambda: there.append(asyncio.run(buffers_read_into())))
    thread.start()
    thread.join()
    assert len(here) == 1
    assert len(there) == 1
    assert here != there[0]


async def test_reading_small_messages_allocates_no_read_sized_buffer() -> None:
    """asyncio's own reading allocates a new buffer of the read size for every read (which
    the C library maps from the kernel and unmaps again); these reads allocate none."""
    async with two_clients(tls=False) as ends:
        (client, server), _ = ends
        await server.send("warm up")
        assert await client.recv() == "warm up"
        tracemalloc.start()
        try:
            for i in range(20):
                await server.send(f"message {i}")
                assert await client.recv() == f"message {i}"
                await client.send(f"reply {i}")
                assert await server.recv() == f"reply {i}"
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert peak < READ_SIZE // 4


def test_messages_flow_on_uvloop_which_reads_as_before() -> None:
    """uvloop hands a connection what it read (``data_received``; a connection is an
    ``asyncio.Protocol`` too), from a buffer of its own: the same messages, whole."""

    async def exchange() -> list[str | bytes]:
        async with two_clients(tls=False) as ends:
            (client, server), _ = ends
            big = "x" * (3 * READ_SIZE)  # more than one read's worth
            taker = Taker()
            assert client.deliver_to(taker)
            for message in ("small", big, "after"):
                await server.send(message)
            async with asyncio.timeout(scaled(5)):
                return await taker.until(3)

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        taken = runner.run(exchange())
    assert taken == ["small", "x" * (3 * READ_SIZE), "after"]
