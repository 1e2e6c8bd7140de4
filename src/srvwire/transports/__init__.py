"""Transports: how srvwire's messages travel between a server and its clients.

* :mod:`~srvwire.transports.base`: the seam, :class:`~srvwire.transports.base.Transport` and
  :class:`~srvwire.transports.base.Connection`, and the rules every transport keeps;
* :mod:`~srvwire.transports.websockets`: WebSocket over TCP, the default;
* :mod:`~srvwire.transports.picows`: WebSocket over TCP on ``picows`` (``srvwire[fast]``), the
  native one: the same wire, with frames parsed in C and no reader task per connection;
* :mod:`~srvwire.transports.memory`: an in-process pair, for tests, with no port.
"""

from __future__ import annotations

from srvwire.transports.base import Transport

__all__ = ["get_transport"]


def get_transport(transport: str | Transport) -> Transport:
    """Return the transport ``transport`` names, or ``transport`` itself when it is one.

    Raise ``ValueError`` for a name there is no transport of.
    """
    if isinstance(transport, Transport):
        return transport
    if transport == "websockets":
        # Imported here, so that the seam and the other transports never import websockets.
        from srvwire.transports.websockets import WebSocketsTransport

        return WebSocketsTransport()
    if transport == "picows":
        try:
            from srvwire.transports.picows import PicowsTransport
        except ImportError as exc:
            raise ValueError(
                "the picows transport needs the picows package: pip install 'srvwire[fast]'"
            ) from exc
        return PicowsTransport()
    if transport == "memory":
        raise ValueError(
            "the memory transport is a world shared by a server and its clients: "
            "pass a MemoryTransport() instance, the same one to both, not the name 'memory'"
        )
    raise ValueError(
        f"unknown transport {transport!r}: use 'websockets', 'picows' or a Transport instance, "
        "such as MemoryTransport()"
    )
