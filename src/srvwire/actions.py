"""Actions: a goal, its feedback and its outcome, on both sides of a connection.

An action is served as a service whose request is the action's ``Goal`` and whose response is
its *outcome*, ``{"status": ..., "result": Result}`` (:func:`goal_service` builds that type
once per action class). So a goal is one call, and deadlines, ``$/cancel``, typed errors and
"a connection that ends fails what is pending" apply to it unchanged. The rules of the wire
(states, notifications, keep-latest feedback) are :mod:`srvwire.goals`'.

Server invariants:

* **A goal is accepted before its handler runs**: ``accept`` (when given) refuses it with
  :class:`~srvwire.errors.GoalRejected` (or by returning False), and the refusal is the
  call's error reply; otherwise ``$/goal accepted`` then ``$/goal executing`` are sent, in
  that order, before the handler starts.
* **``max_concurrency`` counts handlers, as a service's does.** An accepted goal waits for a
  slot of its action, in order, in the state ``accepted``; ``executing`` is sent when it has
  one. Its deadline still ends the wait, and a cancellation asked for meanwhile ends the goal
  ``canceled`` with the result's defaults, its handler never run. A plain ``def`` handler's
  thread holds its slot until the handler returns, even after the goal was answered; one
  whose goal ended before a thread took it never runs.
* **Shutdown asks before it cuts.** When the server shuts down, each running goal is asked
  to stop exactly as a client's cancellation asks (``$/goal canceling``,
  :attr:`GoalHandle.cancel_requested`), but has the server's ``grace_period`` instead of the
  action's ``cancel_grace``; one still running when that passes is cancelled with the other
  calls, and answers ``UNAVAILABLE``.
* **The outcome's status is the handler's word, else the cancellation's**: a handler that
  called :meth:`GoalHandle.abort`, :meth:`GoalHandle.succeed` or :meth:`GoalHandle.canceled`
  gets that status; otherwise a goal whose cancellation was requested ends ``canceled`` and
  any other ``succeeded``. An exception is the call's error, as for a service.
* **Feedback is validated and written once**, by the handler's own thread, then handed to
  the connection's keep-latest outbox; feedback given after the outcome is ignored.
  ``await handle.feedback(...)`` returns once that message left the outbox (sent, replaced,
  or the goal ended); ``publish_feedback`` never waits.

Client invariants:

* :meth:`ClientGoal.result` never loses a result: a cancellation only *asks* the server,
  and whatever the server answers (a result, or ``CANCELLED`` when the handler was stopped)
  is the goal's outcome.
* A client keeps only the latest feedback of a goal too: :meth:`ClientGoal.feedback` yields
  the newest one each time it is read, so a slow reader skips, never queues.
"""

from __future__ import annotations

import asyncio
import functools
import inspect
import threading
import types
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Literal, Protocol, TypeVar, cast

import pydantic
from pydantic import BaseModel, ValidationError

from srvwire.errors import Cancelled, DeadlineExceeded, GoalRejected, InvalidRequest, RPCError
from srvwire.goals import (
    GoalNews,
    advance,
    feedback_notification,
    goal_notification,
)
from srvwire.models import (
    Action,
    Message,
    ModelDecoder,
    Service,
    dump_json,
    error_data,
    summarize_errors,
    validate_python,
    validate_wire,
)
from srvwire.threads import ConcurrencyLimit, SlotJob

__all__ = [
    "ClientGoal",
    "GoalChannel",
    "GoalHandle",
    "GoalResult",
    "GoalRunner",
    "goal_service",
    "reply_done",
]

DEFAULT_CANCEL_GRACE = 5.0
"""Seconds a goal's handler has, after its cancellation was asked for, to return."""

R = TypeVar("R")
_FINAL: Any = Literal["succeeded", "canceled", "aborted"]  # an outcome's status


class GoalService(Service):
    """The service an action is served as: ``Request`` is its goal, ``Response`` its outcome."""

    action: ClassVar[type[Action]]
    Feedback: ClassVar[type[Message]]


