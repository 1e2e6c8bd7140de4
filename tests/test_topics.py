"""Topics end to end: a server's topics, srvwire's client and a raw wire, on each transport."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from conftest import Subtract, Wire, open_wire, subtract
from srvwire import (
    ConnectionLost,
    DeadlineExceeded,
    Identity,
    InvalidParams,
    PermissionDenied,
    ResourceExhausted,
    Server,
    ServiceNotFound,
    ServiceUnavailable,
    TokenAuth,
    connect,
    load_message,
    load_service,
    serve,
    serving,
)
from srvwire.errors import RegistrationError
from srvwire.server import RunningServer
from srvwire.serving import ServedConnection, Writer
from srvwire.transports.base import Connection, Transport, TransportClosed
from srvwire.transports.memory import MemoryConnection, MemoryTransport
from srvwire.typeregistry import fingerprint, full_definition
from support import scaled

JointState = load_message("sensor_msgs/msg/JointState")
String = load_message("std_msgs/msg/String")


def joints(n: int) -> Any:
    return JointState(name=["shoulder"], position=[float(n)])


async def recv_topic(wire: Wire, within: float = 5.0) -> Any:
    """The next message that is not an announcement."""
    while True:
        message = await wire.recv(within)
        if message.get("method") not in ("$/services", "$/topics"):
            return message


@pytest.fixture
def robot() -> Server:
    server = Server(grace_period=scaled(2))
    server.add_service("/subtract", Subtract, subtract)
    return server


@pytest.fixture
async def running(robot: Server, transport: Transport) -> AsyncIterator[RunningServer]:
    async with serve(robot, "127.0.0.1", 0, transport=transport) as running:
        yield running


def client_of(running: RunningServer, **options: Any) -> connect:
    return connect(running.url, transport=running.transport, timeout=scaled(5), **options)


# --- round trips ---------------------------------------------------------------------------------


@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
@pytest.mark.parametrize("durability", ["volatile", "transient_local"])
async def test_every_qos_round_trips(
    robot: Server, running: RunningServer, reliability: str, durability: str
) -> None:
    qos = {"depth": 3, "reliability": reliability, "durability": durability}
    pub = robot.topic("/joint_states", JointState, qos=qos)
    for n in range(1, 6):  # before anyone subscribes: kept only by transient_local
        assert pub.publish(joints(n)) == 0
    async with client_of(running) as client:
        info = await client.wait_for_topic("/joint_states")
        assert (info.type, dict(info.qos), info.publish) == (
            "sensor_msgs/msg/JointState",
            qos,
            False,
        )
        async with client.subscribe("joint_states") as sub:
            assert sub.granted["reliability"] == reliability
            assert sub.granted["durability"] == durability
            assert sub.granted["seq"] == 5
            assert pub.subscription_count == 1
            if durability == "transient_local":
                replayed = [await sub.receive() for _ in range(3)]
                assert [m.position for m in replayed] == [[3.0], [4.0], [5.0]]
                assert sub.seq == 5
            assert pub.publish(joints(6)) == 1
            message = await sub.receive()
            assert type(message) is JointState
            assert message.position == [6.0] and sub.seq == 6 and sub.missed == 0
            assert sub.dropped == 0


async def test_the_server_receives_what_clients_publish(
    robot: Server, running: RunningServer
) -> None:
    received: asyncio.Queue[Any] = asyncio.Queue()

    @robot.subscription("/joint_states", JointState)
    def on_joint_states(msg: Any) -> None:
        received.put_nowait(msg)

    async with client_of(running) as client, client_of(running) as listener:
        await client.wait_for_topic("/joint_states")
        async with listener.subscribe("/joint_states") as sub:
            await client.publish("/joint_states", {"name": ["elbow"], "position": [1.5]})
            got = await received.get()
            assert type(got) is JointState and got.name == ["elbow"]
            relayed = await sub.receive()  # other subscribers get it too, as in ROS
            assert relayed == got
            await client.publish("/joint_states", joints(2), ack=True)
            assert (await received.get()).position == [2.0]
        with pytest.raises(InvalidParams) as caught:  # refused here, before sending
            await client.publish("/joint_states", {"position": ["high"]})
        assert caught.value.data["errors"][0]["path"] == "message.position[0]"


async def test_an_acknowledged_publish_with_bad_data_is_answered_with_field_paths(
    robot: Server, running: RunningServer
) -> None:
    seen: list[Any] = []
    robot.subscription("/joint_states", JointState)(seen.append)
    wire = await open_wire(running)
    publish = {
        "jsonrpc": "2.0",
        "id": 7,
        "method": "$/publish",
        "params": {"topic": "/joint_states", "message": {"name": "elbow", "position": [1, "x"]}},
    }
    await wire.send(publish)
    reply = await recv_topic(wire)
    assert reply["id"] == 7
    assert reply["error"]["message"] == (
        "invalid message for /joint_states: message.name: Input should be a valid list (and 1 more)"
    )
    assert reply["error"]["data"]["errors"] == [
        {"path": "message.name", "message": "Input should be a valid list", "type": "list_type"},
        {
            "path": "message.position[1]",
            "message": "Input should be a valid number",
            "type": "float_type",
        },
    ]
    publish["params"]["message"] = {"name": ["elbow"]}
    await wire.send(publish)
    assert await recv_topic(wire) == {"jsonrpc": "2.0", "id": 7, "result": None}
    assert [m.name for m in seen] == [["elbow"]]
    await wire.ws.close()


async def test_publishing_on_a_topic_announced_publish_false_raises_before_sending(
    transport: Transport, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(serving, "DROP_LOG_INTERVAL", 0)  # a line for each message dropped
    caplog.set_level(logging.INFO, "srvwire.server")
    auth = TokenAuth({"guest": "guest"})
    server = Server(auth=auth)
    server.add_service("/subtract", Subtract, subtract)
    server.topic("/status", String)  # the server publishes it; clients only subscribe
    server.subscription("/cmd", String, scopes={"admin"})(lambda msg: None)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, token="guest") as guest:
            info = await guest.wait_for_topic("/status")
            assert info.publish is False
            for ack in (False, True):
                with pytest.raises(PermissionDenied) as caught:
                    await guest.publish("/status", {"data": "hi"}, ack=ack)
                assert caught.value.message == (
                    "the server does not take messages on /status; only subscribe to it"
                )
            # A topic the connection may not see is not refused here: the server logs it.
            await guest.publish("/cmd", {"data": "go"}, msg_type=String)
            # A call after it is answered after the message was handled.
            await guest.call("/subtract", {"minuend": 2, "subtrahend": 1})
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped ")]
    host = "memory" if transport.name == "memory" else "127.0.0.1"
    assert len(lines) == 1, lines  # nothing was sent on /status
    assert lines[0].startswith(f"dropped a message on /cmd from ('{host}', ")
    assert lines[0].endswith(
        ": permission denied: /cmd needs the scope admin, which this connection's identity "
        "does not hold"
    )


async def test_the_server_logs_a_message_published_where_it_takes_none(
    robot: Server,
    running: RunningServer,
    caplog: pytest.LogCaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(serving, "DROP_LOG_INTERVAL", 1e9)  # the whole test is one interval
    caplog.set_level(logging.INFO, "srvwire.server")
    robot.topic("/status", String)
    wire = await open_wire(running)
    for topic in ("/status", "/nowhere", "/status"):
        params = {"topic": topic, "message": {"data": "hi"}}
        await wire.send({"jsonrpc": "2.0", "method": "$/publish", "params": params})
    call = {"jsonrpc": "2.0", "id": 1, "method": "/subtract", "params": {"minuend": 1}}
    await wire.send(call)
    assert (await recv_topic(wire))["id"] == 1  # nothing answered the messages
    await wire.ws.close()
    await running.close()  # the count of the others is said when the connection ends
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("dropped ")]
    first, more = lines
    assert first.startswith("dropped a message on /status from (")
    assert first.endswith(": the server does not take messages on /status; only subscribe to it")
    assert more.startswith("dropped 2 more notifications from (")


async def test_notify_sends_a_call_nobody_answers(robot: Server, running: RunningServer) -> None:
    done: asyncio.Queue[int] = asyncio.Queue()

    @robot.service("/remember", Subtract)
    def remember(request: Any) -> Any:
        done.put_nowait(request.minuend)
        return subtract(request)

    async with client_of(running) as client:
        await client.notify("/remember", {"minuend": 5, "subtrahend": 1})
        assert await done.get() == 5
        assert client.in_flight == 0
        with pytest.raises(InvalidParams):
            await client.notify("/remember", {"minuend": "five"})


async def test_a_topic_typed_only_by_the_servers_description(
    robot: Server, running: RunningServer, tmp_path: Any
) -> None:
    from srvwire.models import build_message
    from srvwire.parser import parse_message

    Pose = build_message(parse_message("float64 x\nfloat64 y\n", "inproc_topics", "Pose2"))
    pub = robot.topic("/pose", Pose)
    async with client_of(running) as client:
        await client.wait_for_topic("/pose")
        async with client.subscribe("/pose") as sub:
            pub.publish(Pose(x=1.0, y=2.0))
            message = await sub.receive()
    assert type(message).type_name == "inproc_topics/msg/Pose2"  # type: ignore[attr-defined]
    assert (message.x, message.y) == (1.0, 2.0)  # type: ignore[attr-defined]


# --- discovery and security ----------------------------------------------------------------------


async def test_discovery_lists_topics_apart_from_services(
    robot: Server, running: RunningServer
) -> None:
    robot.topic("/joint_states", JointState, qos={"depth": 5})
    async with client_of(running) as client:
        assert [s.name for s in await client.list_services()] == ["/subtract"]
        wire = await open_wire(running)
        await wire.send({"jsonrpc": "2.0", "id": 1, "method": "rpc.discover"})
        document = (await recv_topic(wire))["result"]
        [topic] = [m for m in document["methods"] if m.get("x-srvwire-kind") == "topic"]
        assert topic["name"] == "/joint_states"
        assert topic["x-srvwire-type"] == "sensor_msgs/msg/JointState"
        assert topic["x-srvwire-qos"] == {
            "depth": 5,
            "reliability": "reliable",
            "durability": "volatile",
        }
        assert "std_msgs/msg/Header" in topic["x-srvwire-definitions"]
        digest = fingerprint(full_definition(JointState) or {})
        assert topic["x-srvwire-fingerprint"] == client._topics["/joint_states"]["fingerprint"]
        assert topic["x-srvwire-fingerprint"] == digest
        await wire.ws.close()


async def test_topics_obey_scopes() -> None:
    auth = TokenAuth({"op": Identity("operator", {"robot:read"}), "guest": "guest"})
    server = Server(auth=auth)
    pub = server.topic("/joint_states", JointState, scopes={"robot:read"})
    server.subscription("/commands", String, scopes={"robot:write"})(lambda msg: None)
    transport = MemoryTransport()
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, token="guest") as guest:
            assert dict(guest.topics) == {}
            with pytest.raises(PermissionDenied) as caught:
                await guest.subscribe("/joint_states", JointState).start()
            assert caught.value.message == (
                "permission denied: /joint_states needs the scope robot:read, which this "
                "connection's identity does not hold"
            )
            with pytest.raises(PermissionDenied):
                await guest.publish("/commands", {"data": "go"}, msg_type=String, ack=True)
        async with connect(running.url, transport=transport, token="op") as operator:
            await operator.wait_for_topic("/joint_states")
            assert list(operator.topics) == ["/joint_states"]
            async with operator.subscribe("/joint_states") as sub:
                pub.publish(joints(1))
                assert (await sub.receive()).position == [1.0]


async def test_a_later_declaration_sets_the_scopes_and_qos_an_earlier_one_left_out(
    transport: Transport,
) -> None:
    auth = TokenAuth({"op": Identity("operator", {"admin"}), "guest": "guest"})
    server = Server(auth=auth)

    @server.subscription("/cmd", String)  # declares /cmd with the defaults
    def on_cmd(msg: Any) -> None:
        pass

    qos = {"depth": 1, "reliability": "reliable", "durability": "transient_local"}
    pub = server.topic("/cmd", String, scopes={"admin"}, qos=qos)
    assert pub.qos.to_json() == qos
    assert server.topic("/cmd", String).qos.to_json() == qos  # leaving them out keeps them
    pub.publish(String(data="first"))
    pub.publish(String(data="latest"))
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, token="guest") as guest:
            assert dict(guest.topics) == {}
            with pytest.raises(PermissionDenied, match="/cmd needs the scope admin"):
                await guest.subscribe("/cmd", String).start()
        async with connect(running.url, transport=transport, token="op") as operator:
            await operator.wait_for_topic("/cmd")
            async with operator.subscribe("/cmd") as sub:
                assert sub.granted["durability"] == "transient_local"
                assert (await sub.receive()).data == "latest"  # the history of depth 1
            server.topic("/plain", String)
            await operator.wait_for_topic("/plain")
            async with operator.subscribe("/plain"):
                with pytest.raises(RegistrationError, match="once clients subscribe"):
                    server.topic("/plain", String, scopes={"admin"})


def test_declaring_a_topic_twice_with_other_scopes_or_qos_is_refused() -> None:
    server = Server()
    server.topic("/cmd", String, scopes={"admin"}, qos={"depth": 1})
    with pytest.raises(RegistrationError) as caught:
        server.topic("/cmd", String, scopes={"guest"})
    assert "/cmd is declared with the scopes ['admin'], not ['guest']" in str(caught.value)
    with pytest.raises(RegistrationError) as caught:
        server.topic("/cmd", String, qos={"depth": 2})
    assert "/cmd is declared with the QoS {'depth': 1," in str(caught.value)
    assert "not {'depth': 2," in str(caught.value)
    with pytest.raises(RegistrationError, match="declared with the scopes"):
        server.subscription("/cmd", String, scopes={"other"})(lambda msg: None)
    same = server.topic("/cmd", String, scopes={"admin"}, qos={"depth": 1})
    assert (same.qos.depth, server.registry.topics.get("/cmd").scopes) == (  # type: ignore[union-attr]
        1,
        frozenset({"admin"}),
    )
    server.subscription("/cmd", String)(lambda msg: None)  # leaves them out: keeps them
    server.subscription("/plain", String)(lambda msg: None)
    server.topic("/plain", String, qos={"depth": 10})  # the default, but given: it holds
    with pytest.raises(RegistrationError, match="/plain is declared with the QoS"):
        server.topic("/plain", String, qos={"depth": 3})


# --- the end of a subscription -------------------------------------------------------------------


async def test_cancel_disconnect_and_removal_end_subscriptions(
    robot: Server, running: RunningServer
) -> None:
    pub = robot.topic("/joint_states", JointState)
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        # $/cancel: the server has read it once a call sent after it is answered.
        async with client.subscribe("/joint_states"):
            assert pub.subscription_count == 1
        await client.call("/subtract", {"minuend": 1, "subtrahend": 1})
        assert pub.subscription_count == 0
        (served,) = running._connections
        assert served.writer.outbox.queued == 0 and not served.writer.outbox.subscriptions
        # Removing the topic ends the subscription with a reply.
        sub = client.subscribe("/joint_states")
        await sub.start()
        pub.publish(joints(1))  # still queued on the server: dropped with the subscription
        robot.remove_topic("/joint_states")
        with pytest.raises(ServiceNotFound) as caught:
            await sub.receive()
        assert caught.value.message == "the topic /joint_states was removed"
        assert not sub.active and not client._subscriptions
        with pytest.raises(RegistrationError):
            robot.remove_topic("/joint_states")
    # The connection closing ends the rest.
    pub = robot.topic("/joint_states", JointState)
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        await client.subscribe("/joint_states").start()
        await client.subscribe("/joint_states", qos={"depth": 1}).start()
        (served,) = running._connections
        assert pub.subscription_count == 2
    writer = served.writer.task
    assert writer is not None
    await asyncio.wait({writer})
    assert pub.subscription_count == 0 and not served.writer.outbox.subscriptions


async def test_a_deadline_ends_a_subscription(robot: Server, running: RunningServer) -> None:
    pub = robot.topic("/joint_states", JointState)
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        (served,) = running._connections
        outbox = served.writer.outbox
        async with client.subscribe("/joint_states", duration=0.25) as sub:
            pub.publish(joints(1))
            assert (await sub.receive()).position == [1.0]
            with pytest.raises(DeadlineExceeded) as caught:
                await sub.receive()
        assert caught.value.message == (
            "the subscription to /joint_states reached its deadline (0.25 s)"
        )
        assert caught.value.data == {"timeout": 0.25} and caught.value.service == "/joint_states"
        assert not sub.active and not client._subscriptions
        assert pub.subscription_count == 0 and not outbox.subscriptions and outbox.queued == 0
        # Ended earlier ($/cancel here), its deadline's timer is cancelled with it.
        async with client.subscribe("/joint_states", duration=scaled(60)):
            (running_sub,) = outbox.subscriptions.values()
            assert running_sub.timer is not None
        await client.call("/subtract", {"minuend": 1, "subtrahend": 1})
        assert running_sub.timer is None and pub.subscription_count == 0
        with pytest.raises(ValueError, match="duration must be a finite number of seconds > 0"):
            client.subscribe("/joint_states", duration=0)
    # On the wire: the deadline is the request's _meta.timeout, answered DEADLINE_EXCEEDED.
    wire = await open_wire(running)
    try:
        await wire.send(
            {
                "jsonrpc": "2.0",
                "id": 5,
                "method": "$/subscribe",
                "params": {"topic": "/joint_states", "_meta": {"timeout": 0.1}},
            }
        )
        assert (await recv_topic(wire))["method"] == "$/subscribed"
        reply = await recv_topic(wire)
        assert reply == {
            "jsonrpc": "2.0",
            "id": 5,
            "error": {
                "code": -32001,
                "message": "the subscription to /joint_states reached its deadline (0.1 s)",
                "data": {"status": "DEADLINE_EXCEEDED", "timeout": 0.1},
            },
        }
        assert pub.subscription_count == 0
    finally:
        await wire.close()


async def test_a_reliable_subscriber_that_does_not_keep_up_is_ended(
    robot: Server, running: RunningServer
) -> None:
    pub = robot.topic("/joint_states", JointState, qos={"depth": 2})
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        async with client.subscribe("/joint_states") as sub:
            for n in range(5):
                pub.publish(joints(n))
            # Busy elsewhere while the five arrive (the server wrote them before it read the
            # call, so they come before its reply): the subscriber's queue of 2 overflows.
            assert (await client.call("/subtract", {"minuend": 3})).difference == 3
            assert [(await sub.receive()).position for _ in range(2)] == [[0.0], [1.0]]
            with pytest.raises(ResourceExhausted) as caught:
                await sub.receive()
            assert "did not keep up: its queue of 2 messages was full" in caught.value.message
            assert "subscribe with a larger depth, or best_effort" in caught.value.message
        assert pub.subscription_count == 0


async def test_a_best_effort_subscriber_is_told_what_it_missed(
    robot: Server, running: RunningServer
) -> None:
    pub = robot.topic("/joint_states", JointState, qos={"depth": 2, "reliability": "best_effort"})
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        async with client.subscribe("/joint_states") as sub:
            for n in range(1, 6):
                pub.publish(joints(n))
            assert (await client.call("/subtract", {"minuend": 3})).difference == 3  # busy
            first = await sub.receive()
            second = await sub.receive()
            assert [first.position, second.position] == [[4.0], [5.0]]
            assert sub.dropped == 3 and sub.seq == 5


# --- bursts --------------------------------------------------------------------------------------


async def read_all(sub: Any, count: int) -> list[Any]:
    """What a subscriber that reads as messages come receives: ``count`` messages."""
    return [await sub.receive() for _ in range(count)]


@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
async def test_a_burst_from_a_handler_reaches_a_reading_subscriber_whole_and_in_order(
    robot: Server, running: RunningServer, reliability: str
) -> None:
    # Several times the depth, published in one turn of the loop: the connection takes it all,
    # so nothing is dropped and no reliable subscriber is ended (depth bounds what waits on a
    # connection that takes no more, not what one turn publishes).
    pub = robot.topic("/detections", String, qos={"depth": 10, "reliability": reliability})
    Trigger = load_service("std_srvs/srv/Trigger")
    reached = []

    @robot.service("/scan", Trigger)
    async def scan(request: Any) -> Any:
        for n in range(50):
            reached.append(pub.publish({"data": f"object {n}"}))
        return {"success": True}

    async with client_of(running) as client:
        await client.wait_for_topic("/detections")
        async with client.subscribe("/detections") as sub:
            reader = asyncio.ensure_future(read_all(sub, 50))
            assert (await client.call("/scan")).success
            got = await asyncio.wait_for(reader, scaled(10))
            assert [m.data for m in got] == [f"object {n}" for n in range(50)]
            assert (sub.seq, sub.dropped) == (50, 0)
            assert pub.subscription_count == 1
    assert reached == [1] * 50


async def test_a_burst_of_client_publications_reaches_a_reading_subscriber_whole_and_in_order(
    robot: Server, running: RunningServer
) -> None:
    robot.subscription("/commands", String)(lambda msg: None)  # clients may publish on it
    async with client_of(running) as listener, client_of(running) as publisher:
        await publisher.wait_for_topic("/commands")
        async with listener.subscribe("/commands", qos={"depth": 2}) as sub:
            reader = asyncio.ensure_future(read_all(sub, 50))
            for n in range(50):  # notifications, none waiting for the server
                await publisher.publish("/commands", {"data": f"r{n}"})
            got = await asyncio.wait_for(reader, scaled(10))
            assert [m.data for m in got] == [f"r{n}" for n in range(50)]
            assert (sub.seq, sub.dropped) == (50, 0)


async def test_reconnecting_resumes_subscriptions_and_reports_the_gap() -> None:
    server = Server()
    pub = server.topic(
        "/joint_states", JointState, qos={"depth": 1, "durability": "transient_local"}
    )
    transport = MemoryTransport()
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(
            running.url, transport=transport, reconnect=True, timeout=scaled(5)
        ) as client:
            await client.wait_for_topic("/joint_states")
            async with client.subscribe("/joint_states") as sub:
                pub.publish(joints(1))
                assert (await sub.receive()).position == [1.0]
                (served,) = running._connections
                assert isinstance(served.conn, MemoryConnection)
                served.conn.abort()  # the network drops: these never reach the client
                for n in (2, 3, 4):
                    pub.publish(joints(n))
                resumed = await sub.receive()  # the topic's last message, replayed
                assert resumed.position == [4.0]
                assert (sub.seq, sub.missed, sub.dropped) == (4, 2, 2)
                assert sub.gaps.resumed == 1
                assert pub.subscription_count == 1
                pub.publish(joints(5))
                assert (await sub.receive()).position == [5.0]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on (it was free a moment ago)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def served_history(published: int, tag: str) -> Server:
    """A server whose topic /tl keeps its last 3 messages, of which it published ``published``
    before anyone connects (``tag`` 1, ``tag`` 2, ...)."""
    server = Server(grace_period=0)
    pub = server.topic("/tl", String, qos={"depth": 3, "durability": "transient_local"})
    for n in range(1, published + 1):
        pub.publish(String(data=f"{tag}{n}"))
    return server


async def receive_some(sub: Any, count: int) -> list[tuple[int, str]]:
    """The next ``count`` messages of ``sub``, with their sequence numbers."""
    async with asyncio.timeout(scaled(10)):  # a message that never comes fails, not hangs
        return [((message := await sub.receive()) and sub.seq, message.data) for _ in range(count)]


@pytest.mark.parametrize("transport_name", ["websockets", "picows"])
async def test_the_resume_log_says_the_last_message_seen_before_a_restart(
    transport_name: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, "srvwire.client")
    port = free_port()
    async with connect(f"ws://127.0.0.1:{port}", reconnect=True, timeout=scaled(5)) as client:
        async with serve(served_history(3, "old"), "127.0.0.1", port, transport=transport_name):
            await client.wait_for_topic("/tl", timeout=scaled(10))
            sub = await client.subscribe("/tl").start()
            assert await receive_some(sub, 3) == [(1, "old1"), (2, "old2"), (3, "old3")]
        async with serve(served_history(1, "new"), "127.0.0.1", port, transport=transport_name):
            assert await receive_some(sub, 1) == [(1, "new1")]  # the new server's
            assert sub.gaps.restarts == 1
    lines = [r.getMessage() for r in caplog.records if "resumed" in r.getMessage()]
    assert lines == ["resumed the subscription to /tl after reconnecting (last message seen: 3)"]


@pytest.mark.parametrize("transport_name", ["websockets", "picows"])
async def test_a_resumed_subscription_gets_a_restarted_servers_history_though_its_seq_went_on(
    transport_name: str,
) -> None:
    port = free_port()
    async with connect(f"ws://127.0.0.1:{port}", reconnect=True, timeout=scaled(5)) as client:
        async with serve(served_history(3, "old"), "127.0.0.1", port, transport=transport_name):
            await client.wait_for_topic("/tl", timeout=scaled(10))
            sub = await client.subscribe("/tl").start()
            first_epoch = sub.granted.get("epoch")
            assert await receive_some(sub, 3) == [(1, "old1"), (2, "old2"), (3, "old3")]
        # Another server, which published 4: it keeps 2, 3 and 4, none of them seen.
        async with serve(served_history(4, "new"), "127.0.0.1", port, transport=transport_name):
            assert await receive_some(sub, 3) == [(2, "new2"), (3, "new3"), (4, "new4")]
            assert sub.granted["epoch"] != first_epoch
            assert (sub.gaps.restarts, sub.gaps.resumed, sub.dropped) == (1, 1, 0)


async def test_without_reconnect_a_lost_connection_ends_the_subscription() -> None:
    server = Server()
    server.topic("/joint_states", JointState)
    transport = MemoryTransport()
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, timeout=scaled(5)) as client:
            await client.wait_for_topic("/joint_states")
            sub = await client.subscribe("/joint_states").start()
            (served,) = running._connections
            assert isinstance(served.conn, MemoryConnection)
            served.conn.abort()
            with pytest.raises(ConnectionLost):
                await sub.receive()


# --- data never delays control -------------------------------------------------------------------


async def test_a_flooded_topic_does_not_delay_another_on_the_same_connection(
    robot: Server, running: RunningServer
) -> None:
    flood = robot.topic("/flood", String, qos={"depth": 500})
    quiet = robot.topic("/quiet", String)
    wire = await open_wire(running)
    for id, name in ((1, "/flood"), (2, "/quiet")):
        await wire.send(
            {"jsonrpc": "2.0", "id": id, "method": "$/subscribe", "params": {"topic": name}}
        )
        assert (await recv_topic(wire))["method"] == "$/subscribed"
    for n in range(300):
        flood.publish({"data": f"flood {n}"})
    quiet.publish({"data": "news"})
    await wire.send({"jsonrpc": "2.0", "id": 3, "method": "/subtract", "params": {"minuend": 3}})
    order = []
    while len(order) < 302:
        message = await recv_topic(wire)
        order.append(message["params"]["subscription"] if "method" in message else "reply")
    # Round-robin: the quiet topic's one message goes out second, not after 300 others.
    assert order.index(2) == 1
    assert order.count(1) == 300 and "reply" in order
    await wire.ws.close()


async def test_each_message_is_written_once_for_every_subscriber(
    robot: Server, running: RunningServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    pub = robot.topic("/joint_states", JointState)
    writes: list[Any] = []
    entry = pub._topic.entry
    write = entry.write
    monkeypatch.setattr(entry, "write", lambda m: writes.append(m) or write(m))
    wires = [await open_wire(running) for _ in range(3)]
    for wire in wires:
        await wire.send(
            {
                "jsonrpc": "2.0",
                "id": 1,
                "method": "$/subscribe",
                "params": {"topic": "/joint_states"},
            }
        )
        assert (await recv_topic(wire))["method"] == "$/subscribed"
    assert pub.publish(joints(1)) == 3
    assert len(writes) == 1
    for wire in wires:
        message = await recv_topic(wire)
        assert message["params"]["message"]["position"] == [1.0]
        await wire.ws.close()


def test_declaring_topics_checks_names_types_and_handlers() -> None:
    server = Server()
    server.topic("/joint_states", JointState)
    with pytest.raises(RegistrationError, match="declared with sensor_msgs/msg/JointState"):
        server.topic("/joint_states", String)
    with pytest.raises(RegistrationError, match="must be a message type"):
        server.topic("/x", Subtract)  # type: ignore[arg-type]
    with pytest.raises(RegistrationError, match="must take one argument, the message"):
        server.subscription("/joint_states", JointState)(lambda: None)
    with pytest.raises(RegistrationError, match="depth must be an integer"):
        server.topic("/y", String, qos={"depth": 0})
    assert json.loads(json.dumps(server.registry.discover()))["methods"][0]["name"] == (
        "/joint_states"
    )


# --- a subscriber that never reads ---------------------------------------------------------------

SERVERS = Path(__file__).parent / "servers"


def rss(pid: int) -> int:
    """The resident memory of process ``pid``, in bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


