"""The websockets transport handing messages over in its read callback (``deliver_to``).

Every test runs on real sockets on 127.0.0.1. What a message is, how a connection ends and
why must be the same whether the connection is read with ``recv`` (``pull``) or hands its
messages to a receiver (``push``): the tests that compare the two run both and assert the same
outcome, so "as today" is checked, not assumed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import connect as websockets_connect
from websockets.asyncio.messages import MAX_FRAGMENTS
from websockets.frames import Frame

from conftest import Subtract, subtract
from srvwire import connect
from srvwire.inline import first_step
from srvwire.server import Server, serve
from srvwire.transports.base import Connection, Options, TransportClosed
from srvwire.transports.websockets import WebSocketsConnection, WebSocketsTransport
from support import scaled, tls_on_localhost
from test_transports import closed_with, connected, count_writes, listening

MODES = ["pull", "push"]


class Taker:
    """A receiver that keeps what it is handed and lets a test await the ``count``-th one."""

    def __init__(self) -> None:
        self.taken: list[str | bytes] = []
        self.waiting: dict[int, asyncio.Future[None]] = {}

    def __call__(self, message: str | bytes) -> None:
        self.taken.append(message)
        future = self.waiting.pop(len(self.taken), None)
        if future is not None:
            future.set_result(None)

    async def until(self, count: int) -> list[str | bytes]:
        """Wait until ``count`` messages were taken; return them all."""
        if len(self.taken) < count:
            future = self.waiting[count] = asyncio.get_running_loop().create_future()
            await future
        return self.taken


async def received(connection: Connection, mode: str, count: int) -> list[str | bytes]:
    """The next ``count`` messages of ``connection``: by ``recv``, or handed to a receiver."""
    if mode == "pull":
        return [await connection.recv() for _ in range(count)]
    taker = Taker()
    assert connection.deliver_to(taker)
    return await taker.until(count)


async def accept(accepted: asyncio.Queue[Connection]) -> WebSocketsConnection:
    server = await accepted.get()
    assert isinstance(server, WebSocketsConnection)
    return server


async def fill_the_queue(pair: Any, prefix: str) -> WebSocketsConnection:
    """Send the client of ``pair`` 100 messages (``prefix 0``, ``prefix 1``, ...), and return
    it once websockets' queue is full and has stopped reading the socket."""
    client = pair.client
    assert isinstance(client, WebSocketsConnection)
    queue = client._ws.recv_messages
    paused = asyncio.get_running_loop().create_future()
    pause = queue.pause

    def pausing() -> None:
        pause()
        if not paused.done():
            paused.set_result(None)

    queue.pause = pausing
    for i in range(100):
        await pair.server.send(f"{prefix} {i}")
    await paused
    return client


# Messages


