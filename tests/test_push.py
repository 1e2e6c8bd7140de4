"""The server's reading of pushed messages: answered in the transport's read callback, as the
connection's parked reader task, wherever the connection hands messages over
(``Connection.deliver_to``), with the same behaviour as the reader that pulls them.

Each test runs over real sockets on both WebSocket transports; what only a connection that
pushes does (the reader parked during a first step, reading paused) is checked where the
served connection pushes, and ``test_a_picows_server_connection_is_read_by_push`` makes sure
that at least one transport does.
"""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

import pytest

from conftest import Echo, Hang, open_wire
from srvwire import serving
from srvwire.inline import Pending, first_step
from srvwire.server import RunningServer, Server, serve
from srvwire.serving import ServedConnection
from srvwire.session import ServerSession
from srvwire.transports.base import Connection, Transport
from support import ROOT, run_benchmark, run_python, scaled
from test_server import closed_code, error, request
from test_transports import connected

real_transports = pytest.mark.parametrize("transport", ["websockets", "picows"], indirect=True)


def pushes(conn: ServedConnection) -> bool:
    """Whether ``conn`` takes pushed messages: its transport's connection hands them over."""
    return type(conn.conn).deliver_to is not Connection.deliver_to


def served(running: RunningServer) -> ServedConnection:
    (conn,) = running._connections
    return conn


async def test_the_read_callback_sees_the_current_task_as_asyncio_does() -> None:
    """A message is answered in the read callback only when no task is current: the check
    reads the task asyncio's own ``current_task()`` reads, inside a task and outside one."""
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None and serving._current_task(loop) is task
    outside: asyncio.Future[Any] = loop.create_future()
    loop.call_soon(lambda: outside.set_result((serving._current_task(loop), "checked")))
    assert await outside == (None, "checked")


@pytest.mark.parametrize("transport", ["picows"], indirect=True)
async def test_a_picows_server_connection_is_read_by_push(
    server: Server, transport: Transport
) -> None:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("echo", {"text": "a"}))["result"] == {"text": "a"}
        conn = served(running)
        assert pushes(conn) and conn.pushed
        await w.ws.close()


async def test_a_lone_call_is_started_without_a_coroutine_for_its_message(
    server: Server, transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The usual message, a single call, is started by ``handle`` itself, pushed or pulled;
    any other message is ``handle_events``'s, and each is answered as before."""
    handled: list[list[Any]] = []
    handle_events = ServedConnection.handle_events

    def recording(self: ServedConnection, events: list[Any], reader: Any) -> Any:
        handled.append([type(event).__name__ for event in events])
        return handle_events(self, events, reader)

    monkeypatch.setattr(ServedConnection, "handle_events", recording)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for id in (1, 2):
            assert (await w.request("echo", {"text": "a"}, id=id))["result"] == {"text": "a"}
        assert handled == []
        batch = await w.call([request("echo", {"text": "b"}, id=3)])
        assert [reply["result"] for reply in batch] == [{"text": "b"}]
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 9}})
        assert error(await w.call(request("no_such", id=4))) == (4, -32601, "SERVICE_NOT_FOUND")
        assert handled == [["Call"], [], ["bytes"]]
        await w.ws.close()


@real_transports
async def test_a_first_step_runs_as_the_reader_and_a_call_that_waits_keeps_that_task(
    server: Server, transport: Transport
) -> None:
    seen: list[Any] = []
    release = asyncio.Event()

    async def waits(request: Any) -> Any:
        conn = served(running)
        task = asyncio.current_task()
        # Pushed: answered in the read callback while the reader task waits for messages.
        parked = conn.parked is not None and not conn.parked.done()
        seen.append((task, task is conn.reader, parked))
        if request.text == "wait":
            await release.wait()
            seen.append(asyncio.current_task())
        return {"text": request.text}

    server.add_service("/waits", Echo, waits)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("/waits", {"text": "now"}, id=1))["result"] == {"text": "now"}
        await w.send(request("/waits", {"text": "wait"}, id=2))
        assert (await w.request("/waits", {"text": "next"}, id=3))["result"] == {"text": "next"}
        conn = served(running)
        (first, first_is_reader, parked), (second, second_is_reader, _), (third, *_) = seen
        assert first is second and first_is_reader and second_is_reader
        assert parked == pushes(conn)
        assert third is conn.reader and third is not second  # a new reader took over
        assert second in conn.counted and not second.done()
        release.set()
        assert (await w.recv_reply())["result"] == {"text": "wait"}
        assert seen[3] is second  # the same task from its first line to its last
        await w.ws.close()


