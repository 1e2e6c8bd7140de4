"""Actions: goals with feedback, cancellation and an outcome, on both transports."""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import AsyncIterator
from typing import Any

import pytest

from conftest import open_wire
from srvwire import GoalHandle, GoalRejected, load_action, load_service
from srvwire.actions import ClientGoal, GoalResult, GoalRunner, goal_service
from srvwire.auth import Identity, TokenAuth
from srvwire.client import Client, connect
from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InterfaceConflictError,
    PermissionDenied,
    RegistrationError,
    ServiceUnavailable,
)
from srvwire.goals import FeedbackOutbox, GoalNews, advance, feedback_notification, goal_news
from srvwire.inline import Pending, finish, first_step
from srvwire.models import ModelDecoder, build_action
from srvwire.parser import parse_action
from srvwire.server import RunningServer, Server, serve
from srvwire.serving import ServedConnection, Writer
from srvwire.threads import ConcurrencyLimit, HandlerThreads
from srvwire.topics import Outbox, QoS, Topic
from srvwire.transports.base import Transport
from srvwire.typeregistry import fingerprint, full_definition
from support import scaled

Fibonacci = load_action("example_interfaces/action/Fibonacci")


def fibonacci(order: int) -> list[int]:
    sequence = [0, 1]
    while len(sequence) < order + 1:
        sequence.append(sequence[-1] + sequence[-2])
    return sequence[: order + 1]


class Gate:
    """Things a handler waits for and tells, so that a test awaits instead of sleeping."""

    def __init__(self) -> None:
        self.started = asyncio.Event()
        self.release = asyncio.Event()
        self.ended = asyncio.Event()
        self.handles: list[GoalHandle] = []


@pytest.fixture
def gate() -> Gate:
    return Gate()


@pytest.fixture
async def server(gate: Gate) -> Server:
    server = Server(grace_period=scaled(2))

    @server.action("/fibonacci", Fibonacci)
    async def run(goal: Any, handle: GoalHandle) -> Any:
        """Feedback after each number; waits for the gate before the last when order < 0."""
        sequence = [0, 1]
        for _ in range(goal.order - 1):
            sequence.append(sequence[-1] + sequence[-2])
            await handle.feedback({"sequence": sequence})
        return Fibonacci.Result(sequence=sequence)

    @server.action("/waits", Fibonacci, cancel_grace=scaled(30))
    async def waits(goal: Any, handle: GoalHandle) -> Any:
        """Sends feedback, then waits for the gate or a cancellation; returns what it has."""
        gate.handles.append(handle)
        try:
            await handle.feedback({"sequence": [0]})
            gate.started.set()
            done = asyncio.ensure_future(gate.release.wait())
            cancelled = asyncio.ensure_future(handle.cancelled())
            await asyncio.wait({done, cancelled}, return_when=asyncio.FIRST_COMPLETED)
            done.cancel()
            cancelled.cancel()
            if goal.order == 1:  # done whatever happened: the result stands
                handle.succeed()
            return {"sequence": [0, 1]}
        finally:
            gate.ended.set()

    @server.action("/stubborn", Fibonacci, cancel_grace=scaled(0.05))
    async def stubborn(goal: Any, handle: GoalHandle) -> Any:
        """Ignores cancellation; only being cancelled ends it."""
        gate.handles.append(handle)
        gate.started.set()
        try:
            await asyncio.Event().wait()
        finally:
            gate.ended.set()

    @server.action("/swallows", Fibonacci, cancel_grace=scaled(0.05))
    async def swallows(goal: Any, handle: GoalHandle) -> Any:
        """Swallows its cancellation, then cleans up until the gate opens, and at last tries
        to report and return."""
        gate.handles.append(handle)
        gate.started.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            pass
        await gate.release.wait()
        await handle.feedback({"sequence": [7]})
        gate.ended.set()
        return {"sequence": [7]}

    add_ping(server)

    @server.action("/burst", Fibonacci)
    async def burst(goal: Any, handle: GoalHandle) -> Any:
        """Gives ``order`` feedback messages in one step, then waits for the gate."""
        for n in range(1, goal.order + 1):
            handle.publish_feedback({"sequence": [n]})
        await gate.release.wait()
        return {"sequence": [goal.order]}

    @server.action("/aborts", Fibonacci)
    async def aborts(goal: Any, handle: GoalHandle) -> Any:
        handle.abort()
        return {"sequence": [7]}

    @server.action("/picky", Fibonacci, accept=lambda goal: goal.order <= 10)
    async def picky(goal: Any, handle: GoalHandle) -> Any:
        if goal.order == 5:
            raise GoalRejected("five is not a goal I take")
        return {"sequence": fibonacci(goal.order)}

    @server.action("/threaded", Fibonacci)
    def threaded(goal: Any, handle: GoalHandle) -> Any:
        assert threading.current_thread() is not threading.main_thread()
        for n in range(1, goal.order + 1):
            handle.publish_feedback({"sequence": fibonacci(n)})
        return {"sequence": fibonacci(goal.order)}

    loop = asyncio.get_running_loop()

    @server.action("/steps", Fibonacci)
    def steps(goal: Any, handle: GoalHandle) -> Any:
        """A plain def handler: a step at a time until cancelled, feedback after each."""
        done: list[int] = []
        try:
            for n in range(10_000):
                handle.publish_feedback({"sequence": [n]})
                if handle.wait_for_cancel(0 if n else None):  # the first step waits for it
                    break
                done.append(n)
            return {"sequence": done}
        finally:
            loop.call_soon_threadsafe(gate.ended.set)

    return server


@pytest.fixture
async def running(server: Server, transport: Transport) -> AsyncIterator[RunningServer]:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        yield running


def connection(running: RunningServer) -> ServedConnection:
    (served,) = running._connections
    return served


def assert_nothing_left(served: ServedConnection) -> None:
    assert served.session.in_flight == 0
    assert not served.session.calls
    assert not served.counted
    assert len(served.writer.feedback) == 0


# --- the client's view ------------------------------------------------------------------------


