"""Every transport keeps the rules of srvwire.transports.base: one suite, run on each of them.

The WebSocket transport runs on real sockets on 127.0.0.1; the memory one in process. What only
one of them has (abort, binary frames) is tested after the shared suite.
"""

from __future__ import annotations

import ast
import asyncio
import contextlib
import errno
import itertools
import logging
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import picows
import pytest
from websockets.asyncio.client import connect as websockets_connect

import srvwire
import srvwire.transports
from srvwire.transports import get_transport
from srvwire.transports.base import (
    Admitted,
    Answered,
    Connection,
    Handshake,
    Listener,
    Options,
    Transport,
    TransportClosed,
    TransportError,
    WriteTimedOut,
    write_timeout_reason,
)
from srvwire.transports.memory import MemoryConnection, MemoryTransport
from srvwire.transports.picows import PicowsConnection, PicowsTransport
from srvwire.transports.websockets import WebSocketsTransport, _url
from support import run_python, scaled

SCHEMES = {"websockets": "ws", "picows": "ws", "memory": "memory"}

# Enough turns of the event loop for anything that can happen without the peer to happen.
TURNS = 1000


@pytest.fixture(params=["websockets", "picows", "memory"])
def transport(request: pytest.FixtureRequest) -> Transport:
    if request.param == "websockets":
        return WebSocketsTransport()
    if request.param == "picows":
        return PicowsTransport()
    return MemoryTransport()


@pytest.fixture
def memory() -> MemoryTransport:
    return MemoryTransport()


async def turns(count: int = TURNS) -> None:
    """Let the event loop run ``count`` times: what can run without a peer has run by then."""
    for _ in range(count):
        await asyncio.sleep(0)


async def hold(connection: Connection) -> None:
    """A handler that keeps its connection open and never reads."""
    await asyncio.Event().wait()


@dataclass
class Pair:
    client: Connection
    server: Connection
    listener: Listener


@contextlib.asynccontextmanager
async def connected(
    transport: Transport, options: Options | None = None, server_options: Options | None = None
) -> AsyncIterator[Pair]:
    """Listen on 127.0.0.1, connect, and yield both ends; the server end stays open until exit."""
    options = options or Options()
    accepted: asyncio.Queue[Connection] = asyncio.Queue()
    done = asyncio.Event()

    async def handler(connection: Connection) -> None:
        accepted.put_nowait(connection)
        await done.wait()

    listener = await transport.listen(handler, "127.0.0.1", 0, server_options or options)
    try:
        client = await transport.connect(listener.url, options)
        try:
            async with asyncio.timeout(scaled(5)):
                server = await accepted.get()
            yield Pair(client, server, listener)
        finally:
            done.set()
            async with asyncio.timeout(scaled(5)):
                await client.close()
    finally:
        listener.close()
        async with asyncio.timeout(scaled(5)):
            await listener.wait_closed()


async def closed_with(connection: Connection) -> TransportClosed:
    """Receive until the connection ends; fail on any message; return how it ended.

    The connection's ``close_code`` and ``close_reason`` must then say the same.
    """
    with pytest.raises(TransportClosed) as info:
        async with asyncio.timeout(scaled(5)):
            message = await connection.recv()
            pytest.fail(f"received {message!r} where the connection should have ended")
    closed = info.value
    assert (connection.close_code, connection.close_reason) == (closed.code, closed.reason)
    return closed


# Messages


async def test_text_travels_both_ways(transport: Transport) -> None:
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        await pair.client.send("héllo ☃")
        assert await pair.server.recv() == "héllo ☃"
        await pair.server.send("wörld")
        assert await pair.client.recv() == "wörld"


async def test_messages_sent_without_a_pause_arrive_whole_and_in_order(
    transport: Transport,
) -> None:
    # The picows server corks them into one write, and writes at once past 64 KiB.
    sent = [f"small {index}" for index in range(100)] + ["x" * 200_000, "é" * 70_000, "last"]
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):

        async def send_all() -> None:
            for message in sent:
                await pair.server.send(message)

        sending = asyncio.create_task(send_all())
        assert [await pair.client.recv() for _ in sent] == sent
        await sending


async def test_utf8_bytes_are_received_as_text(transport: Transport) -> None:
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        await pair.client.send("héllo ☃".encode())
        assert await pair.server.recv() == "héllo ☃"
        await pair.server.send(b'{"jsonrpc": "2.0"}')
        assert await pair.client.recv() == '{"jsonrpc": "2.0"}'


async def test_messages_arrive_in_order(transport: Transport) -> None:
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        for i in range(500):
            await pair.client.send(f"up {i}")
            await pair.server.send(f"down {i}".encode())
        assert [await pair.server.recv() for _ in range(500)] == [f"up {i}" for i in range(500)]
        assert [await pair.client.recv() for _ in range(500)] == [f"down {i}" for i in range(500)]


async def test_a_receiver_given_gets_every_message_in_order_once(transport: Transport) -> None:
    # Where the transport hands messages over as they arrive (websockets, picows), the ones already
    # received go first; where it does not, recv goes on as before. Either way every message
    # arrives once, in order, and recv says how the connection ended.
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        for i in range(200):
            await pair.server.send(f"before {i}")
        first = await pair.client.recv()  # the others are on their way, or arrived
        taken: list[str | bytes] = []
        all_taken = asyncio.get_running_loop().create_future()

        def receive(message: str | bytes) -> None:
            taken.append(message)
            if len(taken) == 399 and not all_taken.done():
                all_taken.set_result(None)

        delivers = pair.client.deliver_to(receive)
        assert delivers is (transport.name != "memory")
        for i in range(200):
            await pair.server.send(f"after {i}")
        if delivers:
            await all_taken
        else:
            taken.extend([await pair.client.recv() for _ in range(399)])
        expected = [f"before {i}" for i in range(200)] + [f"after {i}" for i in range(200)]
        assert [first, *taken] == expected
        await pair.server.close(4000, "done")
        assert (await closed_with(pair.client)).code == 4000
        assert [first, *taken] == expected  # nothing more


async def test_remote_address_names_the_peer(transport: Transport) -> None:
    async with connected(transport) as pair:
        assert pair.client.remote_address == ("127.0.0.1", pair.listener.port)
        if transport.name == "memory":
            assert pair.server.remote_address == ("memory", 1)
        else:
            host, port = pair.server.remote_address
            assert host == "127.0.0.1"
            assert port not in (0, pair.listener.port)


# Closing


async def test_open_connection_has_no_close_code(transport: Transport) -> None:
    async with connected(transport) as pair:
        for end in (pair.client, pair.server):
            assert end.close_code is None
            assert end.close_reason == ""


async def test_peer_sees_the_close_code_and_reason(transport: Transport) -> None:
    async with connected(transport) as pair:
        await pair.client.close(4000, "done here")
        assert pair.client.close_code == 4000
        assert pair.client.close_reason == "done here"
        closed = await closed_with(pair.server)
        assert (closed.code, closed.reason) == (4000, "done here")
        assert (pair.server.close_code, pair.server.close_reason) == (4000, "done here")
        assert str(pair.server.closed()) == "the connection closed with code 4000 (done here)"


async def test_recv_and_send_raise_once_closed(transport: Transport) -> None:
    async with connected(transport) as pair:
        await pair.server.close(1001, "going away")
        for end in (pair.server, pair.client):
            closed = await closed_with(end)
            assert (closed.code, closed.reason) == (1001, "going away")
            with pytest.raises(TransportClosed) as info:
                await end.send("too late")
            assert (info.value.code, info.value.reason) == (1001, "going away")


async def test_close_is_idempotent(transport: Transport) -> None:
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        await pair.client.close(4001, "first")
        await pair.client.close(4002, "second")
        assert (pair.client.close_code, pair.client.close_reason) == (4001, "first")
        closed = await closed_with(pair.server)
        assert (closed.code, closed.reason) == (4001, "first")


