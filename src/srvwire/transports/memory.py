"""An in-process transport: a server and its clients in one event loop, with no socket.

Tests (srvwire's and its users') serve and connect on one :class:`MemoryTransport` instance,
which is a little world of its own: ``listen`` registers an address there, ``connect`` finds it
there, and another instance sees none of it. ::

    transport = MemoryTransport()
    async with serve(server, "localhost", 0, transport=transport) as running:
        async with connect(running.url, transport=transport) as client:
            ...

It keeps the rules of :mod:`srvwire.transports.base` as the WebSocket transport does:

* Each end has an inbox: the messages its peer sent and it has not received yet, in order,
  with their size in bytes. The connection ends for both ends at once, but ``recv`` returns
  what is left in the inbox before it raises :class:`TransportClosed`, as a close frame
  arrives after the data sent before it.
* ``send`` puts the message in the peer's inbox, then waits while that inbox holds more than
  the high-water mark (the sender's ``max_queued_bytes``, else the transport's ``high_water``),
  until the peer reads it down to the low-water mark (a quarter of it) or the connection ends.
  In between the sender is congested: a ``send`` that starts then waits before it puts
  anything in the inbox. Congested for the sender's ``write_timeout``, the connection ends
  as a socket the sender aborts: both inboxes are emptied and the peer sees it drop
  (code None), while the sender's ``recv`` and ``send`` raise :class:`WriteTimedOut` (1008).
* A message larger than the receiver's ``max_message_size`` is not delivered: the connection
  ends with 1009. Bytes are delivered as text; when they are not UTF-8, the receiver ends the
  connection with 1007 on reading them, and drops what it had not read.
* ``close`` ends the connection at once, both ends: there is no handshake to wait for.
  :meth:`MemoryConnection.abort` ends it without a close code, as a dropped TCP connection.
* The listener runs each connection's handler in a task of its own, as websockets does: when
  the handler returns, its end closes with 1000; when it raises, the error is logged and the
  end closes with 1011; when it is cancelled, the connection drops.
* There is no keepalive: an in-process peer cannot go silent while its event loop runs, so
  ``ping_interval`` and ``ping_timeout`` are ignored, and so is ``compression``.
* A listener's gate sees each connection as a WebSocket upgrade of ``/`` with
  ``Host: host:port`` and the headers the client gave (so a test can send a token and call a
  scoped service in memory); a refusal fails ``connect`` with its status and reason. There is
  no TLS (``ssl`` is refused) and no HTTP besides, so no health check.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import ssl as _ssl
import urllib.parse
from collections import deque
from collections.abc import Sequence
from typing import Any

from srvwire.transports.base import (
    WRITE_TIMEOUT_CODE,
    Admitted,
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
    write_timeout_reason,
)

__all__ = ["MemoryConnection", "MemoryListener", "MemoryTransport"]

logger = logging.getLogger(__name__)


def _netloc(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _parse(url: str) -> tuple[str, int]:
    """Return the address of a ``memory://host:port`` URL; raise ``ValueError`` saying why not."""
    try:
        parts = urllib.parse.urlsplit(url)
        port = parts.port
    except ValueError as exc:  # a port that is no number, a bad IPv6 host
        why = str(exc)
    else:
        if parts.scheme != "memory":
            why = "the scheme is not memory"
        elif not parts.hostname:
            why = "no host"
        elif port is None:
            why = "no port"
        else:
            return parts.hostname, port
    raise ValueError(f"not a memory URL: {url!r} ({why})")