@real_transports
async def test_a_handler_that_cancels_itself_inline_leaves_the_messages_behind_it_answered(
    server: Server, transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    async def cancels_itself(request: Any) -> Any:
        task = asyncio.current_task()
        assert task is not None
        task.cancel()
        return {"text": "returned"}

    server.add_service("/cancels_itself", Echo, cancels_itself)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.WARNING, logger="srvwire.server"):
            # Back to back: the later ones arrive while the cancellation is being taken back.
            await w.send(request("/cancels_itself", {"text": ""}, id=1))
            for id in (2, 3, 4):
                await w.send(request("echo", {"text": str(id)}, id=id))
            replies = [await w.recv_reply() for _ in range(4)]
        assert [reply["id"] for reply in replies] == [1, 2, 3, 4]
        assert replies[0]["result"] == {"text": "returned"}
        assert [reply["result"]["text"] for reply in replies[1:]] == ["2", "3", "4"]
        assert "cancelled its own task without waiting" in caplog.text
        reader = served(running).reader
        assert reader is not None and reader.cancelling() == 0 and not reader.done()
        assert (await w.request("echo", {"text": "after"}, id=5))["result"] == {"text": "after"}
        await w.ws.close()


@real_transports
@pytest.mark.parametrize("delay", [0, -1])
async def test_a_timeout_that_expires_at_once_in_a_first_step_reaches_that_handler(
    server: Server, transport: Transport, delay: float
) -> None:
    # The timeout cancels the task it was entered in, the reader's, at the loop's next turn:
    # after the call was handed to the reader, which must deliver it to the call.
    async def times_out(request: Any) -> Any:
        try:
            async with asyncio.timeout(delay):
                await asyncio.Event().wait()
        except TimeoutError:
            task = asyncio.current_task()
            assert task is not None
            return {"text": f"timed out, cancelling {task.cancelling()}"}
        return {"text": "never"}

    server.add_service("/times_out", Echo, times_out)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/times_out", {"text": ""}, id=1))
        await w.send(request("echo", {"text": "behind it"}, id=2))
        replies = {reply["id"]: reply for reply in [await w.recv_reply(), await w.recv_reply()]}
        assert replies[1]["result"] == {"text": "timed out, cancelling 0"}
        assert replies[2]["result"] == {"text": "behind it"}
        reader = served(running).reader
        assert reader is not None and reader.cancelling() == 0
        await w.ws.close()


@real_transports
async def test_a_cancel_in_the_same_read_as_its_call_reaches_it(transport: Transport) -> None:
    server = Server(grace_period=scaled(2))
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("/hangs", {"text": ""}, id=1))
        await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": 1}})
        assert error(await w.recv_reply()) == (1, -32002, "CANCELLED")
        assert hangs.cancelled.is_set()
        await w.ws.close()


@real_transports
async def test_a_batch_and_the_calls_around_it_are_all_answered(
    server: Server, transport: Transport
) -> None:
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(request("echo", {"text": "before"}, id="before"))
        await w.send(
            [request("echo", {"text": str(id)}, id=id) for id in range(3)]
            + [{"jsonrpc": "2.0", "method": "echo", "params": {"text": "note"}}]
        )
        await w.send(request("echo", {"text": "after"}, id="after"))
        first, second, third = [await w.recv() for _ in range(3)]
        assert first["id"] == "before"
        batch, single = (second, third) if isinstance(second, list) else (third, second)
        assert single["result"] == {"text": "after"}
        assert sorted((reply["id"], reply["result"]["text"]) for reply in batch) == [
            (0, "0"),
            (1, "1"),
            (2, "2"),
        ]
        await w.ws.close()


