"""A close frame that arrives in the same read as messages before it, on both WebSocket
transports: the messages count as received, whichever end closes.

The peer is raw: websockets' sans-I/O protocol on an asyncio stream, so that it writes the
messages and its close frame in one ``write`` (one read at the other end, on loopback), which
no srvwire end does on purpose.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from asyncio.tasks import _enter_task, _leave_task
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from ssl import SSLContext
from typing import Any

import pytest
from websockets.client import ClientProtocol
from websockets.frames import Close, Frame, Opcode
from websockets.http11 import Request
from websockets.protocol import Protocol, State
from websockets.server import ServerProtocol
from websockets.uri import parse_uri

from conftest import Echo, Hang
from srvwire import ConnectionLost, connect
from srvwire.inline import Pending, finish, first_step
from srvwire.server import Server, serve
from srvwire.transports.base import Connection, Options
from srvwire.transports.websockets import WebSocketsConnection, WebSocketsTransport
from support import scaled, tls_on_localhost

both_transports = pytest.mark.parametrize("transport", ["websockets", "picows"])


class RawEnd:
    """One end of a WebSocket connection, run by hand: what it writes goes out in one
    ``write``, and :meth:`read` feeds what arrives to the protocol."""

    def __init__(
        self, protocol: Protocol, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.protocol = protocol
        self.reader = reader
        self.writer = writer
        self.frames: list[Frame] = []

    def write(self) -> None:
        """Write everything the protocol has to send, in one write (an end of stream last)."""
        data = self.protocol.data_to_send()
        self.writer.write(b"".join(data))
        if data and not data[-1]:
            self.writer.close()

    async def read(self) -> bool:
        """Read once; keep the frames, answer what the protocol answers. False at the end."""
        data = await self.reader.read(2**16)
        if data:
            self.protocol.receive_data(data)
        else:
            self.protocol.receive_eof()
        self.frames += [e for e in self.protocol.events_received() if isinstance(e, Frame)]
        self.write()
        return bool(data)

    async def text(self) -> Any:
        """The next text message, as JSON."""
        while not any(frame.opcode is Opcode.TEXT for frame in self.frames):
            assert await self.read()
        frame = next(frame for frame in self.frames if frame.opcode is Opcode.TEXT)
        self.frames.remove(frame)
        return json.loads(bytes(frame.data))

    async def to_the_end(self) -> list[tuple[str, Any]]:
        """Read until the connection ends; return what came, in order: ``("text", JSON)`` and
        ``("close", code)``."""
        async with asyncio.timeout(scaled(10)):
            while await self.read():
                pass
        self.writer.close()
        return [
            ("close", Close.parse(bytes(frame.data)).code)
            if frame.opcode is Opcode.CLOSE
            else ("text", json.loads(bytes(frame.data)))
            for frame in self.frames
        ]


ECHO_SERVICES = [{"name": "/echo", "type": "srvwire_tests/srv/Echo"}]
"""What a raw server announces when its client calls ``/echo``."""


async def raw_server_end(
    reader: asyncio.StreamReader, writer: asyncio.StreamWriter, services: list[dict[str, str]]
) -> RawEnd:
    """A raw server's end of a connection a client opened: the opening accepted, and
    ``$/services`` announcing ``services`` written."""
    end = RawEnd(ServerProtocol(), reader, writer)
    protocol = end.protocol
    assert isinstance(protocol, ServerProtocol)
    requests: list[object] = []
    while not requests:
        protocol.receive_data(await reader.read(2**16))
        requests = protocol.events_received()
    (request,) = requests
    assert isinstance(request, Request)
    protocol.send_response(protocol.accept(request))
    announce = {"jsonrpc": "2.0", "method": "$/services", "params": {"services": services}}
    protocol.send_text(json.dumps(announce).encode())
    end.write()
    return end


async def raw_client(port: int, url: str, ssl: SSLContext | None = None) -> RawEnd:
    """A raw client connected to the server at ``url``, past its ``$/services``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port, ssl=ssl)
    protocol = ClientProtocol(parse_uri(url))
    client = RawEnd(protocol, reader, writer)
    protocol.send_request(protocol.connect())
    client.write()
    assert (await client.text())["method"] == "$/services"
    return client


def call(id: int, method: str, text: str) -> bytes:
    message = {"jsonrpc": "2.0", "id": id, "method": method, "params": {"text": text}}
    return json.dumps(message).encode()


@both_transports
@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
async def test_calls_in_the_same_read_as_the_clients_close_are_answered_before_it(
    transport: str, tls: bool
) -> None:
    """The calls a client sent before its close frame are read; the replies the server makes
    as it reads them go out ahead of its close, and a call still running then is cancelled, as
    on any connection that closes."""
    server = Server(grace_period=scaled(2))

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    hang = Hang()
    server.add_service("/echo", Echo, echo)
    server.add_service("/hang", Echo, hang)
    server_ssl, client_ssl = tls_on_localhost(tls)
    async with serve(server, "127.0.0.1", 0, transport=transport, ssl=server_ssl) as running:
        client = await raw_client(running.port, running.url, client_ssl)
        client.protocol.send_text(call(1, "/echo", "a"))
        client.protocol.send_text(call(2, "/echo", "b"))
        client.protocol.send_text(call(3, "/hang", "c"))
        client.protocol.send_close(1000)
        client.write()
        assert await client.to_the_end() == [
            ("text", {"jsonrpc": "2.0", "id": 1, "result": {"text": "a"}}),
            ("text", {"jsonrpc": "2.0", "id": 2, "result": {"text": "b"}}),
            ("close", 1000),
        ]
        async with asyncio.timeout(scaled(5)):
            await hang.cancelled.wait()


