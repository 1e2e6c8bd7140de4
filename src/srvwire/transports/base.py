"""What a connection is to srvwire: the one seam between its sessions and the network.

A :class:`Transport` listens for connections and dials them; a :class:`Connection` carries whole
messages, in order, both ways. srvwire's server and client speak only to these classes, so
another transport (an in-process pair, a faster WebSocket library) changes nothing above it.

Rules every transport keeps:

* **Messages, not bytes.** :meth:`Connection.recv` returns one whole message: a ``str`` for a
  text message, ``bytes`` for a binary one. :meth:`Connection.send` sends one message as text:
  a ``str``, or ``bytes`` that already are UTF-8 text (srvwire writes its messages as bytes,
  so a large reply is never decoded and encoded again).
* **Flow control.** ``send`` returns once the message is in the transport's buffer. While the
  peer does not read and that buffer is past its high-water mark, ``send`` waits: that is the
  backpressure a client that writes faster than it reads feels. ``recv`` waits for the next
  message; a connection that is not read holds at most what the transport buffers.
* **A budget for what waits to be sent.** The high-water mark is ``Options.max_queued_bytes``
  (the transport's own default when None). Past it the connection is :attr:`~Connection.congested`
  until the peer has read it down to a quarter of it: a ``send`` that starts then waits before it
  queues anything, so at most the budget plus one message waits in the buffer, and
  :meth:`~Connection.writable` waits for the end of it (a server stops reading calls there).
* **A peer that does not read is closed.** Congested for ``Options.write_timeout`` seconds in a
  row (or, where the transport has keepalive, ``ping_interval + ping_timeout`` when that is
  sooner: a ping cannot be answered through a buffer that does not drain), the connection is
  closed at once, without a closing handshake (the peer would not read
  it), dropping what was queued: this side's ``recv`` and ``send`` raise :class:`WriteTimedOut`,
  code :data:`WRITE_TIMEOUT_CODE` (1008, policy violation); the peer sees the connection drop.
* **Limits end the connection, not the process.** A message larger than the receiver's
  ``max_message_size`` closes the connection with code 1009; a text message that is not UTF-8
  closes it with 1007. Messages received before it are still delivered.
* **How it ended is told once, with srvwire's exception.** Once a connection has ended,
  ``recv`` and ``send`` raise :class:`TransportClosed`, which carries the close code and reason
  (``None``: it dropped without a close frame). :meth:`Connection.close` is idempotent and
  waits for the closing handshake, within the transport's own bound. A transport maps its
  library's exceptions to these in one place, with ``raise ... from``.
* **Who may connect is the server's decision, not the transport's.** A listener given a
  ``gate`` hands it each opening request as a :class:`Handshake` before the connection is
  accepted (for a WebSocket: before the upgrade) and carries out its answer: an
  :class:`Admitted` connection gets the identity on :attr:`Connection.identity`; a
  :class:`Answered` one gets that HTTP response instead, and the handler never runs.
"""

from __future__ import annotations

import abc
import ssl as _ssl
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "CREDENTIAL_HEADERS",
    "WRITE_TIMEOUT_CODE",
    "Admitted",
    "Answered",
    "Connection",
    "ConnectionHandler",
    "Gate",
    "Handshake",
    "Headers",
    "Hosts",
    "Listener",
    "Options",
    "Transport",
    "TransportClosed",
    "TransportError",
    "WriteTimedOut",
    "opening_failed",
    "write_timeout_reason",
]

CREDENTIAL_HEADERS = frozenset({"authorization", "cookie", "proxy-authorization"})
"""Headers whose values are credentials: no ``repr`` or log line shows them."""

WRITE_TIMEOUT_CODE = 1008
"""The close code of a connection closed because its peer did not read for ``write_timeout``:
1008, policy violation, since reading what one asked for is the peer's part of the protocol."""


@dataclass(frozen=True, slots=True)
class Options:
    """What a connection is allowed: the same options on the server and the client.

    ``max_message_size`` bounds one incoming message in bytes (None: no limit);
    ``ping_interval``/``ping_timeout`` the keepalive, where the transport has one (None turns
    it off); ``compression="deflate"`` asks for per-message compression, where the transport
    has it. ``max_queued_bytes`` is the budget of bytes waiting to be sent, past which the
    connection is congested (None: the transport's default); ``write_timeout`` how long it may
    stay congested before it is closed with :data:`WRITE_TIMEOUT_CODE` (None: forever).
    """

    max_message_size: int | None = 2**20
    ping_interval: float | None = 20.0
    ping_timeout: float | None = 20.0
    compression: str | None = None
    max_queued_bytes: int | None = None
    write_timeout: float | None = None


class Headers(tuple[tuple[str, str], ...]):
    """Headers as ``(name, value)`` pairs, whose ``repr`` hides the values of credentials."""

    __slots__ = ()

    def __repr__(self) -> str:
        return repr(
            [
                (key, "<hidden>" if key.lower() in CREDENTIAL_HEADERS else value)
                for key, value in self
            ]
        )