def goal_service(action: type[Action]) -> type[GoalService]:
    """Return the service type ``action`` is served as (built once per action class)."""
    built = action.__dict__.get("_srvwire_goal_service")
    if built is not None:
        return cast("type[GoalService]", built)
    outcome = pydantic.create_model(
        f"{action.__name__}_Outcome",
        __config__=pydantic.ConfigDict(extra="forbid"),
        status=(_FINAL, ...),
        result=(action.Result, ...),
    )
    namespace = {
        "__module__": action.__module__,
        "__qualname__": f"{action.__qualname__}_Goal",
        "Request": action.Goal,
        "Response": outcome,
        "Feedback": action.Feedback,
        "action": action,
        "type_name": action.type_name,
        "text": getattr(action, "text", ""),
    }
    service = types.new_class(
        f"{action.__name__}_GoalService",
        (GoalService,),
        {},
        lambda ns: ns.update(namespace),
    )
    type.__setattr__(action, "_srvwire_goal_service", service)
    return cast("type[GoalService]", service)


# --- the server's side ---------------------------------------------------------------------------


class GoalChannel(Protocol):
    """What a goal needs of the connection it came on (a served connection is one)."""

    @property
    def loop(self) -> asyncio.AbstractEventLoop: ...

    @property
    def executor(self) -> Executor | None: ...

    @property
    def closing(self) -> bool:
        """Whether the server is shutting down: a goal accepted now is asked to stop at once."""
        ...

    async def send(self, data: bytes) -> None:
        """Send a control message (a ``$/goal``), ahead of any feedback."""
        ...

    def feedback(self, call: Any, message: bytes) -> None:
        """Keep ``message`` as the call's latest feedback (on the loop's thread)."""
        ...

    def goal_done(self, call: Any) -> None:
        """The call's outcome is written: its pending feedback is dropped."""
        ...

    async def feedback_flushed(self, call: Any) -> None:
        """Wait until the call has no feedback waiting to be sent."""
        ...


