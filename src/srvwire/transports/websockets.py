"""The WebSocket transport, on the ``websockets`` library: the only module that imports it.

A :class:`WebSocketsConnection` is a thin wrapper on one ``websockets`` connection: ``recv``
and ``send`` are one call each, with no extra ``await``, because every call of srvwire goes
through them. ``websockets`` already keeps the rules of :mod:`srvwire.transports.base`: its
write buffer gives the backpressure, ``max_size`` the 1009, UTF-8 checks the 1007, and
``close`` waits for the closing handshake (within its ``close_timeout``). Its 1009 close reason
is prefixed with the side and the setting that refused the message (``over the server's
max_message_size (frame with 2097170 bytes exceeds limit of 1048576 bytes)``), so that the
peer's error says what to raise.

Exceptions are mapped here and nowhere else:

* ``ConnectionClosed`` (any subclass) -> :class:`TransportClosed`, with the code and reason of
  the close frame received, else of the one sent, else ``None``;
* ``OSError`` and ``WebSocketException`` while connecting -> :class:`TransportError`, with the
  same text;
* ``InvalidURI`` from :meth:`WebSocketsTransport.check_url` -> ``ValueError``.
"""

from __future__ import annotations

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, InvalidURI, WebSocketException
from websockets.frames import Close, CloseCode
from websockets.protocol import Protocol, Side, State
from websockets.uri import parse_uri

from srvwire.transports.base import (
    Connection,
    ConnectionHandler,
    Listener,
    Options,
    Transport,
    TransportClosed,
    TransportError,
)

__all__ = ["WebSocketsConnection", "WebSocketsListener", "WebSocketsTransport"]


def _closed(exc: ConnectionClosed) -> TransportClosed:
    """Translate how ``websockets`` says a connection ended into :class:`TransportClosed`."""
    frame = exc.rcvd if exc.rcvd is not None else exc.sent
    if frame is None:
        return TransportClosed(None)
    return TransportClosed(frame.code, frame.reason)


def _name_the_limit(protocol: Protocol) -> None:
    """Make the close reason of a message over ``max_size`` name the setting and the side."""
    fail = protocol.fail
    side = "server" if protocol.side is Side.SERVER else "client"

    def fail_naming_the_limit(code: int, reason: str = "") -> None:
        if code == CloseCode.MESSAGE_TOO_BIG:
            # A close reason holds at most 123 bytes; this one is ASCII.
            reason = f"over the {side}'s max_message_size ({reason})"[:123]
        fail(code, reason)

    protocol.fail = fail_naming_the_limit  # type: ignore[method-assign]


def _url(host: str, port: int) -> str:
    """Return the ``ws://`` URL of ``host``:``port``, with an IPv6 host in brackets."""
    return f"ws://[{host}]:{port}" if ":" in host else f"ws://{host}:{port}"


class WebSocketsConnection(Connection):
    """One WebSocket connection, server or client side."""

    __slots__ = ("_ws", "remote_address")

    def __init__(self, ws: ServerConnection | ClientConnection) -> None:
        self._ws = ws
        self.remote_address = ws.remote_address
        _name_the_limit(ws.protocol)

    async def recv(self) -> str | bytes:
        try:
            return await self._ws.recv()
        except ConnectionClosed as exc:
            raise _closed(exc) from exc

    async def send(self, message: str | bytes) -> None:
        # text=True sends bytes as a text frame as they are, and a str as usual.
        try:
            await self._ws.send(message, text=True)
        except ConnectionClosed as exc:
            raise _closed(exc) from exc

    async def close(self, code: int = 1000, reason: str = "") -> None:
        await self._ws.close(code, reason)

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


class WebSocketsListener(Listener):
    """A ``websockets`` server; closing it keeps the connections it accepted.

    ``host`` is the name it was asked to listen on (``localhost`` stays ``localhost``), else
    the address its first socket bound; ``port`` is the port really bound.
    """

    def __init__(self, server: Server, host: str | None = None) -> None:
        self._server = server
        address = server.sockets[0].getsockname()
        self.host = host or address[0]
        self.port = address[1]
        self.url = _url(self.host, self.port)

    def close(self) -> None:
        self._server.close(close_connections=False)

    async def wait_closed(self) -> None:
        await self._server.wait_closed()


class WebSocketsTransport(Transport):
    """WebSocket over TCP, with ``ws://`` URLs."""

    name = "websockets"

    async def listen(
        self, handler: ConnectionHandler, host: str, port: int, options: Options
    ) -> WebSocketsListener:
        async def handle(ws: ServerConnection) -> None:
            # When this returns, websockets closes with 1000; when it raises, with 1011.
            await handler(WebSocketsConnection(ws))

        server = await serve(
            handle,
            host,
            port,
            compression=options.compression,
            max_size=options.max_message_size,
            ping_interval=options.ping_interval,
            ping_timeout=options.ping_timeout,
        )
        return WebSocketsListener(server, host)

    async def connect(self, url: str, options: Options) -> WebSocketsConnection:
        # The caller bounds the whole opening; websockets' own timeout would be a second bound.
        try:
            ws = await connect(
                url,
                max_size=options.max_message_size,
                ping_interval=options.ping_interval,
                ping_timeout=options.ping_timeout,
                compression=options.compression,
                open_timeout=None,
            )
        except (OSError, WebSocketException) as exc:
            raise TransportError(str(exc)) from exc
        return WebSocketsConnection(ws)

    def check_url(self, url: str) -> None:
        try:
            parse_uri(url)
        except (InvalidURI, ValueError) as exc:  # ValueError: a port out of range
            raise ValueError(f"not a WebSocket URL: {url!r} ({exc})") from exc
