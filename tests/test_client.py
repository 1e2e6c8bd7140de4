"""The client against a scripted peer (faults a real server never makes) and a real server.

The scripted peer, :class:`FakePeer`, is a bare ``websockets`` server that records every message
it receives and answers only what a test tells it to. Proving a deadline against it is safe:
a peer that never answers leaves the deadline as the only possible outcome.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import math
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any
from unittest.mock import ANY

import pytest
import uvloop
from websockets.asyncio.server import Server as WsServer, ServerConnection, serve as ws_serve
from websockets.exceptions import ConnectionClosed

import srvwire.session
import srvwire.transports.picows
from conftest import Echo
from srvwire.client import Client, ServiceInfo, connect
from srvwire.errors import (
    Cancelled,
    ConnectionLost,
    DeadlineExceeded,
    InterfaceNotFoundError,
    InternalError,
    InvalidParams,
    InvalidRequest,
    ParseError,
    PermissionDenied,
    ResourceExhausted,
    RPCError,
    ServiceError,
    ServiceNotFound,
    ServiceUnavailable,
    Unauthenticated,
)
from srvwire.inline import Pending
from srvwire.link import MAX_READY, Answer, Link
from srvwire.loader import load_service
from srvwire.models import Service, build_service
from srvwire.parser import parse_service
from srvwire.protocol import RawReply
from srvwire.server import RunningServer, Server, serve
from srvwire.transports.base import Transport
from srvwire.transports.picows import PicowsConnection
from support import record_calls, scaled

ADD = "/add_two_ints"
ADD_TYPE = "example_interfaces/srv/AddTwoInts"
SERVICES = [{"name": ADD, "type": ADD_TYPE}, {"name": "/trigger", "type": "std_srvs/srv/Trigger"}]

Reply = Callable[[ServerConnection, dict[str, Any]], Awaitable[None]]


def services_text(services: list[dict[str, str]]) -> str:
    return json.dumps({"jsonrpc": "2.0", "method": "$/services", "params": {"services": services}})


class FakePeer:
    """A scripted peer: advertises ``services``, records what it gets, answers via ``reply``."""

    def __init__(self, services: list[dict[str, str]] | None = None, *, advertise: bool = True):
        self.services = SERVICES if services is None else services
        self.advertise = advertise
        self.reply: Reply | None = None
        self.received: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self.connections: list[ServerConnection] = []
        self.server: WsServer | None = None

    async def start(self, port: int = 0) -> None:
        self.server = await ws_serve(self._handle, "127.0.0.1", port)

    async def stop(self) -> None:
        assert self.server is not None
        self.server.close()
        await self.server.wait_closed()

    @property
    def url(self) -> str:
        assert self.server is not None
        port = self.server.sockets[0].getsockname()[1]
        return f"ws://127.0.0.1:{port}"

    async def _handle(self, ws: ServerConnection) -> None:
        self.connections.append(ws)
        if self.advertise:
            await ws.send(services_text(self.services))
        try:
            async for text in ws:
                message = json.loads(text)
                await self.received.put(message)
                if self.reply is not None:
                    await self.reply(ws, message)
        except ConnectionClosed:
            pass  # tests close and abort connections on purpose

    async def next(self, method: str | None = None) -> dict[str, Any]:
        """Return the next message received (skipping others when ``method`` is given)."""
        while True:
            message = await asyncio.wait_for(self.received.get(), scaled(5))
            if method is None or message.get("method") == method:
                return message


async def answer_add(ws: ServerConnection, message: dict[str, Any]) -> None:
    """Answer AddTwoInts calls the way a real server would; ignore everything else."""
    if message.get("method") == ADD and "id" in message:
        params = message["params"]
        result = {"sum": params.get("a", 0) + params.get("b", 0)}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))


@pytest.fixture
async def peer() -> AsyncIterator[FakePeer]:
    fake = FakePeer()
    await fake.start()
    yield fake
    await fake.stop()


@pytest.fixture(params=["websockets", "picows"])
async def client(peer: FakePeer, request: pytest.FixtureRequest) -> AsyncIterator[Client]:
    """A client of the scripted peer, on each network transport in turn (on both, replies
    reach their calls from the transport's read callback: Connection.deliver_to)."""
    async with connect(peer.url, timeout=scaled(5), transport=request.param) as opened:
        yield opened


@pytest.fixture
def add_two_ints() -> type[Service]:
    return load_service(ADD_TYPE)


def free_port() -> int:
    """Return a TCP port on 127.0.0.1 that nothing listens on (it was free a moment ago)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


# --- opening and closing ----------------------------------------------------------------------


async def test_connect_works_as_await_and_as_async_with(peer: FakePeer) -> None:
    peer.reply = answer_add
    client = await connect(peer.url)
    assert client.connected
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    await client.close()
    assert not client.connected
    async with connect(peer.url) as other:
        assert (await other.call(ADD, {"a": 2, "b": 2})).sum == 4
    assert not other.connected


async def test_connect_to_a_closed_port_is_a_typed_error() -> None:
    url = f"ws://127.0.0.1:{free_port()}"
    with pytest.raises(ServiceUnavailable) as caught:
        await connect(url, open_timeout=scaled(5))
    assert type(caught.value) is ServiceUnavailable
    assert caught.value.data == {"url": url}
    assert isinstance(caught.value.__cause__, OSError)
    assert str(caught.value).startswith(f"UNAVAILABLE (-32003): cannot connect to {url}: ")


async def test_a_server_that_never_advertises_is_not_a_srvwire_server() -> None:
    silent = FakePeer(advertise=False)
    await silent.start()
    url = silent.url
    try:
        with pytest.raises(ServiceUnavailable) as caught:
            await connect(url, open_timeout=scaled(0.2))
    finally:
        await silent.stop()
    assert caught.value.message == (
        f"cannot connect to {url}: the WebSocket opened, but its server sent no "
        f"$/services within {scaled(0.2):g} s (open_timeout): is it a srvwire server?"
    )


async def test_a_server_whose_first_message_is_not_the_services_list_is_refused() -> None:
    odd = FakePeer(advertise=False)

    async def greet(ws: ServerConnection) -> None:
        await ws.send('{"jsonrpc":"2.0","method":"hello","params":{}}')
        await ws.wait_closed()

    odd.server = await ws_serve(greet, "127.0.0.1", 0)
    try:
        with pytest.raises(ServiceUnavailable, match=r"first message was not \$/services"):
            await connect(odd.url, open_timeout=scaled(5))
    finally:
        await odd.stop()


def test_bad_arguments_are_refused_at_once() -> None:
    with pytest.raises(ValueError, match="not a WebSocket URL"):
        connect("http://localhost:8765")
    with pytest.raises(ValueError, match="finite number of seconds > 0, not Infinity"):
        connect(timeout=float("inf"))
    with pytest.raises(ValueError, match="finite number of seconds > 0, not NaN"):
        connect(timeout=float("nan"))
    with pytest.raises(ValueError, match="finite number of seconds > 0, not -1"):
        connect(timeout=-1)
    with pytest.raises(ValueError, match="finite number of seconds"):
        connect(timeout=0)
    with pytest.raises(ValueError, match="not an integer too large for a float"):
        connect(timeout=10**400)
    assert connect(timeout=3).timeout == 3.0
    with pytest.raises(TypeError, match="number of seconds"):
        connect(timeout="5")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown transport 'carrier pigeon'"):
        connect(transport="carrier pigeon")


@pytest.mark.parametrize("reconnect", [False, True])
async def test_close_closes_the_socket(peer: FakePeer, reconnect: bool) -> None:
    peer.reply = answer_add
    client = await connect(peer.url, reconnect=reconnect)
    # A round trip lets the reconnect supervisor start watching the connection's reader.
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    await client.close()
    (ws,) = peer.connections
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    assert ws.close_code == 1000  # the client said goodbye; the connection did not just drop
    assert not client.connected


async def test_close_during_a_reconnect_dial_closes_that_socket() -> None:
    dialled: asyncio.Queue[ServerConnection] = asyncio.Queue()

    async def first_advertises_then_leaves_the_rest_silent(ws: ServerConnection) -> None:
        await dialled.put(ws)
        if dialled.qsize() == 1:  # the first connection: advertise, then drop it
            await ws.send(services_text(SERVICES))
            await ws.close(1012, "restarting")
        await ws.wait_closed()

    server = await ws_serve(first_advertises_then_leaves_the_rest_silent, "127.0.0.1", 0)
    try:
        port = server.sockets[0].getsockname()[1]
        client = await connect(f"ws://127.0.0.1:{port}", reconnect=True, open_timeout=scaled(30))
        await asyncio.wait_for(dialled.get(), scaled(5))
        redial = await asyncio.wait_for(dialled.get(), scaled(5))
        # The supervisor now waits for the $/services that will never come.
        await client.close()
        await asyncio.wait_for(redial.wait_closed(), scaled(5))
        assert not client.connected
    finally:
        server.close()
        await server.wait_closed()


async def test_a_closed_client_fails_calls_at_once(peer: FakePeer) -> None:
    client = await connect(peer.url)
    await client.close()
    await client.close()  # idempotent
    with pytest.raises(ConnectionLost, match="the client is closed") as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    assert caught.value.service == ADD


# --- requests and responses -------------------------------------------------------------------


async def test_requests_as_model_dict_or_fields(
    peer: FakePeer, client: Client, add_two_ints: type[Service]
) -> None:
    peer.reply = answer_add
    by_model = await client.call(ADD, add_two_ints.Request.model_validate({"a": 1, "b": 2}))
    by_dict = await client.call("add_two_ints", {"a": 3, "b": 4})
    by_fields = await client.call(ADD, {"a": 5, "b": 6})
    defaults = await client.call(ADD)
    assert [r.sum for r in (by_model, by_dict, by_fields, defaults)] == [3, 7, 11, 0]
    assert all(isinstance(r, add_two_ints.Response) for r in (by_model, by_dict, by_fields))


async def test_the_request_on_the_wire(peer: FakePeer, client: Client) -> None:
    peer.reply = answer_add
    await client.call("add_two_ints", {"a": 1, "b": 2}, timeout=scaled(3))
    await client.call(ADD, {"a": 7})
    first, second = await peer.next(), await peer.next()
    assert first["jsonrpc"] == "2.0"
    assert first["method"] == ADD
    assert isinstance(first["id"], int)
    assert second["id"] > first["id"]
    meta = first["params"].pop("_meta")
    assert 0 < meta["timeout"] <= scaled(3)
    assert first["params"] == {"a": 1, "b": 2}
    assert second["params"]["b"] == 0  # the typed request filled in the default


async def test_an_invalid_request_is_refused_locally(peer: FakePeer, client: Client) -> None:
    peer.reply = answer_add
    with pytest.raises(InvalidParams) as caught:
        await client.call(ADD, {"a": "one", "b": 2, "c": 3})
    error = caught.value
    assert error.service == ADD
    assert error.errors == [
        {"path": "a", "message": "Input should be a valid integer", "type": "int_type"},
        {"path": "c", "message": "Extra inputs are not permitted", "type": "extra_forbidden"},
    ]
    assert "checked by the client; nothing was sent" in error.message
    # Nothing was sent: the first message the peer sees is the next, valid call.
    assert (await client.call(ADD, {"a": 1, "b": 1})).sum == 2
    assert (await peer.next())["params"]["a"] == 1


async def test_a_request_of_the_wrong_type_is_a_type_error(client: Client) -> None:
    trigger = load_service("std_srvs/srv/Trigger")
    with pytest.raises(TypeError, match="takes example_interfaces/srv/AddTwoInts requests"):
        await client.call(ADD, trigger.Request())
    with pytest.raises(TypeError, match="not both"):
        await client.proxy(ADD)({"a": 1}, b=2)


async def test_a_type_found_neither_here_nor_on_the_server_is_an_error() -> None:
    unknown = FakePeer([{"name": "/echo", "type": "nowhere_msgs/srv/Echo"}])

    async def describe_nothing(ws: ServerConnection, message: dict[str, Any]) -> None:
        result = {"openrpc": "1.3.2", "methods": [{"name": "/echo"}]}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))

    unknown.reply = describe_nothing
    await unknown.start()
    try:
        async with connect(unknown.url, timeout=scaled(5)) as client:
            for srv_type in (None, "nowhere_msgs/srv/Echo"):
                with pytest.raises(InterfaceNotFoundError) as excinfo:
                    await client.call("/echo", {"x": [1, 2]}, srv_type=srv_type)
                assert str(excinfo.value) == (
                    "cannot type the calls of /echo: nowhere_msgs/srv/Echo is not on the local "
                    f"search path, and the server {unknown.url} does not describe types"
                )
            # The client asked for the description, once per connection, and sent no call.
            assert (await unknown.next())["method"] == "rpc.discover"
            assert unknown.received.empty()
    finally:
        await unknown.stop()


async def test_a_call_waiting_for_the_description_another_asked_for_keeps_its_deadline() -> None:
    silent = FakePeer([{"name": "/echo", "type": "nowhere_msgs/srv/Echo"}])  # never answers
    await silent.start()
    try:
        async with connect(silent.url, timeout=scaled(5)) as client:
            first = asyncio.create_task(client.call("/echo", {}))
            assert (await silent.next())["method"] == "rpc.discover"  # the first one asked
            with pytest.raises(DeadlineExceeded) as excinfo:
                await client.call("/echo", {}, timeout=0.05)
            assert (excinfo.value.message, excinfo.value.service) == (
                "no response within 0.05 s",
                "/echo",
            )
            assert silent.received.empty()  # it waited for the first one's answer
            first.cancel()
            await asyncio.gather(first, return_exceptions=True)
    finally:
        await silent.stop()


async def test_a_lone_surrogate_is_refused_before_sending() -> None:
    # A str with a lone surrogate ("\ud800"; os.fsdecode(b"\x80") gives "\udc80") validates as
    # a ROS string but cannot be written as UTF-8 JSON: the client says which field, sends nothing.
    state_type = "advanced_communication_tutorials/srv/RobotStateQuery"
    peer = FakePeer([{"name": "/state", "type": state_type}])  # /echo is not advertised

    async def echo(ws: ServerConnection, message: dict[str, Any]) -> None:
        params = {k: v for k, v in message["params"].items() if k != "_meta"}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": params}))

    peer.reply = echo
    await peer.start()
    bad = "pose\ud800"
    expected = [
        {
            "path": "query_type",
            "message": (
                "String should not contain the lone surrogate '\\ud800' (at index 4): "
                "it cannot be written as UTF-8"
            ),
            "type": "string_unicode",
        }
    ]
    try:
        async with connect(peer.url, timeout=scaled(5)) as client:
            typed = load_service(state_type)
            for request in ({"query_type": bad}, typed.Request(query_type=bad)):
                with pytest.raises(InvalidParams) as caught:
                    await client.call("/state", request)
                assert caught.value.errors == expected
                assert caught.value.message == (
                    f"invalid params for /state: query_type: {expected[0]['message']} "
                    "(checked by the client; nothing was sent)"
                )
            with pytest.raises(InvalidParams) as untyped:  # not advertised: a plain dict too
                await client.call("/echo", {"names": ["ok", bad]})
            assert [(e["path"], e["type"]) for e in untyped.value.errors] == [
                ("names[1]", "string_unicode")
            ]
            # Nothing was sent: the first message the peer sees is the next, valid call.
            assert await client.call("/echo", {"names": ["ok"]}) == {"names": ["ok"]}
            assert (await peer.next())["params"]["names"] == ["ok"]
    finally:
        await peer.stop()


async def test_srv_type_overrides_the_advertised_type(peer: FakePeer, client: Client) -> None:
    async def answer_trigger(ws: ServerConnection, message: dict[str, Any]) -> None:
        result = {"success": True, "message": "done"}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))

    peer.reply = answer_trigger
    response = await client.call("/unadvertised", srv_type="std_srvs/srv/Trigger")
    assert (response.success, response.message) == (True, "done")


async def test_a_response_that_does_not_match_the_type_is_an_internal_error(
    peer: FakePeer, client: Client
) -> None:
    async def wrong(ws: ServerConnection, message: dict[str, Any]) -> None:
        result = {"sum": "three"}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))

    peer.reply = wrong
    with pytest.raises(InternalError, match="does not match example_interfaces") as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    assert caught.value.data["errors"][0]["path"] == "sum"


async def test_proxies(peer: FakePeer, client: Client, add_two_ints: type[Service]) -> None:
    peer.reply = answer_add
    add = client.proxy("add_two_ints", add_two_ints, timeout=scaled(2))
    assert add.name == ADD
    assert (await add(a=2, b=3)).sum == 5
    assert (await add({"a": 4})).sum == 4
    assert (await add(add_two_ints.Request.model_validate({"a": 1, "b": 1}))).sum == 2
    untyped = client.proxy(ADD)  # the type comes from the server's advertisement
    assert (await untyped(a=10, b=1)).sum == 11
    assert await untyped.wait_for_service() == ServiceInfo(ADD, ADD_TYPE)


async def test_the_advertised_services_are_a_read_only_snapshot(
    peer: FakePeer, client: Client
) -> None:
    services = client.services
    assert dict(services) == {ADD: ADD_TYPE, "/trigger": "std_srvs/srv/Trigger"}
    with pytest.raises(TypeError):
        services["/x"] = "pkg/srv/X"  # type: ignore[index]
    ws = peer.connections[0]
    await ws.send(services_text([{"name": "late", "type": "std_srvs/srv/Empty"}]))
    assert await client.wait_for_service("/late") == ServiceInfo("/late", "std_srvs/srv/Empty")
    assert dict(client.services) == {"/late": "std_srvs/srv/Empty"}
    assert dict(services) == {ADD: ADD_TYPE, "/trigger": "std_srvs/srv/Trigger"}  # unchanged
    await ws.close()
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    with pytest.raises(ConnectionLost):
        await client.wait_for_service("/late")  # returns once the client saw the connection end
    assert dict(client.services) == {}
    assert peer.received.empty()  # no rpc.discover was needed for any of it


async def test_list_services(peer: FakePeer, client: Client) -> None:
    async def discover(ws: ServerConnection, message: dict[str, Any]) -> None:
        assert "params" not in message
        methods = [
            {"name": "/b", "x-srvwire-type": "std_srvs/srv/Trigger"},
            {"name": "a", "x-srvwire-type": ADD_TYPE},
            {"name": "rpc.other"},  # not a srvwire service: left out
        ]
        document = {"openrpc": "1.3.2", "methods": methods}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": document}))

    peer.reply = discover
    assert await client.list_services() == [
        ServiceInfo("/a", ADD_TYPE),
        ServiceInfo("/b", "std_srvs/srv/Trigger"),
    ]


# --- errors from the server -------------------------------------------------------------------


ERROR_CASES: list[tuple[int, type[RPCError], Any, Any]] = [
    # code, class, data sent, data the exception carries (the status is taken out)
    (-32700, ParseError, {"status": "PARSE_ERROR"}, None),
    (-32600, InvalidRequest, {"status": "INVALID_REQUEST"}, None),
    (
        -32601,
        ServiceNotFound,
        {"status": "SERVICE_NOT_FOUND", "candidates": ["/add_two_ints"]},
        {"candidates": ["/add_two_ints"]},
    ),
    (
        -32602,
        InvalidParams,
        {"status": "INVALID_PARAMS", "errors": [{"path": "a", "message": "m", "type": "t"}]},
        {"errors": [{"path": "a", "message": "m", "type": "t"}]},
    ),
    (-32603, InternalError, {"status": "INTERNAL"}, None),
    (-32001, DeadlineExceeded, {"status": "DEADLINE_EXCEEDED"}, None),
    (-32002, Cancelled, {"status": "CANCELLED"}, None),
    (-32003, ServiceUnavailable, {"status": "UNAVAILABLE"}, None),
    (-32004, ResourceExhausted, {"status": "RESOURCE_EXHAUSTED", "limit": 8}, {"limit": 8}),
    (-32005, Unauthenticated, {"status": "UNAUTHENTICATED"}, None),
    (
        -32006,
        PermissionDenied,
        {"status": "PERMISSION_DENIED", "missing_scopes": ["a"]},
        {"missing_scopes": ["a"]},
    ),
    (4001, ServiceError, {"battery": 0.1}, {"battery": 0.1}),
    (-1, ServiceError, None, None),
    (-32050, RPCError, {"x": 1}, {"x": 1}),
]


@pytest.mark.parametrize(("code", "cls", "sent", "carried"), ERROR_CASES)
async def test_every_error_code_raises_its_class(
    peer: FakePeer, client: Client, code: int, cls: type[RPCError], sent: Any, carried: Any
) -> None:
    async def fail(ws: ServerConnection, message: dict[str, Any]) -> None:
        error: dict[str, Any] = {"code": code, "message": f"failed with {code}"}
        if sent is not None:
            error["data"] = sent
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "error": error}))

    peer.reply = fail
    with pytest.raises(RPCError) as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    error = caught.value
    assert type(error) is cls
    assert (error.code, error.message, error.data, error.service) == (
        code,
        f"failed with {code}",
        carried,
        ADD,
    )
    assert client.in_flight == 0
    # The connection is still good after any error reply.
    peer.reply = answer_add
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3


async def test_invalid_params_from_the_server_point_into_the_request(
    peer: FakePeer, client: Client
) -> None:
    async def refuse(ws: ServerConnection, message: dict[str, Any]) -> None:
        errors = [{"path": "b", "message": "too big", "type": "less_than_equal"}]
        error = {
            "code": -32602,
            "message": "bad b",
            "data": {"status": "INVALID_PARAMS", "errors": errors},
        }
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "error": error}))

    peer.reply = refuse
    with pytest.raises(InvalidParams) as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    assert caught.value.errors == [{"path": "b", "message": "too big", "type": "less_than_equal"}]


# --- deadlines and cancellation ---------------------------------------------------------------


async def test_a_deadline_against_a_peer_that_never_answers(peer: FakePeer, client: Client) -> None:
    with pytest.raises(DeadlineExceeded) as caught:
        await client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(0.2))
    error = caught.value
    assert isinstance(error, TimeoutError)
    assert (error.code, error.service) == (-32001, ADD)
    assert error.data == {"timeout": scaled(0.2)}
    request = await peer.next(ADD)
    cancel = await peer.next("$/cancel")
    assert cancel == {"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": request["id"]}}
    assert client.in_flight == 0


async def test_a_thousand_timeouts_leave_nothing_pending(peer: FakePeer, client: Client) -> None:
    assert client._link is not None
    session = client._link.session
    issued: set[int] = set()  # the ids of the calls the client wrote a request for
    request = session.request

    def recording(method: str, *args: Any) -> tuple[int, bytes]:
        id, data = request(method, *args)
        issued.add(id)
        return id, data

    session.request = recording  # type: ignore[method-assign]
    calls = [client.call(ADD, {"a": i, "b": 0}, timeout=scaled(0.3)) for i in range(1000)]
    results = await asyncio.gather(*calls, return_exceptions=True)
    assert all(isinstance(r, DeadlineExceeded) for r in results)
    assert client.in_flight == 0
    # Every call given up on after its request was made sends a $/cancel; a request still
    # waiting for room to be written when its deadline passed is never written, but cancelled
    # all the same. On a loaded machine a call may find its deadline passed before it makes its
    # request (all of them wait for the first to prepare the service): it has nothing to
    # cancel. The peer is read for as long as the messages take to arrive, seconds apart on a
    # loaded machine: only the suite's timeout bounds it.
    requested: set[int] = set()
    cancelled: set[int] = set()
    while cancelled != issued:
        message = await peer.received.get()
        if message["method"] == "$/cancel":
            cancelled.add(message["params"]["id"])
            assert cancelled <= issued
        else:
            requested.add(message["id"])
    assert requested <= cancelled


async def test_cancelling_the_caller_cancels_the_call_on_the_server(
    peer: FakePeer, client: Client
) -> None:
    task = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}))
    request = await peer.next(ADD)
    assert client.in_flight == 1
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    cancel = await peer.next("$/cancel")
    assert cancel["params"] == {"id": request["id"]}
    assert client.in_flight == 0


class Routed(dict[int, Any]):
    """A session's pending calls that call ``routed`` each time a call is taken out of them
    (as the reader routes a reply to it, or as it is given up)."""

    def __init__(self, pending: dict[int, Any], routed: Callable[[], None]) -> None:
        super().__init__(pending)
        self.routed = routed

    def pop(self, key: int, default: Any = None) -> Any:
        waiter = super().pop(key, None)
        if waiter is None:
            return default
        self.routed()
        return waiter


def when_routed(client: Client, routed: Callable[[], None]) -> None:
    """Call ``routed`` each time a call is taken out of the client's pending calls: when its
    reply reaches the reader, just before the reader resolves the call (or as it is given
    up)."""
    session = client._link.session  # type: ignore[union-attr]
    session.pending = Routed(session.pending, routed)


def call_cancelled_as_answered(client: Client, monkeypatch: pytest.MonkeyPatch) -> Any:
    """Start ``client.call(ADD, a=1, b=2)`` in a task, cancelled in the step its reply arrives.

    The reader takes the call out of the pending calls, and at once (before it resolves the
    call, so before the call resumes) the call's task is cancelled.
    """
    call: asyncio.Task[Any] | None = None

    def cancel() -> None:
        if call is not None and not call.done() and not call.cancelling():
            call.cancel()

    when_routed(client, cancel)
    call = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}))
    return call


async def test_a_cancellation_that_races_the_reply_still_cancels(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The reply resolves the call, and in the same step the caller is cancelled, before the
    # call resumes: Python 3.11's wait_for would return the reply and lose the cancellation.
    peer.reply = answer_add
    call = call_cancelled_as_answered(client, monkeypatch)
    with pytest.raises(asyncio.CancelledError):
        await call
    assert client.in_flight == 0
    monkeypatch.undo()
    assert (await client.call(ADD, {"a": 2, "b": 2})).sum == 4  # answered: no $/cancel was needed
    assert [(await peer.next())["method"] for _ in range(2)] == [ADD, ADD]


async def test_a_late_reply_is_ignored(
    peer: FakePeer, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    with pytest.raises(DeadlineExceeded):
        await client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(0.1))
    late = await peer.next(ADD)
    caplog.set_level(logging.DEBUG, logger="srvwire.client")
    ws = peer.connections[0]
    await ws.send(json.dumps({"jsonrpc": "2.0", "id": late["id"], "result": {"sum": 3}}))
    await ws.send(json.dumps({"jsonrpc": "2.0", "id": "nobody", "result": {}}))
    peer.reply = answer_add
    assert (await client.call(ADD, {"a": 2, "b": 2})).sum == 4
    dropped = [r.getMessage() for r in caplog.records if "no call waits" in r.getMessage()]
    assert dropped == [
        f"dropping a reply for id {late['id']}: no call waits for it",
        "dropping a reply for id 'nobody': no call waits for it",
    ]


# --- waking the caller ------------------------------------------------------------------------


async def answer_add_or_fail(ws: ServerConnection, message: dict[str, Any]) -> None:
    """Answer AddTwoInts as :func:`answer_add` does, or with an error reply when ``a`` is 0."""
    if message.get("method") == ADD and message["params"].get("a") == 0:
        error = {"code": 4001, "message": "a is 0"}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "error": error}))
    else:
        await answer_add(ws, message)


async def turns_to_wake(client: Client, request: dict[str, int]) -> int:
    """Call ``client.call(ADD, request)`` and count the loop turns from the step its reply
    reaches the client (the reader takes the call out of the pending calls, in the transport's
    read callback) to the step the caller resumes (an error reply counts as a reply)."""
    loop = asyncio.get_running_loop()
    turns = 0
    ticking = False

    def tick() -> None:  # once per loop turn, while ticking: scheduled ahead of the wake-up
        nonlocal turns
        if ticking:
            turns += 1
            loop.call_soon(tick)

    def routed() -> None:
        nonlocal ticking
        ticking = True
        loop.call_soon(tick)

    when_routed(client, routed)
    with contextlib.suppress(ServiceError):
        await client.call(ADD, request)
    ticking = False
    return turns


@pytest.mark.parametrize("reply", ["result", "error"])
async def test_a_reply_wakes_its_caller_at_the_next_loop_turn(
    peer: FakePeer, client: Client, reply: str
) -> None:
    # As awaiting the call's future bare would: on Python 3.11, wait_for's own done callback
    # would wake the caller a turn later (link.Answer runs it as the reply is set).
    peer.reply = answer_add_or_fail
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3  # its type found, kept
    assert await turns_to_wake(client, {"a": 0 if reply == "error" else 1, "b": 2}) == 1
    assert client.in_flight == 0


@pytest.mark.parametrize("transport", ["websockets", "picows"])
def test_a_reply_wakes_its_caller_at_the_next_loop_turn_on_uvloop(transport: str) -> None:
    async def turns() -> list[int]:
        peer = FakePeer()
        await peer.start()
        peer.reply = answer_add_or_fail
        try:
            async with connect(peer.url, timeout=scaled(5), transport=transport) as client:
                assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
                return [await turns_to_wake(client, {"a": a, "b": 2}) for a in (1, 0)]
        finally:
            await peer.stop()

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        assert runner.run(turns()) == [1, 1]


async def test_a_calls_future_runs_no_other_callback_and_steps_no_task_at_once() -> None:
    # Only wait_for's own callback (a partial of _release_waiter) runs as the result is set;
    # a task awaiting the future itself, or any other callback, is woken at the next turn.
    loop = asyncio.get_running_loop()
    future: asyncio.Future[Any] = Answer(loop=loop)
    ran: list[str] = []
    waiting = asyncio.Event()

    async def wait() -> None:
        waiting.set()
        ran.append(await future)

    future.add_done_callback(lambda _: ran.append("callback"))
    task = loop.create_task(wait())
    await waiting.wait()  # the task awaits the future
    future.set_result("task")
    assert ran == []
    await task
    assert ran == ["callback", "task"]
    with pytest.raises(asyncio.InvalidStateError):
        future.set_result("again")


# --- a connection that drops or goes bad ------------------------------------------------------


@pytest.mark.parametrize("how", ["close", "abort"])
async def test_a_peer_that_closes_mid_call_fails_every_pending_call(
    peer: FakePeer, client: Client, how: str
) -> None:
    # The deadline is long: a call that waited for it would fail DeadlineExceeded, not
    # ConnectionLost, so the exception type proves the calls failed when the connection did.
    calls = [asyncio.create_task(client.call(ADD, {"a": i}, timeout=scaled(30))) for i in range(20)]
    for _ in calls:
        await peer.next(ADD)
    ws = peer.connections[0]
    if how == "close":
        await ws.close(1011, "going down")
    else:
        ws.transport.abort()
    results = await asyncio.gather(*calls, return_exceptions=True)
    assert all(type(r) is ConnectionLost for r in results), results
    errors = [r for r in results if isinstance(r, ConnectionLost)]
    assert {e.service for e in errors} == {ADD}
    if how == "close":
        assert errors[0].message == "the connection closed with code 1011 (going down)"
        assert errors[0].data == {
            "close_code": 1011,
            "close_reason": "going down",
            "url": peer.url,
        }
    else:
        assert errors[0].message == "the connection dropped (no close frame)"
    assert client.in_flight == 0
    assert not client.connected
    # Without reconnect=True the connection stays down: calls and waits fail fast.
    with pytest.raises(ConnectionLost, match="not connected"):
        await client.call(ADD, {"a": 1})
    with pytest.raises(ConnectionLost, match="not connected"):
        await client.wait_for_service(ADD)


@pytest.mark.parametrize(
    ("garbage", "reason"),
    [
        ("this is not JSON", "Parse error"),
        (b"\xff\xfe", "invalid UTF-8"),
        ("[1, 2]", "expected an object, got a number"),
        ('{"jsonrpc": "2.0", "id": 1}', "neither 'result' nor an 'error' object"),
        ('{"jsonrpc": "2.0", "method": "$/services", "params": {}}', "needs params"),
    ],
)
async def test_garbage_from_the_server_fails_the_connection(
    peer: FakePeer,
    client: Client,
    garbage: str | bytes,
    reason: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    task = asyncio.create_task(client.call(ADD, {"a": 1}, timeout=scaled(30)))
    await peer.next(ADD)
    ws = peer.connections[0]
    await ws.send(garbage)
    with pytest.raises(ConnectionLost) as caught:
        await task
    assert caught.value.message.startswith("the server broke the protocol: ")
    assert reason in caught.value.message
    assert caught.value.data["close_code"] == 1008
    await ws.wait_closed()
    assert ws.close_code == 1008
    assert client.in_flight == 0
    assert any("not JSON-RPC" in r.getMessage() for r in caplog.records)


async def test_unknown_notifications_are_ignored(peer: FakePeer, client: Client) -> None:
    peer.reply = answer_add
    await peer.connections[0].send('{"jsonrpc":"2.0","method":"$/progress","params":{"n":1}}')
    assert (await client.call(ADD, {"a": 1, "b": 1})).sum == 2


async def test_a_reply_larger_than_max_message_size_drops_the_connection(
    peer: FakePeer,
) -> None:
    async def huge(ws: ServerConnection, message: dict[str, Any]) -> None:
        result = {"success": True, "message": "x" * 2000}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))

    peer.reply = huge
    async with connect(peer.url, max_message_size=1000) as client:
        with pytest.raises(ConnectionLost) as caught:
            await client.call("/trigger")
    assert caught.value.data["close_code"] == 1009


# --- replies routed unparsed ------------------------------------------------------------------

STATE_TYPE = "advanced_communication_tutorials/srv/RobotStateQuery"


def compact(id: int, result: str) -> str:
    """A response written as srvwire servers write it, with ``result`` as it is."""
    return f'{{"jsonrpc":"2.0","id":{id},"result":{result}}}'


async def answer_add_compactly(ws: ServerConnection, message: dict[str, Any]) -> None:
    """Answer AddTwoInts calls as a srvwire server does: compact JSON, one result member."""
    if message.get("method") == ADD and "id" in message:
        params = message["params"]
        total = params.get("a", 0) + params.get("b", 0)
        await ws.send(compact(message["id"], f'{{"sum":{total}}}'))


class Parses:
    """Records every message the client parses in full: in its reader, or in a caller."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.by_reader: list[str | bytes] = []
        self.by_callers: list[str] = []
        reader_parse, caller_parse = srvwire.session.parse_replies, RawReply.parse

        def by_reader(data: str | bytes) -> Any:
            self.by_reader.append(data)
            return reader_parse(data)

        def by_caller(raw: RawReply) -> Any:
            self.by_callers.append(raw.message)
            return caller_parse(raw)

        monkeypatch.setattr(srvwire.session, "parse_replies", by_reader)
        monkeypatch.setattr(RawReply, "parse", by_caller)


async def next_call_id(peer: FakePeer) -> int:
    request = await peer.next(ADD)
    return int(request["id"])


async def test_a_reply_as_srvwire_servers_write_it_is_never_parsed_apart_from_its_result(
    peer: FakePeer, client: Client, add_two_ints: type[Service], monkeypatch: pytest.MonkeyPatch
) -> None:
    parses = Parses(monkeypatch)
    peer.reply = answer_add_compactly
    response = await client.call(ADD, {"a": 1, "b": 2})
    assert type(response) is add_two_ints.Response and response.sum == 3
    assert (parses.by_reader, parses.by_callers) == ([], [])
    assert client.in_flight == 0


async def test_a_call_to_an_unadvertised_service_gets_the_dict_from_a_reply_routed_unparsed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    unknown = FakePeer([])  # a peer that answers a service it does not advertise: no type

    async def echo(ws: ServerConnection, message: dict[str, Any]) -> None:
        params = {k: v for k, v in message["params"].items() if k != "_meta"}
        await ws.send(compact(message["id"], json.dumps(params, separators=(",", ":"))))

    unknown.reply = echo
    await unknown.start()
    try:
        async with connect(unknown.url, timeout=scaled(5)) as client:
            parses = Parses(monkeypatch)
            assert await client.call("/echo", {"x": [1, 2.5], "y": None}) == {
                "x": [1, 2.5],
                "y": None,
            }
            # Parsed once, in full, by the caller: the reader only routed it.
            assert parses.by_reader == []
            assert [json.loads(text)["result"] for text in parses.by_callers] == [
                {"x": [1, 2.5], "y": None}
            ]
    finally:
        await unknown.stop()


async def test_a_reply_with_more_members_after_its_result_still_works(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    parses = Parses(monkeypatch)
    typed = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}))
    untyped = asyncio.create_task(client.call("/unadvertised", {}))  # no type: plain data
    ws = peer.connections[0]
    first, second = await peer.next(), await peer.next()
    calls = {first["method"]: first["id"], second["method"]: second["id"]}
    # The text between the opening and the final brace is no JSON value, but the message is
    # valid JSON-RPC, and the member after the result is ignored, as it always was.
    await ws.send(compact(calls[ADD], '{"sum":3},"x":2'))
    await ws.send(compact(calls["/unadvertised"], '1,"x":2'))
    assert (await typed).sum == 3
    assert await untyped == 1
    assert parses.by_reader == []
    assert len(parses.by_callers) == 2
    assert client.connected


