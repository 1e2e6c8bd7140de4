"""The websockets transport taking a read's whole frames itself (``_Watched.take_frames``).

A connection that hands its messages to a receiver takes the final text and binary frames at
the start of a read without websockets' parser, and leaves the rest of the read to it. What
arrives must end the same either way: the same messages handed over, the same frames the
connection sends of itself (pongs, closes, with their codes and reasons), the same state. Each
test feeds crafted bytes to a connection's ``data_received``, as the event loop hands it a
read, split into reads at every offset where a split can matter, and compares the outcome with
that of the same connection with the direct path off (websockets' parser for every frame).

The connections are real ones, on 127.0.0.1, opened by a real handshake; the crafted reads
stand in for what the peer would send, so that where a read ends is the test's to choose.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import struct
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass
from typing import Any

import pytest

from srvwire.transports.base import Options
from srvwire.transports.websockets import WebSocketsConnection, WebSocketsTransport, _Watched
from support import scaled
from test_transports import connected
from test_websockets_push import Taker

KEY = b"\x37\xfa\x21\x3d"


def frame(first: int, payload: bytes, *, masked: bool, form: int | None = None) -> bytes:
    """A frame's bytes as they go on the wire: ``first`` is FIN, the RSV bits and the opcode;
    the length in the shortest form, or in ``form`` (126 or 127) when given; a masked frame
    with :data:`KEY`."""
    length = len(payload)
    if form is None:
        form = length if length < 126 else 126 if length < 2**16 else 127
    if form == 126:
        header = bytes((first, 126)) + struct.pack("!H", length)
    elif form == 127:
        header = bytes((first, 127)) + struct.pack("!Q", length)
    else:
        header = bytes((first, length))
    if not masked:
        return header + payload
    masked_payload = bytes(b ^ KEY[i % 4] for i, b in enumerate(payload))
    return bytes((header[0], header[1] | 0x80)) + header[2:] + KEY + masked_payload


TEXT, BINARY, CONT_FIN, TEXT_PART, CLOSE, PING, PONG = 0x81, 0x82, 0x80, 0x01, 0x88, 0x89, 0x8A


@dataclass
class Outcome:
    """What a connection did with the reads it was fed."""

    messages: list[str | bytes]
    sent: list[tuple[int, bytes]]  # the frames its protocol sent of itself: opcode, payload
    state: str
    close: tuple[int, str] | None  # the close frame it sent, if any
    parsed: int  # reads websockets' parser was given


class Fed:
    """One end of a real connection that hands its messages to a receiver, fed crafted reads."""

    def __init__(self, connection: WebSocketsConnection, direct: bool) -> None:
        self.ws: _Watched = connection._ws
        self.messages: list[str | bytes] = []
        assert connection.deliver_to(self.messages.append)
        assert self.ws.direct  # no compression, no debug log: the direct path is on
        self.ws.direct = direct
        protocol = self.ws.protocol
        self.sent: list[tuple[int, bytes]] = []
        send_frame = protocol.send_frame
        self.parsed = 0
        receive_data = protocol.receive_data

        def recording(frame: Any) -> None:
            self.sent.append((frame.opcode.value, bytes(frame.data)))
            send_frame(frame)

        def counting(data: bytes | bytearray) -> None:
            self.parsed += 1
            receive_data(data)

        protocol.send_frame = recording  # type: ignore[method-assign]
        protocol.receive_data = counting  # type: ignore[method-assign]

    def feed(self, reads: Iterable[bytes]) -> Outcome:
        """Hand ``reads`` to the connection as the event loop would; what came of them."""
        first_message, first_sent, parsed = len(self.messages), len(self.sent), self.parsed
        for read in reads:
            # As buffer_updated hands a read over: a view of the thread's read buffer.
            buffer = bytearray(read)
            self.ws.data_received(memoryview(buffer))  # type: ignore[arg-type]
            buffer[:] = b"\xee" * len(buffer)  # the next read overwrites it: nothing may keep it
        protocol = self.ws.protocol
        close = protocol.close_sent
        return Outcome(
            self.messages[first_message:],
            self.sent[first_sent:],
            protocol.state.name,
            None if close is None else (close.code, close.reason),
            self.parsed - parsed,
        )


@contextlib.asynccontextmanager
async def fed(side: str, direct: bool, options: Options | None = None) -> AsyncIterator[Fed]:
    """The server end (fed a client's frames) or the client end (fed a server's) of a real
    connection, direct path on or off."""
    async with connected(WebSocketsTransport(), options) as pair, asyncio.timeout(scaled(10)):
        end = pair.server if side == "server" else pair.client
        assert isinstance(end, WebSocketsConnection)
        yield Fed(end, direct)


def splits(frames: list[bytes], large: bool = False) -> list[list[bytes]]:
    """``frames`` joined, then: in one read; cut in two at every offset in or next to a
    frame's header and at the last byte of each payload; and (unless ``large``) one read per
    byte."""
    stream = b"".join(frames)
    offsets: set[int] = set()
    at = 0
    for each in frames:
        offsets.update(range(max(1, at - 1), at + 15))
        at += len(each)
        offsets.add(at - 1)
    cuts = [[stream[:o], stream[o:]] for o in sorted(offsets) if 0 < o < len(stream)]
    bytewise = [] if large else [[stream[i : i + 1] for i in range(len(stream))]]
    return [[stream], *cuts, *bytewise]


def agree(direct: Outcome, parser: Outcome, reads: list[bytes]) -> Outcome:
    """Assert both paths did the same (but for how much websockets' parser was given)."""
    assert direct.parsed <= parser.parsed
    direct.parsed = parser.parsed = 0
    assert direct == parser, f"reads of {[len(r) for r in reads]} bytes"
    return direct


async def compare(
    side: str, frames: list[bytes], options: Options | None = None, *, large: bool = False
) -> Outcome:
    """Feed ``frames`` to both paths in every split (one connection each, kept: the frames
    leave it open); assert the outcomes agree; return the first."""
    outcomes = []
    async with fed(side, True, options) as direct, fed(side, False, options) as parser:
        for reads in splits(frames, large):
            outcomes.append(agree(direct.feed(reads), parser.feed(reads), reads))
            assert outcomes[-1].state == "OPEN"
    assert all(o == outcomes[0] for o in outcomes)  # however the bytes were cut
    return outcomes[0]


async def compare_ending(side: str, frames: list[bytes], options: Options | None = None) -> Outcome:
    """As :func:`compare`, for frames that end the connection: new connections for each
    split, cut only around the last two frames' headers."""
    outcomes = []
    head = len(b"".join(frames[:-2]))
    for reads in splits(frames):
        if len(reads) == 2 and not head - 1 <= len(reads[0]) <= len(b"".join(frames)):
            continue
        async with fed(side, True, options) as direct, fed(side, False, options) as parser:
            outcomes.append(agree(direct.feed(reads), parser.feed(reads), reads))
    assert all(o == outcomes[0] for o in outcomes)
    return outcomes[0]


SIDES = ["server", "client"]


def on(side: str) -> Callable[..., bytes]:
    """Frames as the peer of ``side`` sends them: a client's masked (RFC 6455, 5.1)."""

    def make(first: int, payload: bytes, form: int | None = None) -> bytes:
        return frame(first, payload, masked=side == "server", form=form)

    return make


def looks_like(side: str, wire: bytes) -> bytes:
    """A payload whose bytes on the wire are ``wire``: read from where its frame's header
    ends, it is taken for that frame."""
    if side == "client":
        return wire
    return bytes(b ^ KEY[i % 4] for i, b in enumerate(wire))  # unmasked, it is masked again


# The direct path is taken


@pytest.mark.parametrize("side", SIDES)
async def test_whole_frames_are_taken_without_websockets_parser(side: str) -> None:
    f = on(side)
    frames = [f(TEXT, "hé".encode()), f(BINARY, b"\x00\xff"), f(TEXT, b"x" * 300)]
    async with fed(side, True) as direct, fed(side, False) as parser:
        taken = direct.feed([b"".join(frames)])
        assert taken.messages == ["hé", b"\x00\xff", "x" * 300]
        assert taken.parsed == 0
        assert parser.feed([b"".join(frames)]).parsed == 1
        # A frame cut short: what was whole is taken, the rest is websockets' from its start.
        assert direct.feed([frames[0] + frames[1][:3], frames[1][3:]]).parsed == 2
        # Then whole frames are taken again.
        assert direct.feed([frames[2]]).parsed == 0
        assert direct.messages == ["hé", b"\x00\xff", "x" * 300] * 2


async def test_compression_or_websockets_frame_log_leave_every_frame_to_websockets(
    caplog: pytest.LogCaptureFixture,
) -> None:
    deflate = Options(compression="deflate")
    async with connected(WebSocketsTransport(), deflate) as pair:
        assert pair.server.deliver_to(lambda message: None)
        assert not pair.server._ws.direct  # type: ignore[attr-defined]
    caplog.set_level(logging.DEBUG, logger="websockets")
    async with connected(WebSocketsTransport()) as pair, asyncio.timeout(scaled(5)):
        taker = Taker()
        assert pair.server.deliver_to(taker)
        assert not pair.server._ws.direct  # type: ignore[attr-defined]
        await pair.client.send("logged")
        assert await taker.until(1) == ["logged"]
    assert any(r.getMessage().startswith("< TEXT 'logged'") for r in caplog.records)


# The same outcome as websockets' parser


@pytest.mark.parametrize("side", SIDES)
async def test_data_frames_in_every_split(side: str) -> None:
    f = on(side)
    frames = [
        f(TEXT, "hé".encode()),
        f(BINARY, b"\x00\xff"),
        f(TEXT, b""),
        f(BINARY, b""),
        f(TEXT, b"y" * 125),
        f(TEXT, "z☃".encode() * 100),  # a length in two bytes
        f(TEXT, b"short", form=126),  # a length in more bytes than needed, as websockets takes
        f(BINARY, looks_like(side, f(TEXT, b"A"))),  # a whole frame's bytes as a payload
    ]
    outcome = await compare(side, frames)
    assert outcome.messages == [
        "hé",
        b"\x00\xff",
        "",
        b"",
        "y" * 125,
        "z☃" * 100,
        "short",
        looks_like(side, f(TEXT, b"A")),
    ]
    assert outcome.sent == []


@pytest.mark.parametrize("side", SIDES)
async def test_pings_and_pongs_among_data_frames(side: str) -> None:
    f = on(side)
    frames = [f(TEXT, b"a"), f(PING, b"p"), f(TEXT, b"b"), f(PONG, b"q"), f(TEXT, b"c")]
    outcome = await compare(side, frames)
    assert outcome.messages == ["a", "b", "c"]
    assert outcome.sent == [(0x0A, b"p")]  # the ping answered


@pytest.mark.parametrize("side", SIDES)
async def test_a_fragmented_message_among_whole_ones(side: str) -> None:
    f = on(side)
    frames = [
        f(TEXT, b"a"),
        f(TEXT_PART, b"he"),
        f(PING, b"p"),  # between fragments, as RFC 6455 allows
        f(CONT_FIN, b"llo"),
        f(BINARY, b"b"),
    ]
    outcome = await compare(side, frames)
    assert outcome.messages == ["a", "hello", b"b"]
    assert outcome.sent == [(0x0A, b"p")]


@pytest.mark.parametrize("side", SIDES)
async def test_large_frames_among_small_ones(side: str) -> None:
    f = on(side)
    large = bytes(range(256)) * 300  # 76 800 bytes: a length in eight bytes
    frames = [f(TEXT, b"a"), f(BINARY, large), f(TEXT, b"b"), f(TEXT, b"c" * 70_000, form=127)]
    outcome = await compare(side, frames, Options(max_message_size=2**20), large=True)
    assert outcome.messages == ["a", large, "b", "c" * 70_000]


def close_payload(code: int, reason: str) -> bytes:
    return struct.pack("!H", code) + reason.encode()


@pytest.mark.parametrize("side", SIDES)
@pytest.mark.parametrize(
    ("last", "close"),
    [
        ((CLOSE, close_payload(1000, "bye")), (1000, "bye")),
        ((TEXT, b"ok \xc3"), (1007, "unexpected end of data at position 3")),
        ((0xC1, b"x"), (1002, "reserved bits must be 0")),
        ((0x83, b"x"), (1002, "invalid opcode")),
        ((CONT_FIN, b"x"), (1002, "unexpected continuation frame")),
        ((0x09, b"x"), (1002, "fragmented control frame")),
    ],
    ids=["close", "not-utf8", "rsv1", "opcode", "continuation", "fragmented-ping"],
)
async def test_frames_that_end_the_connection(
    side: str, last: tuple[int, bytes], close: tuple[int, str]
) -> None:
    f = on(side)
    after = f(TEXT, b"never")
    outcome = await compare_ending(side, [f(TEXT, b"a"), f(*last), after])
    assert outcome.messages == ["a"]
    assert outcome.close == close
    assert outcome.state != "OPEN"


@pytest.mark.parametrize("side", SIDES)
async def test_a_frame_masked_as_the_other_side_masks_ends_the_connection(side: str) -> None:
    wrong = frame(TEXT, b"x", masked=side != "server")
    outcome = await compare_ending(side, [on(side)(TEXT, b"a"), wrong, on(side)(TEXT, b"b")])
    assert outcome.messages == ["a"]
    assert outcome.close == (1002, "incorrect masking")


@pytest.mark.parametrize("side", SIDES)
async def test_a_frame_over_the_limit_ends_the_connection_naming_it(side: str) -> None:
    f = on(side)
    limit = Options(max_message_size=64)
    outcome = await compare_ending(
        side, [f(TEXT, b"a" * 64), f(TEXT, b"b" * 65), f(TEXT, b"c")], limit
    )
    assert outcome.messages == ["a" * 64]
    assert outcome.close == (
        1009,
        f"over the {side}'s max_message_size (frame with 65 bytes exceeds limit of 64 bytes)",
    )


@pytest.mark.parametrize("side", SIDES)
async def test_a_data_frame_inside_a_fragmented_message_ends_the_connection(side: str) -> None:
    f = on(side)
    outcome = await compare_ending(side, [f(TEXT_PART, b"x"), f(TEXT, b"y"), f(TEXT, b"z")])
    assert outcome.messages == []
    assert outcome.close == (1002, "expected a continuation frame")