def masked_text_frame(text: str) -> bytes:
    """One WebSocket text frame from a client (masked), written by hand."""
    payload = text.encode()
    assert len(payload) < 126
    mask = os.urandom(4)
    return (
        bytes([0x81, 0x80 | len(payload)])
        + mask
        + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    )


async def never_reading_subscriber(port: int, topic: str) -> asyncio.StreamWriter:
    """Open a WebSocket by hand with a small receive buffer, subscribe to ``topic``, and never
    read again (asyncio stops reading the socket once its own small buffer is full)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    reader, writer = await asyncio.open_connection(sock=sock, limit=4096)
    writer.write(
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert (await reader.readuntil(b"\r\n\r\n")).startswith(b"HTTP/1.1 101")
    subscribe = {"jsonrpc": "2.0", "id": 1, "method": "$/subscribe", "params": {"topic": topic}}
    writer.write(masked_text_frame(json.dumps(subscribe)))
    await writer.drain()
    return writer


async def test_a_subscriber_that_never_reads_costs_bounded_memory_and_slows_nobody() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable, str(SERVERS / "flooding_server.py"), stdout=asyncio.subprocess.PIPE
    )
    stalled = []
    try:
        assert process.stdout is not None
        port = int(await asyncio.wait_for(process.stdout.readline(), scaled(20)))
        url = f"ws://127.0.0.1:{port}"
        stalled = [await never_reading_subscriber(port, "/flood") for _ in range(3)]
        async with connect(url, timeout=scaled(10)) as client:
            async with client.subscribe("/flood", qos={"depth": 100}) as sub:
                for _ in range(1000):  # the stalled sockets' buffers fill meanwhile
                    await sub.receive()
                before = rss(process.pid)
                received = 0
                for n in range(3000):  # about 3 s, 30 MB published
                    message = await sub.receive()
                    assert len(message.data) == 10_000  # type: ignore[attr-defined]
                    received += 1
                    if n % 250 == 0:
                        reply = await client.call("/add_two_ints", {"a": n, "b": 1})
                        assert reply.sum == n + 1
                after = rss(process.pid)
        # Queued without bound, the stalled subscribers would hold 30 MB more by now (the
        # messages' bytes are shared); bounded, they hold what they held before.
        assert after - before < 10 * 2**20, (before, after)
        assert received == 3000
    finally:
        for writer in stalled:
            writer.close()
        process.kill()
        await process.wait()


async def test_closing_a_client_ends_its_subscriptions_quietly(
    robot: Server, running: RunningServer, caplog: pytest.LogCaptureFixture
) -> None:
    robot.topic("/joint_states", JointState)
    async with client_of(running) as client:
        await client.wait_for_topic("/joint_states")
        sub = await client.subscribe("/joint_states").start()
    assert not sub.active and client.in_flight == 0
    with pytest.raises(StopAsyncIteration):
        await sub.receive()
    assert [r for r in caplog.records if r.levelname == "WARNING"] == []


async def test_a_reply_goes_ahead_of_topic_data_the_server_holds() -> None:
    # The handler publishes a burst and answers: the burst waits in the connection's outbox for
    # the writer's turn, and the reply, written at once, overtakes it.
    server = Server(max_queued_bytes=20_000)
    flood = server.topic("/flood", String, qos={"depth": 200})

    @server.service("/subtract", Subtract)
    async def answer(request: Any) -> Any:  # async: answered on the reader, no thread
        for n in range(3):
            flood.publish({"data": f"{n:05d}" + "x" * 5000})
        return subtract(request)

    transport = MemoryTransport()
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        wire = await open_wire(running)
        params = {"topic": "/flood"}
        await wire.send({"jsonrpc": "2.0", "id": 1, "method": "$/subscribe", "params": params})
        assert (await recv_topic(wire))["method"] == "$/subscribed"
        call = {"jsonrpc": "2.0", "id": 2, "method": "/subtract", "params": {"minuend": 5}}
        await wire.send(call)
        order = []
        while len(order) < 4:
            message = await recv_topic(wire)
            order.append("reply" if message.get("id") == 2 else message["params"]["seq"])
        assert order == ["reply", 1, 2, 3]
        await wire.ws.close()


# --- the connection's budget bounds topic data ---------------------------------------------------

KIB = 2**10
TEN_KB = {"data": "x" * 10_000}
FRAME = len(b'{"jsonrpc":"2.0","method":"$/message","params":{}}') + 10_100  # a message, at most
KERNEL = 64 * KIB  # what the two sockets' buffers may hold, at most, once made small (measured)


async def stalled_subscriber(
    port: int, qos: dict[str, Any]
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A WebSocket opened by hand with a small receive buffer, subscribed to ``/flood``; it
    reads nothing after ``$/subscribed`` until the test reads it with :func:`read_frame`."""
    reader, writer = await asyncio.open_connection(
        sock=await small_buffered_socket(port), limit=4096
    )
    writer.write(
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    assert (await reader.readuntil(b"\r\n\r\n")).startswith(b"HTTP/1.1 101")
    subscribe = {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "$/subscribe",
        "params": {"topic": "/flood", "qos": qos},
    }
    writer.write(masked_text_frame(json.dumps(subscribe)))
    while (await read_frame(reader)).get("method") != "$/subscribed":
        pass
    return reader, writer


def small_send_buffer(running: RunningServer) -> Any:
    """The server's one connection, whose socket's send buffer is made small (8 KiB), so that
    what the kernel holds does not hide what the server holds (loopback grows it to megabytes)."""
    (served,) = running._connections
    sock = served.conn._ws.transport.get_extra_info("socket")
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8 * KIB)
    return served


