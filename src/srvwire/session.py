"""The rules of a srvwire conversation, without I/O: one session object per side.

:class:`ServerSession` takes what a client sent and says what to do: answer at once, start a
call, run a notification, cancel a call. It writes every reply. :class:`ClientSession` writes
requests under fresh ids and routes what the server sends to the call that waits for it. Neither
awaits, reads a clock or touches a socket; the asyncio shells (:mod:`srvwire.server`,
:mod:`srvwire.client`) move bytes between a transport and these objects and run the handlers.

Server invariants:

* **Every request gets exactly one reply** while the session is open: an immediate one (an
  error, discovery, a ``$/cancel`` acknowledgement) from :meth:`ServerSession.receive`, or the
  one :meth:`ServerSession.reply` or :meth:`ServerSession.fail` writes for a started
  :class:`Call`, after which the runner says it was :meth:`~ServerSession.sent`. A call that
  ends without a reply (its connection went away) is :meth:`~ServerSession.forget`-ten. A call
  is answered once: :meth:`~ServerSession.reply` and :meth:`~ServerSession.fail` write nothing
  for a call answered already (cancelled, and answered so, while its handler ran on).
* **Admission, in this order:** a closing session answers ``UNAVAILABLE``; once the
  connection's credentials have :meth:`~ServerSession.expire`-d, ``UNAUTHENTICATED``; a method
  that is not a service is discovery, ``$/cancel`` or ``SERVICE_NOT_FOUND``; a service whose
  ``scopes`` the connection does not all hold is ``PERMISSION_DENIED`` (before its params are
  read); past ``max_in_flight`` a call is answered ``RESOURCE_EXHAUSTED``; an id already in
  flight is ``INVALID_REQUEST``. A ``$/subscribe`` past ``max_subscriptions`` running on the
  connection is answered ``RESOURCE_EXHAUSTED`` too.
* **A connection sees only what it may call**: ``rpc.discover`` and ``$/services`` list the
  services whose scopes it holds.
* **In flight** counts calls from admission until the runner says :meth:`~ServerSession.sent`:
  once their reply has been sent (so replies a client does not read count against its limit,
  and past it the reader's own answers push back), or, for a call answered when it was
  cancelled, once its handler's task ended; and notifications from their start to
  :meth:`~ServerSession.done`. A batch's calls count one by one, like single calls.
* **``$/cancel`` reaches a call while it is in :attr:`ServerSession.calls`**, from admission
  until its reply is written; a boolean is never an id, and numbers equal in value are the
  same id. A call with ``"id": null`` cannot be named, but shutdown still finds it in
  :attr:`ServerSession.anonymous`.
* **A batch is answered once, as one array**, in the order of its items, when its last call
  has replied; a batch of notifications only is not answered at all. A batch longer than
  ``max_batch`` is refused whole, with one ``INVALID_REQUEST``, even one of notifications
  only: it is not read. ``rpc.discover`` is answered once per batch, so that no reply is much
  larger than its request.
* **A notification is never answered.** One that cannot run is reported as :class:`Dropped`.
* **Topic requests go to the topics** (:mod:`srvwire.topics`), after the same closing and
  credential checks as calls: ``$/subscribe`` starts a subscription in the connection's outbox,
  whose reply is written when it ends; ``$/publish`` becomes a :class:`Publish` for the shell to
  validate. Neither is read in a batch, and a subscription's id is in use, for calls too, until
  it ends; ``$/cancel`` of it ends it with ``CANCELLED``. One with ``_meta.timeout`` is also a
  :class:`SubscriptionDeadline` for the shell to arm (``DEADLINE_EXCEEDED`` when it passes).
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Generic, Protocol, TypeVar

from srvwire.errors import (
    Cancelled,
    InvalidParams,
    InvalidRequest,
    ParseError,
    PermissionDenied,
    ResourceExhausted,
    RPCError,
    ServiceUnavailable,
    Unauthenticated,
)
from srvwire.protocol import (
    CANCEL_METHOD,
    DISCOVER_METHOD,
    MESSAGE_METHOD,
    PUBLISH_METHOD,
    SERVICES_METHOD,
    SUBSCRIBE_METHOD,
    SUBSCRIBED_METHOD,
    TOPICS_METHOD,
    CallWriter,
    Decoder,
    ErrorResponse,
    Id,
    Notification,
    ProtocolViolation,
    RawJSON,
    Request,
    Response,
    cancel_notification,
    canonical_name,
    parse_incoming,
    parse_replies,
    peek_reply,
    read_cancel,
    serialize_batch,
    services_notification,
    write_call,
    write_response,
)

_TOPIC_METHODS = frozenset({SUBSCRIBE_METHOD, PUBLISH_METHOD})

__all__ = [
    "Call",
    "CancelCall",
    "ClientSession",
    "Dropped",
    "Entry",
    "Notice",
    "NotificationCall",
    "Outbox",
    "Publish",
    "RefusedMessage",
    "ServerSession",
    "Services",
    "ServicesChanged",
    "Stray",
    "Subscribed",
    "SubscriptionDeadline",
    "TopicMessage",
    "Topics",
    "TopicsChanged",
]

_PROTOCOL_PREFIX = "$/"


class Entry(Protocol):
    """What the session needs of a service: its canonical name, and the scopes it needs."""

    @property
    def name(self) -> str: ...

    @property
    def scopes(self) -> frozenset[str]: ...


E = TypeVar("E", bound=Entry)
E_co = TypeVar("E_co", bound=Entry, covariant=True)
W = TypeVar("W")
T = TypeVar("T")


class Services(Protocol[E_co]):
    """What the session needs of a registry (:class:`srvwire.dispatch.ServiceRegistry` is one)."""

    def get(self, name: str) -> E_co | None: ...

    def resolve(self, name: str) -> E_co:
        """Return the entry, or raise the ``ServiceNotFound`` to answer."""
        ...

    def services(self, scopes: frozenset[str] | None = None) -> list[tuple[str, str]]: ...

    def fingerprints(self) -> Mapping[str, str]: ...

    def discover_json(self, scopes: frozenset[str] | None = None) -> str: ...


class Outbox(Protocol):
    """What the session needs of a connection's outbox (:class:`srvwire.topics.Outbox`)."""

    @property
    def subscriptions(self) -> Mapping[Id, Any]: ...

    def cancel(self, id: Id) -> bool: ...