@dataclass(frozen=True, slots=True)
class Handshake:
    """An opening request as a transport received it, for the server to admit or refuse.

    ``headers`` are ``(name, value)`` pairs as they came (a name may repeat); ``peer`` is who
    connected, as :attr:`Connection.remote_address` names it; ``tls`` whether the connection
    is encrypted; ``client_certificate`` the peer's certificate as :meth:`ssl.SSLSocket.getpeercert`
    returns it (None without mutual TLS); ``subprotocols`` what the client offered. Its
    ``repr`` leaves out the values of credential headers, so it can be logged.
    """

    path: str = "/"
    headers: Sequence[tuple[str, str]] = ()
    peer: Any = None
    method: str = "GET"
    tls: bool = False
    client_certificate: dict[str, Any] | None = None
    subprotocols: Sequence[str] = ()

    def header(self, name: str) -> str | None:
        """The first value of the header ``name`` (any case), or None."""
        wanted = name.lower()
        for key, value in self.headers:
            if key.lower() == wanted:
                return value
        return None

    def __repr__(self) -> str:
        offered = len(self.subprotocols)
        return (
            f"Handshake({self.method} {self.path.split('?', 1)[0]!r}, peer={self.peer!r}, "
            f"tls={self.tls}, headers={Headers(self.headers)!r}, {offered} subprotocols offered)"
        )


@dataclass(frozen=True, slots=True)
class Admitted:
    """The server admits the connection: who it is, and the subprotocol to select (or None)."""

    identity: Any = None
    subprotocol: str | None = None


@dataclass(frozen=True, slots=True)
class Answered:
    """The server answers the opening request with a plain HTTP response instead of a
    connection: a refusal, or the health check. ``status`` is the HTTP status, ``reason`` the
    body, a line for a person; ``headers`` extra response headers."""

    status: int
    reason: str
    headers: tuple[tuple[str, str], ...] = field(default=())


Gate = Callable[[Handshake], Awaitable[Admitted | Answered]]
"""What a listener asks about each opening request (see the module's rules)."""


class TransportError(OSError):
    """Raised when a connection cannot be opened: nothing listens there, or the peer refused."""


class TransportClosed(Exception):
    """Raised by :meth:`Connection.recv` and :meth:`Connection.send` once the connection ended.

    ``code`` and ``reason`` come from the close frame received, else the one sent; ``code`` is
    None when the connection dropped without one.
    """

    def __init__(self, code: int | None, reason: str = "") -> None:
        super().__init__(code, reason)
        self.code = code
        self.reason = reason

    @property
    def clean(self) -> bool:
        """Whether the connection was closed on purpose (1000 normal, 1001 going away)."""
        return self.code in (1000, 1001)

    def __str__(self) -> str:
        if self.code is None or self.code == 1006:
            return "the connection dropped (no close frame)"
        return f"the connection closed with code {self.code}" + (
            f" ({self.reason})" if self.reason else ""
        )


class WriteTimedOut(TransportClosed):
    """Raised by :meth:`Connection.recv` and :meth:`Connection.send` once this side closed the
    connection because its peer did not read for ``write_timeout`` seconds."""

    def __init__(self, timeout: float) -> None:
        super().__init__(WRITE_TIMEOUT_CODE, write_timeout_reason(timeout))
        self.timeout = timeout


def write_timeout_reason(timeout: float) -> str:
    """The close reason of a connection whose peer did not read for ``timeout`` seconds."""
    return f"write timeout: the peer did not read what was sent for {timeout:g} s"