async def test_a_raw_reply_that_is_not_json_rpc_fails_every_pending_call(
    peer: FakePeer, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    calls = [asyncio.create_task(client.call(ADD, {"a": i}, timeout=scaled(30))) for i in range(3)]
    ids = [await next_call_id(peer) for _ in calls]
    ws = peer.connections[0]
    error = '{"code":1,"message":"m"}'
    await ws.send(compact(ids[0], f'{{}},"error":{error}'))
    results = await asyncio.gather(*calls, return_exceptions=True)
    assert all(type(r) is ConnectionLost for r in results), results
    expected = "the server broke the protocol: Invalid reply: both 'result' and 'error'"
    for lost in results:
        assert isinstance(lost, ConnectionLost)
        assert (lost.message, lost.service) == (expected, ADD)
        assert lost.data == {"close_code": 1008, "url": peer.url}
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    assert ws.close_code == 1008
    assert client.in_flight == 0 and not client.connected
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR] == [
        f"{peer.url} sent something that is not JSON-RPC: Invalid reply: both 'result' and "
        "'error'; closing the connection"
    ]


@pytest.mark.parametrize(
    ("tail", "reason"),
    [
        (',"id":{other}', "Invalid reply: 'id' given twice ({id} and {other})"),
        (',"method":"$/services","params":{{}}', "Invalid reply: both 'result' and 'method'"),
        (",x", "Parse error: key must be a string at line 1 column {column}"),
    ],
)
async def test_a_raw_reply_that_is_not_the_response_it_opens_as_fails_the_connection(
    peer: FakePeer, client: Client, tail: str, reason: str
) -> None:
    calls = [asyncio.create_task(client.call(ADD, {"a": i}, timeout=scaled(30))) for i in range(2)]
    ids = [await next_call_id(peer) for _ in calls]
    text = compact(ids[0], "{}" + tail.format(other=ids[1]))
    await peer.connections[0].send(text)
    results = await asyncio.gather(*calls, return_exceptions=True)
    why = reason.format(id=ids[0], other=ids[1], column=len(text) - 1)  # where the x is
    assert [getattr(r, "message", r) for r in results] == [
        f"the server broke the protocol: {why}"
    ] * 2
    assert not client.connected


