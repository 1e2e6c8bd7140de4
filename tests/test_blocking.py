"""Blocking (plain ``def``) handlers on a server: they cannot starve each other.

Every handler here blocks on a ``threading.Event`` the test holds, never on a clock, so what
runs when is decided by the test alone. Each test sets the events at its end, so that no thread
outlives it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest

from conftest import Subtract, open_wire
from srvwire.dispatch import QUEUE_WARNING_INTERVAL, Context, ServiceRegistry, _Blocking
from srvwire.errors import RegistrationError
from srvwire.server import Server, serve
from srvwire.threads import HandlerThreads
from srvwire.transports.base import Transport
from support import scaled


def call(method: str, id: int, timeout: float | None = None, **params: Any) -> dict[str, Any]:
    if timeout is not None:
        params["_meta"] = {"timeout": timeout}
    return {"jsonrpc": "2.0", "method": method, "id": id, "params": params}


def status(reply: Any) -> str:
    if "result" in reply:
        return "OK"
    return str(reply["error"]["data"]["status"])


class Blocker:
    """A blocking handler that waits for ``release``; counts how many run at once, and tells
    the event loop each time one starts (``started``, and ``changed``)."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.lock = threading.Lock()
        self.running = 0
        self.most = 0
        self.runs = 0
        self.loop = asyncio.get_running_loop()
        self.started: asyncio.Queue[int] = asyncio.Queue()
        self.changed = asyncio.Event()  # set on the loop when a handler starts

    def __call__(self, request: Any) -> Any:
        with self.lock:
            self.running += 1
            self.runs += 1
            self.most = max(self.most, self.running)
            number = self.runs
        self.loop.call_soon_threadsafe(self.started.put_nowait, number)
        self.loop.call_soon_threadsafe(self.changed.set)
        try:
            self.release.wait(scaled(30))
        finally:
            with self.lock:
                self.running -= 1
        return {"difference": number}

    async def next_start(self) -> int:
        async with asyncio.timeout(scaled(5)):
            return await self.started.get()


class WatchedThreads(HandlerThreads):
    """Handler threads that set ``changed`` on the loop as each piece of work ends: a future's
    callbacks run once its result is set, after the pool's accounting (``abandoned``)."""

    def __init__(self, changed: asyncio.Event, **options: Any) -> None:
        super().__init__(**options)
        self.changed = changed
        self.loop = asyncio.get_running_loop()

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Any:
        work = super().submit(fn, *args, **kwargs)
        work.add_done_callback(self.wake)
        return work

    def wake(self, work: Any) -> None:
        # A handler released as its test ends returns after that test's loop closed: nobody
        # waits then (call_soon_threadsafe raises RuntimeError on a closed loop, and
        # concurrent.futures would log it as an error, into whichever test runs next).
        if not self.loop.is_closed():
            with contextlib.suppress(RuntimeError):  # closed in between
                self.loop.call_soon_threadsafe(self.changed.set)


@pytest.fixture
async def blocker() -> AsyncIterator[Blocker]:
    blocking = Blocker()
    try:
        yield blocking
    finally:
        blocking.release.set()


async def test_handlers_past_their_deadline_do_not_starve_a_fast_service(
    blocker: Blocker, transport: Transport
) -> None:
    # The case: every thread is taken by slow handlers whose callers gave up. Their
    # threads are abandoned and replaced, so an unrelated fast service still gets one.
    threads = WatchedThreads(blocker.changed, max_workers=2, max_abandoned=8)
    server = Server(executor=threads)
    server.add_service("/slow", Subtract, blocker)
    server.add_service("/fast", Subtract, lambda request: {"difference": 1})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for id in range(8):
            await w.send(call("slow", id, timeout=scaled(1)))
        assert {await blocker.next_start(), await blocker.next_start()} == {1, 2}
        replies = [await w.recv_reply() for _ in range(8)]
        assert [status(r) for r in replies] == ["DEADLINE_EXCEEDED"] * 8
        # A replacement may have taken a call whose deadline had not quite passed yet. Every
        # handler that runs still blocks its thread, and was abandoned. A thread is abandoned
        # once it has taken its call, which may be before it has entered the handler, or
        # before it sees that the caller left and skips the handler (then it stops counting
        # as abandoned as it ends): wait until every abandoned thread's handler has started.
        async with asyncio.timeout(scaled(5)):
            while True:
                blocker.changed.clear()
                if blocker.runs == threads.abandoned:
                    break
                await blocker.changed.wait()
        assert 2 <= blocker.runs == blocker.running == threads.abandoned
        reply = await w.call(call("fast", 100, timeout=scaled(5)))
        assert reply["result"] == {"difference": 1}
        blocker.release.set()
        await w.ws.close()


