"""One open connection of a client: the transport's, its session, and its one reader task.

A :class:`Link` lives as long as its connection. The reader is the only code that receives: it
resolves the future of the call a reply belongs to (a srvwire-shaped response unparsed, routed
by its opening; anything else through the :class:`~srvwire.session.ClientSession`, which
routes it the same way), and tells its :class:`Owner` (the client) when the services change
or the connection ends. On a transport that hands messages over as they arrive (both network
transports do), the reader takes them in the transport's read callback (:meth:`Link.take`),
and its task only waits for the end. :meth:`Link.roundtrip` is one call's send and wait.

Invariants:

* **Every pending call ends** with its reply, its deadline, its caller's cancellation, or
  ``ConnectionLost`` when the connection ends; the session forgets its id in every case.
* **Something that is not JSON-RPC fails the connection** (close 1008), found by the reader,
  by a caller decoding a reply the reader left unparsed, or by a subscription decoding its
  ``$/message``; nothing the reader takes in after that reaches a subscription.
* **A reader is cancelled only when its event loop ends** (``asyncio.run`` returning): the
  connection is closed with 1001, and a client used from another loop says so.
* **A call given up on is cancelled on the server** by a ``$/cancel`` sent in the
  background, best effort.
* **A request larger than** ``max_message_size`` **is never sent**: the call raises
  :class:`~srvwire.errors.ResourceExhausted` naming the setting, and the connection carries
  on. The client's limit stands for the server's, which it cannot know.
* **A goal's news reaches its goal**: the ``$/goal`` and ``$/feedback`` notifications for a
  call in :attr:`Link.goals` are handed to it, in the order they came; news for a call no
  longer there (its outcome arrived) is dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import ssl as _ssl
import sys
from collections.abc import Coroutine, Hashable, Sequence
from typing import Any, Protocol, TypeAlias

from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InvalidRequest,
    ResourceExhausted,
    RPCError,
    ServiceUnavailable,
)
from srvwire.goals import FEEDBACK_METHOD, GOAL_METHOD, GoalNews, goal_news
from srvwire.inline import Pending, finish_within, first_step
from srvwire.protocol import (
    REPLY_OPENING,
    ErrorResponse,
    ProtocolViolation,
    RawReply,
    Response,
    cancel_notification,
    peek_reply,
)
from srvwire.session import (
    ClientSession,
    Notice,
    ServicesChanged,
    Stray,
    Subscribed,
    TopicMessage,
    TopicsChanged,
)
from srvwire.transports.base import Connection, Options, Transport, TransportClosed

__all__ = [
    "CLOSE_PROTOCOL_VIOLATION",
    "LOOP_ENDED",
    "MAX_READY",
    "Answer",
    "Arrived",
    "Link",
    "LoggerLike",
    "Owner",
    "Stream",
    "foreign_loop",
]

Arrived: TypeAlias = Response | ErrorResponse | RawReply
"""A reply as it reaches its caller: parsed, or routed unparsed."""


if sys.version_info >= (3, 12):
    # wait_for awaits the call's future itself, from the caller's task: nothing to hasten.
    Answer = asyncio.Future
else:

    class Answer(asyncio.Future[Arrived]):
        """A call's future on Python 3.11, whose reply wakes its caller a loop turn sooner.

        Python 3.11's ``asyncio.wait_for(future, timeout)`` waits on a future of its own, the
        waiter, and adds ``functools.partial(asyncio.tasks._release_waiter, waiter)`` to
        ``future``'s done callbacks. Set on a plain future, a reply runs that callback at the
        next loop turn, and it wakes the caller's task at the turn after. Set on this one, it
        takes that callback off and calls it at once: the caller wakes at the next turn, as
        it would awaiting the future bare.

        Invariants: only a ``partial`` of ``_release_waiter`` is ever called early, and it
        only sets the waiter's result (which schedules the task's wake-up, as ever; no task is
        stepped here), so it runs once, earlier, and nothing else changes. A result set before
        ``wait_for`` waits (a reply that came while the send waited) finds no such callback.
        An exception (the connection lost) and a cancellation wake the caller as on a plain
        future.
        """

        __slots__ = ()

        def set_result(self, result: Arrived, /) -> None:
            callbacks = self._callbacks  # a new list, None once done (then set_result raises)
            if callbacks is not None:
                for fn, _ in callbacks:
                    if type(fn) is functools.partial and fn.func is _RELEASE_WAITER:
                        self.remove_done_callback(fn)
                        _SET_RESULT(self, result)
                        fn(self)
                        return
            _SET_RESULT(self, result)

    _SET_RESULT = asyncio.Future.set_result
    _RELEASE_WAITER = asyncio.tasks._release_waiter  # type: ignore[attr-defined]


LoggerLike: TypeAlias = logging.Logger | logging.LoggerAdapter[logging.Logger]

CLOSE_PROTOCOL_VIOLATION = 1008
"""The close code sent when the server breaks the protocol (RFC 6455 "policy violation")."""

MAX_READY = 1024
"""How many calls' names and types a link keeps at most (see :meth:`Link.remember`)."""