async def small_buffered_socket(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    return sock


async def read_frame(reader: asyncio.StreamReader) -> Any:
    """One text frame from the server (unmasked), parsed."""
    head = await asyncio.wait_for(reader.readexactly(2), scaled(10))
    size = head[1] & 0x7F
    if size == 126:
        size = int.from_bytes(await reader.readexactly(2), "big")
    elif size == 127:
        size = int.from_bytes(await reader.readexactly(8), "big")
    return json.loads(await reader.readexactly(size))


@pytest.mark.parametrize("budget", [64 * KIB, 512 * KIB])
async def test_a_reliable_subscriber_that_never_reads_is_ended_where_the_budget_is_spent(
    budget: int,
) -> None:
    server = Server(max_queued_bytes=budget)
    flood = server.topic("/flood", String, qos={"depth": 10_000})
    async with serve(server, "127.0.0.1", 0) as running:
        reader, writer = await stalled_subscriber(running.port, {})
        small_send_buffer(running)
        try:
            published = 0
            while flood.subscription_count:
                flood.publish(TEN_KB)
                published += 1
                await asyncio.sleep(0)  # a turn of the loop: the writer sends, the socket fills
            # The budget was spent before the subscriber was ended, and no more than the budget
            # (and the kernel's buffers, and the one message an empty outbox always takes).
            assert budget <= published * FRAME <= budget + KERNEL + 2 * FRAME, published
            while "id" not in (ended := await read_frame(reader)):
                pass
            assert ended["id"] == 1
            error = ended["error"]
            assert error["data"]["status"] == "RESOURCE_EXHAUSTED"
            assert error["data"]["max_queued_bytes"] == budget
            assert f"spent the connection's budget of {budget} bytes" in error["message"]
        finally:
            writer.close()


async def test_a_reliable_subscriber_that_never_reads_is_ended_at_its_depth_once_congested() -> (
    None
):
    server = Server(max_queued_bytes=64 * KIB)
    flood = server.topic("/flood", String)
    async with serve(server, "127.0.0.1", 0) as running:
        reader, writer = await stalled_subscriber(running.port, {"depth": 1})
        served = small_send_buffer(running)
        try:
            published = 0
            while flood.subscription_count:
                flood.publish(TEN_KB)
                published += 1
                if not served.conn.congested:
                    assert flood.subscription_count == 1  # while it takes more, never ended
                await asyncio.sleep(0)  # a turn of the loop: the writer sends, the socket fills
            assert published * FRAME >= 64 * KIB  # ended only once the transport held the budget
            while "id" not in (ended := await read_frame(reader)):
                pass
            error = ended["error"]
            assert error["data"]["status"] == "RESOURCE_EXHAUSTED"
            why = "its queue of 1 messages was full while its connection took no more"
            assert why in error["message"]
        finally:
            writer.close()


@pytest.mark.parametrize("budget", [64 * KIB, 512 * KIB])
async def test_a_best_effort_subscriber_that_never_reads_gets_the_budget_and_the_drop_count(
    budget: int,
) -> None:
    server = Server(max_queued_bytes=budget)
    flood = server.topic("/flood", String, qos={"depth": 10_000, "reliability": "best_effort"})
    async with serve(server, "127.0.0.1", 0) as running:
        reader, writer = await stalled_subscriber(running.port, {})
        served = small_send_buffer(running)
        try:
            published = 0
            while not served.conn.congested:  # until the transport holds the budget
                flood.publish(TEN_KB)
                published += 1
                await asyncio.sleep(0)  # a turn of the loop: the writer sends, the socket fills
            assert budget <= published * FRAME <= budget + KERNEL + 2 * FRAME, published
            for _ in range(100):  # then well past it
                flood.publish(TEN_KB)
                published += 1
                await asyncio.sleep(0)
            assert served.outbox.queued <= FRAME  # the one, newest, message an empty outbox takes
            seqs, dropped = [], 0
            while not seqs or seqs[-1] < published:
                params = (await read_frame(reader))["params"]
                if seqs:
                    assert params["dropped"] == params["seq"] - seqs[-1] - 1
                seqs.append(params["seq"])
                dropped += params["dropped"]
        finally:
            writer.close()
    assert len(seqs) + dropped == published  # every message delivered, or reported dropped
    # Past the budget the outbox keeps one message, the newest: of the last 100, 99 dropped.
    assert dropped == 99 and seqs[-1] == published
    assert budget <= len(seqs) * FRAME <= budget + KERNEL + 2 * FRAME


async def test_wait_for_topic_is_woken_by_the_announcement(
    robot: Server, running: RunningServer
) -> None:
    async with client_of(running) as client:
        waiting = asyncio.create_task(client.wait_for_topic("/joint_states"))
        await client.call("/subtract", {"minuend": 1})  # the client is connected and reading
        assert not waiting.done()
        robot.topic("/joint_states", JointState)  # $/topics goes to every connection
        info = await waiting
        assert info.name == "/joint_states" and info.type == "sensor_msgs/msg/JointState"
        assert dict(client.topics) == {"/joint_states": "sensor_msgs/msg/JointState"}
        with pytest.raises(ServiceUnavailable) as caught:  # a topic that never comes
            await client.wait_for_topic("/never", timeout=scaled(0.2))
        assert caught.value.message == (f"the topic was not announced within {scaled(0.2):g} s")


async def test_topics_work_with_the_access_log_on(caplog: pytest.LogCaptureFixture) -> None:
    server = Server(access_log=True)
    server.add_service("/subtract", Subtract, subtract)
    pub = server.topic("/joint_states", JointState)
    transport = MemoryTransport()
    caplog.set_level(logging.INFO, logger="srvwire.access")
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, timeout=scaled(5)) as client:
            await client.wait_for_topic("/joint_states")
            async with client.subscribe("/joint_states") as sub:
                pub.publish(joints(1))
                assert (await sub.receive()).position == [1.0]
                await client.call("/subtract", {"minuend": 2})
    lines = [r.getMessage() for r in caplog.records if r.name == "srvwire.access"]
    assert any(" /subtract OK " in line for line in lines), lines