class Topics(Protocol):
    """What the session needs of a server's topics (:class:`srvwire.topics.TopicBoard`)."""

    def subscribe(self, outbox: Any, id: Id, params: Any, scopes: frozenset[str]) -> Any:
        """Start a subscription (its ``$/subscribed`` goes out through ``outbox``), or return
        the error reply as bytes."""
        ...

    def find(self, name: Any, scopes: frozenset[str], publish: bool = False) -> Any:
        """Return the topic, or raise the error to answer."""
        ...

    def announcement(self, scopes: frozenset[str]) -> bytes | None: ...


@dataclass(slots=True)
class Publish:
    """A message a client published on ``topic``: to validate, then hand to the server's
    handlers and the topic's subscribers. ``id`` is the request's when it wants an answer."""

    topic: Any
    id: Id
    message: Any


@dataclass(frozen=True, slots=True)
class RefusedMessage:
    """A message a client published as a notification on ``topic`` that was refused (a topic
    unknown, hidden by scopes or not taking messages), and why (for the log)."""

    topic: str
    reason: str


@dataclass(frozen=True, slots=True)
class SubscriptionDeadline:
    """A subscription started with ``_meta.timeout``: end it after ``timeout`` seconds
    (the asyncio shell arms a timer and calls the outbox's ``expire``)."""

    subscription: Any
    timeout: float


class _Batch:
    """The replies of one batch, in item order; sent when ``waiting`` reaches zero."""

    __slots__ = ("discovered", "replies", "waiting")

    def __init__(self) -> None:
        self.replies: list[bytes | None] = []
        self.waiting = 0
        self.discovered = False  # whether it asked rpc.discover already


class Call(Generic[E]):
    """A call the session admitted: what to run, and where its reply goes.

    ``context``, ``deadline``, ``task``, ``started`` and ``task_cancelled`` belong to whoever
    runs the call (the server keeps them here so that a call is one object); the session never
    reads them.
    """

    __slots__ = (
        "batch",
        "context",
        "deadline",
        "entry",
        "id",
        "index",
        "params",
        "started",
        "task",
        "task_cancelled",
        "timeout",
    )

    def __init__(
        self, id: Id, entry: E, params: Any, timeout: float | None, batch: _Batch | None = None
    ) -> None:
        self.id = id
        self.entry = entry
        self.params = params
        self.timeout = timeout
        self.batch = batch
        self.index = 0
        self.context: Any = None
        self.deadline: float | None = None
        self.task: Any = None
        self.started = False
        self.task_cancelled = False

    def __repr__(self) -> str:
        return f"<Call {self.entry.name} id={self.id!r}>"