@pytest.mark.parametrize(
    ("bad", "split", "why"),
    [
        (b"\xff", False, "invalid start byte"),
        # Half a character ends the first fragment, so each frame on its own could still be
        # the start of valid text: only the joined message is not UTF-8.
        (b"\xc3x", True, "invalid continuation byte"),
    ],
    ids=["one frame", "fragments"],
)
async def test_invalid_utf8_in_a_reply_routed_unparsed_still_closes_with_1007(
    peer: FakePeer, client: Client, bad: bytes, split: bool, why: str
) -> None:
    task = asyncio.create_task(client.call("/trigger", timeout=scaled(30)))
    request = await peer.next("/trigger")
    ws = peer.connections[0]
    text = compact(request["id"], '{"success":true,"message":"?"}').encode().replace(b"?", bad)
    position = text.index(bad)
    if split:  # a text message in two frames, cut after the half character
        await ws.send([text[: position + 1], text[position + 1 :]], text=True)
    else:
        await ws.send(text, text=True)  # a text frame that is not UTF-8
    with pytest.raises(ConnectionLost) as caught:
        await task
    reason = f"{why} at position {position}"
    assert caught.value.message == f"the connection closed with code 1007 ({reason})"
    assert caught.value.data == {"close_code": 1007, "close_reason": reason, "url": peer.url}
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    assert ws.close_code == 1007


