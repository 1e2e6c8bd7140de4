"""Topics without I/O: QoS, each topic's sequence and history, and each connection's outbox.

A :class:`Topic` numbers what is published on it and keeps the last ``depth`` messages when
it is ``transient_local``. A :class:`Subscription` is one client's request to receive a topic:
a keep-last queue of ``depth`` messages while its connection takes no more. An
:class:`Outbox` is what one connection has to write: control messages (replies that end
subscriptions, ``$/subscribed``) first, then the queued topic data, one subscription after the
other. The asyncio shell (:class:`srvwire.serving.Writer`) takes :meth:`Outbox.next` and sends
it, one message at a time, and takes nothing while the connection is past its budget of bytes
waiting to be sent.

Invariants:

* **A message is serialized once.** :meth:`Topic.publish` takes the message's JSON bytes and
  shares them with every subscription; only the small envelope of ``$/message`` is written per
  subscriber, when the message is taken out.
* **Control goes first.** :meth:`Outbox.next` returns a control message whenever one waits; topic
  data only when none does.
* **Round-robin.** Subscriptions with data take turns, one message each, so a flooded topic
  cannot starve another on the same connection.
* **Depth bounds what waits on a connection that takes no more.** While the connection's
  transport takes more (:attr:`Outbox.writable`: it is not congested), a message is queued
  whatever the count, bounded by the budget below alone: a burst published within one turn of
  the event loop, before the writer runs, is what the writer sends next, not a subscriber
  that did not keep up. While the transport is congested (the peer does not read what was
  sent), a subscription holds at most ``depth`` messages.
* **One budget per connection.** The topic data an outbox holds and the bytes its
  connection's transport holds (replies, and data already sent) share the connection's
  ``budget`` (the server's ``max_queued_bytes``): topic data may take what the transport
  leaves, ``budget - buffered()``, checked as each message is offered (a message is always
  accepted into an empty outbox, so that one message can always pass). When a message does
  not fit (the budget, or the depth of a congested connection), ``best_effort`` drops the
  subscription's oldest (counted in the next ``dropped``; the ``seq`` numbers show the gap);
  ``reliable`` ends the subscription with ``RESOURCE_EXHAUSTED`` and never drops silently. A
  reply is never refused: once it is queued, :meth:`Outbox.fit` gives up topic data until the
  two fit again, best effort's oldest messages first, then whole reliable subscriptions, which
  end as above.
* **Sequence numbers per topic.** Every publication takes the next ``seq`` (from 1); a
  subscriber sees them increasing, and ``seq - previous - 1 == dropped`` for each message of
  a best-effort subscription.
* **Every subscription ends once, with a reply**: ``$/cancel`` (``CANCELLED``), the topic
  removed (``SERVICE_NOT_FOUND``), a reliable subscriber that cannot keep up
  (``RESOURCE_EXHAUSTED``), its ``_meta.timeout`` passed (``DEADLINE_EXCEEDED``, armed by the
  asyncio shell, which calls :meth:`Outbox.expire`); or silently with its connection. Its
  queue is dropped then, and its deadline's timer cancelled.
"""

from __future__ import annotations

import secrets
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from srvwire.errors import (
    Cancelled,
    DeadlineExceeded,
    InvalidParams,
    PermissionDenied,
    ResourceExhausted,
    RPCError,
    ServiceNotFound,
)
from srvwire.protocol import (
    SUBSCRIBED_METHOD,
    TOPICS_METHOD,
    ErrorResponse,
    Id,
    Notification,
    Response,
    encode_json,
)

__all__ = [
    "Gaps",
    "Outbox",
    "QoS",
    "Subscription",
    "Topic",
    "TopicBoard",
    "publish_ack",
    "topics_notification",
]


RELIABILITIES = ("reliable", "best_effort")
DURABILITIES = ("volatile", "transient_local")
MAX_DEPTH = 10_000

T = TypeVar("T")


def _qos_error(path: str, message: str) -> InvalidParams:
    return InvalidParams(
        f"invalid params: {path}: {message}",
        {"errors": [{"path": path, "message": message, "type": "value_error"}]},
    )