async def test_a_goal_succeeds_with_typed_feedback_and_result(running: RunningServer) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        assert client.services["/fibonacci"] == "example_interfaces/action/Fibonacci"
        handle = await client.send_goal("/fibonacci", {"order": 6})
        assert handle.status in ("accepted", "executing")
        seen = [fb async for fb in handle.feedback()]
        assert all(isinstance(fb, Fibonacci.Feedback) for fb in seen)
        outcome = await handle.result()
        assert outcome == GoalResult("succeeded", Fibonacci.Result(sequence=fibonacci(6)))
        assert isinstance(outcome.result, Fibonacci.Result)
        assert handle.status == "succeeded"
        # Keep-latest: what was seen is in order, and may skip, but never repeats.
        assert [len(fb.sequence) for fb in seen] == sorted({len(fb.sequence) for fb in seen})
        assert not client._link.goals and not client._link.session.pending  # type: ignore[union-attr]


async def test_a_plain_def_handler_runs_on_a_thread_and_publishes_feedback(
    running: RunningServer,
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/threaded", {"order": 5})
        outcome = await handle.result()
        assert outcome.status == "succeeded"
        assert outcome.result.sequence == fibonacci(5)


async def test_a_plain_def_handler_stops_when_cancelled(running: RunningServer) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/steps", {"order": 1})
        first = await anext(handle.feedback())  # the handler is in its first step
        assert first.sequence == [0]
        assert await handle.cancel() is True
        outcome = await handle.result()
        assert outcome == GoalResult("canceled", Fibonacci.Result(sequence=[]))
        assert_nothing_left(connection(running))


async def test_a_plain_def_handler_is_told_to_stop_when_its_deadline_passes(
    running: RunningServer, gate: Gate
) -> None:
    wire = await open_wire(running)  # no client of ours to cancel it first: the deadline does
    params = {"order": 1, "_meta": {"timeout": scaled(0.3)}}
    await wire.send({"jsonrpc": "2.0", "id": 1, "method": "/steps", "params": params})
    reply = await wire.recv()
    while "id" not in reply:  # $/goal and $/feedback
        reply = await wire.recv()
    assert reply["error"]["data"]["status"] == "DEADLINE_EXCEEDED"
    await gate.ended.wait()  # its thread returned: wait_for_cancel woke when the goal ended
    assert_nothing_left(connection(running))
    await wire.ws.close()


async def test_an_aborted_goal_says_so_with_its_result(running: RunningServer) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/aborts", {"order": 3})
        assert await handle.result() == GoalResult("aborted", Fibonacci.Result(sequence=[7]))
        assert handle.status == "aborted"


async def test_a_refused_goal_raises_goal_rejected_with_the_reason(
    running: RunningServer,
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        with pytest.raises(GoalRejected) as refused:
            await client.send_goal("/picky", {"order": 11})
        assert str(refused.value) == "GOAL_REJECTED (-32007) [/picky]: /picky rejected the goal"
        # The handler may refuse too, after the goal was accepted: its result() says why.
        handle = await client.send_goal("/picky", {"order": 5})
        with pytest.raises(GoalRejected, match="five is not a goal I take"):
            await handle.result()
        assert handle.status == "aborted"
        ok = await client.send_goal("/picky", {"order": 4})
        assert (await ok.result()).status == "succeeded"
    assert_nothing_left_after(running)


def assert_nothing_left_after(running: RunningServer) -> None:
    for served in running._connections:
        assert_nothing_left(served)


async def test_a_cancelled_goal_returns_its_partial_result_as_canceled(
    running: RunningServer, gate: Gate
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/waits", {"order": 2})
        await gate.started.wait()
        assert await handle.cancel() is True
        outcome = await handle.result()
        assert outcome == GoalResult("canceled", Fibonacci.Result(sequence=[0, 1]))
        assert handle.status == "canceled"
        assert gate.handles[0].cancel_requested
        assert await handle.cancel() is False  # over: nothing to cancel
        assert_nothing_left(connection(running))


async def test_a_handler_that_ignores_cancellation_is_cancelled_after_its_grace(
    running: RunningServer, gate: Gate
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/stubborn", {"order": 2})
        await gate.started.wait()
        await handle.cancel()
        assert await handle.result() == GoalResult("canceled", Fibonacci.Result())
        await gate.ended.wait()
        assert_nothing_left(connection(running))


async def test_a_result_that_arrives_as_the_client_cancels_is_delivered(
    running: RunningServer, gate: Gate
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        # order 1: the handler declares success whatever happens once released, so which of
        # the result and the cancellation reaches the other side first does not matter.
        handle = await client.send_goal("/waits", {"order": 1})
        await gate.started.wait()
        gate.release.set()
        await handle.cancel()
        assert await handle.result() == GoalResult("succeeded", Fibonacci.Result(sequence=[0, 1]))
        assert handle.status == "succeeded"


async def test_a_cancel_after_the_result_arrived_changes_nothing(
    running: RunningServer, gate: Gate
) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/waits", {"order": 2})
        await gate.started.wait()
        gate.release.set()
        await asyncio.wait({handle.reply})  # the outcome is here, not read yet
        assert await handle.cancel() is False
        assert await handle.result() == GoalResult("succeeded", Fibonacci.Result(sequence=[0, 1]))


async def test_the_deadline_ends_a_goal_on_both_sides(running: RunningServer, gate: Gate) -> None:
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        handle = await client.send_goal("/stubborn", {"order": 2}, timeout=scaled(0.2))
        with pytest.raises(DeadlineExceeded):
            await handle.result()
        assert handle.status == "aborted"
        await gate.ended.wait()  # the server cancelled the handler too
        served = connection(running)
        assert_nothing_left(served)
        assert not client._link.goals and not client._link.session.pending  # type: ignore[union-attr]


async def test_a_lost_connection_ends_the_goal_on_both_sides(
    running: RunningServer, gate: Gate
) -> None:
    client = await connect(running.url, transport=running.transport, timeout=scaled(5))
    handle = await client.send_goal("/stubborn", {"order": 2})
    await gate.started.wait()
    served = connection(running)
    await served.conn.close(1001, "going away")
    with pytest.raises(ConnectionLost) as lost:
        await handle.result()
    assert lost.value.service == "/stubborn"  # named as a call's error names its service
    assert str(lost.value).startswith("UNAVAILABLE (-32003) [/stubborn]: ")
    assert handle.status == "aborted"
    await gate.ended.wait()
    await asyncio.wait({served.reading})
    assert_nothing_left(served)
    await client.close()


async def test_actions_obey_scopes(transport: Transport) -> None:
    server = Server(auth=TokenAuth({"op": Identity("operator", {"robot:move"}), "guest": "guest"}))
    server.add_action("/move", Fibonacci, lambda goal, handle: None, scopes={"robot:move"})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, token="guest") as client:
            assert "/move" not in client.services
            with pytest.raises(PermissionDenied):
                await client.send_goal("/move", {"order": 1}, action_type=Fibonacci)
        async with connect(running.url, transport=transport, token="op") as client:
            outcome = await (await client.send_goal("/move", {"order": 1})).result()
            assert outcome == GoalResult("succeeded", Fibonacci.Result())


async def test_an_action_type_the_client_does_not_have_comes_from_the_description(
    transport: Transport,
) -> None:
    text = "int32 steps\n---\nbool done\n---\nfloat32 progress\n"
    Spin = build_action(parse_action(text, "srvwire_action_tests", "Spin"))
    server = Server()

    @server.action("/spin", Spin)
    async def spin(goal: Any, handle: GoalHandle) -> Any:
        await handle.feedback(Spin.Feedback(progress=0.5))
        return {"done": True}

    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        (described,) = [m for m in await client._discover(None) if m["name"] == "/spin"]
        assert described["x-srvwire-kind"] == "action"
        assert described["x-srvwire-definitions"] == {"srvwire_action_tests/action/Spin": text}
        assert described["x-srvwire-feedback-schema"]["properties"]["progress"]["type"] == (
            "number"
        )
        handle = await client.send_goal("/spin", {"steps": 2})
        outcome = await handle.result()
        assert outcome.status == "succeeded" and outcome.result.done is True


async def test_a_local_action_type_is_checked_against_the_servers_fingerprint(
    transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = "int32 turns\n---\nbool done\n---\nfloat32 progress\n"
    Turn = build_action(parse_action(text, "srvwire_fp_actions", "Turn"))
    # The same definition in other words (comments); and another one.
    Same = build_action(parse_action("# How many.\n" + text, "srvwire_fp_actions", "Turn"))
    Other = build_action(parse_action(text.replace("int32", "int64"), "srvwire_fp_actions", "Turn"))
    server = Server()

    @server.action("/turn", Turn)
    async def turn(goal: Any, handle: GoalHandle) -> Any:
        return {"done": True}

    asked: list[str] = []
    methods = Client._methods

    async def counted(self: Client, *args: Any) -> Any:
        asked.append(self.url)
        return await methods(self, *args)

    monkeypatch.setattr(Client, "_methods", counted)
    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        assert client._link is not None
        assert client._link.fingerprints == {"/turn": fingerprint(full_definition(Turn) or {})}
        handle = await client.send_goal("/turn", {"turns": 1}, action_type=Same)
        assert (await handle.result()).status == "succeeded"
        assert asked == [] and client._link.verified == {
            ("/turn", goal_service(Same))
        }  # no description asked for
    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        with pytest.raises(InterfaceConflictError) as caught:
            await client.send_goal("/turn", {"turns": 1}, action_type=Other)
        assert asked == [running.url]  # the description, asked for only to say what differs
        assert server.registry.get("/turn") is not None
        assert not connection(running).session.calls  # nothing was sent
    assert str(caught.value) == (
        "two different definitions of srvwire_fp_actions/action/Turn: the local class and "
        f"server {running.url} (declaration 1: 'int64 turns' against 'int32 turns'); "
        "a type name has one definition per process"
    )


# --- the wire ---------------------------------------------------------------------------------


async def test_on_the_wire_a_goal_is_one_call_with_notifications_between(
    running: RunningServer, gate: Gate
) -> None:
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": 9, "method": "/waits", "params": {"order": 2}})
    accepted = await wire.recv()
    assert accepted["method"] == "$/goal"
    goal_id = accepted["params"]["goal_id"]
    assert accepted["params"] == {"call": 9, "goal_id": goal_id, "status": "accepted"}
    assert len(goal_id) == 36  # a UUID
    executing = await wire.recv()
    assert executing["params"] == {"call": 9, "goal_id": goal_id, "status": "executing"}
    feedback = await wire.recv()
    assert feedback == {
        "jsonrpc": "2.0",
        "method": "$/feedback",
        "params": {"call": 9, "seq": 1, "feedback": {"sequence": [0]}},
    }
    gate.release.set()
    assert await wire.recv() == {
        "jsonrpc": "2.0",
        "id": 9,
        "result": {"status": "succeeded", "result": {"sequence": [0, 1]}},
    }
    await wire.ws.close()


async def test_feedback_faster_than_the_connection_is_kept_latest(
    running: RunningServer, gate: Gate
) -> None:
    # The handler gives 30 feedback messages in one step: only the last one goes out.
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": 1, "method": "/burst", "params": {"order": 30}})
    assert [(await wire.recv())["params"]["status"] for _ in range(2)] == [
        "accepted",
        "executing",
    ]
    feedback = await wire.recv()
    assert feedback["params"] == {"call": 1, "seq": 30, "feedback": {"sequence": [30]}}
    served = connection(running)
    assert served.writer.feedback.replaced == 29 and len(served.writer.feedback) == 0
    gate.release.set()
    assert (await wire.recv())["result"] == {"status": "succeeded", "result": {"sequence": [30]}}
    assert_nothing_left(served)
    await wire.ws.close()


@pytest.mark.parametrize("transport", ["memory"], indirect=True)
async def test_a_client_that_does_not_read_costs_one_feedback_message(
    transport: Transport,
) -> None:
    # On the memory transport the budget is all the buffer there is (a real socket adds the
    # kernel's, which srvwire does not count): what reaches the client is what fit in it.
    server = Server(max_queued_bytes=4_000, grace_period=0)
    published = asyncio.Event()
    loop = asyncio.get_running_loop()
    count, size = 2_000, 200

    @server.action("/flood", Fibonacci)
    def flood(goal: Any, handle: GoalHandle) -> Any:
        for n in range(count):
            handle.publish_feedback({"sequence": [n] * size})
        loop.call_soon_threadsafe(published.set)
        assert handle.wait_for_cancel()  # until the client has seen the flood
        return {"sequence": [count]}

    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        wire = await open_wire(running)
        await wire.send({"jsonrpc": "2.0", "id": 1, "method": "/flood", "params": {}})
        await published.wait()  # every feedback was given, and the client read none
        served = connection(running)
        assert len(served.writer.feedback) <= 1  # at most the latest waits, whatever was given
        await wire.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 1}})
        messages = []
        while not messages or messages[-1].get("id") != 1:
            messages.append(await wire.recv())
        seqs = [m["params"]["seq"] for m in messages if m.get("method") == "$/feedback"]
        assert seqs == sorted(seqs) and len(seqs) < 4_000 / size + 3  # what fit, and no more
        assert served.writer.feedback.replaced >= count - len(seqs) - 1
        assert messages[-1]["result"]["status"] == "canceled"
        assert_nothing_left(served)
        await wire.ws.close()


def test_the_writer_sends_control_first_then_topic_data_and_feedback_in_turn() -> None:
    loop = asyncio.new_event_loop()
    try:
        writer = Writer(None, loop)  # type: ignore[arg-type]  # nothing is sent here
        writer.outbox = Outbox()  # no wake: the writer's task is not started
        topic: Topic[None] = Topic("/t", None, QoS(depth=5))
        writer.outbox.subscribe(7, topic, QoS(depth=5))
        control = writer.outbox.next()  # $/subscribed
        assert control is not None and b"$/subscribed" in control
        writer.feedback.put(1, b"f1")
        writer.feedback.put(2, b"f2")
        topic.publish(b"{}")
        topic.publish(b"{}")
        writer.outbox.push(b"reply")
        order = []
        while (taken := writer.next()) is not None:
            data, goal = taken
            order.append(goal if goal is not None else data[:12])
        message = b'{"jsonrpc":"'  # a topic's $/message
        assert order == [b"reply", 1, message, 2, message]  # data in turn, behind control
    finally:
        loop.close()


async def test_a_cancel_on_the_wire_asks_the_goal_to_stop(
    running: RunningServer, gate: Gate
) -> None:
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": "g", "method": "/waits", "params": {"order": 2}})
    await gate.started.wait()
    await wire.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": "g"}})
    received = []
    while not received or received[-1].get("id") != "g":
        received.append(await wire.recv())
    states = [m["params"]["status"] for m in received if m.get("method") == "$/goal"]
    assert states == ["accepted", "executing", "canceling"]
    assert received[-1]["result"] == {"status": "canceled", "result": {"sequence": [0, 1]}}
    await wire.ws.close()


@pytest.mark.parametrize("ended_by", ["cancel", "deadline"])
async def test_a_goal_that_ignores_its_cancellation_is_answered_when_its_grace_or_deadline_ends(
    running: RunningServer, gate: Gate, ended_by: str
) -> None:
    wire = await open_wire(running)
    params: dict[str, Any] = {"order": 1}
    if ended_by == "deadline":
        params["_meta"] = {"timeout": scaled(0.1)}
    await wire.send({"jsonrpc": "2.0", "id": "g", "method": "/swallows", "params": params})
    await gate.started.wait()
    if ended_by == "cancel":
        await wire.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": "g"}})
    received = []
    while not received or received[-1].get("id") != "g":
        received.append(await wire.recv())
    states = [m["params"]["status"] for m in received if m.get("method") == "$/goal"]
    if ended_by == "cancel":  # asked, and cut when its cancel_grace passed
        assert states == ["accepted", "executing", "canceling"]
        assert received[-1]["error"]["code"] == -32002
        assert received[-1]["error"]["data"]["status"] == "CANCELLED"
    else:
        assert states == ["accepted", "executing"]
        assert received[-1]["error"]["code"] == -32001
        assert received[-1]["error"]["data"]["status"] == "DEADLINE_EXCEEDED"
    assert not gate.ended.is_set()  # answered while its handler still runs
    gate.release.set()
    await gate.ended.wait()
    # What it reports and returns after its answer is never sent: the next message is the reply
    # to the next call.
    ping = {"jsonrpc": "2.0", "id": "p", "method": "/ping"}
    assert await wire.call(ping) == {
        "jsonrpc": "2.0",
        "id": "p",
        "result": {"success": True, "message": ""},
    }
    assert_nothing_left(connection(running))
    await wire.ws.close()


async def test_a_refused_goal_on_the_wire_is_an_error_reply(running: RunningServer) -> None:
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": 3, "method": "/picky", "params": {"order": 99}})
    reply = await wire.recv()
    assert reply["error"]["code"] == -32007
    assert reply["error"]["message"] == "/picky rejected the goal"
    assert reply["error"]["data"]["status"] == "GOAL_REJECTED"
    await wire.ws.close()


# --- the rules, without I/O -------------------------------------------------------------------


def test_the_outbox_keeps_the_latest_feedback_per_goal_round_robin() -> None:
    outbox = FeedbackOutbox()
    assert outbox.put(1, b"a1") is True
    assert outbox.put(2, b"b1") is False
    assert outbox.put(1, b"a2") is False  # replaces a1, keeps goal 1's turn
    assert outbox.replaced == 1 and len(outbox) == 2
    assert 1 in outbox and 3 not in outbox
    assert outbox.take() == (1, b"a2")
    outbox.put(1, b"a3")  # goal 1 had its turn: behind goal 2 now
    assert outbox.take() == (2, b"b1")
    outbox.discard(1)
    assert outbox.take() is None and len(outbox) == 0


def test_a_goal_state_never_steps_back() -> None:
    assert advance("pending", "accepted") == "accepted"
    assert advance("canceling", "executing") == "canceling"
    assert advance("executing", "canceling") == "canceling"
    assert advance("canceling", "succeeded") == "succeeded"
    assert advance("succeeded", "executing") == "succeeded"
    assert advance("executing", "sleeping") == "executing"


async def test_a_slow_reader_of_feedback_sees_the_latest_never_a_queue() -> None:
    loop = asyncio.get_running_loop()

    class Link:
        def __init__(self) -> None:
            self.loop = loop

    service = goal_service(Fibonacci)
    goal: ClientGoal[Any] = ClientGoal(
        Link(),  # type: ignore[arg-type]
        "/fibonacci",
        Fibonacci,
        ModelDecoder(service.Response),
        loop.time() + 5,
        5,
    )
    for n in range(1, 51):
        goal.news(GoalNews(1, seq=n, feedback={"sequence": list(range(n))}))
    reader = goal.feedback()
    first = await anext(reader)
    assert first.sequence == list(range(50))
    goal.reply.set_result(None)  # ended: the iteration stops
    with pytest.raises(StopAsyncIteration):
        await anext(reader)


def test_goal_news_is_read_or_refused() -> None:
    assert goal_news("$/goal", {"call": 4, "goal_id": "g", "status": "executing"}) == GoalNews(
        4, status="executing", goal_id="g"
    )
    assert goal_news("$/feedback", {"call": 4, "seq": 2, "feedback": {"a": 1}}) == GoalNews(
        4, seq=2, feedback={"a": 1}
    )
    for method, params in [
        ("$/goal", {"call": "4", "goal_id": "g", "status": "executing"}),  # not our id
        ("$/goal", {"call": 4, "status": "executing"}),
        ("$/feedback", {"call": 4, "seq": True, "feedback": {}}),
        ("$/feedback", {"call": 4, "seq": 1}),
        ("$/feedback", [4, 1, {}]),
    ]:
        assert goal_news(method, params) is None, params


async def test_a_goal_sent_as_a_notification_is_refused_and_logged(
    running: RunningServer, gate: Gate, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("INFO", logger="srvwire.server")
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "method": "/waits", "params": {"order": 2}})
    await wire.send({"jsonrpc": "2.0", "id": 2, "method": "/aborts", "params": {"order": 1}})
    assert (await wire.recv())["params"]["status"] == "accepted"  # the request's, id 2
    assert not gate.handles  # the notification's handler never ran
    assert any(
        "a goal for the action /waits must be a request with an id" in m for m in caplog.messages
    )
    await wire.ws.close()


def test_feedback_is_written_around_the_message_bytes() -> None:
    assert feedback_notification(7, 3, b'{"x":1}') == (
        b'{"jsonrpc":"2.0","method":"$/feedback","params":{"call":7,"seq":3,"feedback":{"x":1}}}'
    )


def test_the_startup_line_counts_services_and_actions_apart() -> None:
    server = Server()
    assert server.summary() == "0 services"
    server.add_action("/a", Fibonacci, lambda goal, handle: None)
    assert server.summary() == "0 services and 1 action"
    server.add_service("/s", load_service("std_srvs/srv/Trigger"), lambda request: None)
    server.add_action("/b", Fibonacci, lambda goal, handle: None)
    assert server.summary() == "1 service and 2 actions"


def test_an_action_type_is_not_a_service_type() -> None:
    server = Server()
    with pytest.raises(RegistrationError, match=r"is an action type; serve it with server\.action"):
        server.add_service("/fibonacci", Fibonacci, lambda request: None)  # type: ignore[arg-type]
    service = load_action("example_interfaces/action/Fibonacci")
    with pytest.raises(RegistrationError, match="must be an action type"):
        server.add_action("/x", service.Goal, lambda goal, handle: None)  # type: ignore[arg-type]


# --- max_concurrency: goals wait for a slot, as a service's calls do ----------------------------

Trigger = load_service("std_srvs/srv/Trigger")


def add_ping(server: Server) -> None:
    """A service to make a round trip with: its reply comes after every message sent before."""
    server.add_service("/ping", Trigger, lambda request: {"success": True})


async def round_trip(client: Client) -> None:
    """Once it returns, the server has read every goal sent before, and run each up to its
    first wait (a goal runs on the reader until it has to wait)."""
    assert (await client.call("/ping", {})).success


def limit_of(server: Server, name: str) -> ConcurrencyLimit:
    entry = server.registry.get(name)
    assert entry is not None and isinstance(entry.handler, GoalRunner)
    assert entry.handler.limit is not None
    return entry.handler.limit


async def test_an_async_actions_max_concurrency_bounds_its_handlers_over_all_connections(
    transport: Transport,
) -> None:
    server = Server()
    add_ping(server)
    release = asyncio.Event()
    both_run = asyncio.Event()
    running_now: list[int] = []
    peak = 0

    @server.action("/limited", Fibonacci, max_concurrency=2)
    async def limited(goal: Any, handle: GoalHandle) -> Any:
        nonlocal peak
        running_now.append(goal.order)
        peak = max(peak, len(running_now))
        if len(running_now) == 2:
            both_run.set()
        try:
            await release.wait()
        finally:
            running_now.remove(goal.order)
        return {"sequence": [goal.order]}

    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        url, how = running.url, running.transport
        async with (
            connect(url, transport=how, timeout=scaled(10)) as one,
            connect(url, transport=how, timeout=scaled(10)) as two,
        ):
            first = [await one.send_goal("/limited", {"order": n}) for n in (1, 2)]
            await both_run.wait()
            later = [
                await two.send_goal("/limited", {"order": 3}),
                await one.send_goal("/limited", {"order": 4}),
            ]
            await round_trip(one)
            await round_trip(two)
            limit = limit_of(server, "/limited")
            assert (limit.running, limit.waiting) == (2, 2)
            assert [h.status for h in later] == ["accepted", "accepted"]  # not executing yet
            assert running_now == [1, 2]
            release.set()
            outcomes = [await h.result() for h in (*first, *later)]
            assert outcomes == [
                GoalResult("succeeded", Fibonacci.Result(sequence=[n])) for n in (1, 2, 3, 4)
            ]
            assert peak == 2
            assert (limit.running, limit.waiting) == (0, 0)
            assert_nothing_left_after(running)


async def test_a_goal_waiting_for_a_slot_ends_on_cancel_and_deadline_without_running(
    transport: Transport,
) -> None:
    server = Server()
    add_ping(server)
    release = asyncio.Event()
    started: list[int] = []

    # A long cancel_grace: a goal cancelled as it waits must end at once, not be cut later.
    @server.action("/one_at_a_time", Fibonacci, max_concurrency=1, cancel_grace=scaled(60))
    async def one_at_a_time(goal: Any, handle: GoalHandle) -> Any:
        started.append(goal.order)
        await release.wait()
        return {"sequence": [goal.order]}

    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=running.transport, timeout=scaled(10)) as client,
    ):
        busy = await client.send_goal("/one_at_a_time", {"order": 1})
        cancelled = await client.send_goal("/one_at_a_time", {"order": 2})
        await round_trip(client)
        assert cancelled.status == "accepted"
        assert await cancelled.cancel() is True
        # Canceled before it ran: the outcome is the result's defaults, sent by the server.
        assert await cancelled.result() == GoalResult("canceled", Fibonacci.Result())
        # The server's deadline, with no client of ours to give up first.
        wire = await open_wire(running)
        params = {"order": 3, "_meta": {"timeout": scaled(0.3)}}
        await wire.send(
            {"jsonrpc": "2.0", "id": "late", "method": "/one_at_a_time", "params": params}
        )
        received = [await wire.recv()]
        while received[-1].get("id") != "late":
            received.append(await wire.recv())
        states = [m["params"]["status"] for m in received if m.get("method") == "$/goal"]
        assert states == ["accepted"]
        assert received[-1]["error"]["data"]["status"] == "DEADLINE_EXCEEDED"
        limit = limit_of(server, "/one_at_a_time")
        assert (limit.running, limit.waiting) == (1, 0)
        release.set()
        assert (await busy.result()).status == "succeeded"
        assert started == [1]
        assert (limit.running, limit.waiting) == (0, 0)
        assert_nothing_left_after(running)
        await wire.ws.close()