class GoalHandle:
    """What an action's handler holds for its goal: feedback out, cancellation in.

    ``handler(goal, handle)``: send progress with ``await handle.feedback(...)`` (or
    :meth:`publish_feedback` from a plain ``def`` handler's thread), watch
    :attr:`cancel_requested` (or ``await handle.cancelled()``, or
    :meth:`wait_for_cancel` on a thread), and return the result.
    """

    __slots__ = (
        "_cancel_event",
        "_cancel_waiters",
        "_closed",
        "_final",
        "_grace",
        "_seq",
        "call",
        "cancel_grace",
        "cancel_requested",
        "channel",
        "context",
        "feedback_model",
        "goal",
        "goal_id",
        "name",
        "status",
    )

    def __init__(
        self,
        name: str,
        goal: Message,
        context: Any,
        channel: GoalChannel,
        feedback_model: type[Message],
        cancel_grace: float,
    ) -> None:
        self.name = name
        """The action's canonical name."""
        self.goal = goal
        self.context = context
        """The call's :class:`~srvwire.dispatch.Context` (identity, peer, deadline)."""
        self.channel = channel
        self.feedback_model = feedback_model
        self.cancel_grace = cancel_grace
        self.call = context.request_id
        self.goal_id = str(uuid.uuid4())
        """The goal's id, a UUID, as the ``$/goal`` notifications name it."""
        self.status = "accepted"
        """The goal's state: ``accepted``, ``executing``, ``canceling``."""
        self.cancel_requested = False
        """Whether the client asked to cancel the goal, or the server is shutting down: stop,
        and return what there is."""
        self._cancel_waiters: list[asyncio.Future[None]] = []
        self._cancel_event = threading.Event()  # for a plain def handler's thread
        self._closed = False
        self._final: str | None = None
        self._grace: asyncio.TimerHandle | None = None
        self._seq = 0

    def __repr__(self) -> str:
        return f"<GoalHandle {self.name} goal {self.goal_id} {self.status}>"

    # --- feedback -------------------------------------------------------------------------------

    async def feedback(self, feedback: BaseModel | dict[str, Any]) -> None:
        """Send ``feedback`` (a ``Feedback`` or a dict of its fields), and wait until the
        connection took it: sent, or superseded by newer feedback. So an ``async`` handler
        that reports in a loop goes at the pace of its client, and holds one message."""
        self.publish_feedback(feedback)
        await self.channel.feedback_flushed(self.call)

    def publish_feedback(self, feedback: BaseModel | dict[str, Any]) -> None:
        """Send ``feedback`` from any thread (a plain ``def`` handler's too); never waits. An
        older feedback not sent yet is replaced (keep-latest). Raise ``ValueError``
        (pydantic's) for feedback that does not fit."""
        if self._closed:
            return
        model = self.feedback_model
        value = feedback if isinstance(feedback, model) else validate_python(model, feedback)
        self._seq += 1
        message = feedback_notification(self.call, self._seq, dump_json(value, strict=True))
        loop = self.channel.loop
        if _on_thread_of(loop):
            self.channel.feedback(self.call, message)
        else:
            loop.call_soon_threadsafe(self._put, message)

    def _put(self, message: bytes) -> None:
        if not self._closed:
            self.channel.feedback(self.call, message)

    # --- cancellation and the outcome -----------------------------------------------------------

    async def cancelled(self) -> None:
        """Return once the goal was asked to stop, by its client or by the server's shutdown
        (at once if it was)."""
        if self.cancel_requested:
            return
        waiter: asyncio.Future[None] = self.channel.loop.create_future()
        self._cancel_waiters.append(waiter)
        try:
            await waiter
        finally:
            if waiter in self._cancel_waiters:
                self._cancel_waiters.remove(waiter)

    def wait_for_cancel(self, timeout: float | None = None) -> bool:
        """Block a plain ``def`` handler's thread until the goal is asked to stop (by its
        client, or the server's shutdown) or ends without it (its deadline passed, its
        connection closed), or ``timeout`` seconds pass; return whether it should stop. Never
        call it on the event loop.

        ``if handle.wait_for_cancel(0.2): break`` is a step of work that stops at once when
        cancelled."""
        return self._cancel_event.wait(timeout)

    def succeed(self) -> None:
        """End the goal ``succeeded`` when the handler returns, even if cancelling."""
        self._final = "succeeded"

    def abort(self) -> None:
        """End the goal ``aborted`` when the handler returns: it could not reach it."""
        self._final = "aborted"

    def canceled(self) -> None:
        """End the goal ``canceled`` when the handler returns."""
        self._final = "canceled"

    def request_cancel(self, stop: Callable[[], None] | None) -> bytes | None:
        """The client (or the server's shutdown) asked to cancel (server use, on the loop):
        mark it, wake the handler, and arm ``stop`` after the action's grace period (without
        ``stop``, whoever asked keeps time). Return the ``$/goal canceling`` to send, or None
        when a cancellation was asked for already or the goal is over."""
        if self.cancel_requested or self._closed:
            return None
        self.cancel_requested = True
        self.status = "canceling"
        self._cancel_event.set()
        for waiter in self._cancel_waiters:
            if not waiter.done():
                waiter.set_result(None)
        if stop is not None:
            self._grace = self.channel.loop.call_later(self.cancel_grace, stop)
        return goal_notification(self.call, self.goal_id, "canceling")

    def outcome_status(self) -> str:
        if self._final is not None:
            return self._final
        return "canceled" if self.cancel_requested else "succeeded"

    def close(self) -> None:
        """The goal ended (its handler returned, or was cut off by a deadline, a lost
        connection or the grace period): no more feedback, no grace timer, pending feedback
        dropped, and a handler still running on a thread told to stop. Once only: a goal
        answered while its handler runs on is closed then, and its handler's end changes
        nothing (its call's id may be another goal's by then)."""
        if self._closed:
            return
        self._closed = True
        self._cancel_event.set()
        if self._grace is not None:
            self._grace.cancel()
            self._grace = None
        self.channel.goal_done(self.call)


def _on_thread_of(loop: asyncio.AbstractEventLoop) -> bool:
    try:
        return asyncio.get_running_loop() is loop
    except RuntimeError:
        return False


Accept = Callable[[Any], Any]
"""``accept(goal)``: return True (or None) to accept, False or raise GoalRejected to refuse."""