class MemoryConnection(Connection):
    """One end of an in-process connection."""

    __slots__ = (
        "_code",
        "_ended",
        "_high",
        "_inbox",
        "_limit",
        "_low",
        "_peer",
        "_reason",
        "_receiver",
        "_side",
        "_stall",
        "_timed_out",
        "_unread",
        "_writable",
        "_write_timeout",
        "identity",
        "remote_address",
    )

    def __init__(self, remote_address: Any, options: Options, high_water: int, side: str) -> None:
        self.remote_address = remote_address
        self.identity: Any = None
        self._side = side  # "client" or "server", for the close reason
        self._peer = self
        self._limit = options.max_message_size
        # The marks of what this end sends, in its peer's inbox.
        self._high = high_water if options.max_queued_bytes is None else options.max_queued_bytes
        self._low = self._high // 4
        self._write_timeout = options.write_timeout
        self._inbox: deque[tuple[str | bytes, int]] = deque()
        self._unread = 0  # bytes in the inbox
        self._receiver: asyncio.Future[None] | None = None  # the recv waiting for a message
        self._writable = asyncio.Event()  # the inbox went no higher than the peer's high mark
        self._writable.set()  # since it was last down to the low mark
        self._stall: asyncio.TimerHandle | None = None  # the peer's write timeout, on the inbox
        self._timed_out = False  # this end closed the connection for its write timeout
        self._ended = False
        self._code: int | None = None
        self._reason = ""

    async def recv(self) -> str:
        inbox = self._inbox
        while not inbox:
            if self._ended:
                raise self.closed()
            if self._receiver is not None:
                raise RuntimeError("another coroutine is already waiting for the next message")
            self._receiver = asyncio.get_running_loop().create_future()
            try:
                await self._receiver
            finally:
                self._receiver = None
        message, size = inbox.popleft()
        self._unread -= size
        if self._unread <= self._peer._low and not self._writable.is_set():
            self._writable.set()
            if self._stall is not None:
                self._stall.cancel()
                self._stall = None
        if isinstance(message, str):
            return message
        try:
            return message.decode()
        except UnicodeDecodeError as exc:
            inbox.clear()
            self._unread = 0
            self._end(1007, f"{exc.reason} at position {exc.start}")
            raise self.closed() from exc

    async def send(self, message: str | bytes) -> None:
        if self._ended:
            raise self.closed()
        peer = self._peer
        if not peer._writable.is_set():  # congested: queue nothing more until it drains
            await self.writable()
        if isinstance(message, str):
            size = len(message) if message.isascii() else len(message.encode())
        else:
            size = len(message)
        limit = peer._limit
        if limit is not None and size > limit:
            # Sent, then refused by the peer: the sender learns it from the close, as on a socket.
            self._end(
                1009,
                f"over the {peer._side}'s max_message_size "
                f"(message of {size} bytes, limit {limit} bytes)",
            )
            return
        peer._inbox.append((message, size))
        peer._unread += size
        receiver = peer._receiver
        if receiver is not None and not receiver.done():
            receiver.set_result(None)
        if peer._unread > self._high:
            if peer._writable.is_set():
                peer._writable.clear()
                if self._write_timeout is not None:
                    loop = asyncio.get_running_loop()
                    peer._stall = loop.call_later(self._write_timeout, self._stalled)
            await peer._writable.wait()
            if self._ended:
                raise self.closed()

    @property
    def congested(self) -> bool:
        return not self._peer._writable.is_set()

    def buffered(self) -> int:
        return self._peer._unread

    async def writable(self) -> None:
        writable = self._peer._writable
        if writable.is_set():
            return
        while not writable.is_set():  # woken together, the first to send may congest it again
            await writable.wait()
        if self._ended:
            raise self.closed()

    def closed(self) -> TransportClosed:
        if self._timed_out:
            assert self._write_timeout is not None
            return WriteTimedOut(self._write_timeout)
        return TransportClosed(self._code, self._reason)

    def _stalled(self) -> None:
        """The peer did not read down to the low mark within the write timeout: end it."""
        assert self._write_timeout is not None
        peer = self._peer
        peer._stall = None
        for end in (self, peer):  # as an aborted socket drops what was not read, both ways
            end._inbox.clear()
            end._unread = 0
        self._end(None, "")  # the peer sees the connection drop ...
        self._timed_out = True  # ... this end knows why
        self._code = WRITE_TIMEOUT_CODE
        self._reason = write_timeout_reason(self._write_timeout)

    async def close(self, code: int = 1000, reason: str = "") -> None:
        if not self._ended:
            self._end(code, reason)

    def abort(self) -> None:
        """Drop the connection without a close code, as a lost network does; idempotent."""
        if not self._ended:
            self._end(None, "")

    @property
    def close_code(self) -> int | None:
        return self._code

    @property
    def close_reason(self) -> str:
        return self._reason

    def _end(self, code: int | None, reason: str) -> None:
        """End the connection at both ends; wake whoever waits on either."""
        for end in (self, self._peer):
            end._ended = True
            end._code = code
            end._reason = reason
            receiver = end._receiver
            if receiver is not None and not receiver.done():
                receiver.set_result(None)
            end._writable.set()
            if end._stall is not None:
                end._stall.cancel()
                end._stall = None


