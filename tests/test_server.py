"""The server over real sockets on 127.0.0.1, driven by a raw WebSocket client."""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import socket
import sys
import threading
from collections.abc import AsyncIterator, Callable, Iterator
from concurrent.futures import Future
from contextlib import asynccontextmanager, contextmanager
from typing import Any, TypeVar

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st
from websockets.asyncio.client import connect as ws_connect
from websockets.client import ClientProtocol
from websockets.exceptions import ConnectionClosed
from websockets.frames import Frame, Opcode
from websockets.sync.client import connect as sync_connect
from websockets.uri import parse_uri

import srvwire
from conftest import Echo, Hang, Subtract, Wire, build, open_wire, real_websockets, subtract
from srvwire import serving
from srvwire.dispatch import Context
from srvwire.errors import RegistrationError, ServiceError
from srvwire.loader import InterfaceLoader
from srvwire.server import RunningServer, Server, serve
from srvwire.serving import CallRunner, ServedConnection
from srvwire.threads import HandlerThreads
from srvwire.transports.base import Options, Transport, TransportClosed
from srvwire.transports.memory import MemoryConnection, MemoryTransport
from srvwire.transports.picows import PicowsConnection
from srvwire.transports.websockets import WebSocketsConnection
from srvwire.typeregistry import fingerprint, full_definition
from support import ROOT, scaled

Sum = build("int64 a\nint64 b\nint64 c\n---\nint64 sum\n", "Sum")
Notify = build("int64[] values\n---\n", "Notify")
GetData = build("---\nstring text\nint64 count\n", "GetData")

T = TypeVar("T")


def request(method: str, params: Any = None, id: Any = 1) -> dict[str, Any]:
    message: dict[str, Any] = {"jsonrpc": "2.0", "method": method, "id": id}
    if params is not None:
        message["params"] = params
    return message


def error(reply: Any) -> tuple[Any, int, str]:
    """``(id, code, status)`` of an error reply, checking its shape on the way."""
    assert set(reply) == {"jsonrpc", "id", "error"}, reply
    assert reply["jsonrpc"] == "2.0"
    return reply["id"], reply["error"]["code"], reply["error"]["data"]["status"]


async def closed_code(wire: Wire) -> int | None:
    """Read until the connection closes; return its close code."""
    with pytest.raises(TransportClosed):
        async with asyncio.timeout(scaled(5)):
            while True:
                await wire.ws.recv()
    return wire.ws.close_code


# --- the JSON-RPC 2.0 specification's examples ----------------------------------------------------


@pytest.fixture
def spec_server(server: Server) -> Server:
    server.add_service("/sum", Sum, lambda r: {"sum": r.a + r.b + r.c})
    server.add_service("/notify_hello", Notify, lambda r: {})
    server.add_service("/update", Notify, lambda r: {})
    server.add_service("/get_data", GetData, lambda r: {"text": "hello", "count": 5})
    return server


@pytest.fixture
async def spec_wire(spec_server: Server) -> Any:
    async with serve(spec_server, "127.0.0.1", 0) as running:
        wire = await open_wire(running)
        yield wire
        await wire.ws.close()


async def test_spec_positional_and_named_params(spec_wire: Wire) -> None:
    w = spec_wire
    cases = [
        ('{"jsonrpc": "2.0", "method": "subtract", "params": [42, 23], "id": 1}', 19, 1),
        ('{"jsonrpc": "2.0", "method": "subtract", "params": [23, 42], "id": 2}', -19, 2),
        (
            '{"jsonrpc": "2.0", "method": "subtract", '
            '"params": {"subtrahend": 23, "minuend": 42}, "id": 3}',
            19,
            3,
        ),
        (
            '{"jsonrpc": "2.0", "method": "subtract", '
            '"params": {"minuend": 42, "subtrahend": 23}, "id": 4}',
            19,
            4,
        ),
    ]
    for text, difference, id in cases:
        assert await w.call(text) == {
            "jsonrpc": "2.0",
            "result": {"difference": difference},
            "id": id,
        }


async def test_spec_notifications_get_no_reply(spec_wire: Wire) -> None:
    await spec_wire.send('{"jsonrpc": "2.0", "method": "update", "params": [[1,2,3,4,5]]}')
    await spec_wire.send('{"jsonrpc": "2.0", "method": "foobar"}')
    reply = await spec_wire.call(request("subtract", [1, 1], id="after"))
    assert reply["id"] == "after"  # nothing came before it


async def test_spec_errors(spec_wire: Wire) -> None:
    w = spec_wire
    reply = await w.call('{"jsonrpc": "2.0", "method": "foobar", "id": "1"}')
    assert error(reply) == ("1", -32601, "SERVICE_NOT_FOUND")
    reply = await w.call('{"jsonrpc": "2.0", "method": "foobar, "params": "bar", "baz]')
    assert error(reply) == (None, -32700, "PARSE_ERROR")
    reply = await w.call('{"jsonrpc": "2.0", "method": 1, "params": "bar"}')
    assert error(reply) == (None, -32600, "INVALID_REQUEST")


async def test_spec_batches(spec_wire: Wire) -> None:
    w = spec_wire
    reply = await w.call(
        '[{"jsonrpc": "2.0", "method": "sum", "params": [1,2,4], "id": "1"},'
        '{"jsonrpc": "2.0", "method"]'
    )
    assert error(reply) == (None, -32700, "PARSE_ERROR")
    assert error(await w.call("[]")) == (None, -32600, "INVALID_REQUEST")
    (one,) = await w.call("[1]")
    assert error(one) == (None, -32600, "INVALID_REQUEST")
    three = await w.call("[1,2,3]")
    assert [error(r) for r in three] == [(None, -32600, "INVALID_REQUEST")] * 3


async def test_spec_mixed_batch(spec_wire: Wire) -> None:
    replies = await spec_wire.call(
        """[
        {"jsonrpc": "2.0", "method": "sum", "params": [1,2,4], "id": "1"},
        {"jsonrpc": "2.0", "method": "notify_hello", "params": [[7]]},
        {"jsonrpc": "2.0", "method": "subtract", "params": [42,23], "id": "2"},
        {"foo": "boo"},
        {"jsonrpc": "2.0", "method": "foo.get", "params": {"name": "myself"}, "id": "5"},
        {"jsonrpc": "2.0", "method": "get_data", "id": "9"}
    ]"""
    )
    assert replies[0] == {"jsonrpc": "2.0", "result": {"sum": 7}, "id": "1"}
    assert replies[1] == {"jsonrpc": "2.0", "result": {"difference": 19}, "id": "2"}
    assert error(replies[2]) == (None, -32600, "INVALID_REQUEST")
    assert error(replies[3]) == ("5", -32601, "SERVICE_NOT_FOUND")
    assert replies[4] == {"jsonrpc": "2.0", "result": {"text": "hello", "count": 5}, "id": "9"}
    assert len(replies) == 5


async def test_spec_all_notification_batch_gets_nothing(spec_wire: Wire) -> None:
    await spec_wire.send(
        '[{"jsonrpc": "2.0", "method": "notify_sum", "params": [1,2,4]},'
        '{"jsonrpc": "2.0", "method": "notify_hello", "params": [[7]]}]'
    )
    assert (await spec_wire.call(request("subtract", [2, 1], id="next")))["id"] == "next"


# --- types: ROS 2's own test services ------------------------------------------------------------


def mirror(srv: Any) -> Any:
    def handler(request: Any) -> Any:
        return srv.Response.model_validate_json(request.model_dump_json())

    return handler


EXTREMES = {
    "bool_value": True,
    "byte_value": 255,
    "char_value": 255,
    "float32_value": 3.4028234663852886e38,
    "float64_value": -1.7976931348623157e308,
    "int8_value": -128,
    "uint8_value": 255,
    "int16_value": -32768,
    "uint16_value": 65535,
    "int32_value": -(2**31),
    "uint32_value": 2**32 - 1,
    "int64_value": -(2**63),
    "uint64_value": 2**64 - 1,
    "string_value": "ü" * 20_000,
}


@pytest.fixture
async def ros_wire(ros_interfaces: InterfaceLoader, transport: Transport) -> Any:
    server = Server()
    for name in ("BasicTypes", "Arrays", "Empty"):
        srv = ros_interfaces.load_service(f"ros_test_interfaces/srv/{name}")
        server.add_service(name.lower(), srv, mirror(srv))
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        wire = await open_wire(running)
        yield wire
        await wire.ws.close()


async def test_basic_types_round_trip_at_their_extremes(ros_wire: Wire) -> None:
    reply = await ros_wire.call(request("basictypes", EXTREMES))
    assert reply == {"jsonrpc": "2.0", "id": 1, "result": EXTREMES}
    low = {
        **EXTREMES,
        "float32_value": -3.4028234663852886e38,
        "uint64_value": 0,
        "string_value": "",
    }
    assert (await ros_wire.call(request("basictypes", low)))["result"] == low


async def test_float32s_maximum_as_other_languages_write_it_is_a_float32(ros_wire: Wire) -> None:
    # Rust, Go and Java write the largest float32 as 3.4028235e38, C's %.9g as 3.40282347e+38:
    # both round to it. What rounds beyond it (from 2**128 - 2**103 on) is refused.
    for written in (3.4028235e38, 3.40282347e38, -3.4028235e38):
        reply = await ros_wire.call(request("basictypes", {"float32_value": written}))
        assert reply["result"]["float32_value"] == written
    for beyond in (3.4028235677973366e38, -3.4028235677973366e38, 3.5e38):
        reply = await ros_wire.call(request("basictypes", {"float32_value": beyond}, id=2))
        assert error(reply) == (2, -32602, "INVALID_PARAMS")
        assert [e["type"] for e in reply["error"]["data"]["errors"]] == ["float32_range"]


async def test_a_number_too_large_for_a_double_is_infinity_however_written(
    ros_wire: Wire,
) -> None:
    # One rule, as JavaScript's JSON.parse has: 1e400 and a 400-digit integer alike. Alone, a
    # call is read in one pass; in a batch, by the full parse: the same either way.
    digits = "1" + "0" * 400
    for literal, written in (
        (digits, "Infinity"),
        ("1e400", "Infinity"),
        ("-" + digits, "-Infinity"),
    ):
        params = f'{{"float64_value":{literal}}}'
        text = f'{{"jsonrpc":"2.0","id":4,"method":"basictypes","params":{params}}}'
        for message in (text, f"[{text}]"):
            await ros_wire.ws.send(message)
            reply = await ros_wire.recv()
            reply = reply[0] if isinstance(reply, list) else reply
            assert reply["result"]["float64_value"] == written, (literal, message[0])


async def test_arrays_round_trip(ros_wire: Wire) -> None:
    small = {k: v for k, v in EXTREMES.items() if k != "string_value"}
    params = {
        "bool_values": [True, False, True],
        "byte_values": [0, 1, 255],
        "float32_values": [1.125, 0.0, -3.4028234663852886e38],
        "int64_values": [-(2**63), 0, 2**63 - 1],
        "uint64_values": [0, 1, 2**64 - 1],
        "string_values": ["", "é" * 20_000, "z"],
        "basic_types_values": [small, small, small],
    }
    result = (await ros_wire.call(request("arrays", params)))["result"]
    for name, value in params.items():
        if name != "byte_values":
            assert result[name] == value, name
    assert result["byte_values"] == "AAH/"  # bytes travel as base64 text
    assert result["uint64_values_default"] == [0, 1, 2**64 - 1]
    assert result["string_values_default"] == ["", "max value", "min value"]


async def test_empty_round_trips(ros_wire: Wire) -> None:
    assert (await ros_wire.call(request("empty")))["result"] == {}
    assert (await ros_wire.call(request("empty", {})))["result"] == {}
    assert (await ros_wire.call(request("empty", [])))["result"] == {}