async def test_a_plain_def_actions_slot_is_held_until_its_thread_returns(
    transport: Transport,
) -> None:
    server = Server()
    add_ping(server)
    loop = asyncio.get_running_loop()
    unblock = threading.Event()
    lock = threading.Lock()
    started: list[int] = []
    first_started = asyncio.Event()
    now = peak = 0

    @server.action("/device", Fibonacci, max_concurrency=1, cancel_grace=scaled(0.05))
    def device(goal: Any, handle: GoalHandle) -> Any:
        """Ignores its cancellation: only ``unblock`` ends it."""
        nonlocal now, peak
        with lock:
            now += 1
            peak = max(peak, now)
            started.append(goal.order)
        loop.call_soon_threadsafe(first_started.set)
        try:
            unblock.wait(scaled(30))
        finally:
            with lock:
                now -= 1
        return {"sequence": [goal.order]}

    try:
        async with (
            serve(server, "127.0.0.1", 0, transport=transport) as running,
            connect(running.url, transport=running.transport, timeout=scaled(10)) as client,
        ):
            first = await client.send_goal("/device", {"order": 1})
            await first_started.wait()
            second = await client.send_goal("/device", {"order": 2})
            await first.cancel()
            # Cut off after its grace period: the client hears CANCELLED, reported as canceled.
            assert await first.result() == GoalResult("canceled", Fibonacci.Result())
            await round_trip(client)
            # Its thread still runs, and still holds the one slot: the second goal waits.
            limit = limit_of(server, "/device")
            assert (limit.running, limit.waiting) == (1, 1)
            assert second.status == "accepted"
            assert started == [1]
            assert isinstance(server.executor, HandlerThreads)
            assert server.executor.busy() == [device.__qualname__]
            unblock.set()
            assert await second.result() == GoalResult("succeeded", Fibonacci.Result(sequence=[2]))
            assert started == [1, 2]
            assert peak == 1
            assert (limit.running, limit.waiting) == (0, 0)
            assert_nothing_left_after(running)
    finally:
        unblock.set()