class GoalRunner:
    """The handler an action is registered with: accepts the goal, waits for a slot when the
    action has a ``limit``, runs the user's handler with a :class:`GoalHandle`, and returns
    the outcome (see the module's invariants)."""

    def __init__(
        self,
        name: str,
        action: type[Action],
        handler: Callable[..., Any],
        *,
        accept: Accept | None = None,
        cancel_grace: float = DEFAULT_CANCEL_GRACE,
        limit: ConcurrencyLimit | None = None,
    ) -> None:
        if not callable(handler):
            raise TypeError(f"the handler for {name} must be callable")
        self.name = name
        self.action = action
        self.handler = handler
        self.accept = accept
        self.cancel_grace = cancel_grace
        self.limit = limit
        """How many of its handlers may run at once (``max_concurrency``); None for no limit."""
        self.is_async = inspect.iscoroutinefunction(handler) or inspect.iscoroutinefunction(
            getattr(handler, "__call__", None)  # noqa: B004 - an object with an async __call__
        )

    async def __call__(self, goal: Message, context: Any) -> dict[str, Any]:
        channel: GoalChannel | None = getattr(context, "channel", None)
        if channel is None or context.request_id is None:
            raise InvalidRequest(
                f"a goal for the action {self.name} must be a request with an id",
                service=self.name,
            )
        if self.accept is not None:
            verdict = self.accept(goal)
            if inspect.isawaitable(verdict):
                verdict = await verdict
            if verdict is False:
                raise GoalRejected(f"{self.name} rejected the goal", service=self.name)
        handle = GoalHandle(
            self.name, goal, context, channel, self.action.Feedback, self.cancel_grace
        )
        context.goal = handle
        limit = self.limit
        holds_slot = False  # until the handler returns, or a blocking handler's job takes it
        try:
            await channel.send(goal_notification(handle.call, handle.goal_id, "accepted"))
            if channel.closing:  # the server began to shut down as the goal was accepted
                canceling = handle.request_cancel(None)
                if canceling is not None:
                    await channel.send(canceling)
            if limit is not None:
                if not await _take_slot(limit, handle):
                    return {"status": "canceled", "result": self.action.Result()}
                holds_slot = True
            if not handle.cancel_requested:
                handle.status = "executing"
                await channel.send(goal_notification(handle.call, handle.goal_id, "executing"))
            if self.is_async:
                result = await self.handler(goal, handle)
            else:
                run = functools.partial(self.handler, goal, handle)
                job = _BlockingGoal(run, handle, limit if holds_slot else None)
                holds_slot = False
                try:
                    result = await channel.loop.run_in_executor(channel.executor, job)
                except BaseException:
                    job.leave()
                    raise
        finally:
            if holds_slot:
                assert limit is not None
                limit.release()
            handle.close()
        if result is None:
            result = self.action.Result()
        return {"status": handle.outcome_status(), "result": result}


async def _take_slot(limit: ConcurrencyLimit, handle: GoalHandle) -> bool:
    """Wait for a slot of ``limit``, in order; return whether the goal holds one. It holds
    none when its cancellation was asked for first, nor when the wait itself is cancelled
    (its deadline passed)."""
    if handle.cancel_requested:
        return False
    if limit.running < limit.limit and not limit.waiting:
        await limit.acquire()  # a free slot: taken without waiting
        return True
    loop = handle.channel.loop
    taking = loop.create_task(limit.acquire())
    asked = loop.create_task(handle.cancelled())
    taken = False
    try:
        await asyncio.wait((taking, asked), return_when=asyncio.FIRST_COMPLETED)
        taken = taking.done() and not taking.cancelled() and not handle.cancel_requested
    finally:
        asked.cancel()
        if not taking.done():
            taking.cancel()  # a slot handed to it meanwhile is passed on (ConcurrencyLimit)
        elif not taken and not taking.cancelled() and taking.exception() is None:
            limit.release()  # taken, but the goal will not run
    return taken