@pytest.mark.parametrize(
    ("method", "params", "paths"),
    [
        ("basictypes", {"uint64_value": 2**64}, ["uint64_value"]),
        (
            "basictypes",
            {"int8_value": -129, "float32_value": 3.5e38},
            ["float32_value", "int8_value"],
        ),
        ("basictypes", {"uint32_value": "1", "bool_value": 1}, ["bool_value", "uint32_value"]),
        ("basictypes", {"no_such_field": 1}, ["no_such_field"]),
        ("basictypes", {"float64_value": 1e400, "byte_value": -1}, ["byte_value"]),
        ("arrays", {"int8_values": [0, 0, 128]}, ["int8_values[2]"]),
        ("arrays", {"bool_values": [True]}, ["bool_values"]),
        (
            "arrays",
            {"basic_types_values": [{}, {"uint8_value": 256}, {}]},
            ["basic_types_values[1].uint8_value"],
        ),
        ("basictypes", [1, 2, 3], ["bool_value"]),
    ],
)
async def test_bad_values_name_their_fields(
    ros_wire: Wire, method: str, params: Any, paths: list[str]
) -> None:
    reply = await ros_wire.call(request(method, params, id=5))
    assert error(reply) == (5, -32602, "INVALID_PARAMS")
    assert sorted(e["path"] for e in reply["error"]["data"]["errors"]) == paths
    assert (await ros_wire.call(request("empty", id=6)))["result"] == {}


MOVE = build("uint32 from\nuint32 to\n---\nuint32 got\n", "Move")


async def test_a_renamed_field_goes_by_its_interface_name_only_on_the_wire(
    transport: Transport,
) -> None:
    # Python calls the field from_ (a keyword cannot be a name); JSON, the file's from. A peer
    # sending from_ names a field the type does not have, in one pass and in the full parse.
    server = Server()
    server.add_service("/move", MOVE, lambda request: {"got": request.from_})
    assert MOVE.Request(from_=3).from_ == 3  # Python code keeps its name
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        wire = await open_wire(running)
        assert (await wire.call(request("/move", {"from": 7})))["result"] == {"got": 7}
        for params in ({"from_": 7}, {"from": 1, "from_": 2}):
            for batch in (False, True):  # a batch is read by the full parse, not in one pass
                message = request("/move", params, id=3)
                reply = await wire.call([message] if batch else message)
                reply = reply[0] if batch else reply
                assert error(reply) == (3, -32602, "INVALID_PARAMS")
                assert reply["error"]["data"]["errors"] == [
                    {
                        "path": "from_",
                        "message": "Extra inputs are not permitted",
                        "type": "extra_forbidden",
                    }
                ]
        await wire.ws.close()


# --- handlers that fail, hang, refuse ------------------------------------------------------------


async def test_a_hanging_handler_meets_the_deadline(server: Server, transport: Transport) -> None:
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.call(request("hangs", {"_meta": {"timeout": scaled(0.05)}}, id=8))
        assert error(reply) == (8, -32001, "DEADLINE_EXCEEDED")
        assert reply["error"]["message"] == (
            "the deadline for /hangs passed before the handler finished"
        )
        assert hangs.entered.is_set() and hangs.cancelled.is_set()
        assert (await w.call(request("subtract", [3, 1], id=9)))["result"] == {"difference": 2}


async def test_a_raising_handler_is_internal_without_a_traceback(
    server: Server, caplog: pytest.LogCaptureFixture, transport: Transport
) -> None:
    def broken(request: Any) -> Any:
        raise RuntimeError("the password is hunter2")

    server.add_service("/broken", Echo, broken)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("broken", id=1))
        raw = await asyncio.wait_for(w.ws.recv(), scaled(5))
        assert json.loads(raw) == {
            "jsonrpc": "2.0",
            "id": 1,
            "error": {
                "code": -32603,
                "message": "handler for /broken raised an exception",
                "data": {"status": "INTERNAL"},
            },
        }
        assert "hunter2" not in str(raw) and "Traceback" not in str(raw)
        assert (await w.call(request("subtract", [3, 1], id=2)))["result"] == {"difference": 2}
    assert any("hunter2" in str(r.exc_info[1]) for r in caplog.records if r.exc_info)


async def test_a_cancellation_nobody_asked_for_is_still_answered(
    server: Server, transport: Transport
) -> None:
    # Awaiting a future that something else cancelled raises CancelledError in the handler
    # while its task is not being cancelled: the call must still get its one reply.
    async def awaits_a_cancelled_future(request: Any) -> Any:
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        future.cancel()
        await future

    server.add_service("/stray", Echo, awaits_a_cancelled_future)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.call(request("stray", {"_meta": {"timeout": scaled(30)}}, id="s"))
        assert error(reply) == ("s", -32603, "INTERNAL")
        batch = await w.call([request("stray", id="b1"), request("subtract", [3, 1], id="b2")])
        assert [r["id"] for r in batch] == ["b1", "b2"]
        assert error(batch[0]) == ("b1", -32603, "INTERNAL")
        assert batch[1]["result"] == {"difference": 2}
        assert (await w.call(request("subtract", [3, 1], id=2)))["result"] == {"difference": 2}


async def test_a_service_error_reaches_the_caller_as_it_was_raised(
    server: Server, transport: Transport
) -> None:
    async def refuses(request: Any) -> Any:
        raise ServiceError(4001, "the robot is e-stopped", {"since": "12:00", "ids": [1, 2]})

    server.add_service("/refuses", Echo, refuses)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert await w.call(request("refuses", id="r")) == {
            "jsonrpc": "2.0",
            "id": "r",
            "error": {
                "code": 4001,
                "message": "the robot is e-stopped",
                "data": {"since": "12:00", "ids": [1, 2]},
            },
        }


async def test_cancel_stops_the_handler_and_answers_cancelled(
    server: Server, transport: Transport
) -> None:
    entered = asyncio.Event()
    cancelled = asyncio.Event()

    async def hangs(request: Any) -> Any:
        entered.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            cancelled.set()
            raise

    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("hangs", id="c1"))
        await entered.wait()
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": "c1"}})
        reply = await w.recv_reply()
        assert error(reply) == ("c1", -32002, "CANCELLED")
        assert reply["error"]["message"] == "the caller cancelled the call"
        assert cancelled.is_set()
        # cancelling what is not running is ignored; as a request it is answered with null
        assert (await w.call(request("$/cancel", {"id": "c1"}, id=3)))["result"] is None
        assert (await w.call(request("subtract", [3, 1], id=2)))["result"] == {"difference": 2}


async def test_a_cancel_request_without_an_id_is_refused_and_a_notification_ignored(
    server: Server, transport: Transport
) -> None:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {}})  # no answer
        reply = await w.call(request("$/cancel", {"call": "c1"}, id=8))
        assert reply == {  # as docs/protocol.md shows it
            "jsonrpc": "2.0",
            "id": 8,
            "error": {
                "code": -32602,
                "message": 'invalid params: $/cancel needs the id of the call to cancel: {"id": 7}',
                "data": {
                    "status": "INVALID_PARAMS",
                    "errors": [{"path": "id", "message": "missing", "type": "missing"}],
                },
            },
        }
        assert (await w.call(request("subtract", [3, 1], id=2)))["result"] == {"difference": 2}


@pytest.mark.parametrize("method", ["$/nope", "rpc.nope", ""])
async def test_a_method_that_cannot_be_a_service_is_named_as_sent(
    server: Server, transport: Transport, method: str
) -> None:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.call(request(method, id=5))
        assert error(reply) == (5, -32601, "SERVICE_NOT_FOUND")
        assert reply["error"]["message"] == f'no method named "{method}"'


