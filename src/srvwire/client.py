"""The asyncio client: call services over one connection, with deadlines and typed errors.

:func:`connect` holds the options, once, and opens a :class:`Client` (awaited, with
``async with``, or with ``async for`` to reconnect). A client is made of smaller objects:

* the current :class:`~srvwire.link.Link`, one per open connection: the transport's
  connection, the :class:`~srvwire.session.ClientSession` that numbers requests and routes
  replies, and its reader (the transport's read callback, where the transport hands messages
  over; else a task);
* its :class:`~srvwire.calls.ServiceTypes`: the type of each service, from ``srv_type``, or
  by the advertised name from the local search path, else from the server's description
  (``rpc.discover``), and its decoder;
* the supervisor that re-dials with backoff when ``reconnect=True``;
* the call itself (:meth:`Client.call`): encode once, send and wait under one deadline, decode
  in the caller's task.

Invariants:

* **Every call ends.** Every call has a finite deadline (the client's ``timeout`` unless the
  call gives its own), fixed in loop time when the call starts; ``asyncio.wait_for`` enforces
  it, and waiting for the connection or the service (``wait_for_ready``) spends from it. The
  time left travels to the server as ``params._meta.timeout``.
* **Waiting is event-driven.** ``wait_for_service`` and ``wait_for_ready`` sleep on an event
  pulsed when ``$/services`` arrives or the connection comes or goes; nothing polls.
* **Reconnection is opt-in.** A call in flight when the connection drops is never retried: it
  may have run. ``close()`` always closes the connection it owns, whatever the supervisor was
  doing.
* **Options and payload never share a namespace.** A request is one positional value (a model
  or a mapping), so every field name is free; :class:`ServiceProxy` takes fields as keywords
  and holds its options itself.
* **A client belongs to the event loop that opened it.** When that loop ends, the connection
  is closed with 1001; used from another loop, the client raises ``RuntimeError`` saying so.
  Blocking code uses :mod:`srvwire.sync`, which runs a client on a loop of its own.
* **Always typed.** Every advertised service has a type: the local one, else the one the
  server describes. A mapping is validated locally (:class:`~srvwire.errors.InvalidParams`
  before anything is sent) and the result is the typed ``Response``. A type found in neither
  place is an :class:`~srvwire.errors.InterfaceError`, never plain dicts. Only a service the
  server does not advertise is called with the mapping as it is (and a srvwire server answers
  ``ServiceNotFound``).
  For a type checker too: :meth:`Client.call` with a generated
  ``Request`` (a :class:`~srvwire.models.ServiceRequest`), or with a
  :class:`~srvwire.models.TypedService` as ``srv_type``, returns that service's ``Response``,
  and so does a :class:`ServiceProxy` made with one.
"""

from __future__ import annotations

import asyncio
import functools
import ipaddress
import logging
import os
import random
import ssl as _ssl
import urllib.parse
from collections import deque
from collections.abc import AsyncIterator, Coroutine, Generator, Iterable, Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType, TracebackType
from typing import Any, Generic, NoReturn, TypeAlias, TypeVar, overload

from pydantic import BaseModel, ValidationError

from srvwire.actions import ClientGoal, goal_service, reply_done
from srvwire.calls import (
    MessageResolver,
    ServiceCodec,
    ServiceInfo,
    ServiceTypes,
    SrvType,
    TypeResolver,
    check_timeout,
    encode_message,
    encode_request,
    remote_message,
    typed_by_request,
)
from srvwire.dispatch import service_not_found
from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    InterfaceNotFoundError,
    InternalError,
    PermissionDenied,
    ResourceExhausted,
    RPCError,
    ServiceNotFound,
    ServiceUnavailable,
)
from srvwire.inline import Pending, finish_within, first_step
from srvwire.link import Arrived, Link, LoggerLike, foreign_loop
from srvwire.loader import SearchPath, load_action, load_message, load_service
from srvwire.models import (
    INF_NAN_MODES,
    Action,
    InfNan,
    Message,
    ModelDecoder,
    Service,
    ServiceRequest,
    TypedService,
    error_data,
    summarize_errors,
)
from srvwire.protocol import (
    DISCOVER_METHOD,
    PUBLISH_METHOD,
    SUBSCRIBE_METHOD,
    Notification,
    ProtocolViolation,
    RawJSON,
    canonical_name,
    encode_json,
)
from srvwire.session import Subscribed, TopicMessage
from srvwire.topics import Gaps
from srvwire.transports import get_transport
from srvwire.transports.base import Headers, Options, Transport, TransportClosed

__all__ = [
    "DEFAULT_TIMEOUT",
    "DEFAULT_URL",
    "Client",
    "ServiceInfo",
    "ServiceProxy",
    "Subscription",
    "TopicInfo",
    "connect",
]

DEFAULT_URL = "ws://localhost:8765"
"""Where :func:`connect` goes when no URL is given."""

DEFAULT_TIMEOUT = 10.0
"""The deadline, in seconds, of a call that does not give its own."""

R = TypeVar("R", bound=Message)

Ready: TypeAlias = tuple[str, ServiceCodec | None]
"""What a call needs before it is written: its service's canonical name, and its type (None:
a service not advertised, whose request is sent as it is)."""

# Reconnection backoff: first retry at once, then from this delay, growing to the cap.
_BACKOFF_INITIAL = 0.05
_BACKOFF_FACTOR = 2.0
_BACKOFF_MAX = 5.0


def _backoff() -> Iterator[float]:
    """Yield reconnection delays: 0, then exponential growth to a cap, with jitter."""
    yield 0.0
    delay = _BACKOFF_INITIAL
    while True:
        yield delay * random.uniform(0.8, 1.2)
        delay = min(delay * _BACKOFF_FACTOR, _BACKOFF_MAX)