@dataclass(frozen=True, slots=True)
class QoS:
    """Quality of service in ROS's words (ROS's defaults: keep last 10, reliable, volatile).

    ``depth`` is the keep-last queue of each subscription (and the history a
    ``transient_local`` topic keeps); ``reliability`` is ``"reliable"`` or ``"best_effort"``;
    ``durability`` is ``"volatile"`` or ``"transient_local"``.
    """

    depth: int = 10
    reliability: str = "reliable"
    durability: str = "volatile"

    def __post_init__(self) -> None:
        if type(self.depth) is not int or not 1 <= self.depth <= MAX_DEPTH:
            raise ValueError(f"depth must be an integer from 1 to {MAX_DEPTH}, not {self.depth!r}")
        if self.reliability not in RELIABILITIES:
            raise ValueError(
                f"reliability must be 'reliable' or 'best_effort', not {self.reliability!r}"
            )
        if self.durability not in DURABILITIES:
            raise ValueError(
                f"durability must be 'volatile' or 'transient_local', not {self.durability!r}"
            )

    @property
    def best_effort(self) -> bool:
        return self.reliability == "best_effort"

    def to_json(self) -> dict[str, Any]:
        return {
            "depth": self.depth,
            "reliability": self.reliability,
            "durability": self.durability,
        }

    def grant(self, asked: Any) -> QoS:
        """The QoS a subscription gets when it asks for ``asked`` (a JSON object or None) on a
        topic with this QoS; raise :class:`InvalidParams` with the field path.

        A subscriber chooses its own ``depth`` and ``reliability`` (they are about its own
        queue); it gets ``transient_local`` only from a topic that keeps history, and then at
        most the topic's ``depth`` messages are replayed.
        """
        if asked is None:
            return self
        if type(asked) is not dict:
            raise _qos_error("qos", "expected an object")
        for key in asked:
            if key not in ("depth", "reliability", "durability"):
                raise _qos_error(f"qos.{key}", "unknown QoS setting")
        depth = asked.get("depth", self.depth)
        reliability = asked.get("reliability", self.reliability)
        durability = asked.get("durability", self.durability)
        if type(depth) is not int or not 1 <= depth <= MAX_DEPTH:
            raise _qos_error("qos.depth", f"expected an integer from 1 to {MAX_DEPTH}")
        if reliability not in RELIABILITIES:
            raise _qos_error("qos.reliability", "expected 'reliable' or 'best_effort'")
        if durability not in DURABILITIES:
            raise _qos_error("qos.durability", "expected 'volatile' or 'transient_local'")
        if self.durability == "volatile":
            durability = "volatile"
        return QoS(depth, reliability, durability)


class Topic(Generic[T]):
    """One topic: its name, type and QoS, its sequence, its history, its subscriptions.

    ``entry`` is whatever the shell keeps with it (the message class, the handlers of
    client-published messages); this module never reads it. ``accepts`` says whether clients
    may publish on it. ``epoch``, random, names this instance of the topic, whose sequence
    numbers start at 1: a subscriber resuming on a server restarted (or a topic declared
    anew) finds another epoch in ``$/subscribed``, and knows not to compare the numbers.
    """

    __slots__ = (
        "accepts",
        "entry",
        "epoch",
        "history",
        "name",
        "qos",
        "scopes",
        "seq",
        "subscriptions",
    )

    def __init__(
        self,
        name: str,
        entry: T,
        qos: QoS = QoS(),
        *,
        scopes: frozenset[str] = frozenset(),
        accepts: bool = False,
    ) -> None:
        self.name = name
        self.entry = entry
        self.qos = qos
        self.scopes = scopes
        self.accepts = accepts
        self.seq = 0  # the last sequence number published
        self.epoch = secrets.token_hex(8)
        self.history: deque[tuple[int, bytes]] = deque(
            maxlen=qos.depth if qos.durability == "transient_local" else 0
        )
        self.subscriptions: set[Subscription] = set()

    def set_qos(self, qos: QoS) -> None:
        """Change the topic's QoS (before anyone subscribes): the history keeps the newest
        messages it may still hold."""
        self.qos = qos
        self.history = deque(
            self.history, maxlen=qos.depth if qos.durability == "transient_local" else 0
        )

    def publish(self, data: bytes) -> int:
        """Publish the message ``data`` (its JSON, written once) to every subscription; return
        how many subscriptions it reached (a reliable one it ended is not counted)."""
        self.seq += 1
        seq = self.seq
        if self.history.maxlen:
            self.history.append((seq, data))
        subscriptions = self.subscriptions
        if subscriptions:
            for subscription in tuple(subscriptions):
                subscription.offer(seq, data)
        return len(subscriptions)

    def describe(self) -> dict[str, Any]:
        """What ``$/topics`` says of it (the type name comes from the entry's ``type_name``,
        the type's fingerprint from its ``fingerprint``, when it has one)."""
        described = {
            "name": self.name,
            "type": str(getattr(self.entry, "type_name", "")),
            "qos": self.qos.to_json(),
            "publish": self.accepts,
        }
        digest = getattr(self.entry, "fingerprint", None)
        if isinstance(digest, str):
            described["fingerprint"] = digest
        return described


