"""The threads that run blocking (plain ``def``) handlers, off the event loop.

A thread cannot be cancelled: a handler blocked in ``time.sleep`` or on a device keeps its
thread until it returns, whatever its caller and its deadline did. :class:`HandlerThreads`
makes that cost bounded and visible instead of fatal:

* **A stuck handler never keeps the process alive.** Its threads are daemon threads that
  nothing joins, neither ``asyncio.run`` (which waits only for the loop's default executor)
  nor the interpreter at exit; a server that shuts down leaves them behind and says which
  handlers they were running (:meth:`HandlerThreads.busy`).
* **At most ``max_workers`` threads work for callers.** Work waits in order for a free
  thread; a thread that has waited ``idle_timeout`` seconds with nothing to do ends, so an idle
  server holds none.
* **A thread whose caller left no longer counts.** Cancelling the future of work that is
  already running (what asyncio does when the call's deadline passes, or it is cancelled)
  *abandons* its thread: the handler goes on, but the thread stops counting against
  ``max_workers``, so the next work gets a thread of its own. At most ``max_abandoned`` threads
  are abandoned at a time, and reaching that cap is logged; past it, a thread whose caller left
  keeps counting. An abandoned thread that finishes takes work again if the pool has room, else
  it ends.

:class:`ConcurrencyLimit` bounds how many handlers of one service run at once; a slot is held
until the handler really returns, so a service of slow blocking handlers holds at most that
many threads, abandoned or not.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any, TypeVar

__all__ = ["ConcurrencyLimit", "HandlerThreads", "SlotJob"]

T = TypeVar("T")


def _label(fn: Callable[..., Any]) -> str:
    """Name what a thread runs: a handler (through ``func`` wrappers, such as a
    ``functools.partial``) by its name."""
    inner: Any = fn
    while hasattr(inner, "func"):
        inner = inner.func
    return str(getattr(inner, "__qualname__", None) or type(inner).__qualname__)


class _Work(Future[Any]):
    """One piece of work and its result: cancelling it once it runs abandons its thread."""

    def __init__(
        self,
        pool: HandlerThreads,
        fn: Callable[..., Any],
        args: tuple[Any, ...],
        kwargs: dict[str, Any],
    ) -> None:
        super().__init__()
        self.pool = pool
        self.fn: Callable[..., Any] | None = fn
        self.args = args
        self.kwargs = kwargs
        self.abandoned = False  # these two change under the pool's lock
        self.finished = False  # its handler returned: nothing to abandon

    def cancel(self) -> bool:
        if super().cancel():
            return True
        self.pool._abandon(self)  # running: the caller left, the thread goes on
        return False


class HandlerThreads(Executor):
    """An executor of daemon threads for blocking handlers; see the module's rules.

    ``max_abandoned`` (default: ``max_workers``) bounds the threads replaced because their
    caller left while their handler still ran; ``logger`` says when that cap is reached.
    """

    def __init__(
        self,
        max_workers: int | None = None,
        *,
        idle_timeout: float = 60.0,
        max_abandoned: int | None = None,
        logger: logging.Logger | None = None,
    ) -> None:
        if max_workers is None:
            max_workers = min(32, (os.cpu_count() or 1) + 4)  # asyncio's default, for I/O
        if max_workers < 1:
            raise ValueError(f"max_workers must be at least 1, not {max_workers}")
        if max_abandoned is None:
            max_abandoned = max_workers
        if max_abandoned < 0:
            raise ValueError(f"max_abandoned must not be negative, not {max_abandoned}")
        self.max_workers = max_workers
        self.idle_timeout = idle_timeout
        self.max_abandoned = max_abandoned
        self.log = logger if logger is not None else logging.getLogger(__name__)
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)  # notified: work was queued
        self._queue: collections.deque[_Work] = collections.deque()
        self._workers = 0  # live threads that count against max_workers
        self._idle = 0  # of those, the ones waiting for work
        self._abandoned = 0  # threads running work whose caller left
        self._cap_logged = False  # the cap was reached and said so; reset below it
        self._busy: dict[int, str] = {}  # thread ident -> what it runs
        self._names = itertools.count(1)
        self._shutdown = False

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Future[T]:
        work = _Work(self, fn, args, kwargs)
        with self._lock:
            if self._shutdown:
                raise RuntimeError("cannot run new work after shutdown")
            self._queue.append(work)
            self._ready.notify()
            self._grow()
        return work

    def busy(self) -> list[str]:
        """What the threads are running now, by name (a handler's qualified name)."""
        with self._lock:
            return sorted(self._busy.values())

    @property
    def abandoned(self) -> int:
        """How many threads run work whose caller left (see the module's rules)."""
        return self._abandoned

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Refuse new work and let idle threads end; never waits for a busy one.

        ``wait`` is accepted for the Executor interface, and ignored: a thread stuck in a
        handler could not be waited for.
        """
        with self._lock:
            self._shutdown = True
            cancelled = list(self._queue) if cancel_futures else []
            if cancel_futures:
                self._queue.clear()
            self._ready.notify_all()
        for work in cancelled:
            work.cancel()

    # --- the pool's accounting, under its lock -------------------------------------------------

    def _grow(self) -> None:
        """Start a thread when more work waits than idle threads can take, and there is room."""
        if len(self._queue) > self._idle and self._workers < self.max_workers:
            self._workers += 1
            threading.Thread(
                target=self._run, name=f"srvwire-handler-{next(self._names)}", daemon=True
            ).start()

    def _abandon(self, work: _Work) -> None:
        """The caller of running ``work`` left: stop counting its thread, within the cap."""
        with self._lock:
            if work.abandoned or work.finished or not work.running():
                return
            if self._abandoned >= self.max_abandoned:
                if not self._cap_logged:
                    self._cap_logged = True
                    # Every busy thread is named, so the count says how many there are: the
                    # abandoned ones, and those that count (this one among them).
                    busy = sorted(self._busy.values())
                    self.log.warning(
                        "blocking handlers still running after their callers left have reached "
                        "the cap (max_abandoned=%d): a thread whose caller leaves now keeps "
                        "counting against max_workers=%d until its handler returns; busy "
                        "threads now: %d (%s)",
                        self.max_abandoned,
                        self.max_workers,
                        len(busy),
                        ", ".join(busy),
                    )
                return
            work.abandoned = True
            self._abandoned += 1
            self._workers -= 1
            self._grow()

    def _run(self) -> None:
        ident = threading.get_ident()
        lock = self._lock
        lock.acquire()
        try:
            while True:
                while not self._queue:
                    if self._shutdown:
                        self._workers -= 1
                        return
                    self._idle += 1
                    notified = self._ready.wait(self.idle_timeout)
                    self._idle -= 1
                    if not notified and not self._queue:
                        self._workers -= 1  # nothing to do for idle_timeout: end
                        return
                work = self._queue.popleft()
                if not work.set_running_or_notify_cancel():
                    continue
                fn, args, kwargs = work.fn, work.args, work.kwargs
                assert fn is not None
                self._busy[ident] = _label(fn)
                work.fn, work.args, work.kwargs = None, (), {}  # not held after it ran
                lock.release()
                error: BaseException | None = None
                try:
                    result = fn(*args, **kwargs)
                except BaseException as exc:
                    result, error = None, exc
                del fn, args, kwargs
                lock.acquire()
                # Not busy before its caller hears of it: busy() names only what still runs.
                del self._busy[ident]
                work.finished = True
                extra = False
                if work.abandoned:
                    self._abandoned -= 1
                    if self._abandoned < self.max_abandoned:
                        self._cap_logged = False
                    # Replaced meanwhile: with no room, this thread is one too many.
                    extra = self._shutdown or self._workers >= self.max_workers
                    if not extra:
                        self._workers += 1  # room again: take work like any other
                lock.release()
                try:
                    if error is None:
                        work.set_result(result)
                    else:
                        work.set_exception(error)
                finally:
                    del work, result, error
                    lock.acquire()
                if extra:
                    return
        finally:
            lock.release()


class ConcurrencyLimit:
    """At most ``limit`` handlers of one service at once; the calls past it wait, in order.

    :meth:`acquire` waits for a slot on the running loop; :meth:`release` gives it back and may
    be called from any thread (a blocking handler's thread releases when its handler returns,
    even after its caller left). A slot handed to a waiter that was cancelled meanwhile is
    passed on, so none is lost.
    """

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"max_concurrency must be at least 1, not {limit}")
        self.limit = limit
        self.running = 0
        self._lock = threading.Lock()
        self._waiters: collections.deque[asyncio.Future[None]] = collections.deque()

    def __repr__(self) -> str:
        return f"<ConcurrencyLimit {self.running}/{self.limit}, {len(self._waiters)} waiting>"

    @property
    def waiting(self) -> int:
        """How many calls wait for a slot."""
        return len(self._waiters)

    async def acquire(self) -> None:
        """Take a slot, waiting for one in order; a cancelled wait takes none."""
        with self._lock:
            if self.running < self.limit and not self._waiters:
                self.running += 1
                return
            waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
        try:
            await waiter
        except asyncio.CancelledError:
            with self._lock:
                if waiter in self._waiters:  # never handed a slot
                    self._waiters.remove(waiter)
                    raise
            if not waiter.cancelled():  # handed one, then cancelled: give it back
                self.release()
            raise  # else _hand_over sees the cancelled waiter and passes the slot on

    def release(self) -> None:
        """Give a slot back: to the first waiter, else to the pool of free ones."""
        with self._lock:
            while self._waiters:
                waiter = self._waiters.popleft()
                try:
                    waiter.get_loop().call_soon_threadsafe(self._hand_over, waiter)
                except RuntimeError:  # its loop is closed: nobody waits there any more
                    continue
                return
            self.running -= 1

    def _hand_over(self, waiter: asyncio.Future[None]) -> None:
        if waiter.done():  # cancelled before the slot reached it
            self.release()
        else:
            waiter.set_result(None)


class SlotJob:
    """A blocking handler's run, as a thread runs it, holding a :class:`ConcurrencyLimit`'s
    slot (or none: ``limit=None``) until the handler returns.

    A job whose caller leaves before a thread takes it (:meth:`leave`) gives its slot back
    then and never runs its handler; one a thread took keeps the slot until the handler
    returns, even after its caller left. Subclasses say when nobody waits for the job any
    more (:meth:`abandoned`) and what to do as it starts or leaves (:meth:`starting`,
    :meth:`leaving`).
    """

    __slots__ = ("call", "limit", "lock", "state")

    def __init__(self, call: Callable[[], Any], limit: ConcurrencyLimit | None) -> None:
        self.call = call
        self.limit = limit
        self.state = "queued"  # then "running", or "left" (its caller left first)
        self.lock = threading.Lock()

    @property
    def func(self) -> Callable[[], Any]:
        """What it runs, for :class:`HandlerThreads` to name it."""
        return self.call

    def abandoned(self) -> bool:
        """Whether nobody waits for the job any more, so that a thread need not run it."""
        return False

    def starting(self) -> None:
        """Called in the thread just before the handler runs."""

    def leaving(self) -> None:
        """Called when the caller left before a thread took the job."""

    def __call__(self) -> Any:
        with self.lock:
            if self.state == "left":
                return None  # its caller left meanwhile: the slot was given back then
            self.state = "running"
        try:
            if self.abandoned():
                return None
            self.starting()
            return self.call()
        finally:
            if self.limit is not None:
                self.limit.release()

    def leave(self) -> None:
        """Its caller left (cancelled, deadline, shutdown): give the slot back if no thread
        took the job."""
        with self.lock:
            if self.state != "queued":
                return
            self.state = "left"
        self.leaving()
        if self.limit is not None:
            self.limit.release()