async def test_a_reply_in_a_binary_frame_is_parsed_by_the_reader(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    parses = Parses(monkeypatch)
    task = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}))
    text = compact(await next_call_id(peer), '{"sum":3}')
    await peer.connections[0].send(text.encode())  # bytes: a binary frame
    assert (await task).sum == 3
    assert parses.by_reader == [text.encode()]


async def test_a_reply_nobody_waits_for_is_parsed_and_dropped_or_fails_the_connection(
    peer: FakePeer, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="srvwire.client")
    with pytest.raises(DeadlineExceeded):
        await client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(0.1))
    late = await next_call_id(peer)
    ws = peer.connections[0]
    await ws.send(compact(late, '{"sum":3}'))  # well-formed: dropped
    peer.reply = answer_add_compactly
    assert (await client.call(ADD, {"a": 2, "b": 2})).sum == 4
    assert f"dropping a reply for id {late}: no call waits for it" in caplog.messages
    # The same reply with a tail that is not JSON is checked as before, and fails the connection.
    peer.reply = None
    task = asyncio.create_task(client.call(ADD, {"a": 1}, timeout=scaled(30)))
    assert (await peer.next(ADD))["params"]["a"] == 2  # the call answered above
    assert (await peer.next(ADD))["params"]["a"] == 1  # this one: the client waits for it
    await ws.send(compact(late, '{"sum":3},"error":{}'))
    with pytest.raises(ConnectionLost) as caught:
        await task
    assert caught.value.message == (
        "the server broke the protocol: Invalid reply: both 'result' and 'error'"
    )
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    assert ws.close_code == 1008