class Subscription:
    """One subscription: its id (the ``$/subscribe`` request's), its topic, its queue."""

    __slots__ = ("dropped", "id", "outbox", "prefix", "qos", "queue", "ready", "timer", "topic")

    def __init__(self, id: Id, topic: Topic[Any], qos: QoS, outbox: Outbox) -> None:
        self.id = id
        self.topic = topic
        self.qos = qos
        self.outbox = outbox
        self.queue: deque[tuple[int, bytes]] = deque()
        self.dropped = 0  # dropped since the last message taken out
        self.ready = False  # in the outbox's round-robin: exactly while its queue is not empty
        self.timer: Any = None  # its deadline's timer (has cancel()), set by the asyncio shell
        self.prefix = (
            b'{"jsonrpc":"2.0","method":"$/message","params":{"subscription":'
            + encode_json(id).encode()
            + b',"seq":'
        )

    def offer(self, seq: int, data: bytes) -> None:
        """Queue the message ``seq``; past the bounds, drop the oldest or end (see module)."""
        outbox = self.outbox
        queue = self.queue
        size = len(data)
        queued = outbox.queued
        if (len(queue) >= self.qos.depth and not outbox.writable()) or (
            queued and queued + size > outbox.budget - outbox.buffered()
        ):
            if not self.make_room(seq, size):
                return
        queue.append((seq, data))
        outbox.queued += size
        if not self.ready:
            self.ready = True
            outbox.ready.append(self)
        if not outbox.woken:
            outbox.woken = True
            outbox.wake()

    def make_room(self, seq: int, size: int) -> bool:
        """Make room for the message ``seq`` of ``size`` bytes: drop the oldest (best effort)
        or end the subscription (reliable); return whether the message may be queued."""
        outbox = self.outbox
        queue = self.queue
        room = outbox.budget - outbox.buffered()
        depth = None if outbox.writable() else self.qos.depth  # None: no count bound now
        while (depth is not None and len(queue) >= depth) or (
            outbox.queued and outbox.queued + size > room
        ):
            if not self.qos.best_effort:
                full = depth is not None and len(queue) >= depth
                outbox.end(self, self.exhausted(seq, None if full else room))
                return False
            if not queue:  # the connection's budget is held by other subscriptions
                self.dropped += 1
                if self.ready:  # it gave up its last message: nothing left to take turns
                    self.ready = False
                    outbox.ready.remove(self)
                return False
            _, old = queue.popleft()
            outbox.queued -= len(old)
            self.dropped += 1
        return True

    def exhausted(self, seq: int, room: int | None) -> ResourceExhausted:
        """How a reliable subscription that did not keep up ends: its queue was full (``room``
        None), or the connection's budget was spent, with ``room`` bytes left for topic data."""
        outbox = self.outbox
        if room is None:
            why = (
                f"its queue of {self.qos.depth} messages was full while its connection took no "
                "more (the peer did not read what was sent), and the subscription is reliable; "
                "read faster, or subscribe with a larger depth, or best_effort to drop the "
                "oldest instead"
            )
        else:
            why = (
                f"{outbox.queued} bytes of topic data queued and {outbox.budget - room} bytes "
                f"waiting to be sent spent the connection's budget of {outbox.budget} bytes "
                "(max_queued_bytes), and the subscription is reliable; read faster, or "
                "subscribe with best_effort to drop the oldest instead, or give the server a "
                "larger max_queued_bytes"
            )
        return ResourceExhausted(
            f"the subscriber to {self.topic.name} did not keep up: {why}",
            {"depth": self.qos.depth, "seq": seq, "max_queued_bytes": outbox.budget},
            service=self.topic.name,
        )

    def __repr__(self) -> str:
        return f"<Subscription {self.id!r} to {self.topic.name}, {len(self.queue)} queued>"


