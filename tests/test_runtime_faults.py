"""Faults across components: a killed server process, hanging and failing handlers, overload.

Each test runs the real client against the real server (in this process, or in a subprocess
that is killed), and proves what a caller sees when something breaks: the exception type is the
evidence, never a measured time alone.
"""

from __future__ import annotations

import asyncio
import signal
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from srvwire.client import connect
from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InternalError,
    ResourceExhausted,
    ServiceUnavailable,
)
from srvwire.loader import load_service
from srvwire.server import RunningServer, Server, serve
from srvwire.transports.base import Transport
from support import scaled

SERVERS = Path(__file__).parent / "servers"
TRIGGER = load_service("std_srvs/srv/Trigger")
ADD = load_service("example_interfaces/srv/AddTwoInts")


async def read_line(process: asyncio.subprocess.Process) -> str:
    assert process.stdout is not None
    line = await asyncio.wait_for(process.stdout.readline(), scaled(20))
    assert line, "the server process exited early"
    return line.decode().strip()


async def test_killing_the_server_process_fails_every_pending_call() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        str(SERVERS / "hanging_server.py"),
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        port = int(await read_line(process))
        async with connect(f"ws://127.0.0.1:{port}", timeout=scaled(30)) as client:
            calls = [asyncio.create_task(client.call("/hang")) for _ in range(10)]
            started = {await read_line(process) for _ in calls}
            assert started == {f"started {n}" for n in range(1, 11)}
            assert client.in_flight == 10
            process.send_signal(signal.SIGKILL)
            results = await asyncio.gather(*calls, return_exceptions=True)
            # The deadline is 30 s: a call that waited for it would be DeadlineExceeded.
            assert all(type(r) is ConnectionLost for r in results), results
            lost = [r for r in results if isinstance(r, ConnectionLost)]
            assert {e.service for e in lost} == {"/hang"}
            assert lost[0].message == "the connection dropped (no close frame)"
            assert client.in_flight == 0
            assert not client.connected
    finally:
        if process.returncode is None:
            process.kill()
        # The exit status is not asserted: under load, asyncio's child watcher in Python 3.11
        # can lose the race to reap the process and reports 255 instead of -9. The calls
        # failing with ConnectionLost above are the evidence that the process died.
        await process.wait()


class Hangs:
    """A handler that never returns, and records when the server cancels it."""

    def __init__(self) -> None:
        self.started = asyncio.Event()
        self.cancelled = asyncio.Event()

    async def __call__(self, request: Any) -> None:
        self.started.set()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            self.cancelled.set()
            raise


@pytest.fixture
async def hanging(transport: Transport) -> AsyncIterator[tuple[RunningServer, Hangs]]:
    handler = Hangs()
    server = Server(grace_period=scaled(0.1))
    server.add_service("/hang", TRIGGER, handler)

    calls = 0

    def flaky(request: Any) -> dict[str, int]:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("the first call always fails")
        return {"sum": request.a + request.b}

    server.add_service("/flaky", ADD, flaky)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        yield running, handler


async def test_a_hanging_handler_meets_the_deadline_and_is_cancelled(
    hanging: tuple[RunningServer, Hangs],
) -> None:
    running, handler = hanging
    async with connect(running.url, transport=running.transport) as client:
        loop = asyncio.get_running_loop()
        start = loop.time()
        with pytest.raises(DeadlineExceeded) as caught:
            await client.call("/hang", timeout=scaled(0.3))
        elapsed = loop.time() - start
        # The server's own deadline (sent in _meta) and the client's race; either way the
        # caller sees DeadlineExceeded, near the deadline.
        assert caught.value.service == "/hang"
        assert scaled(0.3) * 0.9 <= elapsed < scaled(0.3) + scaled(1)
        await asyncio.wait_for(handler.cancelled.wait(), scaled(5))
        assert client.in_flight == 0