@pytest.mark.parametrize("mode", MODES)
async def test_fragments_are_joined_and_binary_stays_bytes(mode: str) -> None:
    async with (
        listening(WebSocketsTransport()) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        server = await accept(accepted)
        await ws.send(["hé", "llo", " ☃"])  # one text message in three frames
        await ws.send([b"\x00", b"\xff"])  # one binary message in two
        await ws.send(b"\x00\xff binary")
        await ws.send([b"\xc3", b"\xa9"], text=True)  # "é", its two bytes in two frames
        await ws.send("after")
        assert await received(server, mode, 5) == ["héllo ☃", b"\x00\xff", b"\x00\xff binary",
                                                   "é", "after"]  # fmt: skip


async def test_messages_queued_while_reading_was_paused_go_first_and_reading_resumes() -> None:
    """websockets' queue stopped reading the socket when it filled up; handing its messages
    over empties it, so reading resumes and the later messages follow in order."""
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        client = await fill_the_queue(pair, "before")  # and the socket is no longer read
        queue = client._ws.recv_messages
        taker = Taker()
        assert client.deliver_to(taker)
        assert len(queue.frames) == 0
        for i in range(100):
            await pair.server.send(f"after {i}")
        expected = [f"before {i}" for i in range(100)] + [f"after {i}" for i in range(100)]
        assert await taker.until(200) == expected


async def test_a_message_begun_in_the_queue_is_finished_by_the_hand_over() -> None:
    async with (
        listening(WebSocketsTransport()) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        server = await accept(accepted)
        queue = server._ws.recv_messages
        first_frame = asyncio.get_running_loop().create_future()
        put = queue.put

        def putting(frame: Frame) -> None:
            put(frame)
            if not first_frame.done():
                first_frame.set_result(None)

        queue.put = putting  # type: ignore[method-assign]
        go_on = asyncio.Event()

        async def fragments() -> AsyncIterator[str]:
            yield "hé"
            await go_on.wait()
            yield "llo"

        sending = asyncio.create_task(ws.send(fragments()))
        await first_frame  # the message's first frame waits in websockets' queue
        taker = Taker()
        assert server.deliver_to(taker)
        go_on.set()
        await sending
        await ws.send("after")
        assert await taker.until(2) == ["héllo", "after"]


async def test_recv_returns_no_message_once_they_are_handed_over() -> None:
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        taker = Taker()
        assert pair.server.deliver_to(taker)
        receiving = asyncio.create_task(pair.server.recv())
        await pair.client.send("one")
        await pair.client.send("two")
        assert await taker.until(2) == ["one", "two"]
        assert not receiving.done()
        await pair.client.close(4000, "done")
        with pytest.raises(TransportClosed) as info:
            await receiving
        assert (info.value.code, info.value.reason) == (4000, "done")
        assert taker.taken == ["one", "two"]


async def test_compressed_messages_are_handed_over_whole() -> None:
    deflate = Options(compression="deflate")
    async with connected(WebSocketsTransport(), deflate) as pair, asyncio.timeout(scaled(5)):
        taker = Taker()
        assert pair.server.deliver_to(taker)
        sent = ["héllo ☃" * 100, "x" * 100_000, "small"]
        for message in sent:
            await pair.client.send(message)
        assert await taker.until(3) == sent


async def test_pongs_are_taken_while_messages_are_handed_over() -> None:
    """Keepalive goes on: each ping's pong is acknowledged, so no ping times out."""
    keepalive = Options(ping_interval=scaled(0.02), ping_timeout=scaled(1))
    async with connected(WebSocketsTransport(), keepalive) as pair, asyncio.timeout(scaled(5)):
        client = pair.client
        assert isinstance(client, WebSocketsConnection)
        assert client.deliver_to(Taker())
        acknowledged: list[bytes] = []
        three = asyncio.get_running_loop().create_future()
        acknowledge = client._ws.acknowledge_pings

        def counting(data: bytes) -> None:
            acknowledge(data)
            acknowledged.append(data)
            if len(acknowledged) == 3:
                three.set_result(None)

        client._ws.acknowledge_pings = counting  # type: ignore[method-assign]
        await three
        assert client._ws.latency > 0
        assert client.close_code is None


# How a connection ends: the same either way


@pytest.mark.parametrize("mode", MODES)
async def test_text_that_is_not_utf8_closes_with_1007(mode: str) -> None:
    async with (
        listening(WebSocketsTransport()) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        server = await accept(accepted)
        await ws.send("before")
        await ws.send([b"ok ", b"\xc3"], text=True)  # a character cut short at the end
        assert await received(server, mode, 1) == ["before"]
        closed = await closed_with(server)
        assert (closed.code, closed.reason) == (1007, "unexpected end of data at position 3")
        await ws.wait_closed()
        assert (ws.close_code, ws.close_reason) == (closed.code, closed.reason)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize(
    ("message", "reason"),
    [
        ("x" * 11, "frame with 11 bytes exceeds limit of 10 bytes"),
        (["x" * 6, "x" * 6], "frame with 6 bytes after reading 6 bytes exceeds limit of 10 bytes"),
    ],
    ids=["whole", "fragments"],
)
async def test_a_message_over_the_size_limit_closes_with_1009(
    mode: str, message: str | list[str], reason: str
) -> None:
    async with (
        listening(WebSocketsTransport(), Options(max_message_size=10)) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        server = await accept(accepted)
        await ws.send("small")
        await ws.send(message)
        assert await received(server, mode, 1) == ["small"]
        closed = await closed_with(server)
        assert (closed.code, closed.reason) == (
            1009,
            f"over the server's max_message_size ({reason})",
        )
        await ws.wait_closed()
        assert ws.close_code == 1009


@pytest.mark.parametrize("mode", MODES)
async def test_too_many_fragments_close_with_1009(mode: str) -> None:
    async with (
        listening(WebSocketsTransport()) as (listener, accepted),
        asyncio.timeout(scaled(10)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        server = await accept(accepted)
        # websockets' send ends a fragmented message with an empty frame of its own.
        await ws.send(["x"] * (MAX_FRAGMENTS - 1))  # as many frames as websockets takes
        await ws.send(["y"] * MAX_FRAGMENTS)  # one more
        assert await received(server, mode, 1) == ["x" * (MAX_FRAGMENTS - 1)]
        closed = await closed_with(server)
        assert (closed.code, closed.reason) == (
            1009,
            "over the server's max_message_size (too many fragments)",
        )


async def test_a_receiver_that_raises_closes_with_1011_and_is_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        taken: list[str | bytes] = []

        def receive(message: str | bytes) -> None:
            taken.append(message)
            if message == "bad":
                raise ValueError("the receiver broke")

        assert pair.server.deliver_to(receive)
        for message in ("good", "bad", "never"):  # in one write, so in one read
            await pair.client.send(message)
        assert (await closed_with(pair.client)).code == 1011
        assert (await closed_with(pair.server)).code == 1011
        assert taken == ["good", "bad"]
    [record] = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert record.getMessage() == "the receiver of messages failed; closing the connection"
    assert record.exc_info is not None
    assert str(record.exc_info[1]) == "the receiver broke"


# Pausing and resuming reading


async def turns(count: int = 1000) -> None:
    """Let the event loop run ``count`` times: a socket that is read has been read by then."""
    for _ in range(count):
        await asyncio.sleep(0)


@contextlib.asynccontextmanager
async def ends(tls: bool) -> AsyncIterator[tuple[Connection, WebSocketsConnection]]:
    """A client and the server's end of its connection, over TLS or not."""
    transport = WebSocketsTransport()
    server_ssl, client_ssl = tls_on_localhost(tls)
    async with listening(transport, ssl=server_ssl) as (listener, accepted):
        client = await transport.connect(listener.url, Options(), ssl=client_ssl)
        try:
            async with asyncio.timeout(scaled(5)):
                yield client, await accept(accepted)
        finally:
            async with asyncio.timeout(scaled(5)):
                await client.close()


@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
async def test_pause_stops_delivery_and_resume_restarts_it(tls: bool) -> None:
    async with ends(tls) as (client, server):
        taker = Taker()
        assert server.deliver_to(taker)
        await client.send("first")
        assert await taker.until(1) == ["first"]
        server.pause_reading()
        assert not server._ws.transport.is_reading()
        for i in range(3):
            await client.send(f"held {i}")
        await turns()
        assert taker.taken == ["first"]
        server.resume_reading()
        assert await taker.until(4) == ["first", "held 0", "held 1", "held 2"]


async def test_websockets_queue_does_not_resume_reading_that_srvwire_paused() -> None:
    """Read with recv: the queue, which paused reading when it filled up, resumes it as recv
    drains it, except while srvwire holds reading back; and srvwire's resume leaves a full
    queue paused."""
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        client = await fill_the_queue(pair, "m")
        queue = client._ws.recv_messages
        client.pause_reading()
        client.resume_reading()  # the queue is still full: it stays paused
        assert not client._ws.transport.is_reading()
        client.pause_reading()
        taken = [await client.recv() for _ in range(len(queue.frames))]  # the queue drains
        assert not client._ws.transport.is_reading()
        client.resume_reading()
        taken += [await client.recv() for _ in range(100 - len(taken))]
        assert taken == [f"m {i}" for i in range(100)]


async def test_close_while_paused_completes_the_handshake() -> None:
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        assert pair.server.deliver_to(Taker())
        pair.server.pause_reading()
        await pair.server.close(4000, "bye")  # the client's answer is read: no close timeout
        assert (pair.server.close_code, pair.server.close_reason) == (4000, "bye")
        assert (await closed_with(pair.client)).code == 4000


# Writing what is held


async def test_sends_of_a_connection_that_hands_messages_over_go_out_at_the_end_of_the_turn() -> (
    None
):
    """Nothing calls recv to write what is held before waiting: the end of the turn does."""
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        assert pair.client.deliver_to(Taker())
        writes = count_writes(pair.client)
        for i in range(3):
            await pair.client.send(f"call {i}")
        assert writes == []  # held
        assert [await pair.server.recv() for _ in range(3)] == ["call 0", "call 1", "call 2"]
        assert len(writes) == 1


async def test_the_first_send_after_a_read_of_one_message_writes_at_once() -> None:
    """A peer calling one call at a time: its next call goes out in the send itself, not a
    turn later; the sends after it in the same turn, and those after a read of several
    messages (a pipelined peer's), are held to be written together."""
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        taker = Taker()
        assert pair.client.deliver_to(taker)
        writes = count_writes(pair.client)
        await pair.server.send("reply 0")
        await taker.until(1)
        await pair.client.send("call 1")
        assert len(writes) == 1  # at once
        await pair.client.send("call 2")
        await pair.client.send("call 3")
        assert len(writes) == 1  # held
        assert [await pair.server.recv() for _ in range(3)] == ["call 1", "call 2", "call 3"]
        assert len(writes) == 2
        await pair.server.send("reply 1")  # two messages in one write, so (on loopback) one read
        await pair.server.send("reply 2")
        await taker.until(3)
        await pair.client.send("call 4")
        assert len(writes) == 2  # held: the peer sent several at once
        assert await pair.server.recv() == "call 4"
        assert len(writes) == 3


async def test_replies_made_in_the_receiver_leave_in_one_write_at_the_end_of_the_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    flushes: list[WebSocketsConnection] = []
    flush = WebSocketsConnection.flush

    def counting(self: WebSocketsConnection) -> None:
        flushes.append(self)
        flush(self)

    monkeypatch.setattr(WebSocketsConnection, "flush", counting)
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        server = pair.server
        writes = count_writes(server)
        read_ended: list[int] = []  # how many writes there were when each read ended
        ws = server._ws  # type: ignore[attr-defined]
        data_received = ws.data_received

        def reading(data: bytes) -> None:
            data_received(data)
            read_ended.append(len(writes))

        ws.data_received = reading

        def answer(message: str | bytes) -> None:
            assert first_step(server.send(f"reply to {message}")) is None  # held, not awaited

        assert server.deliver_to(answer)
        for i in range(3):  # one write, so (on loopback) one read
            await pair.client.send(f"call {i}")
        assert [await pair.client.recv() for _ in range(3)] == [
            f"reply to call {i}" for i in range(3)
        ]
        assert read_ended == [1]  # written by the end of the read, not a turn later
        assert len(writes) == 1
        # and no write was scheduled for the end of the turn: the read's end was enough
        assert [end for end in flushes if end is server] == [server]


# The client


async def test_a_clients_replies_reach_their_calls_from_the_read_callback() -> None:
    server = Server()
    server.add_service("/subtract", Subtract, subtract)
    async with (
        serve(server, "127.0.0.1", 0) as running,
        connect(running.url, timeout=scaled(5)) as client,
        asyncio.timeout(scaled(5)),
    ):
        calls = (client.call("/subtract", {"minuend": i, "subtrahend": 1}) for i in range(50))
        replies = await asyncio.gather(*calls)
        assert [reply.difference for reply in replies] == [i - 1 for i in range(50)]
        link = client._link
        assert link is not None
        conn = link.conn
        assert isinstance(conn, WebSocketsConnection)
        assert conn._ws.receive == link.take  # handed over, never queued for recv
        assert len(conn._ws.recv_messages.frames) == 0