@dataclass(slots=True)
class NotificationCall(Generic[E]):
    """A notification to run; tell the session with :meth:`ServerSession.done` when it ends.

    ``in_batch``: it came in a batch. ``context``, ``deadline``, ``task``, ``started`` and
    ``task_cancelled`` belong to whoever runs it, as a :class:`Call`'s do; it has nothing to
    answer, so it counts as started from the first.
    """

    entry: E
    params: Any
    timeout: float | None
    in_batch: bool = False
    context: Any = None
    deadline: float | None = None
    task: Any = None
    started: bool = True
    task_cancelled: bool = False


@dataclass(slots=True)
class CancelCall(Generic[E]):
    """Cancel ``call``, which is to answer ``error`` (``None``: the connection is gone)."""

    call: Call[E]
    error: RPCError | None


@dataclass(slots=True)
class Dropped(Generic[E]):
    """A notification to ``entry`` that was not run, and why (for the log)."""

    entry: E
    reason: str
    busy: bool = False  # dropped because too many calls were in flight


class ServerSession(Generic[E]):
    """The server's side of one connection: admission, cancellation, batches, shutdown.

    ``scopes`` are those the connection's identity holds (none without one).
    """

    def __init__(
        self,
        services: Services[E],
        *,
        max_in_flight: int = 256,
        max_batch: int = 100,
        scopes: frozenset[str] = frozenset(),
        topics: Topics | None = None,
        outbox: Outbox | None = None,
        max_subscriptions: int = 256,
    ) -> None:
        self.services = services
        self.topics = topics
        self.outbox: Outbox = _NoOutbox() if outbox is None else outbox
        """What this connection has to write besides replies: subscriptions and their data."""
        self.max_in_flight = max_in_flight
        self.max_subscriptions = max_subscriptions
        self.max_batch = max_batch
        self.scopes = scopes
        self.expired = False
        self.calls: dict[Id, Call[E]] = {}
        """Calls in flight that ``$/cancel`` can name, by id."""
        self.anonymous: set[Call[E]] = set()
        """Calls in flight with ``"id": null``."""
        self.in_flight = 0
        self.closing = False
        # Whether the registry reads a call in one pass (ServiceRegistry.read_call).
        self._one_pass = hasattr(services, "read_call")

    # --- what the client sent -----------------------------------------------------------------

    def receive(self, data: str | bytes) -> list[Any]:
        """Read one message; return what to do about it, in order.

        Each event is ``bytes`` to send, a :class:`Call` to start, a
        :class:`NotificationCall` to run, a :class:`CancelCall` to carry out, a
        :class:`Publish` to hand on, a :class:`SubscriptionDeadline` to arm, or a
        :class:`Dropped` notification to log. Never raises on what a peer sent.

        A single request to a service is first offered to the registry's ``read_call``, when
        it has one, which reads it and validates its params in one pass; what that refuses is
        parsed in full, so every answer is the one the full parse gives.
        """
        if self._one_pass:
            read = self.services.read_call(data)  # type: ignore[attr-defined]
            if read is not None:
                id, method, params, timeout = read
                events: list[Any] = []
                admitted = self._admit(id, method, params, timeout, None, events)
                if admitted is not None:  # always: it is a call to a service
                    events.append(admitted)
                return events
        incoming = parse_incoming(data)
        items = incoming.items
        if not incoming.is_batch:
            item = items[0]
            if type(item) is Request:
                events = []
                admitted = self._admit(
                    item.id, item.method, item.params, item.timeout, None, events
                )
                if admitted is not None:  # None: a subscription, which answers later
                    events.append(admitted)
                return events
            if type(item) is Notification:
                event = self._notification(item)
                return [] if event is None else [event]
            assert type(item) is ErrorResponse
            return [item.serialize()]
        if len(items) > self.max_batch:
            too_long = InvalidRequest(
                f"Invalid Request: a batch of {len(items)} messages; at most "
                f"{self.max_batch} are read in one batch"
            )
            return [ErrorResponse(None, too_long).serialize()]
        batch = _Batch()
        events = []
        for item in items:
            if type(item) is Request:
                index = len(batch.replies)
                batch.replies.append(None)
                admitted = self._admit(
                    item.id, item.method, item.params, item.timeout, batch, events
                )
                assert admitted is not None  # a batch's $/subscribe is answered at once
                if isinstance(admitted, bytes):
                    batch.replies[index] = admitted
                else:
                    admitted.index = index
                    batch.waiting += 1
                    events.append(admitted)
            elif type(item) is Notification:
                event = self._notification(item)
                if event is not None:
                    if type(event) is NotificationCall:
                        event.in_batch = True
                    events.append(event)
            else:
                assert type(item) is ErrorResponse
                batch.replies.append(item.serialize())
        if batch.replies and not batch.waiting:
            events.append(serialize_batch(r for r in batch.replies if r is not None))
        return events

    def _admit(
        self,
        id: Id,
        method: str,
        params: Any,
        timeout: float | None,
        batch: _Batch | None,
        events: list[Any],
    ) -> bytes | Call[E] | None:
        """Admit a call (a :class:`~srvwire.protocol.Request`'s fields, so that a request read
        in one pass needs no object of its own), or return its reply; a ``$/cancel`` adds its
        event to ``events``."""
        if self.closing:
            return self._refuse(id, ServiceUnavailable("the server is shutting down"))
        if self.expired:
            return self._refuse(id, _expired())
        entry = self.services.get(method)
        if entry is None:
            return self._special(Request(id, method, params, timeout), batch, events)
        if not entry.scopes <= self.scopes:
            return ErrorResponse(id, self._denied(entry)).serialize()
        if self.in_flight >= self.max_in_flight:
            exhausted = ResourceExhausted(
                f"too many calls in flight on this connection (the limit is {self.max_in_flight})",
                {"limit": self.max_in_flight},
                service=entry.name,
            )
            return self._refuse(id, exhausted)
        if id is not None and (id in self.calls or id in self.outbox.subscriptions):
            duplicate = InvalidRequest(
                f"Invalid Request: id {id!r} is already used by a call in flight on this "
                "connection",
                service=entry.name,
            )
            return self._refuse(id, duplicate)
        call = Call(id, entry, params, timeout, batch)
        if id is not None:
            self.calls[id] = call
        else:
            self.anonymous.add(call)
        self.in_flight += 1
        return call

    def _special(self, request: Request, batch: _Batch | None, events: list[Any]) -> bytes | None:
        """Answer a request for a method that is not a service: discovery, protocol, topics,
        unknown; None for a subscription, which answers when it ends."""
        if request.method == DISCOVER_METHOD:
            if batch is not None:
                if batch.discovered:  # the document once per batch: a reply stays small
                    again = InvalidRequest(
                        "Invalid Request: rpc.discover is answered once per batch"
                    )
                    return self._refuse(request.id, again)
                batch.discovered = True
            document = self.services.discover_json(self.scopes)
            return Response(request.id, RawJSON(document)).serialize()
        if request.method == CANCEL_METHOD:
            named = read_cancel(request.params)
            if isinstance(named, InvalidParams):  # a request is answered; a notification not
                return self._refuse(request.id, named)
            cancel = self._cancel(named)
            if cancel is not None:
                events.append(cancel)
            return Response(request.id, None).serialize()
        if request.method in _TOPIC_METHODS and self.topics is not None:
            return self._topic_request(request, batch, events)
        try:
            self.services.resolve(request.method)
        except RPCError as exc:
            return self._refuse(request.id, exc)
        raise AssertionError("unreachable: resolve() found what get() did not")  # pragma: no cover

    def _topic_request(
        self, request: Request, batch: _Batch | None, events: list[Any]
    ) -> bytes | None:
        """``$/subscribe`` or an acknowledged ``$/publish`` (see :mod:`srvwire.topics`)."""
        id = request.id
        assert self.topics is not None
        if batch is not None or id is None:
            refused = InvalidRequest(
                f"Invalid Request: {request.method} is read only on its own, with an id"
            )
            return self._refuse(request.id, refused)
        if id in self.calls or id in self.outbox.subscriptions:
            duplicate = InvalidRequest(
                f"Invalid Request: id {id!r} is already used by a call in flight on this connection"
            )
            return self._refuse(request.id, duplicate)
        if request.method == SUBSCRIBE_METHOD:
            limit = self.max_subscriptions
            if len(self.outbox.subscriptions) >= limit:
                topic = request.params.get("topic") if type(request.params) is dict else None
                exhausted = ResourceExhausted(
                    f"too many subscriptions on this connection (the limit is {limit}); end "
                    "one with $/cancel first, or give the server a larger max_subscriptions",
                    {"limit": limit},
                    service=topic if type(topic) is str else None,
                )
                return self._refuse(id, exhausted)
            subscribed = self.topics.subscribe(self.outbox, id, request.params, self.scopes)
            if type(subscribed) is bytes:
                return subscribed
            if request.timeout is not None:
                events.append(SubscriptionDeadline(subscribed, request.timeout))
            return None
        publish = self._publish(request.params, id)
        if not isinstance(publish, Publish):
            return ErrorResponse(id, publish).serialize()
        events.append(publish)
        return None

    def _publish(self, params: Any, id: Id) -> Publish | RPCError:
        """Admit a ``$/publish``: the message to validate and hand on, or the error that
        refuses it (the reply to a request, the log line of a notification)."""
        assert self.topics is not None
        try:
            if type(params) is not dict or "message" not in params:
                raise InvalidParams(
                    "invalid params: $/publish needs params {'topic': name, 'message': {...}}"
                )
            topic = self.topics.find(params.get("topic"), self.scopes, publish=True)
        except RPCError as exc:
            return exc
        return Publish(topic, id, params["message"])

    def _refuse(self, id: Id, error: RPCError) -> bytes:
        """The error reply to the request ``id``, answered at once, without running anything."""
        return ErrorResponse(id, error).serialize()

    def _notification(self, note: Notification) -> Any:
        method = note.method
        if method.startswith(_PROTOCOL_PREFIX):
            if method == PUBLISH_METHOD and self.topics is not None and not self.closing:
                publish = self._publish(note.params, None)
                if isinstance(publish, Publish):
                    return publish
                named = note.params.get("topic") if type(note.params) is dict else None
                return RefusedMessage(named if type(named) is str else "?", publish.message)
            return self._cancel(read_cancel(note.params)) if method == CANCEL_METHOD else None
        entry = self.services.get(method)
        if entry is None or self.closing:
            return None
        if self.expired:
            return Dropped(entry, _expired().message)
        if not entry.scopes <= self.scopes:
            return Dropped(entry, self._denied(entry).message)
        if note.error is not None:
            return Dropped(entry, str(note.error))
        if self.in_flight >= self.max_in_flight:
            return Dropped(entry, "too many calls in flight", busy=True)
        self.in_flight += 1
        return NotificationCall(entry, note.params, note.timeout)

    def _denied(self, entry: E) -> PermissionDenied:
        missing = sorted(entry.scopes - self.scopes)
        return PermissionDenied(
            f"permission denied: {entry.name} needs the "
            f"{'scope' if len(missing) == 1 else 'scopes'} {', '.join(missing)}, "
            "which this connection's identity does not hold",
            {"missing_scopes": missing},
            service=entry.name,
        )

    def _cancel(self, id: Id | InvalidParams) -> CancelCall[E] | None:
        """``$/cancel`` of the call ``id`` (what :func:`read_cancel` read of its params), if it
        is still in flight; params that name no call cancel nothing."""
        if isinstance(id, InvalidParams):
            return None
        call = self.calls.get(id)
        if call is None:
            self.outbox.cancel(id)  # a subscription: its writer answers CANCELLED
            return None
        return CancelCall(call, Cancelled("the caller cancelled the call"))

    # --- what the runner reports ----------------------------------------------------------------

    def reply(self, call: Call[E], result: bytes, whole: bool = False) -> bytes | None:
        """Write the reply to ``call`` with ``result`` (its JSON, or with ``whole`` the whole
        response already written); None while its batch waits, or when ``call`` was answered
        already."""
        id = call.id
        if call.batch is None and id is not None:  # most replies: _answer's steps, inline
            if self.calls.get(id) is not call:
                return None  # answered already: a call has one reply
            del self.calls[id]
            return result if whole else write_response(id, result)
        return self._answer(call, result if whole else write_response(id, result))

    def fail(self, call: Call[E], error: RPCError) -> bytes | None:
        """Write the error reply to ``call``; None while its batch waits, or when ``call`` was
        answered already."""
        return self._answer(call, ErrorResponse(call.id, error).serialize())

    def _answer(self, call: Call[E], reply: bytes) -> bytes | None:
        if not self._unlist(call):
            return None  # answered already: a call has one reply
        batch = call.batch
        if batch is None:
            return reply
        batch.replies[call.index] = reply
        batch.waiting -= 1
        if batch.waiting:
            return None
        return serialize_batch(r for r in batch.replies if r is not None)

    def refuse(self, id: Id, error: RPCError) -> bytes:
        """The error reply to a request the session does not track (an acknowledged publish)."""
        return ErrorResponse(id, error).serialize()

    def answering(self, call: Call[E]) -> bool:
        """Whether ``call`` is still in flight: admitted, and its reply not written yet."""
        if call.id is None:
            return call in self.anonymous
        return self.calls.get(call.id) is call

    def sent(self, call: Call[E]) -> None:
        """The reply :meth:`reply` or :meth:`fail` wrote has gone out (or to its batch)."""
        self.in_flight -= 1

    def forget(self, call: Call[E]) -> None:
        """``call`` ended without a reply (its connection went away): it no longer counts."""
        if self._unlist(call):
            self.in_flight -= 1

    def _unlist(self, call: Call[E]) -> bool:
        """Take ``call`` out of the lists ``$/cancel`` and shutdown look in; say if it was."""
        id = call.id
        if id is None:
            if call in self.anonymous:
                self.anonymous.discard(call)
                return True
        elif self.calls.get(id) is call:
            del self.calls[id]
            return True
        return False

    def done(self, notification: NotificationCall[E]) -> None:
        """A notification's handler ended: it no longer counts as in flight."""
        self.in_flight -= 1

    # --- shutdown -------------------------------------------------------------------------------

    def announcement(self) -> bytes:
        """The ``$/services`` notification: the first message, and the one after each change."""
        services = self.services.services(self.scopes)
        return services_notification(services, self.services.fingerprints()).serialize()

    def topics_announcement(self) -> bytes | None:
        """The ``$/topics`` notification, after ``$/services``; None for a server that has no
        topics (and never said it had any)."""
        return None if self.topics is None else self.topics.announcement(self.scopes)

    def expire(self) -> None:
        """The connection's credentials expired: from now on every call is answered
        ``UNAUTHENTICATED`` (the calls in flight finish)."""
        self.expired = True

    def close(self) -> None:
        """Stop admitting: from now on every new call is answered ``UNAVAILABLE``."""
        self.closing = True

    def cancel_all(self, error: RPCError | None) -> list[CancelCall[E]]:
        """Cancel every call in flight; with ``error`` they answer it, without they stay silent.

        Without ``error`` (the connection is gone) the session also forgets them.
        """
        cancels = [CancelCall(call, error) for call in (*self.calls.values(), *self.anonymous)]
        if error is None:
            self.calls.clear()
            self.anonymous.clear()
            self.in_flight -= len(cancels)
        return cancels