async def test_a_raw_reply_that_does_not_match_the_type_is_an_internal_error(
    peer: FakePeer, client: Client
) -> None:
    async def wrong(ws: ServerConnection, message: dict[str, Any]) -> None:
        await ws.send(compact(message["id"], '{"sum":"three","extra":1}'))

    peer.reply = wrong
    with pytest.raises(InternalError) as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    # The errors and their wording are those of validating the decoded data, as before.
    assert caught.value.message == (
        "the response does not match example_interfaces/srv/AddTwoInts: "
        "sum: Input should be a valid integer (and 1 more)"
    )
    assert caught.value.data == {
        "errors": [
            {"path": "sum", "message": "Input should be a valid integer", "type": "int_type"},
            {
                "path": "extra",
                "message": "Extra inputs are not permitted",
                "type": "extra_forbidden",
            },
        ]
    }
    assert client.connected


async def test_a_reply_naming_a_renamed_field_by_its_python_name_is_refused() -> None:
    # The JSON name of a field is its name in the file (from); from_ is Python's only.
    move = build_service(parse_service("uint32 to\n---\nuint32 from\n", "srvwire_tests", "Go"))
    peer = FakePeer([{"name": "/go", "type": "srvwire_tests/srv/Go"}])
    results: list[str] = []

    async def answer_twice(ws: ServerConnection, message: dict[str, Any]) -> None:
        # Written as srvwire writes it (read in one pass), or otherwise (parsed first).
        text = results.pop(0)
        if text.startswith(" "):
            await ws.send(f'{{"result": {text}, "jsonrpc": "2.0", "id": {message["id"]}}}')
        else:
            await ws.send(compact(message["id"], text))

    peer.reply = answer_twice
    await peer.start()
    try:
        async with connect(peer.url, timeout=scaled(5)) as client:
            results.append('{"from":7}')
            assert (await client.call("/go", move.Request(), srv_type=move)).from_ == 7
            for text in ('{"from_":7}', ' {"from_": 7}'):
                results.append(text)
                with pytest.raises(InternalError) as caught:
                    await client.call("/go", move.Request(), srv_type=move)
                assert caught.value.data == {
                    "errors": [
                        {
                            "path": "from_",
                            "message": "Extra inputs are not permitted",
                            "type": "extra_forbidden",
                        }
                    ]
                }
    finally:
        await peer.stop()


async def test_non_finite_floats_and_integers_beyond_a_double_decode_as_infinity() -> None:
    state = FakePeer([{"name": "/state", "type": STATE_TYPE}])
    values: list[str] = []

    async def answer(ws: ServerConnection, message: dict[str, Any]) -> None:
        await ws.send(compact(message["id"], f'{{"values":[{values.pop(0)}]}}'))

    state.reply = answer
    await state.start()
    beyond = "1" + "0" * 309  # an integer literal a double cannot hold
    try:
        async with connect(state.url, timeout=scaled(5)) as client:
            values.append("NaN,Infinity,-Infinity")
            nan, inf, minus_inf = (await client.call("/state")).values
            assert nan != nan and (inf, minus_inf) == (float("inf"), float("-inf"))
            # Too large for a double, written as a float or as an integer: infinity either way.
            values.append(f"1e400,{beyond},-{beyond}")
            assert (await client.call("/state")).values == [math.inf, math.inf, -math.inf]
            values.append('"not a number"')
            with pytest.raises(InternalError) as caught:
                await client.call("/state")
            (error,) = caught.value.data["errors"]
            assert (error["path"], error["type"]) == ("values[0]", "float_type")
    finally:
        await state.stop()


async def test_a_raw_reply_checked_as_its_caller_gives_up_still_fails_the_connection(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The reader hands the unparsed reply over, and in the same step the caller is cancelled:
    # the reply is checked anyway, as the reader checked every reply before.
    call = call_cancelled_as_answered(client, monkeypatch)
    await a_bad_reply_to_the_cancelled_call_fails_the_connection(peer, client, call)


async def a_bad_reply_to_the_cancelled_call_fails_the_connection(
    peer: FakePeer, client: Client, call: asyncio.Task[Any]
) -> None:
    """Answer ``call`` with both a result and an error: the call ends cancelled, and the
    client, which read the reply all the same, closes the connection with 1008."""
    ws = peer.connections[0]
    await ws.send(compact(await next_call_id(peer), '{"sum":3},"error":{}'))
    with pytest.raises(asyncio.CancelledError):
        await call
    await asyncio.wait_for(ws.wait_closed(), scaled(5))
    assert ws.close_code == 1008
    assert not client.connected


async def test_a_raw_reply_whose_call_was_cancelled_as_it_came_is_still_checked(
    peer: FakePeer, client: Client
) -> None:
    # From Python 3.12 a cancelled caller cancels the future it awaits at once, so a reply
    # routed in that step finds its call's future already done: it is checked all the same.
    class CancelledAsTaken(dict[int, Any]):
        def pop(self, key: int, default: Any = None) -> Any:
            future = super().pop(key, None)
            if future is None:
                return default
            future.cancel()  # what Python 3.12 does to it as its caller is cancelled
            return future

    session = client._link.session  # type: ignore[union-attr]
    session.pending = CancelledAsTaken(session.pending)
    call = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}))
    await a_bad_reply_to_the_cancelled_call_fails_the_connection(peer, client, call)


# --- waiting for services and for the server --------------------------------------------------


async def test_wait_for_service_wakes_when_the_service_is_advertised(
    peer: FakePeer, client: Client
) -> None:
    waiter = asyncio.create_task(client.wait_for_service("late", timeout=scaled(5)))
    await asyncio.sleep(0)  # let the waiter start waiting (no message will satisfy it yet)
    assert not waiter.done()
    ws = peer.connections[0]
    await ws.send(services_text([*SERVICES, {"name": "/other", "type": ADD_TYPE}]))
    await ws.send(services_text([*SERVICES, {"name": "/late", "type": "std_srvs/srv/Empty"}]))
    assert await waiter == ServiceInfo("/late", "std_srvs/srv/Empty")
    assert peer.received.empty()  # woken by $/services, not by asking the server


async def test_wait_for_service_gives_up_with_service_unavailable(client: Client) -> None:
    with pytest.raises(ServiceUnavailable) as caught:
        await client.wait_for_service("/never", timeout=scaled(0.2))
    assert type(caught.value) is ServiceUnavailable
    assert caught.value.service == "/never"
    assert caught.value.message == f"the service was not advertised within {scaled(0.2):g} s"


async def test_an_advertised_service_is_there_at_once(client: Client) -> None:
    assert await client.wait_for_service(ADD, timeout=scaled(1)) == ServiceInfo(ADD, ADD_TYPE)


async def test_wait_for_ready_waits_for_a_server_that_comes_up_later() -> None:
    port = free_port()
    late = FakePeer()
    late.reply = answer_add
    async with connect(f"ws://127.0.0.1:{port}", reconnect=True) as client:
        assert not client.connected
        with pytest.raises(ConnectionLost, match="not connected"):
            await client.call(ADD, {"a": 1, "b": 2})  # without wait_for_ready: fail fast
        call = asyncio.create_task(
            client.call(ADD, {"a": 1, "b": 2}, wait_for_ready=True, timeout=scaled(10))
        )
        await late.start(port)
        try:
            assert (await call).sum == 3
            assert client.connected
        finally:
            await late.stop()


