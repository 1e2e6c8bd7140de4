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
* **Limits end the connection, not the process.** A message larger than the receiver's
  ``max_message_size`` closes the connection with code 1009; a text message that is not UTF-8
  closes it with 1007. Messages received before it are still delivered.
* **How it ended is told once, with srvwire's exception.** Once a connection has ended,
  ``recv`` and ``send`` raise :class:`TransportClosed`, which carries the close code and reason
  (``None``: it dropped without a close frame). :meth:`Connection.close` is idempotent and
  waits for the closing handshake, within the transport's own bound. A transport maps its
  library's exceptions to these in one place, with ``raise ... from``.
"""

from __future__ import annotations

import abc
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = [
    "Connection",
    "ConnectionHandler",
    "Hosts",
    "Listener",
    "Options",
    "Transport",
    "TransportClosed",
    "TransportError",
]


@dataclass(frozen=True, slots=True)
class Options:
    """What a connection is allowed: the same options on the server and the client.

    ``max_message_size`` bounds one incoming message in bytes (None: no limit);
    ``ping_interval``/``ping_timeout`` the keepalive, where the transport has one (None turns
    it off); ``compression="deflate"`` asks for per-message compression, where the transport
    has it.
    """

    max_message_size: int | None = 2**20
    ping_interval: float | None = 20.0
    ping_timeout: float | None = 20.0
    compression: str | None = None


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


class Connection(abc.ABC):
    """One open connection: receive and send whole messages, then close it."""

    __slots__ = ()

    remote_address: Any
    """Who is at the other end, as the transport names it (a ``(host, port)`` for TCP)."""

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
        self, handler: ConnectionHandler, host: Hosts, port: int, options: Options
    ) -> Listener:
        """Accept connections on ``host``:``port`` (0: any free port) and run ``handler``.

        ``host`` may name several hosts, or be None for every interface, where the transport
        can listen on more than one. Raise :class:`OSError` when the address cannot be used,
        ``ValueError`` for hosts the transport cannot listen on.
        """

    @abc.abstractmethod
    async def connect(self, url: str, options: Options) -> Connection:
        """Open a connection to ``url``; raise :class:`TransportError` when that fails."""

    @abc.abstractmethod
    def check_url(self, url: str) -> None:
        """Raise ``ValueError`` saying why when ``url`` is not an address of this transport."""