class _BlockingGoal(SlotJob):
    """A plain ``def`` handler's goal, as its thread runs it.

    It holds the action's slot (if it has a limit) until the handler returns, or, if its goal
    ends before a thread takes it, until then: such a job never runs its handler.
    """

    __slots__ = ("handle",)

    def __init__(
        self, call: Callable[[], Any], handle: GoalHandle, limit: ConcurrencyLimit | None
    ) -> None:
        super().__init__(call, limit)
        self.handle = handle

    def abandoned(self) -> bool:
        return self.handle._closed  # its goal ended: nobody waits for it any more


# --- the client's side ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class GoalResult(Generic[R]):
    """How a goal ended: its final ``status`` and its typed ``result``.

    For a goal whose handler the server stopped after a cancellation (it answered
    ``CANCELLED`` instead of a result), ``result`` is the action's ``Result`` with its
    defaults, as ROS gives a goal that ended without one.
    """

    status: str
    result: R


class GoalLink(Protocol):
    """What a client's goal needs of its connection (a :class:`srvwire.link.Link` is one)."""

    loop: asyncio.AbstractEventLoop
    goals: dict[int, Any]

    def give_up(self, method: str, id: int, future: asyncio.Future[Any]) -> None: ...

    def failure(self, method: str, exc: Any) -> RPCError: ...

    async def send_quietly(self, data: bytes) -> None: ...

    def cancel_goal(self, id: int) -> bytes | None: ...

    def forget_goal(self, id: int) -> None: ...


