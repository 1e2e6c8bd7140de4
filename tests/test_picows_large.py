"""Large and fragmented messages on the WebSocket transports, read from a raw peer's frames.

The peer is a plain socket that does the opening handshake and then writes frames built here,
so that a test can send what no WebSocket library sends (a continuation frame with nothing to
continue, a message begun inside another) and hold its frames ready before a measurement.
Well-formed fragments are read alike by both WebSocket transports; the picows transport's own
checks of fragments, and how many copies of a large message it makes while reading one, are
tested on picows.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import os
import re
import socket
import tracemalloc
from collections.abc import AsyncIterator

import pytest
from websockets.frames import Frame, Opcode

from srvwire.transports.base import Connection, Options, Transport
from srvwire.transports.picows import PicowsTransport
from support import ROOT, run_benchmark, scaled, tls_on_localhost
from test_transports import closed_with, listening, real  # noqa: F401 (real: a fixture)


def frame(opcode: Opcode, payload: bytes, fin: bool = True) -> bytes:
    """One client-to-server frame, masked as RFC 6455 asks of a client."""
    return Frame(opcode, payload, fin=fin).serialize(mask=True)


@contextlib.asynccontextmanager
async def raw_peer(
    transport: Transport, options: Options | None = None
) -> AsyncIterator[tuple[socket.socket, Connection]]:
    """Listen on ``transport``, open a WebSocket to it from a plain socket, and yield the
    socket (past the server's answer to the opening) and the server's end of the connection."""
    loop = asyncio.get_running_loop()
    async with listening(transport, options) as (listener, accepted):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        try:
            async with asyncio.timeout(scaled(5)):
                await loop.sock_connect(sock, ("127.0.0.1", listener.port))
                key = base64.b64encode(os.urandom(16)).decode()
                opening = (
                    f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{listener.port}\r\n"
                    "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                    f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
                )
                await loop.sock_sendall(sock, opening.encode())
                answer = b""
                while b"\r\n\r\n" not in answer:
                    read = await loop.sock_recv(sock, 4096)
                    assert read, f"the server closed the connection after {answer!r}"
                    answer += read
                assert answer.startswith(b"HTTP/1.1 101 "), answer
                server = await accepted.get()
            yield sock, server
        finally:
            sock.close()


async def send(sock: socket.socket, *frames: bytes) -> None:
    await asyncio.get_running_loop().sock_sendall(sock, b"".join(frames))


# Fragments


async def test_fragments_of_every_shape_are_joined_and_decoded_once(real: Transport) -> None:  # noqa: F811
    async with raw_peer(real) as (sock, server), asyncio.timeout(scaled(5)):
        large = os.urandom(300_000)
        await send(
            sock,
            # "é" is two bytes in UTF-8, split here across two frames.
            frame(Opcode.TEXT, b"h\xc3", fin=False),
            frame(Opcode.CONT, b"\xa9llo"),
            # An empty first fragment, and an empty last one.
            frame(Opcode.TEXT, b"", fin=False),
            frame(Opcode.CONT, b"after empty", fin=False),
            frame(Opcode.CONT, b""),
            # A large binary message in fragments of several sizes.
            frame(Opcode.BINARY, large[:1], fin=False),
            frame(Opcode.CONT, large[1:200_000], fin=False),
            frame(Opcode.CONT, large[200_000:]),
            frame(Opcode.TEXT, b"last"),
        )
        received = [await server.recv() for _ in range(4)]
        assert received == ["héllo", "after empty", large, "last"]


async def test_fragments_that_are_not_utf8_once_joined_close_with_1007() -> None:
    async with raw_peer(PicowsTransport()) as (sock, server):
        await send(
            sock,
            frame(Opcode.TEXT, b"fine"),
            frame(Opcode.TEXT, b"ends in half a character \xc3", fin=False),
            frame(Opcode.CONT, b"x"),
        )
        async with asyncio.timeout(scaled(5)):
            assert await server.recv() == "fine"
        assert (await closed_with(server)).code == 1007


@pytest.mark.parametrize(
    "frames",
    [
        [frame(Opcode.CONT, b"nothing to continue")],
        [frame(Opcode.TEXT, b"begun", fin=False), frame(Opcode.TEXT, b"another")],
        [frame(Opcode.TEXT, b"", fin=False), frame(Opcode.BINARY, b"another")],
    ],
    ids=["continuation alone", "a message inside another", "inside an empty beginning"],
)
async def test_frames_out_of_order_close_with_1002(frames: list[bytes]) -> None:
    async with raw_peer(PicowsTransport()) as (sock, server):
        await send(sock, frame(Opcode.TEXT, b"fine"), *frames)
        async with asyncio.timeout(scaled(5)):
            assert await server.recv() == "fine"
        assert (await closed_with(server)).code == 1002


async def test_a_fragment_past_the_limit_closes_with_1009_and_the_size_so_far() -> None:
    async with raw_peer(PicowsTransport(), Options(max_message_size=10)) as (sock, server):
        await send(
            sock,
            frame(Opcode.TEXT, b"x" * 10),
            frame(Opcode.TEXT, b"x" * 6, fin=False),
            frame(Opcode.CONT, b"x" * 4, fin=False),  # 10 bytes: at the limit
            frame(Opcode.CONT, b"x" * 3),
        )
        async with asyncio.timeout(scaled(5)):
            assert await server.recv() == "x" * 10
        closed = await closed_with(server)
        assert (closed.code, closed.reason) == (
            1009,
            "over the server's max_message_size (message of 13 bytes, limit 10 bytes)",
        )


@pytest.mark.parametrize(
    ("frames", "code"),
    [
        ([frame(Opcode.TEXT, b"x" * 11)], 1009),
        ([frame(Opcode.TEXT, b"x" * 8, fin=False), frame(Opcode.CONT, b"y" * 8)], 1009),
        ([frame(Opcode.TEXT, b"\xff")], 1007),
        ([frame(Opcode.CONT, b"nothing to continue")], 1002),
    ],
    ids=["over the limit", "fragments over the limit", "not utf-8", "continuation alone"],
)
async def test_a_message_behind_a_frame_that_fails_the_connection_is_not_delivered(
    frames: list[bytes], code: int
) -> None:
    """Once this side has failed the connection, nothing it reads is delivered (RFC 6455,
    section 7.1.7): not even a valid message that came in the same read, behind the frame
    (websockets' parser stops at such a frame)."""
    async with raw_peer(PicowsTransport(), Options(max_message_size=10)) as (sock, server):
        await send(sock, *frames, frame(Opcode.TEXT, b"after"))
        assert (await closed_with(server)).code == code


# How many copies of a large message picows makes while reading it


async def test_a_large_text_message_is_held_once_while_it_is_read() -> None:
    """A text message that arrives in one frame becomes a ``str`` straight from picows' read
    buffer: while it is read, the process holds one copy of it more, not two (a ``bytes`` of
    the payload and then the ``str`` decoded from it)."""
    size = 2**20
    payload = b"[" + b"1.5," * (size // 4 - 1) + b"2.5]"
    frames = [frame(Opcode.TEXT, payload) for _ in range(3)]  # ready before the measurement
    options = Options(max_message_size=4 * size)
    async with raw_peer(PicowsTransport(), options) as (sock, server), asyncio.timeout(scaled(10)):
        # The first two grow picows' read buffer to what such a message needs; it keeps it.
        for warm in frames[:2]:
            await send(sock, warm)
            assert len(await server.recv()) == len(payload)
        tracemalloc.start()
        try:
            await send(sock, frames[2])
            message = await server.recv()
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert message == payload.decode()
        assert len(payload) < peak < 1.5 * len(payload)


# How a picows server writes a large message


async def test_a_large_message_a_server_holds_is_written_without_joining_its_bulk() -> None:
    from srvwire.transports.picows import WRITE_APART, PicowsConnection, _header

    class Underlying:
        def __init__(self) -> None:
            self.written: list[bytes | memoryview] = []

        def write(self, data: bytes | memoryview) -> None:
            self.written.append(data)

    class FakeWS:
        is_close_frame_sent = False
        underlying_transport = Underlying()

    ws = FakeWS()
    for size in (WRITE_APART, WRITE_APART + 1, 1_000_000):
        conn = PicowsConnection(Options())
        conn._ws = ws  # type: ignore[assignment]
        conn._framing = True  # a server's: it frames its own messages
        message = os.urandom(size)
        conn._corked = [_header(5), b"small", _header(size), message]
        conn._corked_size = 5 + size
        conn._flush()
        written, ws.underlying_transport.written = ws.underlying_transport.written, []
        assert b"".join(written) == _header(5) + b"small" + _header(size) + message
        if size == WRITE_APART:  # joined, as every smaller one is
            assert len(written) == 1
        else:
            head, rest = written
            assert head == _header(5) + b"small" + _header(size) + message[:WRITE_APART]
            assert isinstance(rest, memoryview) and rest.obj is message  # not a copy
        assert (conn._corked, conn._corked_size) == ([], 0)


@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
async def test_large_messages_between_small_ones_arrive_whole_and_in_order(tls: bool) -> None:
    from srvwire.transports.picows import WRITE_APART

    server_ssl, client_ssl = tls_on_localhost(tls)
    transport = PicowsTransport()
    sizes = [10, WRITE_APART + 1, 3, 2_000_000, WRITE_APART, 7, 5_000_000]
    messages = [os.urandom(size // 2).hex() for size in sizes]
    options = Options(max_message_size=None)
    async with (
        listening(transport, options, ssl=server_ssl) as (listener, accepted),
        asyncio.timeout(scaled(20)),
    ):
        client = await transport.connect(listener.url, options, ssl=client_ssl)
        try:
            server = await accepted.get()
            for message in messages:  # in one turn: held, and written as they come
                await server.send(message)
            assert [await client.recv() for _ in messages] == messages
        finally:
            await client.close()


@pytest.mark.parametrize("loop", ["asyncio", "uvloop"])
def test_the_large_send_benchmark_reads_every_message_it_sends(loop: str) -> None:
    # A smoke run: the script exits with an error unless every frame arrived as it was sent.
    script = ROOT / "benchmarks" / "picows_large_send.py"
    result = run_benchmark(script, "--size", "100000", "--messages", "12", "--loop", loop)
    figure = re.fullmatch(
        rf"{loop}: (\S+) ms of CPU per message, sender and reader\n", result.stdout
    )
    assert figure is not None, result.stdout
    assert float(figure[1]) > 0