@both_transports
async def test_a_message_refused_before_the_clients_close_in_the_same_read_ends_with_1007(
    transport: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Text that is not UTF-8 fails the connection with 1007 before the close behind it is
    answered: the reply to the call before it goes out, the close is not echoed, and nothing
    is logged as an error."""
    server = Server(grace_period=scaled(2))

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    server.add_service("/echo", Echo, echo)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await raw_client(running.port, running.url)
        client.protocol.send_text(call(1, "/echo", "a"))
        client.protocol.send_frame(Frame(Opcode.TEXT, b"\xff"))
        client.protocol.send_text(call(2, "/echo", "b"))
        client.protocol.send_close(1000)
        client.write()
        assert await client.to_the_end() == [
            ("text", {"jsonrpc": "2.0", "id": 1, "result": {"text": "a"}}),
            ("close", 1007),
        ]
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


@both_transports
async def test_replies_in_the_same_read_as_the_servers_close_reach_their_calls(
    transport: str,
) -> None:
    """A client given replies and the server's close frame in one read resolves the calls
    they answer; only the call left without a reply fails, with ConnectionLost."""
    answered: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    async def raw_server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        server = await raw_server_end(reader, writer, ECHO_SERVICES)
        protocol = server.protocol
        calls = [await server.text() for _ in range(3)]
        for message in calls[:2]:  # the last call gets no reply
            result = {"text": message["params"]["text"]}
            reply = {"jsonrpc": "2.0", "id": message["id"], "result": result}
            protocol.send_text(json.dumps(reply, separators=(",", ":")).encode())
        protocol.send_close(1001, "going away")
        server.write()
        await server.to_the_end()
        answered.set_result(None)

    listening = await asyncio.start_server(raw_server, "127.0.0.1", 0)
    port = listening.sockets[0].getsockname()[1]
    async with listening, connect(f"ws://127.0.0.1:{port}", transport=transport) as client:
        results = await asyncio.gather(
            *[client.call("/echo", {"text": str(i)}, srv_type=Echo) for i in range(3)],
            return_exceptions=True,
        )
        await answered
    assert [r.text for r in results[:2]] == ["0", "1"]
    assert type(results[2]) is ConnectionLost
    assert results[2].data["close_code"] == 1001


@contextlib.asynccontextmanager
async def raw_pair(receive: Callable[[Connection, str | bytes], None]) -> AsyncIterator[Pair]:
    """A websockets-transport server connection that hands its messages to ``receive`` (with
    itself) in the read callback, and a raw client connected to it, past the handshake."""
    accepted: asyncio.Queue[Connection] = asyncio.Queue()
    done = asyncio.Event()

    async def handler(connection: Connection) -> None:
        accepted.put_nowait(connection)
        await done.wait()

    listener = await WebSocketsTransport().listen(handler, "127.0.0.1", 0, Options())
    try:
        port = int(listener.url.rstrip("/").rsplit(":", 1)[1])
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        client = RawEnd(ClientProtocol(parse_uri(listener.url)), reader, writer)
        client.protocol.send_request(client.protocol.connect())
        client.write()
        async with asyncio.timeout(scaled(5)):
            server = await accepted.get()
            while client.protocol.state is State.CONNECTING:
                assert await client.read()
        server.deliver_to(lambda message: receive(server, message))
        yield Pair(client, server)
    finally:
        done.set()
        listener.close()
        async with asyncio.timeout(scaled(5)):
            await listener.wait_closed()


@dataclass
class Pair:
    client: RawEnd
    server: Connection


@pytest.mark.parametrize(
    ("fragmented", "first_close"),
    [(True, 1000), (False, 1001)],
    ids=["parsed-by-websockets", "taken-directly"],
)
async def test_a_close_begun_from_a_message_that_came_with_the_clients_close(
    fragmented: bool, first_close: int, caplog: pytest.LogCaptureFixture
) -> None:
    """A server's close begun from a message that came with the client's close (as a handler's
    first step, run in the read callback, or an eager task would begin it).

    A message websockets' parser reads (here, one in two fragments) is handed over as the
    client's close is being answered: that answer is the one close the server sends. A whole
    frame at the start of the read is taken before websockets reads the close, as when the
    close comes in a later read: the server's own close goes first. Either way the server's
    close returns once the connection has ended, and nothing is logged."""
    closing: list[Pending | None] = []
    loop = asyncio.get_running_loop()
    # The step runs with a task current, as a server runs a handler's first step with its
    # connection's reader task current (websockets' close needs one).
    reader = asyncio.create_task(asyncio.Event().wait())

    def receive(server: Connection, message: str | bytes) -> None:
        if message == "close-me":
            _enter_task(loop, reader)
            try:
                closing.append(first_step(server.close(1001, "going away")))
            finally:
                _leave_task(loop, reader)

    async with raw_pair(receive) as pair:
        if fragmented:
            pair.client.protocol.send_text(b"close-", fin=False)
            pair.client.protocol.send_continuation(b"me", fin=True)
        else:
            pair.client.protocol.send_text(b"close-me")
        pair.client.protocol.send_close(1000)
        pair.client.write()
        assert await pair.client.to_the_end() == [("close", first_close)]
        [pending] = closing
        if pending is not None:
            async with asyncio.timeout(scaled(5)):
                await finish(pending)
        assert pair.server.close_code == 1000  # the client's, which it received
    reader.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await reader
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


async def test_a_message_refused_as_the_clients_close_is_answered_is_the_close_sent(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A receiver that fails on a message that came with the client's close: the server's
    close is 1011 instead of the echo, and websockets records that close as the one sent."""

    def receive(server: Connection, message: str | bytes) -> None:
        raise RuntimeError("the receiver broke")

    async with raw_pair(receive) as pair:
        pair.client.protocol.send_text(b"break")
        pair.client.protocol.send_close(1000)
        pair.client.write()
        assert await pair.client.to_the_end() == [("close", 1011)]
        server = pair.server
        assert isinstance(server, WebSocketsConnection)
        sent = server._ws.protocol.close_sent
        assert sent is not None and sent.code == 1011
    [record] = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert record.getMessage() == "the receiver of messages failed; closing the connection"


@both_transports
@pytest.mark.parametrize(
    "refused",
    [
        Frame(Opcode.TEXT, b"x").serialize(mask=True)[:1].replace(b"\x81", b"\x83"),
        b"",  # the same frame unmasked: a client must mask its frames
    ],
    ids=["an unknown opcode", "an unmasked frame"],
)
async def test_a_frame_the_parser_refuses_after_a_call_in_the_same_read(
    transport: str, refused: bytes
) -> None:
    """A frame the WebSocket parser refuses fails the connection with 1002, and the call
    before it in the same read is handled. On websockets its reply goes out before the close;
    picows sends its close as it reads the refused frame's header, before it hands over the
    frame before it, so the reply has nowhere to go (docs/transports.md, "What differs on
    picows")."""
    server = Server()
    calls: list[str] = []

    async def echo(request: Any) -> Any:
        calls.append(request.text)
        return {"text": request.text}

    server.add_service("/echo", Echo, echo)
    if refused:  # an unknown opcode: the masked frame with opcode 3 in its first byte
        bad = refused + Frame(Opcode.TEXT, b"x").serialize(mask=True)[1:]
    else:
        bad = Frame(Opcode.TEXT, b"x").serialize(mask=False)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await raw_client(running.port, running.url)
        client.writer.write(Frame(Opcode.TEXT, call(1, "/echo", "a")).serialize(mask=True) + bad)
        # picows may drop the connection with a reset once its close is out: what came before
        # the reset is what the test reads.
        with contextlib.suppress(ConnectionResetError):
            await client.to_the_end()
    assert calls == ["a"]
    outcome = [
        ("close", Close.parse(bytes(frame.data)).code)
        if frame.opcode is Opcode.CLOSE
        else ("text", json.loads(bytes(frame.data)))
        for frame in client.frames
    ]
    reply = ("text", {"jsonrpc": "2.0", "id": 1, "result": {"text": "a"}})
    assert outcome == ([reply] if transport == "websockets" else []) + [("close", 1002)]


@both_transports
async def test_a_ping_after_calls_in_the_same_read_is_answered_after_their_replies(
    transport: str,
) -> None:
    """The replies made to the calls before a ping in the same read go out before its pong,
    as if the ping came in a later read (docs/transports.md)."""
    server = Server()

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    server.add_service("/echo", Echo, echo)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await raw_client(running.port, running.url)
        client.protocol.send_text(call(1, "/echo", "a"))
        client.protocol.send_text(call(2, "/echo", "b"))
        client.protocol.send_ping(b"are you there")
        client.write()
        async with asyncio.timeout(scaled(10)):
            while sum(frame.opcode is Opcode.TEXT for frame in client.frames) < 2:
                assert await client.read()
        client.protocol.send_close(1000)
        client.write()
        async with asyncio.timeout(scaled(10)):
            while await client.read():
                pass
        client.writer.close()
    assert [(frame.opcode, bytes(frame.data)) for frame in client.frames[:3]] == [
        (Opcode.TEXT, b'{"jsonrpc":"2.0","id":1,"result":{"text":"a"}}'),
        (Opcode.TEXT, b'{"jsonrpc":"2.0","id":2,"result":{"text":"b"}}'),
        (Opcode.PONG, b"are you there"),
    ]
