"""A frame with a reserved bit set, on both WebSocket transports, at either end.

No extension is ever negotiated on picows, and srvwire negotiates none that uses RSV2 or RSV3
on websockets; without compression, RSV1 is not meant either. RFC 6455 (section 5.2) then
asks the receiving end to fail the connection: both transports close with 1002 and
websockets' reason, ``reserved bits must be 0``, for every data and control opcode, without
taking the frame (no message handed over, no pong, no close echoed as if it were the peer's).

The peer is raw: websockets' sans-I/O protocol on an asyncio stream (see
``test_close_in_one_read``), writing the frame with the reserved bit as bytes made here, since
no WebSocket library sends one.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from websockets.frames import Close, Frame, Opcode

from conftest import Echo
from srvwire import ConnectionLost, connect
from srvwire.server import Server, serve
from support import scaled
from test_close_in_one_read import ECHO_SERVICES, RawEnd, raw_client, raw_server_end

REASON = "reserved bits must be 0"
RSV = {"rsv1": 0x40, "rsv2": 0x20, "rsv3": 0x10}
# Each opcode with a payload it may carry; a continuation follows a first fragment.
OPCODES = {
    "text": (Opcode.TEXT, b'{"jsonrpc":"2.0","id":7,"method":"/echo","params":{"text":"x"}}'),
    "binary": (Opcode.BINARY, b'{"jsonrpc":"2.0","id":7,"method":"/echo","params":{"text":"x"}}'),
    "continuation": (Opcode.CONT, b'"x"}}'),
    "close": (Opcode.CLOSE, Close(1000, "bye").serialize()),
    "ping": (Opcode.PING, b"are you there"),
    "pong": (Opcode.PONG, b"unasked"),
}
FIRST_PART = b'{"jsonrpc":"2.0","id":7,"method":"/echo","params":{"text":'

transports = pytest.mark.parametrize("transport", ["websockets", "picows"])
reserved = pytest.mark.parametrize("bit", list(RSV))
opcodes = pytest.mark.parametrize("kind", list(OPCODES))


def raw_frame(opcode: Opcode, payload: bytes, *, rsv: int, mask: bool, fin: bool = True) -> bytes:
    """A frame's bytes with the reserved bits ``rsv`` set in its first byte (which
    websockets' ``Frame.serialize`` refuses to write)."""
    data = Frame(opcode, payload, fin=fin).serialize(mask=mask)
    return bytes((data[0] | rsv,)) + data[1:]


def with_reserved_bit(kind: str, bit: str, *, mask: bool) -> bytes:
    """The bytes of a ``kind`` frame with ``bit`` set, after a first fragment for a
    continuation."""
    opcode, payload = OPCODES[kind]
    before = b""
    if opcode is Opcode.CONT:
        before = Frame(Opcode.TEXT, FIRST_PART, fin=False).serialize(mask=mask)
    return before + raw_frame(opcode, payload, rsv=RSV[bit], mask=mask)


def closes(end: RawEnd) -> list[tuple[int, str]]:
    """The close frames ``end`` received: code and reason."""
    parsed = [Close.parse(bytes(f.data)) for f in end.frames if f.opcode is Opcode.CLOSE]
    return [(close.code, close.reason) for close in parsed]


def test_a_frame_made_here_has_only_the_bit_asked_for() -> None:
    data = raw_frame(Opcode.PING, b"p", rsv=RSV["rsv2"], mask=False)
    assert data == bytes((0x80 | 0x20 | 0x9, 1)) + b"p"


