"""The threads that run blocking (plain ``def``) handlers, off the event loop.

A thread cannot be cancelled: a handler blocked in ``time.sleep`` or on a device keeps its
thread until it returns, whatever its caller and its deadline did. :class:`HandlerThreads`
makes that cost bounded and visible instead of fatal:

* **A stuck handler never keeps the process alive.** Its threads are daemon threads that
  nothing joins, neither ``asyncio.run`` (which waits only for the loop's default executor)
  nor the interpreter at exit; a server that shuts down leaves them behind and says which
  handlers they were running (:meth:`HandlerThreads.busy`).
* **At most ``max_workers`` threads.** Work waits in order for a free thread; a thread that
  has waited ``idle_timeout`` seconds with nothing to do ends, so an idle server holds none.
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any, TypeVar

__all__ = ["HandlerThreads"]

T = TypeVar("T")

_Work = tuple[Future[Any], Callable[..., Any], tuple[Any, ...], dict[str, Any]]


def _label(fn: Callable[..., Any]) -> str:
    """Name what a thread runs: a handler (through a ``functools.partial``) by its name."""
    inner = getattr(fn, "func", fn)
    return str(getattr(inner, "__qualname__", None) or repr(inner))


class HandlerThreads(Executor):
    """An executor of daemon threads for blocking handlers; see the module's rules."""

    def __init__(self, max_workers: int | None = None, *, idle_timeout: float = 60.0) -> None:
        if max_workers is None:
            max_workers = min(32, (os.cpu_count() or 1) + 4)  # asyncio's default, for I/O
        if max_workers < 1:
            raise ValueError(f"max_workers must be at least 1, not {max_workers}")
        self.max_workers = max_workers
        self.idle_timeout = idle_timeout
        self._work: queue.SimpleQueue[_Work | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._threads = 0
        self._idle = 0
        self._busy: dict[int, str] = {}  # thread ident -> what it runs
        self._shutdown = False

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Future[T]:
        future: Future[T] = Future()
        with self._lock:
            if self._shutdown:
                raise RuntimeError("cannot run new work after shutdown")
            self._work.put((future, fn, args, kwargs))
            if self._idle:
                self._idle -= 1  # that thread takes it
            elif self._threads < self.max_workers:
                self._threads += 1
                threading.Thread(
                    target=self._run, name=f"srvwire-handler-{self._threads}", daemon=True
                ).start()
        return future

    def busy(self) -> list[str]:
        """What the threads are running now, by name (a handler's qualified name)."""
        with self._lock:
            return sorted(self._busy.values())

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Refuse new work and let idle threads end; never waits for a busy one.

        ``wait`` is accepted for the Executor interface, and ignored: a thread stuck in a
        handler could not be waited for.
        """
        with self._lock:
            self._shutdown = True
            threads = self._threads
        if cancel_futures:
            while True:
                try:
                    work = self._work.get_nowait()
                except queue.Empty:
                    break
                if work is not None:
                    work[0].cancel()
        for _ in range(threads):
            self._work.put(None)

    def _run(self) -> None:
        ident = threading.get_ident()
        while True:
            try:
                work = self._work.get(timeout=self.idle_timeout)
            except queue.Empty:
                with self._lock:
                    if self._idle:  # nobody counts on this thread: end it
                        self._idle -= 1
                        self._threads -= 1
                        return
                continue
            if work is None:
                with self._lock:
                    self._threads -= 1
                return
            future, fn, args, kwargs = work
            if future.set_running_or_notify_cancel():
                with self._lock:
                    self._busy[ident] = _label(fn)
                try:
                    result = fn(*args, **kwargs)
                except BaseException as exc:
                    self._finished(ident)  # before the caller can see the outcome
                    future.set_exception(exc)
                else:
                    self._finished(ident)
                    future.set_result(result)
            del work, future, fn, args, kwargs  # not held while waiting for the next
            with self._lock:
                self._idle += 1

    def _finished(self, ident: int) -> None:
        with self._lock:
            del self._busy[ident]