async def test_a_plain_def_goal_that_ends_before_a_thread_takes_it_never_runs(
    transport: Transport,
) -> None:
    # One thread, held by a blocking service whose caller waits: the goal queues for it.
    server = Server(executor=HandlerThreads(max_workers=1))
    loop = asyncio.get_running_loop()
    hogging = asyncio.Event()
    unblock = threading.Event()
    ran: list[int] = []

    def hog(request: Any) -> Any:
        loop.call_soon_threadsafe(hogging.set)
        unblock.wait(scaled(30))
        return {"success": True}

    server.add_service("/hog", Trigger, hog)

    @server.action("/queued", Fibonacci, max_concurrency=1)
    def queued(goal: Any, handle: GoalHandle) -> Any:
        ran.append(goal.order)
        return {"sequence": [goal.order]}

    try:
        async with (
            serve(server, "127.0.0.1", 0, transport=transport) as running,
            connect(running.url, transport=running.transport, timeout=scaled(10)) as client,
        ):
            hogged = asyncio.create_task(client.call("/hog", {}))
            await hogging.wait()
            late = await client.send_goal("/queued", {"order": 1}, timeout=scaled(0.2))
            with pytest.raises(DeadlineExceeded):
                await late.result()
            # The goal left before a thread took it: it gave its slot back, so the next one
            # gets it (were the slot lost, this goal would wait past its deadline).
            next_goal = await client.send_goal("/queued", {"order": 2})
            unblock.set()
            assert (await hogged).success
            assert await next_goal.result() == GoalResult(
                "succeeded", Fibonacci.Result(sequence=[2])
            )
            assert ran == [2]  # the first goal's handler never ran
            limit = limit_of(server, "/queued")
            assert (limit.running, limit.waiting) == (0, 0)
            assert_nothing_left_after(running)
    finally:
        unblock.set()


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2"])
def test_an_actions_max_concurrency_is_a_whole_number_at_least_one(bad: Any) -> None:
    server = Server()
    with pytest.raises(RegistrationError) as refused:
        server.add_action("/a", Fibonacci, lambda goal, handle: None, max_concurrency=bad)
    assert str(refused.value) == (
        f"max_concurrency for /a must be a whole number at least 1, not {bad!r}"
    )