class _NoOutbox:
    """The outbox of a session without topics: no subscription, ever."""

    subscriptions: Mapping[Id, Any] = MappingProxyType({})

    def cancel(self, id: Id) -> bool:
        return False


def _expired() -> Unauthenticated:
    return Unauthenticated("the credentials of this connection expired; reconnect with fresh ones")


# --- the client's side ---------------------------------------------------------------------------


@dataclass(slots=True)
class ServicesChanged:
    """The server's ``$/services``: every service it offers now, canonical name -> type, and
    the fingerprints of their definitions where the server gives them."""

    services: dict[str, str]
    fingerprints: dict[str, str] = field(default_factory=dict)


@dataclass(slots=True)
class Notice:
    """Another notification from the server (a goal's ``$/goal`` or ``$/feedback``), parsed;
    for whoever follows that method."""

    method: str
    params: Any


@dataclass(slots=True)
class TopicsChanged:
    """The server's ``$/topics``: every topic it offers now, canonical name -> its entry
    (``type``, ``qos``, ``publish``)."""

    topics: dict[str, dict[str, Any]]


@dataclass(slots=True)
class Subscribed:
    """The server's ``$/subscribed``: the subscription ``id`` started, with what it granted
    (``seq``: the last sequence number the topic published)."""

    id: int
    granted: dict[str, Any]


