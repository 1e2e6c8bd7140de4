"""One connection a server serves: its session, its reader, and the runner of its calls.

A :class:`ServedConnection` reads and does what its :class:`~srvwire.session.ServerSession`
asks: send a reply, start a call, run a notification, cancel a call. Its :class:`CallRunner`
runs the calls. The rules of the conversation are the session's; the rules of time and tasks
are this module's.

Invariants:

* **The reader never waits for a handler.** One task at a time reads a connection. A call (or
  notification) runs inline on it, in a copy of its context, up to the call's first suspension
  (:func:`~srvwire.inline.first_step`): most handlers answer there, with no task, timer or loop
  turn of their own, and their reply is sent before the next message is read. A call that has
  to wait keeps the task it started on (so ``asyncio.current_task()`` stays its own), and a new
  reader task takes over. A batch's calls run in tasks of their own, started once the whole
  batch is read, so a ``$/cancel`` in the same batch reaches them before they start.
* **Pushed or pulled, the same reader.** Where the connection hands each message over as it
  arrives (:meth:`~srvwire.transports.base.Connection.deliver_to`), the reader task does not
  wait for ``recv``: it *parks* on a future of its own, and a message that comes while it is
  parked, with nothing queued and the connection not congested, is answered right there, in
  the transport's read callback, *as the reader* (made the loop's current task for the time,
  so handlers see the same ``asyncio.current_task()`` as when pulled): no wake-up, future or
  loop turn per message. What has to wait there (a call, or a send held back) is *handed* to
  the parked reader, which wakes to finish it exactly as it would have pulled it: a call keeps
  it, taken over at once (counted, deadline armed, a new reader started), and a cancellation
  of the reader thrown at its parking (``asyncio.timeout()``, a handler's own) is requested
  again, so that it lands where the handed steps wait. Any other message (the reader not
  parked: busy, new, or a task current) is queued and the reader takes it; past
  :data:`PUSH_HIGH_WATER` queued, the transport is asked to read no more until the reader is
  down to :data:`PUSH_LOW_WATER`. The connection's handler (:meth:`ServedConnection.serve`)
  awaits only the end, from ``recv``, and wakes the reader, which answers what is queued
  first; a failure of the reading inside srvwire, or a cancellation of the parked reader
  while :meth:`~ServedConnection.serve` runs on (a handler that answered on it, kept it as its
  ``current_task()`` and cancelled it later; not serve's own stop, nor the end of the event
  loop), ends the connection with 1011, as a pulling reader's end ends it. Elsewhere
  (the memory transport, or an asyncio without its private ``_enter_task``) the reader pulls
  with ``recv``.
* **The reader waits only to send, and while the connection is congested**, which is what
  pushes back on a client that writes faster than it reads: a reply held by such a client
  counts in flight until it is sent, so past ``max_in_flight`` the reader answers the next call
  itself, and waits; and while the bytes waiting to be sent are past the connection's budget
  (:attr:`~srvwire.transports.base.Connection.congested`), it reads nothing, and a batch's call
  waits before its handler runs: no reply is built that could not be queued.
* **A call's** :class:`~srvwire.dispatch.Context` **is made when something needs it**: its
  handler takes one or runs in a thread, the call is cancelled, or it is late
  (:meth:`CallRunner.context_of`). A call that answers without any of these never has one;
  its deadline is kept on the call itself.
* **A deadline is a cancellation with a reason.** A call's ``_meta.timeout`` is armed as one
  timer only when the call has to wait; when it fires, the call is cancelled with
  ``DEADLINE_EXCEEDED`` exactly as ``$/cancel`` cancels it with ``CANCELLED`` and shutdown with
  ``UNAVAILABLE``: the reason is recorded in the call's :class:`~srvwire.dispatch.Context`
  first (the first one wins), then its task is cancelled, at most once, and the call is
  answered the reason at once, from a task of its own (:meth:`CallRunner.send_answer`):
  the answer never waits for the handler, which may ignore its cancellation (swallow it, or
  clean up for long). Its task is left to end on its own: what it returns then is dropped,
  and what it raises is logged, once, and answers nothing (the session writes one reply per
  call). It still counts in flight, and shutdown still waits for
  it and names it if it outlives the connections (:attr:`CallRunner.running_on`); a goal's
  feedback stops with its answer. A reply already written is not cancelled. A task cancelled
  without a reason (its connection went away) answers nothing. A handler that cancels its own
  task is answered ``INTERNAL``, unless it returns without waiting: then its result is its
  answer, and the reader takes the cancellation back.
* **In flight is counted twice, for two purposes.** The session counts calls for admission
  (a call answered as it was cancelled counts until its task ends: its handler still holds
  what it holds); :attr:`CallRunner.counted` holds the tasks that shutdown waits for: a reader
  task a waiting call took over, until the call is done, each batch item's task, from its
  creation until its coroutine's ``finally`` (a task cancelled before its first step gets a
  done-callback instead), and each task sending the answer of a cancelled call. A task an
  eager task factory already ran to its end inside ``create_task`` is not counted.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import time
import types
from collections import deque
from collections.abc import Callable, Coroutine
from concurrent.futures import Executor
from contextvars import copy_context
from dataclasses import dataclass
from typing import Any, TypeAlias

from srvwire.dispatch import (
    Context,
    ServiceEntry,
    ServiceRegistry,
    handler_error,
    run_handler,
    write_result,
)
from srvwire.errors import Cancelled, DeadlineExceeded, InternalError, RPCError, ServiceError
from srvwire.goals import FeedbackOutbox
from srvwire.inline import Pending, finish, first_step
from srvwire.protocol import PUBLISH_METHOD, SUBSCRIBE_METHOD, Id
from srvwire.session import (
    Call,
    CancelCall,
    Dropped,
    NotificationCall,
    Publish,
    RefusedMessage,
    ServerSession,
    SubscriptionDeadline,
)
from srvwire.topics import Outbox, QoS, Subscription, Topic, publish_ack
from srvwire.transports.base import Connection, TransportClosed

try:  # private: what asyncio makes a task current with around each of its steps (3.11-3.14)
    from asyncio.tasks import _enter_task, _leave_task

    CAN_PUSH = True
except ImportError:  # pragma: no cover - a Python without them: messages are pulled
    CAN_PUSH = False
_current_task: Callable[[asyncio.AbstractEventLoop], asyncio.Task[Any] | None]
_current_task = asyncio.current_task  # compiled from 3.12 on
if type(_current_task) is types.FunctionType:  # 3.11's, in Python: the dict it reads, itself
    _current_tasks = getattr(asyncio.tasks, "_current_tasks", None)  # private, as _enter_task
    if type(_current_tasks) is dict:
        _current_task = _current_tasks.get

__all__ = [
    "AccessLog",
    "AccessLoggedOutbox",
    "AccessLoggedSession",
    "CallRunner",
    "ServedConnection",
    "Writer",
]


DROP_LOG_INTERVAL = 1.0
"""Seconds: at most one line about dropped notifications per connection in this time; the
drops in between are counted, and their number said when it ends (or the connection does)."""

PUSH_HIGH_WATER = 64
"""Pushed messages queued for the reader at which the transport is asked to read no more."""
PUSH_LOW_WATER = 16
"""Pushed messages still queued at which the transport is asked to read again."""

Work: TypeAlias = Call[ServiceEntry] | NotificationCall[ServiceEntry]
"""What a connection runs: a call, or a notification."""


@dataclass(frozen=True, slots=True)
class Handed:
    """A call whose first step ran in the transport's read callback, as the parked reader,
    and has to wait: the reader took it over then (its deadline's ``timer`` armed); the
    ``steps`` left are the reader's to finish."""

    steps: Pending
    timer: asyncio.TimerHandle | None


class CallRunner:
    """Runs the calls and notifications of one connection, under their deadlines.

    A call answers through the session, which writes the reply (or, for the last call of a
    batch, the batch's); the runner sends it on ``conn`` itself, as
    :meth:`ServedConnection.send` sends, ahead of the data ``outbox`` holds.
    """

    __slots__ = (
        "channel",
        "conn",
        "counted",
        "executor",
        "identity",
        "log",
        "loop",
        "notification_timeout",
        "outbox",
        "peer",
        "running_on",
        "session",
    )

    def __init__(
        self,
        session: ServerSession[ServiceEntry],
        outbox: Outbox,
        *,
        conn: Connection,
        peer: Any,
        executor: Executor | None,
        logger: logging.Logger,
        notification_timeout: float | None = None,
        identity: Any = None,
        channel: Any = None,
    ) -> None:
        self.session = session
        self.outbox = outbox
        self.channel = channel  # what an action's goal sends its states and feedback through
        self.conn = conn
        self.peer = peer
        self.identity = identity
        self.executor = executor
        self.log = logger
        self.notification_timeout = notification_timeout
        self.loop = asyncio.get_running_loop()
        self.counted: set[asyncio.Task[Any]] = set()  # calls and notifications in flight
        # The tasks of calls answered as they were cancelled, until they end: their services.
        self.running_on: dict[asyncio.Task[Any], str] = {}

    # --- tasks --------------------------------------------------------------------------------

    def spawn_counted(self, coro: Any) -> asyncio.Task[Any]:
        """Spawn a call or notification task; it counts until its coroutine :meth:`settle` s."""
        task: asyncio.Task[Any] = self.loop.create_task(coro)
        if not task.done():
            self.counted.add(task)
        return task

    def settle(self) -> None:
        """Uncount the running task, a call's or a notification's; its coroutine's last step."""
        try:
            task = asyncio.current_task()
        except RuntimeError:  # closed by the garbage collector after its loop: nothing counts
            return
        if task is not None:
            self.counted.discard(task)

    # --- deadlines and cancellation -----------------------------------------------------------

    def begin(self, work: Work) -> None:
        """Give a call or notification its deadline, measured from now.

        A notification without a deadline of its own gets ``notification_timeout``: nobody
        waits for it, so nothing else would ever end one that hangs.
        """
        timeout = work.timeout
        if timeout is None and type(work) is NotificationCall:
            timeout = self.notification_timeout
        deadline = work.deadline = None if timeout is None else time.monotonic() + timeout
        if work.context is not None:  # made before it began, by a cancellation
            work.context.deadline = deadline

    def context_of(self, work: Work) -> Context:
        """The :class:`~srvwire.dispatch.Context` of a call or notification, made the first
        time something needs it (see the invariants)."""
        context: Context | None = work.context
        if context is None:
            context = work.context = Context(
                service=work.entry.name,
                request_id=work.id if type(work) is Call else None,
                peer=self.peer,
                deadline=work.deadline,
                identity=self.identity,
                channel=self.channel,
            )
        return context

    def arm(self, work: Work) -> asyncio.TimerHandle | None:
        """Arm the deadline of a call or notification that waits; None when it has none."""
        deadline = work.deadline
        if deadline is None:
            return None
        return self.loop.call_later(deadline - time.monotonic(), self.expire, work)

    def expire(self, work: Work) -> None:
        """A deadline passed: cancel the call or notification with ``DEADLINE_EXCEEDED``."""
        name = work.entry.name
        error = DeadlineExceeded(
            f"the deadline for {name} passed before the handler finished", service=name
        )
        if type(work) is Call and not self.session.answering(work):
            return  # its reply is written: let it go out
        self.cancel(work, error)

    def cancel(self, work: Work, error: RPCError | None) -> None:
        """Cancel a call or notification; with ``error`` a call answers that error, without it
        stays silent.

        A call whose task has not started is only marked: it answers when it starts. A task is
        cancelled once at most, since the call takes one cancellation back before replying. A
        started call is answered ``error`` now, whether or not its handler heeds the
        cancellation (see the invariants): its task is left to end on its own.
        """
        context = self.context_of(work)
        context._mark_cancelled(error)
        task = work.task
        if task is not None and not work.task_cancelled and (work.started or error is None):
            work.task_cancelled = True
            task.cancel()
            if error is not None and type(work) is Call:
                self.running_on[task] = work.entry.name
                task.add_done_callback(self.running_on.pop)
                reply = self.session.fail(work, error)
                if context.goal is not None:  # answered: its feedback is dropped from now on
                    context.goal.close()
                if reply is not None:
                    self.spawn_counted(self.send_answer(reply))

    def request_cancel(self, work: Work, error: RPCError | None) -> bytes | None:
        """``$/cancel`` (or shutdown, or the connection's end) reached a call.

        An action's goal that the client cancelled is asked to stop first: its handler sees
        ``cancel_requested``, and is cancelled only if it has not returned after its grace
        period. Return the ``$/goal canceling`` to send then. Anything else is cancelled now.
        """
        context: Context | None = work.context
        goal = None if context is None else context.goal
        if goal is None or type(error) is not Cancelled:
            self.cancel(work, error)
            return None
        canceling: bytes | None = goal.request_cancel(lambda: self.stop_goal(work, error))
        return canceling

    def stop_goal(self, work: Work, error: RPCError) -> None:
        """A goal's grace period after its cancellation passed: cancel its handler."""
        if type(work) is Call and self.session.answering(work):
            self.cancel(work, error)

    async def send_answer(self, reply: bytes) -> None:
        """Send the answer to a call cancelled while it ran (or its batch's), in a task of its
        own, counted as calls are, so that shutdown waits for it too."""
        try:
            await self.send_ahead(reply)
        finally:
            self.settle()

    async def send_ahead(self, data: bytes) -> None:
        """Send one message ahead of the topic data the outbox holds, which gives up what no
        longer fits in the budget; a connection that is gone is not an error here."""
        try:
            await self.conn.send(data)
        except TransportClosed:
            return  # the caller left; its calls are being cancelled
        if self.outbox.queued:
            self.outbox.fit()

    @staticmethod
    async def take_back_cancellation() -> None:
        """Take back the one cancellation of this task that srvwire requested.

        It may not have been delivered yet (the handler swallowed an earlier one, or finished
        as it was requested): let it arrive here, where it is harmless, then uncount it.
        """
        task = asyncio.current_task()
        assert task is not None
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.sleep(0)
        task.uncancel()

    # --- running ------------------------------------------------------------------------------

    def start_in_task(self, work: Work) -> None:
        """Start a batch's call or notification in a task of its own, counted from now."""
        self.begin(work)
        work.task = self.spawn_counted(self.run_in_task(work))

    async def run_in_task(self, work: Work) -> None:
        """Run a batch's call or notification in its own task, under its deadline."""
        timer = self.arm(work)
        try:
            if isinstance(work, Call):
                await self.run_call(work)
            else:
                await self.run_notification(work)
        finally:
            if timer is not None:
                timer.cancel()
            self.settle()

    async def run_call(self, call: Call[ServiceEntry]) -> None:
        """Run one call and send its reply (or its batch's, when it is the last to reply)."""
        call.started = True
        context: Context | None = call.context  # None: nothing has needed it yet
        session = self.session
        entry = call.entry
        log = self.log
        reply: bytes | None
        try:
            if context is not None and context._cancel_error is not None:  # before it started
                reply = session.fail(call, context._cancel_error)
            else:
                if call.batch is not None and self.conn.congested:  # see the invariants
                    try:
                        await self.conn.writable()
                    except TransportClosed:  # nobody to answer: do not run it
                        session.forget(call)
                        return
                params = call.params
                deadline = call.deadline
                if (
                    entry.usual
                    and type(params) is entry.request_model  # read in one pass: validated
                    and (deadline is None or deadline > time.monotonic())
                ):
                    # run_handler's steps for the usual handler, without a coroutine of its own
                    try:
                        result = await entry.handler(params)
                    except (Exception, asyncio.CancelledError) as exc:
                        mapped = handler_error(entry, exc, self.context_of, call, log)
                        if mapped is exc:
                            raise
                        raise mapped from None
                    result = write_result(entry, result, log, call.id)
                else:
                    result = await run_handler(  # the whole response, written in one pass
                        entry, params, deadline, self.context_of, call, self.executor, log, call.id
                    )
                if call.task_cancelled:  # cancelled meanwhile, and the handler finished anyway
                    context = self.context_of(call)
                    if context._cancel_error is not None:
                        reply = None  # answered as it was cancelled: its result is too late
                    else:  # the connection went away
                        await self.take_back_cancellation()
                        session.forget(call)
                        raise asyncio.CancelledError
                else:
                    if log.isEnabledFor(logging.DEBUG):
                        log.debug("%s id %r from %s: ok", entry.name, call.id, self.peer)
                    reply = session.reply(call, result, True)  # whole
                del result  # not held through the send: a large result would be held twice
        except RPCError as exc:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s id %r from %s: %s", entry.name, call.id, self.peer, exc)
            reply = session.fail(call, exc)
        except asyncio.CancelledError:
            error = self.context_of(call)._cancel_error
            if error is not None:  # srvwire cancelled it, for this reason: take it back
                asyncio.current_task().uncancel()  # type: ignore[union-attr]
            elif call.task_cancelled:  # the connection went away: nobody to answer
                session.forget(call)
                raise
            else:  # nothing in srvwire cancelled it: the handler cancelled its own task
                log.error("the handler for %s id %r cancelled its own task", entry.name, call.id)
                error = InternalError(
                    f"handler for {entry.name} was cancelled by its own code", service=entry.name
                )
                if call.task is not None:  # else inline: the reader takes the request back
                    await self.take_back_cancellation()
            reply = session.fail(call, error)
        except Exception:  # a bug in srvwire: still answer, so that the caller is not left waiting
            log.exception("%s id %r from %s failed inside srvwire", entry.name, call.id, self.peer)
            reply = session.fail(
                call,
                InternalError(f"the server failed to answer {entry.name}", service=entry.name),
            )
        try:
            if reply is not None:  # send_ahead, inline: a step less on every call
                try:
                    await self.conn.send(reply)
                except TransportClosed:
                    pass  # the caller left; its calls are being cancelled
                else:
                    if self.outbox.queued:
                        self.outbox.fit()
        finally:
            session.sent(call)  # until now it counted: a reply the client does not read holds

    async def run_notification(self, note: NotificationCall[ServiceEntry]) -> None:
        """Run a notification's handler; nothing is answered, a failure is logged."""
        entry = note.entry
        try:
            await run_handler(
                entry, note.params, note.deadline, self.context_of, note, self.executor, self.log
            )
        except RPCError as exc:
            if self.log.isEnabledFor(logging.INFO):
                self.log.info("notification to %s failed: %s", entry.name, exc)
        except asyncio.CancelledError:
            error = self.context_of(note)._cancel_error
            if error is None:
                raise
            asyncio.current_task().uncancel()  # type: ignore[union-attr]
            if self.log.isEnabledFor(logging.INFO):
                self.log.info("notification to %s failed: %s", entry.name, error)
        finally:
            self.session.done(note)


class Writer:
    """Sends what one connection's :class:`~srvwire.topics.Outbox` holds, one message at a time.

    The outbox decides the order (control messages first, then subscriptions round-robin) and
    the bounds (``depth`` per subscription while the connection is congested; what it holds
    and what the transport holds share the connection's ``budget``); the writer only takes
    the next message and sends it, and takes none while the connection is
    :attr:`~srvwire.transports.base.Connection.congested` (past its budget of bytes waiting
    to be sent). So what a slow reader costs is the connection's budget, and while the writer
    waits, the outbox keeps deciding what to drop (best effort) or end (reliable). Replies to
    calls do not go through it: they are sent at once, never behind the data the outbox holds
    (which then gives up what no longer fits, :meth:`~srvwire.topics.Outbox.fit`), and when a
    drain wakes a reply and the writer together, the reply goes first.

    It runs as a task from the first :meth:`wake` until :meth:`stop`; anything that keeps
    low-priority data in an outbox (topics, feedback) reuses it by calling ``outbox.wake``.

    Goals' feedback (:attr:`feedback`, keep-latest per goal) is data too: it takes turns with
    topic data, one message each, behind every control message; :attr:`feedback_sent` is told
    of each goal whose feedback went out.
    """

    __slots__ = (
        "conn",
        "failed",
        "feedback",
        "feedback_sent",
        "loop",
        "outbox",
        "task",
        "turn",
        "waiter",
    )

    def __init__(
        self,
        conn: Connection,
        loop: asyncio.AbstractEventLoop,
        budget: int = 4 * 2**20,
        make_outbox: Callable[..., Outbox] = Outbox,
    ) -> None:
        self.conn = conn
        self.loop = loop
        # What the transport holds; a stand-in connection without it (a test's) holds nothing.
        buffered = getattr(conn, "buffered", None) or (lambda: 0)
        self.outbox = make_outbox(self.wake, budget, buffered, lambda: not conn.congested)
        self.feedback = FeedbackOutbox()
        self.feedback_sent: Callable[[Any], object] = lambda call: None
        # Told of a failure inside srvwire that ended the task (the connection ends it).
        self.failed: Callable[[Exception], object] = lambda exc: None
        self.turn = False  # whether feedback goes before topic data next time both wait
        self.task: asyncio.Task[None] | None = None
        self.waiter: asyncio.Future[None] | None = None

    def next(self) -> tuple[bytes, Any] | None:
        """The next message and the goal it is feedback of (None for anything else): a
        control message first, then topic data and feedback in turn; None when nothing waits.
        """
        outbox = self.outbox
        feedback = self.feedback
        if feedback and not outbox.control and (self.turn or not outbox.ready):
            self.turn = False
            call, data = feedback.take()  # type: ignore[misc]  # not empty
            return data, call
        self.turn = True
        data = outbox.next()  # None resets its woken flag: the writer may wait then
        if data is not None:
            return data, None
        taken = feedback.take()
        return None if taken is None else (taken[1], taken[0])

    def wake(self) -> None:
        """The outbox has something to send: start the task, or wake it."""
        if self.task is None:
            self.task = self.loop.create_task(self.run())
        elif self.waiter is not None and not self.waiter.done():
            self.waiter.set_result(None)

    async def run(self) -> None:
        outbox = self.outbox
        conn = self.conn
        send = conn.send
        try:
            while True:
                if conn.congested:
                    # Past the connection's budget: hold the data here, where the outbox
                    # drops or ends per QoS, and let replies woken by the same drain go first.
                    await conn.writable()
                    await asyncio.sleep(0)
                    continue
                taken = self.next()
                if taken is None:
                    self.waiter = self.loop.create_future()
                    await self.waiter
                    self.waiter = None
                    continue
                data, goal = taken
                sending = first_step(send(data))
                if isinstance(sending, Pending):  # it waited for a drain: so may replies
                    await finish(sending)
                    await asyncio.sleep(0)  # those woken by the same drain go first
                if goal is not None:
                    self.feedback_sent(goal)
        except TransportClosed:
            outbox.close()
        except Exception as exc:  # a bug in srvwire: nothing more goes out, say so
            self.failed(exc)

    def stop(self) -> None:
        """The connection ended: end every subscription and stop the task."""
        try:
            self.outbox.close()
        finally:
            if self.task is not None:
                self.task.cancel()


def _peer(address: Any) -> str:
    """``host:port`` (``[v6]:port``) for a TCP peer, else the transport's own name for it."""
    if isinstance(address, tuple) and len(address) >= 2:
        host = str(address[0])
        return f"[{host}]:{address[1]}" if ":" in host else f"{host}:{address[1]}"
    return str(address)


def _method(name: str) -> str:
    """A method name as the access log writes it: as it is when plain, else quoted, and short."""
    if len(name) > 100:
        name = name[:100] + "..."
    return name if name.isprintable() and " " not in name and name else repr(name)


class AccessLog:
    """The access log of one connection: writes its lines, at INFO, on ``log``.

    A line is ``PEER SERVICE OUTCOME DURATION``; a line about a topic is ``PEER METHOD TOPIC
    OUTCOME DURATION``, then its counts as ``name value`` pairs (see docs/logging.md). A name
    that is not plain is quoted and cut short (:func:`_method`); nothing of the credentials is
    ever written. The record carries every field as an attribute too.
    """

    __slots__ = ("log", "peer")

    def __init__(self, log: logging.Logger, peer: Any) -> None:
        self.log = log
        self.peer = _peer(peer)

    def line(
        self,
        service: str,
        outcome: str,
        duration: float | None = None,
        topic: str | None = None,
        **counts: int,
    ) -> None:
        log = self.log
        if not log.isEnabledFor(logging.INFO):
            return
        ms = None if duration is None else round(duration * 1000, 3)
        extra: dict[str, Any] = {
            "peer": self.peer,
            "service": service,
            "outcome": outcome,
            "duration_ms": ms,
        }
        text = "%s %s %s %s"
        args: list[Any] = [self.peer, service, outcome, "-" if ms is None else f"{ms:.2f} ms"]
        if topic is not None:
            text = "%s %s %s %s %s"
            args.insert(2, topic)
            extra["topic"] = topic
        for name, count in counts.items():
            text += f" {name} %d"
            args.append(count)
            extra[name] = count
        log.info(text, *args, extra=extra)


class AccessLoggedOutbox(Outbox):
    """An outbox that also writes the access log's line of each subscription as it ends.

    The line is ``PEER $/subscribe TOPIC OUTCOME DURATION delivered N dropped M``: the outcome
    is ``CLOSED`` when the connection went away, else the status of the reply that ended it
    (``CANCELLED``, ``DEADLINE_EXCEEDED``, ``RESOURCE_EXHAUSTED``, ``SERVICE_NOT_FOUND`` for a
    topic removed); the duration runs from ``$/subscribe`` until the end; ``delivered`` counts
    the messages written, ``dropped`` the ones best effort dropped. Only a connection with the
    access log on has one, so counting the messages costs nothing otherwise.
    """

    __slots__ = ("access", "counts")

    def __init__(
        self,
        wake: Callable[[], object],
        budget: int,
        buffered: Callable[[], int],
        writable: Callable[[], bool],
        *,
        access: AccessLog,
    ) -> None:
        super().__init__(wake, budget, buffered, writable)
        self.access = access
        # Each running subscription's start (on perf_counter), messages delivered and dropped.
        self.counts: dict[Subscription, list[Any]] = {}

    def subscribe(self, id: Id, topic: Topic[Any], qos: QoS) -> Subscription:
        started = time.perf_counter()
        subscription = super().subscribe(id, topic, qos)
        if subscription.id in self.subscriptions:  # not ended as its history was replayed
            self.counts.setdefault(subscription, [started, 0, 0])
        return subscription

    def next(self) -> bytes | None:
        ready = self.ready
        if self.control or not ready:
            return super().next()
        subscription = ready[0]  # the one whose message is taken
        dropped = subscription.dropped
        data = super().next()
        counts = self.counts.get(subscription)
        if counts is not None:
            counts[1] += 1
            counts[2] += dropped
        return data

    def end(self, subscription: Subscription, error: RPCError | None) -> bool:
        dropped = subscription.dropped  # dropped since its last message, never said
        ended = super().end(subscription, error)
        if ended:
            now = time.perf_counter()
            started, delivered, said = self.counts.pop(subscription, (now, 0, 0))
            self.access.line(
                SUBSCRIBE_METHOD,
                "CLOSED" if error is None else _outcome(error),
                now - started,
                _method(subscription.topic.name),
                delivered=delivered,
                dropped=said + dropped,
            )
        return ended


class AccessLoggedSession(ServerSession[ServiceEntry]):
    """A server session that also writes the access log: one line per call, at INFO.

    A line is ``PEER SERVICE OUTCOME DURATION``, as ``127.0.0.1:50312 /add_two_ints OK
    0.42 ms``. The outcome is ``OK`` or the status name of the error answered (an application
    error adds its code); the duration runs from the call's admission until its reply was sent.
    A call answered at once without running anything (a service that does not exist, too many
    calls in flight, shutdown, discovery, ``$/cancel``) shows ``-`` for its duration; a call
    whose connection went away before its reply shows ``CLOSED``. Notifications have no line.

    Topics (``$/subscribe`` and ``$/publish`` name their topic after the method): a
    subscription has its line when it ends (:class:`AccessLoggedOutbox`); an acknowledged
    publish is a call, with its line once answered; publishes without an answer are counted
    per topic, and :meth:`summarize` writes one line per topic when the connection ends:
    ``PEER $/publish TOPIC OUTCOME DURATION received N invalid M``, where the outcome is
    ``OK``, or ``INVALID_PARAMS`` when some were invalid, and the duration runs from the first
    message to the last (a topic removed meanwhile has its line then).

    A connection uses this class only when the access log is on, so a server without it does
    no work for it on any call or message.
    """

    def __init__(
        self,
        services: ServiceRegistry,
        *,
        max_in_flight: int,
        max_batch: int,
        scopes: frozenset[str] = frozenset(),
        access_log: logging.Logger,
        peer: Any,
        topics: Any = None,
        outbox: Outbox | None = None,
        max_subscriptions: int = 256,
    ) -> None:
        super().__init__(
            services,
            max_in_flight=max_in_flight,
            max_batch=max_batch,
            scopes=scopes,
            topics=topics,
            outbox=outbox,
            max_subscriptions=max_subscriptions,
        )
        self.access = (
            outbox.access if isinstance(outbox, AccessLoggedOutbox) else AccessLog(access_log, peer)
        )
        self.access_log = access_log
        self.peer = self.access.peer
        self.admitted: dict[Call[ServiceEntry], float] = {}  # when, on perf_counter
        self.outcomes: dict[Call[ServiceEntry], str] = {}
        self.refused: RPCError | None = None  # how the request being admitted was answered
        self.acknowledging: dict[Id, float] = {}  # acknowledged publishes, when admitted
        # Publishes without an answer, by topic: the first's and last's time, how many, invalid.
        self.published: dict[str, list[Any]] = {}

    def _admit(
        self,
        id: Id,
        method: str,
        params: Any,
        timeout: float | None,
        batch: Any,
        events: list[Any],
    ) -> bytes | Call[ServiceEntry] | None:
        self.refused = None
        admitted = super()._admit(id, method, params, timeout, batch, events)
        if type(admitted) is bytes:
            refused = self.refused
            if method == SUBSCRIBE_METHOD or method == PUBLISH_METHOD:
                # Refused by the topics, whose error replies do not pass through _refuse.
                self.line(method, _status_of(admitted), topic=_topic_param(params))
            else:
                self.line(_method(method), "OK" if refused is None else _outcome(refused))
        elif admitted is not None:  # None: a subscription, or a publish, answered later
            assert isinstance(admitted, Call)
            self.admitted[admitted] = time.perf_counter()
        return admitted

    def _refuse(self, id: Id, error: RPCError) -> bytes:
        self.refused = error
        return super()._refuse(id, error)

    def _publish(self, params: Any, id: Id) -> Publish | RPCError:
        publish = super()._publish(params, id)
        if not isinstance(publish, Publish):  # refused at once: with an id, _admit writes its line
            return publish
        now = time.perf_counter()
        if id is not None:
            self.acknowledging[id] = now
            return publish
        counts = self.published.get(publish.topic.name)
        if counts is None:
            self.published[publish.topic.name] = [now, now, 1, 0]
        else:
            counts[1] = now
            counts[2] += 1
        return publish

    def publish_done(self, event: Publish, error: RPCError | None) -> None:
        """A publish was handed on (``error`` None) or refused as invalid: an acknowledged one
        has its line now, an invalid one without an answer is counted."""
        topic = event.topic.name
        if event.id is None:
            counts = self.published.get(topic)
            if error is not None and counts is not None:
                counts[3] += 1
            return
        admitted = self.acknowledging.pop(event.id, None)
        duration = None if admitted is None else time.perf_counter() - admitted
        outcome = "OK" if error is None else _outcome(error)
        self.line(PUBLISH_METHOD, outcome, duration, topic=_method(topic))

    def summarize(self, topic: str | None = None) -> None:
        """The connection ended (``topic`` None), or ``topic`` was removed: one line per topic
        it published on without an answer, and counting starts again."""
        if topic is None:
            published, self.published = self.published, {}
        else:
            counts = self.published.pop(topic, None)
            published = {} if counts is None else {topic: counts}
        for name, (first, last, received, invalid) in published.items():
            self.line(
                PUBLISH_METHOD,
                "INVALID_PARAMS" if invalid else "OK",
                last - first,
                topic=_method(name),
                received=received,
                invalid=invalid,
            )

    def reply(self, call: Call[ServiceEntry], result: bytes, whole: bool = False) -> bytes | None:
        if self.answering(call):  # else answered already, and that answer is its outcome
            self.outcomes[call] = "OK"
        return super().reply(call, result, whole)

    def fail(self, call: Call[ServiceEntry], error: RPCError) -> bytes | None:
        if self.answering(call):
            self.outcomes[call] = _outcome(error)
        return super().fail(call, error)

    def sent(self, call: Call[ServiceEntry]) -> None:
        super().sent(call)
        self.ended(call, self.outcomes.pop(call, "INTERNAL"))

    def forget(self, call: Call[ServiceEntry]) -> None:
        super().forget(call)
        self.outcomes.pop(call, None)
        self.ended(call, "CLOSED")

    def ended(self, call: Call[ServiceEntry], outcome: str) -> None:
        admitted = self.admitted.pop(call, None)
        if admitted is not None:
            self.line(call.entry.name, outcome, time.perf_counter() - admitted)

    def line(
        self,
        service: str,
        outcome: str,
        duration: float | None = None,
        topic: str | None = None,
        **counts: int,
    ) -> None:
        self.access.line(service, outcome, duration, topic, **counts)


def _topic_param(params: Any) -> str:
    """The topic a ``$/subscribe`` or ``$/publish`` named, as the access log writes it."""
    name = params.get("topic") if type(params) is dict else None
    return _method(name) if isinstance(name, str) else "-"


def _status_of(reply: bytes) -> str:
    """The outcome of a request answered at once with ``reply``: ``OK``, or its error's
    status (every error reply srvwire writes says its status in its data)."""
    error = json.loads(reply).get("error")
    if error is None:
        return "OK"
    data = error.get("data")
    return str(data.get("status", "INTERNAL")) if isinstance(data, dict) else "INTERNAL"


def _outcome(error: RPCError) -> str:
    if isinstance(error, ServiceError):
        return f"{error.status} {error.code}"
    return error.status


class ServedConnection:
    """One client connection: its session, its reader, and the runner of its calls."""

    __slots__ = (
        "access",
        "conn",
        "drops",
        "drops_level",
        "drops_logged",
        "drops_timer",
        "ended",
        "expiry",
        "flushed",
        "handed",
        "log",
        "loop",
        "outbox",
        "parked",
        "paused",
        "pushed",
        "queue",
        "reader",
        "reading",
        "runner",
        "serving",
        "session",
        "tasks",
        "waiting",
        "writer",
    )

    def __init__(
        self,
        conn: Connection,
        registry: ServiceRegistry,
        *,
        max_in_flight: int,
        max_batch: int = 100,
        notification_timeout: float | None = None,
        executor: Executor | None,
        logger: logging.Logger,
        access_log: logging.Logger | None = None,
        max_queued_bytes: int = 4 * 2**20,
        max_subscriptions: int = 256,
    ) -> None:
        self.conn = conn
        self.log = logger
        identity = getattr(conn, "identity", None)
        scopes: frozenset[str] = getattr(identity, "scopes", frozenset())
        self.loop = asyncio.get_running_loop()
        if access_log is None:
            self.writer = Writer(conn, self.loop, max_queued_bytes)
        else:
            logged = functools.partial(
                AccessLoggedOutbox, access=AccessLog(access_log, conn.remote_address)
            )
            self.writer = Writer(conn, self.loop, max_queued_bytes, logged)
        self.writer.failed = self.writer_failed
        self.outbox = self.writer.outbox
        self.session: ServerSession[ServiceEntry]
        self.access: AccessLoggedSession | None = None  # the session, when it is logged
        if access_log is None:
            self.session = ServerSession(
                registry,
                max_in_flight=max_in_flight,
                max_batch=max_batch,
                scopes=scopes,
                topics=registry.topics,
                outbox=self.writer.outbox,
                max_subscriptions=max_subscriptions,
            )
        else:
            self.session = AccessLoggedSession(
                registry,
                max_in_flight=max_in_flight,
                max_batch=max_batch,
                scopes=scopes,
                access_log=access_log,
                peer=conn.remote_address,
                topics=registry.topics,
                outbox=self.writer.outbox,
                max_subscriptions=max_subscriptions,
            )
            self.access = self.session
        self.runner = CallRunner(
            self.session,
            self.outbox,
            conn=conn,
            peer=conn.remote_address,
            executor=executor,
            logger=logger,
            notification_timeout=notification_timeout,
            identity=identity,
            channel=self,
        )
        # Goals' feedback: keep-latest per goal, sent by the writer as topic data is.
        self.writer.feedback_sent = self.release
        self.flushed: dict[Any, list[asyncio.Future[None]]] = {}  # feedback_flushed's waiters
        self.drops = 0  # notifications dropped and not logged yet
        self.drops_level = logging.INFO  # the most serious level among them
        self.drops_logged = -DROP_LOG_INTERVAL  # when a line about drops was last written
        self.drops_timer: asyncio.TimerHandle | None = None  # says the count when it fires
        # Credentials that expire: past then, the session answers UNAUTHENTICATED.
        expires = getattr(identity, "expires", None)
        self.expiry: asyncio.TimerHandle | None = None
        if expires is not None:
            self.expiry = self.loop.call_later(max(0.0, expires - time.time()), self.expire)
        self.tasks: set[asyncio.Task[Any]] = set()  # other tasks: announcements
        self.reader: asyncio.Task[None] | None = None  # the task reading the socket now
        self.reading: asyncio.Future[None] = self.loop.create_future()  # done: reading ended
        # Pushed messages (see the invariants).
        self.pushed = False  # whether messages are pushed
        self.queue: deque[str | bytes] | None = None  # pushed, not yet taken (made when needed)
        self.paused = False  # whether the queue made the transport stop reading
        self.parked: asyncio.Future[None] | None = None  # the reader waits here for messages
        self.handed: Pending | Handed | None = None  # what the parked reader is to finish
        self.waiting: tuple[Work, Pending] | None = None  # what handle() found has to wait
        self.ended: TransportClosed | None = None  # how the connection ended
        self.serving: asyncio.Task[Any] | None = None  # the task running serve()

    @property
    def peer(self) -> Any:
        """Who is at the other end, as the transport names it."""
        return self.runner.peer

    @property
    def counted(self) -> set[asyncio.Task[Any]]:
        """The tasks of calls and notifications in flight (see the module's invariants)."""
        return self.runner.counted

    def spawn(self, coro: Any) -> asyncio.Task[Any]:
        task: asyncio.Task[Any] = self.loop.create_task(coro)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    async def send(self, data: bytes) -> None:
        """Send one message ahead of the topic data the outbox holds (see
        :meth:`CallRunner.send_ahead`)."""
        await self.runner.send_ahead(data)

    # --- goals' feedback (what an action's GoalHandle needs of its connection) ----------------

    @property
    def executor(self) -> Executor | None:
        """Where a plain ``def`` action handler runs."""
        return self.runner.executor

    @property
    def closing(self) -> bool:
        """Whether the server is shutting down: a goal accepted now is asked to stop."""
        return self.session.closing

    def feedback(self, call: Any, message: bytes) -> None:
        """Keep ``message`` as the goal ``call``'s latest feedback, and have it sent."""
        waiting = self.writer.feedback
        if call in waiting:
            self.release(call)  # its waiting message is superseded
        waiting.put(call, message)
        self.writer.wake()

    async def feedback_flushed(self, call: Any) -> None:
        """Wait until the goal ``call`` has no feedback waiting: it went out, was superseded,
        or the goal ended."""
        if call not in self.writer.feedback:
            return
        waiter: asyncio.Future[None] = self.loop.create_future()
        self.flushed.setdefault(call, []).append(waiter)
        await waiter

    def release(self, call: Any) -> None:
        """The goal ``call``'s feedback went out, was superseded, or was dropped."""
        for waiter in self.flushed.pop(call, ()):
            if not waiter.done():
                waiter.set_result(None)

    def goal_done(self, call: Any) -> None:
        """The goal ``call`` ended: the feedback it had not sent is dropped."""
        self.writer.feedback.discard(call)
        self.release(call)

    def expire(self) -> None:
        """The connection's credentials expired (see :meth:`ServerSession.expire`)."""
        self.expiry = None
        self.session.expire()
        self.log.info("the credentials of the connection from %s expired", self.peer)

    def writer_failed(self, exc: Exception) -> None:
        """The writer stopped on a failure inside srvwire: log it and end the connection with
        1011, as a handler that raises does, since nothing more would be sent on it."""
        self.log.error(
            "the writer of the connection from %s failed inside srvwire; closing the connection",
            self.peer,
            exc_info=exc,
        )
        self.spawn(self.conn.close(1011))

    def cancel_all(self, error: RPCError | None) -> None:
        """Cancel every call in flight; with ``error`` they answer it, without they stay silent.

        Without ``error`` (the connection is gone) every task is cancelled, even one that has
        not started; since such a task never runs its coroutine's ``finally``, each counted
        task gets a done-callback that settles it. Each step of that cleanup runs even if
        one before it fails inside srvwire (logged), so that nothing of the connection stays.
        """
        runner = self.runner
        for cancel in self.session.cancel_all(error):
            runner.cancel(cancel.call, cancel.error)
        if error is None:
            for step in (self.writer.stop, self.summarize, self.stop_tasks):
                try:
                    step()
                except Exception:
                    self.log.exception(
                        "ending the connection from %s failed inside srvwire", self.peer
                    )

    def summarize(self) -> None:
        if self.access is not None:
            self.access.summarize()

    def stop_tasks(self) -> None:
        """Cancel the expiry timer, the connection's tasks and its counted calls."""
        if self.expiry is not None:
            self.expiry.cancel()
            self.expiry = None
        for task in list(self.tasks):
            task.cancel()
        counted = self.runner.counted
        for task in list(counted):
            task.cancel()
            task.add_done_callback(counted.discard)

    # --- reading ------------------------------------------------------------------------------

    async def serve(self) -> None:
        """Read the connection until it ends, one reader task at a time (see :meth:`read`):
        pushed messages where the transport hands them over as they arrive, else pulled."""
        self.serving = asyncio.current_task()
        self.pushed = CAN_PUSH  # before deliver_to, which hands over what it holds already
        if CAN_PUSH and not self.conn.deliver_to(self.receive):
            self.pushed = False
        self.start_reader()
        try:
            if self.pushed:
                self.reading.add_done_callback(self.reading_ended)
                await self.watch_end()
            await self.reading
        finally:
            self.log_drops()
            if not self.reading.done():  # this handler was cancelled: stop reading too
                self.reading.remove_done_callback(self.reading_ended)
                self.reading.cancel()
                if self.reader is not None:
                    self.reader.cancel()

    def start_reader(self) -> None:
        # A plain task, not the loop's task factory: an eager factory would run the new reader
        # inside this call, before it is recorded, and nest one reader in the next.
        self.reader = asyncio.Task(self.read(), loop=self.loop)

    async def read(self) -> None:
        """Read and answer messages until the connection ends or a call has to wait.

        A call that has to wait keeps this task, and a new reader takes over; the call's
        deadline is armed then, and only then.
        """
        task = asyncio.current_task()
        assert task is not None
        waiting: tuple[Work, Pending] | Handed | None
        try:
            if not self.pushed:
                waiting = await self.read_until_a_call_waits(task)
            else:
                waiting = await self.take_pushed()
        except asyncio.CancelledError:
            self.reading.cancel()
            raise
        except BaseException as exc:  # the connection ended, or a bug in srvwire
            if not self.reading.done():
                self.reading.set_exception(exc)
            if not isinstance(exc, TransportClosed):
                raise
            return
        if waiting is None:
            if not self.reading.done():
                self.reading.set_result(None)
            return
        if isinstance(waiting, Handed):  # taken over as it was handed to this task
            steps, timer = waiting.steps, waiting.timer
        else:
            work, steps = waiting
            timer = self.take_over(work, task)
        try:
            await finish(steps)
        finally:
            if timer is not None:
                timer.cancel()
            self.runner.counted.discard(task)

    def take_over(self, work: Work, task: asyncio.Task[Any]) -> asyncio.TimerHandle | None:
        """Make ``task``, the reader a call's first step ran on, the call's own (counted, and
        what cancels it), arm the call's deadline, and start a new reader; return the timer."""
        runner = self.runner
        runner.counted.add(task)
        work.task = task
        if type(work) is Call:
            work.started = True
            context = work.context
            if context is not None and context.cancelled:  # cancelled while its first step ran
                runner.cancel(work, context._cancel_error)
        timer = runner.arm(work)
        self.start_reader()
        return timer

    async def read_until_a_call_waits(self, task: asyncio.Task[Any]) -> tuple[Work, Pending] | None:
        """Pull messages and answer them, as ``task``; return a call or notification that has
        to wait, and its steps; return None when the connection ended cleanly."""
        conn = self.conn
        while True:
            try:
                if conn.congested:  # read nothing while what waits to be sent is past the budget
                    await conn.writable()
                data = await conn.recv()
            except TransportClosed as exc:
                if exc.clean:
                    return None
                raise
            rest = self.handle(data, task)
            if rest is not None:
                await rest
            waiting = self.waiting
            if waiting is not None:
                self.waiting = None
                return waiting

    # Pushed messages (see the module's invariants).

    def receive(self, data: str | bytes) -> None:
        """Take one message as the transport hands it over (:meth:`Connection.deliver_to`).

        When the reader is parked with nothing queued and the connection is not congested, the
        message is answered here, in the transport's read callback, as the reader: what would
        wait is handed to the reader to finish. Otherwise it is queued for the reader.
        """
        parked = self.parked
        loop = self.loop
        if (
            parked is None
            or parked.done()
            or self.queue
            or self.conn.congested
            or _current_task(loop) is not None
        ):
            self.hold(data)
            return
        reader = self.reader
        assert reader is not None
        pending = None
        _enter_task(loop, reader)
        try:
            handling = self.handle(data, reader)
            # Stepped as a for loop steps an iterator: one that ends raises no StopIteration.
            if handling is not None:
                for yielded in handling.__await__():
                    pending = Pending(handling, yielded, None)
                    break
        except Exception as exc:  # a bug in srvwire: the reading ends with it, as a reader's would
            if not self.reading.done():
                self.reading.set_exception(exc)
            reader.cancel()
            return
        finally:
            _leave_task(loop, reader)
        assert self.handed is None
        if pending is not None:  # answering it waits itself: a send held back, say
            self.handed = pending
        else:
            waiting = self.waiting
            if waiting is None:
                return  # answered
            self.waiting = None  # a call that has to wait: the reader becomes its task
            work, steps = waiting
            self.handed = Handed(steps, self.take_over(work, reader))
        if not parked.done():  # else cancelled meanwhile: the reader wakes all the same
            parked.set_result(None)

    def hold(self, data: str | bytes) -> None:
        """Queue a pushed message for the reader, and wake it if it is parked; past
        :data:`PUSH_HIGH_WATER` messages queued, read the network no further."""
        if not self.pushed or self.reading.done():
            return
        queue = self.queue
        if queue is None:
            queue = self.queue = deque()
        queue.append(data)
        if len(queue) >= PUSH_HIGH_WATER:  # every time: a transport may have resumed meanwhile
            self.paused = True
            self.conn.pause_reading()
        parked = self.parked
        if parked is not None and not parked.done():
            parked.set_result(None)

    async def take_pushed(self) -> tuple[Work, Pending] | Handed | None:
        """Answer the queued messages, then park until one is handed over or queued; return a
        call or notification that has to wait, and its steps (:class:`Handed` when it was
        handed over already taken over); return None when the connection ended cleanly."""
        conn = self.conn
        loop = self.loop
        task = asyncio.current_task(loop)
        assert task is not None
        waiting: tuple[Work, Pending] | None
        while True:
            while queue := self.queue:
                if conn.congested:  # read nothing while what waits to be sent is past the budget
                    try:
                        await conn.writable()
                    except TransportClosed as exc:
                        if exc.clean:
                            return None
                        raise
                    continue
                data = queue.popleft()
                if self.paused and len(queue) <= PUSH_LOW_WATER:
                    self.paused = False
                    conn.resume_reading()
                rest = self.handle(data, task)
                if rest is not None:
                    await rest
                waiting = self.waiting
                if waiting is not None:
                    self.waiting = None
                    return waiting
            ended = self.ended
            if ended is not None:
                if ended.clean:
                    return None
                raise ended
            parked = self.parked = loop.create_future()
            try:
                await parked
            except asyncio.CancelledError:
                if self.handed is None:
                    raise
                # Meant for what was handed over, which this task would have been running:
                # requested again, it is delivered where that waits, as it would have been.
                task.cancel()
                task.uncancel()
            finally:
                if self.parked is parked:
                    self.parked = None
            handed, self.handed = self.handed, None
            if isinstance(handed, Handed):
                return handed
            if handed is not None:
                await finish(handed)
                waiting = self.waiting
                if waiting is not None:
                    self.waiting = None
                    return waiting

    async def watch_end(self) -> None:
        """Wait for the end of a connection whose messages are pushed (what :meth:`serve`
        does first), and wake the reader to finish what is queued and end the reading."""
        try:
            message = await self.conn.recv()
        except TransportClosed as exc:
            self.ended = exc
        else:  # a transport that breaks deliver_to's rule: fail loudly, not silently
            error = RuntimeError(f"{self.conn!r} returned {message!r} from recv after deliver_to")
            if not self.reading.done():
                self.reading.set_exception(error)
            return
        parked = self.parked
        if parked is not None and not parked.done():
            parked.set_result(None)

    def reading_ended(self, reading: asyncio.Future[None]) -> None:
        """The reading of pushed messages failed (a bug in srvwire) or was cancelled (by a
        handler that answered inline, kept ``asyncio.current_task()`` and cancelled it later;
        :meth:`serve` takes this callback off before it stops the reading itself) before the
        connection ended: end it, with 1011 as a handler that raises does, so that
        :meth:`serve` stops waiting for the end, as a pulling reader's end stops it."""
        if self.ended is not None:
            return
        if reading.cancelled():
            serving = self.serving
            if serving is None or serving.done() or serving.cancelling():
                return  # serve() is being stopped too (an event loop that ends cancels all)
            self.log.error(
                "the reader of the connection from %s was cancelled by a handler that had "
                "answered on it; closing the connection",
                self.peer,
            )
            self.spawn(self.conn.close(1011))
            return
        failure = reading.exception()
        if failure is not None and not isinstance(failure, TransportClosed):
            self.spawn(self.conn.close(1011))

    def handle(
        self, data: str | bytes, reader: asyncio.Task[Any]
    ) -> Coroutine[Any, Any, None] | None:
        """Do what one message asks, as ``reader`` (the task current while it runs); return
        what is left to await, None when nothing is. A call or notification that has to wait
        is left in :attr:`waiting` with its steps, before anything after it in the message.

        A lone call, the usual message, is started here, with no coroutine of its own (what
        a call needs of one, its steps, are :meth:`CallRunner.run_call`'s); any other message
        is :meth:`handle_events`'s.
        """
        events = self.session.receive(data)
        if len(events) == 1:
            call = events[0]
            if type(call) is Call and call.batch is None:  # as handle_events starts it
                timeout = call.timeout  # its deadline, as runner.begin sets it (no context yet)
                if timeout is not None:
                    call.deadline = time.monotonic() + timeout
                steps = first_step(self.runner.run_call(call), copy_context())
                if steps is not None:
                    self.waiting = (call, steps)
                elif reader.cancelling():
                    return self.ignore_cancellation(call.entry)
                return None
        return self.handle_events(events, reader)

    async def handle_events(self, events: list[Any], reader: asyncio.Task[Any]) -> None:
        """Do what :meth:`handle` leaves to a coroutine: the events of one message, in order
        (returning nothing, a finished handling costs its caller no ``StopIteration``)."""
        runner = self.runner
        for event in events:
            kind = type(event)
            if kind is bytes:
                await runner.send_ahead(event)
            elif kind is Call:
                if event.batch is not None:
                    runner.start_in_task(event)
                    continue
                timeout = event.timeout  # its deadline, as runner.begin sets it (no context yet)
                if timeout is not None:
                    event.deadline = time.monotonic() + timeout
                steps = first_step(runner.run_call(event), copy_context())
                if isinstance(steps, Pending):
                    self.waiting = (event, steps)
                    return
                if reader.cancelling():
                    await self.ignore_cancellation(event.entry)
            elif kind is NotificationCall:
                if event.in_batch:
                    runner.start_in_task(event)
                    continue
                runner.begin(event)
                try:
                    steps = first_step(runner.run_notification(event), copy_context())
                except asyncio.CancelledError:  # only the handler can have cancelled it
                    steps = None
                if isinstance(steps, Pending):
                    self.waiting = (event, steps)
                    return
                if reader.cancelling():
                    await self.ignore_cancellation(None)
            elif kind is CancelCall:
                canceling = runner.request_cancel(event.call, event.error)
                if canceling is not None:
                    await self.send(canceling)
            elif kind is Publish:
                await self.publish(event)
            elif kind is SubscriptionDeadline:
                subscription = event.subscription
                subscription.timer = self.loop.call_later(
                    event.timeout,
                    self.writer.outbox.expire,
                    subscription,
                    event.timeout,
                )
            elif kind is RefusedMessage:
                self.log_drop(
                    logging.INFO, "dropped a message on %s from %s: %s", event.topic, event.reason
                )
            else:
                assert kind is Dropped
                self.log_drop(
                    logging.WARNING if event.busy else logging.INFO,
                    "dropped a notification to %s from %s: %s",
                    event.entry.name,
                    event.reason,
                )

    async def publish(self, event: Publish) -> None:
        """A message a client published: validate it, hand it to the server's handlers (an
        async one in a task of its own), then to the topic's subscribers; acknowledge it when
        asked. A message that does not fit is answered INVALID_PARAMS, or logged."""
        topic = event.topic
        entry = topic.entry  # a srvwire.pubsub.TopicEntry
        try:
            message = entry.validate(event.message, wire=True)
        except RPCError as exc:
            if event.id is not None:
                await self.send(self.session.refuse(event.id, exc))
            else:
                self.log.info("dropped a message on %s from %s: %s", topic.name, self.peer, exc)
            if self.access is not None:
                self.access.publish_done(event, exc)
            return
        for handler in entry.handlers:
            try:
                result = handler(message)
                if asyncio.iscoroutine(result):
                    self.spawn(self.run_topic_handler(topic.name, result))
            except Exception:
                self.log.exception("the handler of %s failed", topic.name)
        topic.publish(entry.write(message))
        if event.id is not None:
            await self.send(publish_ack(event.id))
            if self.access is not None:
                self.access.publish_done(event, None)

    async def run_topic_handler(self, name: str, coro: Any) -> None:
        try:
            await coro
        except Exception:
            self.log.exception("the handler of %s failed", name)

    def log_drop(self, level: int, line: str, name: str, reason: str) -> None:
        """Log a dropped notification or published message (``line`` takes its service or
        topic ``name``, the peer and the ``reason``), or count it if a line about drops was
        written less than :data:`DROP_LOG_INTERVAL` ago; the count is said when that interval
        ends."""
        now = self.loop.time()
        if now - self.drops_logged < DROP_LOG_INTERVAL:
            self.drops += 1
            self.drops_level = max(self.drops_level, level)
            if self.drops_timer is None:
                wait = self.drops_logged + DROP_LOG_INTERVAL - now
                self.drops_timer = self.loop.call_later(wait, self.log_drops)
            return
        self.drops_logged = now
        self.log.log(level, line, name, self.peer, reason)

    def log_drops(self) -> None:
        """Say how many notifications were dropped without a line of their own, at the level
        the most serious of them had."""
        if self.drops_timer is not None:
            self.drops_timer.cancel()
            self.drops_timer = None
        if self.drops:
            self.log.log(
                self.drops_level,
                "dropped %d more %s from %s since the last line about one",
                self.drops,
                "notification" if self.drops == 1 else "notifications",
                self.peer,
            )
            self.drops = 0
            self.drops_level = logging.INFO
            self.drops_logged = self.loop.time()

    async def ignore_cancellation(self, entry: ServiceEntry | None) -> None:
        """Take back a cancellation of the reader that a handler requested while it ran inline.

        Nothing else can cancel the reader while a call runs on it without waiting: the handler
        cancelled what it took for its own task (``asyncio.current_task().cancel()``), and that
        call is over. The request is delivered at the reader's next suspension; it is made here,
        and taken back, so that it can reach neither the reading nor the next call.
        """
        what = f"the handler for {entry.name}" if entry is not None else "a notification handler"
        self.log.warning("%s cancelled its own task without waiting for anything; ignored", what)
        try:
            await asyncio.sleep(0)
        except asyncio.CancelledError:
            if self.reading.done():  # serve() stopped the reading meanwhile: stop
                raise
        task = asyncio.current_task(self.loop)
        while task is not None and task.cancelling():
            task.uncancel()