# --- shutdown: running goals are asked to stop, then cut after the grace period ----------------


class Shutdown:
    """A server whose actions meet a shutdown: two that honour the request to stop (``async``
    and plain ``def``), two that ignore it, and one that takes a goal at a time."""

    def __init__(self, grace_period: float) -> None:
        self.server = server = Server(grace_period=grace_period)
        add_ping(server)
        loop = asyncio.get_running_loop()
        self.started: dict[str, asyncio.Event] = {}
        self.ended: dict[str, asyncio.Event] = {}
        self.handles: dict[str, GoalHandle] = {}
        self.unblock = threading.Event()  # what ends the deaf thread
        for name in ("/polite", "/polite_thread", "/deaf", "/deaf_thread", "/single"):
            self.started[name] = asyncio.Event()
            self.ended[name] = asyncio.Event()
        orders: list[int] = []
        self.orders = orders

        def begin(name: str, handle: GoalHandle) -> None:
            self.handles[name] = handle
            loop.call_soon_threadsafe(self.started[name].set)

        def end(name: str) -> None:
            loop.call_soon_threadsafe(self.ended[name].set)

        @server.action("/polite", Fibonacci, cancel_grace=scaled(60))
        async def polite(goal: Any, handle: GoalHandle) -> Any:
            """Works until asked to stop, then says where it got to, and returns that."""
            begin("/polite", handle)
            try:
                await handle.feedback({"sequence": [0]})
                await handle.cancelled()
                await handle.feedback({"sequence": [0, 1]})  # a last word
                return {"sequence": [0, 1]}
            finally:
                end("/polite")

        @server.action("/polite_thread", Fibonacci, cancel_grace=scaled(60))
        def polite_thread(goal: Any, handle: GoalHandle) -> Any:
            begin("/polite_thread", handle)
            try:
                steps = [0]
                handle.publish_feedback({"sequence": steps})
                while not handle.wait_for_cancel(scaled(30)):
                    steps.append(len(steps))  # never reached: the backstop of a hang
                handle.publish_feedback({"sequence": [*steps, 1]})
                return {"sequence": [*steps, 1]}
            finally:
                end("/polite_thread")

        @server.action("/deaf", Fibonacci, cancel_grace=scaled(60))
        async def deaf(goal: Any, handle: GoalHandle) -> Any:
            begin("/deaf", handle)
            try:
                await asyncio.Event().wait()  # only being cancelled ends it
            finally:
                end("/deaf")

        @server.action("/deaf_thread", Fibonacci, cancel_grace=scaled(60))
        def deaf_thread(goal: Any, handle: GoalHandle) -> Any:
            begin("/deaf_thread", handle)
            try:
                self.unblock.wait(scaled(30))
                return {"sequence": [1]}
            finally:
                end("/deaf_thread")

        @server.action("/single", Fibonacci, max_concurrency=1, cancel_grace=scaled(60))
        async def single(goal: Any, handle: GoalHandle) -> Any:
            orders.append(goal.order)
            begin("/single", handle)
            await handle.cancelled()
            return {"sequence": [goal.order]}