@dataclass(slots=True)
class TopicMessage:
    """One ``$/message`` of the subscription ``id``, with its ``seq`` and ``dropped``.

    Recognised by its opening alone (``start`` > 0, as a srvwire server writes it),
    ``message`` is the whole text, not parsed past the opening, and the message member begins
    at ``start``; else (``start`` 0) ``message`` is the parsed message data. Either way
    :meth:`decode` makes the typed message.
    """

    id: int
    seq: int
    dropped: int
    message: Any
    start: int = 0

    def decode(self, decoder: Decoder[T]) -> T:
        """Return the message, typed: validated in one pass when it can be, else parsed in full.

        A recognised message validates the text of its message member straight into its type;
        when that is refused, only the full parse can tell a message that does not fit
        (``decoder``'s ``ValueError``, from the parsed data) from one that is not the
        ``$/message`` its opening says (:class:`~srvwire.protocol.ProtocolViolation`).
        """
        start = self.start
        if start:
            try:
                return decoder.from_json(self.message[start:-2])
            except ValueError:
                pass
            return decoder.from_data(self.parse().message)
        return decoder.from_data(self.message)

    def parse(self) -> TopicMessage:
        """Parse the whole text of a recognised message, as :meth:`ClientSession.receive`
        parses any other; return it parsed.

        Raise :class:`~srvwire.protocol.ProtocolViolation` when it is not JSON-RPC, not a
        well-formed ``$/message``, or not the one its opening says: a later member may name
        another ``method``, ``subscription``, ``seq`` or ``dropped``.
        """
        try:
            (notification,) = parse_replies(self.message)  # it opens with "{": not a batch
        except (ParseError, InvalidRequest) as exc:
            raise ProtocolViolation(exc) from None
        if not isinstance(notification, Notification) or notification.method != MESSAGE_METHOD:
            raise ProtocolViolation(
                InvalidRequest(f"Invalid {MESSAGE_METHOD}: 'method' given twice")
            )
        parsed = _topic_news(notification)
        assert isinstance(parsed, TopicMessage)  # the method is $/message
        if (parsed.id, parsed.seq, parsed.dropped) != (self.id, self.seq, self.dropped):
            raise ProtocolViolation(
                InvalidRequest(
                    f"Invalid {MESSAGE_METHOD}: 'subscription', 'seq' or 'dropped' given twice"
                )
            )
        return parsed


