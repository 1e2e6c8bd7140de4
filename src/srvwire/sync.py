"""The blocking client: srvwire's async client, driven from plain code and from any thread.

``with srvwire.sync.connect(url) as client: client.call(...)``. :func:`connect` takes the
options of :func:`srvwire.connect` (it passes them on, so they are never written twice) and
returns a :class:`Client` that is already open. Each client runs the async
:class:`~srvwire.client.Client` on an event loop of its own, in a daemon thread of its own
(a :class:`LoopThread`); every blocking method hands its coroutine to that loop with
``asyncio.run_coroutine_threadsafe`` and waits for the answer. One loop per client, not one
shared by all: a client's loop and thread begin and end with it, and no state is kept between
clients.

Invariants:

* **One connection, many threads.** Calls from several threads run at once on the one
  connection, as concurrent calls do on the async client; a call never opens a connection.
* **The async client keeps the time.** A call's deadline is the async client's (its
  ``timeout``, or the call's own); the blocking wait only backs it up, waiting at most
  :data:`BACKSTOP` seconds past it, so it ends even if the loop thread is stuck. A call
  pending when the loop ends (the client closed from another thread, or the thread dying)
  fails at once with :class:`~srvwire.errors.ConnectionLost`. The one wait without a
  deadline is a subscription's for its next message, unless given a ``timeout``; it too
  ends at once when the loop ends.
* **Nothing waits for itself.** A blocking call from the client's own loop thread (a type
  resolver, a log handler) raises ``RuntimeError`` instead of waiting forever.
* **An unclosed client never keeps the process alive.** Its thread is a daemon thread; when
  the client is garbage-collected, or the interpreter exits, its loop is stopped, which
  closes the connection with 1001.
* **Works where a loop is already running**, as in Jupyter: the client's loop is not the
  caller's, so a blocking call from a thread that runs an event loop still finishes (that
  loop waits meanwhile; there, ``await`` the async client instead).

The same exception classes as the async client's are raised, with the same meaning.

An action's goal is a :class:`Goal`, whose methods block: :meth:`Client.send_goal` returns
once the server accepted it, :meth:`Goal.feedback` is a plain iterator whose ``next`` waits
on the loop, :meth:`Goal.result` waits for the outcome. Ctrl-C (``KeyboardInterrupt``) while
:meth:`Goal.result` or :meth:`Goal.feedback` waits, or anywhere in the client's ``with``
block, asks the server to cancel each goal still running and waits for its outcome (at most
its deadline; a second Ctrl-C stops waiting) before the ``KeyboardInterrupt`` goes on and the
connection closes, so a handler sees :attr:`srvwire.GoalHandle.cancel_requested` and has its
``cancel_grace``. A topic's subscription is a
:class:`Subscription` in the same way: a plain iterator of typed messages, and a context
manager; it stands on the async :class:`~srvwire.client.Subscription`, whose queue stays on
the loop, so a wait given up (a ``timeout`` per message) loses no message.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import functools
import threading
import weakref
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine, Iterator, Mapping
from types import TracebackType
from typing import Any, Generic, ParamSpec, TypeVar, overload

from pydantic import BaseModel

from srvwire import client as aio
from srvwire.actions import ClientGoal, GoalResult
from srvwire.calls import ServiceInfo, SrvType, check_timeout
from srvwire.client import TopicInfo
from srvwire.errors import ConnectionLost, DeadlineExceeded, RPCError, ServiceUnavailable
from srvwire.models import Action, Message, ServiceRequest, TypedService

__all__ = [
    "BACKSTOP",
    "Client",
    "Goal",
    "LoopEnded",
    "LoopThread",
    "LoopTimeout",
    "ServiceProxy",
    "Subscription",
    "connect",
]

BACKSTOP = 1.0
"""Seconds a blocking call waits past its deadline for the loop's answer before giving up."""

