"""How the websockets transport reads its sockets: into one buffer per thread.

Every test runs on real sockets on 127.0.0.1. The buffer is shared by every connection of a
thread, so what matters is that nothing is read into it before what the last read brought was
taken out: a frame that arrives in pieces, on two connections at once, must come out whole.
A client reads a large payload from the socket straight into the buffer it is handed over as,
and a server hands over websockets' buffer when it holds exactly such a payload (the reader is
also tested alone, fed by hand).
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import threading
import tracemalloc
from collections.abc import AsyncIterator, Callable
from typing import Any

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


def feed(reader: Any, n: int, pieces: list[bytes], eof: bool = False) -> Any:
    """What ``reader.read_exact(n)`` returns once ``pieces`` were fed to it one at a time (and
    then the end of the stream, with ``eof``), or raises."""
    reading = reader.read_exact(n)
    try:
        next(reading)  # waits for the first piece
        for piece in pieces:
            reader.feed_data(piece)
            next(reading)
        if eof:
            reader.feed_eof()
            next(reading)
    except StopIteration as done:
        return done.value
    raise AssertionError("read_exact still waits")


def test_the_reader_hands_over_a_large_payload_that_fills_it_as_its_buffer() -> None:
    """From LARGE_MESSAGE bytes, a payload that came whole before it was asked for is handed
    over as the reader's buffer when that holds exactly it (a new buffer takes its place); with
    bytes behind it it is read as websockets' reader reads it; so is a short count, and a
    payload that ends early fails with websockets' words."""
    from websockets.streams import StreamReader

    from srvwire.transports.websockets import LARGE_MESSAGE, _WholeReader

    size = LARGE_MESSAGE + 3
    payload = bytes(range(256)) * (size // 256) + b"xyz"[: size % 256]
    pieces = [payload[:1000], payload[1000:50_000], payload[50_000:]]

    reader = _WholeReader()
    buffer = reader.buffer
    reader.feed_data(payload)
    taken = feed(reader, size, [])
    assert taken is buffer and taken == payload
    assert reader.buffer is not buffer and reader.buffer == b""

    for make in (StreamReader, _WholeReader):  # the same answers from each
        reader = make()
        taken = feed(reader, size, [*pieces[:2], pieces[2] + b"next"])
        assert (taken, reader.buffer) == (payload, b"next")
        reader = make()
        reader.feed_data(payload + b"next")
        assert (feed(reader, size, []), reader.buffer) == (payload, b"next")
        reader = make()
        assert feed(reader, 2, [b"\x81\x7f"]) == b"\x81\x7f"
        reader = make()
        short = f"^stream ends after 1000 bytes, expected {size} bytes$"
        with pytest.raises(EOFError, match=short):
            feed(reader, size, pieces[:1], eof=True)


def test_a_clients_reader_reads_a_large_payload_into_a_buffer_of_its_size() -> None:
    """Once a large payload is asked for, what arrives goes into ``target``, the payload's own
    buffer, which is what is handed over; the bytes behind it stay in the reader's buffer."""
    from srvwire.transports.websockets import LARGE_MESSAGE, _WholeReader

    size = LARGE_MESSAGE * 3
    payload = bytes(range(251)) * (size // 251) + bytes(size % 251)
    reader = _WholeReader()
    reader.feed_data(payload[:100])  # the first read: a header's worth and a little more
    reading = reader.read_exact(size)
    next(reading)
    target = reader.target
    assert isinstance(target, bytearray) and len(target) == size
    assert (reader.filled, reader.buffer) == (100, b"")
    target[100:5000] = payload[100:5000]  # as the event loop reads the socket into it
    reader.filled += 4900
    reader.feed_data(b"")
    next(reading)
    reader.feed_data(payload[5000:] + b"after")  # as a read into another buffer hands it over
    with pytest.raises(StopIteration) as done:
        next(reading)
    assert done.value.value is target and target == payload
    assert (reader.target, reader.buffer) == (None, b"after")


@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
@pytest.mark.parametrize("mode", MODES)
async def test_a_clients_large_reply_is_read_from_the_socket_into_its_payload(
    mode: str, tls: bool
) -> None:
    """Past the read that brought its header, the event loop reads a large reply's payload
    straight into the buffer it is handed over as: no more than a read's worth of it goes
    through websockets' reader. A reply followed by two messages in one write comes out whole
    too."""
    async with two_clients(tls) as ends:
        (client, server), _ = ends
        ws = client._ws  # type: ignore[attr-defined]
        fed: list[int] = []
        reader = ws.protocol.reader
        feed_data = reader.feed_data

        def counting(data: bytes) -> None:
            fed.append(len(data))
            feed_data(data)

        reader.feed_data = counting
        reply = "[" + ",".join(str(i / 7) for i in range(40_000)) + "]"  # under 1 MiB
        assert len(reply) > 2 * READ_SIZE
        await server.send(reply)
        async with asyncio.timeout(scaled(5)):
            assert await received(client, mode, 1) == [reply]
        assert 0 < sum(fed) <= READ_SIZE
        then = [text_frame(b"a" * 1000), text_frame(b"b" * 2000)]
        server._ws.transport.write(b"\x81\x7f" + struct.pack("!Q", len(reply)) + reply.encode())
        server._ws.transport.write(b"".join(then))
        async with asyncio.timeout(scaled(5)):
            assert await received(client, mode, 3) == [reply, "a" * 1000, "b" * 2000]


async def test_only_a_client_with_a_size_limit_reads_in_place() -> None:
    """A server's peers are not trusted with memory they have not sent, nor is a peer whose
    messages no limit bounds: their large payloads are gathered as websockets gathers them."""
    transport = WebSocketsTransport()
    async with listening(transport) as (listener, accepted):
        for options, in_place in [(Options(), True), (Options(max_message_size=None), False)]:
            client = await transport.connect(listener.url, options)
            try:
                async with asyncio.timeout(scaled(5)):
                    server = await accept(accepted)
                reader = client._ws.whole_reader  # type: ignore[attr-defined]
                assert (reader is not None) is in_place
                assert server._ws.whole_reader is None  # type: ignore[attr-defined]
            finally:
                async with asyncio.timeout(scaled(5)):
                    await client.close()