@real_transports
async def test_congestion_stops_the_reading_and_every_call_is_answered_in_order_after(
    transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A client that writes calls and does not read their large replies: the server stops
    # answering at its budget, queues what it is handed, asks the transport to read no more,
    # and once the client reads again answers everything, starting the calls in the order
    # they came (replies may pass each other when sends wait, as JSON-RPC allows).
    server = Server(max_queued_bytes=2**16, write_timeout=scaled(30))
    large = "x" * 60_000  # 300 of them: more than the socket buffers of both ends hold
    started: list[int] = []

    async def echo(request: Any) -> Any:  # async: its first step runs as the call starts
        started.append(int(request.text))
        return {"text": request.text + large}

    server.add_service("echo", Echo, echo)
    paused = asyncio.Event()
    resumed = asyncio.Event()
    queue = ServedConnection.hold

    def hold(self: ServedConnection, data: str | bytes) -> None:
        was = self.paused
        queue(self, data)
        if self.paused and not was:
            paused.set()

    monkeypatch.setattr(ServedConnection, "hold", hold)
    calls = 300
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running, max_message_size=None)
        conn = served(running)
        if pushes(conn):
            resume = type(conn.conn).resume_reading

            def resume_reading(self: Any) -> None:
                resumed.set()
                resume(self)

            monkeypatch.setattr(type(conn.conn), "resume_reading", resume_reading)
        for id in range(calls):
            await w.send(request("echo", {"text": str(id)}, id=id))
        if pushes(conn):
            await asyncio.wait_for(paused.wait(), scaled(10))  # queued only while congested
        replies = {}
        for _ in range(calls):
            reply = await w.recv_reply(within=10)
            replies[reply["id"]] = reply["result"]["text"]
        assert replies == {id: f"{id}{large}" for id in range(calls)}
        assert started == list(range(calls))
        if pushes(conn):
            assert resumed.is_set() and not conn.paused and not conn.queue
        await w.ws.close()


@real_transports
async def test_shutdown_answers_a_waiting_call_and_ends_the_parked_reader(
    transport: Transport,
) -> None:
    server = Server(grace_period=scaled(0.05))
    hangs = Hang()
    server.add_service("/hangs", Echo, hangs)
    running = await serve(server, "127.0.0.1", 0, transport=transport)
    w = await open_wire(running)
    await w.send(request("/hangs", {"text": ""}, id=1))
    await hangs.entered.wait()
    conn = served(running)
    reader = conn.reader
    assert reader is not None
    await running.close()
    assert error(await w.recv_reply()) == (1, -32003, "UNAVAILABLE")
    await asyncio.wait_for(asyncio.wait({conn.reading}), scaled(5))
    await asyncio.wait_for(asyncio.wait({reader}), scaled(5))
    assert conn.reading.done() and reader.done() and not conn.counted


@pytest.mark.parametrize("transport", ["picows"], indirect=True)
async def test_replies_made_in_the_read_callback_are_written_before_it_returns(
    transport: Transport,
) -> None:
    # On picows the server corks what it sends while taking the frames of one read, and
    # writes it all after the read's last frame: in that callback, not a loop turn later.
    count = 40
    async with connected(transport) as pair, asyncio.timeout(scaled(5)):
        server: Any = pair.server
        protocol = server._ws.underlying_transport.get_protocol()
        read = protocol.buffer_updated
        left: list[int] = []  # for each read: the bytes still corked when it returned

        def buffer_updated(nbytes: int) -> None:
            read(nbytes)
            left.append(server._corked_size)

        protocol.buffer_updated = buffer_updated

        def receive(message: str | bytes) -> None:
            sending = first_step(server.send(f"re {message}"))
            assert not isinstance(sending, Pending)

        assert pair.server.deliver_to(receive)
        for i in range(count):
            await pair.client.send(f"up {i}")
        assert [await pair.client.recv() for _ in range(count)] == [
            f"re up {i}" for i in range(count)
        ]
        assert left and not any(left)


@pytest.mark.parametrize("shape", ["sequential", "fan-in", "pipelined"])
def test_the_picows_path_benchmark_answers_every_call(shape: str) -> None:
    # A smoke run; the script exits unless every call got its typed reply.
    script = ROOT / "benchmarks" / "picows_path.py"
    result = run_benchmark(script, "--shape", shape, "--calls", "256", "--connections", "4")
    assert result.stdout.startswith(f"{shape}: ") and "µs of CPU per call" in result.stdout


def test_the_picows_path_benchmark_runs_on_the_default_transport_too() -> None:
    script = ROOT / "benchmarks" / "picows_path.py"
    result = run_benchmark(script, "--shape", "fan-in", "--calls", "64", "--connections", "4",
                           "--transport", "websockets")  # fmt: skip
    assert result.stdout.startswith("fan-in: ") and "µs of CPU per call" in result.stdout


def test_the_picows_path_benchmark_counts_the_python_steps_of_a_call() -> None:
    # --steps: bytecode instructions per call, by function, both ends; a lone call's reply
    # leaves as it is made, so the server's cork is never flushed.
    script = ROOT / "benchmarks" / "picows_path.py"
    result = run_benchmark(script, "--steps", "--shape", "sequential", "--calls", "200")
    title, *rows = result.stdout.splitlines()
    assert title.startswith("sequential, both ends: ") and title.endswith(" per call")
    steps = {name: float(n) for n, name in (row.split(maxsplit=1) for row in rows)}
    assert {"serving.py:run_call", "picows.py:on_ws_frame", "picows.py:send"} <= set(steps)
    assert "picows.py:_flush" not in steps