CLOSE_WITHIN = 10.0
"""Seconds :meth:`Client.close` waits for the connection's closing handshake."""

T = TypeVar("T")
P = ParamSpec("P")
R = TypeVar("R", bound=Message)
M = TypeVar("M", bound=BaseModel)


class LoopTimeout(TimeoutError):
    """Raised by :meth:`LoopThread.run` when the loop did not finish the coroutine in time."""


class LoopEnded(RuntimeError):
    """Raised by :meth:`LoopThread.run` when the loop ended before the coroutine did."""


class LoopThread:
    """An event loop running in a daemon thread, and blocking calls into it from other threads.

    The loop runs until :meth:`stop`; then, as :func:`asyncio.run` does, the tasks still there
    are cancelled and finish, and the loop is closed. Once it has stopped, :meth:`run` hands it
    nothing more (:class:`LoopEnded` at once): what was handed over before is a task by the
    time of the last sweep, so every coroutine handed over ends, none is dropped with the loop.
    """

    def __init__(self, name: str = "srvwire event loop") -> None:
        self.loop = asyncio.new_event_loop()
        self._handing = threading.Lock()  # held while handing over, and to end the hand-overs
        self._ended = False  # under _handing: the loop has stopped; hand nothing more over
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def __repr__(self) -> str:
        return f"<LoopThread {self.thread.name!r} {'running' if self.running else 'ended'}>"

    @property
    def running(self) -> bool:
        """Whether the loop still runs (it may be stopping)."""
        return self.thread.is_alive()

    def _run(self) -> None:
        loop = self.loop
        try:
            loop.run_forever()
        finally:
            try:
                with self._handing:
                    self._ended = True
                # What was handed over before becomes a task now, for the sweep to end it.
                loop.run_until_complete(_nothing())
                # Again while cancelling makes more.
                while tasks := asyncio.all_tasks(loop):
                    for task in tasks:
                        task.cancel()
                    loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
            finally:
                loop.close()

    def run(self, coro: Coroutine[Any, Any, T], within: float | None) -> T:
        """Run ``coro`` on the loop and return its result, or raise its exception.

        Raise :class:`LoopTimeout` (and cancel it) if it has not finished after ``within``
        seconds (``None``: wait as long as it runs), :class:`LoopEnded` if the loop ended
        first, and ``RuntimeError`` when called from the loop's own thread, which would wait
        for itself. An exception that interrupts the wait (``KeyboardInterrupt``) cancels the
        coroutine.
        """
        if threading.current_thread() is self.thread:
            coro.close()
            raise RuntimeError(
                "a blocking srvwire call from its client's own event loop thread would wait "
                "for itself; await the async client there instead"
            )
        try:
            with self._handing:
                if self._ended:
                    raise RuntimeError("the loop has stopped")
                future = asyncio.run_coroutine_threadsafe(coro, self.loop)
        except RuntimeError:  # the loop has stopped, or is closed
            coro.close()
            raise LoopEnded("the event loop has ended") from None
        except BaseException:  # interrupted (Ctrl-C) once handed over: find it to cancel it
            self.loop.call_soon_threadsafe(_cancel_the_task_of, coro)
            raise
        try:
            future.exception(within)  # waits; the coroutine's own error is raised below
        except concurrent.futures.CancelledError:
            # Only the loop cancels a coroutine this thread still waits for: it is ending.
            raise LoopEnded("the event loop ended before the call finished") from None
        except TimeoutError:
            future.cancel()
            raise LoopTimeout(f"the event loop did not finish within {within:g} s") from None
        except BaseException:
            future.cancel()
            raise
        return future.result()

    def stop(self, within: float = CLOSE_WITHIN) -> None:
        """Stop the loop and wait up to ``within`` seconds for its thread to end; idempotent.

        From the loop's own thread, only ask it to stop.
        """
        try:
            self.loop.call_soon_threadsafe(self.loop.stop)
        except RuntimeError:
            pass  # closed already
        if threading.current_thread() is not self.thread:
            self.thread.join(within)