async def test_cancel_reaches_a_call_that_has_not_started_yet(transport: Transport) -> None:
    server = Server(max_in_flight=1)
    ran: list[bool] = []

    async def handler(request: Any) -> Any:
        ran.append(True)
        return {"text": "ran"}

    server.add_service("/once", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        # In one batch the call's task is created, then cancelled before its first step.
        replies = await w.call(
            [request("once", id=1), {"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 1}}]
        )
        assert [error(r) for r in replies] == [(1, -32002, "CANCELLED")]
        assert not ran
        # The cancelled call no longer counts against the limit of one.
        assert (await w.call(request("once", id=2)))["result"] == {"text": "ran"}


async def test_results_are_sent_in_text_frames(wire: Wire) -> None:
    # The server sends a result as the UTF-8 bytes pydantic wrote, flagged as text.
    await wire.ws.send(json.dumps(request("echo", {"text": "hé"}, id=1)))
    frame = await asyncio.wait_for(wire.ws.recv(), scaled(5))
    assert frame == '{"jsonrpc":"2.0","id":1,"result":{"text":"hé"}}'


def served(server: Server, socket: Any) -> ServedConnection:
    """A connection of ``server`` over a stand-in for the transport's connection."""
    return ServedConnection(
        socket,
        server.registry,
        max_in_flight=server.max_in_flight,
        executor=server.executor,
        logger=server.logger,
    )


def batch_of_two_calls_and_a_notification(conn: ServedConnection) -> list[Any]:
    """Hand the connection's session a batch and start its work as the reader would."""
    events = conn.session.receive(
        json.dumps(
            [
                request("echo", {"text": "a"}, id=1),
                request("echo", {"text": "b"}, id=2),
                {"jsonrpc": "2.0", "method": "echo", "params": {"text": "c"}},
            ]
        )
    )
    for work in events:
        conn.runner.start_in_task(work)
    return events


async def test_calls_cancelled_before_their_first_step_are_settled(server: Server) -> None:
    # The connection goes away between the creation of call tasks and their first step: their
    # coroutines never run, so the teardown itself must uncount them and forget the calls.
    class Socket:
        remote_address = ("127.0.0.1", 1)

    conn = served(server, Socket())
    first, second, _ = batch_of_two_calls_and_a_notification(conn)
    tasks = set(conn.counted)
    session = conn.session
    assert session.in_flight == 3 and len(tasks) == 3 and set(session.calls) == {1, 2}
    assert not any(call.started for call in session.calls.values())
    conn.cancel_all(None)
    await asyncio.wait(tasks)
    assert all(task.cancelled() for task in tasks) and {first.task, second.task} <= tasks
    assert not conn.counted and not session.calls


async def test_finished_calls_and_notifications_settle_themselves(server: Server) -> None:
    class Socket:
        remote_address = ("127.0.0.1", 1)

        async def send(self, message: str | bytes) -> None:
            sent.append(message)

    sent: list[str | bytes] = []
    conn = served(server, Socket())
    batch_of_two_calls_and_a_notification(conn)
    tasks = set(conn.counted)
    assert len(tasks) == 3
    await asyncio.wait(tasks)
    (batch,) = sent  # the last call of the batch to reply sends the batch's replies
    assert [reply["id"] for reply in json.loads(batch)] == [1, 2]
    assert conn.session.in_flight == 0 and not conn.counted and not conn.session.calls


async def test_sync_handlers_do_not_block_the_loop(server: Server, transport: Transport) -> None:
    release = threading.Event()
    entered = threading.Event()

    def blocks(request: Any) -> Any:
        entered.set()
        release.wait(scaled(10))
        return {"text": "released"}

    server.add_service("/blocks", Echo, blocks)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("blocks", id="slow"))
        assert await asyncio.to_thread(entered.wait, scaled(5))
        assert await w.call(request("echo", {"text": "fast"}, id="fast")) == {
            "jsonrpc": "2.0",
            "id": "fast",
            "result": {"text": "fast"},
        }
        release.set()
        assert (await w.recv_reply())["result"] == {"text": "released"}


async def test_a_handler_may_ask_for_its_context(server: Server, transport: Transport) -> None:
    seen: list[Context] = []

    async def handler(request: Any, response: Any, context: Context) -> Any:
        seen.append(context)
        response.text = f"{context.service} {context.request_id}"
        return response

    server.add_service("/ctx", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.call(request("ctx", {"_meta": {"timeout": scaled(30)}}, id=77))
        assert reply["result"] == {"text": "/ctx 77"}
        (context,) = seen
        assert context.peer[0] == ("memory" if transport.name == "memory" else "127.0.0.1")
        remaining = context.time_remaining()
        assert remaining is not None and 0 < remaining <= scaled(30)


async def test_a_notification_runs_its_handler_without_a_reply(
    server: Server, transport: Transport
) -> None:
    ran = asyncio.Event()

    async def handler(request: Any) -> Any:
        ran.set()
        raise RuntimeError("not reported to anyone but the log")

    server.add_service("/fire", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send({"jsonrpc": "2.0", "method": "fire", "params": {"text": "x"}})
        await ran.wait()
        assert (await w.call(request("subtract", [1, 1], id="n")))["id"] == "n"


async def test_a_notification_with_a_bad_meta_is_dropped_not_answered(
    server: Server,
    caplog: pytest.LogCaptureFixture,
    transport: Transport,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(serving, "DROP_LOG_INTERVAL", 1e9)  # the whole test is one interval
    caplog.set_level(logging.INFO, "srvwire.server")  # until the connection has ended too
    ran: list[Any] = []

    async def handler(request: Any) -> Any:
        ran.append(request)
        return {"text": request.text}

    server.add_service("/note", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.INFO, "srvwire.server"):
            await w.send('{"jsonrpc":"2.0","method":"note","params":{"_meta":5}}')
            await w.send('{"jsonrpc":"2.0","method":"note","params":{"_meta":{"timeout":-1}}}')
            await w.send('[{"jsonrpc":"2.0","method":"note","params":{"_meta":"x"}}]')
            # The first reply on the wire must be this call's: nothing answered the above.
            first = await w.call(request("subtract", [5, 3], id="after"))
        assert first == {"jsonrpc": "2.0", "id": "after", "result": {"difference": 2}}
        assert ran == []
    # The first drop says why; the burst's others are counted, and said when the connection ends.
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped ")]
    host = "memory" if transport.name == "memory" else "127.0.0.1"
    first, more = lines
    assert first.startswith(f"dropped a notification to /note from ('{host}', ")
    assert first.endswith("invalid _meta: must be an object, not a number")
    assert more.startswith("dropped 2 more notifications from (")  # said as the connection ended
    assert more.endswith(") since the last line about one")


async def test_a_flood_of_notifications_writes_two_lines_not_thousands(
    caplog: pytest.LogCaptureFixture, transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(serving, "DROP_LOG_INTERVAL", 1e9)  # the whole test is one interval
    server = Server(max_in_flight=1, grace_period=0)
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/hangs", id=1))  # takes the one slot
        await hangs.entered.wait()
        for _ in range(1_000):
            await w.send({"jsonrpc": "2.0", "method": "/hangs"})
        # A call after them, answered RESOURCE_EXHAUSTED, shows they were all read.
        assert error(await w.call(request("/hangs", id=2))) == (2, -32004, "RESOURCE_EXHAUSTED")
        await w.ws.close()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped ")]
    assert len(lines) == 2
    assert lines[0].endswith("too many calls in flight")
    assert lines[1].startswith("dropped 999 more notifications from ")


async def test_a_notification_without_a_deadline_gets_the_servers(transport: Transport) -> None:
    # Nobody waits for a notification, so only the server's own deadline ends one that hangs,
    # and gives its slot back.
    server = Server(max_in_flight=1, notification_timeout=scaled(0.05))
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    server.add_service("/echo", Echo, lambda request: {"text": request.text})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send({"jsonrpc": "2.0", "method": "/hangs"})
        await hangs.entered.wait()
        await hangs.cancelled.wait()  # ended by the server's deadline
        reply = await w.request("/echo", {"text": "the slot is free"}, id=1)
        assert reply["result"] == {"text": "the slot is free"}
        await w.ws.close()
    with pytest.raises(ValueError, match="notification_timeout must be a number of seconds > 0"):
        Server(notification_timeout=0)


async def test_an_id_in_flight_cannot_be_reused(server: Server, transport: Transport) -> None:
    release = asyncio.Event()

    async def waits(request: Any) -> Any:
        await release.wait()
        return {"text": "ok"}

    server.add_service("/waits", Echo, waits)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("waits", id=1))
        reply = await w.call(request("waits", id=1))
        assert error(reply) == (1, -32600, "INVALID_REQUEST")
        assert reply["error"]["message"] == (
            "Invalid Request: id 1 is already used by a call in flight on this connection"
        )
        release.set()
        assert (await w.recv_reply())["result"] == {"text": "ok"}


# --- limits --------------------------------------------------------------------------------------


async def test_a_flood_past_the_in_flight_limit_is_refused_and_the_connection_lives(
    transport: Transport,
) -> None:
    server = Server(max_in_flight=4)
    release = asyncio.Event()
    entered = 0
    all_in = asyncio.Event()

    async def waits(request: Any) -> Any:
        nonlocal entered
        entered += 1
        if entered == 4:
            all_in.set()
        await release.wait()
        return {"text": request.text}

    server.add_service("/waits", Echo, waits)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for i in range(10):
            await w.send(request("waits", {"text": str(i)}, id=i))
        refused = [await w.recv_reply() for _ in range(6)]
        assert sorted(r["id"] for r in refused) == [4, 5, 6, 7, 8, 9]
        for reply in refused:
            assert error(reply)[1:] == (-32004, "RESOURCE_EXHAUSTED")
            assert reply["error"]["data"]["limit"] == 4
        await all_in.wait()
        release.set()
        done = [await w.recv_reply() for _ in range(4)]
        assert sorted((r["id"], r["result"]["text"]) for r in done) == [
            (i, str(i)) for i in range(4)
        ]
        assert (await w.call(request("waits", {"text": "again"}, id=99)))["result"] == {
            "text": "again"
        }


async def test_a_thousand_concurrent_calls_on_one_connection(transport: Transport) -> None:
    server = Server(max_in_flight=1000)

    async def add(request: Any) -> Any:
        await asyncio.sleep(0)  # let the calls interleave
        return {"difference": request.minuend - request.subtrahend}

    server.add_service("/subtract", Subtract, add)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for i in range(1000):
            await w.send(request("subtract", [i, -i], id=i))
        replies = [await w.recv_reply() for _ in range(1000)]
        assert sorted((r["id"], r["result"]["difference"]) for r in replies) == [
            (i, 2 * i) for i in range(1000)
        ]


async def test_a_hundred_connections_at_once(running: RunningServer) -> None:
    async def one(i: int) -> Any:
        w = await open_wire(running)
        try:
            return await w.call(request("subtract", [i, 1], id=i))
        finally:
            await w.ws.close()

    replies = await asyncio.gather(*(one(i) for i in range(100)))
    assert [r["result"]["difference"] for r in replies] == [i - 1 for i in range(100)]


async def test_an_oversized_message_closes_only_that_connection(transport: Transport) -> None:
    server = Server(max_message_size=1024)
    server.add_service("/subtract", Subtract, subtract)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        big = await open_wire(running)
        other = await open_wire(running)
        await big.send(request("subtract", {"minuend": 1, "pad": "x" * 2000}))
        assert await closed_code(big) == 1009
        assert (await other.call(request("subtract", [5, 3])))["result"] == {"difference": 2}


def echo_request_of_size(size: int) -> tuple[str, str]:
    """An ``echo`` call that is exactly ``size`` bytes of UTF-8, and the text it echoes."""
    head = '{"jsonrpc":"2.0","id":1,"method":"echo","params":{"text":"'
    tail = '"}}'
    echoed = "x" * (size - len(head) - len(tail))
    message = head + echoed + tail
    assert len(message.encode()) == size
    return message, echoed


async def test_by_default_a_message_may_be_one_mebibyte_and_no_more(transport: Transport) -> None:
    server = Server()
    assert server.max_message_size == 2**20
    server.add_service("/echo", Echo, lambda r: {"text": r.text})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running, max_message_size=None)
        message, echoed = echo_request_of_size(2**20)
        assert (await w.call(message))["result"] == {"text": echoed}
        message, _ = echo_request_of_size(2**20 + 1)
        await w.send(message)
        assert await closed_code(w) == 1009


async def test_by_default_permessage_deflate_is_declined() -> None:
    async with serve(Server(), "127.0.0.1", 0) as running:
        async with ws_connect(running.url, compression="deflate") as ws:  # offers deflate
            assert ws.request is not None and ws.response is not None
            assert "permessage-deflate" in ws.request.headers["Sec-WebSocket-Extensions"]
            assert "Sec-WebSocket-Extensions" not in ws.response.headers
            assert ws.protocol.extensions == []
    async with serve(Server(compression="deflate"), "127.0.0.1", 0) as running:
        async with ws_connect(running.url, compression="deflate") as ws:  # the check can fail
            assert [e.name for e in ws.protocol.extensions] == ["permessage-deflate"]


async def first_ping(url: str) -> Frame:
    """Connect with websockets' sans-I/O client and return the first Ping frame received."""
    uri = parse_uri(url)
    protocol = ClientProtocol(uri)
    reader, writer = await asyncio.open_connection(uri.host, uri.port)
    try:
        protocol.send_request(protocol.connect())
        async with asyncio.timeout(scaled(5)):
            while True:
                for data in protocol.data_to_send():  # the handshake, then the pongs
                    writer.write(data)
                await writer.drain()
                for event in protocol.events_received():
                    if isinstance(event, Frame) and event.opcode is Opcode.PING:
                        return event
                data = await reader.read(2**16)
                assert data, "the server closed the connection without a ping"
                protocol.receive_data(data)
    finally:
        writer.close()
        await writer.wait_closed()


@pytest.mark.parametrize("transport", ["websockets", "picows"])
async def test_keepalive_pings_are_on_by_default(transport: str) -> None:
    default = Server()
    assert (default.ping_interval, default.ping_timeout) == (20.0, 20.0)
    # The interval reaches the socket: with a short one, a ping arrives on a quiet connection.
    async with serve(Server(ping_interval=0.01), "127.0.0.1", 0, transport=transport) as running:
        ping = await first_ping(running.url)
    assert ping.opcode is Opcode.PING


@real_websockets
async def test_binary_frames_are_read_as_utf8(running: RunningServer) -> None:
    async with ws_connect(running.url, compression=None) as ws:
        await ws.recv()  # $/services
        await ws.send(b'{"jsonrpc":"2.0","id":1,"method":"subtract","params":[2,1]}')
        assert json.loads(await ws.recv())["result"] == {"difference": 1}  # binary JSON is fine
        await ws.send(b"\xff\xfe{}")
        reply = json.loads(await ws.recv())
        assert error(reply) == (None, -32700, "PARSE_ERROR")
        assert reply["error"]["message"] == "Parse error: invalid UTF-8 at byte 0"


async def test_invalid_utf8_in_a_text_message_closes_the_connection(wire: Wire) -> None:
    await wire.ws.send(b'"\xff"')  # bytes go out as a text message, as they are
    assert await closed_code(wire) == 1007


@real_websockets
async def test_fragments_not_utf8_once_joined_close_that_connection_alone_with_1007(
    running: RunningServer,
) -> None:
    async with (
        ws_connect(running.url, compression=None) as bad,
        ws_connect(running.url, compression=None) as good,
        asyncio.timeout(scaled(5)),
    ):
        for ws in (bad, good):
            await ws.recv()  # $/services
        # Each fragment ends where valid text could go on ("\xc3" begins a character); the
        # joined message is not UTF-8.
        text = json.dumps(request("echo", {"text": "?"})).encode()
        cut = text.index(b"?")
        await bad.send([text[:cut] + b"\xc3", b"x" + text[cut + 1 :]], text=True)
        with pytest.raises(ConnectionClosed):
            await bad.recv()
        assert bad.close_code == 1007
        assert bad.close_reason == f"invalid continuation byte at position {cut}"
        await good.send(json.dumps(request("echo", {"text": "still here"})))
        assert json.loads(await good.recv())["result"] == {"text": "still here"}


async def test_bad_input_is_answered_and_the_connection_carries_on(wire: Wire) -> None:
    deep = "[" * 100_000 + "]" * 100_000
    cases: list[tuple[Any, tuple[Any, int, str]]] = [
        ("not json", (None, -32700, "PARSE_ERROR")),
        (deep, (None, -32700, "PARSE_ERROR")),
        ('{"a":' * 100_000 + "1" + "}" * 100_000, (None, -32700, "PARSE_ERROR")),
        ('{"jsonrpc":"2.0","id":[1],"method":"subtract"}', (None, -32600, "INVALID_REQUEST")),
        ('{"jsonrpc":"2.0","id":Infinity,"method":"subtract"}', (None, -32600, "INVALID_REQUEST")),
        ('{"jsonrpc":"2.0","id":1e400,"method":"subtract"}', (None, -32600, "INVALID_REQUEST")),
        ('{"jsonrpc":"2.0","id":NaN,"method":"subtract"}', (None, -32600, "INVALID_REQUEST")),
        (request("subtract", "ab", id=2), (2, -32600, "INVALID_REQUEST")),
        (request("subtract", {"minuend": "ab"}, id=3), (3, -32602, "INVALID_PARAMS")),
        (request("subtract", {"minuend": 1.5}, id=4), (4, -32602, "INVALID_PARAMS")),
        (request("subtract", {"minuend": True}, id=5), (5, -32602, "INVALID_PARAMS")),
        (request("subtract", {"minuend": 2**63}, id=6), (6, -32602, "INVALID_PARAMS")),
        (request("subtract", {"extra": 1}, id=7), (7, -32602, "INVALID_PARAMS")),
        (request("subtract", [1, 2, 3], id=8), (8, -32602, "INVALID_PARAMS")),
        (request("subtract", {"_meta": {"timeout": "x"}}, id=9), (9, -32602, "INVALID_PARAMS")),
        (request("subtract", {"_meta": {"timeout": 10**400}}, id=9), (9, -32602, "INVALID_PARAMS")),
        (request("/a//b", id=10), (10, -32601, "SERVICE_NOT_FOUND")),
        (request("$/whatever", id=11), (11, -32601, "SERVICE_NOT_FOUND")),
    ]
    for message, expected in cases:
        assert error(await wire.call(message)) == expected, message
    reply = await wire.call(request("subtract", {"minuend": 2**63, "subtrahend": "x"}, id=12))
    assert [(e["path"], e["type"]) for e in reply["error"]["data"]["errors"]] == [
        ("minuend", "less_than_equal"),
        ("subtrahend", "int_type"),
    ]
    # The handler itself fails to build a response that overflows int64: INTERNAL.
    overflow = await wire.call(request("subtract", [2**62, -(2**62)], id=13))
    assert error(overflow) == (13, -32603, "INTERNAL")
    assert (await wire.call(request("subtract", [9, 3])))["result"] == {"difference": 6}


async def test_a_lone_surrogate_in_a_request_is_a_parse_error_and_the_connection_lives(
    wire: Wire,
) -> None:
    # "\ud800" is a valid JSON escape, but no UTF-8 text can hold what it means, so the JSON
    # decoder refuses the whole message: PARSE_ERROR, with id null since no id could be read.
    await wire.send('{"jsonrpc":"2.0","id":1,"method":"echo","params":{"text":"a\\ud800"}}')
    reply = await wire.recv_reply()
    assert error(reply) == (None, -32700, "PARSE_ERROR")
    assert reply["error"]["message"].startswith("Parse error: ")
    await wire.send('{"jsonrpc":"2.0","id":2,"method":"echo","params":{"text":"\\ud83d\\ude00"}}')
    assert (await wire.recv_reply())["result"] == {"text": "\U0001f600"}  # a pair is fine


@pytest.mark.parametrize("shape", ["dict", "model"])
async def test_a_response_with_a_lone_surrogate_is_internal_and_the_reason_is_logged(
    server: Server, caplog: pytest.LogCaptureFixture, shape: str, transport: Transport
) -> None:
    # A str can hold a lone surrogate (os.fsdecode(b"\x80") gives "\udc80") and still
    # validate as a ROS string; it fails only when the response is written as JSON.
    async def unencodable(request: Any) -> Any:
        text = request.text + "\udc80"
        return {"text": text} if shape == "dict" else Echo.Response(text=text)

    server.add_service("/unencodable", Echo, unencodable)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.ERROR, "srvwire.server"):
            reply = await w.call(request("unencodable", {"text": "file"}, id=1))
        assert reply == {
            "jsonrpc": "2.0",
            "id": 1,
            "error": {
                "code": -32603,
                "message": "handler for /unencodable returned an invalid response",
                "data": {"status": "INTERNAL"},
            },
        }
        assert (await w.call(request("subtract", [3, 1], id=2)))["result"] == {"difference": 2}
    returned = "dict" if shape == "dict" else "Echo_Response"
    # At ERROR only: closing may also warn about the thread of /subtract, which can still be
    # winding down after its reply went out.
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == [
        f"handler for /unencodable returned {returned}, which is not a valid "
        "srvwire_tests/srv/Echo response: text: String should not contain the lone surrogate "
        "'\\udc80' (at index 4): it cannot be written as UTF-8"
    ]


async def test_a_failure_inside_srvwire_is_still_answered(
    server: Server,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
    transport: Transport,
) -> None:
    async def broken_run_handler(*args: Any, **kwargs: Any) -> bytes:
        raise RuntimeError("a bug in srvwire")

    def broken_write_result(*args: Any, **kwargs: Any) -> bytes:
        raise RuntimeError("a bug in srvwire")

    # Both ways the runner runs a handler: run_handler, and the usual handler's own steps.
    monkeypatch.setattr("srvwire.serving.run_handler", broken_run_handler)
    monkeypatch.setattr("srvwire.serving.write_result", broken_write_result)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.call(request("echo", {"text": "hi"}, id=7))
        assert error(reply) == (7, -32603, "INTERNAL")
        assert reply["error"]["message"] == "the server failed to answer /echo"
        batch = await w.call([request("echo", id=8), request("echo", id=9)])
        assert [error(r) for r in batch] == [(8, -32603, "INTERNAL"), (9, -32603, "INTERNAL")]
    assert any(r.exc_info and str(r.exc_info[1]) == "a bug in srvwire" for r in caplog.records)


async def test_the_usual_handler_is_answered_as_any_other_for_every_outcome(
    transport: Transport, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``async def f(request)`` runs on the runner's own steps, any other handler through
    run_handler: the same answer, and the same log, for whatever the handler does."""
    from srvwire.errors import InvalidParams

    async def outcome(request: Any) -> Any:
        text = request.text
        if text == "typed":
            return Echo.Response(text="ok")
        if text == "dict":
            return {"text": "from a dict"}
        if text == "none":
            return None
        if text == "application":
            raise ServiceError(4001, "battery too low", {"left": 3})
        if text == "rpc":
            raise InvalidParams("no such mode")
        if text == "raises":
            raise ValueError("a bug in the handler")
        if text == "cancelled under it":
            future = asyncio.get_running_loop().create_future()
            asyncio.get_running_loop().call_soon(future.cancel)
            return await future
        if text == "wrong type":
            return 42
        if text == "unwritable":
            return Echo.Response.model_construct(text=object())
        await asyncio.sleep(0)  # answers after waiting
        return Echo.Response(text="waited")

    async def usual(request: Any) -> Any:
        return await outcome(request)

    async def with_context(request: Any, context: Context) -> Any:
        return await outcome(request)

    texts = ["typed", "dict", "none", "application", "rpc", "raises", "cancelled under it"]
    texts += ["wrong type", "unwritable", "waits"]
    caplog.set_level(logging.ERROR, logger="srvwire")
    through_run_handler = []
    run_handler = serving.run_handler

    async def counting(*args: Any) -> bytes:
        through_run_handler.append(args[0].name)
        return await run_handler(*args)

    monkeypatch.setattr(serving, "run_handler", counting)
    transcripts = []
    for handler in (usual, with_context):
        server = Server()
        server.add_service("/outcome", Echo, handler)
        entry = server.registry.get("/outcome")
        assert entry is not None and entry.usual is (handler is usual)
        caplog.clear()
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            w = await open_wire(running)
            replies = [
                await w.call(request("outcome", {"text": text}, id=i))
                for i, text in enumerate(texts)
            ]
            await w.ws.close()
        transcripts.append((replies, [record.getMessage() for record in caplog.records]))
    assert transcripts[0] == transcripts[1]
    assert through_run_handler == ["/outcome"] * len(texts)  # the second handler's calls only
    replies, logged = transcripts[0]
    assert [reply.get("result") for reply in replies] == [
        {"text": "ok"}, {"text": "from a dict"}, *[None] * 7, {"text": "waited"},
    ]  # fmt: skip
    assert [reply["error"]["code"] for reply in replies[2:9]] == [
        -32603, 4001, -32602, -32603, -32603, -32603, -32603,
    ]  # fmt: skip
    assert replies[3]["error"]["data"] == {"left": 3}
    assert logged.count("handler for /outcome raised an exception (request id 5)") == 1
    assert logged.count("handler for /outcome raised an exception (request id 6)") == 1


# --- services and discovery ----------------------------------------------------------------------


async def test_services_are_announced_on_connect_and_on_change(
    server: Server, running: RunningServer
) -> None:
    w = await open_wire(running)
    # Each with the fingerprint of its type's full definition.
    echo, subtract, sum_ = (fingerprint(full_definition(t) or {}) for t in (Echo, Subtract, Sum))
    assert w.services == [
        {"name": "/echo", "type": "srvwire_tests/srv/Echo", "fingerprint": echo},
        {"name": "/subtract", "type": "srvwire_tests/srv/Subtract", "fingerprint": subtract},
    ]
    server.add_service("/robot1/sum", Sum, lambda r: {"sum": r.a + r.b + r.c})
    note = await w.recv()
    assert note == {
        "jsonrpc": "2.0",
        "method": "$/services",
        "params": {
            "services": [
                {"name": "/echo", "type": "srvwire_tests/srv/Echo", "fingerprint": echo},
                {"name": "/robot1/sum", "type": "srvwire_tests/srv/Sum", "fingerprint": sum_},
                {
                    "name": "/subtract",
                    "type": "srvwire_tests/srv/Subtract",
                    "fingerprint": subtract,
                },
            ]
        },
    }
    server.remove_service("echo")
    names = [s["name"] for s in (await w.recv())["params"]["services"]]
    assert names == ["/robot1/sum", "/subtract"]
    await asyncio.to_thread(server.add_service, "/from_a_thread", Sum, lambda r: {"sum": 1})
    names = [s["name"] for s in (await w.recv())["params"]["services"]]
    assert names == ["/from_a_thread", "/robot1/sum", "/subtract"]
    assert (await w.call(request("robot1/sum", [1, 2, 3])))["result"] == {"sum": 6}
    assert error(await w.call(request("echo")))[1] == -32601


async def test_services_change_on_the_loop_thread_whatever_thread_asks(
    server: Server, running: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    registry = server.registry
    changed_on: list[int] = []
    add, remove = registry.add, registry.remove

    def recording_add(*args: Any, **options: Any) -> Any:
        changed_on.append(threading.get_ident())
        return add(*args, **options)

    def recording_remove(*args: Any) -> Any:
        changed_on.append(threading.get_ident())
        return remove(*args)

    monkeypatch.setattr(registry, "add", recording_add)
    monkeypatch.setattr(registry, "remove", recording_remove)
    w = await open_wire(running)

    def from_a_thread() -> int:
        server.add_service("/threaded", Sum, lambda r: {"sum": 1})
        with pytest.raises(RegistrationError, match="already registered"):
            server.add_service("/threaded", Sum, lambda r: {"sum": 2})
        server.remove_service("/threaded")
        with pytest.raises(RegistrationError, match="no service named /threaded"):
            server.remove_service("/threaded")
        return threading.get_ident()

    worker = await asyncio.to_thread(from_a_thread)
    assert worker != threading.get_ident()
    assert changed_on == [threading.get_ident()] * 4
    assert "/threaded" in [s["name"] for s in (await w.recv())["params"]["services"]]
    assert "/threaded" not in [s["name"] for s in (await w.recv())["params"]["services"]]
    await w.ws.close()


def test_services_change_at_once_when_not_listening() -> None:
    server = Server()
    thread = threading.Thread(target=server.add_service, args=("/sum", Sum, lambda r: {}))
    thread.start()
    thread.join(scaled(5))
    assert "/sum" in server.registry


async def test_registration_errors_reach_the_caller_verbatim(server: Server) -> None:
    with pytest.raises(RegistrationError) as caught:
        server.add_service("/subtract", Subtract, subtract)
    assert str(caught.value) == (
        "a service named /subtract is already registered (srvwire_tests/srv/Subtract); "
        "remove it first"
    )
    with pytest.raises(RegistrationError) as caught:

        @server.service("/robot//x", Subtract)
        def handler(request: Any) -> Any: ...

    assert str(caught.value) == (
        "service name '/robot//x' contains '//'; a name is segments of letters, digits and '_', "
        "each starting with a letter, joined by '/'"
    )

    @server.service("/robot/x", Subtract)
    def decorated(request: Any) -> Any:
        return {"difference": 0}

    assert decorated(None) == {"difference": 0}
    assert "/robot/x" in server.registry


async def test_rpc_discover(wire: Wire) -> None:
    doc = (await wire.call(request("rpc.discover", id="d")))["result"]
    assert doc["openrpc"] == "1.3.2"
    assert doc["info"] == {"title": "srvwire", "version": srvwire.__version__}
    assert [m["name"] for m in doc["methods"]] == ["/echo", "/subtract"]
    method = doc["methods"][1]
    assert method["x-srvwire-type"] == "srvwire_tests/srv/Subtract"
    assert method["x-srvwire-srv"].startswith("# Subtract one integer")
    assert [(p["name"], p["schema"]["type"], p["required"]) for p in method["params"]] == [
        ("minuend", "integer", False),
        ("subtrahend", "integer", False),
    ]
    assert method["result"]["schema"]["properties"]["difference"]["type"] == "integer"
    assert method["x-srvwire-request-schema"]["title"] == "Subtract_Request"


# --- running and shutting down -------------------------------------------------------------------


async def test_serve_works_as_await_and_as_async_with(server: Server, transport: Transport) -> None:
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    scheme = "memory" if transport.name == "memory" else "ws"
    assert running.port > 0 and running.url == f"{scheme}://127.0.0.1:{running.port}"
    w = await open_wire(running)
    await running.close()
    await running.close()  # idempotent
    assert await closed_code(w) == 1001
    with pytest.raises(OSError):
        await open_wire(running)
    async with serve(server, "127.0.0.1", 0, transport=transport) as again:
        assert (await (await open_wire(again)).call(request("subtract", [1, 1])))["result"]


async def test_shutdown_lets_calls_finish_and_refuses_new_ones(
    server: Server, transport: Transport
) -> None:
    entered = asyncio.Event()
    release = asyncio.Event()

    async def slow(request: Any) -> Any:
        entered.set()
        await release.wait()
        return {"text": "finished"}

    server.add_service("/slow", Echo, slow)
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    w = await open_wire(running)
    await w.send(request("slow", id="old"))
    await entered.wait()
    closing = asyncio.create_task(running.close())
    await asyncio.sleep(0)  # one loop turn: the shutdown's first step refuses new calls at once
    assert running.closing
    reply = await w.call(request("subtract", [1, 1], id="new"))
    assert error(reply) == ("new", -32003, "UNAVAILABLE")
    assert reply["error"]["message"] == "the server is shutting down"
    release.set()
    assert await w.recv_reply() == {"jsonrpc": "2.0", "id": "old", "result": {"text": "finished"}}
    await closing
    assert await closed_code(w) == 1001


async def test_shutdown_cancels_calls_past_the_grace_period(transport: Transport) -> None:
    server = Server(grace_period=scaled(0.05))
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    w = await open_wire(running)
    await w.send(request("hangs", id="h"))
    await hangs.entered.wait()
    await running.close()
    reply = await w.recv_reply()
    assert error(reply) == ("h", -32003, "UNAVAILABLE")
    assert reply["error"]["message"] == "the server shut down before the call finished"
    assert hangs.cancelled.is_set()
    assert await closed_code(w) == 1001


async def test_a_client_leaving_cancels_its_calls(server: Server, transport: Transport) -> None:
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("hangs"))
        await hangs.entered.wait()
        await w.ws.close()
        async with asyncio.timeout(scaled(5)):
            await hangs.cancelled.wait()


SERVE_SCRIPT = """\
import asyncio, logging, sys
sys.path.insert(0, {tests!r})
from conftest import Subtract, subtract
from srvwire.server import Server
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
server = Server()
server.add_service("/subtract", Subtract, subtract)
url = ""
def ready(running):
    global url
    url = running.url
    print("ready", url, flush=True)
def stopping(running):  # handed the same server as ready
    print("stopping", running.url == url, flush=True)
{serve}
print("stopped", flush=True)
"""


Served = tuple[asyncio.subprocess.Process, asyncio.StreamReader, asyncio.StreamReader, str]
"""A script's process, its output and its errors, and the URL it serves on."""


@asynccontextmanager
async def serving_script(folder: Any, name: str, text: str) -> AsyncIterator[Served]:
    """Run ``text`` as the Python script ``folder/name``, which prints ``ready URL`` once it
    serves; yield the process, its output and errors, and that URL, all within 20 s; kill the
    process at the end if it still runs."""
    path = folder / name
    path.write_text(text)
    process = await asyncio.create_subprocess_exec(
        sys.executable, str(path), stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    try:
        assert process.stdout is not None and process.stderr is not None
        async with asyncio.timeout(scaled(20)):
            line = (await process.stdout.readline()).decode()
            assert line.startswith("ready ws://127.0.0.1:"), line
            yield process, process.stdout, process.stderr, line.split()[1]
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()


@pytest.mark.parametrize(
    ("serve_call", "signum"),
    [
        ("server.run('127.0.0.1', 0, ready=ready, stopping=stopping)", signal.SIGTERM),
        (
            "asyncio.run(server.serve_forever('127.0.0.1', 0, ready=ready, stopping=stopping))",
            signal.SIGINT,
        ),
    ],
    ids=["run-SIGTERM", "serve_forever-SIGINT"],
)
async def test_serving_until_a_signal_reports_the_bound_url(
    tmp_path: Any, serve_call: str, signum: signal.Signals
) -> None:
    text = SERVE_SCRIPT.format(tests=str(ROOT / "tests"), serve=serve_call)
    async with serving_script(tmp_path, "serve.py", text) as (process, out, err, url):
        w = await open_wire(url)
        assert (await w.call(request("subtract", [7, 2])))["result"] == {"difference": 5}
        process.send_signal(signum)
        assert await closed_code(w) == 1001
        assert await process.wait() == 0
        assert (await out.read()).decode() == "stopping True\nstopped\n"
        log = (await err.read()).decode()
        assert f"serving 1 service on {url}\n" in log
        assert "Traceback" not in log


async def test_serve_forever_stops_when_cancelled_and_restores_signal_handlers(
    server: Server, caplog: pytest.LogCaptureFixture, transport: Transport
) -> None:
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    bound: asyncio.Future[RunningServer] = asyncio.get_running_loop().create_future()
    caplog.set_level(logging.INFO, "srvwire.server")
    task = asyncio.create_task(
        server.serve_forever("127.0.0.1", 0, ready=bound.set_result, transport=transport)
    )
    running = await bound
    assert running.transport is transport
    assert f"serving 2 services on {running.url}" in caplog.messages
    scheme = "memory" if transport.name == "memory" else "ws"
    assert running.url == f"{scheme}://127.0.0.1:{running.port}" and running.port > 0
    w = await open_wire(running)
    assert (await w.call(request("subtract", [4, 1])))["result"] == {"difference": 3}
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert await closed_code(w) == 1001
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


# --- nothing a client sends breaks the server ----------------------------------------------------


@contextmanager
def server_in_a_thread(server: Server) -> Iterator[str]:
    """Run ``server`` on its own event loop in a thread, so a sync test can drive it."""
    loop = asyncio.new_event_loop()
    running = loop.run_until_complete(serve(server, "127.0.0.1", 0))
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    try:
        yield running.url
    finally:
        asyncio.run_coroutine_threadsafe(running.close(), loop).result(scaled(10))
        loop.call_soon_threadsafe(loop.stop)
        thread.join(scaled(10))
        loop.run_until_complete(loop.shutdown_default_executor())
        loop.close()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=10),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=5), children, max_size=4)
    ),
    max_leaves=12,
)
ids = st.none() | st.integers() | st.text(max_size=5) | st.floats(allow_nan=False) | json_values
methods = st.sampled_from(["subtract", "/subtract", "echo", "rpc.discover", "$/cancel", "nope"])
messages = st.fixed_dictionaries(
    {},
    optional={
        "jsonrpc": st.just("2.0") | json_values,
        "id": ids,
        "method": methods | st.text(max_size=8),
        "params": json_values,
    },
)
payloads = st.one_of(
    messages.map(json.dumps),
    st.lists(messages | json_values, max_size=4).map(json.dumps),
    json_values.map(json.dumps),
    st.text(max_size=40),
)


