"""The asyncio server: a set of services, listening on a transport, and its shutdown.

A :class:`Server` holds a :class:`~srvwire.dispatch.ServiceRegistry` and its options; it does not
listen by itself. :func:`serve` makes it listen on a transport (WebSockets by default) and returns
a :class:`RunningServer`, which gives each connection a
:class:`~srvwire.serving.ServedConnection`: a :class:`~srvwire.session.ServerSession` for the
rules of the conversation, and the reader and call runner that carry them out.

Invariants:

* **Nothing a client sends stops the server.** A connection that ends cancels that
  connection's calls and nothing more.
* **Shutdown is graceful and bounded.** :meth:`RunningServer.close` at once refuses new
  connections (HTTP 503; ``/healthz`` says ``draining``) and answers new calls
  ``UNAVAILABLE``; asks every running goal to stop (``$/goal canceling``, as a client's
  cancellation asks); then it waits up to ``grace_period`` for calls in flight, goals
  included, cancels the rest (they answer ``UNAVAILABLE`` at once, whether their handlers stop
  or not; one that goes on is named in the log), stops listening, and closes every connection
  with 1001 (going away).
* **Who may connect is decided before the connection opens**, by the server's
  :class:`~srvwire.handshake.EdgePolicy` (origins, Host, ``max_connections``, ``auth``),
  which the transport asks about each opening request.
* **The registry changes on the event loop's thread.** While the server listens,
  :meth:`Server.add_service` and :meth:`Server.remove_service` called from another thread hand
  the change to the loop and wait for it; every connection is then sent ``$/services``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import signal
import ssl as _ssl
import threading
from collections.abc import Callable, Coroutine, Generator, Iterable, Mapping
from concurrent.futures import Executor
from types import TracebackType
from typing import Any, TypeVar

from pydantic import BaseModel

from srvwire.actions import DEFAULT_CANCEL_GRACE, Accept, GoalRunner, goal_service
from srvwire.auth import Authenticator
from srvwire.dispatch import (
    Handler,
    ServiceRegistry,
    normalize_name,
    refuse_large_defaults,
    refuse_large_service,
)
from srvwire.errors import RegistrationError, ServiceUnavailable
from srvwire.handshake import EdgePolicy, describe_reach, is_loopback
from srvwire.inline import Pending, finish, first_step
from srvwire.models import INF_NAN_MODES, Action, InfNan, Service
from srvwire.pubsub import Publisher, TopicEntry, check_handler, qos_of
from srvwire.serving import ServedConnection
from srvwire.threads import ConcurrencyLimit, HandlerThreads
from srvwire.topics import QoS, Topic
from srvwire.transports import get_transport
from srvwire.transports.base import (
    Admitted,
    Answered,
    Connection,
    Handshake,
    Hosts,
    Listener,
    Options,
    Transport,
    TransportClosed,
    WriteTimedOut,
)

__all__ = ["RunningServer", "Server", "serve"]

H = TypeVar("H", bound=Handler)
T = TypeVar("T", bound=Callable[[Any], Any])
M = TypeVar("M", bound=BaseModel)

# Marks the log lines that say the server started or is stopping, for a caller that prints
# them its own way (srvwire serve) to leave out: record.srvwire_lifecycle is True.
_LIFECYCLE = {"srvwire_lifecycle": True}
LEFT_TASKS_LINGER = 1.0
"""Seconds :meth:`Server.run` gives the tasks still running after the server closed (handlers
that did not end when cancelled) to end once cancelled again, before it returns anyway."""
_LOOP_CHECK_INTERVAL = 1.0  # seconds between checks that a loop we wait on still runs
ACCEPT_FAILURE_LOG_INTERVAL = 10.0
"""Seconds: at most one line in this time about connections that cannot be accepted because
the process is out of file descriptors (asyncio retries the accept every second)."""
_ACCEPT_FAILED = "socket.accept() out of system resource"  # asyncio's words for it


@contextlib.contextmanager
def _show_log_unless_configured() -> Generator[None, None, None]:
    """Show the ``srvwire`` loggers on stderr at INFO while in the block, when nothing else
    would show them; leave a configured logging alone."""
    package = logging.getLogger("srvwire")
    if package.hasHandlers():
        yield
        return
    handler = logging.StreamHandler()  # stderr
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    level = package.level
    package.addHandler(handler)
    if package.getEffectiveLevel() > logging.INFO:
        package.setLevel(logging.INFO)
    try:
        yield
    finally:
        package.removeHandler(handler)
        package.setLevel(level)


def _running_loop() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None


def _run_bounded(main: Coroutine[Any, Any, None]) -> None:
    """Run ``main`` on a new event loop, as :func:`asyncio.run` does, but end in bounded time.

    :func:`asyncio.run` cancels the tasks still there at the end and waits for all of them, so
    one handler that swallows every cancellation (shutdown has already answered its call and
    named it) would keep it from ever returning. Here they get :data:`LEFT_TASKS_LINGER`
    seconds to end after that cancellation; those that go on are left with the closed loop,
    without asyncio's "Task was destroyed but it is pending" about them.
    """
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)  # as asyncio.run does, for code that asks for "the" loop
    left: set[asyncio.Task[Any]] = set()

    def quiet_about_left(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        if context.get("task") in left:
            return
        if previous is not None:
            previous(loop, context)
        else:
            loop.default_exception_handler(context)

    previous = None
    try:
        loop.run_until_complete(main)
    finally:
        try:
            remaining = asyncio.all_tasks(loop)
            for task in remaining:
                task.cancel()
            if remaining:
                loop.run_until_complete(asyncio.wait(remaining, timeout=LEFT_TASKS_LINGER))
            left.update(task for task in remaining if not task.done())
            for task in remaining - left:
                if not task.cancelled() and task.exception() is not None:
                    loop.call_exception_handler(
                        {
                            "message": "unhandled exception during the server's shutdown",
                            "exception": task.exception(),
                            "task": task,
                        }
                    )
            previous = loop.get_exception_handler()
            loop.set_exception_handler(quiet_about_left)
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.run_until_complete(loop.shutdown_default_executor())
        finally:
            asyncio.set_event_loop(None)
            loop.close()


class Server:
    """A set of services and the options to serve them with; :func:`serve` makes it listen.

    ``max_in_flight`` bounds the calls running at once on one connection (a reply counts until
    it is sent); ``max_subscriptions`` the subscriptions running at once on one connection
    (past it ``$/subscribe`` is answered ``RESOURCE_EXHAUSTED``); ``max_batch`` the messages
    of one batch; ``notification_timeout`` how long a notification's handler may run when
    the notification gives no deadline (None: forever);
    ``max_message_size`` the size of one incoming message in bytes (None: no limit);
    ``max_queued_bytes`` the budget of a connection's bytes waiting to be sent, replies and
    topic data together (topic data takes what replies leave): past it the connection reads no
    more calls until its client has read them down to a quarter of it;
    ``write_timeout`` how long a connection may stay past its budget before it is closed with
    code 1008 (None: forever; with keepalive on, at most ``ping_interval + ping_timeout``);
    see ``docs/limits.md`` for what they bound;
    ``grace_period`` how long shutdown waits for calls in flight (running action goals are
    asked to stop first, as a client's cancellation asks);
    ``ping_interval``/``ping_timeout`` the keepalive (None turns it off);
    ``compression="deflate"`` turns permessage-deflate on (off by default: it slows small
    calls down); ``executor`` runs sync handlers (default: the server's own
    :class:`~srvwire.threads.HandlerThreads`, whose threads never keep the process alive);
    ``inf_nan`` how responses write ``inf``, ``-inf`` and ``nan``: ``"strings"`` (the default;
    ``"Infinity"``, ``"-Infinity"``, ``"NaN"``), ``"null"`` or ``"constants"`` (the bare tokens
    Python's :mod:`json` writes, which a browser cannot parse); requests are read in every
    spelling (see :data:`~srvwire.models.InfNan`).

    At the edge (see :mod:`srvwire.handshake` and docs/security.md): ``origins`` lists the
    browser origins allowed besides pages of the server's own host (``"null"``, or ``"*"``
    for all, which lets any web page call the services); ``auth`` authenticates each
    connection (such as :class:`~srvwire.auth.TokenAuth`; None: no authentication);
    ``max_connections`` bounds the connections open at once (past it: HTTP 503).

    ``access_log=True`` writes a line per call to the ``srvwire.access`` logger (or to the
    logger given): peer, service, outcome and duration (see
    :class:`~srvwire.serving.AccessLoggedSession`), a line per subscription as it ends, and
    one per topic a connection published on without asking for answers, as the connection
    ends (or the topic is removed); off, it costs nothing.
    """

    def __init__(
        self,
        *,
        max_in_flight: int = 256,
        max_batch: int = 100,
        notification_timeout: float | None = 30.0,
        max_message_size: int | None = 2**20,
        max_queued_bytes: int = 4 * 2**20,
        write_timeout: float | None = 30.0,
        grace_period: float = 5.0,
        ping_interval: float | None = 20.0,
        ping_timeout: float | None = 20.0,
        compression: str | None = None,
        executor: Executor | None = None,
        logger: logging.Logger | None = None,
        origins: Iterable[str] = (),
        auth: Authenticator | None = None,
        max_connections: int | None = 512,
        inf_nan: InfNan = INF_NAN_MODES[0],
        access_log: bool | logging.Logger = False,
        max_subscriptions: int = 256,
    ) -> None:
        if max_connections is not None and max_connections < 1:
            raise ValueError(f"max_connections must be at least 1, not {max_connections}")
        if auth is not None and not callable(auth):
            raise TypeError(
                "auth must be an authenticator, such as TokenAuth({token: identity}), "
                f"not a {type(auth).__name__}"
            )
        self.origins = tuple(origins)
        EdgePolicy("localhost", origins=self.origins)  # says now what is wrong with one
        self.auth = auth
        self.max_connections = max_connections
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be at least 1, not {max_in_flight}")
        if max_batch < 1:
            raise ValueError(f"max_batch must be at least 1, not {max_batch}")
        if max_subscriptions < 0:
            raise ValueError(f"max_subscriptions must not be negative, not {max_subscriptions}")
        if notification_timeout is not None and not notification_timeout > 0:
            raise ValueError(
                f"notification_timeout must be a number of seconds > 0, not {notification_timeout}"
            )
        if max_queued_bytes < 0:
            raise ValueError(f"max_queued_bytes must not be negative, not {max_queued_bytes}")
        if write_timeout is not None and not write_timeout > 0:
            raise ValueError(
                f"write_timeout must be a number of seconds > 0 or None, not {write_timeout}"
            )
        if grace_period < 0:
            raise ValueError(f"grace_period must not be negative, not {grace_period}")
        self.registry = ServiceRegistry(inf_nan=inf_nan)
        self.max_in_flight = max_in_flight
        self.max_subscriptions = max_subscriptions
        self.max_batch = max_batch
        self.notification_timeout = notification_timeout
        self.max_message_size = max_message_size
        self.max_queued_bytes = max_queued_bytes
        self.write_timeout = write_timeout
        self.grace_period = grace_period
        self.ping_interval = ping_interval
        self.ping_timeout = ping_timeout
        self.compression = compression
        self.executor: Executor = executor if executor is not None else HandlerThreads()
        self.logger = logger if logger is not None else logging.getLogger(__name__)
        self.access_log: logging.Logger | None = (
            access_log
            if isinstance(access_log, logging.Logger)
            else logging.getLogger("srvwire.access")
            if access_log
            else None
        )
        self._running: set[RunningServer] = set()

    def __repr__(self) -> str:
        return f"<Server with {len(self.registry)} services>"

    @property
    def options(self) -> Options:
        """What each connection is allowed, as the transport takes it."""
        return Options(
            max_message_size=self.max_message_size,
            ping_interval=self.ping_interval,
            ping_timeout=self.ping_timeout,
            compression=self.compression,
            max_queued_bytes=self.max_queued_bytes,
            write_timeout=self.write_timeout,
        )

    # --- services ---------------------------------------------------------------------------

    def add_service(
        self,
        name: str,
        srv_type: type[Service],
        handler: Handler,
        *,
        scopes: Iterable[str] = (),
        max_concurrency: int | None = None,
    ) -> None:
        """Serve ``handler`` for ``srv_type`` under ``name``; tell connected clients.

        With ``scopes``, only a connection whose identity holds every one of them may call it
        (or see it); any other is answered ``PERMISSION_DENIED``. ``max_concurrency`` bounds
        how many calls of this service run their handler at once, over all connections; the
        others wait for a slot, in order, within their deadline. A blocking handler holds its
        slot until it returns, even after its caller left, so a slow service cannot take more
        threads than that. Raise
        :class:`~srvwire.errors.RegistrationError` for a bad name, a name already taken,
        a type that is not a service type, a handler that cannot be called as one, a
        ``max_concurrency`` below 1, or a request (or a response the handler takes) that,
        made without its fields, holds more values than ``max_message_size`` can carry
        (docs/limits.md; checked again when the server starts). Safe to
        call from any thread: while the server listens, the change is made on its event loop.
        """

        def add() -> None:
            self.registry.add(
                name,
                srv_type,
                handler,
                scopes,
                max_concurrency=max_concurrency,
                max_values=self.max_message_size,
            )
            self._services_changed()

        self._change_services(add)

    def remove_service(self, name: str) -> None:
        """Stop serving ``name``; calls already running finish. Tell connected clients.

        Raise :class:`~srvwire.errors.RegistrationError` if no service has that name. Safe to
        call from any thread, as :meth:`add_service` is.
        """

        def remove() -> None:
            self.registry.remove(name)
            self._services_changed()

        self._change_services(remove)

    def service(
        self,
        name: str,
        srv_type: type[Service],
        *,
        scopes: Iterable[str] = (),
        max_concurrency: int | None = None,
    ) -> Callable[[H], H]:
        """Decorate a handler to serve it under ``name`` (see :meth:`add_service`); the
        handler is returned unchanged."""

        def register(handler: H) -> H:
            self.add_service(
                name, srv_type, handler, scopes=scopes, max_concurrency=max_concurrency
            )
            return handler

        return register

    def add_action(
        self,
        name: str,
        action_type: type[Action],
        handler: Handler,
        *,
        scopes: Iterable[str] = (),
        accept: Accept | None = None,
        cancel_grace: float = DEFAULT_CANCEL_GRACE,
        max_concurrency: int | None = None,
    ) -> None:
        """Serve the action ``action_type`` under ``name`` with ``handler(goal, handle)``.

        The handler (``async def``, or plain ``def`` run on a thread like a service's) gets
        the goal and a :class:`~srvwire.actions.GoalHandle`, sends feedback through it,
        watches ``handle.cancel_requested``, and returns the result (a ``Result``, a dict of
        its fields, or None for the default). ``accept(goal)`` may refuse a goal before it
        starts: return False or raise :class:`~srvwire.errors.GoalRejected` with the reason.
        After the client asks to cancel, the handler has ``cancel_grace`` seconds to return
        before it is cancelled and the goal answered ``CANCELLED`` (then, whether or not the
        handler stops); when the server shuts down, it is asked the same way and has the
        server's ``grace_period``. ``scopes`` as for :meth:`add_service`, and listed with
        the services (``$/services``, ``rpc.discover``). ``max_concurrency`` bounds how many
        goals of this action run their handler at once, over all connections, as for
        :meth:`add_service`: the others are accepted and wait for a slot, in order, within
        their deadline (a cancellation meanwhile ends one ``canceled``, its handler never run);
        a plain ``def`` handler holds its slot until it returns.
        """
        canonical = normalize_name(name)
        if not (isinstance(action_type, type) and hasattr(action_type, "Goal")):
            raise RegistrationError(
                f"the type of the action {canonical} must be an action type (such as "
                f"load_action('example_interfaces/action/Fibonacci')), not {action_type!r}"
            )
        if not callable(handler):
            raise RegistrationError(
                f"the handler for {canonical} must be callable, not {type(handler).__name__}"
            )
        if accept is not None and not callable(accept):
            raise RegistrationError(f"the accept function of {canonical} must be callable")
        if not cancel_grace >= 0:
            raise RegistrationError(
                f"the cancel_grace of {canonical} must be a number of seconds, not {cancel_grace!r}"
            )
        if max_concurrency is not None and (
            type(max_concurrency) is not int or max_concurrency < 1
        ):
            raise RegistrationError(
                f"max_concurrency for {canonical} must be a whole number at least 1, "
                f"not {max_concurrency!r}"
            )
        runner = GoalRunner(
            canonical,
            action_type,
            handler,
            accept=accept,
            cancel_grace=cancel_grace,
            limit=None if max_concurrency is None else ConcurrencyLimit(max_concurrency),
        )
        self.add_service(canonical, goal_service(action_type), runner, scopes=scopes)

    def action(
        self,
        name: str,
        action_type: type[Action],
        *,
        scopes: Iterable[str] = (),
        accept: Accept | None = None,
        cancel_grace: float = DEFAULT_CANCEL_GRACE,
        max_concurrency: int | None = None,
    ) -> Callable[[H], H]:
        """Decorate ``handler(goal, handle)`` to serve it as an action under ``name`` (see
        :meth:`add_action`); the handler is returned unchanged."""

        def register(handler: H) -> H:
            self.add_action(
                name,
                action_type,
                handler,
                scopes=scopes,
                accept=accept,
                cancel_grace=cancel_grace,
                max_concurrency=max_concurrency,
            )
            return handler

        return register

    # --- topics -----------------------------------------------------------------------------

    def topic(
        self,
        name: str,
        msg_type: type[M],
        *,
        qos: QoS | Mapping[str, Any] | None = None,
        scopes: Iterable[str] = (),
    ) -> Publisher[M]:
        """Declare the topic ``name`` of ``msg_type`` and return its :class:`Publisher`.

        ``qos`` is a :class:`~srvwire.topics.QoS` or a mapping of its settings (default: keep
        the last 10, reliable, volatile); with ``scopes`` only a connection holding them all
        may subscribe (or see it). Declaring a topic declared already (by ``@subscription``
        or another ``topic``) returns its publisher: the type must be the same, and ``qos``
        and ``scopes``, when given, set those no declaration gave before or must equal those
        given (else RegistrationError). Call it on the server's loop (or before serving);
        connected clients get ``$/topics``.
        """
        topic = self._declare_topic(name, msg_type, qos, scopes)
        return Publisher(topic)

    def subscription(
        self,
        name: str,
        msg_type: type[BaseModel],
        *,
        qos: QoS | Mapping[str, Any] | None = None,
        scopes: Iterable[str] = (),
    ) -> Callable[[T], T]:
        """Decorate a handler of the messages clients publish on ``name``; returned unchanged.

        The handler takes the typed message: ``def on_joint_states(msg)`` runs on the event
        loop as the message arrives (keep it quick), ``async def`` in a task of its own. A
        message that does not fit the type is answered ``INVALID_PARAMS`` (when the client
        asked for an answer) and the handler never sees it. What clients publish is also
        delivered to the topic's subscribers. A message type too large to make bare is refused
        as a service's request is (see :meth:`add_service`).
        """

        def register(handler: T) -> T:
            check_handler(normalize_name(name), handler)
            topic = self._declare_topic(name, msg_type, qos, scopes, accepts=True)
            topic.entry.handlers.append(handler)
            return handler

        return register

    def summary(self) -> str:
        """What the server offers, for its startup line: ``2 services and 1 action``."""
        actions = sum(1 for entry in self.registry if isinstance(entry.handler, GoalRunner))
        services = len(self.registry) - actions
        said = f"{services} {'service' if services == 1 else 'services'}"
        if actions:
            said += f" and {actions} {'action' if actions == 1 else 'actions'}"
        return said

    def remove_topic(self, name: str) -> None:
        """Remove the topic ``name``: its subscriptions end with an error that says so, and
        connected clients get ``$/topics``. Raise RegistrationError when there is none."""
        canonical = normalize_name(name)
        try:
            self.registry.topics.remove(canonical)
        except KeyError:
            raise RegistrationError(f"no topic named {canonical} is declared") from None
        self.registry.topics_changed()
        for running in self._running:  # the access log sums up what was published on it
            for conn in running._connections:
                if conn.access is not None:
                    conn.access.summarize(canonical)
        self._services_changed()

    def _declare_topic(
        self,
        name: str,
        msg_type: type[BaseModel],
        qos: QoS | Mapping[str, Any] | None,
        scopes: Iterable[str],
        *,
        accepts: bool = False,
    ) -> Topic[TopicEntry]:
        canonical = normalize_name(name)
        if isinstance(scopes, str):
            raise RegistrationError(
                f"the scopes of {canonical} must be a collection of names, not the string "
                f"{scopes!r}"
            )
        if accepts:
            self._refuse_large_messages(canonical, msg_type)
        board = self.registry.topics
        topic = board.get(canonical)
        if topic is not None:
            if topic.entry.msg_type is not msg_type:
                raise RegistrationError(
                    f"the topic {canonical} is declared with {topic.entry.type_name}, not "
                    f"{getattr(msg_type, 'type_name', msg_type)}"
                )
            changed = self._redeclare(topic, qos, frozenset(scopes))
            if accepts and not topic.accepts:
                topic.accepts = changed = True
            if changed:
                self.registry.topics_changed()
                self._services_changed()
            return topic
        try:
            entry = TopicEntry.of(canonical, msg_type)
            topic = board.add(
                Topic(canonical, entry, qos_of(qos), scopes=frozenset(scopes), accepts=accepts)
            )
        except (TypeError, ValueError) as exc:
            raise RegistrationError(f"cannot declare the topic {canonical}: {exc}") from None
        entry.qos_given = qos is not None
        entry.scopes_given = bool(topic.scopes)
        self.registry.topics_changed()
        self._services_changed()
        return topic

    def _redeclare(
        self,
        topic: Topic[TopicEntry],
        qos: QoS | Mapping[str, Any] | None,
        scopes: frozenset[str],
    ) -> bool:
        """Apply a second declaration's ``qos`` and ``scopes`` to ``topic``; return whether
        they changed it.

        A declaration that leaves them out takes the declared ones. One that gives them
        sets them when no declaration gave them before (``@subscription`` with its defaults,
        then ``topic(..., scopes=...)``), and must otherwise give the same: a different
        value raises RegistrationError rather than leave an access rule or a history
        silently unapplied. They cannot change once a client has subscribed.
        """
        entry, name = topic.entry, topic.name
        new_qos = None
        if qos is not None:
            try:
                new_qos = qos_of(qos)
            except (TypeError, ValueError) as exc:
                raise RegistrationError(f"cannot declare the topic {name}: {exc}") from None
            if new_qos == topic.qos:
                new_qos, entry.qos_given = None, True
            elif entry.qos_given:
                raise RegistrationError(
                    f"the topic {name} is declared with the QoS {topic.qos.to_json()}, not "
                    f"{new_qos.to_json()}: give every declaration of it the same QoS, or "
                    "give it once"
                )
        new_scopes = None
        if scopes == topic.scopes:
            entry.scopes_given = entry.scopes_given or bool(scopes)
        elif scopes:
            if entry.scopes_given:
                raise RegistrationError(
                    f"the topic {name} is declared with the scopes {sorted(topic.scopes)}, "
                    f"not {sorted(scopes)}: give every declaration of it the same scopes, "
                    "or give them once"
                )
            new_scopes = scopes
        if new_qos is None and new_scopes is None:
            return False
        if topic.subscriptions:
            raise RegistrationError(
                f"cannot change the QoS or scopes of the topic {name} once clients subscribe "
                "to it: declare them before serving"
            )
        if new_qos is not None:
            topic.set_qos(new_qos)
            entry.qos_given = True
        if new_scopes is not None:
            topic.scopes = new_scopes
            entry.scopes_given = True
        return True

    def _refuse_large_defaults(self) -> None:
        """Check every service and every topic clients publish on against the
        ``max_message_size`` the server starts with, which may have changed since they were
        registered (``srvwire serve --max-message-size``); see :meth:`add_service`."""
        for entry in self.registry:
            refuse_large_service(
                entry.name,
                entry.request_model,
                entry.response_model,
                entry.takes_response,
                self.max_message_size,
            )
        for topic in self.registry.topics:
            if topic.accepts:
                self._refuse_large_messages(topic.name, topic.entry.msg_type)

    def _refuse_large_messages(self, topic: str, msg_type: type[BaseModel]) -> None:
        """Refuse to take messages of ``msg_type`` on ``topic`` when one made bare holds more
        values than ``max_message_size`` can carry (see :func:`refuse_large_defaults`)."""
        refuse_large_defaults(
            f"cannot take messages on the topic {topic}",
            msg_type,
            "for each message a client publishes that leaves them out",
            self.max_message_size,
        )

    def _change_services(self, change: Callable[[], None]) -> None:
        """Run ``change`` on the thread of the loop the server listens on; wait, and re-raise.

        Not listening, or already on that loop, ``change`` runs at once. If the loop stops
        before it gets to the change, the change is made here instead.
        """
        loop = next((r._loop for r in tuple(self._running) if r._loop is not None), None)
        if loop is None or not loop.is_running() or _running_loop() is loop:
            change()
            return
        done: concurrent.futures.Future[None] = concurrent.futures.Future()

        def on_loop() -> None:
            if not done.set_running_or_notify_cancel():
                return  # the caller gave up on this loop and made the change itself
            try:
                change()
            except BaseException as exc:
                done.set_exception(exc)
                if not isinstance(exc, Exception):
                    raise
            else:
                done.set_result(None)

        try:
            loop.call_soon_threadsafe(on_loop)
        except RuntimeError:  # the loop was closed in the meantime
            change()
            return
        while True:
            try:
                return done.result(timeout=_LOOP_CHECK_INTERVAL)
            except concurrent.futures.TimeoutError:
                if not loop.is_running() and done.cancel():
                    change()
                    return

    def _services_changed(self) -> None:
        for running in list(self._running):
            running._announce()

    # --- running ----------------------------------------------------------------------------

    def run(
        self,
        host: Hosts = "127.0.0.1",
        port: int = 8765,
        *,
        ready: Callable[[RunningServer], object] | None = None,
        stopping: Callable[[RunningServer], object] | None = None,
        transport: str | Transport = "websockets",
        ssl: _ssl.SSLContext | None = None,
    ) -> None:
        """Serve until Ctrl-C or SIGTERM, then shut down gracefully; for scripts.

        The blocking form of :meth:`serve_forever`, which describes ``ready`` and ``stopping``.
        When logging is not configured for srvwire (no handler on the ``srvwire`` logger, its
        parents or the root), srvwire's log is shown on stderr at INFO while it runs: the
        ``serving ... on URL, ...`` line, the shutdown, warnings, the access log if on.
        Configure logging (``logging.basicConfig(...)``) and nothing is added.
        """
        with contextlib.suppress(KeyboardInterrupt), _show_log_unless_configured():
            _run_bounded(
                self.serve_forever(
                    host, port, ready=ready, stopping=stopping, transport=transport, ssl=ssl
                )
            )

    async def serve_forever(
        self,
        host: Hosts = "127.0.0.1",
        port: int = 8765,
        *,
        ready: Callable[[RunningServer], object] | None = None,
        stopping: Callable[[RunningServer], object] | None = None,
        transport: str | Transport = "websockets",
        ssl: _ssl.SSLContext | None = None,
    ) -> None:
        """Serve on ``host``:``port`` until SIGINT or SIGTERM, then shut down gracefully.

        ``ready`` is called with the :class:`RunningServer` once it listens (its ``url`` has the
        port really bound, useful with port 0); ``stopping`` once a signal arrived, before the
        graceful shutdown. Signal handlers are installed only in the main thread, and the ones
        they replaced are restored on return; elsewhere (or where the loop cannot handle
        signals) cancel the task, or let Ctrl-C raise KeyboardInterrupt, to stop. An OSError
        means the address could not be bound.
        """
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        replaced: list[tuple[signal.Signals, Any]] = []
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                previous = signal.getsignal(signum)
                try:
                    loop.add_signal_handler(signum, stop.set)
                except (NotImplementedError, RuntimeError):  # Windows: KeyboardInterrupt instead
                    continue
                replaced.append((signum, previous))
        try:
            async with serve(self, host, port, transport=transport, ssl=ssl) as running:
                self.logger.info(
                    "serving %s on %s",
                    self.summary(),
                    ", ".join(running.urls),
                    extra=_LIFECYCLE,
                )
                self.logger.info("%s", running.reach, extra=_LIFECYCLE)
                if ready is not None:
                    ready(running)
                await stop.wait()
                self.logger.info("shutting down", extra=_LIFECYCLE)
                if stopping is not None:
                    stopping(running)
        finally:
            for signum, previous in replaced:
                loop.remove_signal_handler(signum)
                if previous is not None:  # None: installed outside Python, cannot be restored
                    signal.signal(signum, previous)


class serve:
    """Serve ``server`` on ``host``:``port`` (0 picks a free port) over ``transport``.

    ``host`` may also be a list of hosts, or None for every interface, IPv4 and IPv6 (on the
    WebSocket transport); :attr:`RunningServer.urls` then names each address.

    ``transport`` is ``"websockets"`` (the default) or a :class:`~srvwire.transports.base.Transport`
    such as a :class:`~srvwire.transports.memory.MemoryTransport`; ``ssl`` (an
    :class:`ssl.SSLContext` with the server's certificate) makes it speak TLS, at ``wss://``.
    Use it as
    ``async with serve(server) as running: ...`` (closed on exit) or as
    ``running = await serve(server)`` (then ``await running.close()``).
    """

    def __init__(
        self,
        server: Server,
        host: Hosts = "127.0.0.1",
        port: int = 8765,
        *,
        transport: str | Transport = "websockets",
        ssl: _ssl.SSLContext | None = None,
    ) -> None:
        self._server = server
        self._host = host
        self._port = port
        self._transport = get_transport(transport)
        self._ssl = ssl
        self._running: RunningServer | None = None

    async def _start(self) -> RunningServer:
        running = RunningServer(self._server, self._transport)
        await running._start(self._host, self._port, self._ssl)
        self._running = running
        return running

    def __await__(self) -> Generator[Any, None, RunningServer]:
        return self._start().__await__()

    async def __aenter__(self) -> RunningServer:
        return await self._start()

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._running is not None:
            await self._running.close()


def _ask_goals_to_stop(conn: ServedConnection) -> None:
    """Ask every goal running on ``conn`` to stop, as a client's ``$/cancel`` asks: each is
    sent ``$/goal canceling`` before its handler wakes, and has the grace period to return.

    All of them at once: a send that has to wait for a congested peer goes on in a task of
    its own (one of the connection's, which shutdown waits for), and holds up no other goal.
    """
    for call in list(conn.session.calls.values()):
        goal = None if call.context is None else call.context.goal
        if goal is None:
            continue  # a service's call, or a goal not accepted yet (it asks itself)
        canceling = goal.request_cancel(None)
        if canceling is not None:
            sending = first_step(conn.send(canceling))
            if isinstance(sending, Pending):
                conn.spawn(_go_on(sending))


async def _go_on(pending: Pending) -> None:
    """The rest of a send that had to wait."""
    await finish(pending)


class RunningServer:
    """A server listening on a transport: where it listens, its connections, how to stop it."""

    host: str
    port: int

    def __init__(self, server: Server, transport: Transport) -> None:
        self.server = server
        self.transport = transport
        self.closing = False
        self._connections: set[ServedConnection] = set()
        # Handlers answered as they were cancelled, still running after their connection ended:
        # their services, for shutdown to name.
        self._running_on: dict[asyncio.Task[Any], str] = {}
        self._listener: Listener | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._close_task: asyncio.Task[None] | None = None
        self.policy: EdgePolicy | None = None
        self._accept_failures = 0  # since the last line about them
        self._accept_failure_logged: float | None = None
        self._previous_handler: Any = None
        self.tls = False
        self.authenticated = False
        """Whether every connection authenticates: with ``auth``, or a client certificate."""

    async def _start(self, host: Hosts, port: int, ssl: _ssl.SSLContext | None = None) -> None:
        self._loop = asyncio.get_running_loop()
        server = self.server
        server._refuse_large_defaults()
        self.policy = EdgePolicy(
            host,
            origins=server.origins,
            auth=server.auth,
            max_connections=server.max_connections,
            logger=server.logger,
        )
        self.tls = ssl is not None
        mutual = ssl is not None and ssl.verify_mode == _ssl.CERT_REQUIRED
        self.authenticated = server.auth is not None or mutual
        self._listener = await self.transport.listen(
            self._handle, host, port, server.options, gate=self._admit, ssl=ssl
        )
        self.host = self._listener.host
        self.bound: Hosts = host  # what it was asked to listen on, for reach
        self.port = self._listener.port
        self.server._running.add(self)
        if not self.authenticated and not is_loopback(host) and self.transport.name != "memory":
            server.logger.warning(
                "%s, with no authentication: anyone who can reach it can call every service "
                "(give the Server an auth=, or listen on 127.0.0.1)",
                describe_reach(host, authenticated=False, tls=self.tls).split(";")[0],
            )
        self._previous_handler = self._loop.get_exception_handler()
        self._loop.set_exception_handler(self._loop_exception)

    def _loop_exception(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """Say "out of file descriptors" at most once per :data:`ACCEPT_FAILURE_LOG_INTERVAL`,
        with how many times it happened since; pass anything else on to the loop's handler."""
        if context.get("message") != _ACCEPT_FAILED:
            if self._previous_handler is not None:
                self._previous_handler(loop, context)
            else:
                loop.default_exception_handler(context)
            return
        self._accept_failures += 1
        now = loop.time()
        last = self._accept_failure_logged
        if last is not None and now - last < ACCEPT_FAILURE_LOG_INTERVAL:
            return
        self._accept_failure_logged = now
        count, self._accept_failures = self._accept_failures, 0
        self.server.logger.error(
            "cannot accept new connections: %s (%d connections open; %d failed accepts since "
            "the last line, said at most every %g s); raise the limit of open files "
            "(ulimit -n) or lower max_connections",
            context.get("exception"),
            len(self._connections),
            count,
            ACCEPT_FAILURE_LOG_INTERVAL,
        )

    async def _admit(self, handshake: Handshake) -> Admitted | Answered:
        """The gate the transport asks about each opening request."""
        assert self.policy is not None
        return await self.policy.admit(
            handshake, connections=len(self._connections), draining=self.closing
        )

    @property
    def reach(self) -> str:
        """Who can reach this server, in words (its startup log line says it)."""
        return describe_reach(self.bound, authenticated=self.authenticated, tls=self.tls)

    @property
    def url(self) -> str:
        """The address clients connect to, such as ``ws://127.0.0.1:8765``."""
        assert self._listener is not None
        return self._listener.url

    @property
    def urls(self) -> list[str]:
        """Every address clients can connect to, :attr:`url` first: on a wildcard host
        (``0.0.0.0``, ``::``, None), each address of the machine's interfaces."""
        assert self._listener is not None
        return self._listener.urls

    def __repr__(self) -> str:
        state = "closing" if self.closing else "serving"
        return f"<RunningServer {state} on {self.url}, {len(self._connections)} connections>"

    async def __aenter__(self) -> RunningServer:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def close(self) -> None:
        """Shut down gracefully (see the module's invariants); safe to call more than once."""
        if self._close_task is None:
            self._stop_accepting()
            self._close_task = asyncio.create_task(self._close())
        await asyncio.shield(self._close_task)

    aclose = close

    async def wait_closed(self) -> None:
        """Wait until the server has been closed by :meth:`close`."""
        assert self._listener is not None
        await self._listener.wait_closed()

    def _stop_accepting(self) -> None:
        """The first step of shutdown, at once: no new connection, no new call.

        The listener stays open while calls drain, so that a new connection is told 503 and
        ``/healthz`` says ``draining``; it closes once they have.
        """
        assert self._listener is not None
        self.closing = True
        self.server._running.discard(self)
        for conn in self._connections:
            conn.session.close()

    async def _close(self) -> None:
        assert self._listener is not None
        options = self.server
        for conn in self._connections:
            _ask_goals_to_stop(conn)
        tasks = {task for conn in self._connections for task in (*conn.tasks, *conn.counted)}
        if tasks:
            _, pending = await asyncio.wait(tasks, timeout=options.grace_period)
            if pending:
                options.logger.warning(
                    "cancelling %d calls still running after the %.3g s grace period",
                    len(pending),
                    options.grace_period,
                )
                for conn in list(self._connections):
                    conn.cancel_all(
                        ServiceUnavailable("the server shut down before the call finished")
                    )
                # The cancelled calls are answered at once, in tasks of their own: wait for
                # those, but not long on a peer that does not read, nor on a handler that
                # ignores its cancellation (its task is left to end on its own).
                answering = {task for conn in self._connections for task in conn.counted}
                await asyncio.wait(pending | answering, timeout=1.0)
        running_on = sorted(
            name
            for running in (
                self._running_on,
                *(conn.runner.running_on for conn in self._connections),
            )
            for task, name in running.items()
            if not task.done()
        )
        if running_on:
            options.logger.warning(
                "leaving %d %s running that did not end when cancelled (%s answered): %s; "
                "%s cancelled again as the connections close",
                len(running_on),
                "handler" if len(running_on) == 1 else "handlers",
                "its call was" if len(running_on) == 1 else "their calls were",
                ", ".join(running_on),
                "it is" if len(running_on) == 1 else "they are",
            )
        self._listener.close()  # the open connections stay, to be closed with 1001
        loop = self._loop
        if loop is not None and loop.get_exception_handler() == self._loop_exception:
            loop.set_exception_handler(self._previous_handler)
        closes = [conn.conn.close(1001, "server shutting down") for conn in self._connections]
        if closes:
            await asyncio.gather(*closes, return_exceptions=True)
        executor = options.executor
        stuck = executor.busy() if isinstance(executor, HandlerThreads) else []
        if stuck:
            options.logger.warning(
                "leaving %d blocking %s running in %s: %s (a thread cannot be "
                "cancelled; it does not keep the process alive)",
                len(stuck),
                "handler" if len(stuck) == 1 else "handlers",
                "its thread" if len(stuck) == 1 else "their threads",
                ", ".join(stuck),
            )
        await self._listener.wait_closed()

    def _announce(self) -> None:
        """Send every connection its ``$/services``; callable from any thread."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        if _running_loop() is not loop:
            loop.call_soon_threadsafe(self._announce)
            return
        for conn in list(self._connections):
            conn.spawn(conn.send(conn.session.announcement()))
            topics = conn.session.topics_announcement()
            if topics is not None:
                conn.writer.outbox.push(topics)

    async def _handle(self, transport_connection: Connection) -> None:
        server = self.server
        conn = ServedConnection(
            transport_connection,
            server.registry,
            max_in_flight=server.max_in_flight,
            max_batch=server.max_batch,
            notification_timeout=server.notification_timeout,
            executor=server.executor,
            logger=server.logger,
            access_log=server.access_log,
            max_queued_bytes=server.max_queued_bytes,
            max_subscriptions=server.max_subscriptions,
        )
        if self.closing:
            conn.session.close()
        self._connections.add(conn)
        log = self.server.logger
        if log.isEnabledFor(logging.DEBUG):
            log.debug("connection from %s opened", conn.peer)
        try:
            await transport_connection.send(conn.session.announcement())
            topics = conn.session.topics_announcement()
            if topics is not None:
                await transport_connection.send(topics)
            await conn.serve()
        except WriteTimedOut as exc:
            log.warning(
                "closed the connection from %s with code %d: %s", conn.peer, exc.code, exc.reason
            )
        except TransportClosed as exc:
            if log.isEnabledFor(logging.DEBUG):
                log.debug("connection from %s closed: %s", conn.peer, exc)
        finally:
            self._connections.discard(conn)
            conn.cancel_all(None)
            for task, name in conn.runner.running_on.items():
                if task not in self._running_on:
                    self._running_on[task] = name
                    task.add_done_callback(self._running_on.pop)