class ClientGoal(Generic[R]):
    """A goal the client sent: its state, its latest feedback, its outcome.

    ``status`` is ``accepted``, ``executing``, ``canceling``, then ``succeeded``,
    ``canceled`` or ``aborted``. Returned by :meth:`srvwire.Client.send_goal` once the server
    accepted the goal.
    """

    def __init__(
        self,
        link: GoalLink,
        method: str,
        action: type[Action],
        decoder: ModelDecoder[Any],
        deadline: float,
        budget: float,
    ) -> None:
        self.link = link
        self.method = method
        self.action = action
        self.decoder = decoder
        self.deadline = deadline
        self.budget = budget
        self.id = 0
        self.goal_id: str | None = None
        """The server's id for the goal (a UUID), once accepted."""
        self.status = "pending"
        self.reply: asyncio.Future[Any] = link.loop.create_future()
        self.cancel_sent = False
        self._seq = 0  # the latest feedback's
        self._feedback: Any = None
        self._changed: asyncio.Future[None] = link.loop.create_future()
        self._outcome: GoalResult[R] | None = None
        self._error: RPCError | None = None

    def __repr__(self) -> str:
        return f"<ClientGoal {self.method} id {self.id} {self.status}>"

    @property
    def done(self) -> bool:
        """Whether the goal's outcome arrived (or the connection ended)."""
        return self.reply.done()

    def news(self, news: GoalNews) -> None:
        """A ``$/goal`` or ``$/feedback`` about this goal arrived (the link's reader)."""
        if news.status is not None:
            self.status = advance(self.status, news.status)
            if self.goal_id is None:
                self.goal_id = news.goal_id
        elif news.seq > self._seq:
            self._seq = news.seq
            self._feedback = news.feedback
        self._wake()

    def _wake(self) -> None:
        if not self._changed.done():
            self._changed.set_result(None)

    async def _next_change(self) -> None:
        changed = self._changed
        if changed.done():
            self._changed = self.link.loop.create_future()
            return
        await asyncio.wait((changed, self.reply), return_when=asyncio.FIRST_COMPLETED)
        if changed.done():
            self._changed = self.link.loop.create_future()

    async def accepted(self) -> None:
        """Wait until the server accepted the goal; raise the error it answered instead."""
        while self.status == "pending" and not self.reply.done():
            await self._wait(self._next_change())
        if self.status == "pending":
            await self.result()  # refused: raise the reason (GoalRejected)

    async def _wait(self, awaitable: Awaitable[Any]) -> None:
        remaining = self.deadline - self.link.loop.time()
        try:
            async with asyncio.timeout(remaining):
                await awaitable
        except TimeoutError:
            self.give_up()
            self._end_with(
                DeadlineExceeded(
                    f"no outcome within {self.budget:g} s",
                    {"timeout": self.budget},
                    service=self.method,
                )
            )
            raise self._error from None  # type: ignore[misc]

    def forget(self) -> None:
        """Stop waiting for the outcome, and tell the server nothing (after :meth:`cancel`,
        a program that leaves). :meth:`result` raises ``asyncio.CancelledError`` then."""
        self.link.forget_goal(self.id)
        self.reply.cancel()

    def give_up(self) -> None:
        """Stop waiting for the outcome: ``$/cancel`` it on the server, forget it here."""
        self.link.give_up(self.method, self.id, self.reply)
        self.reply.cancel()  # its done-callback forgets the goal and wakes its readers

    def _end_with(self, error: RPCError) -> None:
        if self._outcome is None and self._error is None:
            if error.service is None:  # the connection's end: named, as a call's is
                error.service = self.method
            self._error = error
            self.status = "canceled" if isinstance(error, Cancelled) else "aborted"

    async def feedback(self) -> AsyncIterator[Any]:
        """Yield the goal's feedback (typed) as it arrives, the latest each time; end with
        the goal. A reader slower than the server skips feedback, never queues it."""
        seen = 0
        model = self.action.Feedback
        while True:
            if self._seq > seen:
                seen = self._seq
                yield validate_wire(model, self._feedback)
                continue
            if self.reply.done():
                return
            await self._wait(self._next_change())

    async def result(self) -> GoalResult[R]:
        """Wait for the outcome: the final status and the typed result.

        Raise what the server answered instead of an outcome (``GoalRejected``,
        ``InternalError``, ``DeadlineExceeded``, ``ConnectionLost``, ...); a goal whose handler
        the server stopped after a cancellation ends ``canceled`` with the result's defaults.

        Cancelling the task that awaits it ends only that wait, as a ``timeout`` on a blocking
        ``result`` does: the goal goes on, on the server and in the client's ``in_flight``,
        until its outcome or its deadline; await :meth:`cancel` to have the server stop it.
        """
        if self._outcome is not None:
            return self._outcome
        if self._error is not None:
            raise self._error
        if not self.reply.done():
            await self._wait(asyncio.wait((self.reply,)))
        self.link.goals.pop(self.id, None)  # its done-callback may not have run yet
        try:
            outcome = self.reply.result().decode(self.decoder)
        except RPCError as exc:
            if isinstance(exc, Cancelled) and self.cancel_sent:
                self._outcome = GoalResult("canceled", cast("R", self.action.Result()))
                self.status = "canceled"
                return self._outcome
            error = self.link.failure(self.method, exc)
            self._end_with(error)
            raise error from None
        except ValidationError as exc:
            data = error_data(exc)
            error = RPCError(
                f"the outcome does not match {self.action.type_name}: "
                f"{summarize_errors(data['errors'], exc.error_count())}",
                data,
                service=self.method,
            )
            self._end_with(error)
            raise error from None
        except Exception as exc:  # ConnectionLost set on the future by the reader
            if isinstance(exc, RPCError):
                exc.service = self.method
                self._end_with(exc)
            raise
        self._outcome = GoalResult(outcome.status, outcome.result)
        self.status = outcome.status
        return self._outcome

    async def cancel(self) -> bool:
        """Ask the server to cancel the goal; return whether the request was sent (False:
        its outcome had arrived already). The outcome still arrives, through
        :meth:`result`: ``canceled``, or whatever the goal reached first."""
        data = self.link.cancel_goal(self.id)
        if data is None or self.cancel_sent:
            return False
        self.cancel_sent = True
        await self.link.send_quietly(data)
        return True


def reply_done(goals: dict[int, Any], id: int) -> Callable[[asyncio.Future[Any]], None]:
    """A done-callback for a goal's reply: forget the goal ``id``, wake its readers."""

    def done(future: asyncio.Future[Any]) -> None:
        goal = goals.pop(id, None)
        if goal is not None:
            goal._wake()
            if future.cancelled():
                return
            exc = future.exception()
            if isinstance(exc, RPCError):  # the connection ended: the goal with it
                goal._end_with(exc)

    return done