def is_reply(item: Any) -> bool:
    if not isinstance(item, dict) or item.get("jsonrpc") != "2.0" or "id" not in item:
        return False
    if not (item["id"] is None or type(item["id"]) in (str, int, float)):
        return False
    if set(item) == {"jsonrpc", "id", "result"}:
        return True
    error = item.get("error")
    return (
        set(item) == {"jsonrpc", "id", "error"}
        and isinstance(error, dict)
        and type(error.get("code")) is int
        and isinstance(error.get("message"), str)
    )


def all_notifications(payload: str) -> bool:
    """Whether the spec says ``payload`` gets no reply at all (every item a valid notification)."""
    try:
        value = json.loads(payload)
    except ValueError:
        return False
    items = value if isinstance(value, list) else [value]
    if not items:
        return False
    for item in items:
        if not isinstance(item, dict) or "id" in item or item.get("jsonrpc") != "2.0":
            return False
        if not isinstance(item.get("method"), str):
            return False
        if "params" in item and not isinstance(item["params"], dict | list):
            return False
    return True


def test_random_input_gets_valid_replies_and_the_server_keeps_serving() -> None:
    server = Server()
    server.add_service("/subtract", Subtract, subtract)
    server.add_service("/echo", Echo, lambda r: {"text": r.text})
    with server_in_a_thread(server) as url, sync_connect(url, compression=None) as ws:
        json.loads(ws.recv(timeout=scaled(5)))  # $/services
        count = 0

        @settings(
            max_examples=200,
            deadline=None,
            suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
        )
        @given(payloads)
        def check(payload: str) -> None:
            nonlocal count
            count += 1
            sentinel = f"sentinel-{count}"
            ws.send(payload)
            ws.send(json.dumps(request("subtract", [count, 0], id=sentinel)))
            replies: list[Any] = []
            seen_sentinel = False
            expect_reply = not all_notifications(payload)
            while not seen_sentinel or (expect_reply and not replies):
                message = json.loads(ws.recv(timeout=scaled(5)))
                if isinstance(message, dict) and message.get("id") == sentinel:
                    assert message["result"] == {"difference": count}
                    seen_sentinel = True
                else:
                    replies.append(message)
            if not expect_reply:
                assert replies == [], payload
                return
            assert len(replies) == 1, (payload, replies)
            (reply,) = replies
            if isinstance(reply, list):
                assert reply and all(is_reply(item) for item in reply), (payload, reply)
            else:
                assert is_reply(reply), (payload, reply)

        check()
        ws.send(json.dumps(request("subtract", [5, 2], id="end")))
        assert json.loads(ws.recv(timeout=scaled(5)))["result"] == {"difference": 3}