async def test_messages_sent_before_close_arrive_first(transport: Transport) -> None:
    async with connected(transport) as pair:
        for text in ("one", "two", "three"):
            await pair.client.send(text)
        await pair.client.close(1000, "bye")
        async with asyncio.timeout(scaled(5)):
            assert [await pair.server.recv() for _ in range(3)] == ["one", "two", "three"]
        closed = await closed_with(pair.server)
        assert (closed.code, closed.reason, closed.clean) == (1000, "bye", True)


async def test_handler_that_returns_closes_with_1000(transport: Transport) -> None:
    async def handler(connection: Connection) -> None:
        await connection.send("hello and goodbye")

    listener = await transport.listen(handler, "127.0.0.1", 0, Options())
    try:
        client = await transport.connect(listener.url, Options())
        async with asyncio.timeout(scaled(5)):
            assert await client.recv() == "hello and goodbye"
        closed = await closed_with(client)
        assert (closed.code, closed.reason) == (1000, "")
    finally:
        listener.close()
        async with asyncio.timeout(scaled(5)):
            await listener.wait_closed()


async def test_handler_that_raises_closes_with_1011(
    transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    async def handler(connection: Connection) -> None:
        raise RuntimeError("the handler broke")

    listener = await transport.listen(handler, "127.0.0.1", 0, Options())
    try:
        client = await transport.connect(listener.url, Options())
        closed = await closed_with(client)
        assert (closed.code, closed.reason) == (1011, "")
    finally:
        listener.close()
        async with asyncio.timeout(scaled(5)):
            await listener.wait_closed()
    [record] = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert record.getMessage() == "connection handler failed"
    assert record.exc_info is not None
    assert str(record.exc_info[1]) == "the handler broke"


# Limits


async def test_message_at_the_size_limit_passes(transport: Transport) -> None:
    limit = Options(max_message_size=1000)
    async with connected(transport, limit) as pair, asyncio.timeout(scaled(5)):
        await pair.client.send("é" * 500)  # 1000 bytes in UTF-8
        assert await pair.server.recv() == "é" * 500
        await pair.server.send(b"x" * 1000)
        assert await pair.client.recv() == "x" * 1000


async def test_message_over_the_size_limit_closes_with_1009(transport: Transport) -> None:
    limit = Options(max_message_size=1000)
    async with connected(transport, limit) as pair:
        await pair.client.send("before")
        await pair.client.send("é" * 500 + "x")  # 501 characters, 1001 bytes
        async with asyncio.timeout(scaled(5)):
            assert await pair.server.recv() == "before"
        for end in (pair.server, pair.client):
            closed = await closed_with(end)
            assert closed.code == 1009
            # The reason names the side and the setting that refused the message.
            assert closed.reason == (
                "over the server's max_message_size (message of 1001 bytes, limit 1000 bytes)"
                if transport.name in ("memory", "picows")
                else "over the server's max_message_size (frame with 1001 bytes exceeds limit of "
                "1000 bytes)"
            )


async def test_the_receivers_size_limit_counts(transport: Transport) -> None:
    small = Options(max_message_size=1000)
    async with connected(transport, options=Options(), server_options=small) as pair:
        async with asyncio.timeout(scaled(5)):
            await pair.server.send("x" * 5000)
            assert await pair.client.recv() == "x" * 5000
        await pair.client.send("x" * 1001)
        assert (await closed_with(pair.server)).code == 1009
        assert (await closed_with(pair.client)).code == 1009


async def test_bytes_that_are_not_utf8_close_with_1007(transport: Transport) -> None:
    async with connected(transport) as pair:
        await pair.client.send(b"\xff not text")
        for end in (pair.server, pair.client):
            closed = await closed_with(end)
            assert (closed.code, closed.reason) == (1007, "invalid start byte at position 0")


# Flow control


@pytest.mark.parametrize("from_server", [False, True], ids=["client sends", "server sends"])
async def test_send_waits_while_the_peer_does_not_read(
    transport: Transport, from_server: bool
) -> None:
    # 96 MiB is more than any buffer between the two ends can hold (socket buffers, the
    # receiver's queue of 16 messages, the memory transport's 64 KiB), so only reading it
    # lets the sender finish. Messages of 1 MiB are large: each end writes them apart from
    # their header, and they count against the budget all the same.
    size, count = 2**20, 96
    filler = "x" * size
    async with connected(transport) as pair:
        sender_end, receiver = (
            (pair.server, pair.client) if from_server else (pair.client, pair.server)
        )
        sent = 0

        async def send_all() -> None:
            nonlocal sent
            for i in range(count):
                await sender_end.send(f"{i:04}" + filler[4:])
                sent += 1

        sender = asyncio.create_task(send_all())
        try:
            await turns()
            assert not sender.done()
            assert sent < count
            assert sender_end.congested
            async with asyncio.timeout(scaled(20)):
                for i in range(count):
                    message = await receiver.recv()
                    assert (message[:4], len(message)) == (f"{i:04}", size)
                await sender
            assert sent == count
        finally:
            sender.cancel()


async def press(connection: Connection, size: int = 2**16) -> None:
    """Send from ``connection`` forever, numbered, as a server whose client keeps calling does:
    each send waits while the connection is congested. A peer that reads only what its
    transport buffers on its own then keeps it congested for good."""
    filler = "x" * size
    for i in itertools.count():
        await connection.send(f"{i:06}" + filler[6:])


async def congested(connection: Connection) -> None:
    """Return once ``connection`` is congested: a state the sends reach turn by turn, as the
    peer's transport fills up, with no event to await; each turn lets both ends run."""
    async with asyncio.timeout(scaled(10)):
        while not connection.congested:  # noqa: ASYNC110
            await asyncio.sleep(0)


async def test_past_its_budget_a_connection_is_congested_until_the_peer_reads(
    transport: Transport,
) -> None:
    budget = Options(max_queued_bytes=2**16)
    received: list[str] = []
    reader: asyncio.Task[None] | None = None
    try:
        async with connected(transport, server_options=budget) as pair:
            assert not pair.server.congested
            pressing = asyncio.create_task(press(pair.server))
            try:
                await congested(pair.server)
            finally:
                pressing.cancel()
            writable = asyncio.create_task(pair.server.writable())
            await turns()
            assert pair.server.congested == (not writable.done())

            async def read() -> None:  # until the end: the closing handshake comes after it all
                with contextlib.suppress(TransportClosed):
                    while True:
                        received.append(str(await pair.client.recv())[:6])

            reader = asyncio.create_task(read())
            async with asyncio.timeout(scaled(10)):
                await writable
            assert not pair.server.congested
    finally:
        if reader is not None:
            reader.cancel()
    assert received == [f"{i:06}" for i in range(len(received))]


async def test_a_peer_that_does_not_read_is_closed_after_the_write_timeout(
    transport: Transport,
) -> None:
    # The side that waits closes at once, with 1008; the peer, which did not read, sees the
    # connection drop after whatever reached it.
    timeout = scaled(0.2)
    budget = Options(max_queued_bytes=2**16, write_timeout=timeout)
    async with connected(transport, server_options=budget) as pair:
        pressing = asyncio.create_task(press(pair.server))
        with pytest.raises(WriteTimedOut) as info:
            async with asyncio.timeout(scaled(20)):
                await pair.server.recv()
        reason = write_timeout_reason(timeout)
        assert (info.value.code, info.value.reason, info.value.timeout) == (1008, reason, timeout)
        assert (pair.server.close_code, pair.server.close_reason) == (1008, reason)
        with pytest.raises(WriteTimedOut):
            await pair.server.send("more")
        with pytest.raises(TransportClosed):
            async with asyncio.timeout(scaled(10)):
                await pressing
        with pytest.raises(TransportClosed) as peer:
            async with asyncio.timeout(scaled(10)):
                while True:
                    await pair.client.recv()
        assert peer.value.code is None


# Listening and connecting


async def test_port_0_binds_a_real_port(transport: Transport) -> None:
    listener = await transport.listen(hold, "127.0.0.1", 0, Options())
    try:
        assert listener.host == "127.0.0.1"
        assert listener.port > 0
        assert listener.url == f"{SCHEMES[transport.name]}://127.0.0.1:{listener.port}"
    finally:
        listener.close()
        await listener.wait_closed()


async def test_the_url_keeps_the_host_name_it_was_given(transport: Transport) -> None:
    listener = await transport.listen(hold, "localhost", 0, Options())
    try:
        assert listener.host == "localhost"
        assert listener.url == f"{SCHEMES[transport.name]}://localhost:{listener.port}"
    finally:
        listener.close()
        await listener.wait_closed()


async def test_listen_on_a_taken_port_raises_oserror(transport: Transport) -> None:
    first = await transport.listen(hold, "127.0.0.1", 0, Options())
    try:
        with pytest.raises(OSError) as info:
            await transport.listen(hold, "127.0.0.1", first.port, Options())
        assert info.value.errno == errno.EADDRINUSE
    finally:
        first.close()
        await first.wait_closed()


async def test_connect_where_nothing_listens_raises_transport_error(transport: Transport) -> None:
    listener = await transport.listen(hold, "127.0.0.1", 0, Options())
    listener.close()
    async with asyncio.timeout(scaled(5)):
        await listener.wait_closed()
        with pytest.raises(TransportError) as info:
            await transport.connect(listener.url, Options())
    if transport.name == "memory":
        assert str(info.value) == f"nothing listens at {listener.url}"
    else:
        # The library's text, as it is: users read it after "cannot connect to {url}: ".
        assert isinstance(info.value.__cause__, ConnectionRefusedError)
        assert str(info.value) == str(info.value.__cause__)


async def test_connect_to_a_bad_url_raises_transport_error(transport: Transport) -> None:
    with pytest.raises(TransportError) as info:
        await transport.connect("http://127.0.0.1:1", Options())
    assert (
        str(info.value)
        == {
            "websockets": "http://127.0.0.1:1 isn't a valid URI: scheme isn't ws or wss",
            "picows": "not a WebSocket URL: 'http://127.0.0.1:1' (the scheme must be ws or wss)",
            "memory": "not a memory URL: 'http://127.0.0.1:1' (the scheme is not memory)",
        }[transport.name]
    )


async def test_closed_listener_refuses_new_connections_but_keeps_open_ones(
    transport: Transport,
) -> None:
    async with connected(transport) as pair:
        pair.listener.close()
        with pytest.raises(TransportError):
            async with asyncio.timeout(scaled(5)):
                await transport.connect(pair.listener.url, Options())
        waiting = asyncio.create_task(pair.listener.wait_closed())
        try:
            async with asyncio.timeout(scaled(5)):
                await pair.client.send("still there?")
                assert await pair.server.recv() == "still there?"
                await pair.server.send("yes")
                assert await pair.client.recv() == "yes"
            await turns()
            assert not waiting.done(), "wait_closed returned while a handler still runs"
        finally:
            waiting.cancel()


@pytest.mark.parametrize(
    ("name", "url", "message"),
    [
        (
            "websockets",
            "http://localhost:1",
            "not a WebSocket URL: 'http://localhost:1' "
            "(http://localhost:1 isn't a valid URI: scheme isn't ws or wss)",
        ),
        (
            "websockets",
            "ws://:1",
            "not a WebSocket URL: 'ws://:1' (ws://:1 isn't a valid URI: hostname isn't provided)",
        ),
        (
            "memory",
            "ws://localhost:1",
            "not a memory URL: 'ws://localhost:1' (the scheme is not memory)",
        ),
        ("memory", "memory://localhost", "not a memory URL: 'memory://localhost' (no port)"),
        ("memory", "memory://:1", "not a memory URL: 'memory://:1' (no host)"),
    ],
)
def test_check_url_refuses_a_bad_url(name: str, url: str, message: str) -> None:
    transport = WebSocketsTransport() if name == "websockets" else MemoryTransport()
    with pytest.raises(ValueError) as info:
        transport.check_url(url)
    assert str(info.value) == message


async def test_check_url_accepts_the_listeners_url(transport: Transport) -> None:
    listener = await transport.listen(hold, "127.0.0.1", 0, Options())
    listener.close()
    await listener.wait_closed()
    transport.check_url(listener.url)
    transport.check_url(listener.url + "/")


def test_websocket_url_brackets_an_ipv6_host() -> None:
    assert _url("::1", 8765) == "ws://[::1]:8765"
    assert _url("127.0.0.1", 8765) == "ws://127.0.0.1:8765"


# How a connection ended, told in words


@pytest.mark.parametrize(
    ("code", "reason", "text", "clean"),
    [
        (None, "", "the connection dropped (no close frame)", False),
        (1006, "", "the connection dropped (no close frame)", False),
        (1000, "", "the connection closed with code 1000", True),
        (1001, "going away", "the connection closed with code 1001 (going away)", True),
        (1011, "", "the connection closed with code 1011", False),
    ],
)
def test_transport_closed_says_how_the_connection_ended(
    code: int | None, reason: str, text: str, clean: bool
) -> None:
    closed = TransportClosed(code, reason)
    assert str(closed) == text
    assert closed.clean is clean
    assert (closed.code, closed.reason) == (code, reason)


# Choosing a transport


def test_get_transport_returns_an_instance_as_it_is() -> None:
    memory = MemoryTransport()
    assert get_transport(memory) is memory


def test_get_transport_makes_the_websocket_transport() -> None:
    transport = get_transport("websockets")
    assert isinstance(transport, WebSocketsTransport)
    assert transport.name == "websockets"


def test_get_transport_wants_a_memory_transport_instance() -> None:
    with pytest.raises(ValueError) as info:
        get_transport("memory")
    assert str(info.value) == (
        "the memory transport is a world shared by a server and its clients: "
        "pass a MemoryTransport() instance, the same one to both, not the name 'memory'"
    )


def test_get_transport_refuses_an_unknown_name() -> None:
    with pytest.raises(ValueError) as info:
        get_transport("pigeons")
    assert str(info.value) == (
        "unknown transport 'pigeons': use 'websockets', 'picows' or a Transport instance, "
        "such as MemoryTransport()"
    )


def imported_modules(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if isinstance(node, ast.ImportFrom):
        return ["." * node.level + (node.module or "")]
    return []


def test_the_seam_does_not_load_the_websocket_transport() -> None:
    # get_transport imports it inside the function, when it is asked for.
    for path in sorted(Path(srvwire.transports.__file__).parent.glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            for name in imported_modules(node):
                assert name not in ("srvwire.transports.websockets", ".websockets"), path.name


# The memory transport only


async def test_abort_drops_the_connection_without_a_close_code(memory: MemoryTransport) -> None:
    async with connected(memory) as pair:
        assert isinstance(pair.client, MemoryConnection)
        await pair.client.send("last words")
        pair.client.abort()
        pair.client.abort()
        async with asyncio.timeout(scaled(5)):
            assert await pair.server.recv() == "last words"
        for end in (pair.server, pair.client):
            closed = await closed_with(end)
            assert (closed.code, closed.reason) == (None, "")
            assert str(closed) == "the connection dropped (no close frame)"
            assert end.close_code is None


async def test_memory_send_waits_past_the_high_water_mark_until_the_low_one() -> None:
    transport = MemoryTransport(high_water=1000)
    async with connected(transport) as pair:
        for _ in range(10):  # 1000 bytes: at the mark, not past it
            await pair.client.send("x" * 100)
        sender = asyncio.create_task(pair.client.send("x" * 100))
        try:
            await turns()
            assert not sender.done()
            for _ in range(8):  # 300 bytes left: above the low-water mark of 250
                await pair.server.recv()
            await turns()
            assert not sender.done()
            await pair.server.recv()  # 200 bytes left
            async with asyncio.timeout(scaled(5)):
                await sender
        finally:
            sender.cancel()


async def test_memory_send_queues_nothing_while_congested() -> None:
    # What a send waits for: once past the budget, the next message stays with its sender
    # until the peer has read down to the low mark (a quarter of the budget).
    budget = Options(max_queued_bytes=1000)
    async with connected(MemoryTransport(), server_options=budget) as pair:
        first = asyncio.create_task(pair.server.send("x" * 1500))
        late = asyncio.create_task(pair.server.send("late"))
        try:
            await turns()
            assert pair.server.congested and not first.done() and not late.done()
            assert isinstance(pair.client, MemoryConnection)
            assert pair.client._unread == 1500  # "late" is not queued
            assert await pair.client.recv() == "x" * 1500
            async with asyncio.timeout(scaled(5)):
                await asyncio.gather(first, late)
            assert await pair.client.recv() == "late"
        finally:
            first.cancel()
            late.cancel()


async def test_memory_send_waiting_for_the_peer_raises_when_the_connection_ends() -> None:
    transport = MemoryTransport(high_water=10)
    async with connected(transport) as pair:
        sender = asyncio.create_task(pair.client.send("x" * 100))
        try:
            await turns()
            assert not sender.done()
            await pair.server.close(1001, "going away")
            with pytest.raises(TransportClosed) as info:
                async with asyncio.timeout(scaled(5)):
                    await sender
            assert (info.value.code, info.value.reason) == (1001, "going away")
        finally:
            sender.cancel()


async def test_memory_refuses_two_receivers_at_once(memory: MemoryTransport) -> None:
    async with connected(memory) as pair:
        first = asyncio.create_task(pair.client.recv())
        try:
            await turns(1)
            with pytest.raises(RuntimeError) as info:
                await pair.client.recv()
            assert str(info.value) == "another coroutine is already waiting for the next message"
            await pair.server.send("for the first")
            async with asyncio.timeout(scaled(5)):
                assert await first == "for the first"
        finally:
            first.cancel()


async def test_memory_ports_count_from_1_and_a_taken_one_is_refused(
    memory: MemoryTransport,
) -> None:
    first = await memory.listen(hold, "localhost", 0, Options())
    second = await memory.listen(hold, "localhost", 0, Options())
    ipv6 = await memory.listen(hold, "::1", 0, Options())
    assert [first.url, second.url, ipv6.url] == [
        "memory://localhost:1",
        "memory://localhost:2",
        "memory://[::1]:3",
    ]
    with pytest.raises(OSError) as info:
        await memory.listen(hold, "localhost", 2, Options())
    assert info.value.errno == errno.EADDRINUSE
    assert str(info.value) == f"[Errno {errno.EADDRINUSE}] memory://localhost:2 is already in use"
    for listener in (first, second, ipv6):
        listener.close()
        await listener.wait_closed()


async def test_memory_transports_are_separate_worlds(memory: MemoryTransport) -> None:
    listener = await memory.listen(hold, "localhost", 0, Options())
    try:
        with pytest.raises(TransportError) as info:
            await MemoryTransport().connect(listener.url, Options())
        assert str(info.value) == "nothing listens at memory://localhost:1"
    finally:
        listener.close()
        await listener.wait_closed()


async def test_memory_listener_waits_for_its_handlers(memory: MemoryTransport) -> None:
    release = asyncio.Event()

    async def handler(connection: Connection) -> None:
        await release.wait()

    listener = await memory.listen(handler, "localhost", 0, Options())
    client = await memory.connect(listener.url, Options())
    listener.close()
    waiting = asyncio.create_task(listener.wait_closed())
    try:
        await turns()
        assert not waiting.done()
        release.set()
        async with asyncio.timeout(scaled(5)):
            await waiting
        assert (await closed_with(client)).code == 1000
    finally:
        waiting.cancel()


async def test_with_keepalive_a_peer_that_does_not_read_is_closed_after_a_ping_period() -> None:
    # No write timeout, but keepalive: websockets' own ping deadline cannot start while the
    # buffer does not drain, so the interval plus the timeout bounds the congestion instead.
    interval, timeout = scaled(0.1), scaled(0.1)
    options = Options(max_queued_bytes=2**16, ping_interval=interval, ping_timeout=timeout)
    async with connected(WebSocketsTransport(), server_options=options) as pair:
        pressing = asyncio.create_task(press(pair.server))
        with pytest.raises(WriteTimedOut) as info:
            async with asyncio.timeout(scaled(20)):
                await pair.server.recv()
        assert info.value.timeout == interval + timeout
        with pytest.raises(TransportClosed):
            async with asyncio.timeout(scaled(10)):
                await pressing
        with pytest.raises(TransportClosed):
            async with asyncio.timeout(scaled(10)):
                while True:
                    await pair.client.recv()


# Real WebSockets: what the websockets and picows transports both do with a raw peer


@pytest.fixture(params=["websockets", "picows"])
def real(request: pytest.FixtureRequest) -> Transport:
    """Each WebSocket transport: they speak the same wire, so a raw peer is the same for both."""
    return get_transport(request.param)


@contextlib.asynccontextmanager
async def listening(
    transport: Transport, options: Options | None = None, **listen: Any
) -> AsyncIterator[tuple[Listener, asyncio.Queue[Connection]]]:
    """Listen on 127.0.0.1 and yield the listener and a queue of the connections it accepted,
    each held open until exit."""
    accepted: asyncio.Queue[Connection] = asyncio.Queue()
    done = asyncio.Event()

    async def handler(connection: Connection) -> None:
        accepted.put_nowait(connection)
        await done.wait()

    listener = await transport.listen(handler, "127.0.0.1", 0, options or Options(), **listen)
    try:
        yield listener, accepted
    finally:
        done.set()
        listener.close()
        async with asyncio.timeout(scaled(5)):
            await listener.wait_closed()


async def test_messages_sent_in_one_turn_go_out_in_one_write() -> None:
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.server)
        for i in range(50):
            await pair.server.send(f"reply {i}".encode())
        assert writes == []  # held until the loop comes round
        assert [await pair.client.recv() for _ in range(50)] == [f"reply {i}" for i in range(50)]
        assert len(writes) == 1
        await pair.server.send(b"later")  # a later turn: a write of its own
        assert await pair.client.recv() == "later"
        assert len(writes) == 2


async def numbered_messages_arrive_in_order(pair: Pair, sizes: list[int]) -> None:
    """Send a message of each size (and a 4-digit number before it) from the client; check
    that the server receives each whole, in order."""
    for i, size in enumerate(sizes):
        await pair.client.send(f"{i:04d}".encode() + b"x" * size)
    received = [await pair.server.recv() for _ in sizes]
    assert [m[:4] for m in received] == [f"{i:04d}" for i in range(len(sizes))]
    assert [len(m) for m in received] == [size + 4 for size in sizes]


def count_writes(connection: Connection) -> list[bytes]:
    """The bytes of every socket write ``connection`` makes from now on, in order.

    On picows, only the writes srvwire makes itself (what it held): picows' own ``send``
    writes through a reference it took when it connected."""
    ws: Any = connection._ws  # type: ignore[attr-defined]
    socket = ws.underlying_transport if isinstance(connection, PicowsConnection) else ws.transport
    writes: list[bytes] = []
    write = socket.write

    def counting(data: bytes) -> None:
        writes.append(bytes(data))
        write(data)

    socket.write = counting
    return writes


async def test_what_is_held_is_written_when_it_reaches_the_cork_limit() -> None:
    """A pipelined peer gets the first replies while later ones are still being made."""
    from srvwire.transports.websockets import CORK_LIMIT

    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.server)
        size = CORK_LIMIT // 4
        for i in range(10):  # two and a half limits' worth, in one turn
            await pair.server.send(f"{i:04d}".encode() + b"x" * (size - 4))
        assert len(writes) == 2  # at each limit reached, before the turn ended
        assert all(CORK_LIMIT <= len(data) < CORK_LIMIT + 64 for data in writes)
        received = [await pair.client.recv() for _ in range(10)]
        assert [m[:4] for m in received] == [f"{i:04d}" for i in range(10)]
        assert len(writes) == 3  # the rest at the end of the turn


async def test_what_is_held_is_written_when_the_reader_is_about_to_wait() -> None:
    """The replies to every message of one read leave together, without waiting for the loop
    to come round."""
    from srvwire.inline import Pending, finish, first_step

    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        for i in range(3):
            await pair.client.send(f"call {i}")
        assert [await pair.server.recv() for _ in range(3)] == ["call 0", "call 1", "call 2"]
        writes = count_writes(pair.server)
        for i in range(3):
            await pair.server.send(f"reply {i}")
        assert writes == []
        waiting = first_step(pair.server.recv())  # nothing left to read: it waits
        assert isinstance(waiting, Pending)
        assert len(writes) == 1  # written before it did
        assert [await pair.client.recv() for _ in range(3)] == [f"reply {i}" for i in range(3)]
        await pair.client.send("next")
        assert await finish(waiting) == "next"
        assert len(writes) == 1


async def test_text_is_counted_in_bytes_against_the_cork_limit() -> None:
    """A text message is held or written by its UTF-8 size, not its number of characters."""
    from srvwire.transports.websockets import CORK_LIMIT

    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.server)
        text = "é" * (CORK_LIMIT * 3 // 4)  # fewer characters than the limit, more bytes
        await pair.server.send(text)
        assert len(writes) == 1  # written through at once, not held for the end of the turn
        assert await pair.client.recv() == text


async def test_a_server_frames_what_it_holds_as_websockets_frames_it() -> None:
    """The bytes a server writes for held messages of every header length are the frames
    websockets' own ``send_text`` writes; neither end calls ``send_text`` for them."""
    from websockets.frames import Frame, Opcode
    from websockets.protocol import Protocol

    from srvwire.transports.websockets import CORK_LIMIT

    framed: list[Any] = []
    send_text = Protocol.send_text

    def recording(self: Protocol, data: bytes, fin: bool = True) -> None:
        framed.append(self.side)
        send_text(self, data, fin)

    lengths = [0, 1, 125, 126, 127, 1000, CORK_LIMIT - 1, CORK_LIMIT]
    messages = [f"{n:05d}".encode()[:n] + b"x" * max(0, n - 5) for n in lengths]
    messages.append("é→€".encode() * 100)  # a str is sent as its UTF-8 bytes
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        Protocol.send_text = recording  # type: ignore[method-assign]
        try:
            writes = count_writes(pair.server)
            for message in messages:
                await pair.server.send(message)
                await pair.server.send("é→€" * 100)
            await pair.client.send("a call")
        finally:
            Protocol.send_text = send_text  # type: ignore[method-assign]
        expected = []
        for message in messages:
            expected.append(Frame(Opcode.TEXT, message).serialize(mask=False))
            expected.append(Frame(Opcode.TEXT, "é→€".encode() * 100).serialize(mask=False))
        received = [await pair.client.recv() for _ in range(2 * len(messages))]
        assert b"".join(writes) == b"".join(expected)
        assert received[::2] == [m.decode() for m in messages]
        assert received[1::2] == ["é→€" * 100] * len(messages)
        assert framed == []  # the client frames its own too (see the test below)
        assert await pair.server.recv() == "a call"


async def test_a_client_frames_what_it_holds_masked_with_a_key_each() -> None:
    """A websockets client's held messages are framed and masked here, each with a fresh key;
    the websockets server, which fails a client's frame that is not masked, reads them all."""
    from srvwire.transports.websockets import CORK_LIMIT

    lengths = [0, 1, 125, 126, 127, 1000, CORK_LIMIT // 2]
    messages = [f"{n:05d}".encode()[:n] + b"x" * max(0, n - 5) for n in lengths]
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.client)
        for message in messages:  # in one turn: held, and written past the limit
            await pair.client.send(message)
        await pair.client.send("é→€" * 100)  # a str is framed as its UTF-8 bytes
        received = [await pair.server.recv() for _ in range(len(messages) + 1)]
        assert received == [m.decode() for m in messages] + ["é→€" * 100]
        frames = [frame for data in writes for frame in client_frames(data)]
        assert [payload for _, payload in frames] == [*messages, "é→€".encode() * 100]
        assert len({key for key, _ in frames}) == len(frames)  # a key each


def writes_of(connection: Connection) -> list[Any]:
    """What ``connection`` hands its socket's transport to write from now on: the objects
    themselves, not copies of them."""
    ws: Any = connection._ws  # type: ignore[attr-defined]
    written: list[Any] = []
    write = ws.transport.write

    def recording(data: Any) -> None:
        written.append(data)
        write(data)

    ws.transport.write = recording
    return written


def frames_in(data: bytes, mask: bool) -> list[Any]:
    """The frames websockets' own parser reads from ``data``, which they fill exactly."""
    from websockets.frames import Frame
    from websockets.streams import StreamReader

    reader = StreamReader()
    reader.feed_data(data)
    reader.feed_eof()
    frames = []
    while reader.buffer:
        parsing = Frame.parse(reader.read_exact, mask=mask)
        with pytest.raises(StopIteration) as parsed:
            next(parsing)
        frames.append(parsed.value.value)
    return frames


@pytest.mark.parametrize("tls", [False, True])
async def test_a_large_message_is_written_apart_from_its_frame_header_uncopied(tls: bool) -> None:
    """From LARGE_MESSAGE bytes, a server writes its frame's header and then the message itself
    (a view of the very bytes object: no copy of it is made on the way to the socket), and a
    client the header with its key and then the payload masked; below it, one write, header and
    payload joined. Each end reads what the other sent, over TCP and TLS, and the bytes are the
    frames websockets' parser reads."""
    from srvwire.transports.websockets import LARGE_MESSAGE
    from support import tls_on_localhost

    transport = WebSocketsTransport()
    server_ssl, client_ssl = tls_on_localhost(tls)
    options = Options(max_message_size=2**22)
    sizes = [LARGE_MESSAGE - 1, LARGE_MESSAGE, 3 * 2**20 + 5]
    messages = [f"{size:09d}".encode() + b"x" * (size - 9) for size in sizes]
    async with listening(transport, options, ssl=server_ssl) as (listener, accepted):
        client = await transport.connect(listener.url, options, ssl=client_ssl)
        try:
            async with asyncio.timeout(scaled(10)):
                server = await accepted.get()
                for sender, receiver, masked in [(server, client, False), (client, server, True)]:
                    written = writes_of(sender)
                    for message in messages:
                        await sender.send(message)
                        assert await receiver.recv() == message.decode()
                    assert [len(data) for data in written] == [
                        4 + 4 * masked + sizes[0],
                        10 + 4 * masked,
                        sizes[1],
                        10 + 4 * masked,
                        sizes[2],
                    ]
                    if not masked:  # the server's payloads are the messages, not copies
                        assert [type(written[i]) for i in (2, 4)] == [memoryview, memoryview]
                        assert written[2].obj is messages[1] and written[4].obj is messages[2]
                    frames = frames_in(b"".join(bytes(data) for data in written), masked)
                    assert [bytes(frame.data) for frame in frames] == messages
                    assert all(frame.fin and frame.opcode.name == "TEXT" for frame in frames)
        finally:
            async with asyncio.timeout(scaled(5)):
                await client.close()


@pytest.mark.parametrize("side", ["client", "server"])
async def test_with_compression_on_each_end_leaves_its_frames_to_websockets(side: str) -> None:
    deflate = Options(compression="deflate")
    async with connected(WebSocketsTransport(), deflate) as pair, asyncio.timeout(scaled(5)):
        sender, receiver = (
            (pair.client, pair.server) if side == "client" else (pair.server, pair.client)
        )
        writes = count_writes(sender)
        for i in range(3):
            await sender.send(f"message {i} " + "x" * 1000)
        assert [await receiver.recv() for _ in range(3)] == [
            f"message {i} " + "x" * 1000 for i in range(3)
        ]
        assert 0 < len(b"".join(writes)) < 1000  # compressed, by websockets


async def test_messages_past_the_cork_limit_write_through_in_order() -> None:
    from srvwire.transports.websockets import CORK_LIMIT

    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        sizes = [CORK_LIMIT // 4, CORK_LIMIT * 2, 10, CORK_LIMIT + 1, CORK_LIMIT // 2] * 3
        await numbered_messages_arrive_in_order(pair, sizes)  # held ones and others, mixed


async def test_a_message_held_when_the_connection_closes_is_delivered_first() -> None:
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        await pair.server.send(b"last words")
        await pair.server.close(1000, "done")
        assert await pair.client.recv() == "last words"
        closed = await closed_with(pair.client)
        assert (closed.code, closed.reason) == (1000, "done")


async def test_held_messages_do_not_escape_backpressure() -> None:
    """A peer that does not read stops the sender once its socket's buffer is full, held
    messages or not: some send waits before 64 MiB went out, and goes on once the peer reads."""
    from srvwire.inline import Pending, finish, first_step

    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(20)):
        message = b"x" * 1000
        count = 0
        while True:
            count += 1
            step = first_step(pair.server.send(message))
            if isinstance(step, Pending):
                break
            assert count * len(message) < 64 * 2**20, "no send ever waited for the peer"

        async def read_all() -> int:
            for _ in range(count):
                assert len(await pair.client.recv()) == len(message)
            return count

        reading = asyncio.create_task(read_all())
        await finish(step)
        assert await reading == count


async def test_a_binary_frame_is_received_as_bytes(real: Transport) -> None:
    async with (
        listening(real) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        await ws.send(b"\x00\xff binary")
        assert await (await accepted.get()).recv() == b"\x00\xff binary"


async def test_fragments_are_joined_into_one_message(real: Transport) -> None:
    async with (
        listening(real) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        await ws.send(["hé", "llo", " ☃"])  # one text message in three frames
        await ws.send([b"\x00", b"\xff"])  # one binary message in two
        await ws.send("after")
        server = await accepted.get()
        assert [await server.recv() for _ in range(3)] == ["héllo ☃", b"\x00\xff", "after"]


async def test_fragments_over_the_size_limit_close_with_1009(real: Transport) -> None:
    async with (
        listening(real, Options(max_message_size=10)) as (listener, accepted),
        asyncio.timeout(scaled(5)),
        websockets_connect(listener.url, open_timeout=None) as ws,
    ):
        await ws.send("small")
        await ws.send(["x" * 6, "x" * 6])  # every frame is under the limit, the message is not
        server = await accepted.get()
        assert await server.recv() == "small"
        assert (await closed_with(server)).code == 1009
        await ws.wait_closed()
        assert ws.close_code == 1009


async def test_no_pong_within_the_timeout_closes_with_1011(real: Transport) -> None:
    # A peer that never answers pings: picows' client with its automatic pong turned off.
    keepalive = Options(ping_interval=scaled(0.05), ping_timeout=scaled(0.05))
    async with listening(real, keepalive) as (listener, accepted):
        silent, _ = await picows.ws_connect(picows.WSListener, listener.url, enable_auto_pong=False)
        try:
            async with asyncio.timeout(scaled(5)):
                server = await accepted.get()
            closed = await closed_with(server)
            assert (closed.code, closed.reason) == (1011, "keepalive ping timeout")
        finally:
            silent.disconnect()


async def test_picows_ends_a_peer_that_neither_reads_nor_answers_pings_with_1011() -> None:
    # A congested one ends by the write timeout first (a ping period): the budget's tests.
    keepalive = Options(ping_interval=scaled(0.05), ping_timeout=scaled(0.05))
    async with listening(get_transport("picows"), keepalive) as (listener, accepted):
        transport, _ = await picows.ws_connect(
            picows.WSListener, listener.url, enable_auto_pong=False
        )
        transport.underlying_transport.pause_reading()  # and it reads nothing either
        try:
            async with asyncio.timeout(scaled(5)):
                server = await accepted.get()
                closed = await closed_with(server)
            assert (closed.code, closed.reason) == (1011, "keepalive ping timeout")
        finally:
            transport.disconnect(False)


class Ponger(picows.WSListener):  # type: ignore[misc]
    """A raw peer that answers pings by hand and says when it has answered three."""

    def __init__(self) -> None:
        super().__init__()
        self.pings = 0
        self.three = asyncio.get_running_loop().create_future()

    def on_ws_frame(self, transport: picows.WSTransport, frame: picows.WSFrame) -> None:
        if frame.msg_type == picows.WSMsgType.PING:
            transport.send_pong(frame.get_payload_as_bytes())
            self.pings += 1
            if self.pings == 3 and not self.three.done():
                self.three.set_result(None)


async def test_pings_go_on_while_pongs_come_back(real: Transport) -> None:
    keepalive = Options(ping_interval=scaled(0.02), ping_timeout=scaled(1))
    async with listening(real, keepalive) as (listener, accepted):
        transport, ponger = await picows.ws_connect(Ponger, listener.url, enable_auto_pong=False)
        try:
            async with asyncio.timeout(scaled(5)):
                server = await accepted.get()
                await ponger.three  # a ping after each pong: the keepalive goes on
                await server.send("still open")
            assert server.close_code is None
        finally:
            transport.disconnect()


@pytest.mark.parametrize(("server", "client"), [("websockets", "picows"), ("picows", "websockets")])
async def test_each_websocket_transport_talks_to_the_other(server: str, client: str) -> None:
    async with listening(get_transport(server)) as (listener, accepted):
        near = await get_transport(client).connect(listener.url, Options())
        async with asyncio.timeout(scaled(5)):
            far = await accepted.get()
            await near.send("ping ☃")
            assert await far.recv() == "ping ☃"
            await far.send(b'{"pong": 1}')
            assert await near.recv() == '{"pong": 1}'
            await near.close(4000, "done")
        assert (await closed_with(far)).code == 4000
        assert (near.close_code, near.close_reason) == (4000, "done")


async def test_picows_refuses_a_gate_that_waits_with_500(caplog: pytest.LogCaptureFixture) -> None:
    async def gate(handshake: Handshake) -> Admitted | Answered:
        await asyncio.sleep(0)  # an authenticator that asks a database, say
        return Admitted()

    async with listening(get_transport("picows"), gate=gate) as (listener, _):
        with pytest.raises(TransportError) as info:
            await get_transport("picows").connect(listener.url, Options())
    assert str(info.value) == (
        "the server refused the connection: HTTP 500: the server failed to check the credentials"
    )
    [record] = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert "its check waited for I/O" in record.getMessage()


async def test_picows_refuses_compression_on_both_ends() -> None:
    transport = get_transport("picows")
    deflate = Options(compression="deflate")
    message = (
        "the picows transport has no compression: pass compression=None, "
        "or use the websockets transport"
    )
    with pytest.raises(ValueError) as listening_info:
        await transport.listen(hold, "127.0.0.1", 0, deflate)
    with pytest.raises(ValueError) as connecting_info:
        await transport.connect("ws://127.0.0.1:1", deflate)
    assert str(listening_info.value) == str(connecting_info.value) == message


def test_get_transport_makes_the_picows_transport() -> None:
    transport = get_transport("picows")
    assert isinstance(transport, PicowsTransport)
    assert transport.name == "picows"


def test_a_missing_picows_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "picows", None)  # what importing it does when it is absent
    monkeypatch.delitem(sys.modules, "srvwire.transports.picows")
    with pytest.raises(ValueError) as info:
        get_transport("picows")
    assert str(info.value) == (
        "the picows transport needs the picows package: pip install 'srvwire[fast]'"
    )


async def test_a_closed_picows_servers_protocol_no_longer_refers_to_itself() -> None:
    """The methods the protocol puts on itself after its first read are bound to it; once the
    connection is lost they are gone, so it is freed with its last owner, not by the cycle
    collector."""
    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        protocol = pair.server._ws.underlying_transport.get_protocol()  # type: ignore[attr-defined]
        await pair.client.send("call")
        assert await pair.server.recv() == "call"
        assert {"get_buffer", "buffer_updated"} <= set(vars(protocol))
        await pair.client.close()
        with pytest.raises(TransportClosed):
            await pair.server.recv()
    assert not {"get_buffer", "buffer_updated"} & set(vars(protocol))


async def test_a_picows_connection_says_it_is_congested_in_an_attribute() -> None:
    """A server reads ``congested`` for every message it is handed: on picows it is a plain
    attribute, not a property (a Python call each time), set and cleared where picows pauses
    and resumes writing (test_past_its_budget_a_connection_is_congested_until_the_peer_reads
    has it follow a real peer)."""
    assert type(vars(PicowsConnection)["congested"]).__name__ == "member_descriptor"
    async with connected(PicowsTransport()) as pair:
        server = pair.server
        assert isinstance(server, PicowsConnection) and server.congested is False
        server.pause_writing()
        writable = asyncio.ensure_future(server.writable())
        await turns()
        assert server.congested is True and not writable.done()
        server.resume_writing()
        assert server.congested is False
        await writable


async def test_once_open_a_picows_servers_reads_go_straight_to_picows() -> None:
    """The server's protocol looks at the first bytes it reads (a TLS record is refused at
    once); every later read reaches picows' own compiled methods, with no Python frame between
    the event loop and the frame parser, and messages still flow both ways."""
    from picows.picows import WSProtocol  # type: ignore[attr-defined]

    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        protocol = pair.server._ws.underlying_transport.get_protocol()  # type: ignore[attr-defined]
        assert protocol.get_buffer == WSProtocol.get_buffer.__get__(protocol)
        assert protocol.buffer_updated == WSProtocol.buffer_updated.__get__(protocol)
        for i in range(3):
            await pair.client.send(f"call {i}")
            assert await pair.server.recv() == f"call {i}"
            await pair.server.send(f"reply {i}".encode())
            assert await pair.client.recv() == f"reply {i}"


async def test_a_receiver_that_pauses_picows_reading_as_it_takes_the_queue_keeps_it_paused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # picows stopped reading the socket for its own queue; deliver_to reads again before it
    # hands that queue over, so a receiver that pauses the reading meanwhile (a server whose
    # own queue is full) keeps it paused, and the peer is held back.
    from srvwire.transports.picows import READ_HIGH_WATER, PicowsConnection

    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        server = pair.server
        assert isinstance(server, PicowsConnection)
        arrived = asyncio.Event()
        deliver = PicowsConnection._deliver
        count = 0

        def counting(self: PicowsConnection, message: str | bytes) -> None:
            nonlocal count
            deliver(self, message)
            if self is server:
                count += 1
                if count == READ_HIGH_WATER:
                    arrived.set()

        monkeypatch.setattr(PicowsConnection, "_deliver", counting)  # its slots hold no method
        for i in range(READ_HIGH_WATER + 6):
            await pair.client.send(str(i))
        await arrived.wait()
        assert not server._reading  # paused for its queue
        taken: list[str | bytes] = []

        def receive(message: str | bytes) -> None:
            taken.append(message)
            server.pause_reading()

        assert server.deliver_to(receive)
        assert taken[:READ_HIGH_WATER] == [str(i) for i in range(READ_HIGH_WATER)]
        assert not server._reading  # the receiver's pause holds
        server.resume_reading()
        assert server._reading


class FakeSocket:
    """What a picows connection writes to its socket, kept."""

    def __init__(self) -> None:
        self.written: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(bytes(data))


class FakePicowsTransport:
    """A stand-in for picows' WSTransport: what goes through its send, and its socket's writes."""

    is_close_frame_sent = False

    def __init__(self) -> None:
        self.underlying_transport = FakeSocket()
        self.sent: list[bytes] = []

    def send(self, kind: Any, message: bytes) -> None:
        self.sent.append(message)


@pytest.mark.parametrize("size", [8192, 8193, 60_000])
async def test_a_lone_reply_goes_through_picows_send_only_when_picows_copies_it(size: int) -> None:
    # Over 8 KiB picows' send writes the header as a view of a buffer it reuses, which asyncio
    # may keep unsent (writelines, Python 3.12+): the next frame would overwrite it. So a
    # larger lone reply is framed here and written as one copy, as several replies are.
    from srvwire.transports.picows import PICOWS_COPIES, PicowsConnection, _header

    assert PICOWS_COPIES == 8192  # the sizes straddle it
    conn = PicowsConnection(Options())
    ws = FakePicowsTransport()
    conn._ws = ws  # type: ignore[assignment]
    conn._framing = True  # a server's: it frames its own messages
    message = b"x" * size
    conn._corked = [_header(size), message]
    conn._corked_size = size
    conn._flush()
    if size <= PICOWS_COPIES:
        assert (ws.sent, ws.underlying_transport.written) == ([message], [])
    else:
        assert (ws.sent, ws.underlying_transport.written) == ([], [_header(size) + message])


async def test_a_picows_servers_reply_to_a_reads_last_frame_goes_out_as_it_is_made() -> None:
    """While the last frame of a read is handed over, a server's first small message goes
    straight to picows' own send (what the cork's flush did with a lone message at the read's
    end, without framing it first); the replies to the frames before it, or a second message,
    are corked and written in one write at the read's end, as before."""
    from picows import WSMsgType

    from srvwire.inline import first_step
    from srvwire.transports.picows import PICOWS_COPIES, _header

    @dataclass
    class Frame:  # what on_ws_frame reads of picows' WSFrame
        payload: bytes
        last_in_buffer: bool
        msg_type: Any = WSMsgType.TEXT
        fin: bool = True
        rsv1: bool = False
        rsv2: bool = False
        rsv3: bool = False

        @property
        def payload_size(self) -> int:
            return len(self.payload)

        def get_payload_as_bytes(self) -> bytes:
            return self.payload

        def get_payload_as_utf8_text(self) -> str:
            return self.payload.decode()

    conn = PicowsConnection(Options())
    ws = FakePicowsTransport()
    conn._ws = ws  # type: ignore[assignment]
    conn._framing = True  # a server's
    seen: list[tuple[list[bytes], list[bytes]]] = []  # what went out, as each reply was made

    def answer(message: str | bytes) -> None:
        for reply in replies.pop(0):
            assert first_step(conn.send(reply)) is None  # sent without waiting
        seen.append((list(ws.sent), list(ws.underlying_transport.written)))

    conn.deliver_to(answer)
    big = b"b" * (PICOWS_COPIES + 1)
    replies = [[b"r1"]]  # a read of one call: its reply leaves as it is made
    conn.on_ws_frame(ws, Frame(b"c1", True))  # type: ignore[arg-type]
    assert seen == [([b"r1"], [])] and conn._corked == []
    replies = [[b"r2"], [b"r3"]]  # two calls in one read: both replies in one write at its end
    conn.on_ws_frame(ws, Frame(b"c2", False))  # type: ignore[arg-type]
    conn.on_ws_frame(ws, Frame(b"c3", True))  # type: ignore[arg-type]
    assert seen[1:] == [([b"r1"], []), ([b"r1"], [])]
    assert ws.underlying_transport.written == [_header(2) + b"r2" + _header(2) + b"r3"]
    replies = [[b"r4", b"r5"]]  # two messages for the last frame: the second is corked
    conn.on_ws_frame(ws, Frame(b"c4", True))  # type: ignore[arg-type]
    assert seen[3] == ([b"r1", b"r4"], ws.underlying_transport.written[:1])
    assert ws.sent == [b"r1", b"r4", b"r5"]  # the lone corked one, by picows at the read's end
    replies = [[big, b"r6"]]  # too big for picows to copy: framed here, and r6 after it
    conn.on_ws_frame(ws, Frame(b"c5", True))  # type: ignore[arg-type]
    assert ws.sent == [b"r1", b"r4", b"r5"]
    assert ws.underlying_transport.written[1:] == [_header(len(big)) + big + _header(2) + b"r6"]
    assert first_step(conn.send(b"later")) is None  # after the read: corked until the turn ends
    assert conn._corked == [_header(5), b"later"]
    await turns()
    assert ws.sent[-1] == b"later" and conn._corked == []


# A picows client's writes: its small messages held to the end of the loop's turn, masked here.


def client_frames(data: bytes) -> list[tuple[bytes, bytes]]:
    """Split ``data`` into the (masking key, unmasked payload) of each final text frame it holds,
    failing on anything else a client may not send (RFC 6455, 5.2 and 5.3)."""
    from websockets.utils import apply_mask

    frames = []
    at = 0
    while at < len(data):
        assert data[at] == 0x81, "a final text frame"
        assert data[at + 1] & 0x80, "masked, as a client's frame must be"
        size = data[at + 1] & 0x7F
        assert size != 127, "no message held here needs an 8-byte length"
        at += 2
        if size == 126:
            size = int.from_bytes(data[at : at + 2], "big")
            at += 2
        key = data[at : at + 4]
        payload = data[at + 4 : at + 4 + size]
        assert len(payload) == size
        frames.append((key, apply_mask(payload, key)))
        at += 4 + size
    return frames


@pytest.mark.parametrize("size", [0, 1, 3, 4, 5, 125, 126, 127, 511, 512])
def test_a_client_frame_made_here_is_masked_as_the_rfc_says(size: int) -> None:
    from srvwire.transports.picows import _masked_frames

    messages = [(bytes(range(256)) * 2)[:size], b"second"]
    frames = client_frames(_masked_frames(messages))
    assert [payload for _, payload in frames] == messages
    assert frames[0][0] != frames[1][0]  # a fresh key for each frame


async def test_a_picows_clients_sends_in_one_turn_go_out_in_one_write() -> None:
    """A pipelined client's calls of one turn leave together; a websockets server, which fails
    a client's frame that is not masked, reads every one."""
    async with listening(WebSocketsTransport()) as (listener, accepted):
        client = await PicowsTransport().connect(listener.url, Options())
        try:
            async with asyncio.timeout(scaled(5)):
                server = await accepted.get()
                writes = count_writes(client)
                messages = [f"call {i} ☃" for i in range(20)]
                for message in messages:
                    await client.send(message)
                assert writes == []  # held until the loop comes round
                assert [await server.recv() for _ in messages] == messages
                assert len(writes) == 1
                frames = client_frames(writes[0])
                assert [payload.decode() for _, payload in frames] == messages
                assert len({key for key, _ in frames}) == len(frames)  # a key each
        finally:
            await client.close()


async def test_a_picows_clients_first_send_after_a_lone_message_is_written_at_once() -> None:
    """A caller that got its reply and calls again is alone in its turn: its call is not held
    for the turn's end. A second send in the turn is."""
    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        client = pair.client
        received: asyncio.Queue[str | bytes] = asyncio.Queue()
        assert client.deliver_to(received.put_nowait)
        await pair.server.send("reply 1")
        assert await received.get() == "reply 1"
        await client.send("call 2")
        assert client._corked == []  # type: ignore[attr-defined]  # written at once
        await client.send("call 3")
        assert client._corked == [b"call 3"]  # type: ignore[attr-defined]  # held
        assert [await pair.server.recv() for _ in range(2)] == ["call 2", "call 3"]
        for i in range(2):  # a read of two messages: the next send is held
            await pair.server.send(f"reply {i}")
        assert [await received.get() for _ in range(2)] == ["reply 0", "reply 1"]
        await client.send("call 4")
        assert client._corked == [b"call 4"]  # type: ignore[attr-defined]
        assert await pair.server.recv() == "call 4"


async def test_a_picows_client_writes_larger_messages_at_once_after_what_it_held() -> None:
    from srvwire.transports.picows import CLIENT_CORK_LIMIT

    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        sizes = [10, CLIENT_CORK_LIMIT - 4, CLIENT_CORK_LIMIT - 3, 100, 70_000, 5] * 3
        await numbered_messages_arrive_in_order(pair, sizes)  # held ones and others, mixed
        # In one turn: up to the limit, held; past it, what is held goes first, then it. The
        # websockets transport's client holds the same messages (those below its CORK_LIMIT).
        from srvwire.transports.websockets import CORK_LIMIT

        assert CLIENT_CORK_LIMIT == CORK_LIMIT - 1
        client = pair.client
        writes = count_writes(client)
        await client.send(b"a" * CLIENT_CORK_LIMIT)
        assert client._corked == [b"a" * CLIENT_CORK_LIMIT]  # type: ignore[attr-defined]
        await client.send(b"b" * (CLIENT_CORK_LIMIT + 1))
        assert client._corked == []  # type: ignore[attr-defined]
        assert writes == []  # a lone held message and the larger one: both through picows
        assert await pair.server.recv() == "a" * CLIENT_CORK_LIMIT  # a client writes text
        assert await pair.server.recv() == "b" * (CLIENT_CORK_LIMIT + 1)


async def test_a_picows_client_writes_what_it_holds_past_a_quarter_of_its_budget() -> None:
    options = Options(max_queued_bytes=4000)
    async with connected(PicowsTransport(), options) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.client)
        for i in range(10):  # 2 500 bytes in one turn: a write at each 1 000
            await pair.client.send(f"{i:04d}".encode() + b"x" * 246)
        assert [len(client_frames(data)) for data in writes] == [4, 4]
        assert pair.client.buffered() >= 500  # type: ignore[attr-defined]
        received = [await pair.server.recv() for _ in range(10)]
        assert [m[:4] for m in received] == [f"{i:04d}" for i in range(10)]
        assert [len(client_frames(data)) for data in writes] == [4, 4, 2]


async def test_a_message_a_picows_client_holds_arrives_before_its_close_frame() -> None:
    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        await pair.client.send("last words")
        assert pair.client._corked  # type: ignore[attr-defined]
        await pair.client.close(4000, "done")
        assert await pair.server.recv() == "last words"
        closed = await closed_with(pair.server)
        assert (closed.code, closed.reason) == (4000, "done")


async def test_a_picows_server_frames_every_length_as_websockets_reads_it() -> None:
    """A server's frames are made here: a websockets client, which checks every header, reads
    each size whole, across the one-byte, two-byte and eight-byte lengths."""
    from websockets.asyncio.client import connect

    sizes = [0, 1, 125, 126, 127, 2**16 - 1, 2**16, 70_000]
    async with listening(PicowsTransport()) as (listener, accepted):
        async with connect(listener.url, max_size=None) as client, asyncio.timeout(scaled(5)):
            server = await accepted.get()
            for size in sizes:  # in one turn: held and written together
                await server.send(b"x" * size)
            assert [len(await client.recv()) for _ in sizes] == sizes


async def test_a_picows_client_writes_what_it_holds_once_it_reaches_its_write_size() -> None:
    """A pipelined client's calls reach the server in a few writes, not one at the turn's end:
    the server works on the first while the client makes the next."""
    from srvwire.transports.picows import CLIENT_CORK_LIMIT, CLIENT_WRITE_AT

    size = 400
    assert size <= CLIENT_CORK_LIMIT and CLIENT_WRITE_AT % size  # held, and not a round count
    per_write = CLIENT_WRITE_AT // size + 1
    async with connected(PicowsTransport()) as pair, asyncio.timeout(scaled(5)):
        writes = count_writes(pair.client)
        count = 2 * per_write + 3
        for i in range(count):  # in one turn
            await pair.client.send(f"{i:04d}".encode() + b"x" * (size - 4))
        assert [len(client_frames(data)) for data in writes] == [per_write, per_write]
        received = [await pair.server.recv() for _ in range(count)]
        assert [m[:4] for m in received] == [f"{i:04d}" for i in range(count)]
        assert [len(client_frames(data)) for data in writes] == [per_write, per_write, 3]


def test_a_forked_child_masks_with_keys_of_its_own() -> None:
    """A websockets client's masking keys come from a supply drawn ahead: a child forked from
    a process that drew some must not send the keys its parent sends next. Run in a process of
    its own, where nothing but this thread runs when it forks."""
    script = """
import os
from srvwire.transports.websockets import _masking_keys

_masking_keys.key()  # the parent has a supply
read, write = os.pipe()
child = os.fork()
if child == 0:
    os.write(write, b"".join(_masking_keys.key() for _ in range(5)))
    os._exit(0)
os.waitpid(child, 0)
theirs = os.read(read, 20)
ours = b"".join(_masking_keys.key() for _ in range(5))
print(len(theirs), theirs != ours)
"""
    assert run_python("-c", script).stdout.split() == ["20", "True"]