async def test_cancelling_the_caller_cancels_the_handler(
    hanging: tuple[RunningServer, Hangs],
) -> None:
    running, handler = hanging
    async with connect(running.url, transport=running.transport) as client:
        task = asyncio.create_task(client.call("/hang", timeout=scaled(30)))
        await asyncio.wait_for(handler.started.wait(), scaled(5))
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await asyncio.wait_for(handler.cancelled.wait(), scaled(5))
        assert client.in_flight == 0
        assert len(await client.list_services(timeout=scaled(5))) == 2  # the connection is fine


async def test_a_handler_that_raises_is_an_internal_error_and_the_next_call_works(
    hanging: tuple[RunningServer, Hangs], caplog: pytest.LogCaptureFixture
) -> None:
    running, _ = hanging
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        with pytest.raises(InternalError) as caught:
            await client.call("/flaky", {"a": 1, "b": 2})
        assert caught.value.service == "/flaky"
        assert "RuntimeError" not in caught.value.message  # no traceback leaves the server
        assert (await client.call("/flaky", {"a": 1, "b": 2})).sum == 3
    assert any("first call always fails" in str(r.exc_info) for r in caplog.records)


async def test_overload_is_resource_exhausted(transport: Transport) -> None:
    handler = Hangs()
    server = Server(max_in_flight=1)
    server.add_service("/hang", TRIGGER, handler)
    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=running.transport) as client,
    ):
        first = asyncio.create_task(client.call("/hang", timeout=scaled(30)))
        await asyncio.wait_for(handler.started.wait(), scaled(5))
        with pytest.raises(ResourceExhausted) as caught:
            await client.call("/hang", timeout=scaled(5))
        assert caught.value.service == "/hang"
        first.cancel()
        with pytest.raises(asyncio.CancelledError):
            await first


async def test_shutdown_answers_unavailable_then_the_connection_is_lost(
    hanging: tuple[RunningServer, Hangs],
) -> None:
    running, handler = hanging
    async with connect(running.url, transport=running.transport, timeout=scaled(30)) as client:
        call = asyncio.create_task(client.call("/hang"))
        await asyncio.wait_for(handler.started.wait(), scaled(5))
        await running.close()  # the grace period passes, the handler is cancelled
        with pytest.raises(ServiceUnavailable) as caught:
            await call
        # Answered UNAVAILABLE by the server, not a dropped connection.
        assert type(caught.value) is ServiceUnavailable
        assert handler.cancelled.is_set()
        with pytest.raises(ConnectionLost):
            await client.call("/hang")


async def test_a_reconnecting_client_that_closes_leaves_no_connection_on_the_server(
    transport: Transport,
) -> None:
    # Closing a reconnect=True client once forgot its socket: the supervisor's cancellation
    # reached the reader, which dropped the connection from the client without closing it.
    server = Server()
    server.add_service("/add", ADD, lambda request: {"sum": request.a + request.b})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        client = await connect(
            running.url, transport=running.transport, reconnect=True, timeout=scaled(5)
        )
        assert (await client.call("/add", {"a": 1, "b": 2})).sum == 3
        (connection,) = running._connections  # the server's record of its one connection
        await client.close()
        await asyncio.wait_for(asyncio.wait({connection.reading}), scaled(5))  # reading ended
        assert connection.conn.close_code == 1000  # closed by the client, not by the shutdown


async def test_a_request_larger_than_the_server_accepts_loses_the_connection(
    transport: Transport,
) -> None:
    server = Server(max_message_size=1000)
    robot = load_service("advanced_communication_tutorials/srv/RobotCommand")
    server.add_service("/command", robot, lambda request: {"success": True})
    async with (
        serve(server, "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=running.transport) as client,
    ):
        assert (await client.call("/command", {"parameters": [0.5] * 10})).success
        with pytest.raises(ConnectionLost) as caught:
            await client.call("/command", {"parameters": [0.5] * 500}, timeout=scaled(10))
        assert caught.value.data["close_code"] == 1009
        assert not client.connected