class Holding(Connection):
    """A connection that holds what is sent, as a transport holds what the peer has not read
    yet: ``buffered()`` says how many bytes; nothing arrives."""

    def __init__(self) -> None:
        self.remote_address = ("127.0.0.1", 1)
        self.identity = None
        self.sent: list[bytes] = []

    async def recv(self) -> str | bytes:
        raise TransportClosed(1000, "")

    async def send(self, message: str | bytes) -> None:
        self.sent.append(message if isinstance(message, bytes) else message.encode())

    def buffered(self) -> int:
        return sum(len(message) for message in self.sent)

    @property
    def congested(self) -> bool:
        return False

    async def writable(self) -> None:
        return None

    async def close(self, code: int = 1000, reason: str = "") -> None:
        return None

    @property
    def close_code(self) -> int | None:
        return None

    @property
    def close_reason(self) -> str:
        return ""


async def test_a_calls_reply_takes_its_room_from_the_best_effort_data_queued() -> None:
    """Replies are never refused: once a call's reply is queued, what topic data no longer
    fits in the connection's budget is given up, best effort's oldest first."""
    server = Server()
    lossy = server.topic("/lossy", String, qos={"depth": 100, "reliability": "best_effort"})

    async def at_once(request: Any) -> Any:
        return subtract(request)

    server.add_service("/subtract", Subtract, at_once)
    size = len(json.dumps({"data": "x" * 100}))
    conn = Holding()
    served = ServedConnection(
        conn,
        server.registry,
        max_in_flight=8,
        executor=None,
        logger=logging.getLogger("srvwire.test"),
        max_queued_bytes=40 * size,
    )
    reader = asyncio.current_task()
    assert reader is not None
    subscribe = {"jsonrpc": "2.0", "id": 1, "method": "$/subscribe", "params": {"topic": "/lossy"}}
    rest = served.handle(json.dumps(subscribe), reader)
    if rest is not None:
        await rest  # nothing to wait for: the loop does not turn
    subscription = served.outbox.subscriptions[1]
    for _ in range(20):  # in one turn: the writer has not run, all of it waits in the outbox
        lossy.publish({"data": "x" * 100})
    queued = served.outbox.queued
    assert queued > 15 * size and subscription.dropped == 0
    call = {"jsonrpc": "2.0", "id": 2, "method": "/subtract", "params": {"minuend": 5}}
    held = 30 * size - conn.buffered()  # the reply, with what is held, leaves 10 messages' room
    conn.sent.append(b" " * held)
    assert served.handle(json.dumps(call), reader) is None  # answered at once
    assert json.loads(conn.sent[-1])["result"] == {"difference": 5}
    assert served.outbox.queued <= 40 * size - conn.buffered()
    assert subscription.dropped > 0 and len(served.outbox.subscriptions) == 1
    served.writer.stop()