LOOP_ENDED = "the client's event loop ended"
"""The reason of the close (1001) a client's connection ends with when its event loop does."""


def foreign_loop(loop: asyncio.AbstractEventLoop) -> RuntimeError:
    """The error for using a client outside ``loop``, the event loop it was opened in."""
    if loop.is_closed():
        return RuntimeError(
            "this client was opened in an event loop that has ended (asyncio.run() ends its "
            "loop when it returns): open the client in the coroutine that uses it, with "
            "'async with srvwire.connect(url) as client', or use srvwire.sync.connect(url) "
            "from blocking code"
        )
    return RuntimeError(
        "this client belongs to another event loop: call it from the loop it was opened in, "
        "or use srvwire.sync.connect(url), which any thread can call"
    )


class Owner(Protocol):
    """What a link needs of its client."""

    url: str
    logger: LoggerLike

    @property
    def closed(self) -> bool:
        """Whether the client was closed (then an ending connection is no news)."""
        ...

    def services_changed(self, link: Link, services: dict[str, str]) -> None:
        """``link``'s server sent ``$/services``; news only while it is the current link."""
        ...

    def topics_changed(self, link: Link, topics: dict[str, dict[str, Any]]) -> None:
        """``link``'s server sent ``$/topics``; news only while it is the current link."""
        ...

    def forget(self, link: Link) -> bool:
        """Drop ``link`` if it is the current one; return whether it was."""
        ...

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None: ...


class Follower(Protocol):
    """What follows a goal's news (the client's goal handle is one)."""

    def news(self, news: GoalNews) -> None: ...


class Stream(Protocol):
    """What a link needs of a subscription: where its ``$/subscribed`` and messages go."""

    def started(self, event: Subscribed) -> None: ...

    def deliver(self, event: TopicMessage) -> None: ...