class MemoryListener(Listener):
    """Where a :class:`MemoryTransport` accepts connections, at ``memory://host:port``."""

    def __init__(
        self,
        transport: MemoryTransport,
        handler: ConnectionHandler,
        host: str,
        port: int,
        options: Options,
        gate: Gate | None = None,
    ) -> None:
        self.host = host
        self.port = port
        self.url = f"memory://{_netloc(host, port)}"
        self._options = options
        self._gate = gate
        self._transport = transport
        self._handler = handler
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = asyncio.Event()

    def close(self) -> None:
        if not self._closed.is_set():
            self._closed.set()
            self._transport._listeners.pop((self.host.lower(), self.port), None)

    async def wait_closed(self) -> None:
        await self._closed.wait()
        while self._tasks:
            await asyncio.wait(set(self._tasks))

    def _accept(self, server_end: MemoryConnection) -> None:
        task = asyncio.get_running_loop().create_task(self._run(server_end))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _run(self, connection: MemoryConnection) -> None:
        # As websockets does: close with 1000 when the handler returns, 1011 when it raises.
        try:
            await self._handler(connection)
        except asyncio.CancelledError:
            connection.abort()
            raise
        except Exception:
            logger.exception("connection handler failed")
            await connection.close(1011)
        else:
            await connection.close()


class MemoryTransport(Transport):
    """An in-process world of listeners and connections; share one instance between both ends.

    ``high_water`` is the most bytes one direction buffers before ``send`` waits, where the
    sender's options give no ``max_queued_bytes``.
    """

    name = "memory"

    def __init__(self, high_water: int = 2**16) -> None:
        if high_water < 0:
            raise ValueError(f"high_water must be 0 or more, not {high_water}")
        self.high_water = high_water
        self._listeners: dict[tuple[str, int], MemoryListener] = {}
        self._next_port = 1
        self._connections = 0

    async def listen(
        self,
        handler: ConnectionHandler,
        host: Hosts,
        port: int,
        options: Options,
        *,
        gate: Gate | None = None,
        ssl: _ssl.SSLContext | None = None,
    ) -> MemoryListener:
        if ssl is not None:
            raise ValueError("the memory transport has no TLS: pass ssl=None")
        if not isinstance(host, str):
            raise ValueError(f"the memory transport listens on one host name, not {host!r}")
        if port == 0:
            while (host.lower(), self._next_port) in self._listeners:
                self._next_port += 1
            port = self._next_port
            self._next_port += 1
        address = (host.lower(), port)
        if address in self._listeners:
            raise OSError(errno.EADDRINUSE, f"memory://{_netloc(host, port)} is already in use")
        listener = MemoryListener(self, handler, host, port, options, gate)
        self._listeners[address] = listener
        return listener

    async def connect(
        self,
        url: str,
        options: Options,
        *,
        headers: Sequence[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | None = None,
    ) -> MemoryConnection:
        try:
            host, port = _parse(url)
        except ValueError as exc:
            raise TransportError(str(exc)) from exc
        listener = self._listeners.get((host.lower(), port))
        if listener is None:
            raise TransportError(f"nothing listens at memory://{_netloc(host, port)}")
        self._connections += 1
        peer = ("memory", self._connections)
        identity = None
        if listener._gate is not None:
            handshake = Handshake(
                path=urllib.parse.urlsplit(url).path or "/",
                headers=[("Host", _netloc(host, port)), ("Upgrade", "websocket"), *headers],
                peer=peer,
            )
            answer = await listener._gate(handshake)
            if not isinstance(answer, Admitted):
                raise TransportError(
                    f"the server refused the connection: HTTP {answer.status}: "
                    + answer.reason.strip()
                )
            identity = answer.identity
        client = MemoryConnection(
            (listener.host, listener.port), options, self.high_water, "client"
        )
        server = MemoryConnection(peer, listener._options, self.high_water, "server")
        server.identity = identity
        client._peer = server
        server._peer = client
        listener._accept(server)
        return client

    def check_url(self, url: str) -> None:
        _parse(url)