class Outbox:
    """What one connection has to write: control messages first, then topic data round-robin.

    ``wake`` is called when the outbox goes from empty to not empty; the writer of the
    connection then takes :meth:`next` until it returns None (which resets :attr:`woken`),
    sending each, and waits for the next ``wake``. ``budget`` is the connection's budget of
    bytes (the server's ``max_queued_bytes``; 4 MiB, its default, when not given),
    ``buffered`` says how many of them its transport holds now, and ``writable`` whether its
    transport takes more now (is not congested; an outbox no writer drains never is), which
    decides whether ``depth`` bounds a subscription's queue (see the module).
    """

    __slots__ = (
        "budget",
        "buffered",
        "control",
        "queued",
        "ready",
        "subscriptions",
        "wake",
        "woken",
        "writable",
    )

    def __init__(
        self,
        wake: Callable[[], object] = lambda: None,
        budget: int = 4 * 2**20,
        buffered: Callable[[], int] = lambda: 0,
        writable: Callable[[], bool] = lambda: False,
    ) -> None:
        self.wake = wake
        self.budget = budget
        self.buffered = buffered
        self.writable = writable
        self.control: deque[bytes] = deque()
        self.ready: deque[Subscription] = deque()
        self.queued = 0  # bytes of topic data in the subscriptions' queues
        self.subscriptions: dict[Id, Subscription] = {}
        self.woken = False  # True from the first new message until the writer finds none

    def push(self, data: bytes) -> None:
        """Queue a control message; it goes out before any topic data."""
        self.control.append(data)
        if not self.woken:
            self.woken = True
            self.wake()

    def next(self) -> bytes | None:
        """The next message to send, or None when there is nothing."""
        if self.control:
            return self.control.popleft()
        ready = self.ready
        if not ready:
            self.woken = False
            return None
        subscription = ready.popleft()
        seq, data = subscription.queue.popleft()
        self.queued -= len(data)
        dropped = subscription.dropped
        subscription.dropped = 0
        if subscription.queue:
            ready.append(subscription)
        else:
            subscription.ready = False
        return b"".join(
            (
                subscription.prefix,
                str(seq).encode(),
                b',"dropped":',
                str(dropped).encode(),
                b',"message":',
                data,
                b"}}",
            )
        )

    def fit(self) -> None:
        """Give up topic data until it fits in what the transport leaves of the budget (called
        once a reply was queued): best effort's oldest messages first, in turn order, then
        reliable subscriptions, ended with ``RESOURCE_EXHAUSTED`` (see the module). As
        :meth:`offer` lets one message into an empty outbox whatever its size, one message
        queued alone is never given up here."""
        room = self.budget - self.buffered()
        if self.queued <= room:
            return
        left = sum(len(subscription.queue) for subscription in self.ready)
        if left <= 1:
            return
        for subscription in tuple(self.ready):
            if not subscription.qos.best_effort:
                continue
            queue = subscription.queue
            while queue and self.queued > room and left > 1:
                _, old = queue.popleft()
                self.queued -= len(old)
                subscription.dropped += 1
                left -= 1
            if not queue:
                subscription.ready = False
                self.ready.remove(subscription)
            if self.queued <= room or left <= 1:
                return
        for subscription in tuple(self.ready):
            seq = subscription.queue[-1][0]
            left -= len(subscription.queue)
            self.end(subscription, subscription.exhausted(seq, room))
            if self.queued <= room or left <= 1:
                return

    def subscribe(self, id: Id, topic: Topic[Any], qos: QoS) -> Subscription:
        """Start a subscription: ``$/subscribed`` now, then the topic's history if it keeps
        any and ``qos`` asks for it, then every new publication."""
        subscription = Subscription(id, topic, qos, self)
        self.subscriptions[id] = subscription
        topic.subscriptions.add(subscription)
        granted = {
            "subscription": id,
            "topic": topic.name,
            "seq": topic.seq,
            "epoch": topic.epoch,
            **qos.to_json(),
        }
        self.push(Notification(SUBSCRIBED_METHOD, granted).serialize())
        if qos.durability == "transient_local":
            history = list(topic.history)[-qos.depth :]
            for seq, data in history:
                subscription.offer(seq, data)
        return subscription

    def end(self, subscription: Subscription, error: RPCError | None) -> bool:
        """End ``subscription``, answering ``error`` (None: silently, the connection is gone).

        Return whether it was still running.
        """
        if self.subscriptions.get(subscription.id) is not subscription:
            return False
        del self.subscriptions[subscription.id]
        subscription.topic.subscriptions.discard(subscription)
        if subscription.timer is not None:
            subscription.timer.cancel()
            subscription.timer = None
        for _, data in subscription.queue:
            self.queued -= len(data)
        subscription.queue.clear()
        if subscription.ready:
            subscription.ready = False
            self.ready.remove(subscription)
        if error is not None:
            self.push(ErrorResponse(subscription.id, error).serialize())
        return True

    def cancel(self, id: Id) -> bool:
        """``$/cancel`` of the subscription ``id``: end it with ``CANCELLED``; say if it ran."""
        subscription = self.subscriptions.get(id)
        if subscription is None:
            return False
        return self.end(subscription, Cancelled("the subscriber cancelled the subscription"))

    def expire(self, subscription: Subscription, timeout: float) -> bool:
        """The subscription's ``_meta.timeout`` (``timeout`` seconds) passed: end it with
        ``DEADLINE_EXCEEDED``; say if it ran."""
        subscription.timer = None
        return self.end(
            subscription,
            DeadlineExceeded(
                f"the subscription to {subscription.topic.name} reached its deadline "
                f"({timeout:g} s)",
                {"timeout": timeout},
                service=subscription.topic.name,
            ),
        )

    def close(self) -> None:
        """The connection is gone: end every subscription silently and drop what is queued.

        Every subscription leaves its topic even if ending one of them fails; the first
        failure is raised once all are ended.
        """
        for subscription in self.ready:  # emptied at once, not one subscription at a time
            subscription.ready = False
        self.ready.clear()
        failure: Exception | None = None
        for subscription in list(self.subscriptions.values()):
            try:
                self.end(subscription, None)
            except Exception as exc:  # the others still leave their topics
                failure = failure or exc
        self.control.clear()
        if failure is not None:
            raise failure


