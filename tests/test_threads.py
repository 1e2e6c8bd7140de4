"""The executor of blocking handlers: daemon threads, bounded, and honest about what is stuck."""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError

import pytest

from srvwire.threads import HandlerThreads
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
    busy = threads.submit(release.wait, scaled(10))
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