_COUNT = r"(0|[1-9][0-9]{0,17})"  # a JSON integer, no leading zero, of at most 18 digits
_MESSAGE_OPENING = re.compile(
    r'\{"jsonrpc":"2\.0","method":"\$/message","params":\{"subscription":' + _COUNT + ","
    r'"seq":' + _COUNT + r',"dropped":' + _COUNT + r',"message":'
)


@dataclass(slots=True)
class Stray:
    """A reply no call waits for (its caller gave up), or an error the server sent about a
    message it could not read (``id`` null); for the log."""

    reply: Response | ErrorResponse


_MAX_WRITERS = 256
"""The methods a client session keeps a :class:`~srvwire.protocol.CallWriter` for at once."""


class ClientSession(Generic[W]):
    """The client's side of one connection: ids, the calls waiting, and what the server said.

    Each waiting call is a *waiter* of the caller's choosing (the client uses a future); the
    session hands it back with its reply. Invariants: ids are positive integers, never reused
    on a session; a waiter is in :attr:`pending` from :meth:`request` until its reply arrives,
    it is :meth:`cancel`-led or taken out of :attr:`pending` by its caller, or the connection is
    :meth:`lost`.
    """

    def __init__(self) -> None:
        self._ids: Iterator[int] = itertools.count(1)
        self.pending: dict[int, W] = {}
        self._writers: dict[str, CallWriter] = {}  # by method, made on its first call

    def request(
        self, method: str, params: str | bytes | None, timeout: float | None, waiter: W
    ) -> tuple[int, bytes]:
        """Write a request for ``method`` and register ``waiter`` under its new id.

        ``params`` is the request's JSON object text, as a string or UTF-8 bytes (None: no
        params), ``timeout`` the time the caller has left, sent as ``_meta.timeout`` rounded to
        the microsecond. Raise ``ValueError`` for params that are not a JSON object when a
        timeout is sent; nothing is registered then.
        """
        id = next(self._ids)
        data = None
        if params is not None and timeout is not None:
            if isinstance(params, bytes):
                writer = self._writers.get(method)
                if writer is None:
                    if len(self._writers) >= _MAX_WRITERS:
                        self._writers.clear()
                    writer = self._writers[method] = CallWriter(method)
                data = writer(id, params, timeout)
            else:
                data = write_call(id, method, params, round(timeout, 6))
        if data is None:
            text = params.decode() if isinstance(params, bytes) else params
            left = None if timeout is None else round(timeout, 6)
            data = Request(id, method, None if text is None else RawJSON(text), left).serialize()
        self.pending[id] = waiter
        return id, data

    def cancel(self, id: int) -> bytes | None:
        """Give up on the call ``id``: the ``$/cancel`` to send, or None if it is not waiting."""
        if self.pending.pop(id, None) is None:
            return None
        return cancel_notification(id).serialize()

    def lost(self) -> list[W]:
        """The connection ended: return every waiter, and wait for nothing any more."""
        waiters = list(self.pending.values())
        self.pending = {}
        return waiters

    def receive(self, data: str | bytes) -> list[Any]:
        """Read one message from the server; return ``(waiter, reply)`` pairs and news
        (:class:`ServicesChanged`, :class:`Notice`, :class:`Stray`).

        A response a call waits for, written as a srvwire server writes it, is handed over
        unparsed (a :class:`~srvwire.protocol.RawReply`, decoded by its caller), and so is a
        ``$/message`` (a :class:`TopicMessage` read up to its message member, decoded by its
        subscription); anything else is parsed here. Raise
        :class:`~srvwire.protocol.ProtocolViolation` when it is not JSON-RPC: the connection
        cannot be trusted to route other replies either.
        """
        if type(data) is str:
            if data.startswith('{"jsonrpc":"2.0","method":"$/message"') and data.endswith("}}"):
                opening = _MESSAGE_OPENING.match(data)
                if opening is not None:  # as a srvwire server writes it: the message unparsed
                    id, seq, dropped = opening.groups()
                    return [TopicMessage(int(id), int(seq), int(dropped), data, opening.end())]
            raw = peek_reply(data)
            if raw is not None:
                waiter = self.pending.pop(raw.id, None)
                if waiter is not None:
                    return [(waiter, raw)]
        try:
            messages = parse_replies(data)
        except (ParseError, InvalidRequest) as exc:
            raise ProtocolViolation(exc) from None
        # Every item is read before any waiter is taken: a violation anywhere in a batch
        # leaves every call pending, for lost() to hand back.
        services = [
            ServicesChanged(parse_services(message), parse_fingerprints(message))
            for message in messages
            if isinstance(message, Notification) and message.method == SERVICES_METHOD
        ]
        events: list[Any] = []
        for message in messages:
            if isinstance(message, Notification):
                method = message.method
                if method == SERVICES_METHOD:
                    events.append(services.pop(0))
                elif method in _TOPIC_NEWS:
                    events.append(_topic_news(message))
                else:
                    events.append(Notice(method, message.params))
                continue
            id = message.id
            waiter = self.pending.pop(id, None) if type(id) is int else None
            events.append(Stray(message) if waiter is None else (waiter, message))
        return events


