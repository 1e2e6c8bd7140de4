"""Shared runtime fixtures: small test service types, a server on a free port, a raw connection.

The raw connection (:class:`Wire`) speaks plain WebSocket JSON, not srvwire's client, so the
server's tests see exactly what a client in another language would.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from srvwire.loader import InterfaceLoader
from srvwire.models import Service, build_service
from srvwire.parser import parse_service
from srvwire.server import RunningServer, Server, serve
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


class Wire:
    """A raw WebSocket connection to a server, with JSON helpers and scaled timeouts."""

    def __init__(self, ws: ClientConnection, services: list[dict[str, str]]) -> None:
        self.ws = ws
        self.services = services  # the first $/services the server sent

    async def send(self, message: Any) -> None:
        """Send ``message``: text or bytes as they are, anything else as JSON."""
        if isinstance(message, str | bytes):
            await self.ws.send(message)
        else:
            await self.ws.send(json.dumps(message))

    async def recv(self, within: float = 5.0) -> Any:
        """Receive and decode one message; fail if none comes within ``within`` seconds (scaled)."""
        async with asyncio.timeout(scaled(within)):
            data = await self.ws.recv()
        assert isinstance(data, str), "the server sends text frames only"
        return json.loads(data)

    async def recv_reply(self, within: float = 5.0) -> Any:
        """Receive the next message that is not a ``$/services`` notification."""
        while True:
            message = await self.recv(within)
            if not (isinstance(message, dict) and message.get("method") == "$/services"):
                return message

    async def call(self, message: Any, within: float = 5.0) -> Any:
        """Send ``message`` and return the reply."""
        await self.send(message)
        return await self.recv_reply(within)

    async def request(self, method: str, params: Any = None, id: Any = 1) -> Any:
        """Call ``method`` with ``params`` under ``id`` and return the reply object."""
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": id, "method": method}
        if params is not None:
            message["params"] = params
        return await self.call(message)


async def open_wire(url: str, **kwargs: Any) -> Wire:
    """Connect to ``url`` and read the ``$/services`` notification that opens the session."""
    ws = await connect(url, compression=None, open_timeout=scaled(5), **kwargs)
    async with asyncio.timeout(scaled(5)):
        first = json.loads(await ws.recv())
    assert first["method"] == "$/services", first
    return Wire(ws, first["params"]["services"])


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
async def running(server: Server) -> AsyncIterator[RunningServer]:
    async with serve(server, "127.0.0.1", 0) as running:
        yield running


@pytest.fixture
async def wire(running: RunningServer) -> AsyncIterator[Wire]:
    w = await open_wire(running.url)
    try:
        yield w
    finally:
        await w.ws.close()


@pytest.fixture(scope="session")
def ros_interfaces() -> InterfaceLoader:
    """A loader over ROS 2's own test interfaces (the package ``ros_test_interfaces``)."""
    return InterfaceLoader([ros_test_interfaces().parent])