def test_the_servers_path_benchmark_pushes_messages_when_asked() -> None:
    # --push hands each message over as it arrives; the script checks every reply.
    script = ROOT / "benchmarks" / "server_path.py"
    result = run_benchmark(script, "--calls", "300", "--repeat", "1", "--json", "--push")
    assert [json.loads(line)["mode"] for line in result.stdout.splitlines()] == [
        "pipelined",
        "one-by-one",
    ]


@real_transports
async def test_a_failure_inside_srvwire_while_reading_ends_the_connection_with_1011(
    server: Server, transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Not a handler's failure (those are answered INTERNAL) but srvwire's own: the reading
    # ends with it, and the connection is closed as a handler that raises closes it.
    receive = ServerSession.receive

    def failing_receive(self: Any, data: str | bytes) -> Any:
        if "breaks srvwire" in str(data):
            raise RuntimeError("a bug in srvwire")
        return receive(self, data)

    monkeypatch.setattr(ServerSession, "receive", failing_receive)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        assert (await w.request("echo", {"text": "before"}, id=1))["result"] == {"text": "before"}
        conn = served(running)
        await w.send(request("echo", {"text": "breaks srvwire"}, id=2))
        assert await closed_code(w) == 1011
        await asyncio.wait_for(asyncio.wait({conn.reading}), scaled(5))
        assert isinstance(conn.reading.exception(), RuntimeError)
        reader = conn.reader
        assert reader is not None
        await asyncio.wait({reader})
        if not reader.cancelled():  # a pulling reader failed with it: asyncio would log it
            assert isinstance(reader.exception(), RuntimeError)


@real_transports
async def test_a_handler_that_cancels_the_reader_later_ends_the_connection_with_1011(
    server: Server, transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    # A handler answered on the reader, kept it as its current task, and cancels it later:
    # the connection ends, with 1011 and a line that says why, as a pulling reader's would;
    # it is not left open and deaf.
    kept: list[asyncio.Task[Any]] = []

    async def keeps_its_task(request: Any) -> Any:
        task = asyncio.current_task()
        assert task is not None
        kept.append(task)
        return {"text": request.text}

    server.add_service("/keeps_its_task", Echo, keeps_its_task)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        reply = await w.request("/keeps_its_task", {"text": "a"}, id=1)
        assert reply["result"] == {"text": "a"}
        assert served(running).pushed
        with caplog.at_level(logging.ERROR, logger="srvwire.server"):
            kept[0].cancel()
            assert await closed_code(w) == 1011
        assert "was cancelled by a handler that had answered on it" in caplog.text


ENDING_LOOP = """
import asyncio, logging, sys
from srvwire import Server, serve
from srvwire.transports import get_transport
from srvwire.loader import load_service
from srvwire.transports.base import Options

logging.basicConfig(level=logging.ERROR, stream=sys.stdout, format="%(message)s")


async def main():
    server = Server()
    add = load_service("example_interfaces/srv/AddTwoInts")
    server.add_service("/add", add, lambda r: {"sum": r.a + r.b})
    running = await serve(server, "127.0.0.1", 0, transport=sys.argv[1]).__aenter__()
    conn = await get_transport(sys.argv[1]).connect(running.url, Options())
    await conn.recv()  # the $/services
    await conn.send('{"jsonrpc": "2.0", "id": 1, "method": "/add", "params": {"a": 1, "b": 2}}')
    print(await conn.recv())
    # and return with the server and the connection open: asyncio.run cancels every task


asyncio.run(main())
"""


@pytest.mark.parametrize("name", ["websockets", "picows"])
def test_an_event_loop_that_ends_with_a_connection_open_says_nothing_of_a_cancelled_reader(
    name: str,
) -> None:
    # asyncio.run cancels every task as it ends, the parked reader among them: that is the
    # end of serving, not a handler's doing, so no error is logged. (In a process of its own:
    # what the ended loop leaves open is not this suite's to collect.)
    result = run_python("-c", ENDING_LOOP, name)
    assert '"result":{"sum":3}' in result.stdout.replace(" ", "")
    assert "was cancelled by a handler" not in result.stdout + result.stderr
