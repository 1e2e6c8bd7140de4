"""The executor of blocking handlers: daemon threads, bounded, and honest about what is stuck."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import CancelledError

import pytest

from srvwire.threads import ConcurrencyLimit, HandlerThreads
from support import scaled


def handler_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("srvwire-handler-")]


def test_work_runs_and_its_result_or_exception_comes_back() -> None:
    threads = HandlerThreads(2)
    assert threads.submit(lambda a, b: a + b, 2, 3).result(scaled(5)) == 5

    def fails() -> None:
        raise KeyError("boom")

    with pytest.raises(KeyError, match="boom"):
        threads.submit(fails).result(scaled(5))
    threads.shutdown()


def test_work_is_no_longer_busy_once_its_outcome_can_be_seen() -> None:
    # A server that shuts down the moment a call's reply is ready must not report that call's
    # handler as still running. A done callback runs in the worker, as the outcome is set.
    threads = HandlerThreads(1)
    seen: list[list[str]] = []
    go = threading.Event()

    def answers() -> int:
        go.wait(scaled(5))  # until the callback is in place
        return 5

    def fails() -> None:
        go.wait(scaled(5))
        raise KeyError("boom")

    for work in (answers, fails):
        go.clear()
        called = threading.Event()

        def look(_: object, called: threading.Event = called) -> None:
            seen.append(threads.busy())
            called.set()

        threads.submit(work).add_done_callback(look)
        go.set()
        assert called.wait(scaled(5))
    assert seen == [[], []]
    threads.shutdown()


def test_at_most_max_workers_run_at_once_and_busy_names_them() -> None:
    threads = HandlerThreads(2)
    release = threading.Event()
    started = threading.Semaphore(0)

    def blocks() -> str:
        started.release()
        release.wait(scaled(10))
        return "done"

    running = [threads.submit(blocks) for _ in range(3)]
    for _ in range(2):
        assert started.acquire(timeout=scaled(5))
    assert not running[2].running()  # the third waits: both threads are taken
    assert (
        threads.busy()
        == ["test_at_most_max_workers_run_at_once_and_busy_names_them.<locals>.blocks"] * 2
    )
    assert all(t.daemon for t in handler_threads())  # none of them keeps the process alive
    release.set()
    assert [f.result(scaled(5)) for f in running] == ["done"] * 3
    threads.shutdown()


def test_an_idle_thread_ends_after_its_timeout() -> None:
    threads = HandlerThreads(1, idle_timeout=scaled(0.05))
    before = set(handler_threads())
    assert threads.submit(lambda: 1).result(scaled(5)) == 1
    (started,) = set(handler_threads()) - before
    started.join(scaled(5))  # it ends by itself, with nothing to do
    assert not started.is_alive()
    assert threads.submit(lambda: 2).result(scaled(5)) == 2  # and a new one takes over
    threads.shutdown()


def test_after_shutdown_no_new_work_and_waiting_work_can_be_cancelled() -> None:
    threads = HandlerThreads(1)
    release = threading.Event()
    started = threading.Event()

    def blocks() -> bool:
        started.set()
        return release.wait(scaled(10))

    busy = threads.submit(blocks)
    assert started.wait(scaled(5))  # it runs: shutdown cannot cancel it
    waiting = threads.submit(lambda: "never")
    threads.shutdown(cancel_futures=True)
    with pytest.raises(CancelledError):
        waiting.result(scaled(5))
    with pytest.raises(RuntimeError, match="after shutdown"):
        threads.submit(lambda: 1)
    release.set()
    assert busy.result(scaled(5)) is True


def test_max_workers_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_workers must be at least 1, not 0"):
        HandlerThreads(0)


class Blocks:
    """Work that blocks until ``release``; ``started`` is set once it runs, in ``thread``."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()
        self.thread: threading.Thread | None = None

    def __call__(self) -> str:
        self.thread = threading.current_thread()
        self.started.set()
        self.release.wait(scaled(10))
        return "done"


def test_cancelling_running_work_abandons_its_thread_and_a_new_one_takes_the_next() -> None:
    threads = HandlerThreads(1)
    blocks = Blocks()
    first = threads.submit(blocks)
    assert blocks.started.wait(scaled(5))
    second = threads.submit(lambda: "next")
    assert first.cancel() is False  # it runs: it cannot be cancelled, its thread is abandoned
    assert threads.abandoned == 1
    assert second.result(scaled(5)) == "next"  # a new thread took it
    blocks.release.set()
    assert first.result(scaled(5)) == "done"
    assert blocks.thread is not None
    blocks.thread.join(scaled(5))  # the pool has its one thread again: this one ends
    assert not blocks.thread.is_alive()
    assert threads.abandoned == 0
    assert threads.submit(lambda: "again").result(scaled(5)) == "again"
    threads.shutdown()


def test_an_abandoned_thread_that_finishes_takes_work_again_when_there_is_room() -> None:
    threads = HandlerThreads(2)
    blocks = Blocks()
    running = threads.submit(blocks)
    assert blocks.started.wait(scaled(5))
    running.cancel()  # abandoned; nothing waits, so no thread replaces it
    assert threads.abandoned == 1
    blocks.release.set()
    assert running.result(scaled(5)) == "done"
    # The pool has room, so that thread counts again and takes the next work: it is the only one.
    on = threads.submit(threading.current_thread).result(scaled(5))
    assert on is blocks.thread
    assert threads.abandoned == 0
    threads.shutdown()


def test_a_backlog_leaves_the_count_of_idle_threads_right() -> None:
    # Threads that took queued work one after the other once counted themselves idle each
    # time; after they ended, new work then waited for a thread that did not exist.
    threads = HandlerThreads(1, idle_timeout=scaled(0.05))
    blocks = Blocks()
    futures = [threads.submit(blocks), threads.submit(lambda: 2), threads.submit(lambda: 3)]
    assert blocks.started.wait(scaled(5))
    blocks.release.set()
    assert [f.result(scaled(5)) for f in futures] == ["done", 2, 3]
    assert blocks.thread is not None
    blocks.thread.join(scaled(5))  # idle for idle_timeout: it ends
    assert not blocks.thread.is_alive()
    assert threads.submit(lambda: 4).result(scaled(5)) == 4
    threads.shutdown()


def test_max_abandoned_must_not_be_negative() -> None:
    with pytest.raises(ValueError, match="max_abandoned must not be negative, not -1"):
        HandlerThreads(2, max_abandoned=-1)


async def test_a_slot_handed_to_a_cancelled_waiter_passes_on() -> None:
    limit = ConcurrencyLimit(1)
    await limit.acquire()
    second = asyncio.create_task(limit.acquire())
    third = asyncio.create_task(limit.acquire())
    await asyncio.sleep(0)  # one turn: both tasks run up to their wait
    assert (limit.running, limit.waiting) == (1, 2)
    limit.release()  # handed to the second, which is cancelled before it gets there
    second.cancel()
    async with asyncio.timeout(scaled(5)):
        await third
    with pytest.raises(asyncio.CancelledError):
        await second
    assert (limit.running, limit.waiting) == (1, 0)
    fourth = asyncio.create_task(limit.acquire())
    await asyncio.sleep(0)
    fourth.cancel()  # cancelled while it waits: it takes nothing
    with pytest.raises(asyncio.CancelledError):
        await fourth
    limit.release()
    assert (limit.running, limit.waiting) == (0, 0)


def test_max_concurrency_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_concurrency must be at least 1, not 0"):
        ConcurrencyLimit(0)