class Client:
    """A connection to one srvwire server, and the calls made over it.

    Made by :func:`connect`, which holds the options and describes them:
    ``async with connect(url) as client:``, or ``client = await connect(url)`` followed by
    ``await client.close()``. A client belongs to the event loop it was opened in.
    """

    def __init__(self, options: connect) -> None:
        self.options = options
        self.url = options.url
        self.timeout = options.timeout
        self.logger: LoggerLike = options._log()
        self._types = ServiceTypes(
            options.type_resolver,
            options.message_resolver,
            inf_nan=options.inf_nan,
            max_values=options.transport_options.max_message_size,
        )
        self._description: tuple[Link, dict[str, dict[str, str]]] | None = None
        self._describing = asyncio.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None  # the loop it was opened in
        self._link: Link | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._services: dict[str, str] = {}
        self._topics: dict[str, dict[str, Any]] = {}
        self._message_types: dict[str, type[BaseModel]] = {}
        self._subscriptions: set[Subscription] = set()
        self._changed = asyncio.Event()
        self._background: set[asyncio.Task[None]] = set()
        self._opened = False
        self._closed = False

    def __repr__(self) -> str:
        state = "closed" if self._closed else "connected" if self._link else "not connected"
        return f"<Client {state} to {self.url}>"

    # --- opening and closing --------------------------------------------------------------

    async def open(self) -> Client:
        """Open the connection; with ``reconnect=True`` a failed first dial is retried later.

        The first dial is made here either way, so it returns within ``open_timeout``.

        Raise :class:`~srvwire.errors.ServiceUnavailable` when the server cannot be reached
        (only with ``reconnect=False``). Opening twice is an error.
        """
        if self._opened:
            raise RuntimeError("this client was already opened")
        self._opened = True
        self._loop = asyncio.get_running_loop()
        if not self.options.reconnect:
            await self._dial()
            return self
        try:
            await self._dial()
        except ServiceUnavailable as exc:
            self.logger.info("%s; will keep trying in the background", exc.message)
        self._supervisor = self._loop.create_task(self._supervise())
        return self

    async def close(self) -> None:
        """Close the connection; calls still pending fail with ``ConnectionLost``.

        They fail first, then the closing handshake is awaited: at most the transport's close
        timeout (10 s) for a peer that does not answer. Idempotent. After it, every call fails
        with ``ConnectionLost``.
        """
        if self._closed:
            return
        self._closed = True
        # Take the link before stopping the supervisor: nothing that happens to the
        # supervisor may make this client forget a connection it still has to close.
        link = self._link
        for subscription in list(self._subscriptions):
            subscription._detach()  # ends with the connection: nothing to tell the server
        if self._supervisor is not None:
            self._supervisor.cancel()
            await asyncio.gather(self._supervisor, return_exceptions=True)
        if link is not None:
            # Fail what waits on it first: the closing handshake may wait for a peer that
            # does not answer, up to the transport's close timeout.
            link.lost(None, None)
            await link.conn.close()
            if link.reader is not None:
                await asyncio.gather(link.reader, return_exceptions=True)
        if self._background:
            await asyncio.gather(*self._background, return_exceptions=True)
        self._pulse()

    async def __aenter__(self) -> Client:
        if not self._opened:
            await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        """Whether a connection is open right now (and its services are known)."""
        return self._link is not None

    @property
    def in_flight(self) -> int:
        """How many calls are waiting for a reply."""
        return 0 if self._link is None else len(self._link.session.pending)

    @property
    def services(self) -> Mapping[str, str]:
        """The services the server advertised: canonical name -> type (``pkg/srv/Name``).

        A read-only snapshot of the latest ``$/services``, in the server's order; empty while
        not connected. No round trip: :meth:`list_services` asks the server instead.
        """
        return MappingProxyType(self._services)  # a snapshot: the dict is replaced, not mutated

    async def _dial(self) -> None:
        """Open a connection and read the server's ``$/services``; start its reader."""
        options = self.options
        link, services = await Link.open(
            self,
            options.transport,
            options.transport_options,
            open_timeout=options.open_timeout,
            headers=options.headers,
            ssl=options.ssl,
        )
        if self._closed:  # close() ran while this dial was under way
            await link.conn.close()
            raise ConnectionLost("the client is closed", {"url": self.url})
        self._services = services
        self._link = link
        link.start()
        self.logger.debug("connected to %s, %d services", self.url, len(services))
        self._pulse()
        for subscription in list(self._subscriptions):
            if subscription._resuming:
                self.spawn(subscription._resume())

    async def _supervise(self) -> None:
        """Keep a connection open: re-dial with backoff whenever there is none."""
        while True:
            link = self._link
            if link is not None and link.reader is not None:
                # asyncio.wait, not gather: cancelling the supervisor must not cancel the
                # reader, which belongs to the connection and ends only when it does.
                await asyncio.wait({link.reader})
            for delay in _backoff():
                if delay:
                    await asyncio.sleep(delay)
                try:
                    await self._dial()
                except ServiceUnavailable as exc:
                    self.logger.debug("%s; retrying", exc.message)
                else:
                    break

    # --- what the link tells -----------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    def services_changed(self, link: Link, services: dict[str, str]) -> None:
        """The server sent ``$/services``: replace the advertised services, wake the waiters.

        A link that is no longer the current one (failed, and closing) is not news.
        """
        if self._link is link:
            self._services = services
            self._description = None
            self._pulse()

    def topics_changed(self, link: Link, topics: dict[str, dict[str, Any]]) -> None:
        """The server sent ``$/topics``: replace the topics, wake the waiters."""
        if self._link is link:
            self._topics = topics
            self._description = None
            self._pulse()

    def forget(self, link: Link) -> bool:
        """``link`` ended: forget it if it is the current one (and say so)."""
        if self._link is not link:
            return False
        self._link = None
        self._services = {}
        self._topics = {}
        self._pulse()
        return True

    def spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        """Run ``coro`` in the background; :meth:`close` waits for it."""
        task = asyncio.get_running_loop().create_task(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _pulse(self) -> None:
        """Wake every task waiting for a change in the connection or the services."""
        self._changed.set()
        self._changed.clear()

    # --- calls ------------------------------------------------------------------------------

    @overload
    async def call(
        self,
        name: str,
        request: ServiceRequest[R],
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> R: ...

    @overload
    async def call(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109
        srv_type: type[TypedService[Any, R]],
        wait_for_ready: bool = False,
    ) -> R: ...

    @overload
    async def call(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> Any: ...

    async def call(
        self,
        name: str,
        request: Any = None,  # the overloads say what it may be
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
        srv_type: SrvType | None = None,
        wait_for_ready: bool = False,
    ) -> Any:
        """Call the service ``name`` with ``request`` and return its response.

        ``request`` is a ``Request`` model or a mapping of its fields (left out: every field
        takes its default). The result is the typed ``Response`` of the service's type:
        ``srv_type``, or the type the server advertised, found as :func:`connect` says (local
        first, then the server's description). A ``Request`` of a class of that type other
        than the one found (a generated module's) types the call by its own service, as
        ``srv_type=`` that service would; one of another type is a ``TypeError`` naming both.
        For fields as keywords, use :meth:`proxy`. Statically, a generated ``Request`` or a
        generated service class as ``srv_type`` makes the result that service's ``Response``;
        otherwise it is ``Any``.

        ``timeout`` (seconds) overrides the client's default deadline. ``wait_for_ready=True``
        first waits, within that deadline, for the connection and for the service to be
        advertised; it raises :class:`~srvwire.errors.ServiceUnavailable` if they are not
        there in time, and nothing was sent.

        Raise the :class:`~srvwire.errors.RPCError` subclass that matches the failure:
        ``DeadlineExceeded``, ``ConnectionLost``, ``InvalidParams`` (also locally, before
        sending), ``ServiceNotFound``, ``InternalError``, ``ServiceError``, and so on; and
        :class:`~srvwire.errors.InterfaceError` when the type can be found neither locally nor
        from the server (:class:`~srvwire.errors.InterfaceConflictError` when the two differ).
        """
        budget = self.timeout if timeout is None else check_timeout(timeout)
        # The client's own loop, not asyncio.get_running_loop(): on Python 3.11 that asks the
        # kernel for the process id on every call, to notice a fork.
        deadline = (self._loop or asyncio.get_running_loop()).time() + budget
        link = self._link
        ready: Ready | None = None
        if link is not None and not wait_for_ready:
            ready = link.ready.get(name if srv_type is None else (name, srv_type))
        if link is None or ready is None:
            link, ready = await self._prepare(name, srv_type, wait_for_ready, deadline, budget)
        method, codec = ready
        params: str | bytes | None = None
        if codec is not None and type(request) is codec.request:  # the common case
            params = codec.params(request)
        elif codec is not None and srv_type is None:
            typed_by = typed_by_request(method, codec, request)
            if typed_by is not None:  # a Request of its own class: typed as srv_type=its service
                ready = link.ready.get((name, typed_by))
                if ready is None:
                    link, ready = await self._prepare(name, typed_by, False, deadline, budget)
                method, codec = ready
        if params is None:
            params = encode_request(method, codec, request)
        reply = await link.roundtrip(method, params, deadline, budget)
        try:
            return reply.decode(None if codec is None else codec.decoder)
        except (RPCError, ProtocolViolation) as exc:
            raise link.failure(method, exc) from None
        except ValidationError as exc:
            assert codec is not None
            data = error_data(exc)
            raise InternalError(
                f"the response does not match {codec.service.type_name}: "
                f"{summarize_errors(data['errors'], exc.error_count())}",
                data,
                service=method,
            ) from None

    async def _prepare(
        self,
        name: str,
        srv_type: SrvType | None,
        wait_for_ready: bool,
        deadline: float,
        budget: float,
    ) -> tuple[Link, Ready]:
        """What a call of ``name`` needs before it is written: the link to send it on, its
        canonical name and its type (None: not advertised, sent as it is).

        Waits for the connection and the service with ``wait_for_ready``; finds the type and
        compares it with the server's, once per connection (again after ``$/services``), and
        keeps the outcome in the link's :attr:`~srvwire.link.Link.ready` for the next call.
        """
        method = canonical_name(name)
        if wait_for_ready:
            await self._wait_until_ready(method, deadline, budget)
        link = self._link
        if link is None:
            raise self._not_connected(method)
        generation = link.ready  # a $/services while this waits replaces it
        advertised = self._services.get(method)
        codec = self._types.known(srv_type, advertised)
        if codec is None:
            named = srv_type if isinstance(srv_type, str) else advertised
            if named is not None:  # not advertised: the server will say it has no such service
                try:
                    codec = await self._type_of(link, method, named, deadline, budget)
                except RPCError as exc:  # asking for the description failed: this call did
                    exc.service = method
                    raise
        if codec is None:
            return link, (method, None)
        if (method, codec.service) not in link.verified:
            await self._verify(link, method, codec, advertised, deadline, budget)
        if link.ready is generation:  # not when $/services came while this looked or compared
            link.remember(name if srv_type is None else (name, srv_type), (method, codec))
        return link, (method, codec)

    async def send_goal(
        self,
        name: str,
        goal: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
        action_type: type[Action] | str | None = None,
    ) -> ClientGoal[Any]:
        """Send ``goal`` to the action ``name``; return its handle once the server accepted it.

        ``goal`` is a ``Goal`` model or a mapping of its fields. ``timeout`` (default: the
        client's) is the deadline of the whole goal, until its outcome. The action's type is
        ``action_type``, or the one the server advertised, found as :meth:`call` finds a
        service's. Then ``async for fb in handle.feedback()``, ``await handle.result()``,
        ``await handle.cancel()``, ``handle.status``.

        Before the first goal of the action on a connection, the action class is compared with
        the server's by the fingerprint ``$/services`` announced, as :meth:`call` compares a
        service's (:class:`~srvwire.errors.InterfaceConflictError` when they differ).

        Raise :class:`~srvwire.errors.GoalRejected` with the server's reason when it refused
        the goal, and the errors :meth:`call` raises.
        """
        method = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + budget
        link = self._link
        if link is None:
            raise self._not_connected(method)
        named = action_type if action_type is not None else self._services.get(method)
        if named is None:
            raise service_not_found(method, self._services)
        action = await self._action_of(link, method, named, deadline, budget)
        service = goal_service(action)
        codec = ServiceCodec(service, self.options.inf_nan)
        if (method, service) not in link.verified:
            await self._verify(link, method, codec, self._services.get(method), deadline, budget)
        params = encode_request(method, codec, goal)
        remaining = deadline - loop.time()
        handle: ClientGoal[Any] = ClientGoal(
            link, method, action, ModelDecoder(service.Response), deadline, budget
        )
        handle.id, data = link.session.request(method, params, round(remaining, 6), handle.reply)
        if link.limit is not None and len(data) > link.limit:
            link.session.pending.pop(handle.id, None)
            raise link.too_large(method, len(data))
        link.goals[handle.id] = handle
        handle.reply.add_done_callback(reply_done(link.goals, handle.id))
        try:
            sending = first_step(link.conn.send(data))
            if isinstance(sending, Pending):
                await finish_within(sending, deadline - loop.time())
            await handle.accepted()
        except TimeoutError:
            handle.give_up()
            raise DeadlineExceeded(
                f"no response within {budget:g} s", {"timeout": budget}, service=method
            ) from None
        except asyncio.CancelledError:
            handle.give_up()
            raise
        except TransportClosed as exc:
            closed = {"close_code": exc.code, "close_reason": exc.reason, "url": self.url}
            raise ConnectionLost(str(exc), closed, service=method) from exc
        return handle

    async def _action_of(
        self, link: Link, method: str, named: type[Action] | str, deadline: float, budget: float
    ) -> type[Action]:
        """The action type ``named``: the class given, the local search path, or the
        server's description."""
        if not isinstance(named, str):
            return named
        try:
            return load_action(named, search_path=self.options.search_path)
        except InterfaceNotFoundError:
            pass
        described = self._description
        if described is None or described[0] is not link:
            try:
                async with asyncio.timeout_at(deadline):
                    methods = await self._methods(link, deadline, budget)
            except TimeoutError:
                raise DeadlineExceeded(
                    f"no response within {budget:g} s", {"timeout": budget}, service=method
                ) from None
            except (ServiceNotFound, InternalError):
                methods = []
            described = self._description = (link, _described(methods))
        source = f"server {self.url}"
        return self._types.remote_action(method, named, described[1].get(method), source)

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

        ``await client.proxy("/add_two_ints")(a=1, b=2)``; the options given here apply to
        every call made through it. With a generated service class as ``srv_type``, a type
        checker knows its calls return that service's ``Response``.
        """
        return ServiceProxy(self, name, srv_type, timeout=timeout, wait_for_ready=wait_for_ready)

    async def wait_for_service(
        self,
        name: str,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - gives up with ServiceUnavailable
    ) -> ServiceInfo:
        """Wait until the server advertises ``name``; return its name and type.

        Woken by ``$/services`` (no polling). With ``reconnect=True`` it also waits for the
        connection to come (back). Raise :class:`~srvwire.errors.ServiceUnavailable` when
        ``timeout`` (default: the client's) passes first, and ``ConnectionLost`` at once when
        the connection is down for good.
        """
        method = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        await self._wait_until_ready(method, deadline, budget)
        return ServiceInfo(method, self._services[method])

    async def list_services(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> list[ServiceInfo]:
        """Ask the server for every service it offers (``rpc.discover``), sorted by name."""
        return await self._listed("service", timeout)

    async def list_actions(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> list[ServiceInfo]:
        """Ask the server for every action it offers (``rpc.discover``), sorted by name."""
        return await self._listed("action", timeout)

    async def _listed(
        self,
        kind: str,
        timeout: float | None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> list[ServiceInfo]:
        """What ``rpc.discover`` lists of ``kind`` (an entry without ``x-srvwire-kind`` is a
        service), by name."""
        found = [
            ServiceInfo(canonical_name(entry["name"]), entry["x-srvwire-type"])
            for entry in await self._discover(timeout)
            if isinstance(entry, dict)
            and isinstance(entry.get("name"), str)
            and isinstance(entry.get("x-srvwire-type"), str)
            and entry.get("x-srvwire-kind", "service") == kind
        ]
        return sorted(found, key=lambda info: info.name)

    async def definitions(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> dict[str, str]:
        """Ask the server for the definition text of every type it serves, by full name.

        The services' types and every message they nest (``rpc.discover``'s
        ``x-srvwire-definitions``), sorted by name: what ``srvwire service describe`` prints.
        """
        texts: dict[str, str] = {}
        for entry in await self._discover(timeout):
            texts.update(_definitions_of(entry))
        return dict(sorted(texts.items()))

    async def service_type(
        self,
        name: str,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> type[Service]:
        """Return the class of the service ``name``'s type, as :meth:`call` finds it.

        From the local search path first, else built from the server's description (see
        :func:`connect`). Raise :class:`~srvwire.errors.ServiceNotFound` when the server does
        not advertise ``name``, and :class:`~srvwire.errors.InterfaceError` when the type can
        be found in neither place.
        """
        method = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        link = self._link
        if link is None:
            raise self._not_connected(method)
        advertised = self._services.get(method)
        if advertised is None:
            raise service_not_found(method, self._services)
        codec = self._types.known(None, advertised) or await self._type_of(
            link, method, advertised, deadline, budget
        )
        return codec.service

    async def _discover(self, timeout: float | None) -> list[Any]:  # noqa: ASYNC109
        """Ask for ``rpc.discover`` and return its ``methods``."""
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        link = self._link
        if link is None:
            raise self._not_connected(DISCOVER_METHOD)
        return await self._methods(link, deadline, budget)

    async def _methods(self, link: Link, deadline: float, budget: float) -> list[Any]:
        reply = await link.roundtrip(DISCOVER_METHOD, None, deadline, budget)
        try:
            document = reply.decode()
        except (RPCError, ProtocolViolation) as exc:
            raise link.failure(DISCOVER_METHOD, exc) from None
        methods = document.get("methods") if isinstance(document, dict) else None
        if not isinstance(methods, list):
            raise InternalError(
                "rpc.discover did not return an OpenRPC document with 'methods'",
                service=DISCOVER_METHOD,
            )
        return methods

    async def _type_of(
        self, link: Link, method: str, name: str, deadline: float, budget: float
    ) -> ServiceCodec:
        """Find the type ``name`` of ``method``: locally, else from the server's description.

        The description is asked for once per connection (again after ``$/services`` says the
        services changed), and only when a type is not on the local search path.
        """
        codec = self._types.local(name)
        if codec is not None:
            return codec
        try:  # one caller asks; those who need it meanwhile wait for that answer
            async with asyncio.timeout_at(deadline):
                await self._describing.acquire()
        except TimeoutError:
            raise DeadlineExceeded(
                f"no response within {budget:g} s", {"timeout": budget}, service=method
            ) from None
        try:
            codec = self._types.known(name, None)
            if codec is not None:  # built by the caller this one waited for
                return codec
            described = self._description
            if described is None or described[0] is not link:
                try:
                    methods = await self._methods(link, deadline, budget)
                except (ServiceNotFound, InternalError):  # a server that does not describe types
                    methods = []
                described = self._description = (link, _described(methods))
            source = f"server {self.url}"
            return self._types.remote(method, name, described[1].get(method), source)
        finally:
            self._describing.release()

    async def _verify(
        self,
        link: Link,
        method: str,
        codec: ServiceCodec,
        advertised: str | None,
        deadline: float,
        budget: float,
    ) -> None:
        """Compare the type a call of ``method`` uses with the server's, once per connection
        (again after ``$/services`` changes), by the fingerprint ``$/services`` announced.

        Equal, or not announced (an older server, a class written by hand), the call goes
        on. Different: raise :class:`~srvwire.errors.InterfaceConflictError` naming the
        local file and the server, and the first declaration that differs, read from the
        server's description (asked for only then).
        """
        service = codec.service
        theirs = link.fingerprints.get(method)
        if theirs is not None and service.type_name == advertised:
            ours = self._types.fingerprint(service)
            if ours is not None and ours != theirs:
                try:
                    methods = await self._methods(link, deadline, budget)
                except RPCError:
                    methods = []
                definitions = _described(methods).get(method)
                raise self._types.conflict(service, definitions, f"server {self.url}")
        link.verified.add((method, service))

    # --- topics -----------------------------------------------------------------------------

    @property
    def topics(self) -> Mapping[str, str]:
        """The topics the server announced (``$/topics``): canonical name -> message type.

        A read-only snapshot; empty while not connected, or for a server without topics.
        """
        return MappingProxyType({name: entry["type"] for name, entry in self._topics.items()})

    async def topic_type(
        self,
        name: str,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> type[BaseModel]:
        """Return the message class of the topic ``name``, as :meth:`subscribe` finds it."""
        topic = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        link = self._link
        if link is None:
            raise self._not_connected(topic)
        return await self._topic_type(link, topic, None, deadline, budget)

    async def list_topics(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> list[TopicInfo]:
        """Ask the server for every topic it offers (``rpc.discover``), sorted by name."""
        methods = await self._discover(timeout)
        found = [
            TopicInfo.of(
                canonical_name(entry["name"]),
                {
                    "type": entry.get("x-srvwire-type"),
                    "qos": entry.get("x-srvwire-qos"),
                    "publish": entry.get("x-srvwire-publish"),
                },
            )
            for entry in methods
            if isinstance(entry, dict)
            and entry.get("x-srvwire-kind") == "topic"
            and isinstance(entry.get("name"), str)
        ]
        return sorted(found, key=lambda info: info.name)

    def subscribe(
        self,
        name: str,
        msg_type: type[BaseModel] | str | None = None,
        *,
        qos: Mapping[str, Any] | None = None,
        timeout: float | None = None,
        duration: float | None = None,
    ) -> Subscription:
        """Subscribe to the topic ``name``: ``async for msg in client.subscribe(name):``.

        Messages are typed: ``msg_type`` (a class, or a type name), else the type the server
        announced, found as :func:`connect` says for calls (local first, then the server's
        description). ``qos`` asks for ``depth``, ``reliability`` and ``durability`` (default:
        the topic's); ``timeout`` bounds the subscribing (default: the client's timeout);
        ``duration`` is the subscription's deadline, sent as ``_meta.timeout``: when it passes,
        the server ends the subscription and iterating raises ``DeadlineExceeded`` (default:
        none, it runs until it is closed).

        Used with ``async for`` alone, leaving the loop ends the subscription; ``async with
        client.subscribe(name) as sub:`` holds it until the block ends, and ``async for msg in
        sub`` inside it may be left and taken up again. With ``reconnect=True`` a subscription
        resumes after the connection comes back, and counts the messages it missed
        (:attr:`Subscription.dropped`). Iterating raises the error that ended it:
        ``ServiceNotFound`` (no such topic, or it was removed), ``PermissionDenied``,
        ``ResourceExhausted`` (a reliable subscriber that did not keep up), ``DeadlineExceeded``
        (its ``duration`` passed), ``ConnectionLost``.
        """
        budget = self.timeout if timeout is None else check_timeout(timeout)
        lifetime = None if duration is None else check_timeout(duration, "duration")
        return Subscription(self, canonical_name(name), msg_type, qos, budget, lifetime)

    async def publish(
        self,
        name: str,
        message: BaseModel | Mapping[str, Any],
        /,
        *,
        msg_type: type[BaseModel] | str | None = None,
        ack: bool = False,
        timeout: float | None = None,  # noqa: ASYNC109 - the deadline travels to the server
    ) -> None:
        """Publish ``message`` on the topic ``name`` (a model, or a mapping of its fields).

        It is validated here first (:class:`~srvwire.errors.InvalidParams` with the fields'
        paths, before anything is sent) and sent as a notification, which returns once it is
        written. With ``ack=True`` it is a request: it returns once the server took the
        message, and raises what the server refused it with (``InvalidParams``,
        ``PermissionDenied``, ``ServiceNotFound``). A topic the server announced it takes no
        messages on (``$/topics``' ``publish: false``) raises ``PermissionDenied`` here, before
        sending, with or without ``ack``.
        """
        topic = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = (self._loop or asyncio.get_running_loop()).time() + budget
        link = self._link
        if link is None:
            raise self._not_connected(topic)
        if self._topics.get(topic, {}).get("publish") is False:
            raise PermissionDenied(
                f"the server does not take messages on {topic}; only subscribe to it",
                service=topic,
            )
        # What _topic_type does, without its coroutine level on every message published.
        cls = await self._find_topic_type(link, topic, msg_type, deadline, budget)
        if self._differs(topic, cls):
            await self._topic_conflict(link, topic, cls, deadline, budget)
        params = (
            '{"topic":'
            + encode_json(topic)
            + ',"message":'
            + encode_message(topic, cls, message)
            + "}"
        )
        if not ack:
            await self._send(link, topic, Notification(PUBLISH_METHOD, RawJSON(params)).serialize())
            return
        reply = await link.roundtrip(PUBLISH_METHOD, params, deadline, budget)
        try:
            reply.decode()
        except (RPCError, ProtocolViolation) as exc:
            raise link.failure(topic, exc) from None

    async def notify(
        self,
        name: str,
        request: BaseModel | Mapping[str, Any] | None = None,
        /,
        *,
        srv_type: SrvType | None = None,
    ) -> None:
        """Call the service ``name`` without waiting for an answer (a JSON-RPC notification).

        The request is typed and validated as :meth:`call` does it; nothing comes back, not
        even an error: the server logs what fails.
        """
        method = canonical_name(name)
        link = self._link
        if link is None:
            raise self._not_connected(method)
        advertised = self._services.get(method)
        codec = self._types.known(srv_type, advertised)
        if codec is None:
            named = srv_type if isinstance(srv_type, str) else advertised
            if named is not None:
                budget = self.timeout
                deadline = asyncio.get_running_loop().time() + budget
                codec = await self._type_of(link, method, named, deadline, budget)
        params = encode_request(method, codec, request)
        await self._send(link, method, Notification(method, RawJSON(params)).serialize())

    async def wait_for_topic(
        self,
        name: str,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - gives up with ServiceUnavailable
    ) -> TopicInfo:
        """Wait until the server announces the topic ``name``; return what it says of it.

        Woken by ``$/topics`` (no polling). Raise
        :class:`~srvwire.errors.ServiceUnavailable` when ``timeout`` (default: the client's)
        passes first, and ``ConnectionLost`` at once when the connection is down for good.
        """
        topic = canonical_name(name)
        budget = self.timeout if timeout is None else check_timeout(timeout)
        deadline = asyncio.get_running_loop().time() + budget
        while self._link is None or topic not in self._topics:
            if self._closed or (self._link is None and not self.options.reconnect):
                raise self._not_connected(topic)
            try:
                async with asyncio.timeout_at(deadline):
                    await self._changed.wait()
            except TimeoutError:
                if self._link is not None and topic in self._topics:
                    break
                raise ServiceUnavailable(
                    f"the topic was not announced within {budget:g} s",
                    {"url": self.url, "timeout": budget},
                    service=topic,
                ) from None
        return TopicInfo.of(topic, self._topics[topic])

    async def _send(self, link: Link, method: str, data: bytes) -> None:
        try:
            await link.conn.send(data)
        except TransportClosed as exc:
            closed = {"close_code": exc.code, "close_reason": exc.reason, "url": self.url}
            raise ConnectionLost(str(exc), closed, service=method) from exc

    async def _topic_type(
        self,
        link: Link,
        topic: str,
        msg_type: type[BaseModel] | str | None,
        deadline: float,
        budget: float,
    ) -> type[BaseModel]:
        """The message class of ``topic`` (see :meth:`_find_topic_type`), compared with the
        server's by the fingerprint ``$/topics`` announced, as :meth:`_verify` compares a
        service's: equal, or not announced, it is used; different, it is an
        :class:`~srvwire.errors.InterfaceConflictError` naming the first declaration that
        differs, read from the server's description (asked for only then)."""
        cls = await self._find_topic_type(link, topic, msg_type, deadline, budget)
        if self._differs(topic, cls):
            await self._topic_conflict(link, topic, cls, deadline, budget)
        return cls

    def _differs(self, topic: str, cls: type[BaseModel]) -> bool:
        """Whether ``cls`` differs from the type ``$/topics`` announced for ``topic``, by its
        fingerprint (announced without one, or as another type, it is not compared)."""
        announced = self._topics.get(topic, {})
        theirs = announced.get("fingerprint")
        if isinstance(theirs, str) and getattr(cls, "type_name", None) == announced.get("type"):
            ours = self._types.fingerprint(cls)
            return ours is not None and ours != theirs
        return False

    async def _topic_conflict(
        self, link: Link, topic: str, cls: type[BaseModel], deadline: float, budget: float
    ) -> NoReturn:
        """Raise the conflict of ``cls`` with the server's type of ``topic``, naming the first
        declaration that differs, read from the server's description (asked for only now)."""
        try:
            methods = await self._methods(link, deadline, budget)
        except RPCError:
            methods = []
        entry = _topic_entry(methods, topic)
        definitions = None if entry is None else _definitions_of(entry)
        raise self._types.conflict(cls, definitions, f"server {self.url}")

    async def _find_topic_type(
        self,
        link: Link,
        topic: str,
        msg_type: type[BaseModel] | str | None,
        deadline: float,
        budget: float,
    ) -> type[BaseModel]:
        """The message class of ``topic``: given, else by its name from the local search path,
        else from the server's description (``rpc.discover``)."""
        if msg_type is not None and not isinstance(msg_type, str):
            return msg_type
        named = msg_type if msg_type is not None else self._topics.get(topic, {}).get("type")
        if named is not None:
            known = self._message_types.get(named) or self._local_message(named)
            if known is not None:
                return known
        try:
            methods = await self._methods(link, deadline, budget)
        except (ServiceNotFound, InternalError):  # a server that does not describe types
            methods = []
        entry = _topic_entry(methods, topic)
        if named is None:
            if entry is None or not isinstance(entry.get("x-srvwire-type"), str):
                topics = ", ".join(sorted(self._topics)) or "none"
                raise ServiceNotFound(
                    f"the server has no topic named {topic} (topics: {topics})", service=topic
                )
            named = str(entry["x-srvwire-type"])
            known = self._local_message(named)
            if known is not None:
                return known
        definitions = {} if entry is None else _definitions_of(entry)
        if named not in definitions:
            raise InterfaceNotFoundError(
                named,
                f"cannot type the messages of {topic}: {named} is not on the local search "
                f"path, and the server {self.url} does not describe it",
            )
        cls = remote_message(
            named,
            definitions,
            f"server {self.url}",
            self.options.message_resolver,
            max_values=self.options.transport_options.max_message_size,
        )
        self._message_types[named] = cls
        return cls

    def _local_message(self, name: str) -> type[BaseModel] | None:
        if len(name.split("/")) != 3:
            return None
        try:
            cls: type[BaseModel] = self.options.message_resolver(name)
        except InterfaceNotFoundError:
            return None
        self._message_types[name] = cls
        return cls

    def _not_connected(self, method: str) -> ConnectionLost:
        if not self._closed:
            self._check_loop()  # a client whose loop ended has lost its connection with it
        why = "the client is closed" if self._closed else f"not connected to {self.url}"
        return ConnectionLost(why, {"url": self.url}, service=method)

    def _check_loop(self) -> None:
        """Raise ``RuntimeError`` when running outside the event loop this client was opened in.

        Only on the paths that wait or fail: asking for the running loop costs a system call
        on Python 3.11, and a call on a connection checks its loop for free.
        """
        if self._loop is not None and self._loop is not asyncio.get_running_loop():
            raise foreign_loop(self._loop)

    async def _wait_until_ready(self, method: str, deadline: float, budget: float) -> None:
        """Wait until connected and ``method`` is advertised, or raise ServiceUnavailable."""
        while self._link is None or method not in self._services:
            if self._closed or (self._link is None and not self.options.reconnect):
                raise self._not_connected(method)
            self._check_loop()
            try:
                async with asyncio.timeout_at(deadline):
                    await self._changed.wait()
            except TimeoutError:
                if self._link is not None and method in self._services:
                    return
                where = "was not advertised" if self._link is not None else "was not reachable"
                raise ServiceUnavailable(
                    f"the service {where} within {budget:g} s",
                    {"url": self.url, "timeout": budget},
                    service=method,
                ) from None


def _definitions_of(entry: Any) -> dict[str, str]:
    """The definition texts one ``rpc.discover`` method object carries, by full name."""
    texts = entry.get("x-srvwire-definitions") if isinstance(entry, dict) else None
    if not isinstance(texts, dict):
        return {}
    return {k: v for k, v in texts.items() if isinstance(k, str) and isinstance(v, str)}


def _topic_entry(methods: list[Any], topic: str) -> dict[str, Any] | None:
    """The method object of the topic ``topic`` in an ``rpc.discover`` document, if any."""
    return next(
        (
            m
            for m in methods
            if isinstance(m, dict)
            and m.get("x-srvwire-kind") == "topic"
            and isinstance(m.get("name"), str)
            and canonical_name(m["name"]) == topic
        ),
        None,
    )


def _described(methods: list[Any]) -> dict[str, dict[str, str]]:
    """Map each method of an ``rpc.discover`` document to the definitions it carries."""
    return {
        canonical_name(entry["name"]): _definitions_of(entry)
        for entry in methods
        if isinstance(entry, dict)
        and isinstance(entry.get("name"), str)
        and "x-srvwire-definitions" in entry
        and entry.get("x-srvwire-kind", "service") in ("service", "action")
    }


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """A topic as the server announces it: name, message type, QoS, whether clients may
    publish on it."""

    name: str
    type: str
    qos: Mapping[str, Any]
    publish: bool

    @classmethod
    def of(cls, name: str, entry: Mapping[str, Any]) -> TopicInfo:
        qos = entry.get("qos")
        return cls(
            name,
            str(entry.get("type", "")),
            MappingProxyType(dict(qos) if isinstance(qos, dict) else {}),
            entry.get("publish") is True,
        )


class Subscription:
    """A subscription to a topic: what :meth:`Client.subscribe` returns.

    An async iterator of typed messages, and an async context manager that holds the
    subscription for the block. Started on entry or on the first message asked for. What it
    counts: :attr:`seq`, the sequence number of the last message returned; :attr:`missed`,
    how many the subscriber did not get just before it; :attr:`dropped`, how many it did not
    get in all (dropped by a best-effort queue, here or on the server, or published while the
    connection was down); :attr:`granted`, the QoS the server granted.

    Messages arrive in a queue of the granted ``depth``: a best-effort subscriber that does
    not keep up loses the oldest (counted in :attr:`dropped`), a reliable one is ended with
    :class:`~srvwire.errors.ResourceExhausted`, as on the server. Not keeping up means a
    message came while the code reading the subscription was not waiting for one and found
    ``depth`` messages queued (what is left of a burst included); whatever arrives while it
    waits (a burst read at once) is kept for it.
    """

    def __init__(
        self,
        client: Client,
        name: str,
        msg_type: type[BaseModel] | str | None,
        qos: Mapping[str, Any] | None,
        budget: float,
        duration: float | None = None,
    ) -> None:
        self.client = client
        self.name = name
        self.msg_type = msg_type
        self.qos = None if qos is None else dict(qos)
        self.budget = budget
        self.duration = duration
        self._until: float | None = None  # when the duration ends, on the loop's clock
        self.granted: dict[str, Any] = {}
        self.gaps = Gaps()
        self.seq: int | None = None
        self.missed = 0
        self._decoder: ModelDecoder[BaseModel] | None = None
        self._queue: deque[tuple[int, int, BaseModel]] = deque()
        self._limit = 1
        self._best_effort = False
        self._end: BaseException | None = None
        self._wakeup: asyncio.Future[None] | None = None
        self._started: asyncio.Future[None] | None = None
        self._link: Link | None = None
        self._id: int | None = None
        self._future: asyncio.Future[Arrived] | None = None
        self._opened = False
        self._managed = False
        self._closed = False
        self._resuming = False

    def __repr__(self) -> str:
        return f"<Subscription to {self.name}, {len(self._queue)} queued>"

    @property
    def dropped(self) -> int:
        """How many messages this subscriber did not get, in all."""
        return self.gaps.missed

    @property
    def active(self) -> bool:
        """Whether the subscription runs (or is resuming), and has not ended."""
        return self._opened and self._end is None

    # --- lifetime ---------------------------------------------------------------------------

    async def start(self) -> Subscription:
        """Subscribe, and return once the server said ``$/subscribed``; idempotent."""
        if self._opened:
            return self
        self._opened = True
        self.client._subscriptions.add(self)
        try:
            await self._subscribe()
        except BaseException:
            self._closed = True
            self.client._subscriptions.discard(self)
            raise
        return self

    async def close(self) -> None:
        """End the subscription (``$/cancel``); the messages queued here are dropped."""
        if self._closed:
            return
        self._closed = True
        self._resuming = False
        self.client._subscriptions.discard(self)
        link, id, future = self._link, self._id, self._future
        self._link = self._id = self._future = None
        if link is not None and id is not None:
            link.streams.pop(id, None)
            data = link.session.cancel(id)
            if future is not None:
                future.cancel()
            if data is not None:
                await link.send_quietly(data)
        self._queue.clear()
        self._finish(StopAsyncIteration())

    async def __aenter__(self) -> Subscription:
        self._managed = True
        return await self.start()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def __aiter__(self) -> AsyncIterator[BaseModel]:
        return self._messages()

    async def _messages(self) -> AsyncIterator[BaseModel]:
        try:
            while True:
                try:
                    message = await self.receive()
                except StopAsyncIteration:
                    return
                yield message
        finally:
            if not self._managed:
                await self.close()

    async def receive(self) -> BaseModel:
        """Return the next message; raise the error that ended the subscription, or
        ``StopAsyncIteration`` once it was closed."""
        if not self._opened:
            await self.start()
        queue = self._queue
        while not queue:
            if self._end is not None:
                raise self._end
            self._wakeup = asyncio.get_running_loop().create_future()
            try:
                await self._wakeup
            finally:
                self._wakeup = None
        seq, missed, message = queue.popleft()
        self.seq, self.missed = seq, missed
        return message

    # --- the wire ---------------------------------------------------------------------------

    async def _subscribe(self) -> None:
        client = self.client
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.budget
        link = client._link
        if link is None:
            raise client._not_connected(self.name)
        if self._decoder is None:
            cls = await client._topic_type(link, self.name, self.msg_type, deadline, self.budget)
            self._decoder = ModelDecoder(cls)
        params: dict[str, Any] = {"topic": self.name}
        if self.qos is not None:
            params["qos"] = self.qos
        left = self.duration
        if left is not None:  # after a reconnect, only what is left of it
            if self._until is None:
                self._until = loop.time() + left
            else:
                left = max(0.0, self._until - loop.time())
        future: asyncio.Future[Arrived] = loop.create_future()
        id, data = link.session.request(SUBSCRIBE_METHOD, encode_json(params), left, future)
        self._link, self._id, self._future = link, id, future
        started = self._started = loop.create_future()
        link.streams[id] = self
        future.add_done_callback(functools.partial(self._ended, id))
        await client._send(link, self.name, data)
        try:
            async with asyncio.timeout_at(deadline):
                await asyncio.shield(started)
        except TimeoutError:
            await self.close()
            raise DeadlineExceeded(
                f"the server did not start the subscription within {self.budget:g} s",
                {"timeout": self.budget},
                service=self.name,
            ) from None

    async def _resume(self) -> None:
        """Subscribe again on the client's new connection."""
        self._resuming = False
        if self._closed:
            return
        try:
            await self._subscribe()
        except RPCError as exc:
            self._finish(exc)

    def started(self, event: Subscribed) -> None:
        """The server's ``$/subscribed``."""
        granted = self.granted = event.granted
        seq = granted.get("seq")
        epoch = granted.get("epoch")
        last = self.gaps.last  # before subscribed() forgets it when the server restarted
        self.gaps.subscribed(seq if type(seq) is int else 0, epoch if type(epoch) is str else None)
        depth = granted.get("depth")
        self._limit = depth if type(depth) is int and depth > 0 else 10
        self._best_effort = granted.get("reliability") == "best_effort"
        if last is not None:
            self.client.logger.warning(
                "resumed the subscription to %s after reconnecting (last message seen: %s)",
                self.name,
                last,
            )
        if self._started is not None and not self._started.done():
            self._started.set_result(None)

    def deliver(self, event: TopicMessage) -> None:
        """One ``$/message`` for this subscription."""
        seq = event.seq
        gaps = self.gaps
        last = gaps.last
        counted = gaps.missed  # to take the message back if it turns out not to be JSON-RPC
        if last is not None and seq == last + 1:  # Gaps.accept's usual case, inline: none missed
            gaps.last = seq
            missed = 0
        else:
            accepted = gaps.accept(seq, event.dropped)
            if accepted is None:
                return  # replayed after a reconnection, and seen already
            missed = accepted
        decoder = self._decoder
        assert decoder is not None
        try:
            message = event.decode(decoder)
        except ValueError as exc:
            self._abandon(
                InternalError(
                    f"a message on {self.name} does not match its type: {exc}", service=self.name
                )
            )
            return
        except ProtocolViolation as exc:  # as the reader does with what is not JSON-RPC
            gaps.last, gaps.missed = last, counted  # a message nobody received: not seen
            if self._link is not None:
                self._link.violation(exc)
            return
        queue = self._queue
        # Depth bounds what waits while the code reading the subscription is busy elsewhere;
        # while it waits in receive() (or was woken and has not run yet), it takes the whole
        # queue at its next turn, so what arrives meanwhile (a burst, read at once) is kept.
        if len(queue) >= self._limit and self._wakeup is None:
            if not self._best_effort:
                self._abandon(
                    ResourceExhausted(
                        f"this subscriber to {self.name} did not keep up: its queue of "
                        f"{self._limit} messages was full while the code reading it was busy "
                        "elsewhere, and the subscription is reliable; take each message as it "
                        "comes, or subscribe with a larger depth, or best_effort to drop the "
                        "oldest instead",
                        {"depth": self._limit, "seq": seq},
                        service=self.name,
                    )
                )
                return
            # The oldest goes; the message after it (the next one queued, or this one) was
            # missed just before by what the oldest was, and the oldest itself.
            _, lost, _ = queue.popleft()
            gaps.missed += 1
            if queue:
                after, before, kept = queue[0]
                queue[0] = (after, before + lost + 1, kept)
            else:
                missed += lost + 1
        queue.append((seq, missed, message))
        if self._wakeup is not None:
            self._wake()

    def _ended(self, id: int, future: asyncio.Future[Arrived]) -> None:
        """The subscription's request got its reply (or the connection ended)."""
        link = self._link
        if self._id != id or link is None:
            return  # an earlier one, or closed here
        link.streams.pop(id, None)
        self._link = self._id = self._future = None
        if future.cancelled():
            return
        error = future.exception()
        if error is None:
            try:
                future.result().decode()
            except (RPCError, ProtocolViolation) as exc:
                error = link.failure(self.name, exc)
            else:
                error = StopAsyncIteration()
        client = self.client
        if isinstance(error, ConnectionLost) and client.options.reconnect and not client.closed:
            self._resuming = True  # the client resubscribes when it has a connection again
            return
        if isinstance(error, RPCError):
            error.service = self.name
        self._finish(error)

    def _detach(self) -> None:
        """The client is closing: end quietly, as the connection's end ends it on the server."""
        self._closed = True
        self._resuming = False
        link, id, future = self._link, self._id, self._future
        self._link = self._id = self._future = None
        if link is not None and id is not None:
            link.streams.pop(id, None)
            link.session.pending.pop(id, None)
        if future is not None:
            future.cancel()
        self._finish(StopAsyncIteration())

    def _abandon(self, error: RPCError) -> None:
        """End the subscription from this side with ``error``, telling the server."""
        link, id = self._link, self._id
        if link is not None and id is not None:
            link.streams.pop(id, None)
            data = link.session.cancel(id)
            if self._future is not None:
                self._future.cancel()
            if data is not None:
                self.client.spawn(link.send_quietly(data))
        self._link = self._id = self._future = None
        self.client._subscriptions.discard(self)
        self._finish(error)

    def _finish(self, error: BaseException) -> None:
        self.client._subscriptions.discard(self)
        if self._end is None:
            self._end = error
        if self._started is not None and not self._started.done():
            self._started.set_exception(error)
            self._started.exception()  # retrieved: start() raises it, or nobody waits
        self._wake()

    def _wake(self) -> None:
        wakeup = self._wakeup
        if wakeup is not None and not wakeup.done():
            wakeup.set_result(None)


class ServiceProxy(Generic[R]):
    """A callable bound to one service: ``await proxy(request)`` or ``await proxy(a=1, b=2)``.

    Made by :meth:`Client.proxy`; the call options are the proxy's, so every field name,
    ``timeout`` included, is free for the request. ``R`` is the response type a type checker
    sees (``Any`` unless the proxy was made with a generated service class).
    """

    def __init__(
        self,
        client: Client,
        name: str,
        srv_type: SrvType | None = None,
        *,
        timeout: float | None = None,
        wait_for_ready: bool = False,
    ) -> None:
        self.client = client
        self.name = canonical_name(name)
        self.srv_type = srv_type
        self.timeout = None if timeout is None else check_timeout(timeout)
        self.wait_for_ready = wait_for_ready

    async def __call__(
        self, request: BaseModel | Mapping[str, Any] | None = None, /, **fields: Any
    ) -> R:
        """Call the service; see :meth:`Client.call`.

        A coroutine function, as a handler a server can be given must be to run on the event
        loop: a proxy registered as a handler relays calls without a thread.
        """
        if request is not None and fields:
            raise TypeError("pass the request object or keyword fields, not both")
        response: R = await self.client.call(
            self.name,
            fields if request is None else request,
            timeout=self.timeout,
            srv_type=self.srv_type,
            wait_for_ready=self.wait_for_ready,
        )
        return response

    async def wait_for_service(
        self,
        *,
        timeout: float | None = None,  # noqa: ASYNC109 - gives up with ServiceUnavailable
    ) -> ServiceInfo:
        """Wait until the server advertises this service; see :meth:`Client.wait_for_service`."""
        return await self.client.wait_for_service(self.name, timeout=timeout)

    def __repr__(self) -> str:
        return f"ServiceProxy({self.name!r}, {self.srv_type!r})"


def plaintext_host(url: str) -> str | None:
    """The host of a plain ``ws://`` ``url`` that is not loopback (where credentials would
    travel in the clear), else None."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "ws":
        return None
    host = (parts.hostname or "").lower()
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    return None if loopback else host


class connect(Coroutine[Any, Any, Client]):
    """Connect to the srvwire server at ``url``: the options, held once.

    Use it as ``async with connect(url) as client:`` (closed on exit) or as
    ``client = await connect(url)`` (close it with ``await client.close()``). It is a
    coroutine too, so what runs a coroutine opens it: ``runner.run(connect(url))`` with an
    :class:`asyncio.Runner` gives a client that the runner's later ``run`` calls use. A client
    lives in the event loop that opened it: one opened by ``asyncio.run(connect(url))`` closes
    its connection when that loop ends, and raises ``RuntimeError`` saying so when used again.
    From blocking code, use :func:`srvwire.sync.connect`.

    * ``timeout``: the default deadline of a call, in seconds; finite.
    * ``open_timeout``: how long opening may take (connection, handshake, the services list).
    * ``max_message_size``: the largest message accepted from the server, in bytes (``None``:
      no limit). A larger one closes the connection with code 1009.
    * ``ping_interval``/``ping_timeout``: keepalive; a peer that stops answering pings is
      treated as a dropped connection.
    * ``compression``: ``"deflate"`` to negotiate per-message compression; off by default,
      since JSON-RPC messages are small and compression costs time on every one.
    * ``reconnect``: re-dial in the background (with backoff) when the connection drops or
      cannot be opened; see :meth:`Client.call`'s ``wait_for_ready``. Opening then never
      raises for an unreachable server.
    * ``search_path``: folders of interface packages searched for types by name, before the
      default search path (``SRVWIRE_INTERFACE_PATH``, then the bundled packages).
    * ``type_resolver``: a function from a service type name to its class, instead of the
      loader; it raises :class:`~srvwire.errors.InterfaceNotFoundError` for a name it does
      not know.
    * ``inf_nan``: how typed requests write ``inf``, ``-inf`` and ``nan``: ``"strings"`` (the
      default), ``"null"`` or ``"constants"``, as :class:`~srvwire.server.Server` takes it;
      responses are read in every spelling.
    * ``logger``: where to log (default: the ``srvwire.client`` logger).
    * ``transport``: ``"websockets"`` (the default) or a
      :class:`~srvwire.transports.base.Transport` instance, such as the
      :class:`~srvwire.transports.memory.MemoryTransport` a server listens on.
    * ``token``: a bearer token, sent as ``Authorization: Bearer <token>``; ``headers``:
      more headers for the opening request (a mapping, or ``(name, value)`` pairs). Neither
      appears in a ``repr``. A token (or an ``Authorization`` header) is not sent over plain
      ``ws://`` to a host that is not loopback, where anyone on the way could read it, unless
      ``allow_plaintext_token=True``.
    * ``ssl``: for a ``wss://`` URL, how to check the server: an :class:`ssl.SSLContext`, or
      the path of a CA certificate file to trust (default: the system's CAs).

    **Where a call's types come from.** Every call is typed: its request is validated here and
    its reply is the type's ``Response`` class. The type is the ``srv_type`` a call gives, else
    the one the server advertises for the service, found in this order:

    1. *local first*: ``type_resolver``, or the search path;
    2. *then the server*: a type the local path does not have is built from the definition
       texts the server gives in ``rpc.discover`` (asked once per connection, when first
       needed). The messages it nests are taken from the local path when they are there.

    A service type found locally is used without asking the server for its description: it
    is compared, before the connection's first call of the service, with the fingerprint the
    server announced in ``$/services``, and one that differs is an
    :class:`~srvwire.errors.InterfaceConflictError` naming the local file, the server and the
    first declaration that differs (the description is read then, to say which). When the
    description is
    read, every type in it is compared with the local file or the process's class of the same
    name (through the process's :class:`~srvwire.typeregistry.TypeRegistry`): one the server
    defines as the local file does is the local class, and one it defines differently is an
    :class:`~srvwire.errors.InterfaceConflictError` that names both sources (the file, and
    ``server ws://...``). A type found in neither place is an
    :class:`~srvwire.errors.InterfaceNotFoundError` that says so. No environment variable or
    option turns a call's result into plain dicts.

    Raise :class:`~srvwire.errors.ServiceUnavailable` when the server cannot be reached
    (without ``reconnect``), and ``ValueError`` for a URL the transport cannot use, or a token
    it would send in the clear.
    """

    def __init__(
        self,
        url: str = DEFAULT_URL,
        *,
        timeout: float = DEFAULT_TIMEOUT,
        open_timeout: float = 10.0,
        max_message_size: int | None = 2**20,
        ping_interval: float | None = 20.0,
        ping_timeout: float | None = 20.0,
        compression: str | None = None,
        reconnect: bool = False,
        search_path: SearchPath | None = None,
        type_resolver: TypeResolver | None = None,
        logger: LoggerLike | None = None,
        transport: str | Transport = "websockets",
        token: str | None = None,
        headers: Mapping[str, str] | Iterable[tuple[str, str]] = (),
        ssl: _ssl.SSLContext | str | os.PathLike[str] | None = None,
        allow_plaintext_token: bool = False,
        inf_nan: InfNan = INF_NAN_MODES[0],
    ) -> None:
        self.transport = get_transport(transport)
        self.transport.check_url(url)
        self.url = url
        pairs = list(headers.items() if isinstance(headers, Mapping) else headers)
        if token is not None:
            pairs.append(("Authorization", f"Bearer {token}"))
        self.headers = Headers(pairs)
        exposed = plaintext_host(url)
        credentials = any(name.lower() == "authorization" for name, _ in pairs)
        if exposed is not None and credentials and not allow_plaintext_token:
            raise ValueError(
                f"refusing to send credentials over plain ws:// to {exposed}, where anyone on "
                "the way can read them: use wss://, or pass allow_plaintext_token=True"
            )
        self.ssl = (
            _ssl.create_default_context(cafile=os.fspath(ssl))
            if isinstance(ssl, str | os.PathLike)
            else ssl
        )
        self.timeout = check_timeout(timeout)
        self.open_timeout = check_timeout(open_timeout, "open_timeout")
        self.transport_options = Options(
            max_message_size=max_message_size,
            ping_interval=ping_interval,
            ping_timeout=ping_timeout,
            compression=compression,
        )
        if inf_nan not in INF_NAN_MODES:
            raise ValueError(f"inf_nan must be one of {', '.join(INF_NAN_MODES)}, not {inf_nan!r}")
        self.inf_nan: InfNan = inf_nan
        self.reconnect = reconnect
        self.search_path = search_path
        self.type_resolver: TypeResolver = type_resolver or functools.partial(
            load_service, search_path=search_path
        )
        self.message_resolver: MessageResolver = functools.partial(
            load_message, search_path=search_path
        )
        self.logger = logger
        self._client: Client | None = None
        self._opening: Coroutine[Any, Any, Client] | None = None  # when run as a coroutine

    def __repr__(self) -> str:
        return f"connect({self.url!r})"

    async def __aiter__(self) -> AsyncIterator[Client]:
        """Yield an open client, and a new one each time the loop comes round again.

        For a loop that reconnects by itself: ``async for client in connect(url):``, with the
        body catching ``ConnectionLost`` and going on to the next client. A server that cannot
        be reached is dialled again with backoff. Each client is closed when the loop comes
        round again; one the loop leaves early (``break``) is closed only when the event loop
        finalizes the iteration, so close it yourself when that matters.
        """
        delays = _backoff()
        while True:
            client = Client(self)
            try:
                await client.open()
            except ServiceUnavailable as exc:
                self._log().info("%s; trying again", exc.message)
                await asyncio.sleep(next(delays))
                continue
            delays = _backoff()
            try:
                yield client
            finally:
                await client.close()

    def _log(self) -> LoggerLike:
        return self.logger or logging.getLogger(__name__)

    async def _open(self) -> Client:
        client = self._client = Client(self)
        return await client.open()

    def __await__(self) -> Generator[Any, None, Client]:
        return self._open().__await__()

    # Run as a coroutine (by asyncio.run, a Runner, create_task): open one client.

    def send(self, value: Any, /) -> Any:
        if self._opening is None:
            self._opening = self._open()
        return self._opening.send(value)

    def throw(self, typ: Any, val: Any = None, tb: Any = None, /) -> Any:
        if self._opening is None:
            self._opening = self._open()
        return self._opening.throw(typ, val, tb)

    def close(self) -> None:
        if self._opening is not None:
            self._opening.close()

    async def __aenter__(self) -> Client:
        return await self._open()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._client is not None:
            await self._client.close()
