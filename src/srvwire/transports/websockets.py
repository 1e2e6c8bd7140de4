"""The WebSocket transport, on the ``websockets`` library: the only module that imports it.

A :class:`WebSocketsConnection` is a thin wrapper on one ``websockets`` connection: ``recv``
and ``send`` are one call each, with no extra ``await``, because every call of srvwire goes
through them. ``websockets`` already keeps the rules of :mod:`srvwire.transports.base`: its
write buffer gives the backpressure, ``max_size`` the 1009, UTF-8 checks the 1007, and
``close`` waits for the closing handshake (within its ``close_timeout``). Its 1009 close reason
is prefixed with the side and the setting that refused the message (``over the server's
max_message_size (frame with 2097170 bytes exceeds limit of 1048576 bytes)``), so that the
peer's error says what to raise.

The budget is websockets' ``write_limit``: the asyncio transport's high-water mark, its low one
a quarter of it. websockets writes a message into the buffer first and waits for it to drain
after, so a ``send`` that finds the connection congested waits before it calls websockets.
websockets' connection classes are subclassed (its ``create_connection``) only to hear the
transport's ``pause_writing``/``resume_writing``: the write timeout is one timer, armed when
writing pauses and cancelled when it resumes. This is also what ends a peer that does not read
when keepalive cannot: websockets writes its ping and then waits for the buffer to drain before
it starts the pong deadline, so past the high-water mark the ping deadline never starts. With
keepalive on, a connection congested for a ping interval plus a ping timeout is closed as one
whose ping went unanswered, when that is sooner than ``write_timeout``.

Exceptions are mapped here and nowhere else:

* ``ConnectionClosed`` (any subclass) -> :class:`TransportClosed`, with the code and reason of
  the close frame received, else of the one sent, else ``None``;
* ``OSError`` and ``WebSocketException`` while connecting -> :class:`TransportError`, with the
  same text;
* ``InvalidURI`` from :meth:`WebSocketsTransport.check_url` -> ``ValueError``.

**Messages sent close together are written together.** A ``send`` frames its message into
websockets' outgoing buffer and returns; what is held goes out in one socket write at the
first of three moments: when this connection's reader is about to wait for the peer (every
message it took from one read has been handled, so the replies to all of them leave
together; with a receiver, when the read that handed the messages over ends), when what is
held reaches :data:`CORK_LIMIT`, and at the end of the loop turn (``call_soon``; the calls
many tasks made in one turn: what writes a client's calls, since its reader never waits in
``recv`` for each reply). One send writes at once instead: the first after a read that handed
a receiver a single message, with nothing held. That is a peer calling one call at a time,
whose next call would otherwise wait a loop turn for nothing to join it; after a read of
several messages (a pipelined peer's replies) the sends they cause are held as above. A
connection frames a message it holds itself, the two or four bytes of a final text frame's
header before it, where websockets' ``send_text`` builds a ``Frame`` and serializes it in
Python: a server's frames unmasked, the same bytes at a quarter of the instructions; a
client's masked with websockets' own C ``apply_mask`` and a fresh key each, drawn from
``os.urandom`` a thousand at a time (:class:`_MaskingKeys`). With compression on, or
websockets' debug log of frames, its own ``send_text`` frames them.
:data:`CORK_LIMIT` is what keeps a pipelined
peer busy: holding every reply to 64 calls until the last is made lets the peer start on none
of them before, and two ends that each answer a whole window in one write settle into taking
turns, each idle while the other works (measured: half the calls a second, at less CPU per
call). Order is kept, since every frame goes through the same buffer, and anything websockets
writes itself (a pong, a close, a send that writes through) writes the held frames first. A
send writes through, as websockets' own ``send`` with its backpressure, when its message alone
is larger than :data:`CORK_LIMIT`, when what is held and what the socket's buffer holds would
pass the budget (``max_queued_bytes``, the high-water mark: held frames count as waiting to be
sent, so a peer that does not read still holds the sender back at the same point), and when
the connection is not open. A message of :data:`LARGE_MESSAGE` bytes or more that writes
through is framed here as well, where frames are (websockets' ``send_text`` would copy it
behind its header): the header, then the payload itself (a server's, as a view of the bytes;
a client's masked), in two writes, inside websockets' own ``send_context``, so with the same
checks of the connection's state and the same wait for the buffer to drain as its ``send``.

**Messages can be handed over in the read callback.** Given a receiver
(:meth:`WebSocketsConnection.deliver_to`, as a client's link and a server ask), a connection
takes each data frame from websockets' protocol in ``process_event`` instead of queueing it for
``recv``,
which saves the reading task's wake-up per message. The protocol has already bounded the
message (``max_size``: 1009, named as above), answered pings and closes, and checked the order
of fragments; here fragments are joined (more than websockets' ``MAX_FRAGMENTS``: 1009), text
is decoded (not UTF-8: 1007, with websockets' reason), pongs are acknowledged, and a receiver
that raises is logged and closes the connection with 1011, as on picows. Failing the connection
here is what websockets' ``recv`` does: the close frame at once, the TCP connection dropped if
the peer has not closed it within ``close_timeout``. :meth:`~WebSocketsConnection.pause_reading`
stops reading the socket, with or without a receiver: websockets' queue, which stops reading
while ``recv`` lags 16 messages behind, resumes it only when srvwire does not hold it back.
websockets answers a close frame as it parses it, before it hands over any event of that read;
a server with a receiver hands the frames before the close over first
(:meth:`_Watched.send_close_last`), so the replies they make at once go out ahead of the
answer, as when the close comes in a later read and as on picows.

**With a receiver, the whole frames that begin a read are taken without websockets' parser.**
websockets parses every frame with a chain of Python generators, a ``Frame`` and an event for
each: a sixth to a fifth of a small call's instructions, both ends. Between two frames, the
parser waits in its reader's ``at_eof`` with no byte buffered; a read that arrives then begins
with a frame's first byte. :meth:`_Watched.take_frames` takes the frames at the start of such
a read that the parser would turn into a whole message as they are: final, text or binary, no
reserved bit, masked as the peer's side must mask (a client's frames, not a server's), a
length in one or three bytes within the size limit the parser would check, the whole frame
in the read, text that is UTF-8; it unmasks the payload with websockets' own ``apply_mask``
and hands it over as :meth:`~_Watched.process_event` would. At the first byte that is not
such a frame (a control frame, a fragment, a large or an invalid frame, text that is not
UTF-8, a frame cut by the end of the read) it stops, and the rest of the read goes to
websockets' parser from that frame's start, which then keeps every rule as before: pings,
closes, fragments, 1002, 1007, 1009. One thing moves: a message taken so is handed over
before the parser reads the frames after it in the same read, as if they came in a later
read. What it begins goes out first: a reply, or the server's own close (a ping after it is
still answered, the peer's close is not echoed); a receiver that raises on it closes with
1011, and the rest of the read is discarded, as a later read would be.
The parser is not asked anything new: nothing is taken unless it is found waiting between
frames, open, not inside a fragmented message and with no fragment limit (websockets' own,
which srvwire does not set); with compression on, or websockets' debug log of frames, or a
websockets whose parser is not built as this module expects (:func:`_parser_as_expected`), it
parses every frame itself.

**Every read goes into one buffer per thread.** asyncio reads a socket into a new bytes object
of :data:`READ_SIZE` (256 KiB), which the C library maps from the kernel and gives back on every
read, however little arrived: three system calls and a page fault per read, more than the
read itself. A connection is an ``asyncio.BufferedProtocol`` instead: the event loop reads into
a buffer of the same size that every connection of the thread shares (:class:`_ReadBuffer`),
and websockets copies what arrived into its own buffer before the next read can start. uvloop,
which reads into a buffer of its own already, still calls ``data_received`` (a connection is an
``asyncio.Protocol`` too). websockets gathers a frame that spans many reads in its reader's
buffer and returns a copy of the payload out of it. A client reads a payload of
:data:`LARGE_MESSAGE` bytes or more into a buffer of its size instead, straight from the
socket, which is the payload handed over (a reply of megabytes, in a few reads;
:class:`_WholeReader`). A server, and a client without a limit, read as websockets reads: the
reader's Python call more for every read of every frame would cost each small call about 4 %
of its instructions, both ends on one connection, more than a server gains on its rare large
messages.

A listener's gate runs in websockets' ``process_request``: an :class:`Answered` request gets
that plain HTTP response (the upgrade never happens), an :class:`Admitted` one its identity
and, through ``select_subprotocol``, its subprotocol. A client's refusal says the HTTP status
and the server's reason, and a TLS handshake that fails says whether the server may not speak
TLS.

A listener can listen on several hosts (``asyncio``'s ``create_server`` takes a list), or on
every interface, IPv4 and IPv6, with ``host=None``; its :attr:`~WebSocketsListener.urls` name
each address clients can use, with the interfaces' own addresses for a wildcard
(``0.0.0.0``, ``::``). ``websockets``' own INFO lines (a connection opened, closed, the server
listening) are left out unless its logger's level was set (:class:`_QuietLogger`); its
warnings and errors always go through.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import os
import socket
import ssl as _ssl
import struct
import sys
import threading
import weakref
from collections.abc import Callable, Generator, Sequence
from types import GeneratorType
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.connection import Connection as WebSocket
from websockets.asyncio.messages import MAX_FRAGMENTS
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import (
    ConnectionClosed,
    InvalidMessage,
    InvalidStatus,
    InvalidURI,
    WebSocketException,
)
from websockets.frames import BINARY, CLOSE, CONT, PONG, TEXT, Close, CloseCode, Frame
from websockets.http11 import Request, Response
from websockets.protocol import OPEN, Event, Protocol, Side, State
from websockets.streams import StreamReader
from websockets.typing import Subprotocol
from websockets.uri import parse_uri

try:  # websockets' C masking, as its own frames use; its Python one where it was not built
    from websockets.speedups import apply_mask
except ImportError:  # websockets ships it compiled for the common platforms
    from websockets.utils import apply_mask

from srvwire.transports.base import (
    CREDENTIAL_HEADERS,
    WRITE_TIMEOUT_CODE,
    Admitted,
    Answered,
    Connection,
    ConnectionHandler,
    Gate,
    Handshake,
    Hosts,
    Listener,
    Options,
    Transport,
    TransportClosed,
    TransportError,
    WriteTimedOut,
    opening_failed,
    write_timeout_reason,
)

__all__ = [
    "CORK_LIMIT",
    "LARGE_MESSAGE",
    "WebSocketsConnection",
    "WebSocketsListener",
    "WebSocketsTransport",
]

CORK_LIMIT = 2**12
"""Bytes of messages a connection holds to write together; reaching it writes them at once, and
a larger message writes through (see the module's docstring)."""


LARGE_MESSAGE = 2**16
"""Bytes from which a message is large: a connection writes its frame's header and its payload
apart, in two socket writes, rather than copying the payload behind the header (a shorter
message goes out in one write, header and payload joined); and reads its payload without
copying it out of websockets' reader (see the module's docstring)."""
# A large message's frame has its length in eight bytes, which RFC 6455 allows only from 2**16.
assert LARGE_MESSAGE >= 2**16

DEFAULT_WRITE_LIMIT = 2**15
"""websockets' own high-water mark, for ``max_queued_bytes=None``."""

# The header of a final, unmasked text frame (RFC 6455, 5.2): FIN and the opcode, then the
# length in the second byte under 126, else 126 and the length in two bytes (CORK_LIMIT is
# below 65536, the next step).
_SHORT_TEXT = [bytes((0x81, length)) for length in range(126)]
_TEXT_126 = bytes((0x81, 126))
_LENGTH = struct.Struct("!H").pack
# LARGE_MESSAGE and more: 127, and the length in eight bytes.
_TEXT_127 = bytes((0x81, 127))
_LENGTH_64 = struct.Struct("!Q").pack
# A client's frames have the mask bit set in the second byte, and the key after the length.
_SHORT_MASKED = [bytes((0x81, 0x80 | length)) for length in range(126)]
_MASKED_126 = bytes((0x81, 0x80 | 126))
_MASKED_127 = bytes((0x81, 0x80 | 127))


class _MaskingKeys(threading.local):
    """Masking keys for a thread's client frames: four bytes each, never used twice, taken
    from ``os.urandom`` a thousand at a time instead of a system call per frame (a key is
    seen on the wire once used, and tells nothing of the next, which the OS drew apart). A
    forked child forgets the supply it was born with, which its parent goes on using."""

    def __init__(self) -> None:
        self.supply = b""
        self.at = 0

    def forget(self) -> None:
        self.supply = b""
        self.at = 0

    def key(self) -> bytes:
        at = self.at
        supply = self.supply
        if at >= len(supply):
            supply = self.supply = os.urandom(4096)
            at = 0
        self.at = at + 4
        return supply[at : at + 4]


# What websockets' parser is suspended in between two frames: its loop, waiting for a frame's
# first byte (see _Watched.take_frames).
_PARSE = getattr(getattr(Protocol, "parse", None), "__code__", None)
_AT_EOF = getattr(getattr(StreamReader, "at_eof", None), "__code__", None)


def _parser_as_expected(protocol: Protocol) -> bool:
    """Whether websockets' parser of ``protocol`` is built as :meth:`_Watched.take_frames`
    reads it (websockets 17: a ``parse`` generator waiting in its reader's ``at_eof`` between
    frames, ``current_size`` and the two size limits on the protocol). Another build leaves
    every frame to websockets."""
    return (
        _PARSE is not None
        and _AT_EOF is not None
        and isinstance(protocol.parser, GeneratorType)
        and all(
            hasattr(protocol, name)
            for name in ("current_size", "max_message_size", "max_fragment_size")
        )
    )


_masking_keys = _MaskingKeys()
os.register_at_fork(after_in_child=_masking_keys.forget)  # the forking thread's, the only one


READ_SIZE = 2**18
"""Bytes a connection reads from its socket at most at once: what asyncio itself reads."""


class _ReadBuffer(threading.local):
    """The buffer every connection of one thread reads its socket into (see the module).

    An event loop runs in one thread and reads one socket at a time, and websockets copies
    what a read brought into its own buffer before the read's callback returns, so one buffer
    serves every connection of the thread; a thread that never reads has none.
    """

    def __init__(self) -> None:
        self.view = memoryview(bytearray(READ_SIZE))


_read_buffer = _ReadBuffer()


class _WholeReader(StreamReader):
    """websockets' reader of a connection's bytes, which hands over a large frame's payload
    without copying it out of a buffer of its own: websockets' reader gathers a payload that
    spans many reads in its buffer and returns a copy of it.

    Only a client's connection with a size limit has one (a server's peers are not trusted
    with memory they have not sent). A large payload not all read yet is read into a buffer of
    its size (``target``, which the limit bounds: websockets checks a frame's length against it
    before it reads the payload), which the connection hands the event loop to read the socket
    into: the payload comes from the socket straight into the bytes it is handed over as, in
    reads as large as what has arrived. One already all read is handed over as the reader's
    buffer itself when that holds exactly it, and read as websockets reads it when more bytes
    follow it.
    """

    target: bytearray | None = None  # the payload being read in place
    filled = 0  # bytes of ``target`` read so far

    def read_exact(self, n: int) -> Generator[None, None, bytearray]:
        # Not a generator itself: the small reads of every frame (its header, a small payload)
        # are websockets' own generator, with no second one around it (about 8 % of a small
        # call's instructions, both ends, when this delegated to it).
        if n < LARGE_MESSAGE:
            return StreamReader.read_exact(self, n)
        return self.read_large(n)

    def read_large(self, n: int) -> Generator[None, None, bytearray]:
        if len(self.buffer) < n:
            return (yield from self.read_in_place(n))
        if len(self.buffer) == n:
            whole, self.buffer = self.buffer, bytearray()
            return whole
        return (yield from StreamReader.read_exact(self, n))

    def read_in_place(self, n: int) -> Generator[None, None, bytearray]:
        target = bytearray(n)
        filled = len(self.buffer)
        target[:filled] = self.buffer
        self.buffer = bytearray()
        self.target, self.filled = target, filled
        try:
            while self.filled < n:
                if self.eof:  # as websockets' reader says it
                    raise EOFError(f"stream ends after {self.filled} bytes, expected {n} bytes")
                yield
        finally:
            self.target = None
        return target

    def feed_data(self, data: bytes | bytearray) -> None:
        target = self.target
        if target is None or self.eof:
            super().feed_data(data)
            return
        filled = self.filled
        taken = min(len(target) - filled, len(data))
        target[filled : filled + taken] = data[:taken]
        self.filled = filled + taken
        if taken < len(data):  # what follows the payload
            super().feed_data(data[taken:])


class _Watched(WebSocket, asyncio.BufferedProtocol):
    """What srvwire adds to a websockets connection: it reads its socket into its thread's
    buffer (an ``asyncio.BufferedProtocol``); it knows when writing is paused, and
    closes the connection when it stays paused for ``write_timeout`` (None: never); once it
    has a receiver (:meth:`WebSocketsConnection.deliver_to`), it hands each message to it in
    the read callback instead of to websockets' queue; and srvwire may hold reading back
    (``held_back``), which the queue, resuming reading as it drains, respects."""

    write_timeout: float | None = None
    # What answers the peer's close instead of its echo (see send_close_last): a class default,
    # set on a connection only then.
    refused: Close | None = None
    # The answer to the latest ping received while congested, sent once it drains (see
    # send_close_last): a class default, set on a connection only then.
    pong_due: Frame | None = None

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.drained = asyncio.Event()  # set while writing is not paused, and once closed
        self.drained.set()
        self.stall: asyncio.TimerHandle | None = None
        self.timed_out = False
        self.receive: Callable[[str | bytes], None] | None = None  # see deliver_to
        self.pushing: WebSocketsConnection | None = None  # the connection, while receive is
        self.fragments: list[Frame] = []  # a message not yet whole, while receive is set
        self.held_back = False  # srvwire paused reading (WebSocketsConnection.pause_reading)
        self.handed = 0  # messages handed to the receiver by the read being processed
        self.closing: asyncio.TimerHandle | None = None  # drops a connection this side failed
        # What the socket is read into: the buffer of this thread, the one its event loop, which
        # made this connection, runs in.
        self.reading = _read_buffer.view
        # A client reads in place what its limit bounds (the frame's length is checked first):
        # the same reader, as a _WholeReader (the parser holds its bound methods). Not on a
        # server, nor without a limit: every frame's reads would pay for a Python call more.
        protocol = self.protocol
        bounded = protocol.max_message_size is not None or protocol.max_fragment_size is not None
        self.whole_reader: _WholeReader | None = None
        if protocol.side is Side.CLIENT and bounded:
            reader = protocol.reader
            reader.__class__ = _WholeReader
            assert isinstance(reader, _WholeReader)
            self.whole_reader = reader
        self.reading_in_place = False  # the event loop reads into the payload read in place
        # Whether a read's leading frames may be taken here rather than by websockets' parser
        # (see take_frames): set with a receiver, once the handshake settled the extensions.
        self.direct = False

    @property
    def close_timeout(self) -> float | None:
        """websockets' wait for the peer's close frame once this side closed; none after a
        keepalive ping went unanswered: a peer that does not answer pings does not answer a
        close either, so the connection is dropped at once, not ``close_timeout`` later."""
        keepalive = self.keepalive_task
        if keepalive is not None and asyncio.current_task() is keepalive:  # the ping timed out
            sent = self.protocol.close_sent
            if sent is not None and sent.code == CloseCode.INTERNAL_ERROR:
                return 0.0
        return self.closing_within

    @close_timeout.setter
    def close_timeout(self, value: float | None) -> None:
        self.closing_within = value

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        self.recv_messages.resume = self.queue_drained

    def queue_drained(self) -> None:
        """websockets' queue of frames went down to its low-water mark: read again, unless
        srvwire holds reading back."""
        if not self.held_back:
            self.transport.resume_reading()

    def get_buffer(self, sizehint: int) -> memoryview:
        """Where the event loop reads the socket: the rest of a large payload read in place,
        else its thread's buffer, whatever the hint."""
        reader = self.whole_reader
        if reader is not None:
            target = reader.target
            if target is not None:
                self.reading_in_place = True
                return memoryview(target)[reader.filled :]
            self.reading_in_place = False
        return self.reading

    def buffer_updated(self, nbytes: int) -> None:
        if self.reading_in_place:  # the bytes are where they belong: say how many arrived
            assert self.whole_reader is not None
            self.whole_reader.filled += nbytes
            self.data_received(b"")
            return
        # websockets' receive_data appends the bytes to its own buffer: nothing keeps the view.
        self.data_received(self.reading[:nbytes])  # type: ignore[arg-type]

    def data_received(self, data: bytes) -> None:
        pushing = self.pushing
        if pushing is None:
            super().data_received(data)
            return
        self.handed = 0
        pushing.read_begins()
        try:
            taken = self.take_frames(data) if self.direct and data else 0
            if not taken:  # websockets' to parse (b"": a payload read in place grew)
                super().data_received(data)
            elif taken < len(data):  # the rest is, from a frame's start
                super().data_received(data[taken:])
        finally:
            pushing.read_ends()
        if self.refused is not None:  # websockets took its echo of the peer's close as sent
            self.protocol.close_sent = self.refused

    def process_event(self, event: Event) -> None:
        receive = self.receive
        if receive is None:
            super().process_event(event)
            return
        assert isinstance(event, Frame)
        opcode = event.opcode
        if opcode is PONG:
            self.acknowledge_pings(bytes(event.data))
            return
        if opcode is not TEXT and opcode is not BINARY and opcode is not CONT:
            return  # a ping or a close: the protocol has answered it
        # The protocol has checked the frames' order and bounded the message by max_size.
        fragments = self.fragments
        if fragments or not event.fin:
            fragments.append(event)
            if len(fragments) > MAX_FRAGMENTS:  # as websockets' queue refuses them
                self.refuse(CloseCode.MESSAGE_TOO_BIG, "too many fragments", None)
                return
            if not event.fin:
                return
            self.fragments = []
            data: bytes | bytearray | memoryview = b"".join(frame.data for frame in fragments)
            text = fragments[0].opcode is TEXT
        else:
            data = event.data
            text = opcode is TEXT
        message: str | bytes
        if text:
            try:
                message = str(data, "utf-8")
            except UnicodeDecodeError as exc:  # what websockets' recv says of it
                reason = f"{exc.reason} at position {exc.start}"
                self.refuse(CloseCode.INVALID_DATA, reason, exc.with_traceback(None))
                return
        else:
            message = data if type(data) is bytes else bytes(data)
        self.hand_over(receive, message)

    def hand_over(self, receive: Callable[[str | bytes], None], message: str | bytes) -> None:
        """Hand a whole message to ``receive``; a receiver that raises closes with 1011."""
        self.handed += 1
        try:
            receive(message)
        except Exception as exc:  # as a handler that raises: 1011, and the error in the log
            self.logger.error(
                "the receiver of messages failed; closing the connection", exc_info=True
            )
            # Kept as the connection's error without its own traceback, whose frames hold views
            # of the thread's read buffer (take_frames), which other connections' reads refill;
            # the log record keeps it, with the exceptions chained to it.
            self.refuse(CloseCode.INTERNAL_ERROR, "", exc.with_traceback(None))

    def take_frames(self, data: bytes | memoryview) -> int:
        """Hand over the whole messages at the start of a read that websockets' parser would
        return as single final frames, and return how many bytes they took (the rest is the
        parser's). See the module: only between frames, and only frames it would take as
        they are, text only when it is UTF-8."""
        protocol = self.protocol
        # The parser is a generator; what it waits in is the innermost one it delegates to.
        parsing: Any = protocol.parser
        if parsing.gi_code is not _PARSE:  # the handshake's parser, which delegates to it
            parsing = parsing.gi_yieldfrom
        waiting: Any = None if parsing is None else parsing.gi_yieldfrom
        if (
            waiting is None
            or waiting.gi_code is not _AT_EOF  # which waits only on an empty buffer
            or protocol.current_size is not None
            or protocol.max_fragment_size is not None  # websockets' own; srvwire sets none
        ):
            return 0  # not between frames, inside a fragmented message, or a fragment limit
        limit = protocol.max_message_size
        masked = protocol.side is Side.SERVER  # a client's frames are masked, a server's not
        expected = 0x80 if masked else 0
        receive = self.receive
        assert receive is not None
        size = len(data)
        at = 0
        # The receiver is read once; what may end it (refuse, which sets another, a close
        # the receiver begins) leaves the connection not open, which stops the loop.
        while at + 2 <= size and protocol.state is OPEN:
            first = data[at]
            if first != 0x81 and first != 0x82:  # FIN, no RSV bit, text or binary
                break
            length = data[at + 1]
            if length & 0x80 != expected:
                break
            length &= 0x7F
            start = at + 2
            if length == 126:
                if start + 2 > size:
                    break
                length = data[start] << 8 | data[start + 1]
                start += 2
            elif length == 127:
                break
            if limit is not None and length > limit:
                break
            if masked:
                key = bytes(data[start : start + 4])
                start += 4
            end = start + length
            if end > size:
                break
            payload = apply_mask(data[start:end], key) if masked else data[start:end]
            message: str | bytes
            if first == 0x81:
                try:
                    message = str(payload, "utf-8")
                except UnicodeDecodeError:  # the parser's, with what follows: then 1007
                    break
            else:
                message = payload if type(payload) is bytes else bytes(payload)
            at = end
            self.hand_over(receive, message)
        return at

    def send_close_last(self, frame: Frame) -> None:
        """The protocol's ``send_frame`` on a server that hands messages over. websockets
        answers a client's close frame as it parses it, before any event of that read is
        taken: the frames before the close are handed over first, so that the replies they
        make at once go out ahead of the answer, as when the close comes in a later read. A
        message refused meanwhile (:meth:`refuse`) turns the answer into its own close. A pong
        is not written to a transport that is closing, and while the connection is congested
        only the latest is kept, written once it drains (RFC 6455, section 5.5.3): a peer that
        pings and does not read holds one pong, not one per ping. Every other frame passes as
        it is: only websockets' own frames come here (a pong, a close, a message it frames
        itself), not those the connection frames."""
        protocol = self.protocol
        if frame.opcode is PONG:
            if self.transport.is_closing():
                return
            if self.paused:
                self.pong_due = frame
                return
        if frame.opcode is CLOSE and protocol.state is OPEN and protocol.close_rcvd is not None:
            for event in protocol.events_received():  # the close frame is not among them yet
                self.process_event(event)
            refused = self.refused
            if refused is not None:
                frame = Frame(CLOSE, refused.serialize())
        Protocol.send_frame(protocol, frame)

    def refuse(self, code: int, reason: str, exc: BaseException | None) -> None:
        """Fail the connection from the read callback, as websockets' ``recv`` fails it for a
        message it cannot return: the close frame now, the TCP connection dropped if the peer
        has not closed it within ``close_timeout``. Nothing more is delivered."""
        self.receive = _ignore
        self.fragments = []
        self.set_connection_exc(exc)
        protocol = self.protocol
        if protocol.state is not OPEN:
            return  # closing already
        if protocol.close_rcvd is not None:  # the peer's close is being answered: with this
            self.refused = Close(code, _limit_named(protocol.side, code, reason))
            return
        protocol.fail(code, reason)
        try:
            self.send_data()
        except Exception as error:  # as data_received: the connection ends anyway
            self.set_connection_exc(error)
        if self.close_timeout is not None and self.closing is None:
            self.closing = self.loop.call_later(self.close_timeout, self.transport.abort)

    def send_data(self) -> None:
        """Write what the protocol has to send, as websockets does, but nothing once the
        transport is closing: websockets writes each frame on its own, and asyncio warns for
        each write past the fifth to a transport whose write failed, so the pongs to a read of
        pings from a peer that reset the connection would each log a line."""
        protocol = self.protocol
        writes = protocol.data_to_send()
        transport = self.transport
        for at, data in enumerate(writes):
            if transport.is_closing():  # nobody left to write to
                return
            if not data:  # websockets half-closes the connection: let it, as it does itself
                protocol.writes[:0] = writes[at:]
                super().send_data()
                return
            transport.write(data)

    def pause_writing(self) -> None:
        super().pause_writing()
        self.drained.clear()
        if self.write_timeout is not None:
            self.stall = self.loop.call_later(self.write_timeout, self.stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        self.drained.set()
        if self.stall is not None:
            self.stall.cancel()
            self.stall = None
        pong = self.pong_due
        if pong is not None:
            self.pong_due = None
            if self.protocol.state is OPEN and not self.transport.is_closing():
                Protocol.send_frame(self.protocol, pong)
                self.send_data()

    def connection_lost(self, exc: Exception | None) -> None:
        super().connection_lost(exc)
        self.drained.set()
        if self.stall is not None:
            self.stall.cancel()
            self.stall = None
        if self.closing is not None:
            self.closing.cancel()
            self.closing = None
        # Nothing more arrives: drop what refers back to this connection, so that it is freed
        # without the cycle collector.
        self.receive = None
        self.pushing = None
        vars(self.protocol).pop("send_frame", None)
        self.recv_messages.resume = self.transport.resume_reading

    def stalled(self) -> None:
        """Close now: the peer does not read, so a closing handshake would wait for nothing."""
        self.stall = None
        assert self.write_timeout is not None
        self.timed_out = True
        if self.protocol.state is OPEN:  # record the close frame that recv will report
            self.protocol.fail(WRITE_TIMEOUT_CODE, write_timeout_reason(self.write_timeout))
        self.transport.abort()


def _ignore(message: str | bytes) -> None:
    """The receiver of a connection that failed: what still arrives is dropped."""


class _ServerConnection(_Watched, ServerConnection):
    pass


class _ClientConnection(_Watched, ClientConnection):
    pass


def _closed(exc: ConnectionClosed, ws: _Watched) -> TransportClosed:
    """Translate how ``websockets`` says a connection ended into :class:`TransportClosed`."""
    if ws.timed_out:
        assert ws.write_timeout is not None
        return WriteTimedOut(ws.write_timeout)
    frame = exc.rcvd if exc.rcvd is not None else exc.sent
    if frame is None:
        return TransportClosed(None)
    return TransportClosed(frame.code, frame.reason)


def _name_the_limit(protocol: Protocol) -> None:
    """Make the close reason of a message over ``max_size`` name the setting and the side."""
    fail = protocol.fail
    side = protocol.side

    def fail_naming_the_limit(code: int, reason: str = "") -> None:
        fail(code, _limit_named(side, code, reason))

    protocol.fail = fail_naming_the_limit  # type: ignore[method-assign]


def _limit_named(side: Side, code: int, reason: str) -> str:
    """The close reason of ``code``: for 1009, naming the setting and the side that refused."""
    if code != CloseCode.MESSAGE_TOO_BIG:
        return reason
    name = "server" if side is Side.SERVER else "client"
    return f"over the {name}'s max_message_size ({reason})"[:123]  # at most 123 bytes, ASCII


def _url(host: str, port: int, tls: bool = False) -> str:
    """Return the ``ws://`` (``wss://``) URL of ``host``:``port``, an IPv6 host in brackets."""
    scheme = "wss" if tls else "ws"
    return f"{scheme}://[{host}]:{port}" if ":" in host else f"{scheme}://{host}:{port}"


def _handshake(ws: ServerConnection, request: Request) -> Handshake:
    """The opening request as srvwire's gate reads it."""
    ssl_object = ws.transport.get_extra_info("ssl_object")
    certificate = ssl_object.getpeercert() if ssl_object is not None else None
    offered = [
        name.strip()
        for value in request.headers.get_all("Sec-WebSocket-Protocol")
        for name in value.split(",")
        if name.strip()
    ]
    return Handshake(
        path=request.path,
        headers=list(request.headers.raw_items()),
        peer=ws.remote_address,
        tls=ssl_object is not None,
        client_certificate=certificate or None,
        subprotocols=offered,
    )


class _Redacting(logging.LoggerAdapter[logging.Logger]):
    """websockets' own logger, with the credentials of the handshake lines it writes at
    DEBUG level hidden: the values of credential headers, bearer subprotocols and query
    strings (where a token may travel)."""

    def log(self, level: int, msg: object, *args: Any, **kwargs: Any) -> None:
        if len(args) == 2 and msg in ("< %s: %s", "> %s: %s"):
            name = str(args[0]).lower()
            if name in CREDENTIAL_HEADERS:
                args = (args[0], "<hidden>")
            elif name == "sec-websocket-protocol" and "srvwire.bearer." in str(args[1]):
                args = (args[0], "<hidden>")
        elif len(args) == 3 and msg in ("< %s %s %s", "> %s %s %s") and "?" in str(args[1]):
            args = (args[0], str(args[1]).split("?", 1)[0] + "?<hidden>", args[2])
        super().log(level, msg, *args, **kwargs)


def _refusal(exc: Exception, url: str) -> TransportError:
    """Say why opening a connection to ``url`` failed (see :func:`opening_failed`)."""
    refused = None
    if isinstance(exc, InvalidStatus):
        body = exc.response.body.decode("utf-8", "replace").strip()
        refused = (exc.response.status_code, body)
    # A response websockets cannot parse is a ValueError; one that never came, an EOFError.
    unreadable = isinstance(exc, InvalidMessage) and isinstance(exc.__cause__, ValueError)
    return opening_failed(
        url,
        exc.__cause__ if unreadable and exc.__cause__ is not None else exc,
        refused=refused,
        closed_early=isinstance(exc, InvalidMessage) and not unreadable,
        not_websocket=unreadable,
    )


_WILDCARDS = ("", "0.0.0.0", "::")
_SIOCGIFADDR = 0x8915  # Linux's ioctl for the IPv4 address of an interface
_LINK_LOCAL_SCOPE = 0x20  # in /proc/net/if_inet6: needs a zone (%eth0) to be used


def interface_addresses(family: socket.AddressFamily) -> list[str]:
    """This machine's addresses in ``family`` (IPv4 or IPv6), loopback first.

    On Linux, every interface's (IPv6 link-local ones left out: they need a zone); elsewhere,
    what the host name resolves to. Never raises: at worst, loopback alone.
    """
    found: list[str] = []
    if sys.platform.startswith("linux"):
        found = _linux_ipv4() if family == socket.AF_INET else _linux_ipv6()
    if not found:
        try:
            infos = socket.getaddrinfo(socket.gethostname(), None, family, socket.SOCK_STREAM)
        except OSError:
            infos = []
        found = [str(info[4][0]) for info in infos]
    loopback = "127.0.0.1" if family == socket.AF_INET else "::1"
    ordered = [loopback] + [a for a in found if not ipaddress.ip_address(a).is_loopback]
    return list(dict.fromkeys(ordered))


def _linux_ipv4() -> list[str]:
    import fcntl

    found = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        for _, name in socket.if_nameindex():
            request = struct.pack("256s", name.encode()[:15])
            try:
                answer = fcntl.ioctl(probe.fileno(), _SIOCGIFADDR, request)
            except OSError:  # the interface has no IPv4 address
                continue
            found.append(socket.inet_ntoa(answer[20:24]))
    return found


def _linux_ipv6() -> list[str]:
    try:
        with open("/proc/net/if_inet6", encoding="ascii") as lines:
            rows = [line.split() for line in lines]
    except OSError:
        return []
    return [
        str(ipaddress.IPv6Address(bytes.fromhex(row[0])))
        for row in rows
        if len(row) >= 4 and int(row[3], 16) != _LINK_LOCAL_SCOPE
    ]


def _socket_order(sock: socket.socket) -> tuple[bool, bool, Any]:
    """IPv4 first, then IPv6; in each, a wildcard or loopback first, then by address."""
    address = ipaddress.ip_address(sock.getsockname()[0])
    local = address.is_unspecified or address.is_loopback
    return sock.family != socket.AF_INET, not local, address


class _QuietLogger(_Redacting):
    """``websockets.server`` without its INFO lines unless asked for; warnings always pass;
    credentials hidden as :class:`_Redacting` hides them.

    A line at INFO or DEBUG goes through only when the level of ``websockets.server`` (or of
    ``websockets``) was set, to that level or lower: ``logging.basicConfig(level=INFO)`` alone
    then does not print a line for every connection.
    """

    def __init__(self) -> None:
        super().__init__(logging.getLogger("websockets.server"), None)

    def isEnabledFor(self, level: int) -> bool:
        if level < logging.WARNING:
            chosen = self.logger.level or logging.getLogger("websockets").level
            if not chosen or level < chosen:
                return False
        return self.logger.isEnabledFor(level)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # keep the extra websockets adds for each connection


class WebSocketsConnection(Connection):
    """One WebSocket connection, server or client side."""

    __slots__ = (
        "_flushing",
        "_frames",
        "_held",
        "_keys",
        "_protocol",
        "_single",
        "_ws",
        "identity",
        "remote_address",
    )

    def __init__(
        self,
        ws: _ServerConnection | _ClientConnection,
        options: Options,
        identity: object = None,
    ) -> None:
        self._ws = ws
        self._protocol = ws.protocol
        self._flushing = False  # a write of the held frames is scheduled
        self._held = 0  # bytes framed since the last write, at most (websockets may write them)
        self._single = False  # the last read handed one message over, and nothing was sent since
        protocol = ws.protocol
        # Whether a held message is framed here (see the module): without extensions, and
        # with websockets' log of frames off, which stays its own. A server's frames go out
        # unmasked, a client's masked with keys from its thread's supply.
        self._frames = not protocol.extensions and not protocol.debug
        self._keys = None if protocol.side is Side.SERVER else _masking_keys
        self.remote_address = ws.remote_address
        self.identity = identity
        ws.write_timeout = _write_timeout(options)
        _name_the_limit(ws.protocol)

    async def recv(self) -> str | bytes:
        ws = self._ws
        if self._held and not ws.recv_messages.frames:  # about to wait: write what is held
            self.flush()
        try:
            return await ws.recv()
        except ConnectionClosed as exc:
            raise _closed(exc, ws) from exc

    async def send(self, message: str | bytes) -> None:
        ws = self._ws
        if isinstance(message, str):  # counted, held and written as its UTF-8 bytes
            message = message.encode()
        length = len(message)
        size = self._held + length
        if (
            length <= CORK_LIMIT
            and not ws.paused
            and self._protocol.state is OPEN
            and ws.transport.get_write_buffer_size() + size <= ws.write_limit_high
        ):
            if not self._frames:
                self._protocol.send_text(message)
            elif self._keys is None:  # a server's text frame, as websockets' send_text frames it
                header = _SHORT_TEXT[length] if length < 126 else _TEXT_126 + _LENGTH(length)
                self._protocol.writes.append(header + message)
            else:  # a client's: masked, with a fresh key each (RFC 6455, 5.3)
                key = self._keys.key()
                header = _SHORT_MASKED[length] if length < 126 else _MASKED_126 + _LENGTH(length)
                self._protocol.writes.append(header + key + apply_mask(message, key))
            if size >= CORK_LIMIT or (self._single and not self._flushing):
                self._single = False  # the first send after a lone message writes at once
                self.flush()
                return
            self._held = size
            if not self._flushing:
                self._flushing = True
                ws.loop.call_soon(self.flush)
            return
        self._held = 0  # websockets' send writes every frame held before its own
        try:
            if ws.paused:  # congested: queue nothing more until it drains
                await self.writable()
            if length >= LARGE_MESSAGE and self._frames and type(message) is bytes:
                async with ws.send_context():  # what websockets' send does around its frame
                    self._protocol.writes += self._apart(message, length)
            else:  # text=True sends bytes as a text frame as they are
                await ws.send(message, text=True)
        except ConnectionClosed as exc:
            raise _closed(exc, ws) from exc

    def _apart(self, message: bytes, length: int) -> list[bytes]:
        """A large message's frame as two writes: the header, then the payload as it is (a
        server's, as a view of it) or masked (a client's), never copied behind the header."""
        keys = self._keys
        if keys is None:
            # A view: asyncio slices what the socket did not take without copying it first.
            return [_TEXT_127 + _LENGTH_64(length), memoryview(message)]  # type: ignore[list-item]
        key = keys.key()
        return [_MASKED_127 + _LENGTH_64(length) + key, apply_mask(message, key)]

    def deliver_to(self, receive: Callable[[str | bytes], None]) -> bool:
        """Hand every message to ``receive`` from the read callback (see the module).

        The messages websockets' queue holds go first, in order. Call it when no ``recv`` is
        waiting; ``recv`` then returns no message and raises at the end as before. A
        ``receive`` that raises is a bug: the error is logged and the connection closed with
        1011, and nothing more is delivered.
        """
        ws = self._ws
        queued = ws.recv_messages.frames.queue
        ws.receive = receive
        ws.pushing = self
        # Frames are taken where they are framed here (no compression, no debug log of
        # frames: see __init__), and the parser is the one take_frames knows.
        ws.direct = self._frames and _parser_as_expected(ws.protocol)
        while queued:
            ws.process_event(queued.popleft())
        ws.recv_messages.maybe_resume()  # the queue is empty: it reads again, if it had paused
        if ws.protocol.state is State.CLOSED:  # nothing more arrives
            ws.receive = None
            ws.pushing = None
        elif self._keys is None:  # a server answers a close after what came before it
            ws.protocol.send_frame = ws.send_close_last  # type: ignore[method-assign]
        return True

    def pause_reading(self) -> None:
        """Stop reading the socket until :meth:`resume_reading`: no message is received but
        those the last read brought, and the peer's sends wait once the buffers between the two
        ends are full. Pings go unanswered meanwhile, so keepalive may end the connection."""
        ws = self._ws
        ws.held_back = True
        ws.transport.pause_reading()

    def resume_reading(self) -> None:
        """Read the socket again after :meth:`pause_reading` (unless websockets' queue of
        messages ``recv`` has not taken is full: then once ``recv`` has taken them down)."""
        ws = self._ws
        ws.held_back = False
        if not ws.recv_messages.paused:
            ws.transport.resume_reading()

    def read_begins(self) -> None:
        """A read hands its messages to the receiver: what they make is held to its end."""
        self._flushing = True  # no write at the end of the turn is needed: read_ends writes

    def read_ends(self) -> None:
        """Every message of a read was handed over: write what they made, in one write."""
        handed = self._ws.handed
        if handed:
            self._single = handed == 1
        if self._held:
            self.flush()
        else:
            self._flushing = False

    @property
    def congested(self) -> bool:
        return self._ws.paused

    def buffered(self) -> int:
        return self._ws.transport.get_write_buffer_size() + self._held

    async def writable(self) -> None:
        ws = self._ws
        if not ws.paused:
            return
        while ws.paused:  # woken together, the first to write may pause it again
            await ws.drained.wait()
        if ws.protocol.state is State.CLOSED:
            raise self.closed()

    def closed(self) -> TransportClosed:
        if self._ws.timed_out:
            assert self._ws.write_timeout is not None
            return WriteTimedOut(self._ws.write_timeout)
        return super().closed()

    def flush(self) -> None:
        """Write the frames held since the last write, in one socket write."""
        self._flushing = False
        self._held = 0
        writes = self._protocol.data_to_send()
        transport = self._ws.transport
        if not writes or transport.is_closing():  # nobody left to write to
            return
        if all(writes):
            transport.write(b"".join(writes))
        else:  # websockets asks for a half-close: let it write, as it does itself
            self._protocol.writes[:0] = writes
            self._ws.send_data()

    async def close(self, code: int = 1000, reason: str = "") -> None:
        ws = self._ws
        if ws.held_back:  # the peer's close frame, or its dropping, must be read
            self.resume_reading()
        protocol = ws.protocol
        if protocol.state is OPEN and protocol.close_rcvd is not None:
            # Begun while the peer's close is being answered (_Watched.send_close_last hands
            # the messages before it over, and one of them led here at once: a handler's first
            # step, an eager task): that answer is this side's close, so wait for the end.
            await ws.wait_closed()
            return
        # websockets bounds the wait for the peer's close frame, not the wait before, for its
        # own to drain behind what a peer that does not read left queued: bound both together.
        try:
            async with asyncio.timeout(ws.close_timeout):  # in this task: its close goes first
                await ws.close(code, reason)
        except TimeoutError:
            ws.transport.abort()
            await ws.wait_closed()

    # Read from the close frames, as _closed does, so that closed() says what recv raised:
    # websockets' own close_code says 1006 where this side failed the connection with 1009.

    @property
    def close_code(self) -> int | None:
        frame = self._final_frame()
        return None if frame is None else frame.code

    @property
    def close_reason(self) -> str:
        frame = self._final_frame()
        return "" if frame is None else frame.reason

    def _final_frame(self) -> Close | None:
        protocol = self._ws.protocol
        if protocol.state is not State.CLOSED:
            return None
        return protocol.close_rcvd if protocol.close_rcvd is not None else protocol.close_sent


def _write_timeout(options: Options) -> float | None:
    """How long a connection may stay congested: ``write_timeout``, and with keepalive on, no
    longer than a ping interval and a ping timeout, in which a ping sent while it is congested
    would have gone unanswered (websockets starts the pong deadline only once it drained)."""
    timeouts = [options.write_timeout]
    if options.ping_interval is not None and options.ping_timeout is not None:
        timeouts.append(options.ping_interval + options.ping_timeout)
    return min((t for t in timeouts if t is not None), default=None)


def _write_limit(options: Options) -> int:
    budget = options.max_queued_bytes
    return DEFAULT_WRITE_LIMIT if budget is None else budget


class WebSocketsListener(Listener):
    """A ``websockets`` server; closing it keeps the connections it accepted.

    ``urls`` are the addresses clients can use: for one host name, that name (``localhost``
    stays ``localhost``); for a wildcard (``0.0.0.0``, ``::``, None), each address of the
    interfaces of its family, loopback first; for several hosts, each. IPv4 comes before IPv6.
    ``url`` is the first, and ``host`` and ``port`` are its. With port 0, each socket has a
    port of its own.
    """

    def __init__(self, server: Server, host: Hosts = None, tls: bool = False) -> None:
        self._server = server
        sockets = sorted(server.sockets, key=_socket_order)  # asyncio's order is a set's
        if isinstance(host, str) and host not in _WILDCARDS:
            address = sockets[0].getsockname()
            self._urls = [_url(host, address[1], tls)]
            self.host, self.port = host, address[1]
        else:
            urls: list[str] = []
            for sock in sockets:
                address = sock.getsockname()
                bound, port = str(address[0]), int(address[1])
                if ipaddress.ip_address(bound).is_unspecified:
                    urls += [_url(a, port, tls) for a in interface_addresses(sock.family)]
                else:
                    urls.append(_url(bound, port, tls))
            self._urls = list(dict.fromkeys(urls))
            self.host = self._urls[0].split("://", 1)[1].rsplit(":", 1)[0].strip("[]")
            self.port = int(sockets[0].getsockname()[1])
        self.url = self._urls[0]

    @property
    def urls(self) -> list[str]:
        return list(self._urls)

    def close(self) -> None:
        self._server.close(close_connections=False)

    async def wait_closed(self) -> None:
        await self._server.wait_closed()


class WebSocketsTransport(Transport):
    """WebSocket over TCP, with ``ws://`` URLs."""

    name = "websockets"

    async def listen(
        self,
        handler: ConnectionHandler,
        host: Hosts,
        port: int,
        options: Options,
        *,
        gate: Gate | None = None,
        ssl: _ssl.SSLContext | None = None,
    ) -> WebSocketsListener:
        # What the gate said of each connection, from process_request to the handler.
        admitted: weakref.WeakKeyDictionary[ServerConnection, Admitted] = (
            weakref.WeakKeyDictionary()
        )

        async def process_request(ws: ServerConnection, request: Request) -> Response | None:
            if gate is None:
                return None
            answer = await gate(_handshake(ws, request))
            if isinstance(answer, Admitted):
                admitted[ws] = answer
                return None
            assert isinstance(answer, Answered)
            response = ws.respond(answer.status, answer.reason)
            for name, value in answer.headers:
                response.headers[name] = value
            return response

        def select_subprotocol(
            ws: ServerConnection, offered: Sequence[Subprotocol]
        ) -> Subprotocol | None:
            answer = admitted.get(ws)
            chosen = None if answer is None else answer.subprotocol
            return Subprotocol(chosen) if chosen is not None and chosen in offered else None

        async def handle(ws: ServerConnection) -> None:
            # When this returns, websockets closes with 1000; when it raises, with 1011.
            assert isinstance(ws, _ServerConnection)
            answer = admitted.pop(ws, None)
            identity = None if answer is None else answer.identity
            await handler(WebSocketsConnection(ws, options, identity))

        if isinstance(host, Sequence) and not isinstance(host, str):
            host = list(host)  # create_server takes a list of hosts
            if not host:
                raise ValueError("no host to listen on: name one, or None for every interface")
        hosts: Any = host
        server = await serve(
            handle,
            hosts,
            port,
            compression=options.compression,
            max_size=options.max_message_size,
            ping_interval=options.ping_interval,
            ping_timeout=options.ping_timeout,
            process_request=process_request,
            select_subprotocol=select_subprotocol,
            ssl=ssl,
            logger=_QuietLogger(),
            write_limit=_write_limit(options),
            create_connection=_ServerConnection,
        )
        return WebSocketsListener(server, host, tls=ssl is not None)

    async def connect(
        self,
        url: str,
        options: Options,
        *,
        headers: Sequence[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | None = None,
    ) -> WebSocketsConnection:
        # The caller bounds the whole opening; websockets' own timeout would be a second bound.
        tls: dict[str, Any] = {"ssl": ssl} if ssl is not None and url[:4].lower() == "wss:" else {}
        try:
            ws = await connect(
                url,
                max_size=options.max_message_size,
                ping_interval=options.ping_interval,
                ping_timeout=options.ping_timeout,
                compression=options.compression,
                write_limit=_write_limit(options),
                open_timeout=None,
                additional_headers=list(headers) or None,
                **tls,
                create_connection=_ClientConnection,
                logger=_Redacting(logging.getLogger("websockets.client")),
            )
        except (OSError, EOFError, WebSocketException) as exc:
            raise _refusal(exc, url) from exc
        assert isinstance(ws, _ClientConnection)
        return WebSocketsConnection(ws, options)

    def check_url(self, url: str) -> None:
        try:
            parse_uri(url)
        except (InvalidURI, ValueError) as exc:  # ValueError: a port out of range
            raise ValueError(f"not a WebSocket URL: {url!r} ({exc})") from exc
