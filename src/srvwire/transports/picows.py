"""The native WebSocket transport, on ``picows``' callback API: the only module that imports it.

``picows`` parses frames in C and calls :meth:`PicowsConnection.on_ws_frame` for each one, in
the event loop's read callback: there is no asyncio stream and no reader task per connection.
This module adds what srvwire's rules (:mod:`srvwire.transports.base`) ask and ``picows``
leaves to its user:

* **Whole messages.** Fragments are joined into one ``bytearray``; a text message is decoded
  once (one that came in one frame straight from ``picows``' read buffer, with no ``bytes`` of
  it made first), and one that is not UTF-8 fails the connection with 1007. A message larger
  than ``max_message_size`` fails it with 1009, and so does a fragment that would make one,
  before it is copied; the reason names the side and the setting (``over the server's
  max_message_size (message of 2000 bytes, limit 1000 bytes)``), so that the peer's error says
  what to raise. Messages received before either are still
  delivered. The bytes held for one frame are bounded too: ``picows`` refuses a frame over
  :data:`FRAME_SLACK` times the limit as soon as its header arrives (1009, its own reason in
  the peer's close, and ``over the client's (or server's) max_message_size (...)`` around it
  here); a
  message that arrived in the same read just before that frame is then lost with
  the connection.
* **Flow control both ways.** ``send`` puts the message in the connection's buffer and waits
  only while ``picows`` says the socket's buffer is past its high-water mark
  (``pause_writing``/``resume_writing``). A server frames its own messages (unmasked: a
  header and the bytes) and *corks* them: the replies made while draining one read go out in
  one write, after the last frame the read brought (the replies made in ``on_ws_frame``), when
  ``recv`` finds nothing more to read, at the loop's next turn, or past the budget, whichever
  comes first; a reply made while the last frame of a read is handed over, with nothing
  corked (a read of one call), goes out at once through ``picows``' ``send``, as the cork's
  write of a lone message would have sent it at the read's end. A client corks its small
  messages too (at most :data:`CLIENT_CORK_LIMIT` bytes), until the loop's next turn or
  :data:`CLIENT_WRITE_AT` bytes: the calls its callers
  make in one turn (a pipelined client woken by a read of many replies) go out in a few
  writes, each frame masked with a fresh key from ``os.urandom``, as RFC 6455 asks (by
  ``websockets``' masking in C, the one thing of that library used here). The first
  message sent after a read that brought a single one is written at once instead, by
  ``picows`` (a caller that waited for its reply and calls again: nothing else is coming this
  turn), and so is a larger message, or a lone one when the turn ends.
  The budget (``max_queued_bytes``) is the socket buffer's high-water mark: a ``send`` that
  finds the connection congested waits before it queues anything, and a
  connection congested for ``write_timeout`` (or a ping period, when sooner) is dropped at once
  and ends with :class:`~srvwire.transports.base.WriteTimedOut`. Messages not yet received
  are held in a queue; past :data:`READ_HIGH_WATER` of them the socket is not read until
  ``recv`` has taken them down to :data:`READ_LOW_WATER`. Once given a receiver
  (:meth:`PicowsConnection.deliver_to`, what a client's link and a server's connection do), a
  connection hands it each message from ``on_ws_frame`` instead, and queues nothing; the
  receiver stops and restarts the reading of the socket itself (``pause_reading``,
  ``resume_reading``).
* **Keepalive** as ``websockets`` does it: a ping every ``ping_interval``; no pong within
  ``ping_timeout`` fails the connection with 1011 ``keepalive ping timeout``.
* **Closing.** A close frame received is answered with the same code, then the TCP connection
  is closed. :meth:`PicowsConnection.close` waits for the peer's answer at most
  :data:`CLOSE_TIMEOUT` seconds, then drops the connection.
* **The gate at the upgrade.** ``picows`` hands the opening request to a synchronous
  function and sends what it returns: a listener (101) or an HTTP response. The gate is a
  coroutine, so it is run here to its end without the loop: srvwire's own policy
  (:class:`~srvwire.handshake.EdgePolicy`) and a synchronous authenticator never wait. An
  authenticator that does wait is refused with 500 and an error in the log that says so; use
  the ``websockets`` transport for it.
* **No compression**: ``picows`` has no permessage-deflate, so ``compression="deflate"`` is
  refused with a ``ValueError`` on both ends. No extension is ever negotiated, so a frame
  with a reserved bit set fails the connection with 1002 and ``websockets``' reason
  (``reserved bits must be 0``), whatever its opcode: ``on_ws_frame`` answers pings itself
  (``picows``' own pong is off), after that check, so such a ping gets no pong; the replies
  corked before a ping is read are written before its pong, as on ``websockets``.

Exceptions are mapped here and nowhere else: how a connection ended (the close frame received,
else the one sent, else none) -> :class:`TransportClosed`; ``OSError`` and ``picows``' errors
while connecting -> :class:`TransportError`, saying why as the ``websockets`` transport does.
"""

from __future__ import annotations

import asyncio
import ctypes
import logging
import mmap
import os
import socket
import ssl as _ssl
import struct
import urllib.parse
from collections import deque
from collections.abc import Callable, Coroutine, Sequence
from http import HTTPStatus
from typing import Any

from picows import (
    WSError,
    WSFrame,
    WSHandshakeError,
    WSListener,
    WSMsgType,
    WSTransport,
    WSUpgradeRequest,
    WSUpgradeResponse,
    WSUpgradeResponseWithListener,
    ws_connect,
)
from picows.picows import WSAutoPingStrategy, WSProtocol  # type: ignore[attr-defined]

try:  # websockets' C masking (websockets is a dependency of srvwire in any case): nothing else
    from websockets.speedups import apply_mask  # of websockets is used here