# --- bookkeeping that must not depend on when a task first runs, or on how often it is cancelled


def _imitate_eager_task_factory() -> Any:
    """Python 3.12's ``asyncio.eager_task_factory``, or an imitation of it on 3.11.

    The imitation builds a pure-Python task, drops the first step ``Task.__init__`` scheduled,
    and runs that step at once, inside ``create_task``, as an eager task does.
    """
    eager = getattr(asyncio, "eager_task_factory", None)
    if eager is not None:
        return eager
    py_task = getattr(asyncio.tasks, "_PyTask", None)
    # Every Python below 3.12 has the pure-Python task this imitation drives; should one ever
    # lack it, the test says so instead of passing without running.
    assert py_task is not None and hasattr(py_task, "_Task__step"), (
        "this Python has neither asyncio.eager_task_factory nor the pure-Python task needed "
        "to imitate it"
    )

    def factory(loop: asyncio.AbstractEventLoop, coro: Any, **kwargs: Any) -> Any:
        scheduled: list[asyncio.Handle] = []
        call_soon = loop.call_soon

        def record(callback: Any, *args: Any, context: Any = None) -> asyncio.Handle:
            handle = call_soon(callback, *args, context=context)
            scheduled.append(handle)
            return handle

        loop.call_soon = record  # type: ignore[method-assign,assignment]
        try:
            task = py_task(coro, loop=loop, **kwargs)
        finally:
            del loop.call_soon
        scheduled[0].cancel()  # the first step runs here instead
        current = asyncio.tasks._current_tasks  # type: ignore[attr-defined]
        outer = current.pop(loop, None)
        try:
            task._Task__step()
        finally:
            if outer is not None:
                current[loop] = outer
        return task

    return factory


async def test_calls_that_finish_inside_create_task_leak_neither_count_nor_id(
    server: Server,
) -> None:
    class Socket:
        remote_address = ("127.0.0.1", 1)

        async def send(self, message: str | bytes) -> None:
            sent.append(message)  # never suspends: the whole call runs in its first step

    sent: list[str | bytes] = []
    conn = served(server, Socket())
    loop = asyncio.get_running_loop()
    loop.set_task_factory(_imitate_eager_task_factory())
    try:
        for _ in range(3):  # the same ids each time: they are free again once answered
            for work in batch_of_two_calls_and_a_notification(conn):
                assert work.task.done()
            session = conn.session
            assert session.in_flight == 0 and not conn.counted and not session.calls
    finally:
        loop.set_task_factory(None)
    assert [[reply["id"] for reply in json.loads(batch)] for batch in sent] == [[1, 2]] * 3