class Link:
    """One open connection of a client and the calls waiting on it."""

    __slots__ = (
        "conn",
        "fingerprints",
        "goals",
        "limit",
        "live",
        "loop",
        "owner",
        "reader",
        "ready",
        "session",
        "streams",
        "verified",
    )

    def __init__(self, owner: Owner, conn: Connection, limit: int | None = None) -> None:
        self.owner = owner
        self.conn = conn
        self.limit = limit  # the largest message sent, in bytes: max_message_size
        self.loop = asyncio.get_running_loop()
        self.session: ClientSession[asyncio.Future[Arrived]] = ClientSession()
        self.reader: asyncio.Task[None] | None = None
        self.live = True  # False once the connection ended or this side failed it
        self.goals: dict[int, Follower] = {}  # the goals waiting for news, by call id
        # What the latest $/services says of each service's definition, and the services
        # and local types the client has compared with it since.
        self.fingerprints: dict[str, str] = {}
        self.verified: set[tuple[str, type]] = set()
        # What the client found for a call (its service's name and type), by what the call
        # named, once compared: the next call finds it here; forgotten with ``verified``.
        self.ready: dict[Hashable, Any] = {}
        self.streams: dict[int, Stream] = {}  # subscriptions on this connection, by id

    @classmethod
    async def open(
        cls,
        owner: Owner,
        transport: Transport,
        options: Options,
        *,
        open_timeout: float,
        headers: Sequence[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | None = None,
    ) -> tuple[Link, dict[str, str]]:
        """Connect to ``owner.url`` and read the server's first message, its ``$/services``.

        Return the link (its reader not started yet) and the services. Raise
        :class:`~srvwire.errors.ServiceUnavailable` when that fails or takes longer than
        ``open_timeout``, saying why; a peer whose first message is not ``$/services`` is not
        a srvwire server, and is closed with 1008.
        """
        url = owner.url
        opened = False
        try:
            async with asyncio.timeout(open_timeout):
                conn = await transport.connect(url, options, headers=headers, ssl=ssl)
                opened = True
                try:
                    first = await conn.recv()
                except BaseException:
                    owner.spawn(conn.close())
                    raise
        except TimeoutError as exc:
            why = (
                f"the WebSocket opened, but its server sent no $/services within "
                f"{open_timeout:g} s (open_timeout): is it a srvwire server?"
                if opened
                else f"not ready within {open_timeout:g} s (open_timeout)"
            )
            raise ServiceUnavailable(f"cannot connect to {url}: {why}", {"url": url}) from exc
        except (OSError, TransportClosed) as exc:
            raise ServiceUnavailable(f"cannot connect to {url}: {exc}", {"url": url}) from exc
        link = cls(owner, conn, options.max_message_size)
        try:
            events = link.session.receive(first)
            if not (len(events) == 1 and type(events[0]) is ServicesChanged):
                raise ProtocolViolation(
                    InvalidRequest("the server's first message was not $/services")
                )
        except ProtocolViolation as exc:
            await conn.close(CLOSE_PROTOCOL_VIOLATION, "not a srvwire server")
            raise ServiceUnavailable(
                f"cannot connect to {url}: {exc.error.message}", {"url": url}
            ) from exc
        link.fingerprints = events[0].fingerprints
        return link, events[0].services

    def remember(self, key: Hashable, ready: Any) -> None:
        """Keep what a call named ``key`` needs, for the next call (at most :data:`MAX_READY`
        of them: past it, the oldest are found again)."""
        if len(self.ready) >= MAX_READY:
            self.ready.clear()
        self.ready[key] = ready

    def start(self) -> None:
        """Start the reader."""
        self.reader = self.loop.create_task(self.read())

    async def read(self) -> None:
        """Receive every message of this connection; on its end, fail what is pending.

        On a transport that hands each message over as it arrives
        (:meth:`~srvwire.transports.base.Connection.deliver_to`), messages go to :meth:`take`
        from the transport's read callback, without a wake-up of this task for each, and this
        task only waits for the end.
        """
        conn = self.conn
        cause: TransportClosed | None = None
        try:
            conn.deliver_to(self.take)  # where it does, recv returns no message: it raises
            while self.live:
                self.take(await conn.recv())
        except TransportClosed as exc:
            cause = exc
        except asyncio.CancelledError:
            # Nothing in srvwire cancels a reader: its event loop is ending (asyncio.run()
            # cancels every task as it returns). The connection ends with the loop, closed
            # with 1001 so that the server is told, and every call still waiting says why.
            cause = TransportClosed(1001, LOOP_ENDED)
            self.live = False
            self.lost(None, cause)
            with contextlib.suppress(Exception):  # however the close goes, the loop ends
                await conn.close(1001, LOOP_ENDED)
            raise
        except Exception:  # a bug in the transport must not leave calls waiting either
            self.broken()
        finally:
            self.live = False
            self.lost(None, cause)  # nothing to do when this side failed the connection

    def take(self, data: str | bytes) -> None:
        """Handle one message from the server: resolve the call it answers, or pass its news
        on. Something that is not JSON-RPC, or a failure here, fails the connection, and
        nothing after it is taken."""
        if not self.live:
            return
        try:
            if type(data) is str and data.startswith(REPLY_OPENING):
                # The common case, a result written as a srvwire server writes it: straight to
                # its call, as receive() would route it, without its list of events.
                raw = peek_reply(data)
                if raw is not None:
                    future = self.session.pending.pop(raw.id, None)
                    if future is not None and not future.done():
                        future.set_result(raw)
                        return
                    # No call waits for it. Its caller may have given up in this very step
                    # (cancelling a task cancels the future it awaits at once, which from
                    # Python 3.12 is the call's own future inside wait_for): the reply is still
                    # read whole below, and one that is not JSON-RPC still fails the connection.
            try:
                events = self.session.receive(data)
            except ProtocolViolation as exc:
                self.live = False
                self.violation(exc)
                return
            for event in events:
                kind = type(event)
                if kind is TopicMessage:
                    stream = self.streams.get(event.id)
                    if stream is not None:  # else cancelled: its last messages are late
                        stream.deliver(event)
                elif kind is tuple:
                    future = event[0]
                    if not future.done():
                        future.set_result(event[1])
                elif kind is ServicesChanged:
                    self.fingerprints = event.fingerprints
                    self.verified = set()
                    self.ready = {}
                    self.owner.services_changed(self, event.services)
                elif kind is Subscribed:
                    stream = self.streams.get(event.id)
                    if stream is not None:
                        stream.started(event)
                elif kind is TopicsChanged:
                    self.owner.topics_changed(self, event.topics)
                elif kind is Notice:
                    self.notice(event)
                else:
                    assert type(event) is Stray
                    self.stray(event.reply)
        except Exception:  # a bug here must not leave calls waiting for their deadlines
            self.broken()

    def broken(self) -> None:
        """The reader failed (a bug): close the connection, and fail every pending call."""
        self.live = False
        self.owner.logger.exception(
            "the reader of %s failed; closing the connection", self.owner.url
        )
        self.fail("the client failed to process a message from the server")

    def notice(self, notice: Notice) -> None:
        """Hand a goal's ``$/goal`` or ``$/feedback`` to its goal; drop anything else."""
        if notice.method not in (GOAL_METHOD, FEEDBACK_METHOD):
            return
        news = goal_news(notice.method, notice.params)
        if news is None:
            self.owner.logger.debug("dropping a malformed %s", notice.method)
            return
        goal = self.goals.get(news.call)
        if goal is not None:
            goal.news(news)

    def cancel_goal(self, id: int) -> bytes | None:
        """The ``$/cancel`` for the goal ``id``, which keeps waiting for its outcome; None
        when its outcome arrived already."""
        if id not in self.session.pending:
            return None
        return cancel_notification(id).serialize()

    def forget_goal(self, id: int) -> None:
        """Wait no more for the goal ``id``'s outcome or news; the server is not told."""
        self.session.pending.pop(id, None)
        self.goals.pop(id, None)

    def stray(self, reply: Response | ErrorResponse) -> None:
        if reply.id is None and isinstance(reply, ErrorResponse):
            # The server could not read one of our messages; it cannot say which.
            self.owner.logger.warning("the server could not read a message: %s", reply.error)
        else:
            self.owner.logger.debug("dropping a reply for id %r: no call waits for it", reply.id)

    def lost(self, failure: str | None, cause: TransportClosed | None) -> None:
        """Forget this connection, which ended, and fail every call still pending on it.

        ``failure`` says why this side is closing it, when it is; else ``cause`` (or the
        connection's own close code) says how it ended.
        """
        owner = self.owner
        if not owner.forget(self):
            return
        waiters = self.session.lost()
        data: dict[str, Any]
        if failure is not None:
            text = failure
            data = {"close_code": CLOSE_PROTOCOL_VIOLATION}
        elif owner.closed:
            text, data = "the client was closed", {}
        else:
            how = cause if cause is not None else self.conn.closed()
            text, data = str(how), {"close_code": how.code, "close_reason": how.reason}
        data["url"] = owner.url
        if waiters or not owner.closed:
            owner.logger.warning(
                "connection to %s lost: %s; failing %d pending calls", owner.url, text, len(waiters)
            )
        for future in waiters:
            if not future.done():
                error = ConnectionLost(text, dict(data))
                error.__cause__ = cause
                future.set_exception(error)

    def fail(self, failure: str) -> ConnectionLost:
        """End this connection from this side: fail every pending call, close with 1008.

        The calls fail first and the close runs in the background, since it may wait for the
        peer; what the reader still takes in meanwhile reaches no call, goal or subscription.
        Return the error
        the pending calls got.
        """
        self.live = False  # nothing the reader still takes in is handed on
        self.lost(failure, None)
        self.streams.clear()
        self.owner.spawn(self.conn.close(CLOSE_PROTOCOL_VIOLATION, "invalid JSON-RPC"))
        return ConnectionLost(
            failure, {"close_code": CLOSE_PROTOCOL_VIOLATION, "url": self.owner.url}
        )

    def violation(self, exc: ProtocolViolation) -> ConnectionLost:
        """Fail this connection: its server sent something that is not JSON-RPC."""
        message = exc.error.message
        self.owner.logger.error(
            "%s sent something that is not JSON-RPC: %s; closing the connection",
            self.owner.url,
            message,
        )
        return self.fail(f"the server broke the protocol: {message}")

    async def roundtrip(
        self, method: str, params: str | bytes | None, deadline: float, budget: float
    ) -> Arrived:
        """Send one request and wait for its reply until ``deadline`` (loop time).

        ``params`` is the request's JSON object text (a string or UTF-8 bytes), sent with the
        time left as ``_meta.timeout``; None sends no params (and no deadline).
        """
        loop = self.loop
        remaining = deadline - loop.time()
        if remaining <= 0:
            raise DeadlineExceeded(
                f"no time left to send the call ({budget:g} s deadline)",
                {"timeout": budget},
                service=method,
            )
        task = asyncio.current_task(loop)
        if task is None:  # not running on this link's loop
            raise foreign_loop(loop)
        future: asyncio.Future[Arrived] = Answer(loop=loop)
        session = self.session
        id, data = session.request(method, params, None if params is None else remaining, future)
        cancelling = task.cancelling()
        try:
            if self.limit is not None and len(data) > self.limit:
                raise self.too_large(method, len(data))
            # The send waits only on backpressure, so it is bounded only if it does wait: by a
            # bare timer (Expired is a TimeoutError), with no task of its own.
            sending = first_step(self.conn.send(data))
            if isinstance(sending, Pending):
                await self.send_unless_lost(sending, future, deadline - loop.time())
            if future.done():
                # Answered (or failed) while the send waited: wait_for would return just this,
                # after arming a timer and waiting a loop turn (Python 3.11's does not look).
                return future.result()
            # On a future, wait_for creates no task: a timer and a done callback (which the
            # reply runs as it is set, on Python 3.11: see Answer).
            reply = await asyncio.wait_for(future, deadline - loop.time())
            if task.cancelling() > cancelling:
                # Python 3.11's wait_for returns the result when a cancellation arrives after
                # the reply did (gh-86296); the caller asked to stop, so stop.
                raise asyncio.CancelledError
            return reply
        except TimeoutError:
            self.give_up(method, id, future)
            raise DeadlineExceeded(
                f"no response within {budget:g} s", {"timeout": budget}, service=method
            ) from None
        except asyncio.CancelledError:
            self.give_up(method, id, future)
            raise
        except TransportClosed as exc:
            lost = None if not future.done() or future.cancelled() else future.exception()
            if isinstance(lost, ConnectionLost):  # failed already, with why: say that, once
                lost.service = method
                raise lost from exc
            closed = {"close_code": exc.code, "close_reason": exc.reason, "url": self.owner.url}
            raise ConnectionLost(str(exc), closed, service=method) from exc
        except ConnectionLost as exc:  # set on the future when the connection dropped
            exc.service = method
            raise
        finally:
            session.pending.pop(id, None)  # answered or given up: forget it

    async def send_unless_lost(
        self, sending: Pending, future: asyncio.Future[Arrived], delay: float
    ) -> None:
        """Finish a send that waits on backpressure within ``delay`` seconds, or until the
        call's ``future`` fails (the connection was lost, or the client closed it): then the
        call raises that failure at once, not when the transport gives the send up."""
        task = asyncio.current_task()
        assert task is not None
        cancelling = task.cancelling()
        interrupted = False
        waiting = True  # a callback scheduled already is not taken back by removing it

        def interrupt(answered: asyncio.Future[Arrived]) -> None:
            nonlocal interrupted
            if waiting and not answered.cancelled() and answered.exception() is not None:
                interrupted = True
                task.cancel()

        future.add_done_callback(interrupt)
        try:
            await finish_within(sending, delay)
        except asyncio.CancelledError:
            if interrupted and task.uncancel() <= cancelling:
                lost = future.exception()
                assert lost is not None
                raise lost from None
            raise
        finally:
            waiting = False
            future.remove_done_callback(interrupt)

    def too_large(self, method: str, size: int) -> ResourceExhausted:
        """The error of a request of ``size`` bytes, over ``max_message_size``, not sent."""
        return ResourceExhausted(
            f"the request is {size} bytes, over max_message_size={self.limit}; nothing was "
            "sent (raise max_message_size on the client and on the server for larger messages)",
            {"size": size, "max_message_size": self.limit},
            service=method,
        )

    def failure(self, method: str, exc: RPCError | ProtocolViolation) -> RPCError:
        """The error a call to ``method`` raises when decoding its reply raised ``exc``.

        An error reply is that error, with the service named. A reply that turns out not to
        be JSON-RPC fails this connection, as the reader would have, and the call raises the
        ``ConnectionLost`` every pending call got.
        """
        error = self.violation(exc) if isinstance(exc, ProtocolViolation) else exc
        error.service = method
        return error

    def give_up(self, method: str, id: int, future: asyncio.Future[Arrived]) -> None:
        """Tell the server to cancel a call we gave up on, in the background."""
        # Resolved as we gave up: mark an error seen so asyncio stays quiet, and check a reply
        # the reader left unparsed as the reader would have checked it.
        if future.done() and not future.cancelled() and future.exception() is None:
            reply = future.result()
            if isinstance(reply, RawReply):
                try:
                    reply.parse()
                except ProtocolViolation as exc:
                    self.violation(exc)
        data = self.session.cancel(id)
        if data is None:
            return  # answered meanwhile, or the connection is gone
        self.owner.logger.debug("cancelling %s (id %d) on the server", method, id)
        self.owner.spawn(self.send_quietly(data))

    async def send_quietly(self, data: bytes) -> None:
        try:
            await self.conn.send(data)
        except TransportClosed:
            pass  # best effort: a closed connection has cancelled everything anyway