async def cancel(w: Any, id: int) -> None:
    """``$/cancel`` the call ``id`` and check that it answered ``CANCELLED``."""
    await w.send({"jsonrpc": "2.0", "method": "$/cancel", "params": {"id": id}})
    assert status(await w.recv_reply()) == "CANCELLED"


async def test_the_cap_on_abandoned_threads_is_logged(
    blocker: Blocker, transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    threads = HandlerThreads(max_workers=1, max_abandoned=1)
    server = Server(executor=threads)
    server.add_service("/slow", Subtract, blocker)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.WARNING, "srvwire.threads"):
            for id in (1, 2):  # one after the other: each runs, then its caller leaves
                await w.send(call("slow", id))
                assert await blocker.next_start() == id
                await cancel(w, id)
        assert threads.abandoned == 1
        # Two threads are busy: the one abandoned, and the one whose caller left past the cap.
        assert caplog.messages == [
            "blocking handlers still running after their callers left have reached the cap "
            "(max_abandoned=1): a thread whose caller leaves now keeps counting against "
            "max_workers=1 until its handler returns; busy threads now: 2 (Blocker, Blocker)"
        ]
        blocker.release.set()
        await w.ws.close()


async def test_max_concurrency_bounds_the_handlers_running_and_the_rest_wait_in_order(
    blocker: Blocker, transport: Transport
) -> None:
    server = Server()
    server.add_service("/limited", Subtract, blocker, max_concurrency=2)
    server.add_service("/fast", Subtract, lambda request: {"difference": 1})
    entry = server.registry.get("/limited")
    assert entry is not None and entry.limit is not None
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for id in range(4):
            await w.send(call("limited", id))
        assert {await blocker.next_start(), await blocker.next_start()} == {1, 2}
        # Messages are read in order: once /fast answers, all four calls have arrived.
        assert (await w.call(call("fast", 100)))["result"] == {"difference": 1}
        assert (entry.limit.running, entry.limit.waiting) == (2, 2)
        blocker.release.set()
        replies = [await w.recv_reply() for _ in range(4)]
        assert sorted(r["result"]["difference"] for r in replies) == [1, 2, 3, 4]
        assert blocker.most == 2
        assert (entry.limit.running, entry.limit.waiting) == (0, 0)
        await w.ws.close()


async def test_an_abandoned_handler_keeps_its_slot_until_it_returns(
    blocker: Blocker, transport: Transport
) -> None:
    # With max_concurrency=1 a slow service holds one thread at most, whatever its callers do.
    server = Server()
    server.add_service("/slow", Subtract, blocker, max_concurrency=1)
    entry = server.registry.get("/slow")
    assert entry is not None and entry.limit is not None
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(call("slow", 1))
        assert await blocker.next_start() == 1
        await cancel(w, 1)  # answered; its handler still runs
        reply = await w.call(call("slow", 2, timeout=scaled(0.1)))
        assert status(reply) == "DEADLINE_EXCEEDED"  # it waited for the slot, and never ran
        assert blocker.runs == 1
        assert entry.limit.running == 1 and entry.limit.waiting == 0
        await w.send(call("slow", 3))
        blocker.release.set()  # the first handler returns; its slot goes to the third call
        reply = await w.recv_reply()
        assert reply["result"] == {"difference": 2}
        await w.ws.close()