async def _nothing() -> None:
    """A step of the loop, for the callbacks queued before it to run."""


def _cancel_the_task_of(coro: Coroutine[Any, Any, Any]) -> None:
    """Cancel the task running ``coro`` on this loop, if there is one."""
    for task in asyncio.all_tasks():
        if task.get_coro() is coro:
            task.cancel()


def _takes_the_options_of(
    async_connect: Callable[P, object],
) -> Callable[[Callable[..., Client]], Callable[P, Client]]:
    """Give a function ``async_connect``'s parameters, for type checkers and ``help()``."""

    def decorate(function: Callable[..., Client]) -> Callable[P, Client]:
        functools.update_wrapper(function, async_connect, assigned=(), updated=())
        return function

    return decorate


@_takes_the_options_of(aio.connect)
def connect(*args: Any, **kwargs: Any) -> Client:
    """Open a blocking client to the srvwire server at ``url``, with srvwire.connect's options.

    The options are those of :func:`srvwire.connect` (``timeout``, ``reconnect``,
    ``transport``, ...), passed on to it as they are.

    Use it as ``with connect(url) as client:`` (closed on exit), or as
    ``client = connect(url)`` followed by ``client.close()``. Raise
    :class:`~srvwire.errors.ServiceUnavailable` when the server cannot be reached (without
    ``reconnect``), and ``ValueError`` or ``TypeError`` for a bad option.
    """
    return Client(aio.connect(*args, **kwargs))