@pytest.mark.parametrize("transport", ["websockets", "picows"], indirect=True)
async def test_best_effort_subscriptions_that_give_up_their_data_all_end_with_the_connection(
    transport: Transport,
) -> None:
    # Two best-effort subscriptions hold a small message each when a message larger than the
    # connection's budget is published: the first gives up its message and the new one (the
    # other holds the room), the second keeps the large one. The writer goes on, and when the
    # peer leaves, both subscriptions leave the topic.
    server = Server(max_queued_bytes=64 * KIB)
    flood = server.topic("/flood", String, qos={"depth": 1, "reliability": "best_effort"})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        reader, writer = await stalled_subscriber(running.port, {})
        params = {"topic": "/flood"}
        writer.write(
            masked_text_frame(
                json.dumps({"jsonrpc": "2.0", "id": 2, "method": "$/subscribe", "params": params})
            )
        )
        while (await read_frame(reader)).get("method") != "$/subscribed":
            pass
        (served,) = running._connections
        flood.publish({"data": "small"})  # in one turn: both queue it, the writer has not run
        flood.publish({"data": "x" * 100_000})
        while len((await read_frame(reader))["params"]["message"]["data"]) < 100_000:
            pass
        flood.publish({"data": "last"})
        last: dict[int, str] = {}
        while sorted(last.items()) != [(1, "last"), (2, "last")]:
            message = (await read_frame(reader))["params"]
            last[message["subscription"]] = message["message"]["data"]
        handler = served.serving
        assert handler is not None
        writer.close()
        await asyncio.wait([handler])
        assert flood.subscription_count == 0 and not served.outbox.subscriptions
        assert not running._connections