async def test_a_call_cancelled_twice_has_its_task_cancelled_once(
    server: Server, monkeypatch: pytest.MonkeyPatch, transport: Transport
) -> None:
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    cancelling: list[int] = []

    def recording(send: Any) -> Any:
        async def recording_send(self: Any, text: str | bytes) -> None:
            if b'"error"' in (text if isinstance(text, bytes) else text.encode()):  # the reply
                task = asyncio.current_task()
                assert task is not None
                cancelling.append(task.cancelling())
            await send(self, text)

        return recording_send

    # What the server's connection sends its replies through, on each transport.
    for connection in (MemoryConnection, WebSocketsConnection, PicowsConnection):
        monkeypatch.setattr(connection, "send", recording(connection.send))
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("hangs", id=1))
        await hangs.entered.wait()
        cancel = {"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 1}}
        await w.send([cancel, cancel])  # a batch of notifications: no reply of its own
        assert error(await w.recv_reply()) == (1, -32002, "CANCELLED")
        assert cancelling == [0]  # the reply went out with no cancellation left pending
        await w.ws.close()


async def test_a_second_cancel_reason_neither_wins_nor_cancels_again(server: Server) -> None:
    from srvwire.errors import Cancelled, ServiceUnavailable

    class Socket:
        remote_address = ("127.0.0.1", 1)

    conn = served(server, Socket())
    (call,) = conn.session.receive(json.dumps(request("echo", id=1)))
    conn.runner.begin(call)
    call.task = asyncio.create_task(asyncio.Event().wait())
    call.started = True
    conn.runner.cancel(call, Cancelled("first"))
    conn.runner.cancel(call, ServiceUnavailable("second"))
    conn.runner.cancel(call, None)  # the connection went away too
    assert call.task.cancelling() == 1
    assert str(call.context._cancel_error) == str(Cancelled("first"))
    with pytest.raises(asyncio.CancelledError):
        await call.task


async def test_shutdown_answers_calls_with_a_null_id_too(transport: Transport) -> None:
    server = Server(grace_period=scaled(0.05))
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    w = await open_wire(running)
    await w.send(request("hangs", id=None))
    await hangs.entered.wait()
    await running.close()
    reply = await w.recv_reply()
    assert error(reply) == (None, -32003, "UNAVAILABLE")
    assert reply["error"]["message"] == "the server shut down before the call finished"
    assert hangs.cancelled.is_set()
    assert await closed_code(w) == 1001


# --- calls run inline on the connection's reader until they have to wait ---------------------


async def test_calls_that_do_not_wait_run_on_the_reader_without_a_task_of_their_own(
    server: Server,
    transport: Transport,
) -> None:
    # Each answer is built before the next message is read, on the task that reads: two calls
    # in a row see the same task, and no call leaves a task behind.
    tasks: list[asyncio.Task[Any] | None] = []

    async def which_task(request: Any) -> Any:
        tasks.append(asyncio.current_task())
        return {"text": request.text}

    server.add_service("/which_task", Echo, which_task)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for id in (1, 2, 3):
            reply = await w.request("/which_task", {"text": str(id)}, id=id)
            assert reply["result"] == {"text": str(id)}
        (conn,) = running._connections
        assert tasks[0] is not None and tasks[0] is tasks[1] is tasks[2]
        assert tasks[0] is conn.reader and not conn.counted and not conn.session.calls
        await w.ws.close()


async def test_a_call_that_waits_keeps_its_task_and_a_new_reader_takes_over(
    server: Server,
    transport: Transport,
) -> None:
    # A handler sees one task from its first line to its last, even though it started on the
    # reader; meanwhile the connection goes on reading and answering.
    seen: dict[str, asyncio.Task[Any] | None] = {}
    release = asyncio.Event()

    async def waits(request: Any) -> Any:
        seen["before"] = asyncio.current_task()
        await release.wait()
        seen["after"] = asyncio.current_task()
        return {"text": "done"}

    async def which_task(request: Any) -> Any:
        seen["other"] = asyncio.current_task()
        return {"text": request.text}

    server.add_service("/waits", Echo, waits)
    server.add_service("/which_task", Echo, which_task)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/waits", {"text": ""}, id="slow"))
        reply = await w.request("/which_task", {"text": "fast"}, id="fast")
        assert reply["result"] == {"text": "fast"}
        (conn,) = running._connections
        assert seen["before"] is not None and seen["before"] in conn.counted
        assert seen["other"] is conn.reader and seen["other"] is not seen["before"]
        release.set()
        assert (await w.recv_reply())["result"] == {"text": "done"}
        assert seen["after"] is seen["before"]
        assert not conn.counted and not conn.session.calls
        await w.ws.close()


async def test_a_call_has_a_context_made_only_when_something_needs_it(
    server: Server, transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A handler that takes no context and answers, at once or after waiting, costs no Context;
    # one that asks gets its own, with its id and deadline; a cancellation or a passed deadline
    # makes one to record its reason, and is answered as always.
    made: list[Context] = []

    class Counted(Context):
        __slots__ = ()

        def __init__(self, **fields: Any) -> None:
            super().__init__(**fields)
            made.append(self)

    monkeypatch.setattr(serving, "Context", Counted)
    release = asyncio.Event()
    hangs = Hang()

    async def waits(request: Any) -> Any:
        await release.wait()
        return {"text": "waited"}

    async def asks(request: Any, context: Context) -> Any:
        return {"text": f"{context.request_id} {context.time_remaining() is not None}"}

    server.add_service("/waits", Echo, waits)
    server.add_service("/asks", Echo, asks)
    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("/echo", {"text": "a"}, id=1))["result"] == {"text": "a"}
        await w.send(request("/waits", {"_meta": {"timeout": 30}}, id=2))
        assert (await w.request("/echo", {"text": "b"}, id=3))["result"] == {"text": "b"}
        release.set()
        assert (await w.recv_reply())["result"] == {"text": "waited"}
        assert made == []
        reply = await w.request("/asks", {"_meta": {"timeout": 30}}, id="x")
        assert reply["result"] == {"text": "x True"}
        assert [context.request_id for context in made] == ["x"]
        assert error(await w.request("/echo", {"_meta": {"timeout": 0}}, id=4)) == (
            4,
            -32001,
            "DEADLINE_EXCEEDED",
        )
        assert [context.request_id for context in made] == ["x", 4]
        await w.send(request("/hangs", {}, id=5))
        await hangs.entered.wait()
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 5}})
        assert error(await w.recv_reply()) == (5, -32002, "CANCELLED")
        assert [context.request_id for context in made] == ["x", 4, 5]
        assert made[2].cancelled
        await w.ws.close()


async def test_each_call_runs_in_a_context_of_its_own(server: Server, transport: Transport) -> None:
    # What a handler sets in a context variable is not seen by the next call on the same
    # connection, as if each call had a task of its own; it is seen by the rest of its own call.
    import contextvars

    tag: contextvars.ContextVar[str] = contextvars.ContextVar("tag", default="unset")
    seen: list[str] = []

    async def tags(request: Any) -> Any:
        seen.append(tag.get())
        tag.set(request.text)
        await asyncio.sleep(0)  # wait once, so the rest runs in the call's own task
        seen.append(tag.get())
        return {"text": request.text}

    async def tags_without_waiting(request: Any) -> Any:
        seen.append(tag.get())
        tag.set(request.text)
        return {"text": request.text}

    server.add_service("/tags", Echo, tags)
    server.add_service("/tags_now", Echo, tags_without_waiting)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.request("/tags_now", {"text": "a"}, id=1)
        await w.request("/tags_now", {"text": "b"}, id=2)
        await w.request("/tags", {"text": "c"}, id=3)
        await w.request("/tags_now", {"text": "d"}, id=4)
        await w.ws.close()
    assert seen == ["unset", "unset", "unset", "c", "unset"]


async def test_a_timeout_a_handler_enters_before_waiting_cancels_only_that_handler(
    server: Server,
    transport: Transport,
) -> None:
    # asyncio.timeout() binds to the current task when it is entered, which for a call that
    # has not waited yet is the reader's: that task must then stay the call's.
    async def times_out(request: Any) -> Any:
        try:
            async with asyncio.timeout(0.01):
                await asyncio.Event().wait()
        except TimeoutError:
            return {"text": "timed out"}
        return {"text": "never"}

    server.add_service("/times_out", Echo, times_out)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("/times_out", {"text": ""}, id=1))["result"] == {
            "text": "timed out"
        }
        assert (await w.request("/echo", {"text": "still here"}, id=2))["result"] == {
            "text": "still here"
        }
        await w.ws.close()


async def test_messages_start_in_the_order_they_arrive(
    server: Server, transport: Transport
) -> None:
    # A notification followed by a call in the same burst: the notification's handler runs
    # first, as the wscat guide's "stop, then status" shows.
    events: list[str] = []

    async def record(request: Any) -> Any:
        events.append(request.text)
        return {"text": ",".join(events)}

    server.add_service("/record", Echo, record)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send({"jsonrpc": "2.0", "method": "/record", "params": {"text": "note"}})
        await w.send(request("/record", {"text": "call"}, id=1))
        assert (await w.recv_reply())["result"] == {"text": "note,call"}
        await w.ws.close()


async def test_only_a_handler_that_waits_is_bounded_by_a_deadline_timer(
    server: Server, monkeypatch: pytest.MonkeyPatch, transport: Transport
) -> None:
    # A handler that answers without waiting cannot be interrupted: its deadline needs no timer.
    # One that waits gets one, disarmed once it has answered.
    armed = record_armed_timers(monkeypatch)

    async def waits(request: Any) -> Any:
        await asyncio.sleep(0)
        return {"text": request.text}

    server.add_service("/waits", Echo, waits)
    meta = {"_meta": {"timeout": 30}}
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("/echo", {"text": "a", **meta}))["result"] == {"text": "a"}
        assert armed == []
        assert (await w.request("/waits", {"text": "b", **meta}))["result"] == {"text": "b"}
        (timer,) = armed
        assert timer.cancelled()
        await w.ws.close()


# --- deadlines: a cancellation with a reason, armed only for a call that waits -----------------


def record_armed_timers(monkeypatch: pytest.MonkeyPatch) -> list[asyncio.TimerHandle]:
    """Record every deadline timer a call runner arms."""
    armed: list[asyncio.TimerHandle] = []
    arm = CallRunner.arm

    def recording_arm(self: CallRunner, work: Any) -> asyncio.TimerHandle | None:
        timer = arm(self, work)
        if timer is not None:
            armed.append(timer)
        return timer

    monkeypatch.setattr(CallRunner, "arm", recording_arm)
    return armed


def deadline(seconds: float) -> dict[str, Any]:
    return {"_meta": {"timeout": scaled(seconds)}}


async def test_a_deadline_cancels_the_handler_and_marks_its_context(
    server: Server, transport: Transport
) -> None:
    hangs = Hang()
    contexts: list[Context] = []

    async def handler(request: Any, context: Context) -> Any:
        contexts.append(context)
        return await hangs(request)

    server.add_service("/hangs", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/hangs", deadline(0.05), id=1)
        assert error(reply) == (1, -32001, "DEADLINE_EXCEEDED")
        assert reply["error"]["message"] == (
            "the deadline for /hangs passed before the handler finished"
        )
        assert hangs.cancelled.is_set()
        (context,) = contexts
        assert context.cancelled and context.time_remaining() == 0.0
        assert (await w.request("/echo", {"text": "after"}, id=2))["result"] == {"text": "after"}
        await w.ws.close()


class StartingFirst(HandlerThreads):
    """Handler threads whose ``submit`` returns once the handler has set ``started``: the
    event loop, held meanwhile, cannot pass a call's deadline before its handler runs,
    however long a loaded machine takes to schedule the thread (a call whose deadline passes
    while it waits for its thread never runs its handler)."""

    def __init__(self, started: threading.Event) -> None:
        super().__init__()
        self.started = started

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Future[T]:
        future = super().submit(fn, *args, **kwargs)
        self.started.wait(scaled(10))
        return future


async def test_a_sync_handler_past_its_deadline_sees_cancelled(transport: Transport) -> None:
    started = threading.Event()
    release = threading.Event()
    observed = threading.Event()

    def handler(request: Any, context: Context) -> Any:
        started.set()
        release.wait(scaled(10))
        if context.cancelled:
            observed.set()
        return {"text": "late"}

    server = Server(grace_period=scaled(2), executor=StartingFirst(started))
    server.add_service("/blocks", Echo, handler)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/blocks", deadline(0.05), id=1)
        assert error(reply) == (1, -32001, "DEADLINE_EXCEEDED")
        release.set()
        assert await asyncio.to_thread(observed.wait, scaled(5))
        await w.ws.close()


async def test_a_handler_that_swallows_its_deadline_still_answers_deadline_exceeded(
    server: Server,
    transport: Transport,
) -> None:
    async def swallows(request: Any) -> Any:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            pass
        return {"text": "swallowed"}

    server.add_service("/swallows", Echo, swallows)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/swallows", deadline(0.05), id=1)
        assert error(reply) == (1, -32001, "DEADLINE_EXCEEDED")
        assert (await w.request("/echo", {"text": "after"}, id=2))["result"] == {"text": "after"}
        await w.ws.close()


async def test_the_first_reason_wins_over_a_deadline_that_passes_later(
    server: Server, transport: Transport
) -> None:
    # Cancelled by the caller, the handler takes a while to clean up, and its deadline passes
    # meanwhile: the answer is CANCELLED, sent at once, and the cleanup is not interrupted a
    # second time.
    started = asyncio.Event()
    cleaned_up = asyncio.Event()
    interrupted: list[bool] = []

    async def slow_cleanup(request: Any) -> Any:
        started.set()
        try:
            await asyncio.Event().wait()
        finally:
            try:
                await asyncio.sleep(scaled(0.2))  # longer than the deadline below
            except asyncio.CancelledError:
                interrupted.append(True)
                raise
            finally:
                cleaned_up.set()

    server.add_service("/slow_cleanup", Echo, slow_cleanup)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/slow_cleanup", deadline(0.1), id=1))
        await started.wait()
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 1}})
        assert error(await w.recv_reply()) == (1, -32002, "CANCELLED")
        await cleaned_up.wait()
        assert interrupted == []
        assert (await w.request("/echo", {"text": "after"}, id=2))["result"] == {"text": "after"}
        await w.ws.close()