async def test_shutdown_asks_a_goal_to_stop_and_its_result_reaches_the_client(
    transport: Transport,
) -> None:
    shutdown = Shutdown(grace_period=scaled(20))  # a goal that did not stop would take it all
    running = await serve(shutdown.server, "127.0.0.1", 0, transport=transport)
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": "g", "method": "/polite", "params": {"order": 2}})
    await shutdown.started["/polite"].wait()
    served = connection(running)
    closing = asyncio.create_task(running.close())
    received = [await wire.recv()]
    while received[-1].get("id") != "g":
        received.append(await wire.recv())
    said = [
        m["params"].get("status") or m["params"]["feedback"] if "method" in m else m["result"]
        for m in received
    ]
    assert said == [
        "accepted",
        "executing",
        {"sequence": [0]},
        "canceling",  # asked as a client's cancellation asks, before the handler woke
        {"sequence": [0, 1]},  # its last word
        {"status": "canceled", "result": {"sequence": [0, 1]}},
    ]
    assert shutdown.handles["/polite"].cancel_requested
    await closing
    assert_nothing_left(served)


async def test_shutdown_asks_a_plain_def_goal_and_the_client_gets_its_result(
    transport: Transport,
) -> None:
    shutdown = Shutdown(grace_period=scaled(20))
    running = await serve(shutdown.server, "127.0.0.1", 0, transport=transport)
    client = await connect(running.url, transport=running.transport, timeout=scaled(10))
    handle = await client.send_goal("/polite_thread", {"order": 2})
    await shutdown.started["/polite_thread"].wait()
    served = connection(running)
    closing = asyncio.create_task(running.close())
    outcome = await handle.result()
    assert outcome == GoalResult("canceled", Fibonacci.Result(sequence=[0, 1]))
    assert handle.status == "canceled"
    await closing
    await shutdown.ended["/polite_thread"].wait()
    assert_nothing_left(served)
    await client.close()


