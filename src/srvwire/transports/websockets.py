"""The WebSocket transport, on the ``websockets`` library: the only module that imports it.

A :class:`WebSocketsConnection` is a thin wrapper on one ``websockets`` connection: ``recv``
and ``send`` are one call each, with no extra ``await``, because every call of srvwire goes
through them. ``websockets`` already keeps the rules of :mod:`srvwire.transports.base`: its
write buffer gives the backpressure, ``max_size`` the 1009, UTF-8 checks the 1007, and
``close`` waits for the closing handshake (within its ``close_timeout``).

Exceptions are mapped here and nowhere else:

* ``ConnectionClosed`` (any subclass) -> :class:`TransportClosed`, with the code and reason of
  the close frame received, else of the one sent, else ``None``;
* ``OSError`` and ``WebSocketException`` while connecting -> :class:`TransportError`, with the
  same text;
* ``InvalidURI`` from :meth:`WebSocketsTransport.check_url` -> ``ValueError``.

A listener can listen on several hosts (``asyncio``'s ``create_server`` takes a list), or on
every interface, IPv4 and IPv6, with ``host=None``; its :attr:`~WebSocketsListener.urls` name
each address clients can use, with the interfaces' own addresses for a wildcard
(``0.0.0.0``, ``::``). ``websockets``' own INFO lines (a connection opened, closed, the server
listening) are left out unless its logger's level was set (:class:`_QuietLogger`); its
warnings and errors always go through.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import struct
import sys
from collections.abc import Sequence
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, InvalidURI, WebSocketException
from websockets.frames import Close
from websockets.protocol import State
from websockets.uri import parse_uri

from srvwire.transports.base import (
    Connection,
    ConnectionHandler,
    Hosts,
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


def _url(host: str, port: int) -> str:
    """Return the ``ws://`` URL of ``host``:``port``, with an IPv6 host in brackets."""
    return f"ws://[{host}]:{port}" if ":" in host else f"ws://{host}:{port}"


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


class _QuietLogger(logging.LoggerAdapter[logging.Logger]):
    """``websockets.server`` without its INFO lines unless asked for; warnings always pass.

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

    __slots__ = ("_ws", "remote_address")

    def __init__(self, ws: ServerConnection | ClientConnection) -> None:
        self._ws = ws
        self.remote_address = ws.remote_address

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

    ``urls`` are the addresses clients can use: for one host name, that name (``localhost``
    stays ``localhost``); for a wildcard (``0.0.0.0``, ``::``, None), each address of the
    interfaces of its family, loopback first; for several hosts, each. IPv4 comes before IPv6.
    ``url`` is the first, and ``host`` and ``port`` are its. With port 0, each socket has a
    port of its own.
    """

    def __init__(self, server: Server, host: Hosts = None) -> None:
        self._server = server
        sockets = sorted(server.sockets, key=_socket_order)  # asyncio's order is a set's
        if isinstance(host, str) and host not in _WILDCARDS:
            address = sockets[0].getsockname()
            self._urls = [_url(host, address[1])]
            self.host, self.port = host, address[1]
        else:
            urls: list[str] = []
            for sock in sockets:
                address = sock.getsockname()
                bound, port = str(address[0]), int(address[1])
                if ipaddress.ip_address(bound).is_unspecified:
                    urls += [_url(a, port) for a in interface_addresses(sock.family)]
                else:
                    urls.append(_url(bound, port))
            self._urls = list(dict.fromkeys(urls))
            self.host = self._urls[0].removeprefix("ws://").rsplit(":", 1)[0].strip("[]")
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
        self, handler: ConnectionHandler, host: Hosts, port: int, options: Options
    ) -> WebSocketsListener:
        async def handle(ws: ServerConnection) -> None:
            # When this returns, websockets closes with 1000; when it raises, with 1011.
            await handler(WebSocketsConnection(ws))

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
            logger=_QuietLogger(),
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