def connection_of(running: RunningServer) -> ServedConnection:
    (served,) = running._connections
    return served


class Stubborn:
    """A handler that swallows its cancellation, then goes on until ``release`` is set (a long
    cleanup), and then returns, or raises ``raises``. ``entered``, ``swallowed`` and ``ended``
    say how far it got, so that a test awaits them instead of sleeping."""

    def __init__(self, raises: BaseException | None = None) -> None:
        self.raises = raises
        self.entered = asyncio.Event()
        self.swallowed = asyncio.Event()
        self.release = asyncio.Event()
        self.ended = asyncio.Event()

    async def __call__(self, request: Any) -> Any:
        self.entered.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            self.swallowed.set()
        try:
            await self.release.wait()
        finally:
            self.ended.set()
        if self.raises is not None:
            raise self.raises
        return {"text": "too late"}


async def finish_stubborn(w: Wire, stubborn: Stubborn, served: ServedConnection) -> None:
    """Let ``stubborn`` end, then check that the connection's next message is the reply to the
    next call (the stubborn call's late result was not sent) and that nothing is left."""
    await stubborn.swallowed.wait()
    assert not stubborn.ended.is_set()
    stubborn.release.set()
    await stubborn.ended.wait()
    assert await w.request("/echo", {"text": "next"}, id="next") == {
        "jsonrpc": "2.0",
        "id": "next",
        "result": {"text": "next"},
    }
    assert served.session.in_flight == 0 and not served.counted and not served.session.calls


async def test_a_handler_that_ignores_its_cancellation_is_answered_when_its_deadline_passes(
    server: Server, transport: Transport
) -> None:
    stubborn = Stubborn()
    server.add_service("/stubborn", Echo, stubborn)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/stubborn", deadline(0.05), id=1)
        assert error(reply) == (1, -32001, "DEADLINE_EXCEEDED")
        assert not stubborn.ended.is_set()  # answered while its handler still runs
        assert (await w.request("/echo", {"text": "meanwhile"}, id=2))["result"] == {
            "text": "meanwhile"
        }
        await finish_stubborn(w, stubborn, connection_of(running))
        await w.ws.close()


async def test_a_handler_that_ignores_its_cancellation_is_answered_when_cancelled(
    server: Server, transport: Transport
) -> None:
    stubborn = Stubborn()
    server.add_service("/stubborn", Echo, stubborn)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/stubborn", deadline(60), id="c"))
        await stubborn.entered.wait()
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": "c"}})
        assert error(await w.recv_reply()) == ("c", -32002, "CANCELLED")
        assert not stubborn.ended.is_set()
        await finish_stubborn(w, stubborn, connection_of(running))
        await w.ws.close()


async def test_a_batch_with_a_handler_that_ignores_its_deadline_is_answered_when_it_passes(
    server: Server, transport: Transport
) -> None:
    stubborn = Stubborn()
    server.add_service("/stubborn", Echo, stubborn)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        replies = await w.call(
            [request("/stubborn", deadline(0.05), id=1), request("/echo", {"text": "b"}, id=2)]
        )
        assert [r["id"] for r in replies] == [1, 2]
        assert error(replies[0]) == (1, -32001, "DEADLINE_EXCEEDED")
        assert replies[1]["result"] == {"text": "b"}
        assert not stubborn.ended.is_set()
        await finish_stubborn(w, stubborn, connection_of(running))
        await w.ws.close()


async def test_a_call_answered_while_its_handler_runs_on_counts_in_flight_until_it_ends(
    transport: Transport,
) -> None:
    server = Server(max_in_flight=1, grace_period=scaled(2))
    stubborn = Stubborn()
    server.add_service("/stubborn", Echo, stubborn)

    async def echo(request: Any) -> Any:
        return {"text": request.text}

    server.add_service("/echo", Echo, echo)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert error(await w.request("/stubborn", deadline(0.05), id=1)) == (
            1,
            -32001,
            "DEADLINE_EXCEEDED",
        )
        # Its task still runs, and still holds what it holds: the limit of one is reached.
        assert error(await w.request("/echo", {"text": "busy"}, id=2)) == (
            2,
            -32004,
            "RESOURCE_EXHAUSTED",
        )
        await finish_stubborn(w, stubborn, connection_of(running))
        await w.ws.close()