async def test_a_blocking_handler_sees_the_cancellation_and_stops_early(
    transport: Transport,
) -> None:
    loop = asyncio.get_running_loop()
    outcomes: asyncio.Queue[tuple[bool, bool, float | None]] = asyncio.Queue()

    entered: asyncio.Queue[None] = asyncio.Queue()

    def patient(request: Any, context: Any) -> Any:
        loop.call_soon_threadsafe(entered.put_nowait, None)
        stopped = context.wait(scaled(30))  # ends when the call does, not after 30 s
        outcome = (stopped, context.cancelled, context.time_remaining())
        loop.call_soon_threadsafe(outcomes.put_nowait, outcome)
        return {"difference": 0}

    server = Server()
    server.add_service("/patient", Subtract, patient)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(call("patient", 1, timeout=scaled(1)))
        async with asyncio.timeout(scaled(5)):
            await entered.get()
        assert status(await w.recv_reply()) == "DEADLINE_EXCEEDED"
        async with asyncio.timeout(scaled(5)):
            assert await outcomes.get() == (True, True, 0.0)
        await w.send(call("patient", 2))
        async with asyncio.timeout(scaled(5)):
            await entered.get()
        await cancel(w, 2)
        async with asyncio.timeout(scaled(5)):
            assert await outcomes.get() == (True, True, None)
        await w.ws.close()


async def test_a_call_that_waits_its_whole_deadline_for_a_thread_is_logged(
    blocker: Blocker, transport: Transport, caplog: pytest.LogCaptureFixture
) -> None:
    server = Server(executor=HandlerThreads(max_workers=1))
    server.add_service("/slow", Subtract, blocker)
    server.add_service("/queued", Subtract, lambda request: {"difference": 1})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(call("slow", 1))  # no deadline: its thread is never abandoned
        assert await blocker.next_start() == 1
        with caplog.at_level(logging.WARNING, "srvwire.server"):
            for id in (2, 3):
                reply = await w.call(call("queued", id, timeout=scaled(0.1)))
                assert status(reply) == "DEADLINE_EXCEEDED"
        (message,) = caplog.messages  # the second is counted, not said (one line per 10 s)
        assert message.startswith("a call to /queued waited ")
        assert message.endswith(
            " s for a thread to run its blocking handler, 100% of its deadline; every thread "
            "is busy: give blocking handlers more threads "
            "(Server(executor=HandlerThreads(max_workers=N))), or bound the slow services "
            "(max_concurrency=N)"
        )
        blocker.release.set()
        assert (await w.recv_reply())["result"] == {"difference": 1}
        await w.ws.close()


def test_a_call_that_waited_past_half_its_deadline_is_logged_once_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # The rule, without a clock to wait on: a job that says it was queued 100 s ago.
    registry = ServiceRegistry()
    entry = registry.add("/queued", Subtract, lambda request: {"difference": 1})
    log = logging.getLogger("test_blocking")

    def job() -> _Blocking:
        context = Context(service=entry.name, deadline=time.monotonic() + 50)
        blocking = _Blocking(entry, lambda: "ran", context, log)
        blocking.queued -= 100  # waited 100 s of a 150 s deadline: two thirds
        return blocking

    with caplog.at_level(logging.WARNING, "test_blocking"):
        assert job()() == "ran"
        assert job()() == "ran"  # within the interval: counted, not said
        entry._queue_warned[0] -= QUEUE_WARNING_INTERVAL  # the interval is over
        assert job()() == "ran"
    first, second = caplog.messages
    assert first.startswith("a call to /queued waited 100 s for a thread")
    assert ", 67% of its deadline; every thread is busy" in first
    assert ", 67% of its deadline (and 1 more since the last such line); every" in second
    fresh = Context(service=entry.name, deadline=time.monotonic() + 50)
    assert _Blocking(entry, lambda: "ran", fresh, log)() == "ran"
    assert len(caplog.messages) == 2  # a job that did not wait says nothing


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_max_concurrency_is_a_whole_number_at_least_one(bad: Any) -> None:
    server = Server()
    with pytest.raises(RegistrationError) as caught:
        server.add_service("/limited", Subtract, lambda request: request, max_concurrency=bad)
    assert str(caught.value) == (
        f"max_concurrency for /limited must be a whole number at least 1, not {bad!r}"
    )