except ImportError:  # websockets ships it compiled for the common platforms
    from websockets.utils import apply_mask

from srvwire.transports.base import (
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
)

__all__ = ["PicowsConnection", "PicowsListener", "PicowsTransport"]

READ_HIGH_WATER = 64
"""Messages received and not yet taken by ``recv`` at which the socket is no longer read."""
READ_LOW_WATER = 16
"""Messages still queued at which reading the socket resumes."""
HANDSHAKE_TIMEOUT = 10.0
"""Seconds a server waits for a new connection's TLS handshake, and then for its opening
request (as ``websockets``)."""
CLOSE_TIMEOUT = 10.0
"""Seconds :meth:`PicowsConnection.close` waits for the peer's close frame (as ``websockets``)."""
NO_LIMIT = 2**62
"""``picows``' frame limit when ``max_message_size`` is None."""
DEFAULT_BUDGET = 2**16
"""The budget of bytes waiting to be sent when ``max_queued_bytes`` is None: the socket
buffer's high-water mark (its low one is a quarter). A server writes its corked frames at
once past a quarter of it, instead of at the end of the read (see
:meth:`PicowsConnection._flush`), so at most the budget and a quarter wait, plus one message."""
PICOWS_COPIES = 8192
"""The largest message ``picows``' ``send`` copies into its own buffer with its header. A larger
one is written as two parts, the header a view of a buffer ``picows`` reuses for the next
frame; where asyncio keeps such a view unsent (``writelines`` from Python 3.12), the next frame
would overwrite the header. So a larger lone message is framed and written here, as a copy."""
WRITE_APART = 2**16
"""A server's held message larger than this, when it is the last one held, is not joined to
what precedes it: the frames before it, its header and its first ``WRITE_APART`` bytes go in
one write, then a view of the rest in a second, which the socket takes straight from the
message. Joined, every byte of it was copied once more (see docs/performance.md, "Large
messages on the picows transport")."""
CLIENT_WRITE_AT = 2**12
"""Bytes of held messages at which a client writes them without waiting for the turn's end:
a pipelined client's calls then reach the server in a few writes, and the server works on the
first while the client makes the next, instead of the two ends taking turns."""
CLIENT_CORK_LIMIT = CLIENT_WRITE_AT - 1
"""The largest message a client corks (see the module), as the ``websockets`` transport's
client: one that reaches :data:`CLIENT_WRITE_AT` alone is written at once by ``picows``, after
what is held."""
RELEASE_AT = 2**16
"""A frame larger than this, once ``picows`` is done with it, has the pages of ``picows``' read
buffer past its first :data:`KEEP_READ` free bytes handed back to the system (see
:func:`_release_read_buffer`): the buffer grew to hold the frame and never shrinks, so without this
every connection that once received a large message keeps that much resident memory."""
KEEP_READ = 2**14
"""Free bytes of ``picows``' read buffer, past what it holds, kept resident for the next reads."""
FRAME_SLACK = 4
"""``picows``' own frame limit is this many times ``max_message_size`` (see the module)."""

_TLS_HANDSHAKE_RECORD = 0x16  # the first byte of a TLS ClientHello
_TEXT = WSMsgType.TEXT
_BINARY = WSMsgType.BINARY
_CONTINUATION = WSMsgType.CONTINUATION
_CLOSE = WSMsgType.CLOSE
_PING = WSMsgType.PING
_PONG = WSMsgType.PONG

log = logging.getLogger(__name__)

_MADV_DONTNEED: int | None = getattr(mmap, "MADV_DONTNEED", None)  # None where no madvise
_madvise: Any = None
if _MADV_DONTNEED is not None:
    _madvise = ctypes.CDLL(None, use_errno=True).madvise
    _madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    _madvise.restype = ctypes.c_int


def _header(size: int) -> bytes:
    """The header of an unmasked, final text frame of ``size`` bytes (RFC 6455, 5.2)."""
    if size < 126:
        return bytes((0x81, size))
    if size < 2**16:
        return struct.pack("!BBH", 0x81, 126, size)
    return struct.pack("!BBQ", 0x81, 127, size)


_HEADER = [_header(size) for size in range(126)]
_HEADER_16 = bytes((0x81, 126))  # then the size in two bytes
_MASKED_HEADER = [bytes((0x81, 0x80 | size)) for size in range(126)]


def _masked_frames(messages: Sequence[bytes]) -> bytes:
    """Frame ``messages`` as a client must (RFC 6455, 5.3): each a final text frame whose
    payload is masked with its own fresh key (``picows`` has no masking of its own to call;
    websockets' is in C), all in one ``bytes`` to write at once."""
    keys = os.urandom(4 * len(messages))
    parts: list[bytes] = []
    at = 0
    for data in messages:
        size = len(data)
        key = keys[at : at + 4]
        at += 4
        parts += (
            _MASKED_HEADER[size] if size < 126 else struct.pack("!BBH", 0x81, 0x80 | 126, size),
            key,
            apply_mask(data, key),
        )
    return b"".join(parts)