async def test_a_late_failure_of_a_handler_already_answered_is_logged_once(
    server: Server, transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    stubborn = Stubborn(raises=RuntimeError("failed in its cleanup"))
    server.add_service("/stubborn", Echo, stubborn)
    server.access_log = logging.getLogger("srvwire.access")
    caplog.set_level(logging.INFO, logger="srvwire.access")
    loop = asyncio.get_running_loop()
    reported: list[dict[str, Any]] = []
    previous = loop.get_exception_handler()
    loop.set_exception_handler(lambda loop, context: reported.append(context))
    try:
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            w = await open_wire(running)
            reply = await w.request("/stubborn", deadline(0.05), id=1)
            assert error(reply) == (1, -32001, "DEADLINE_EXCEEDED")
            await finish_stubborn(w, stubborn, connection_of(running))
            await w.ws.close()
    finally:
        loop.set_exception_handler(previous)
    failures = [
        r for r in caplog.records if r.exc_info and "failed in its cleanup" in str(r.exc_info[1])
    ]
    assert len(failures) == 1
    assert failures[0].getMessage() == "handler for /stubborn raised an exception (request id 1)"
    assert reported == []
    # Its access line, written when its task ended, has the outcome answered, not the failure.
    lines = [r.getMessage() for r in caplog.records if r.name == "srvwire.access"]
    (line,) = [line for line in lines if " /stubborn " in line]
    assert " /stubborn DEADLINE_EXCEEDED " in line, line


async def test_shutdown_answers_a_call_whose_handler_ignores_its_cancellation(
    transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("WARNING", logger="srvwire.server")
    server = Server(grace_period=scaled(0.1))
    stubborn = Stubborn()
    server.add_service("/stubborn", Echo, stubborn)
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    w = await open_wire(running)
    await w.send(request("/stubborn", id="s"))
    await stubborn.entered.wait()
    served = connection_of(running)
    closing = asyncio.create_task(running.close())
    reply = await w.recv_reply()
    assert error(reply) == ("s", -32003, "UNAVAILABLE")
    assert reply["error"]["message"] == "the server shut down before the call finished"
    await stubborn.swallowed.wait()
    (handler_task,) = served.runner.running_on  # its task, cancelled and going on
    await closing  # waits a moment for the handler, which goes on, then closes
    assert await closed_code(w) == 1001
    assert (
        "leaving 1 handler running that did not end when cancelled (its call was answered): "
        "/stubborn; it is cancelled again as the connections close" in caplog.text
    )
    await asyncio.wait([handler_task])  # cancelled again with its connection: its wait ended
    assert stubborn.ended.is_set()
    assert served.session.in_flight == 0 and not served.counted and not served.session.calls
    assert not served.runner.running_on


def cancel_own_task(times: int = 1) -> None:
    """Cancel the running task, as a handler that means to stop itself might."""
    task = asyncio.current_task()
    assert task is not None
    for _ in range(times):
        task.cancel()


async def test_a_handler_that_cancels_its_task_and_returns_does_not_stop_the_reading(
    server: Server, caplog: pytest.LogCaptureFixture, transport: Transport
) -> None:
    # Running inline, the handler's task is the reader's: the cancellation it asks for is taken
    # back, its answer is sent, and the connection reads on.
    async def cancels_itself(request: Any) -> Any:
        cancel_own_task()
        return {"text": "returned"}

    server.add_service("/cancels_itself", Echo, cancels_itself)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.WARNING, logger="srvwire.server"):
            reply = await w.request("/cancels_itself", {"text": ""}, id=1)
        assert reply["result"] == {"text": "returned"}
        assert "cancelled its own task without waiting" in caplog.text
        for id in (2, 3):
            assert (await w.request("/echo", {"text": str(id)}, id=id))["result"] == {
                "text": str(id)
            }
        (conn,) = running._connections
        reader = conn.reader
        assert reader is not None and reader.cancelling() == 0
        await w.ws.close()


async def test_a_handler_that_cancels_its_task_and_waits_is_answered_internal(
    server: Server,
    transport: Transport,
) -> None:
    # Nothing in srvwire asked for that cancellation: the call still gets its one reply.
    async def cancels_then_waits(request: Any) -> Any:
        cancel_own_task()
        await asyncio.sleep(0)
        return {"text": "never"}

    server.add_service("/cancels_then_waits", Echo, cancels_then_waits)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/cancels_then_waits", {"text": ""}, id=1)
        assert error(reply) == (1, -32603, "INTERNAL")
        assert "cancelled by its own code" in reply["error"]["message"]
        assert (await w.request("/echo", {"text": "next"}, id=2))["result"] == {"text": "next"}
        await w.ws.close()


async def test_a_handler_that_cancels_its_task_and_raises_is_answered_internal(
    server: Server,
    transport: Transport,
) -> None:
    # The handler asks for its own cancellation and raises CancelledError at once, before the
    # request was delivered: alone or in a batch, the call is answered and the connection lives.
    async def cancels_and_raises(request: Any) -> Any:
        cancel_own_task()
        raise asyncio.CancelledError

    server.add_service("/cancels_and_raises", Echo, cancels_and_raises)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/cancels_and_raises", {"text": ""}, id=1)
        assert error(reply) == (1, -32603, "INTERNAL")
        assert (await w.request("/echo", {"text": "next"}, id=2))["result"] == {"text": "next"}
        batch = [
            request("/cancels_and_raises", {"text": ""}, id=3),
            request("/echo", {"text": "b"}, id=4),
        ]
        replies = await w.call(batch)
        assert [reply["id"] for reply in replies] == [3, 4]
        assert error(replies[0]) == (3, -32603, "INTERNAL")
        assert replies[1]["result"] == {"text": "b"}
        assert (await w.request("/echo", {"text": "last"}, id=5))["result"] == {"text": "last"}
        await w.ws.close()


async def test_a_notification_handler_that_cancels_its_task_does_not_stop_the_reading(
    server: Server,
    transport: Transport,
) -> None:
    async def cancels_and_raises(request: Any) -> Any:
        cancel_own_task(times=2)  # both requests are taken back
        raise asyncio.CancelledError

    server.add_service("/cancels_and_raises", Echo, cancels_and_raises)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send({"jsonrpc": "2.0", "method": "/cancels_and_raises", "params": {"text": ""}})
        assert (await w.request("/echo", {"text": "next"}, id=1))["result"] == {"text": "next"}
        (conn,) = running._connections
        reader = conn.reader
        assert reader is not None and reader.cancelling() == 0
        await w.ws.close()


async def test_readers_stay_readers_under_an_eager_task_factory(
    server: Server, transport: Transport
) -> None:
    # A waiting call hands the reading to a new task; under an eager task factory that task
    # must not run (and hand over again) inside the hand-over, nesting readers in one stack.
    release = asyncio.Event()

    async def waits(request: Any) -> Any:
        await release.wait()
        return {"text": request.text}

    server.add_service("/waits", Echo, waits)
    loop = asyncio.get_running_loop()
    loop.set_task_factory(_imitate_eager_task_factory())
    try:
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            w = await open_wire(running)
            count = 50
            for id in range(count):
                await w.send(request("/waits", {"text": str(id)}, id=id))
            reply = await w.request("/echo", {"text": "fast"}, id="fast")
            assert reply["result"] == {"text": "fast"}
            (conn,) = running._connections
            assert conn.reader is not None and conn.reader not in conn.counted
            assert len(conn.counted) == count
            release.set()
            replies = [await w.recv_reply() for _ in range(count)]
            assert sorted(reply["id"] for reply in replies) == list(range(count))
            await w.ws.close()
    finally:
        loop.set_task_factory(None)


async def test_a_deadline_that_passes_while_the_reply_is_being_sent_lets_it_go_out(
    server: Server, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The reply is built in time, but the client does not read, so its send waits; the
    # deadline passing then must not cancel the send of a reply that is already written.
    expired = asyncio.Event()
    expire = CallRunner.expire

    def recording_expire(self: CallRunner, work: Any) -> None:
        expire(self, work)
        expired.set()

    async def big(request: Any) -> Any:
        await asyncio.sleep(0)  # wait once, so the deadline is armed
        return {"text": "x" * 10_000}

    monkeypatch.setattr(CallRunner, "expire", recording_expire)
    server.max_queued_bytes = 1_000
    server.add_service("/big", Echo, big)
    transport = MemoryTransport()
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/big", deadline(0.05), id=1))
        await expired.wait()  # the deadline passed while the reply waited for the reader
        reply = await w.recv_reply()
        assert reply["result"] == {"text": "x" * 10_000}
        await w.ws.close()


async def test_replies_a_client_does_not_read_count_against_its_limit() -> None:
    # A client that writes calls and never reads: each reply waits in its send, and counts in
    # flight until it goes out; past the limit the reader answers the next call itself, its
    # own send waits too, and the client's writes are pushed back instead of piling up tasks.
    server = Server(max_in_flight=4, max_queued_bytes=10_000, grace_period=0)

    async def big(request: Any) -> Any:
        return {"text": "x" * 5_000}

    server.add_service("/big", Echo, big)
    transport = MemoryTransport(high_water=10_000)  # what the client sends, unread, holds it
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await transport.connect(running.url, Options(max_message_size=None))

        async def write() -> None:
            for id in range(1_000):
                await client.send(json.dumps(request("/big", id=id)))

        writing = asyncio.create_task(write())
        for _ in range(2_000):  # let both sides run as far as they can
            await asyncio.sleep(0)
        (conn,) = running._connections
        assert not writing.done()  # the client is held back
        assert conn.session.in_flight <= server.max_in_flight
        assert len(conn.counted) <= server.max_in_flight
        writing.cancel()
        await client.close()


class Logged(logging.Handler):
    """Sets ``seen`` once a record whose message contains ``text`` is logged."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text
        self.seen = asyncio.Event()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.records.append(record)
            self.seen.set()


def set_receive_buffer(wire: Wire, size: int) -> None:
    """Fix the receive buffer of ``wire``'s socket at ``size`` bytes (the kernel doubles it).

    Loopback grows a receive buffer while its reader keeps up (up to ``tcp_rmem``'s maximum, 32
    MiB on some machines), and a client that reads a few replies into its own queue first can
    make it grow past what a test sends: then a client that stops reading holds nothing up. The
    memory transport has no socket: its buffers are its own."""
    ws = getattr(wire.ws, "_ws", None)
    if ws is None:
        return
    underlying = getattr(ws, "underlying_transport", None) or ws.transport  # picows, websockets
    sock = underlying.get_extra_info("socket")
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


@pytest.mark.parametrize("batches", [False, True], ids=["calls", "one-call batches"])
async def test_a_client_that_does_not_read_is_read_no_further_and_closed_after_the_write_timeout(
    transport: Transport, batches: bool
) -> None:
    # 300 calls of 100 KB replies is 30 MB, more than any buffer between the two ends holds
    # once the client's receive buffer cannot grow:
    # past the budget the server stops reading (and answering) that client's calls, so only
    # some of them ever run; after the write timeout it closes the connection, says so, and
    # another client's calls are answered all along.
    timeout = scaled(0.5)
    server = Server(max_queued_bytes=2**16, write_timeout=timeout)
    ran = 0

    async def big(request: Any) -> Any:
        nonlocal ran
        ran += 1
        return {"text": "x" * 100_000}

    server.add_service("/big", Echo, big)
    server.add_service("/subtract", Subtract, subtract)
    logged = Logged("closed the connection from")
    server.logger.addHandler(logged)
    calls = 300
    try:
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            stuck = await open_wire(running)  # it reads the $/services, then nothing
            # Small enough that 30 MB cannot hide in it, over loopback's 64 KiB segments so that
            # the client can read what is left at the end at speed.
            set_receive_buffer(stuck, 2**18)
            for id in range(calls):
                call = request("/big", id=id)
                await stuck.send([call] if batches else call)
            async with srvwire.connect(running.url, transport=transport) as other:
                subtract_one = other.proxy("/subtract", Subtract)
                for n in range(20):
                    assert (await subtract_one(minuend=n, subtrahend=1)).difference == n - 1
            async with asyncio.timeout(scaled(20)):
                await logged.seen.wait()
            assert ran < calls
            (record,) = logged.records
            assert record.levelno == logging.WARNING
            assert record.getMessage().endswith(
                f"with code 1008: write timeout: the peer did not read what was sent for "
                f"{timeout:g} s"
            )
            assert not running._connections
            assert await closed_code(stuck) is None  # it sees the connection drop
            async with srvwire.connect(running.url, transport=transport) as other:
                answer = await other.proxy("/subtract", Subtract)(minuend=3, subtrahend=1)
                assert answer.difference == 2
    finally:
        server.logger.removeHandler(logged)


async def test_a_reply_is_not_much_larger_than_the_request_that_caused_it(
    transport: Transport,
) -> None:
    # 20 000 bad elements: the array stops at the first (the error says that one), and
    # 12 bad fields: the error lists the first ten and counts them all.
    server = Server(max_message_size=None)
    fields = "".join(f"int32[] v{i}\n" for i in range(12))
    many = build(f"{fields}---\nbool ok\n", "Many")
    server.add_service("/many", many, lambda request: {"ok": True})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running, max_message_size=None)
        params = {f"v{i}": [1, *["x"] * (20_000 if i == 0 else 1)] for i in range(12)}
        message = json.dumps(request("/many", params))
        await w.send(message)
        reply = await w.recv_reply()
        assert error(reply) == (1, -32602, "INVALID_PARAMS")
        data = reply["error"]["data"]
        assert [e["path"] for e in data["errors"]] == [f"v{i}[1]" for i in range(10)]
        assert data["error_count"] == 12
        assert reply["error"]["message"] == (
            "invalid params for /many: v0[1]: Input should be a valid integer (and 11 more)"
        )
        assert len(json.dumps(reply)) < len(message) // 50
        await w.ws.close()


async def test_the_count_of_dropped_notifications_is_said_when_the_interval_ends(
    caplog: pytest.LogCaptureFixture, transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Not only when the connection ends: a timer says it once the interval has passed.
    monkeypatch.setattr(serving, "DROP_LOG_INTERVAL", scaled(0.05))
    server = Server(max_in_flight=1, grace_period=0)
    hangs = Hang()
    said = asyncio.Event()

    class Said(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            if "more notification" in record.getMessage():
                said.set()

    server.logger.addHandler(handler := Said())
    try:
        server.add_service("/hangs", Echo, hangs)
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            w = await open_wire(running)
            await w.send(request("/hangs", id=1))
            await hangs.entered.wait()
            for _ in range(3):
                await w.send({"jsonrpc": "2.0", "method": "/hangs"})
            await said.wait()
            await w.ws.close()
    finally:
        server.logger.removeHandler(handler)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped ")]
    assert lines[1].startswith("dropped 2 more notifications from ")


STUCK_SCRIPT = """\
import logging, sys, threading
sys.path.insert(0, {tests!r})
from conftest import Echo
from srvwire.server import Server
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
server = Server(grace_period=0.1)
def stuck(request):  # a blocking handler that never returns, as a hung driver call would
    print("entered", flush=True)
    threading.Event().wait()
server.add_service("/stuck", Echo, stuck)
server.run("127.0.0.1", 0, ready=lambda running: print("ready", running.url, flush=True))
print("stopped", flush=True)
"""


async def test_sigterm_ends_the_process_even_with_a_blocking_handler_stuck(
    tmp_path: Any,
) -> None:
    script = tmp_path / "stuck.py"
    script.write_text(STUCK_SCRIPT.format(tests=str(ROOT / "tests")))
    process = await asyncio.create_subprocess_exec(
        sys.executable, str(script), stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE
    )
    try:
        assert process.stderr is not None and process.stdout is not None
        async with asyncio.timeout(scaled(20)):  # a backstop: the process must exit by itself
            line = (await process.stdout.readline()).decode()
            assert line.startswith("ready ws://127.0.0.1:"), line
            w = await open_wire(line.split()[1])
            await w.send(request("/stuck", id=1))
            assert (await process.stdout.readline()).decode() == "entered\n"
            process.send_signal(signal.SIGTERM)
            assert error(await w.recv_reply()) == (1, -32003, "UNAVAILABLE")
            assert await process.wait() == 0
            assert (await process.stdout.read()).decode() == "stopped\n"
            log = (await process.stderr.read()).decode()
            assert "leaving 1 blocking handler running in its thread: stuck (" in log
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ({"max_in_flight": 0}, "max_in_flight must be at least 1, not 0"),
        ({"max_batch": 0}, "max_batch must be at least 1, not 0"),
        ({"notification_timeout": -1}, "notification_timeout must be a number of seconds > 0"),
        ({"grace_period": -1}, "grace_period must not be negative, not -1"),
        ({"max_queued_bytes": -1}, "max_queued_bytes must not be negative, not -1"),
        ({"write_timeout": 0}, "write_timeout must be a number of seconds > 0 or None, not 0"),
    ],
)
def test_bad_server_options_are_refused_at_once(option: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Server(**option)


SWALLOW_SCRIPT = """\
import asyncio, logging, sys
sys.path.insert(0, {tests!r})
from conftest import Echo
from srvwire.server import Server
logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
server = Server(grace_period=0.1)

@server.service("/stubborn", Echo)
async def stubborn(request):
    print("entered", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        while True:  # its cleanup starts over at every cancellation: it never ends
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                continue

server.run("127.0.0.1", 0, ready=lambda running: print("ready", running.url, flush=True),
           transport={transport!r})
print("stopped", flush=True)
"""


@pytest.mark.parametrize("transport_name", ["websockets", "picows"])
@pytest.mark.parametrize("client_leaves", [True, False], ids=["client-gone", "client-stays"])
async def test_shutdown_ends_when_a_handler_never_ends_after_its_cancellation(
    tmp_path: Any, transport_name: str, client_leaves: bool
) -> None:
    # The handler swallows every cancellation: Server.run still returns once the grace period
    # and the second after cancelling are over, names the handler, and the process exits 0.
    text = SWALLOW_SCRIPT.format(tests=str(ROOT / "tests"), transport=transport_name)
    async with serving_script(tmp_path, "swallow.py", text) as (process, out, err, url):
        w = await open_wire(url)
        await w.send(request("/stubborn", {"text": ""}, id="s"))
        assert await out.readline() == b"entered\n"
        process.send_signal(signal.SIGTERM)
        reply = await w.recv_reply()
        assert error(reply) == ("s", -32003, "UNAVAILABLE")
        if client_leaves:
            await w.ws.close()
        else:
            assert await closed_code(w) == 1001
        assert await process.wait() == 0
        assert (await out.read()).decode() == "stopped\n"
        log = (await err.read()).decode()
        assert (
            "leaving 1 handler running that did not end when cancelled (its call was "
            "answered): /stubborn" in log
        ), log
        assert "Traceback" not in log and "destroyed" not in log, log