async def test_wait_for_ready_gives_up_within_the_deadline() -> None:
    url = f"ws://127.0.0.1:{free_port()}"
    async with connect(url, reconnect=True) as client:
        with pytest.raises(ServiceUnavailable) as caught:
            await client.call(ADD, {"a": 1}, wait_for_ready=True, timeout=scaled(0.3))
    assert type(caught.value) is ServiceUnavailable
    assert caught.value.message == f"the service was not reachable within {scaled(0.3):g} s"


async def test_reconnect_after_the_connection_drops(peer: FakePeer) -> None:
    async with connect(peer.url, reconnect=True) as client:
        pending = asyncio.create_task(client.call(ADD, {"a": 1}, timeout=scaled(30)))
        await peer.next(ADD)
        await peer.connections[0].close(1012, "restarting")
        with pytest.raises(ConnectionLost):
            await pending  # a call in flight is never retried: it may have run
        peer.reply = answer_add
        response = await client.call(ADD, {"a": 2, "b": 3}, wait_for_ready=True, timeout=scaled(5))
        assert response.sum == 5
        assert len(peer.connections) == 2


# --- against the real server ------------------------------------------------------------------


def add(request: Any) -> dict[str, int]:
    return {"sum": request.a + request.b}


async def query_state(request: Any) -> dict[str, Any]:
    names = ["x", "y"] if request.query_type == "pose" else []
    return {"success": bool(names), "values": [1.5, -2.0][: len(names)], "names": names}


@pytest.fixture
async def server(transport: Transport) -> AsyncIterator[RunningServer]:
    """The real server, on each transport in turn."""
    srv = Server(max_in_flight=2000)
    srv.add_service(ADD, load_service(ADD_TYPE), add)
    srv.add_service(
        "/robot1/get_robot_state",
        load_service("advanced_communication_tutorials/srv/RobotStateQuery"),
        query_state,
    )
    async with serve(srv, "127.0.0.1", 0, transport=transport) as running:
        yield running


async def test_round_trips_with_the_real_server(server: RunningServer) -> None:
    async with connect(server.url, transport=server.transport, timeout=scaled(5)) as client:
        assert (await client.call(ADD, {"a": 2**40, "b": -(2**62)})).sum == 2**40 - 2**62
        assert (await client.call("add_two_ints", {"a": 1})).sum == 1
        state = await client.call("/robot1/get_robot_state", {"query_type": "pose"})
        assert (state.success, state.values, state.names) == (True, [1.5, -2.0], ["x", "y"])
        assert state.message == ""  # every field is present in the result
        add_proxy = client.proxy(ADD)
        assert (await add_proxy(a=20, b=22)).sum == 42


async def test_the_real_servers_replies_are_routed_unparsed(
    server: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with connect(server.url, transport=server.transport, timeout=scaled(5)) as client:
        parses = Parses(monkeypatch)
        state = await client.call("/robot1/get_robot_state", {"query_type": "pose"})
        assert type(state) is load_service(STATE_TYPE).Response
        assert (state.success, state.values, state.names) == (True, [1.5, -2.0], ["x", "y"])
        assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
        assert (parses.by_reader, parses.by_callers) == ([], [])
        # rpc.discover has no type: its caller parses the whole reply, once.
        assert len(await client.list_services()) == 2
        assert parses.by_reader == [] and len(parses.by_callers) == 1
        with pytest.raises(ServiceNotFound):  # an error reply: the reader parses it
            await client.call("/nowhere")
        assert len(parses.by_reader) == 1


async def test_errors_from_the_real_server(server: RunningServer) -> None:
    async with connect(server.url, transport=server.transport, timeout=scaled(5)) as client:
        with pytest.raises(ServiceNotFound) as not_found:
            await client.call("/add_two_int", {"a": 1})
        assert not_found.value.service == "/add_two_int"
        assert ADD in not_found.value.data["candidates"]
        # A type that validates here but not on the server: the server's InvalidParams.
        set_bool = load_service("std_srvs/srv/SetBool")
        with pytest.raises(InvalidParams) as invalid:
            await client.call(ADD, {"data": True}, srv_type=set_bool)
        assert [e["path"] for e in invalid.value.errors] == ["data"]
        assert (await client.call(ADD, {"a": 1, "b": 1})).sum == 2


async def test_list_services_on_the_real_server(server: RunningServer) -> None:
    async with connect(server.url, transport=server.transport) as client:
        assert await client.list_services() == [
            ServiceInfo(ADD, ADD_TYPE),
            ServiceInfo(
                "/robot1/get_robot_state", "advanced_communication_tutorials/srv/RobotStateQuery"
            ),
        ]


async def test_a_thousand_concurrent_calls_on_one_connection(server: RunningServer) -> None:
    async with connect(server.url, transport=server.transport, timeout=scaled(20)) as client:
        responses = await asyncio.gather(*(client.call(ADD, {"a": i, "b": i}) for i in range(1000)))
        assert [r.sum for r in responses] == [2 * i for i in range(1000)]
        assert client.in_flight == 0


async def test_a_hundred_connections_at_once(server: RunningServer) -> None:
    async def one(i: int) -> int:
        async with connect(
            server.url, transport=server.transport, timeout=scaled(20), open_timeout=scaled(20)
        ) as client:
            response = await client.call(ADD, {"a": i, "b": 1})
            return int(response.sum)

    assert await asyncio.gather(*(one(i) for i in range(100))) == [i + 1 for i in range(100)]


async def test_wait_for_service_wakes_when_the_real_server_adds_it(
    server: RunningServer,
) -> None:
    trigger = load_service("std_srvs/srv/Trigger")
    async with connect(server.url, transport=server.transport) as client:
        waiter = asyncio.create_task(client.wait_for_service("/late", timeout=scaled(5)))
        await asyncio.sleep(0)  # the waiter is waiting now; nothing has added /late yet
        assert not waiter.done()
        server.server.add_service("/late", trigger, lambda request: {"success": True})
        assert await waiter == ServiceInfo("/late", "std_srvs/srv/Trigger")
        assert (await client.call("/late")).success is True
        server.server.remove_service("/late")
        with pytest.raises(ServiceUnavailable):
            await client.wait_for_service("/gone", timeout=scaled(0.2))


async def test_a_call_after_the_services_change_finds_its_type_again(
    server: RunningServer,
) -> None:
    # What a call found for its service (its type, compared with the server's) is kept for
    # the next calls on the connection, until $/services says something changed.
    trigger = load_service("std_srvs/srv/Trigger")
    set_bool = load_service("std_srvs/srv/SetBool")
    server.server.add_service("/switch", trigger, lambda request: {"success": True})
    async with connect(server.url, transport=server.transport) as client:
        await client.wait_for_service("/switch")
        for _ in range(2):  # the second call finds what the first one found
            assert type(await client.call("/switch")) is trigger.Response
        link = client._link
        assert link is not None and link.ready == {"/switch": ("/switch", ANY)}
        server.server.remove_service("/switch")
        server.server.add_service("/switch", set_bool, lambda request: {"success": request.data})
        server.server.add_service("/marker", trigger, lambda request: {"success": True})
        await client.wait_for_service("/marker")  # every $/services before it has arrived
        assert link.ready == {}
        reply = await client.call("switch", {"data": True})  # a Trigger takes no "data"
        assert type(reply) is set_bool.Response and reply.success is True
        assert link.ready == {"switch": ("/switch", ANY)}


async def test_a_type_found_while_the_services_change_is_not_kept(peer: FakePeer) -> None:
    # The client asks the server to describe a type it does not have; the services change
    # before the description arrives. That call goes on with the type it was advertised, but
    # what it found is not kept: the next call finds the new type.
    definitions = {
        "xx_msgs/srv/Foo": "int64 a\n---\nint64 r\n",
        "xx_msgs/srv/Bar": "string s\n---\nstring out\n",
    }
    peer.services = [{"name": "/svc", "type": "xx_msgs/srv/Foo"}]  # no fingerprints

    async def reply(ws: ServerConnection, message: dict[str, Any]) -> None:
        if message.get("method") == "rpc.discover":
            await ws.send(services_text([{"name": "/svc", "type": "xx_msgs/srv/Bar"}]))
            methods = [{"name": "/svc", "x-srvwire-definitions": definitions}]
            document = {"openrpc": "1.3.2", "methods": methods}
            await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": document}))
        elif "id" in message:
            result = {"out": "ok"} if "s" in message["params"] else {"r": 1}
            await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "result": result}))

    peer.reply = reply
    async with connect(peer.url, timeout=scaled(5)) as client:
        assert (await client.call("/svc", {"a": 1})).r == 1  # type: ignore[attr-defined]
        assert client._link is not None and client._link.ready == {}
        assert (await client.call("/svc", {"s": "x"})).out == "ok"  # type: ignore[attr-defined]


async def test_a_link_keeps_a_bounded_number_of_calls_ready() -> None:
    link = Link(None, None)  # type: ignore[arg-type]  # neither is used here
    for i in range(MAX_READY):
        link.remember(f"/s{i}", (f"/s{i}", None))
    assert len(link.ready) == MAX_READY
    link.remember("/one_more", ("/one_more", None))
    assert link.ready == {"/one_more": ("/one_more", None)}


async def test_a_send_that_ends_in_the_turn_its_call_fails_cancels_nothing_after_it() -> None:
    # A call waits in its send (backpressure); the send finishes and the call's future fails
    # (the client closed) in the same loop turn, the send's wake-up first. The call goes on
    # past its send; the failure's callback, already scheduled when the send ended, must not
    # cancel what the task awaits next.
    loop = asyncio.get_running_loop()
    link = Link(None, None)  # type: ignore[arg-type]  # neither is used here
    drained: asyncio.Future[None] = loop.create_future()
    answer: asyncio.Future[Any] = loop.create_future()
    after: asyncio.Future[str] = loop.create_future()

    async def send() -> None:
        await drained

    coroutine = send()
    pending = Pending(coroutine, coroutine.send(None), None)

    async def call() -> str:
        await link.send_unless_lost(pending, answer, 30.0)
        return await after  # what the task awaits next

    task = asyncio.create_task(call())
    await asyncio.sleep(0)  # the task waits in its send
    drained.set_result(None)  # the send ends: the task's wake-up is scheduled...
    answer.set_exception(ConnectionLost("the client was closed"))  # ...then the failure's
    for _ in range(3):
        await asyncio.sleep(0)
    after.set_result("went on")
    assert await task == "went on"