class TopicBoard(Generic[T]):
    """The topics one server offers, by canonical name; what ``$/subscribe`` reads."""

    def __init__(self) -> None:
        self._topics: dict[str, Topic[T]] = {}
        self.announced = False  # once it had a topic, $/topics says when it has none

    def add(self, topic: Topic[T]) -> Topic[T]:
        """Declare ``topic``; raise ValueError when its name is taken."""
        existing = self._topics.get(topic.name)
        if existing is not None:
            raise ValueError(f"a topic named {topic.name} is already declared")
        self._topics[topic.name] = topic
        self.announced = True
        return topic

    def remove(self, name: str) -> Topic[T]:
        """Remove the topic ``name``; end its subscriptions with a reply that says so.

        Raise KeyError when there is none.
        """
        topic = self._topics.pop(name)
        for subscription in list(topic.subscriptions):
            subscription.outbox.end(
                subscription, ServiceNotFound(f"the topic {name} was removed", service=name)
            )
        return topic

    def get(self, name: str) -> Topic[T] | None:
        topic = self._topics.get(name)
        if topic is None and not name.startswith("/"):
            topic = self._topics.get("/" + name)
        return topic

    def __iter__(self) -> Iterator[Topic[T]]:
        return iter(sorted(self._topics.values(), key=lambda t: t.name))

    def __len__(self) -> int:
        return len(self._topics)

    def visible(self, scopes: frozenset[str] | None) -> Iterator[Topic[T]]:
        """The topics a connection holding ``scopes`` may use (None: every topic)."""
        for topic in self:
            if scopes is None or topic.scopes <= scopes:
                yield topic

    def announcement(self, scopes: frozenset[str]) -> bytes | None:
        """The ``$/topics`` notification for a connection holding ``scopes``; None for a
        server that has no topics (and never had any)."""
        if not (self._topics or self.announced):
            return None
        return topics_notification(self.visible(scopes))

    def find(self, name: Any, scopes: frozenset[str], publish: bool = False) -> Topic[T]:
        """The topic ``name`` (a ``$/subscribe``/``$/publish`` param) for a connection holding
        ``scopes``; raise the error to answer."""
        if not isinstance(name, str):
            raise _qos_error("topic", "expected the topic's name, a string")
        topic = self.get(name)
        if topic is None:
            names = ", ".join(t.name for t in self.visible(scopes)) or "none"
            raise ServiceNotFound(f"no topic named {name} (topics: {names})", service=name)
        if not topic.scopes <= scopes:
            missing = sorted(topic.scopes - scopes)
            raise PermissionDenied(
                f"permission denied: {topic.name} needs the "
                f"{'scope' if len(missing) == 1 else 'scopes'} {', '.join(missing)}, "
                "which this connection's identity does not hold",
                {"missing_scopes": missing},
                service=topic.name,
            )
        if publish and not topic.accepts:
            raise PermissionDenied(
                f"the server does not take messages on {topic.name}; only subscribe to it",
                service=topic.name,
            )
        return topic

    def subscribe(
        self, outbox: Outbox, id: Id, params: Any, scopes: frozenset[str]
    ) -> Subscription | bytes:
        """Admit a ``$/subscribe`` request ``id``: the subscription, or the error reply."""
        if type(params) is not dict:
            error: RPCError = _qos_error("topic", "expected params {'topic': name}")
            return ErrorResponse(id, error).serialize()
        try:
            topic = self.find(params.get("topic"), scopes)
            qos = topic.qos.grant(params.get("qos"))
        except RPCError as exc:
            return ErrorResponse(id, exc).serialize()
        if id in outbox.subscriptions:
            duplicate = InvalidParams(f"id {id!r} is already a subscription on this connection")
            return ErrorResponse(id, duplicate).serialize()
        return outbox.subscribe(id, topic, qos)