class Client:
    """A blocking connection to one srvwire server, usable from several threads at once.

    Made by :func:`connect`. Its methods are the async :class:`srvwire.Client`'s, blocking:
    :meth:`call`, :meth:`proxy`, :meth:`wait_for_service`, :meth:`list_services`, the
    topics' :meth:`subscribe`, :meth:`publish`, :meth:`notify`, :meth:`wait_for_topic`,
    :meth:`list_topics`, the actions' :meth:`send_goal`, and :meth:`close`; they take the
    same arguments and raise the same errors.
    """

    def __init__(self, options: aio.connect, *, loop: LoopThread | None = None) -> None:
        """Open a client with ``options`` on its own loop thread, or on ``loop``, shared.

        A client made on a shared ``loop`` leaves it running when it closes.
        """
        self.options = options
        self._loop = LoopThread(f"srvwire client of {options.url}") if loop is None else loop
        self._owns_loop = loop is None
        self._client = aio.Client(options)
        self._closing = threading.Lock()
        self._closed = False
        self._goals: weakref.WeakSet[ClientGoal[Any]] = weakref.WeakSet()  # the link keeps
        self._goals_lock = threading.Lock()  # those pending alive, so they are all here
        try:
            self._run(self._client.open(), options.open_timeout)
        except BaseException:
            if self._owns_loop:
                self._loop.stop()
            raise
        # Collected or left open at exit: stopping the loop closes the connection (1001).
        self._finalizer = weakref.finalize(self, self._loop.stop) if self._owns_loop else None

    def __repr__(self) -> str:
        state = "closed" if self._closed else "connected" if self.connected else "not connected"
        return f"<srvwire.sync.Client {state} to {self.url}>"

    @property
    def url(self) -> str:
        """Where the client connects."""
        return self.options.url

    @property
    def timeout(self) -> float:
        """The deadline, in seconds, of a call that does not give its own."""
        return self.options.timeout

    @property
    def connected(self) -> bool:
        """Whether a connection is open right now (and its services are known)."""
        return self._client.connected

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @property
    def in_flight(self) -> int:
        """How many calls are waiting for a reply."""
        return self._client.in_flight

    @property
    def services(self) -> Mapping[str, str]:
        """The services the server advertised: canonical name -> type; a read-only snapshot."""
        return self._client.services

    def _run(
        self, coro: Coroutine[Any, Any, T], budget: float | None, service: str | None = None
    ) -> T:
        """Run ``coro`` on the client's loop; ``budget`` is its own deadline, in seconds
        (``None``: it has none, as a subscription waiting for its next message)."""
        try:
            return self._loop.run(coro, None if budget is None else budget + BACKSTOP)
        except LoopTimeout as exc:
            raise DeadlineExceeded(
                f"no answer within {budget:g} s: the client's event loop did not finish the call",
                {"timeout": budget},
                service=service,
            ) from exc
        except LoopEnded as exc:
            why = "the client is closed" if self._closed else "the client's event loop ended"
            raise ConnectionLost(why, {"url": self.url}, service=service) from exc

    def _budget(self, timeout: float | None) -> float:
        return self.options.timeout if timeout is None else check_timeout(timeout)

    # --- calls ------------------------------------------------------------------------------

    @overload
    def call(
        self,
        name: str,
        request: ServiceRequest[R],
        /,
        *,
        timeout: float | None = None,
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> R: ...

    @overload
    def call(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,
        srv_type: type[TypedService[Any, R]],
        wait_for_ready: bool = False,
    ) -> R: ...

    @overload
    def call(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> Any: ...

    def call(
        self,
        name: str,
        request: Any = None,  # the overloads say what it may be
        /,
        *,
        timeout: float | None = None,
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> Any:
        """Call the service ``name`` with ``request`` and return its response.

        As :meth:`srvwire.Client.call`: the typed ``Response`` of the service's type;
        ``timeout`` is the call's deadline (default: the client's); the
        :class:`~srvwire.errors.RPCError` subclass of the failure is raised. Statically, as
        there, a generated ``Request`` or a generated service class as ``srv_type`` makes the
        result that service's ``Response``; otherwise it is ``Any``.
        """
        budget = self._budget(timeout)  # a bad timeout is refused before any coroutine exists
        return self._run(
            self._client.call(
                name, request, timeout=timeout, srv_type=srv_type, wait_for_ready=wait_for_ready
            ),
            budget,
            name,
        )

    @overload
    def proxy(
        self,
        name: str,
        srv_type: type[TypedService[Any, R]],
        *,
        timeout: float | None = None,
        wait_for_ready: bool = False,
    ) -> ServiceProxy[R]: ...

    @overload
    def proxy(
        self,
        name: str,
        srv_type: SrvType | None = None,
        *,
        timeout: float | None = None,
        wait_for_ready: bool = False,
    ) -> ServiceProxy[Any]: ...

    def proxy(
        self,
        name: str,
        srv_type: SrvType | None = None,
        *,
        timeout: float | None = None,
        wait_for_ready: bool = False,
    ) -> ServiceProxy[Any]:
        """Return a callable for the service ``name`` that takes fields as keywords.

        ``client.proxy("/add_two_ints")(a=1, b=2)``; the options given here apply to every
        call made through it. With a generated service class as ``srv_type``, a type checker
        knows its calls return that service's ``Response``.
        """
        proxy = self._client.proxy(name, srv_type, timeout=timeout, wait_for_ready=wait_for_ready)
        return ServiceProxy(self, proxy)

    def wait_for_service(self, name: str, *, timeout: float | None = None) -> ServiceInfo:
        """Wait until the server advertises ``name``; return its name and type.

        As :meth:`srvwire.Client.wait_for_service`: woken by the server's announcement, and
        :class:`~srvwire.errors.ServiceUnavailable` when ``timeout`` passes first.
        """
        budget = self._budget(timeout)
        try:
            return self._run(self._client.wait_for_service(name, timeout=timeout), budget, name)
        except DeadlineExceeded as exc:
            if not isinstance(exc.__cause__, LoopTimeout):
                raise
            # The loop thread did not answer in time: the wait's own outcome then.
            raise ServiceUnavailable(
                f"{name} was not advertised within {budget:g} s: the client's event loop did "
                "not finish the wait",
                {"timeout": budget},
                service=name,
            ) from exc.__cause__

    def list_services(self, *, timeout: float | None = None) -> list[ServiceInfo]:
        """Ask the server for every service it offers, sorted by name."""
        budget = self._budget(timeout)
        return self._run(self._client.list_services(timeout=timeout), budget)

    # --- goals ------------------------------------------------------------------------------

    def send_goal(
        self,
        name: str,
        goal: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,
        action_type: type[Action] | str | None = None,
    ) -> Goal:
        """Send ``goal`` to the action ``name``; return its :class:`Goal` once accepted.

        As :meth:`srvwire.Client.send_goal`: ``timeout`` is the deadline of the whole goal;
        a refused goal raises :class:`~srvwire.errors.GoalRejected`.
        """
        budget = self._budget(timeout)
        handle = self._run(
            self._client.send_goal(name, goal, timeout=timeout, action_type=action_type),
            budget,
            name,
        )
        with self._goals_lock:
            self._goals.add(handle)
        return Goal(self, handle, budget)

    def _stop_goals(self, handles: list[ClientGoal[Any]]) -> None:
        """After Ctrl-C: ask the server to cancel each of ``handles`` still running whose
        cancellation was not asked yet, and wait for their outcomes (kept by each handle).

        The wait ends at the last of their deadlines, or at a second ``KeyboardInterrupt``,
        which is raised; an error meanwhile (the connection lost) ends it quietly, as the
        first interruption is what the caller goes on with. Goals whose wait a second
        interruption ended are not waited for again (by the ``with`` block's exit): closing
        the connection stops their handlers.
        """
        if not handles or self._closed:
            return
        budget = max(handle.budget for handle in handles)
        try:
            with contextlib.suppress(RPCError):
                self._run(_cancel_and_wait(handles), budget)
        except KeyboardInterrupt:
            with self._goals_lock:
                for handle in handles:
                    self._goals.discard(handle)
            raise

    # --- topics ---------------------------------------------------------------------------

    @property
    def topics(self) -> Mapping[str, str]:
        """The topics the server announced: canonical name -> message type; a snapshot."""
        return self._client.topics

    @overload
    def subscribe(
        self,
        name: str,
        msg_type: type[M],
        *,
        qos: Mapping[str, Any] | None = None,
        timeout: float | None = None,
        message_timeout: float | None = None,
        duration: float | None = None,
    ) -> Subscription[M]: ...

    @overload
    def subscribe(
        self,
        name: str,
        msg_type: str | None = None,
        *,
        qos: Mapping[str, Any] | None = None,
        timeout: float | None = None,
        message_timeout: float | None = None,
        duration: float | None = None,
    ) -> Subscription[Any]: ...

    def subscribe(
        self,
        name: str,
        msg_type: type[BaseModel] | str | None = None,
        *,
        qos: Mapping[str, Any] | None = None,
        timeout: float | None = None,
        message_timeout: float | None = None,
        duration: float | None = None,
    ) -> Subscription[Any]:
        """Subscribe to the topic ``name``: ``for msg in client.subscribe(name):``.

        As :meth:`srvwire.Client.subscribe` (``msg_type``, ``qos``, and ``timeout`` that bounds
        the subscribing), blocking: leaving a ``for`` loop over it ends the subscription;
        ``with client.subscribe(name) as sub:`` holds it for the block, where ``next(sub)`` or
        ``sub.get(timeout=...)`` take one message. ``message_timeout`` bounds each wait for a
        message (default: none); when it passes, :class:`~srvwire.errors.DeadlineExceeded`
        (a ``TimeoutError``) is raised and the subscription goes on. With a message class as
        ``msg_type``, a type checker knows the messages are of that class. ``duration`` is the
        subscription's deadline on the server, as for :meth:`srvwire.Client.subscribe`: when it
        passes, the subscription ends with :class:`~srvwire.errors.DeadlineExceeded`.
        """
        if message_timeout is not None:
            check_timeout(message_timeout)
        subscription = self._client.subscribe(
            name, msg_type, qos=qos, timeout=timeout, duration=duration
        )
        return Subscription(self, subscription, message_timeout)

    def publish(
        self,
        name: str,
        message: BaseModel | Mapping[str, Any],
        /,
        *,
        msg_type: type[BaseModel] | str | None = None,
        ack: bool = False,
        timeout: float | None = None,
    ) -> None:
        """Publish ``message`` on the topic ``name``; see :meth:`srvwire.Client.publish`.

        Validated here first (``InvalidParams`` with the fields' paths); with ``ack=True``
        it returns once the server took it, and raises what the server refused it with.
        """
        budget = self._budget(timeout)
        self._run(
            self._client.publish(name, message, msg_type=msg_type, ack=ack, timeout=timeout),
            budget,
            name,
        )

    def notify(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        srv_type: SrvType | None = None,
    ) -> None:
        """Call the service ``name`` without waiting for an answer; see
        :meth:`srvwire.Client.notify`."""
        self._run(self._client.notify(name, request, srv_type=srv_type), self.timeout, name)

    def wait_for_topic(self, name: str, *, timeout: float | None = None) -> TopicInfo:
        """Wait until the server announces the topic ``name``; return what it says of it.

        As :meth:`srvwire.Client.wait_for_topic`: ``ServiceUnavailable`` when ``timeout``
        passes first.
        """
        budget = self._budget(timeout)
        return self._run(self._client.wait_for_topic(name, timeout=timeout), budget, name)

    def list_topics(self, *, timeout: float | None = None) -> list[TopicInfo]:
        """Ask the server for every topic it offers, sorted by name."""
        budget = self._budget(timeout)
        return self._run(self._client.list_topics(timeout=timeout), budget)

    # --- closing ----------------------------------------------------------------------------

    def close(self) -> None:
        """Close the connection and end the client's loop thread; idempotent.

        Calls still pending, in other threads, fail with ``ConnectionLost``. After it, every
        call fails with ``ConnectionLost``.
        """
        with self._closing:
            if self._closed:
                return
            self._closed = True
        try:
            self._run(self._client.close(), CLOSE_WITHIN)
        except ConnectionLost:
            pass  # the loop had ended: the connection ended with it
        finally:
            if self._finalizer is not None:
                self._finalizer.detach()
                self._loop.stop()

    def __enter__(self) -> Client:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is not None and issubclass(exc_type, KeyboardInterrupt):
                with self._goals_lock:
                    handles = list(self._goals)
                self._stop_goals(handles)
        finally:
            self.close()


class Goal:
    """A goal the blocking client sent: :class:`srvwire.ClientGoal`'s methods, blocking.

    Each waits on the client's loop, at most the goal's deadline (the async client enforces
    it) plus :data:`BACKSTOP`.
    """

    def __init__(self, client: Client, handle: ClientGoal[Any], budget: float) -> None:
        self.client = client
        self.name = handle.method
        self._handle = handle
        self._budget = budget

    def __repr__(self) -> str:
        return f"<srvwire.sync.Goal {self.name} {self.status}>"

    @property
    def status(self) -> str:
        """The goal's state, as :attr:`srvwire.ClientGoal.status`."""
        return self._handle.status

    @property
    def goal_id(self) -> str | None:
        """The server's id for the goal."""
        return self._handle.goal_id

    @property
    def done(self) -> bool:
        """Whether the goal's outcome arrived (or the connection ended)."""
        return self._handle.done

    def feedback(self) -> Iterator[Any]:
        """Yield the goal's feedback (typed, the latest each time) until it ends."""
        feedback = self._handle.feedback()
        while True:
            try:
                step = self.client._run(_next(feedback), self._budget, self.name)
            except KeyboardInterrupt:
                self.client._stop_goals([self._handle])
                raise
            if step is _END:
                return
            yield step

    def result(self, *, timeout: float | None = None) -> GoalResult[Any]:
        """Wait for the outcome: the final status and the typed result.

        Without ``timeout``, wait as long as the goal's deadline allows (the async client
        ends the goal with ``DeadlineExceeded`` then). With it, raise
        :class:`~srvwire.errors.DeadlineExceeded` after ``timeout`` seconds while the goal
        goes on: ask again, or :meth:`cancel` it.
        """
        if timeout is None:
            waiting = self._handle.result()
            budget = self._budget
        else:
            wait = check_timeout(timeout)
            waiting = _within(self._handle.result(), wait, self.name, "the goal had no outcome")
            budget = min(wait, self._budget)
        try:
            return self.client._run(waiting, budget, self.name)
        except KeyboardInterrupt:  # ask the server to stop it before the program leaves
            self.client._stop_goals([self._handle])
            raise

    def cancel(self) -> bool:
        """Ask the server to cancel the goal; see :meth:`srvwire.ClientGoal.cancel`."""
        return self.client._run(self._handle.cancel(), self._budget, self.name)


_END = object()


async def _within(awaitable: Awaitable[T], seconds: float, name: str, what: str) -> T:
    """Await ``awaitable`` for at most ``seconds``; then raise ``DeadlineExceeded``."""
    try:
        async with asyncio.timeout(seconds):
            return await awaitable
    except TimeoutError:
        raise DeadlineExceeded(
            f"{what} within {seconds:g} s", {"timeout": seconds}, service=name
        ) from None


async def _cancel_and_wait(handles: list[ClientGoal[Any]]) -> None:
    """Ask the server to cancel each goal still running, once (a goal cancelled already is
    not asked again); then wait for the outcomes of them all."""
    running = [handle for handle in handles if not handle.done]
    for handle in running:
        if not handle.cancel_sent:
            await handle.cancel()
    await asyncio.gather(*(handle.result() for handle in running), return_exceptions=True)


async def _next(iterator: AsyncIterator[Any]) -> Any:
    """The next item of ``iterator`` on its loop, or ``_END``."""
    try:
        return await anext(iterator)
    except StopAsyncIteration:
        return _END


async def _receive(subscription: aio.Subscription) -> Any:
    """The subscription's next message, or ``_END`` once it was closed."""
    try:
        return await subscription.receive()
    except StopAsyncIteration:
        return _END


class ServiceProxy(Generic[R]):
    """A blocking callable bound to one service: ``proxy(request)`` or ``proxy(a=1, b=2)``.

    Made by :meth:`Client.proxy`; as :class:`srvwire.ServiceProxy`, the call options are the
    proxy's, so every field name, ``timeout`` included, is free for the request. ``R`` is the
    response type a type checker sees (``Any`` unless made with a generated service class).
    """

    def __init__(self, client: Client, proxy: aio.ServiceProxy[R]) -> None:
        self.client = client
        self.name = proxy.name
        self._proxy = proxy

    def __call__(self, request: BaseModel | Mapping[str, Any] | None = None, /, **fields: Any) -> R:
        """Call the service; see :meth:`Client.call`."""
        budget = self.client._budget(self._proxy.timeout)
        return self.client._run(self._proxy(request, **fields), budget, self.name)

    def wait_for_service(self, *, timeout: float | None = None) -> ServiceInfo:
        """Wait until the server advertises this service; see :meth:`Client.wait_for_service`."""
        return self.client.wait_for_service(self.name, timeout=timeout)

    def __repr__(self) -> str:
        return f"srvwire.sync.ServiceProxy({self.name!r}, {self._proxy.srv_type!r})"


class Subscription(Generic[M]):
    """A subscription of the blocking client: what :meth:`Client.subscribe` returns.

    A plain iterable of typed messages, and a context manager; started on entry, or on the
    first message asked for. ``for msg in sub:`` outside a ``with`` block ends the
    subscription when the loop is left (``break``, an exception, or the end), as ``async for``
    does on the async client; inside ``with client.subscribe(name) as sub:`` the loop may be
    left and taken up again, and the subscription ends with the block. :meth:`close` ends it
    from any thread.

    Every wait runs on the client's loop; the messages queue there, so a wait that ran out
    of time, or was interrupted, loses none. One thread at a time takes messages from a
    subscription; any thread may be that one. Its counters are the async subscription's
    (:attr:`seq`, :attr:`missed`, :attr:`dropped`, :attr:`granted`).
    """

    def __init__(
        self,
        client: Client,
        subscription: aio.Subscription,
        message_timeout: float | None = None,
    ) -> None:
        self.client = client
        self.name = subscription.name
        self.message_timeout = message_timeout
        self._subscription = subscription
        self._managed = False

    def __repr__(self) -> str:
        state = "active" if self.active else "not active"
        return f"<srvwire.sync.Subscription to {self.name}, {state}>"

    @property
    def active(self) -> bool:
        """Whether the subscription runs (or is resuming), and has not ended."""
        return self._subscription.active

    @property
    def seq(self) -> int | None:
        """The sequence number of the last message returned."""
        return self._subscription.seq

    @property
    def missed(self) -> int:
        """How many messages the subscriber did not get just before the last one."""
        return self._subscription.missed

    @property
    def dropped(self) -> int:
        """How many messages this subscriber did not get, in all."""
        return self._subscription.dropped

    @property
    def granted(self) -> Mapping[str, Any]:
        """The QoS the server granted."""
        return self._subscription.granted

    def start(self) -> Subscription[M]:
        """Subscribe, and return once the server started the subscription; idempotent."""
        self.client._run(self._subscription.start(), self._subscription.budget, self.name)
        return self

    def get(self, *, timeout: float | None = None) -> M:
        """Return the next message, waiting at most ``timeout`` seconds (default: the
        subscription's ``message_timeout``; none: as long as it takes).

        Raise :class:`~srvwire.errors.DeadlineExceeded` when ``timeout`` passes (the
        subscription goes on), the error that ended the subscription as the async client
        raises it (``ServiceNotFound``, ``PermissionDenied``, ``ResourceExhausted``,
        ``ConnectionLost``), and ``StopIteration`` once it was closed.
        """
        wait = self.message_timeout if timeout is None else check_timeout(timeout)
        if not self._subscription.active:
            self.start()  # its own deadline is the subscribing's, not a message's
        receive = _receive(self._subscription)
        if wait is None:
            message = self.client._run(receive, None, self.name)
        else:
            message = self.client._run(
                _within(receive, wait, self.name, "no message arrived"), wait, self.name
            )
        if message is _END:
            raise StopIteration
        return message  # type: ignore[no-any-return]

    def __next__(self) -> M:
        return self.get()

    def __iter__(self) -> Iterator[M]:
        """Yield each message as it arrives; outside ``with``, leaving the loop ends it."""
        try:
            while True:
                try:
                    message = self.get()
                except StopIteration:
                    return
                yield message
        finally:
            if not self._managed:
                self.close()

    def close(self) -> None:
        """End the subscription on the server (``$/cancel``); idempotent, from any thread."""
        client = self.client
        if threading.current_thread() is client._loop.thread:
            # Reached from the loop's own thread (a generator collected there): hand it over.
            client._client.spawn(self._subscription.close())  # kept until it is done
            return
        try:
            client._run(self._subscription.close(), client.timeout, self.name)
        except ConnectionLost:
            pass  # the client closed: the subscription ended with its connection

    def __enter__(self) -> Subscription[M]:
        self._managed = True
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