async def test_wait_for_ready_waits_for_the_real_server_to_come_up() -> None:
    port = free_port()
    srv = Server()
    srv.add_service(ADD, load_service(ADD_TYPE), add)
    async with connect(f"ws://127.0.0.1:{port}", reconnect=True) as client:
        call = asyncio.create_task(
            client.call(ADD, {"a": 3, "b": 4}, wait_for_ready=True, timeout=scaled(10))
        )
        assert not client.connected
        async with serve(srv, "127.0.0.1", port):
            assert (await call).sum == 7


class DialFailures(logging.Handler):
    """Counts the client's failed attempts to connect, and wakes whoever waits for one more."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.count = 0
        self.changed = asyncio.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("cannot connect to"):
            self.count += 1
            self.changed.set()

    async def more_than(self, count: int) -> None:
        while self.count <= count:
            self.changed.clear()
            await self.changed.wait()


async def test_wait_for_service_waits_for_a_server_that_starts_later() -> None:
    url = f"ws://127.0.0.1:{free_port()}"
    with pytest.raises(ServiceUnavailable, match="cannot connect"):
        await connect(url, open_timeout=scaled(5))  # without reconnect: fails fast
    srv = Server()
    srv.add_service(ADD, load_service(ADD_TYPE), add)
    failures = DialFailures()
    logger = logging.getLogger(f"{__name__}.late_server")
    logger.setLevel(logging.DEBUG)
    logger.addHandler(failures)
    try:
        async with connect(url, reconnect=True, logger=logger) as client:
            waiting = asyncio.Event()

            async def wait() -> ServiceInfo:
                waiting.set()  # wait_for_service does not yield before it sleeps on its event
                return await client.wait_for_service(ADD, timeout=scaled(10))

            waiter = asyncio.create_task(wait())
            await waiting.wait()
            # Once the waiter sleeps, the client fails to dial again: still no server.
            await failures.more_than(failures.count)
            assert not waiter.done() and not client.connected
            async with serve(srv, "127.0.0.1", int(url.rsplit(":", 1)[1])):
                # Woken by the connection and its $/services; not by asking the server.
                assert await waiter == ServiceInfo(ADD, ADD_TYPE)
                assert client.connected and client.in_flight == 0
    finally:
        logger.removeHandler(failures)


async def test_an_error_without_an_id_is_logged(
    peer: FakePeer, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    error = {"code": -32700, "message": "Parse error", "data": {"status": "PARSE_ERROR"}}
    await peer.connections[0].send(json.dumps({"jsonrpc": "2.0", "id": None, "error": error}))
    peer.reply = answer_add
    assert (await client.call(ADD, {"a": 1, "b": 1})).sum == 2
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        "the server could not read a message: PARSE_ERROR (-32700): Parse error"
    ]


async def test_a_failing_reader_fails_the_calls_instead_of_leaving_them_waiting(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(data: str | bytes) -> None:
        raise RuntimeError("a bug in the reader")

    monkeypatch.setattr(client._link.session, "receive", broken)  # type: ignore[union-attr]
    task = asyncio.create_task(client.call(ADD, {"a": 1}, timeout=scaled(30)))
    await peer.next(ADD)
    await peer.connections[0].send('{"jsonrpc":"2.0","method":"$/progress"}')
    with pytest.raises(ConnectionLost) as caught:
        await task
    assert caught.value.message == "the client failed to process a message from the server"
    assert client.in_flight == 0


def hold_sends_of(
    client: Client, method: str, monkeypatch: pytest.MonkeyPatch
) -> tuple[asyncio.Event, list[BaseException]]:
    """Make the client's sends of calls to ``method`` wait forever, as backpressure would."""
    link = client._link
    assert link is not None
    conn = link.conn
    send = type(conn).send
    held = asyncio.Event()
    ended: list[BaseException] = []

    async def held_send(self: Any, message: str | bytes) -> None:
        data = message.encode() if isinstance(message, str) else message
        if self is not conn or f'"method":"{method}"'.encode() not in data:
            return await send(self, message)
        held.set()
        try:
            await asyncio.Event().wait()  # the peer does not read: the send cannot finish
        except BaseException as exc:
            ended.append(exc)
            raise

    monkeypatch.setattr(type(conn), "send", held_send)
    return held, ended


async def test_a_send_held_by_backpressure_meets_the_deadline(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    held, ended = hold_sends_of(client, ADD, monkeypatch)
    with pytest.raises(DeadlineExceeded, match="no response within"):
        await client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(0.2))
    assert held.is_set() and len(ended) == 1 and isinstance(ended[0], asyncio.CancelledError)
    task = asyncio.current_task()
    assert task is not None and task.cancelling() == 0  # the deadline's request was taken back
    assert client.in_flight == 0
    await asyncio.sleep(scaled(0.3))  # the timer was disarmed: nothing cancels this later


async def test_cancelling_a_caller_held_in_its_send_stays_a_cancellation(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    held, ended = hold_sends_of(client, ADD, monkeypatch)
    call = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(10)))
    await held.wait()
    call.cancel()
    with pytest.raises(asyncio.CancelledError):
        await call
    assert len(ended) == 1 and client.in_flight == 0


async def test_a_request_model_that_is_not_an_object_is_refused_before_sending(
    peer: FakePeer, client: Client
) -> None:
    from pydantic import RootModel

    class Numbers(RootModel[list[int]]):
        pass

    peer.reply = answer_add
    # "/untyped" is not advertised, so the client has no type to check the request against.
    loop = asyncio.get_running_loop()
    started = loop.time()
    with pytest.raises(TypeError, match="must serialize to a JSON object") as caught:
        await client.call("/untyped", Numbers([1, 2]))
    assert "[1,2]" in str(caught.value)
    assert loop.time() - started < scaled(1)  # at once, not at the deadline
    # Nothing was sent: the first message the peer sees is the next, valid call.
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    assert (await peer.next())["method"] == ADD


async def test_only_a_send_that_waits_is_bounded_by_a_timer(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A send that fits in the socket's buffer finishes in its first step: nothing to bound.
    armed = record_calls(monkeypatch, srvwire.link, "finish_within")
    peer.reply = answer_add
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    assert armed == []
    hold_sends_of(client, ADD, monkeypatch)
    with pytest.raises(DeadlineExceeded):
        await client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(0.2))
    assert len(armed) == 1


def hold_sends_until_answered(
    client: Client, method: str, monkeypatch: pytest.MonkeyPatch
) -> asyncio.Event:
    """Make the client's sends of calls to ``method`` write, then wait, as backpressure holds a
    send, until the reply has reached the client; return the event set as it does."""
    link = client._link
    assert link is not None
    conn = link.conn
    send = type(conn).send
    answered = asyncio.Event()
    when_routed(client, answered.set)

    async def send_then_wait(self: Any, message: str | bytes) -> None:
        await send(self, message)
        data = message.encode() if isinstance(message, str) else message
        if self is conn and f'"method":"{method}"'.encode() in data:
            await answered.wait()

    monkeypatch.setattr(type(conn), "send", send_then_wait)
    return answered