def parse_fingerprints(message: Notification) -> dict[str, str]:
    """Read the fingerprints of a ``$/services`` that :func:`parse_services` accepted, by
    canonical service name; an entry with none, or one that is not a string, has none."""
    found: dict[str, str] = {}
    params: Any = message.params
    for entry in params["services"]:
        value = entry.get("fingerprint")
        if isinstance(value, str):
            found[canonical_name(entry["name"])] = value
    return found


_TOPIC_NEWS = frozenset({MESSAGE_METHOD, SUBSCRIBED_METHOD, TOPICS_METHOD})


def _topic_news(message: Notification) -> TopicMessage | Subscribed | TopicsChanged:
    """Read ``$/message``, ``$/subscribed`` or ``$/topics``; raise ProtocolViolation when it
    is malformed."""
    method = message.method
    params = message.params if isinstance(message.params, dict) else {}
    if method == TOPICS_METHOD:
        listed = params.get("topics")
        if isinstance(listed, list) and all(
            isinstance(t, dict)
            and isinstance(t.get("name"), str)
            and isinstance(t.get("type"), str)
            for t in listed
        ):
            return TopicsChanged({canonical_name(t["name"]): t for t in listed})
        raise ProtocolViolation(
            InvalidRequest(f"{TOPICS_METHOD} needs params {{'topics': [{{'name', 'type'}}]}}")
        )
    id = params.get("subscription")
    if type(id) is not int:
        raise ProtocolViolation(InvalidRequest(f"{method} needs an integer 'subscription'"))
    if method == SUBSCRIBED_METHOD:
        return Subscribed(id, params)
    seq = params.get("seq")
    dropped = params.get("dropped", 0)
    if type(seq) is not int or type(dropped) is not int or "message" not in params:
        raise ProtocolViolation(
            InvalidRequest(f"{MESSAGE_METHOD} needs integers 'seq' and 'dropped', and 'message'")
        )
    return TopicMessage(id, seq, dropped, params["message"])


def parse_services(message: Notification) -> dict[str, str]:
    """Read a ``$/services`` notification; raise ProtocolViolation when it is malformed."""
    params = message.params
    listed = params.get("services") if isinstance(params, dict) else None
    if not isinstance(listed, list):
        raise ProtocolViolation(
            InvalidRequest(f"{SERVICES_METHOD} needs params {{'services': [...]}}")
        )
    services: dict[str, str] = {}
    for entry in listed:
        name = entry.get("name") if isinstance(entry, dict) else None
        type_name = entry.get("type") if isinstance(entry, dict) else None
        if not (isinstance(name, str) and isinstance(type_name, str)):
            raise ProtocolViolation(
                InvalidRequest(
                    f"{SERVICES_METHOD} entries need a string 'name' and 'type', got {entry!r}"
                )
            )
        services[canonical_name(name)] = type_name
    return services