async def test_a_writer_that_fails_inside_srvwire_is_logged_and_ends_the_connection(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def broken(self: Writer) -> Any:
        raise RuntimeError("a bug in the writer")

    server = Server()
    flood = server.topic("/flood", String)
    async with serve(server, "127.0.0.1", 0) as running:
        reader, writer = await stalled_subscriber(running.port, {})
        (served,) = running._connections
        handler = served.serving
        assert handler is not None
        monkeypatch.setattr(Writer, "next", broken)
        flood.publish({"data": "x"})
        head = await asyncio.wait_for(reader.readexactly(4), scaled(10))
        assert head[0] == 0x88 and int.from_bytes(head[2:4], "big") == 1011  # a close frame
        writer.close()
        await asyncio.wait([handler])
        assert flood.subscription_count == 0
    [record] = [r for r in caplog.records if "writer" in r.getMessage()]
    assert record.levelname == "ERROR" and "failed inside srvwire" in record.getMessage()
    assert record.exc_info is not None and "a bug in the writer" in str(record.exc_info[1])


@pytest.mark.parametrize("access_log", [False, True], ids=["plain", "access-logged"])
async def test_subscriptions_past_max_subscriptions_are_refused_resource_exhausted(
    transport: Transport, access_log: bool
) -> None:
    server = Server(max_subscriptions=2, access_log=access_log)
    server.add_service("/subtract", Subtract, subtract)
    pub = server.topic("/joint_states", JointState)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with client_of(running) as client:
            await client.wait_for_topic("/joint_states")
            first = await client.subscribe("/joint_states").start()
            await client.subscribe("/joint_states", qos={"depth": 1}).start()
            with pytest.raises(ResourceExhausted) as caught:
                await client.subscribe("/joint_states").start()
            assert caught.value.message == (
                "too many subscriptions on this connection (the limit is 2); end one with "
                "$/cancel first, or give the server a larger max_subscriptions"
            )
            assert caught.value.data == {"limit": 2}
            assert pub.subscription_count == 2
            await first.close()  # its $/cancel, read once a call sent after it is answered
            await client.call("/subtract", {"minuend": 1, "subtrahend": 1})
            assert pub.subscription_count == 1
            async with client_of(running) as other:  # the limit is per connection
                await other.wait_for_topic("/joint_states")
                await other.subscribe("/joint_states").start()
            third = await client.subscribe("/joint_states").start()
            assert third.active and pub.subscription_count == 2


def test_max_subscriptions_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="max_subscriptions must not be negative, not -1"):
        Server(max_subscriptions=-1)