async def test_goals_that_ignore_shutdown_are_cut_after_the_grace_period(
    transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("WARNING", logger="srvwire.server")
    shutdown = Shutdown(grace_period=scaled(0.2))
    running = await serve(shutdown.server, "127.0.0.1", 0, transport=transport)
    client = await connect(running.url, transport=running.transport, timeout=scaled(10))
    try:
        deaf = await client.send_goal("/deaf", {"order": 1})
        deaf_thread = await client.send_goal("/deaf_thread", {"order": 1})
        await shutdown.started["/deaf"].wait()
        await shutdown.started["/deaf_thread"].wait()
        served = connection(running)
        closing = asyncio.create_task(running.close())
        for handle in (deaf, deaf_thread):
            with pytest.raises(ServiceUnavailable) as cut:
                await handle.result()
            assert "the server shut down before the call finished" in str(cut.value)
            assert handle.status == "aborted"
        # Both were asked first, as a client's cancellation asks.
        assert shutdown.handles["/deaf"].cancel_requested
        assert shutdown.handles["/deaf_thread"].cancel_requested
        await closing
        await shutdown.ended["/deaf"].wait()  # the async handler was cancelled
        assert_nothing_left(served)
        assert "cancelling 2 calls still running after the" in caplog.text
        assert "leaving 1 blocking handler running in its thread: " in caplog.text
    finally:
        shutdown.unblock.set()
        await client.close()
    await shutdown.ended["/deaf_thread"].wait()


async def test_shutdown_ends_a_goal_waiting_for_a_slot_without_running_it(
    transport: Transport,
) -> None:
    shutdown = Shutdown(grace_period=scaled(20))
    running = await serve(shutdown.server, "127.0.0.1", 0, transport=transport)
    client = await connect(running.url, transport=running.transport, timeout=scaled(10))
    first = await client.send_goal("/single", {"order": 1})
    await shutdown.started["/single"].wait()
    second = await client.send_goal("/single", {"order": 2})
    await round_trip(client)
    assert second.status == "accepted"
    served = connection(running)
    closing = asyncio.create_task(running.close())
    assert await first.result() == GoalResult("canceled", Fibonacci.Result(sequence=[1]))
    assert await second.result() == GoalResult("canceled", Fibonacci.Result())
    await closing
    assert shutdown.orders == [1]
    limit = limit_of(shutdown.server, "/single")
    assert (limit.running, limit.waiting) == (0, 0)
    assert_nothing_left(served)
    await client.close()


@pytest.mark.parametrize("transport", ["memory"], indirect=True)
async def test_a_connection_that_does_not_read_holds_up_no_other_goals_request_to_stop(
    transport: Transport,
) -> None:
    # On the memory transport the budget is all the buffer there is: one message past it
    # leaves the connection congested until its client reads.
    server = Server(max_queued_bytes=4_000, grace_period=scaled(20))
    started = [asyncio.Event(), asyncio.Event()]

    @server.action("/polite", Fibonacci)
    async def polite(goal: Any, handle: GoalHandle) -> Any:
        await handle.feedback({"sequence": [0]})
        started[goal.order].set()
        await handle.cancelled()
        return {"sequence": [goal.order]}

    running = await serve(server, "127.0.0.1", 0, transport=transport)
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": "a", "method": "/polite", "params": {"order": 0}})
    await started[0].wait()
    stuck = connection(running)
    filler = {"jsonrpc": "2.0", "method": "$/filler", "params": {"x": "x" * 20_000}}
    pressing = asyncio.create_task(stuck.conn.send(json.dumps(filler)))  # read by nobody
    client = await connect(running.url, transport=running.transport, timeout=scaled(10))
    handle = await client.send_goal("/polite", {"order": 1})
    await started[1].wait()
    assert stuck.conn.congested
    closing = asyncio.create_task(running.close())
    # Asked at once, although the first connection's request to stop cannot be sent yet.
    assert await handle.result() == GoalResult("canceled", Fibonacci.Result(sequence=[1]))
    received = [await wire.recv()]
    while received[-1].get("id") != "a":
        received.append(await wire.recv())
    said = [m.get("params", {}).get("status") or m.get("result") for m in received]
    assert said[-2:] == ["canceling", {"status": "canceled", "result": {"sequence": [0]}}]
    await pressing
    await closing
    await client.close()


@pytest.mark.parametrize("transport", ["memory"], indirect=True)
async def test_every_goal_of_a_connection_that_does_not_read_is_asked_to_stop_at_once(
    transport: Transport,
) -> None:
    # The first request to stop cannot be sent until the client reads; the second goal is
    # asked all the same, long before the grace period.
    server = Server(max_queued_bytes=4_000, grace_period=scaled(60))
    started = [asyncio.Event(), asyncio.Event()]
    asked = [asyncio.Event(), asyncio.Event()]

    @server.action("/polite", Fibonacci)
    async def polite(goal: Any, handle: GoalHandle) -> Any:
        started[goal.order].set()
        await handle.cancelled()
        asked[goal.order].set()
        return {"sequence": [goal.order]}

    running = await serve(server, "127.0.0.1", 0, transport=transport)
    wire = await open_wire(running)
    for order in (0, 1):
        await wire.send(
            {"jsonrpc": "2.0", "id": order, "method": "/polite", "params": {"order": order}}
        )
    for event in started:
        await event.wait()
    stuck = connection(running)
    filler = {"jsonrpc": "2.0", "method": "$/filler", "params": {"x": "x" * 20_000}}
    pressing = first_step(stuck.conn.send(json.dumps(filler)))  # read by nobody, yet
    assert isinstance(pressing, Pending) and stuck.conn.congested
    closing = asyncio.create_task(running.close())
    async with asyncio.timeout(scaled(10)):  # a sixth of the grace period
        for event in asked:
            await event.wait()
    received = [await wire.recv()]
    while len([m for m in received if "result" in m]) < 2:
        received.append(await wire.recv())
    results = {m["id"]: m["result"] for m in received if "result" in m}
    assert results == {
        order: {"status": "canceled", "result": {"sequence": [order]}} for order in (0, 1)
    }
    await finish(pressing)
    await closing


async def test_a_goal_accepted_as_shutdown_begins_is_asked_to_stop_at_once(
    transport: Transport,
) -> None:
    server = Server(grace_period=scaled(20))
    accepting = asyncio.Event()
    admit = asyncio.Event()
    seen: list[bool] = []

    async def accept(goal: Any) -> bool:
        accepting.set()
        await admit.wait()
        return True

    @server.action("/late", Fibonacci, accept=accept)
    async def late(goal: Any, handle: GoalHandle) -> Any:
        seen.append(handle.cancel_requested)
        return {"sequence": [1]}

    running = await serve(server, "127.0.0.1", 0, transport=transport)
    wire = await open_wire(running)
    await wire.send({"jsonrpc": "2.0", "id": 1, "method": "/late", "params": {"order": 1}})
    await accepting.wait()
    closing = asyncio.create_task(running.close())
    admit.set()  # the goal goes on after the shutdown's first step: tasks run in order
    received = [await wire.recv()]
    while received[-1].get("id") != 1:
        received.append(await wire.recv())
    states = [m["params"]["status"] for m in received if m.get("method") == "$/goal"]
    assert states == ["accepted", "canceling"]
    assert received[-1]["result"] == {"status": "canceled", "result": {"sequence": [1]}}
    assert seen == [True]
    await closing
