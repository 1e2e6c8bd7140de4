"""Shared runtime fixtures: small test service types, a server on each transport, a raw wire.

The raw connection (:class:`Wire`) speaks plain JSON over the server's own transport, not
srvwire's client, so the server's tests see exactly what a client in another language would.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest

from srvwire import testing
from srvwire.loader import InterfaceLoader
from srvwire.models import Service, build_service
from srvwire.parser import parse_service
from srvwire.server import RunningServer, Server, serve
from srvwire.transports import get_transport
from srvwire.transports.base import Connection, Options, Transport
from srvwire.transports.memory import MemoryTransport
from support import ros_test_interfaces, scaled

SUBTRACT_SRV = """\
# Subtract one integer from another (the JSON-RPC specification's example method).
int64 minuend
int64 subtrahend
---
int64 difference
"""

ECHO_SRV = """\
# Send text back, optionally after waiting on the server.
string text
float64 values
---
string text
"""

# A request with a bounded array and a nested-shape check, for validation paths.
BOUNDED_SRV = """\
uint8 small
int32[<=3] values
string<=5 name
---
bool ok
"""


def build(text: str, name: str, package: str = "srvwire_tests") -> type[Service]:
    """Build a service type from .srv text, as the loader would from a file."""
    return build_service(parse_service(text, package, name))


Subtract = build(SUBTRACT_SRV, "Subtract")
Echo = build(ECHO_SRV, "Echo")
Bounded = build(BOUNDED_SRV, "Bounded")


def subtract(request: Any) -> Any:
    return Subtract.Response(difference=request.minuend - request.subtrahend)


class Hang:
    """A handler that never returns: ``entered`` is set once it runs, ``cancelled`` once it ends.

    Nothing ever sets the event it waits on, so only cancelling its task ends it.
    """

    def __init__(self) -> None:
        self.entered = asyncio.Event()
        self.cancelled = asyncio.Event()

    async def __call__(self, request: Any) -> Any:
        self.entered.set()
        try:
            await asyncio.Event().wait()
        finally:
            self.cancelled.set()


class Wire(testing.Wire):
    """The plugin's raw wire, with the suite's timeouts scaled; ``ws`` is its connection."""

    @property
    def ws(self) -> Connection:
        return self.connection

    async def recv(self, within: float = 5.0) -> Any:
        return await super().recv(scaled(within))


async def open_wire(running: RunningServer | str, **options: Any) -> Wire:
    """Connect to ``running`` on its own transport (a URL: over WebSockets) and read the
    ``$/services`` that opens the session."""
    transport, url = (
        (get_transport("websockets"), running)
        if isinstance(running, str)
        else (running.transport, running.url)
    )
    conn = await transport.connect(url, Options(compression=None, **options))
    wire = Wire(conn, [])
    first = await wire.recv()
    assert first["method"] == "$/services", first
    wire.services = first["params"]["services"]
    return wire


TRANSPORTS = ["websockets", "picows", "memory"]


def make_transport(name: str) -> Transport:
    """A fresh transport by name: the memory one is a world of its own per test."""
    return MemoryTransport() if name == "memory" else get_transport(name)


@pytest.fixture(params=TRANSPORTS)
def transport(request: pytest.FixtureRequest) -> Transport:
    """Each transport in turn, for behaviour that does not depend on the transport."""
    return make_transport(request.param)


websockets_only = pytest.mark.parametrize("transport", ["websockets"], indirect=True)
"""For a test of what only the websockets library does."""

real_websockets = pytest.mark.parametrize("transport", ["websockets", "picows"], indirect=True)
"""For a test of what only a real WebSocket has: binary frames, keepalive, raw frames."""


@pytest.fixture
def server() -> Server:
    """A server with ``/subtract`` and ``/echo`` (sync and async handlers)."""
    srv = Server(grace_period=scaled(2))
    srv.add_service("/subtract", Subtract, subtract)

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    srv.add_service("echo", Echo, echo)
    return srv


@pytest.fixture
async def running(server: Server, transport: Transport) -> AsyncIterator[RunningServer]:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        yield running


@pytest.fixture
async def wire(running: RunningServer) -> AsyncIterator[Wire]:
    w = await open_wire(running)
    try:
        yield w
    finally:
        await w.ws.close()


@pytest.fixture(scope="session")
def ros_interfaces() -> InterfaceLoader:
    """A loader over ROS 2's own test interfaces (the package ``ros_test_interfaces``)."""
    return InterfaceLoader([ros_test_interfaces().parent], use_default_path=False)