@transports
@reserved
@opcodes
async def test_a_server_fails_a_frame_with_a_reserved_bit_with_1002(
    transport: str, bit: str, kind: str
) -> None:
    """The server closes with 1002 and websockets' reason; what came before the frame in the
    same read is answered, the frame itself is not (no reply, no pong, no echoed 1000)."""
    server = Server()

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    server.add_service("/echo", Echo, echo)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await raw_client(running.port, running.url)
        client.protocol.send_text(
            b'{"jsonrpc":"2.0","id":1,"method":"/echo","params":{"text":"a"}}'
        )
        client.write()
        # A second call and the frame in one write: the call is answered, the frame is not.
        client.writer.write(
            Frame(
                Opcode.TEXT, b'{"jsonrpc":"2.0","id":2,"method":"/echo","params":{"text":"b"}}'
            ).serialize(mask=True)
            + with_reserved_bit(kind, bit, mask=True)
        )
        async with asyncio.timeout(scaled(10)):
            while await client.read():
                pass
        client.writer.close()
    texts = [json.loads(bytes(f.data)) for f in client.frames if f.opcode is Opcode.TEXT]
    assert [message["id"] for message in texts] == [1, 2]  # not 7: that frame is not taken
    assert [f.opcode for f in client.frames if f.opcode is Opcode.PONG] == []
    assert closes(client) == [(1002, REASON)]


@transports
@reserved
@opcodes
async def test_a_client_fails_a_frame_with_a_reserved_bit_with_1002(
    transport: str, bit: str, kind: str
) -> None:
    """The client closes with 1002 and websockets' reason; the call the frame would have
    answered fails with ConnectionLost, which names the close."""
    answered: asyncio.Future[list[tuple[int, str]]] = asyncio.get_running_loop().create_future()

    async def raw_server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        end = await raw_server_end(reader, writer, ECHO_SERVICES)
        call = await end.text()
        assert call["method"] == "/echo"
        # The reply the call waits for, with the reserved bit (for a text or binary frame),
        # or the frame in its place.
        reply = json.dumps({"jsonrpc": "2.0", "id": call["id"], "result": {"text": "x"}})
        opcode, payload = OPCODES[kind]
        if opcode in (Opcode.TEXT, Opcode.BINARY):
            payload = reply.encode()
        elif opcode is Opcode.CONT:
            payload = reply.encode()[len(FIRST_PART) :]
        data = raw_frame(opcode, payload, rsv=RSV[bit], mask=False)
        if opcode is Opcode.CONT:
            data = (
                Frame(Opcode.TEXT, reply.encode()[: len(FIRST_PART)], fin=False).serialize(
                    mask=False
                )
                + data
            )
        writer.write(data)
        try:
            async with asyncio.timeout(scaled(10)):
                while await end.read():
                    pass
        finally:
            writer.close()
            answered.set_result(closes(end))

    listening = await asyncio.start_server(raw_server, "127.0.0.1", 0)
    port = listening.sockets[0].getsockname()[1]
    async with listening, connect(f"ws://127.0.0.1:{port}", transport=transport) as client:
        with pytest.raises(ConnectionLost) as lost:
            async with asyncio.timeout(scaled(10)):
                await client.call("/echo", {"text": "x"}, srv_type=Echo)
        async with asyncio.timeout(scaled(10)):
            received = await answered
    assert received == [(1002, REASON)]
    assert lost.value.data["close_code"] == 1002


@transports
async def test_a_client_answers_a_ping_without_reserved_bits_with_its_pong(transport: str) -> None:
    """The check does not stop pongs: picows' own pong is off, and the connection answers."""
    ponged: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()

    async def raw_server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        end = await raw_server_end(reader, writer, [])
        protocol = end.protocol
        protocol.send_ping(b"are you there")
        end.write()
        while not any(frame.opcode is Opcode.PONG for frame in end.frames):
            assert await end.read()
        (pong,) = [frame for frame in end.frames if frame.opcode is Opcode.PONG]
        ponged.set_result(bytes(pong.data))
        while await end.read():
            pass
        writer.close()

    listening = await asyncio.start_server(raw_server, "127.0.0.1", 0)
    port = listening.sockets[0].getsockname()[1]
    async with listening, connect(f"ws://127.0.0.1:{port}", transport=transport):
        async with asyncio.timeout(scaled(10)):
            assert await ponged == b"are you there"