async def test_a_reply_that_arrives_while_the_send_waits_is_returned_at_once(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The send's wait is bounded by its own timer; the reply is there when it ends, so the
    # call returns it without arming wait_for's timer and waiting a loop turn more.
    peer.reply = answer_add
    answered = hold_sends_until_answered(client, ADD, monkeypatch)
    armed = record_calls(monkeypatch, srvwire.link, "finish_within")
    waited = record_calls(monkeypatch, asyncio, "wait_for")
    assert (await client.call(ADD, {"a": 1, "b": 2})).sum == 3
    assert answered.is_set() and len(armed) == 1 and waited == []
    assert client.in_flight == 0
    monkeypatch.undo()
    assert (await client.call(ADD, {"a": 2, "b": 2})).sum == 4  # a call that waits: wait_for
    assert [(await peer.next())["method"] for _ in range(2)] == [ADD, ADD]  # no $/cancel


async def test_an_error_that_arrives_while_the_send_waits_is_raised_at_once(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    async def refuse(ws: ServerConnection, message: dict[str, Any]) -> None:
        if "id" not in message:
            return
        error = {"code": -32602, "message": "no", "data": {"status": "INVALID_PARAMS"}}
        await ws.send(json.dumps({"jsonrpc": "2.0", "id": message["id"], "error": error}))

    peer.reply = refuse
    hold_sends_until_answered(client, ADD, monkeypatch)
    waited = record_calls(monkeypatch, asyncio, "wait_for")
    with pytest.raises(InvalidParams) as caught:
        await client.call(ADD, {"a": 1, "b": 2})
    assert (caught.value.message, caught.value.service) == ("no", ADD)
    assert waited == [] and client.in_flight == 0


# --- options and payload never share a namespace --------------------------------------------

OPTIONS_AS_FIELDS = """\
# A request whose fields are called like the options of a call.
float64 timeout
string srv_type
bool wait_for_ready
---
string seen
"""


async def test_fields_named_like_options_are_payload(transport: Transport) -> None:
    from conftest import build

    options_srv = build(OPTIONS_AS_FIELDS, "OptionsAsFields")

    def seen(request: Any) -> dict[str, str]:
        return {"seen": f"{request.timeout} {request.srv_type} {request.wait_for_ready}"}

    srv = Server()
    srv.add_service("/options", options_srv, seen)
    async with (
        serve(srv, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        fields = {"timeout": 2.5, "srv_type": "x/srv/Y", "wait_for_ready": True}
        expected = "2.5 x/srv/Y True"
        assert (await client.call("/options", fields, srv_type=options_srv)).seen == expected
        proxy = client.proxy("/options", options_srv, timeout=scaled(5))
        assert (await proxy(timeout=2.5, srv_type="x/srv/Y", wait_for_ready=True)).seen == (
            expected
        )
        with pytest.raises(TypeError, match="unexpected keyword argument 'a'"):
            await client.call("/options", a=1)  # type: ignore[call-arg]


# --- connect: awaitable, async with, and async for ------------------------------------------


async def test_async_for_gives_a_new_client_each_round(transport: Transport) -> None:
    srv = Server()
    srv.add_service(ADD, load_service(ADD_TYPE), add)
    clients: list[Client] = []
    async with serve(srv, "127.0.0.1", 0, transport=transport) as running:
        async for client in connect(running.url, transport=transport, timeout=scaled(5)):
            clients.append(client)
            assert (await client.call(ADD, {"a": len(clients), "b": 1})).sum == len(clients) + 1
            if len(clients) == 1:
                await running._connections.copy().pop().conn.close(1001, "going away")
                with pytest.raises(ConnectionLost):
                    await client.call(ADD, {"a": 1})
                continue  # as a loop that reconnects does
            assert not clients[0].connected  # closed as the loop came round
            break
        await clients[1].close()  # the last one is the loop's to close when it leaves early
    first, second = clients
    assert first is not second


async def test_services_from_a_connection_that_is_no_longer_current_are_not_news(
    peer: FakePeer, client: Client
) -> None:
    # A link that failed keeps reading until its close completes; what it reads then must not
    # overwrite the services of the link that replaced it.
    current = client._link
    assert current is not None
    before = dict(client.services)
    client.services_changed(object(), {"/stale": "x/srv/Y"})  # type: ignore[arg-type]
    assert dict(client.services) == before
    client.services_changed(current, {"/fresh": "x/srv/Y"})
    assert dict(client.services) == {"/fresh": "x/srv/Y"}


def test_a_refusal_lists_ten_problems_and_counts_them_all() -> None:
    from conftest import build
    from srvwire.calls import ServiceCodec, encode_request

    names = build("string[] names\n---\nbool ok\n", "Names")
    request = names.Request(names=["\ud800"] * 25)  # validates, but cannot be written
    with pytest.raises(InvalidParams) as caught:
        encode_request("/names", ServiceCodec(names), request)
    data = caught.value.data
    assert [e["path"] for e in data["errors"]] == [f"names[{i}]" for i in range(10)]
    assert data["error_count"] == 25
    assert "(and 24 more)" in caught.value.message


async def test_an_injected_resolver_gives_typed_replies_for_types_no_file_defines(
    transport: Transport,
) -> None:
    from conftest import build

    made_here = build("int64 x\n---\nint64 twice\n", "Twice", package="made_here")
    srv = Server()
    srv.add_service("/twice", made_here, lambda request: {"twice": 2 * request.x})
    resolved: list[str] = []

    def resolve(type_name: str) -> type[Service]:
        resolved.append(type_name)
        return made_here

    async with (
        serve(srv, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, type_resolver=resolve) as client,
    ):
        reply = await client.call("/twice", {"x": 21})
        assert type(reply) is made_here.Response and reply.twice == 42
        await client.call("/twice", {"x": 1})
    assert resolved == ["made_here/srv/Twice"]  # asked once, then kept


async def test_a_proxy_given_to_a_server_as_its_handler_relays_on_the_event_loop() -> None:
    # A proxy is a coroutine function to the server, so a relay needs no thread: it answers
    # while the server's only handler thread is held by a blocking handler.
    from concurrent.futures import ThreadPoolExecutor
    from threading import Event

    from conftest import Subtract, subtract

    backend = Server()
    backend.add_service("/subtract", Subtract, subtract)
    release = Event()
    started = asyncio.Event()
    loop = asyncio.get_running_loop()

    def block(request: Any) -> Any:
        loop.call_soon_threadsafe(started.set)
        release.wait()
        return {"difference": 0}

    with ThreadPoolExecutor(1) as threads:
        front = Server(executor=threads)
        front.add_service("/block", Subtract, block)
        try:
            async with (
                serve(backend, "127.0.0.1", 0) as behind,
                connect(behind.url) as relay,
                serve(front, "127.0.0.1", 0) as running,
                connect(running.url) as client,
                asyncio.timeout(scaled(10)),
            ):
                front.add_service("/relay", Subtract, relay.proxy("/subtract", Subtract))
                blocked = asyncio.create_task(
                    client.call("/block", {"minuend": 0, "subtrahend": 0}, srv_type=Subtract)
                )
                await started.wait()
                answer = await client.call(
                    "/relay", {"minuend": 5, "subtrahend": 2}, srv_type=Subtract
                )
                assert answer.difference == 3
                assert not blocked.done()  # the thread is still held: the relay did not need it
                release.set()
                assert (await blocked).difference == 0
        finally:
            release.set()


async def stop_reading(ws: ServerConnection, message: dict[str, Any]) -> None:
    """Read nothing more: a server that stopped (its closing handshake never comes)."""
    ws.transport.pause_reading()


async def test_close_fails_pending_calls_before_waiting_for_an_unresponsive_peer(
    peer: FakePeer, client: Client, caplog: pytest.LogCaptureFixture
) -> None:
    peer.reply = stop_reading
    waiting = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(30)))
    await peer.next(ADD)
    # Calls stuck in their send, behind a buffer the peer does not take: fill it past the
    # budget, with one call more once it is.
    conn = client._link.conn  # type: ignore[union-attr]
    big = {"text": "x" * 100_000}
    stuck = []
    while not stuck or not conn.congested:
        stuck.append(
            asyncio.create_task(client.call("/echo", big, timeout=scaled(30), srv_type=Echo))
        )
        await asyncio.sleep(0)  # one loop turn: the call's first step writes it
    stuck.append(asyncio.create_task(client.call("/echo", big, timeout=scaled(30), srv_type=Echo)))
    closing = asyncio.create_task(client.close())
    (ws,) = peer.connections
    try:
        for call in (waiting, *stuck):
            with pytest.raises(ConnectionLost, match="the client was closed") as lost:
                await call
            assert lost.value.service in (ADD, "/echo")
        assert not closing.done()  # the closing handshake still waits for the peer
    finally:
        peer.reply = None
        ws.transport.resume_reading()
    await asyncio.wait_for(closing, scaled(10))
    del lost
    gc.collect()
    assert "never retrieved" not in caplog.text


async def test_close_gives_up_on_a_peer_that_never_reads_after_the_close_timeout(
    peer: FakePeer, client: Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The close timeout bounds the whole closing handshake, including the wait for a buffer
    # full of calls the peer never takes to drain (a shorter one here, so the test is quick).
    peer.reply = stop_reading
    conn = client._link.conn  # type: ignore[union-attr]
    if isinstance(conn, PicowsConnection):
        monkeypatch.setattr(srvwire.transports.picows, "CLOSE_TIMEOUT", 0.2)
    else:
        conn._ws.close_timeout = 0.2  # type: ignore[attr-defined]
    big = {"text": "x" * 100_000}
    stuck = []
    while not conn.congested:
        stuck.append(asyncio.create_task(client.call("/echo", big, srv_type=Echo)))
        await asyncio.sleep(0)  # one loop turn: the call's first step writes it
    await asyncio.wait_for(client.close(), scaled(5))
    assert not client.connected
    for call in stuck:
        with pytest.raises(ConnectionLost, match="the client was closed"):
            await call
    peer.reply = None
    peer.connections[0].transport.resume_reading()  # to see the connection dropped


@pytest.mark.parametrize("transport", ["websockets", "picows"])
async def test_a_peer_that_stops_answering_pings_fails_the_calls_after_the_ping_timeout(
    peer: FakePeer, transport: str
) -> None:
    # No closing handshake is awaited with a peer known to be dead: the call fails after
    # ping_interval + ping_timeout, not after the transport's 10 s close timeout too.
    peer.reply = stop_reading
    async with connect(
        peer.url, transport=transport, ping_interval=0.1, ping_timeout=0.1
    ) as client:
        call = asyncio.create_task(client.call(ADD, {"a": 1, "b": 2}, timeout=scaled(30)))
        with pytest.raises(ConnectionLost) as lost:
            await asyncio.wait_for(call, scaled(5))
        assert lost.value.data["close_code"] == 1011
        assert "keepalive" in lost.value.message or "ping" in lost.value.message
    peer.reply = None
    peer.connections[0].transport.resume_reading()  # to see the connection dropped


@pytest.mark.parametrize("transport", ["websockets", "picows"])
async def test_reconnect_returns_after_open_timeout_from_a_server_that_never_answers(
    transport: str,
) -> None:
    # The kernel accepts the TCP connection into the backlog; nothing ever answers the
    # WebSocket handshake. The first dial gives up at open_timeout and the client goes on
    # dialling in the background, as docs/errors.md says.
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        port = silent.getsockname()[1]
        client = await asyncio.wait_for(
            connect(
                f"ws://127.0.0.1:{port}", reconnect=True, open_timeout=0.2, transport=transport
            ),
            scaled(5),
        )
        try:
            assert not client.connected
            with pytest.raises(ServiceUnavailable):
                await client.wait_for_service(ADD, timeout=0.1)
        finally:
            await asyncio.wait_for(client.close(), scaled(5))


async def test_a_reply_frame_picows_refuses_names_the_clients_limit_and_logs_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # picows itself refuses a frame over FRAME_SLACK times max_message_size, as its header
    # arrives: the error still names the client's setting, and asyncio logs nothing more.
    server = Server(max_message_size=None)

    async def huge(request: Any) -> Any:
        return {"text": "x" * 1_000_000}

    server.add_service("/huge", Echo, huge)
    async with serve(server, "127.0.0.1", 0) as running:
        client = await connect(running.url, transport="picows", max_message_size=100_000)
        with pytest.raises(ConnectionLost) as lost:
            await client.call("/huge", {"text": ""})
        await client.close()
    assert lost.value.data["close_code"] == 1009
    assert lost.value.message.startswith(
        "the connection closed with code 1009 (over the client's max_message_size ("
    ), lost.value.message
    del lost
    gc.collect()
    assert "never retrieved" not in caplog.text