class Gaps:
    """A subscriber's account of the sequence numbers it saw, across reconnections.

    :meth:`accept` says whether a message is new (a resumed transient-local subscription
    replays some it saw already) and counts in :attr:`missed` every message it did not get:
    what the server dropped (best effort) and what was published while it was not subscribed.
    A topic whose epoch changed, or, from a server that sends none, whose numbers went back
    (its server restarted) cannot be compared: counting starts again, and :attr:`restarts`
    says so.
    """

    __slots__ = ("epoch", "last", "missed", "restarts", "resumed")

    def __init__(self) -> None:
        self.last: int | None = None  # the last sequence number accepted
        self.epoch: str | None = None  # the topic's, as the last $/subscribed said it
        self.missed = 0
        self.resumed = 0
        self.restarts = 0

    def subscribed(self, seq: int, epoch: str | None = None) -> None:
        """A ``$/subscribed`` said the topic's last sequence number is ``seq``, in ``epoch``
        (None: a server that does not say)."""
        last = self.last
        if last is not None:
            self.resumed += 1
            other = epoch is not None and self.epoch is not None and epoch != self.epoch
            if other or seq < last:
                self.restarts += 1
                self.last = None
        self.epoch = epoch

    def accept(self, seq: int, dropped: int) -> int | None:
        """Account for message ``seq``; return how many were missed just before it, or None
        when it is one seen already."""
        last = self.last
        if last is None:
            missed = dropped
        elif seq <= last:
            return None
        else:
            missed = seq - last - 1
        self.last = seq
        self.missed += missed
        return missed


def topics_notification(topics: Iterable[Topic[Any]]) -> bytes:
    """The ``$/topics`` announcement: every topic a connection may use, by name."""
    return Notification(TOPICS_METHOD, {"topics": [t.describe() for t in topics]}).serialize()


def publish_ack(id: Id) -> bytes:
    """The reply to an acknowledged ``$/publish``."""
    return Response(id, None).serialize()