class Connection(abc.ABC):
    """One open connection: receive and send whole messages, then close it."""

    __slots__ = ()

    remote_address: Any
    """Who is at the other end, as the transport names it (a ``(host, port)`` for TCP)."""

    identity: Any
    """Who the server's gate admitted (:attr:`Admitted.identity`); None on a client, or
    without a gate."""

    @abc.abstractmethod
    async def recv(self) -> str | bytes:
        """Return the next message; raise :class:`TransportClosed` once the connection ended.

        One coroutine receives at a time. Cancelling ``recv`` loses no message.
        """

    @abc.abstractmethod
    async def send(self, message: str | bytes) -> None:
        """Send ``message`` as one text message (bytes: UTF-8 text); wait while the peer lags.

        Raise :class:`TransportClosed` once the connection ended.
        """

    def deliver_to(self, receive: Callable[[str | bytes], None]) -> bool:
        """Hand every message to ``receive`` as it arrives, instead of to :meth:`recv`, where
        the transport can; return whether it does (by default it does not).

        The messages received and not yet taken go first, in order, before this returns.
        ``receive`` then runs in the transport's read callback, so it must not block or
        raise; :meth:`recv` returns no more messages, and raises :class:`TransportClosed` at
        the end as before. It saves a wake-up of the receiving task per message.
        """
        return False

    def pause_reading(self) -> None:
        """Read no more from the network until :meth:`resume_reading`: what a receiver given
        to :meth:`deliver_to` calls when it holds more messages than it means to; where the
        transport cannot, nothing (by default)."""
        return None

    def resume_reading(self) -> None:
        """Read from the network again after :meth:`pause_reading`; nothing by default."""
        return None

    @property
    @abc.abstractmethod
    def congested(self) -> bool:
        """Whether the bytes waiting to be sent are past the budget: a ``send`` would wait."""

    @abc.abstractmethod
    async def writable(self) -> None:
        """Wait until the connection is not :attr:`congested`; raise :class:`TransportClosed`
        when it ended while this waited."""

    def buffered(self) -> int:
        """The bytes sent and not yet taken by the peer that count against the budget (what
        the transport's buffer holds); 0 where the transport cannot tell."""
        return 0

    @abc.abstractmethod
    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Close the connection with ``code`` and ``reason`` and wait until it is closed."""

    @property
    @abc.abstractmethod
    def close_code(self) -> int | None:
        """The code the connection closed with; None while open or when it dropped."""

    @property
    @abc.abstractmethod
    def close_reason(self) -> str:
        """The reason the connection closed with; empty while open."""

    def closed(self) -> TransportClosed:
        """Return how the connection ended, as the exception ``recv`` raises."""
        return TransportClosed(self.close_code, self.close_reason)


ConnectionHandler = Callable[[Connection], Awaitable[None]]
"""What a listener runs for each connection; the connection is closed when it returns."""


Hosts = str | Sequence[str] | None
"""Where to listen: one host, several, or None for every interface (IPv4 and IPv6)."""


class Listener(abc.ABC):
    """Where a transport accepts connections, until :meth:`close`."""

    host: str
    port: int
    url: str
    """The address clients connect to, with the port really bound (useful with port 0)."""

    @property
    def urls(self) -> list[str]:
        """Every address clients can connect to, :attr:`url` first."""
        return [self.url]

    @abc.abstractmethod
    def close(self) -> None:
        """Stop accepting connections; the open ones stay open."""

    @abc.abstractmethod
    async def wait_closed(self) -> None:
        """Wait until the listener is closed and every connection handler has returned."""


class Transport(abc.ABC):
    """A way to carry srvwire's messages: listens on the server, dials on the client."""

    name: str
    """What ``transport=`` calls it (``"websockets"``, ``"memory"``)."""

    @abc.abstractmethod
    async def listen(
        self,
        handler: ConnectionHandler,
        host: Hosts,
        port: int,
        options: Options,
        *,
        gate: Gate | None = None,
        ssl: _ssl.SSLContext | None = None,
    ) -> Listener:
        """Accept connections on ``host``:``port`` (0: any free port) and run ``handler``.

        ``host`` may name several hosts, or be None for every interface, where the transport
        can listen on more than one. ``gate`` admits or refuses each opening request (None:
        every one is admitted); ``ssl`` makes the listener speak TLS, where the transport can.
        Raise
        :class:`OSError` when the address cannot be used, ``ValueError`` for hosts the
        transport cannot listen on.
        """

    @abc.abstractmethod
    async def connect(
        self,
        url: str,
        options: Options,
        *,
        headers: Sequence[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | None = None,
    ) -> Connection:
        """Open a connection to ``url``, sending ``headers`` with the opening request and
        checking the server with ``ssl`` (for a TLS URL); raise :class:`TransportError` when
        that fails, saying why (a refusal: its status and reason)."""

    @abc.abstractmethod
    def check_url(self, url: str) -> None:
        """Raise ``ValueError`` saying why when ``url`` is not an address of this transport."""


def opening_failed(
    url: str,
    exc: BaseException,
    *,
    refused: tuple[int, str] | None = None,
    closed_early: bool = False,
    not_websocket: bool = False,
) -> TransportError:
    """Say why opening a connection to ``url`` failed, as a person can act on it.

    ``refused`` is the HTTP status and body of an upgrade the server answered with something
    else; ``closed_early`` says the server closed the connection during the opening handshake
    (what a TLS server does to a plain client); ``not_websocket`` that it answered with
    something other than an HTTP/1.1 upgrade (a plain web server, such as an HTTP/1.0 one).
    Every transport words its failures here.
    """
    tls = url.lower().startswith("wss:")
    if refused is not None:
        status, body = refused
        return TransportError(
            f"the server refused the connection: HTTP {status}" + (f": {body}" if body else "")
        )
    if not_websocket:
        return TransportError(
            f"the server did not answer as a WebSocket server does ({exc}); "
            "is a srvwire server at this address?"
        )
    if isinstance(exc, _ssl.SSLCertVerificationError):
        return TransportError(f"the server's TLS certificate is not trusted: {exc.verify_message}")
    if tls and isinstance(exc, _ssl.SSLError | ConnectionResetError | EOFError):
        detail = str(exc) or type(exc).__name__
        return TransportError(
            f"the TLS handshake failed; the server may not speak TLS (try ws://): {detail}"
        )
    if not tls and closed_early:
        return TransportError(
            "the server closed the connection during the opening handshake; "
            f"it may speak TLS (try wss://): {exc}"
        )
    return TransportError(str(exc) or type(exc).__name__)