def _release_read_buffer(protocol: WSProtocol) -> None:
    """Hand back to the system the pages of ``protocol``'s read buffer past its first
    :data:`KEEP_READ` free bytes (``madvise(MADV_DONTNEED)``): they stay the buffer's, and read
    as zeros when a later read fills them, but are no longer resident. Nothing is copied.

    ``picows``' ``get_buffer`` returns the buffer's free part, from the end of what it holds to
    its end: what the next read may fill, so nothing there is read before it is written. Run
    from the event loop between reads (never inside one: the event loops srvwire runs on take
    a buffer and fill it within one callback)."""
    if _madvise is None:
        return
    view = protocol.get_buffer(-1)
    start = ctypes.addressof(ctypes.c_char.from_buffer(view))
    page = mmap.PAGESIZE
    first = -(-(start + KEEP_READ) // page) * page  # the first whole page past KEEP_READ
    end = (start + len(view)) // page * page
    if end > first:
        _madvise(first, end - first, _MADV_DONTNEED)


def _url(host: str, port: int, tls: bool = False) -> str:
    """Return the ``ws://`` (``wss://``) URL of ``host``:``port``, an IPv6 host in brackets."""
    scheme = "wss" if tls else "ws"
    return f"{scheme}://[{host}]:{port}" if ":" in host else f"{scheme}://{host}:{port}"


def _code(value: Any) -> int:
    """A close code as an ``int``, whether ``picows`` gives its enum or a number."""
    return int(getattr(value, "value", value))


class PicowsConnection(WSListener, Connection):
    """One WebSocket connection, server or client side: ``picows``' listener for it, too.

    ``picows`` calls the ``on_ws_*`` methods and ``pause_writing``/``resume_writing`` from the
    event loop; srvwire calls :meth:`recv`, :meth:`send` and :meth:`close`.
    """

    __slots__ = (
        "_answering",
        "_awaiting_pong",
        "_budget",
        "_corked",
        "_corked_size",
        "_ended",
        "_failed",
        "_flush_due",
        "_framing",
        "_gone",
        "_handed",
        "_keepalive",
        "_large",
        "_limit",
        "_loop",
        "_messages",
        "_parts",
        "_parts_text",
        "_ping_interval",
        "_ping_timeout",
        "_pong_due",
        "_reading",
        "_receive",
        "_received",
        "_sent",
        "_single",
        "_stall",
        "_timed_out",
        "_waiter",
        "_writable",
        "_write_timeout",
        "_ws",
        "congested",
        "identity",
        "remote_address",
    )

    congested: bool  # see __init__

    def __init__(self, options: Options, identity: object = None) -> None:
        super().__init__()
        self.identity = identity
        self.remote_address: Any = None
        self._loop = asyncio.get_running_loop()
        self._ws: WSTransport | None = None
        self._limit = options.max_message_size
        # A frame past this is over the limit, or grew picows' read buffer (see _whole).
        self._large = RELEASE_AT if self._limit is None else min(self._limit, RELEASE_AT)
        self._ping_interval = options.ping_interval
        self._ping_timeout = options.ping_timeout
        self._keepalive: asyncio.TimerHandle | None = None  # the next ping, or its deadline
        self._awaiting_pong = False
        # The latest ping received while congested, answered once it drains (see on_ws_frame).
        self._pong_due: bytes | None = None
        self._messages: deque[str | bytes] = deque()
        self._waiter: asyncio.Future[None] | None = None  # a recv waiting for a message
        self._reading = True
        self._receive: Callable[[str | bytes], None] | None = None  # see deliver_to
        self._parts: bytearray | None = None  # the fragments of a message being received
        self._parts_text = False
        self._writable: asyncio.Future[None] | None = None  # set while writing is paused
        # Whether the socket's buffer is past its high-water mark: a send would wait. An
        # attribute, not a property: a server reads it for every message it is handed.
        self.congested = False
        # Not yet written (see _flush): a server's frames, header and payload; a client's
        # messages, framed and masked when written.
        self._corked: list[bytes] = []
        self._corked_size = 0
        self._handed = 0  # messages handed over since the read began
        self._single = False  # the last read handed one over, and nothing was sent since
        # Whether the cork will be flushed without send asking: a _flush_later is scheduled,
        # or on_ws_frame is running (it flushes after the read's last frame).
        self._flush_due = False
        # Whether this side failed the connection: nothing read after that is delivered
        # (RFC 6455, section 7.1.7), such as a message behind the failing frame in its read.
        self._failed = False
        # Whether the last frame of a read is being handed over: a server's first small
        # message sent meanwhile, with nothing corked, goes out at once (see send).
        self._answering = False
        self._framing = False  # whether send frames here: on a server (no mask), once open
        self._received: tuple[int, str] | None = None  # the close frame received
        self._sent: tuple[int, str] | None = None  # the close frame sent
        self._ended: TransportClosed | None = None  # set once the TCP connection is gone
        self._gone: asyncio.Future[None] = self._loop.create_future()
        budget = options.max_queued_bytes
        self._budget = DEFAULT_BUDGET if budget is None else budget
        # How long congestion may last: write_timeout, or a ping period when that is sooner
        # (a ping cannot be answered through a buffer that does not drain).
        limits = [options.write_timeout]
        if options.ping_interval is not None and options.ping_timeout is not None:
            limits.append(options.ping_interval + options.ping_timeout)
        self._write_timeout = min((t for t in limits if t is not None), default=None)
        self._stall: asyncio.TimerHandle | None = None
        self._timed_out = False

    # What picows calls.

    def on_ws_connected(self, transport: WSTransport) -> None:
        self._ws = transport
        self._framing = not transport.is_client_side
        transport.underlying_transport.set_write_buffer_limits(
            high=self._budget, low=self._budget // 4
        )
        self.remote_address = transport.underlying_transport.get_extra_info("peername")
        if self._ping_interval is not None:
            self._keepalive = self._loop.call_later(self._ping_interval, self._ping)

    def on_ws_frame(self, transport: WSTransport, frame: WSFrame) -> None:
        kind = frame.msg_type
        last = frame.last_in_buffer
        due = self._flush_due
        self._flush_due = True
        self._answering = last
        try:
            if frame.rsv1 or frame.rsv2 or frame.rsv3:
                # No extension is ever negotiated here (RFC 6455, section 5.2): the frame is
                # not taken, and the close says so as websockets' does.
                self._fail(1002, "reserved bits must be 0")
            elif kind is _TEXT or kind is _BINARY:
                if self._parts is not None:
                    self._fail(1002, "a new message began before the last one ended")
                elif frame.fin:
                    self._whole(frame, kind is _TEXT)
                else:
                    self._parts_text = kind is _TEXT
                    self._parts = bytearray()
                    self._add_part(frame)
            elif kind is _CONTINUATION:
                parts = self._parts
                if parts is None:
                    self._fail(1002, "a continuation frame without a message to continue")
                elif self._add_part(frame) and frame.fin:
                    self._parts = None
                    self._assembled(parts)
            elif kind is _CLOSE:
                code = _code(frame.get_close_code())
                # A close frame without a code is 1005 (RFC 6455, section 7.1.5).
                self._received = (code or 1005, frame.get_close_reason() or "")
                if not transport.is_close_frame_sent:
                    self._send_close(code or 1000, self._received[1] if code else "")
                transport.disconnect()
            elif kind is _PING:
                if not self._failed:  # as websockets, whose parser stops at a failure
                    if self._corked:  # the replies made before it was read go out first
                        self._flush()
                    if self.congested:  # only the latest, once it drains (RFC 6455, 5.5.3)
                        self._pong_due = frame.get_payload_as_bytes()
                    elif not transport.underlying_transport.is_closing():
                        transport.send_pong(frame.get_payload_as_bytes())
            elif kind is _PONG:
                self._pong()
        finally:
            self._flush_due = due
            self._answering = False
        if last:
            # What a client's next send does depends on what this read handed over (see send).
            self._single = self._handed == 1
            self._handed = 0
            if self._corked:  # replies made while taking it (a server's, given a receiver)
                self._flush()  # everything this read brought is answered: in one write
        elif self._corked and not due:
            self._flush_due = True
            self._loop.call_soon(self._flush_later)

    def on_ws_disconnected(self, transport: WSTransport) -> None:
        if self._sent is None:
            # picows itself may have failed the connection (a frame over its limit).
            handshake = transport.close_handshake
            sent = None if handshake is None else handshake.sent
            if sent is not None:
                code, reason = _code(sent.code), sent.reason or ""
                if code == 1009 and not handshake.recv_then_sent:  # a frame over its limit
                    side = "client" if transport.is_client_side else "server"
                    named = f"over the {side}'s max_message_size ({reason})"
                    if self._received == (code, reason):  # the peer's echo of it
                        self._received = (code, named)
                    reason = named
                self._sent = (code, reason)
                if transport.is_client_side:
                    # picows keeps the error for wait_disconnected(), which is not awaited
                    # otherwise: take it, so asyncio does not log it as never retrieved.
                    waiting = self._loop.create_task(transport.wait_disconnected())
                    waiting.add_done_callback(_taken)
        final = self._received if self._received is not None else self._sent
        if self._timed_out:
            assert self._write_timeout is not None
            self._ended = WriteTimedOut(self._write_timeout)
        else:
            self._ended = TransportClosed(None) if final is None else TransportClosed(*final)
        if self._keepalive is not None:
            self._keepalive.cancel()
            self._keepalive = None
        self._wake()
        self.resume_writing()
        if not self._gone.done():
            self._gone.set_result(None)

    def pause_writing(self) -> None:
        if self._writable is None:
            self._writable = self._loop.create_future()
            self.congested = True
            if self._write_timeout is not None and self._ended is None:
                self._stall = self._loop.call_later(self._write_timeout, self._stalled)

    def resume_writing(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None
        writable, self._writable = self._writable, None
        self.congested = False
        pong, self._pong_due = self._pong_due, None
        ws = self._ws
        if pong is not None and ws is not None and self._ended is None:
            if not ws.underlying_transport.is_closing():
                ws.send_pong(pong)
        if writable is not None and not writable.done():
            writable.set_result(None)

    # What srvwire calls.

    async def recv(self) -> str | bytes:
        messages = self._messages
        while not messages:
            if self._corked:
                self._flush()  # the replies to everything read so far, in one write
            if self._ended is not None:
                raise self._closing()
            waiter = self._waiter = self._loop.create_future()
            try:
                await waiter
            finally:
                self._waiter = None
        message = messages.popleft()
        if not self._reading and len(messages) <= READ_LOW_WATER and self._ws is not None:
            self._reading = True
            self._ws.underlying_transport.resume_reading()
        return message

    async def send(self, message: str | bytes) -> None:
        if self._writable is not None:
            await self.writable()  # congested: queue nothing until the peer has read
        ws = self._ws
        if ws is None or self._ended is not None or ws.is_close_frame_sent:
            raise self._closing()
        data = message.encode() if isinstance(message, str) else message
        if self._framing:
            corked = self._corked
            if self._answering and len(data) <= PICOWS_COPIES and not corked:
                # The reply to the last frame of a read, and nothing held: what _flush would
                # do with it at the read's end, done now, without framing it here first.
                self._answering = False
                ws.send(_TEXT, data)
                return
            if not self._flush_due:
                self._flush_due = True
                self._loop.call_soon(self._flush_later)
            size = len(data)
            corked.append(
                _HEADER[size]  # a text frame, unmasked
                if size < 126
                else _HEADER_16 + size.to_bytes(2, "big")
                if size < 2**16
                else _header(size)
            )
            corked.append(data)
            self._corked_size += size
            if self._corked_size >= self._budget // 4:
                self._flush()
        elif self._single or len(data) > CLIENT_CORK_LIMIT:  # a client's, at once
            self._single = False
            if self._corked:
                self._flush()
            ws.send(_TEXT, data)  # picows frames and masks it
        else:  # a client's, corked until the loop's next turn (see the module)
            if not self._flush_due:
                self._flush_due = True
                self._loop.call_soon(self._flush_later)
            self._corked.append(data)
            self._corked_size += len(data)
            if self._corked_size >= CLIENT_WRITE_AT or self._corked_size >= self._budget // 4:
                self._flush()

    def deliver_to(self, receive: Callable[[str | bytes], None]) -> bool:
        # Reading paused for the queue resumes first: nothing is queued once this returns, and a
        # receiver that pauses reading while it takes the queued messages must find it reading.
        if not self._reading and self._ws is not None:
            self._reading = True
            self._ws.underlying_transport.resume_reading()
        messages = self._messages
        while messages:
            receive(messages.popleft())
        self._receive = receive
        return True

    def pause_reading(self) -> None:
        """Read the socket no more until :meth:`resume_reading` (a receiver's choice, see
        :meth:`deliver_to`); once the closing handshake began, the socket is read to its end."""
        ws = self._ws
        if self._reading and ws is not None and self._ended is None and not ws.is_close_frame_sent:
            self._reading = False
            ws.underlying_transport.pause_reading()

    def resume_reading(self) -> None:
        if not self._reading and self._ws is not None:
            self._reading = True
            self._ws.underlying_transport.resume_reading()

    def buffered(self) -> int:
        ws = self._ws
        if ws is None:
            return self._corked_size
        return ws.underlying_transport.get_write_buffer_size() + self._corked_size

    async def writable(self) -> None:
        """Wait until the connection is not :attr:`congested`; raise :class:`TransportClosed`
        when it ended while this waited."""
        if self._writable is None:
            return
        while self._writable is not None:
            await asyncio.shield(self._writable)
        if self._ended is not None:
            raise self._closing()

    async def close(self, code: int = 1000, reason: str = "") -> None:
        ws = self._ws
        if ws is None or self._gone.done():
            return
        if not ws.is_close_frame_sent:
            self._send_close(code, reason)
        if not self._reading:  # the peer's close frame, or its dropping, must be read
            self._reading = True
            ws.underlying_transport.resume_reading()
        try:
            await asyncio.wait_for(asyncio.shield(self._gone), CLOSE_TIMEOUT)
        except TimeoutError:
            ws.disconnect(graceful=False)
            await asyncio.shield(self._gone)

    @property
    def close_code(self) -> int | None:
        return None if self._ended is None else self._ended.code

    @property
    def close_reason(self) -> str:
        return "" if self._ended is None else self._ended.reason

    def __repr__(self) -> str:
        state = "open" if self._ended is None else str(self._ended)
        return f"<PicowsConnection {self.remote_address!r}: {state}>"

    # Helpers.

    def _whole(self, frame: WSFrame, text: bool) -> None:
        """Deliver a message that came in one frame. Its size is checked before it is copied,
        and a text message is decoded straight from ``picows``' buffer: one copy, the
        ``str``, with no ``bytes`` of it made first (see docs/performance.md, "Large messages
        on the picows transport")."""
        size = frame.payload_size
        if size > self._large:  # one check on the path of small messages
            limit = self._limit
            if limit is not None and size > limit:
                self._fail(1009, self._too_big(size))
                return
            self._loop.call_soon(self._release)  # once picows is done with this read
        if text:
            try:
                message: str | bytes = frame.get_payload_as_utf8_text()
            except UnicodeDecodeError as exc:
                self._fail(1007, f"{exc.reason} at position {exc.start}")
                return
        else:
            message = frame.get_payload_as_bytes()
        self._deliver(message)

    def _add_part(self, frame: WSFrame) -> bool:
        """Append a fragment's payload to the message being received; fail with 1009 (and
        return False) instead, without copying it, when it would take the message past the
        size limit."""
        parts = self._parts
        assert parts is not None
        limit = self._limit
        if limit is not None and len(parts) + frame.payload_size > limit:
            self._parts = None
            self._fail(1009, self._too_big(len(parts) + frame.payload_size))
            return False
        parts += frame.get_payload_as_memoryview()  # copied here, within on_ws_frame
        if frame.payload_size > RELEASE_AT:
            self._loop.call_soon(self._release)
        return True

    def _assembled(self, payload: bytearray) -> None:
        """Deliver a message whose fragments :meth:`_add_part` joined, decoded once."""
        if self._parts_text:
            try:
                message: str | bytes = payload.decode()
            except UnicodeDecodeError as exc:
                self._fail(1007, f"{exc.reason} at position {exc.start}")
                return
        else:
            message = bytes(payload)
        self._deliver(message)

    def _deliver(self, message: str | bytes) -> None:
        """Hand ``message`` to the receiver, or queue it for ``recv``; drop it once this side
        has failed the connection."""
        if self._failed:
            return
        if self._receive is not None:
            self._handed += 1
            self._receive(message)
            return
        messages = self._messages
        messages.append(message)
        if len(messages) >= READ_HIGH_WATER and self._reading and self._ws is not None:
            self._reading = False
            self._ws.underlying_transport.pause_reading()
        self._wake()

    def _too_big(self, size: int) -> str:
        """The close reason of a message over the limit: the side and the setting to raise."""
        side = "client" if self._ws is not None and self._ws.is_client_side else "server"
        limit = self._limit
        return f"over the {side}'s max_message_size (message of {size} bytes, limit {limit} bytes)"

    def _release(self) -> None:
        """Give back the pages of picows' read buffer that a large frame grew it by."""
        ws = self._ws
        if ws is not None and self._ended is None:
            _release_read_buffer(ws.underlying_transport.get_protocol())

    def _wake(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def _flush_later(self) -> None:
        self._flush_due = False
        self._flush()

    def _flush(self) -> None:
        """Write the frames ``send`` corked, in one write: on a server, every reply made while
        draining one read goes out in one system call instead of one each; on a client, every
        call made in one turn of the loop. A lone message (on a server, of at most
        :data:`PICOWS_COPIES` bytes) goes out through ``picows``' own ``send``, which frames it
        (and masks it, on a client) and makes the system call in C."""
        corked = self._corked
        if not corked:
            return
        ws = self._ws
        # Nothing may follow a close frame (picows itself may have sent one, on a bad frame).
        if ws is None or self._ended is not None or ws.is_close_frame_sent:
            corked.clear()
            self._corked_size = 0
        elif not self._framing:  # a client's messages
            self._corked_size = 0
            if len(corked) == 1:
                ws.send(_TEXT, corked.pop())
            else:
                data = _masked_frames(corked)
                corked.clear()
                ws.underlying_transport.write(data)
        elif len(corked) == 2 and len(corked[1]) <= PICOWS_COPIES:  # one frame, small
            message = corked[1]
            corked.clear()
            self._corked_size = 0
            ws.send(_TEXT, message)
        elif len(corked[-1]) > WRITE_APART:  # a large message last: its bulk is not copied
            message = corked.pop()
            corked.append(message[:WRITE_APART])
            head = b"".join(corked)
            corked.clear()
            self._corked_size = 0
            underlying = ws.underlying_transport
            underlying.write(head)  # what came before, the header, the message's first bytes
            underlying.write(memoryview(message)[WRITE_APART:])
        else:
            data = b"".join(corked)
            corked.clear()
            self._corked_size = 0
            ws.underlying_transport.write(data)

    def _send_close(self, code: int, reason: str) -> None:
        assert self._ws is not None
        self._flush()
        self._sent = (code, reason)
        self._ws.send_close(code, reason.encode())  # type: ignore[arg-type]  # any code

    def _fail(self, code: int, reason: str, *, graceful: bool = True) -> None:
        """End the connection on this side's error: a close frame, then the TCP connection
        (``graceful``: once what is buffered is written; else at once, dropping it)."""
        ws = self._ws
        if ws is None or self._ended is not None:
            return
        self._failed = True
        if not ws.is_close_frame_sent:
            self._send_close(code, reason)
        ws.disconnect(graceful)

    def _closing(self) -> TransportClosed:
        """How the connection ended, or is ending, for ``recv`` and ``send`` to raise."""
        if self._timed_out:
            assert self._write_timeout is not None
            return WriteTimedOut(self._write_timeout)
        if self._ended is not None:
            return TransportClosed(self._ended.code, self._ended.reason)
        final = self._received if self._received is not None else self._sent
        return TransportClosed(None) if final is None else TransportClosed(*final)

    def _stalled(self) -> None:
        """Close now: the peer has not read for the write timeout, so a closing handshake
        would wait for nothing."""
        self._stall = None
        self._timed_out = True
        if self._ws is not None:
            self._ws.disconnect(graceful=False)

    def _ping(self) -> None:
        ws = self._ws
        if ws is None or self._ended is not None:
            return
        ws.send_ping()
        self._awaiting_pong = True
        if self._ping_timeout is not None:
            self._keepalive = self._loop.call_later(self._ping_timeout, self._no_pong)
        else:
            self._keepalive = None

    def _pong(self) -> None:
        if not self._awaiting_pong:
            return  # a pong nobody asked for: the keepalive's timer stays as it is
        self._awaiting_pong = False
        if self._keepalive is not None:
            self._keepalive.cancel()
        if self._ping_interval is not None and self._ended is None:
            self._keepalive = self._loop.call_later(self._ping_interval, self._ping)

    def _no_pong(self) -> None:
        self._keepalive = None
        # At once: a peer that does not answer may not read either, and then a graceful
        # close would wait for the buffer to drain forever.
        self._fail(1011, "keepalive ping timeout", graceful=False)


def _check_options(options: Options) -> None:
    """Refuse what ``picows`` cannot do, saying what to do instead."""
    if options.compression is not None:
        raise ValueError(
            "the picows transport has no compression: pass compression=None, "
            "or use the websockets transport"
        )


def _taken(task: asyncio.Task[None]) -> None:
    """Retrieve what ``task`` raised: how its connection ended is known already."""
    if not task.cancelled():
        task.exception()


def _frame_limit(options: Options) -> int:
    """The frame size at which ``picows`` itself fails the connection (see the module)."""
    limit = options.max_message_size
    return NO_LIMIT if limit is None else FRAME_SLACK * limit + 2**16


def _decide(gate: Gate, handshake: Handshake) -> Admitted | Answered:
    """Run ``gate`` on ``handshake`` to its end without the event loop (see the module)."""
    coroutine = gate(handshake)
    assert isinstance(coroutine, Coroutine)
    try:
        coroutine.send(None)
    except StopIteration as done:
        answer: Admitted | Answered = done.value
        return answer
    coroutine.close()
    log.error(
        "refused %r: its check waited for I/O, which the picows transport cannot do during "
        "the opening handshake; use an authenticator that answers at once, or the "
        "websockets transport",
        handshake,
    )
    return Answered(500, "the server failed to check the credentials\n")


def _response(answer: Answered) -> WSUpgradeResponse:
    """The plain HTTP response an :class:`Answered` request gets."""
    response: WSUpgradeResponse = WSUpgradeResponse.create_error_response(
        400, answer.reason.encode(), list(answer.headers)
    )
    response.status = HTTPStatus(answer.status)  # create_error_response takes only 4xx/5xx
    return response


class PicowsListener(Listener):
    """A ``picows`` server; closing it keeps the connections it accepted, and
    :meth:`wait_closed` waits for their handlers too.

    ``urls``: for one host name, that name (``localhost`` stays ``localhost``); for several
    hosts or a wildcard, the address each socket is bound to, IPv4 first (a wildcard stays a
    wildcard here, where the websockets transport lists the interfaces' addresses).
    """

    def __init__(self, server: asyncio.Server, handlers: set[asyncio.Task[None]], host: Hosts,
                 tls: bool) -> None:  # fmt: skip
        self._server = server
        self._handlers = handlers
        sockets = sorted(server.sockets, key=lambda sock: sock.family != socket.AF_INET)
        port = int(sockets[0].getsockname()[1])
        if isinstance(host, str) and host not in ("", "0.0.0.0", "::"):
            self._urls = [_url(host, port, tls)]
        else:
            bound = [sock.getsockname()[:2] for sock in sockets]
            self._urls = list(dict.fromkeys(_url(str(a), int(p), tls) for a, p in bound))
        self.url = self._urls[0]
        self.host = self.url.split("://", 1)[1].rsplit(":", 1)[0].strip("[]")
        self.port = port

    @property
    def urls(self) -> list[str]:
        return list(self._urls)

    def close(self) -> None:
        self._server.close()

    async def wait_closed(self) -> None:
        await self._server.wait_closed()
        while self._handlers:
            # Not gather: from Python 3.12 it completes without yielding when every task is
            # done, and a task that just ended leaves the set only in a callback the loop has
            # yet to run, so this would turn forever.
            await asyncio.wait(set(self._handlers))


class PicowsTransport(Transport):
    """WebSocket over TCP on ``picows``, with ``ws://`` URLs: the same wire as
    ``websockets``, so either end may use either transport."""

    name = "picows"

    async def listen(
        self,
        handler: ConnectionHandler,
        host: Hosts,
        port: int,
        options: Options,
        *,
        gate: Gate | None = None,
        ssl: _ssl.SSLContext | None = None,
    ) -> PicowsListener:
        _check_options(options)
        loop = asyncio.get_running_loop()
        handlers: set[asyncio.Task[None]] = set()
        logger = _WithoutConnectionNews(logging.getLogger("picows.server"))

        async def run(connection: PicowsConnection) -> None:
            # As websockets does: 1000 when the handler returns, 1011 when it raises.
            try:
                await handler(connection)
            except Exception:
                log.exception("connection handler failed")
                await connection.close(1011)
            else:
                await connection.close()

        def started(connection: PicowsConnection) -> None:
            task = loop.create_task(run(connection))
            handlers.add(task)
            task.add_done_callback(handlers.discard)

        def protocol() -> WSProtocol:
            ws_protocol: WSProtocol

            def accept(request: WSUpgradeRequest) -> Any:
                identity: Any = None
                subprotocol = None
                if gate is not None:
                    answer = _decide(gate, _handshake(ws_protocol, request))
                    if isinstance(answer, Answered):
                        return WSUpgradeResponseWithListener(_response(answer), None)
                    identity, subprotocol = answer.identity, answer.subprotocol
                connection = _ServerConnection(options, identity, started)
                headers = [("Sec-WebSocket-Protocol", subprotocol)] if subprotocol else None
                response = WSUpgradeResponse.create_101_response(headers)
                return WSUpgradeResponseWithListener(response, connection)

            # picows' own server factory, but with the connection at hand in the gate, and no
            # pong of picows' own: on_ws_frame answers a ping, once it checked the frame.
            ws_protocol = _Opening(
                None, None, False, accept, logger, True, HANDSHAKE_TIMEOUT,
                False, 20.0, 20.0, WSAutoPingStrategy.PING_WHEN_IDLE, False,
                _frame_limit(options), None, 16 * 1024,
            )  # fmt: skip
            return ws_protocol

        hosts = list(host) if isinstance(host, Sequence) and not isinstance(host, str) else host
        # asyncio gives a TLS handshake 60 s, and picows' timeout starts once it is done: a
        # silent connection would be held 60 s. The TLS handshake gets the same timeout, as
        # websockets gives it (its open_timeout).
        tls: dict[str, Any] = {} if ssl is None else {"ssl_handshake_timeout": HANDSHAKE_TIMEOUT}
        server = await loop.create_server(protocol, hosts, port, ssl=ssl, **tls)
        return PicowsListener(server, handlers, host, tls=ssl is not None)

    async def connect(
        self,
        url: str,
        options: Options,
        *,
        headers: Sequence[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | None = None,
    ) -> PicowsConnection:
        _check_options(options)
        try:
            self.check_url(url)
        except ValueError as exc:
            raise TransportError(str(exc)) from exc
        try:
            _, listener = await ws_connect(
                lambda: PicowsConnection(options),
                url,
                ssl_context=ssl,
                websocket_handshake_timeout=None,  # the caller bounds the whole opening
                max_frame_size=_frame_limit(options),
                extra_headers=list(headers) or None,
                max_redirects=0,
                logger_name="client",
                enable_auto_pong=False,  # on_ws_frame answers a ping, once it checked the frame
            )
        except (OSError, EOFError, WSError) as exc:
            raise _refusal(exc, url) from exc
        if listener is None:  # the connection ended before the upgrade's answer came
            hint = "" if url[:4].lower() == "wss:" else "; it may speak TLS (try wss://)"
            raise TransportError(
                f"the server closed the connection during the opening handshake{hint}"
            )
        assert isinstance(listener, PicowsConnection)
        return listener

    def check_url(self, url: str) -> None:
        try:
            parts = urllib.parse.urlsplit(url)
            parts.port  # noqa: B018 (raises ValueError for a port out of range)
        except ValueError as exc:
            raise ValueError(f"not a WebSocket URL: {url!r} ({exc})") from exc
        if parts.scheme.lower() not in ("ws", "wss") or not parts.hostname:
            raise ValueError(f"not a WebSocket URL: {url!r} (the scheme must be ws or wss)")


PEER_LOG_INTERVAL = 1.0
"""Seconds: at most one of ``picows``' server warnings and errors in this time (see
:class:`_WithoutConnectionNews`)."""


class _WithoutConnectionNews(logging.LoggerAdapter[logging.Logger]):
    """``picows``' server logger without its INFO lines, and its warnings and errors at most
    one a :data:`PEER_LOG_INTERVAL`.

    ``picows`` writes two INFO lines for every connection, refused at the upgrade or not
    (accepted, and disconnected), and a peer can make it write a warning or an error at will (a
    frame its parser refuses, a paused write): a client knocking or misbehaving in a loop would
    fill the log past the one line a second srvwire logs refusals at. A warning or error within
    the interval of the last one is counted instead, and the next line says how many were left
    out. DEBUG lines pass when the logger is set to show them. Given an adapter, ``picows``
    also makes no logger of its own per connection."""

    def __init__(self, logger: logging.Logger) -> None:
        super().__init__(logger)
        self.logged_at: float | None = None  # when the last warning or error was written
        self.held = 0  # warnings and errors left out since

    def isEnabledFor(self, level: int) -> bool:
        return level != logging.INFO and self.logger.isEnabledFor(level)

    def log(self, level: int, msg: object, *args: Any, **kwargs: Any) -> None:
        if level >= logging.WARNING and self.isEnabledFor(level):
            now = asyncio.get_running_loop().time()
            if self.logged_at is not None and now - self.logged_at < PEER_LOG_INTERVAL:
                self.held += 1
                return
            self.logged_at = now
            if self.held:
                msg = f"{msg} ({self.held} more warnings or errors since the last line)"
                self.held = 0
        super().log(level, msg, *args, **kwargs)


class _Opening(WSProtocol):  # type: ignore[misc]
    """``picows``' server protocol, which first looks at the opening bytes: a TLS record on a
    listener without TLS (a ``wss://`` client) is refused at once by closing the connection,
    where ``picows`` would wait for the end of an HTTP request until its handshake timeout.
    The client then says its TLS handshake failed and that the server may not speak TLS.

    Only the first read passes through this class: after it, the instance's ``get_buffer`` and
    ``buffer_updated`` are ``picows``' own, so every later read goes from the event loop
    straight to compiled code (an event loop that kept the first ones it saw, as ``uvloop``
    and TLS do, still reaches ``picows`` through them)."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.opening = True  # until the first bytes have been read
        self.buffer: memoryview | None = None

    def get_buffer(self, size_hint: int) -> memoryview:
        buffer: memoryview = super().get_buffer(size_hint)
        if self.opening:
            self.buffer = buffer
        return buffer

    def buffer_updated(self, nbytes: int) -> None:
        if self.opening:
            self.opening = False
            first, self.buffer = self.buffer, None
            # Later reads look these up on the instance first: picows' bound methods.
            self.get_buffer = super().get_buffer  # type: ignore[method-assign]
            self.buffer_updated = super().buffer_updated  # type: ignore[method-assign]
            if nbytes and first is not None and first[0] == _TLS_HANDSHAKE_RECORD:
                self.transport.disconnect()
                return
        super().buffer_updated(nbytes)

    def connection_lost(self, exc: Exception | None) -> None:
        # The bound methods above refer to this instance: without them it is freed at once,
        # not by the cycle collector.
        self.__dict__.pop("get_buffer", None)
        self.__dict__.pop("buffer_updated", None)
        super().connection_lost(exc)


class _ServerConnection(PicowsConnection):
    """A connection a listener accepted: its handler starts once the upgrade is done."""

    __slots__ = ("_started",)

    def __init__(self, options: Options, identity: object, started: Any) -> None:
        super().__init__(options, identity)
        self._started = started

    def on_ws_connected(self, transport: WSTransport) -> None:
        super().on_ws_connected(transport)
        self._started(self)


def _handshake(protocol: WSProtocol, request: WSUpgradeRequest) -> Handshake:
    """The opening request as srvwire's gate reads it."""
    underlying = protocol.transport.underlying_transport
    ssl_object = underlying.get_extra_info("ssl_object")
    certificate = ssl_object.getpeercert() if ssl_object is not None else None
    offered = [
        name.strip()
        for value in request.headers.getall("Sec-WebSocket-Protocol", [])
        for name in value.split(",")
        if name.strip()
    ]
    return Handshake(
        path=request.path.decode("latin-1"),
        headers=list(request.headers.items()),
        peer=underlying.get_extra_info("peername"),
        method=request.method.decode("latin-1"),
        tls=ssl_object is not None,
        client_certificate=certificate or None,
        subprotocols=offered,
    )


def _refusal(exc: Exception, url: str) -> TransportError:
    """Say why opening a connection to ``url`` failed (see :func:`opening_failed`)."""
    refused = None
    if isinstance(exc, WSHandshakeError) and exc.response is not None:
        body = (exc.raw_body or b"").decode("utf-8", "replace").strip()
        refused = (_code(exc.response.status), body)
    # A connection that ends before the answer never gets here (see connect): a WSError is
    # an answer that is not a WebSocket upgrade.
    return opening_failed(url, exc, refused=refused, not_websocket=isinstance(exc, WSError))
